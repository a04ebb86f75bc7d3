"""segment: skin / bone / teeth / intracranial / air-cavity labels against known truth
(a synthetic head here; the virtual patients below), robustness on the real headsq CT, and
clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.filters.segmentation import BONE_THRESHOLD, SKIN_THRESHOLD, TEETH_THRESHOLD
from synthetic_head import HU, dice, synthetic_head


def labels(image, name=arrays.TISSUE):
    return image.point_data[name].reshape(image.dimensions, order="F")


@pytest.fixture(scope="module")
def synthetic():
    ct, truth = synthetic_head(spacing=2.0)
    return ct, truth, pvcmf.filters.segment(ct)


# --------------------------------------------------------------------------- synthetic head
def test_synthetic_dice(synthetic):
    _, truth, seg = synthetic
    t, s = truth[arrays.TISSUE], seg[arrays.TISSUE]
    assert dice(np.isin(s, arrays.SOFT_LABELS), np.isin(t, arrays.SOFT_LABELS)) >= 0.95
    assert dice(np.isin(s, arrays.HARD_LABELS), np.isin(t, arrays.HARD_LABELS)) >= 0.95
    assert dice(s == arrays.INTRACRANIAL, t == arrays.INTRACRANIAL) >= 0.95


def test_table_dropped_sinus_air_teeth_found(synthetic):
    ct, truth, seg = synthetic
    s, t = labels(seg), labels(truth)
    z = ct.points[:, 2].reshape(ct.dimensions, order="F")
    assert np.all(s[z < -94] == arrays.AIR)  # the table, 300 HU, does not touch the head
    # the enclosed sinus: its core stays air, not soft tissue
    core = ndimage.binary_erosion(t == arrays.AIR) & ndimage.binary_fill_holes(t != arrays.AIR)
    assert core.sum() > 20 and np.all(s[core] == arrays.AIR)
    vals = labels(ct, arrays.CT)
    teeth_thr, metal_thr = seg.field_data[arrays.THRESHOLDS][2:]
    assert abs(teeth_thr - TEETH_THRESHOLD) < 150  # placed on the histogram, near the HU level
    assert np.array_equal(s == arrays.TEETH,
                          (vals >= teeth_thr) & (vals < metal_thr) & (s != arrays.AIR))
    assert (s == arrays.TEETH).sum() > 0


def test_bone_array_and_ct_kept(synthetic):
    ct, _, seg = synthetic
    hard = np.isin(seg[arrays.TISSUE], arrays.HARD_LABELS)
    assert seg[arrays.BONE].dtype == np.uint8 and seg[arrays.TISSUE].dtype == np.uint8
    assert np.array_equal(seg[arrays.BONE] == arrays.CRANIUM, hard)
    assert np.all(seg[arrays.BONE][~hard] == arrays.BONE_NONE)
    np.testing.assert_array_equal(seg[arrays.CT], ct[arrays.CT])
    assert seg.spacing == ct.spacing and seg.origin == ct.origin


def test_input_unchanged_and_accessor():
    ct, _ = synthetic_head(spacing=4.0)
    before = {k: np.array(ct.point_data[k]) for k in ct.point_data.keys()}
    out = ct.cmf.segment()
    assert out is not ct
    assert sorted(ct.point_data.keys()) == sorted(before)
    for k, v in before.items():
        np.testing.assert_array_equal(ct.point_data[k], v)
    assert arrays.TISSUE in out.point_data and arrays.TISSUE not in ct.point_data


def test_fill_holes_small_pocket():
    img = pv.ImageData(dimensions=(30, 30, 30), spacing=(2.0, 2.0, 2.0))
    r = np.linalg.norm(img.points - img.center, axis=1)
    ct = np.select([r < 12, r < 18, r < 26], [30.0, 1200.0, -100.0], -1000.0)
    # a one-voxel air pocket in the fat and a big one (a "sinus", 7x7x7 voxels)
    idx = np.ravel_multi_index((15, 15, 4), img.dimensions, order="F")
    ct[idx] = -1000.0
    i, j, k = np.meshgrid(np.arange(30), np.arange(30), np.arange(30), indexing="ij")
    big = ((np.abs(i - 15) <= 3) & (np.abs(j - 15) <= 3) & (np.abs(k - 15) <= 3)).ravel(order="F")
    img[arrays.CT] = ct.astype(np.float32)
    img2 = img.copy()
    img2[arrays.CT] = np.where(big, -1000.0, ct).astype(np.float32)
    filled = pvcmf.filters.segment(img, check=False)[arrays.TISSUE]
    kept = pvcmf.filters.segment(img, fill_holes=False, check=False)[arrays.TISSUE]
    assert filled[idx] == arrays.FAT and kept[idx] == arrays.AIR
    # the big cavity inside the brain volume stays air
    assert np.all(pvcmf.filters.segment(img2, check=False)[arrays.TISSUE][big] == arrays.AIR)


# --------------------------------------------------------------------------- bad input
def _ball(dims=(20, 20, 20)):
    img = pv.ImageData(dimensions=dims, spacing=(2.0, 2.0, 2.0))
    r = np.linalg.norm(img.points - img.center, axis=1)
    img[arrays.CT] = np.select([r < 8, r < 12, r < 16], [30.0, 1200.0, -100.0], -1000.0).astype(
        np.float32
    )
    return img


def test_bad_input_messages():
    with pytest.raises(TypeError, match="ImageData"):
        pvcmf.filters.segment(pv.Sphere())
    with pytest.raises(ValueError, match="no point array 'ct'"):
        pvcmf.filters.segment(pv.ImageData(dimensions=(4, 4, 4)))
    flat = _ball(dims=(20, 20, 1))
    with pytest.raises(ValueError, match="3-D image.*dimensions"):
        pvcmf.filters.segment(flat)
    nan = _ball()
    values = nan[arrays.CT].copy()
    values[5] = np.nan
    nan[arrays.CT] = values
    with pytest.raises(ValueError, match="finite.*1 NaN"):
        pvcmf.filters.segment(nan)
    with pytest.raises(ValueError, match="thresholds must increase.*500"):
        pvcmf.filters.segment(_ball(), skin_threshold=500.0, bone_threshold=400.0)
    with pytest.raises(ValueError, match="teeth_threshold"):
        pvcmf.filters.segment(_ball(), teeth_threshold=float("nan"))
    ints = _ball()
    ints[arrays.CT] = ints[arrays.CT].astype(np.int16)
    with pytest.raises(ValueError, match="dtype float"):
        pvcmf.filters.segment(ints)


def test_empty_results_are_errors():
    air = _ball()
    air[arrays.CT] = np.full(air.n_points, -1000.0, dtype=np.float32)
    with pytest.raises(ValueError, match="no voxel is >= skin_threshold.*HU"):
        pvcmf.filters.segment(air, check=False)
    soft = _ball()
    soft[arrays.CT] = np.minimum(soft[arrays.CT], 40.0)
    with pytest.raises(ValueError, match="bone_threshold"):
        pvcmf.filters.segment(soft, check=False)
    bone_only = _ball()
    bone_only[arrays.CT] = np.where(bone_only[arrays.CT] > -1000.0, 1200.0, -1000.0).astype(
        np.float32
    )
    with pytest.raises(ValueError, match="no extra-cranial soft tissue"):
        pvcmf.filters.segment(bone_only, check=False)


def test_defaults_are_hu():
    assert -1000.0 < SKIN_THRESHOLD < HU["fat"] < HU["muscle"] < BONE_THRESHOLD < TEETH_THRESHOLD


# --------------------------------------------------------------------------- virtual patients
@pytest.fixture(scope="module")
def patients(segmented_patients):
    """conftest's fixture shared by the whole run: phantoms at 2 mm (as test_phantom.py) and segment()."""
    return segmented_patients


@pytest.mark.parametrize("patient", [1, 2, 3, 4])
def test_phantom_dice(patients, patient):
    case, seg = patients[patient]
    t, s = case.truth[arrays.TISSUE], seg[arrays.TISSUE]
    soft = dice(np.isin(s, arrays.SOFT_LABELS), np.isin(t, arrays.SOFT_LABELS))
    hard = dice(np.isin(s, arrays.HARD_LABELS), np.isin(t, arrays.HARD_LABELS))
    intra = dice(s == arrays.INTRACRANIAL, t == arrays.INTRACRANIAL)
    assert soft >= 0.95, f"soft-tissue Dice {soft:.3f}"
    assert hard >= 0.95, f"hard-tissue Dice {hard:.3f}"
    assert intra >= 0.95, f"intracranial Dice {intra:.3f}"
    # the patient table (-150 HU, below the head) is dropped: no label far from the head
    near_head = ndimage.binary_dilation(labels(case.truth) != arrays.AIR, iterations=2)
    assert not np.any((labels(seg) != arrays.AIR) & ~near_head)
    # bone segments: CRANIUM on every hard voxel (cut_bones splits them later)
    assert np.array_equal(seg[arrays.BONE] == arrays.CRANIUM, np.isin(s, arrays.HARD_LABELS))


# --------------------------------------------------------------------------- real CT
def test_headsq_one_skin_component_bone_inside(data_dir):
    if not (data_dir / "headsq" / "quarter.nhdr").is_file():
        pytest.skip("headsq not in the data folder")
    seg = pvcmf.datasets.headsq().cmf.segment()
    t = labels(seg)
    head = t != arrays.AIR
    _, n = ndimage.label(head, structure=ndimage.generate_binary_structure(3, 3))
    assert n == 1
    hard = np.isin(t, arrays.HARD_LABELS)
    assert hard.sum() > 0.05 * head.sum()
    # bone lies inside the skin: (almost) no bone voxel touches the outside air
    outside, _ = ndimage.label(~ndimage.binary_fill_holes(head))
    touching = hard & ndimage.binary_dilation(outside > 0)
    assert touching.sum() < 0.05 * hard.sum()


def test_progress_bar_logs_stages(caplog):
    import logging

    with caplog.at_level(logging.INFO, logger="pvcmf.filters"):
        seg = pvcmf.filters.segment(_ball(), progress_bar=True, check=False)
        pvcmf.filters.classify_tissue(seg, progress_bar=True)
    text = caplog.text
    assert "segment: head mask" in text and "segment: intracranial" in text
    assert "classify_tissue: EM" in text
