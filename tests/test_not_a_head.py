"""Volumes that are no head CT are refused with a message naming what is missing: a chest
(lungs, spine, ribs), a knee (one long bone), the neck and shoulders below a real head, an MR
head; a head cut above the jaws gives no jaw segment to a plan that moves one."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.io.orientation import check_head, standardize
from pvcmf.plan import Osteotomy, Plan
from body_parts import chest, knee


@pytest.mark.parametrize("orient", ["auto", "none"])
def test_a_chest_is_refused_naming_the_lungs(orient):
    with pytest.raises(ValueError, match=r"not a head CT: no cranial cavity.*no teeth.*lungs"):
        standardize(chest(), orient=orient)


def test_a_knee_is_refused_naming_the_missing_cavity_and_teeth():
    with pytest.raises(ValueError, match=r"not a head CT: no cranial cavity.*no teeth") as err:
        standardize(knee(), orient="LAS")
    assert "lungs" not in str(err.value)


def test_a_head_passes_with_its_cavity_and_teeth():
    ct = pvcmf.datasets.phantom(patient=2, spacing=3.0).ct
    _, report = standardize(ct, orient="none")
    cues = report["orientation"]["cues"]
    assert cues["cavity_ml"] > 500 and cues["teeth_ml"] > 1.0
    assert cues["inner_air_ml"] < 0.1 * cues["body_ml"]  # sinuses and airway, no lungs
    # a head without its cranial cavity (a face scan) still passes on its teeth
    check_head({**cues, "cavity_ml": 0})
    with pytest.raises(ValueError, match="no teeth"):
        check_head({**cues, "cavity_ml": 0, "teeth_ml": 0.0})


def test_an_mr_head_is_refused_whatever_the_options():
    """T1-like MR: bright scalp fat, dark skull, grey brain, no air/soft-tissue step of a CT."""
    g = np.indices((48, 48, 48)).astype(float) - 23.5
    r = np.sqrt((g ** 2).sum(axis=0))
    mr = np.select([r < 17, r < 19, r < 22], [600.0, 80.0, 1100.0], 20.0)
    mr += np.random.default_rng(2).normal(0, 20, r.shape)
    img = pv.ImageData(dimensions=mr.shape, spacing=(3.0, 3.0, 3.0))
    img[arrays.CT] = mr.astype(np.float32).ravel(order="F")
    for kwargs in ({}, {"units": "hu", "orient": "none"}):
        with pytest.raises(ValueError, match="not a CT"):
            standardize(img, **kwargs)


def test_the_neck_and_shoulders_of_a_real_scan_are_refused(data_dir, tmp_path):
    """The female scan's lowest 25 slices: neck and shoulders, below the mandible."""
    folder = data_dir / "vhp_female_head"
    if not folder.is_dir():
        pytest.skip(f"{folder} not in the data folder")
    for path in sorted(folder.glob("*.dcm"))[:25]:
        shutil.copy(path, tmp_path / path.name)
    ct = pvcmf.read_ct(tmp_path, frame="patient")
    with pytest.raises(ValueError, match=r"not a head CT: no cranial cavity.*no teeth"):
        standardize(ct, orient="none")


# --------------------------------------------------------------------------- no jaws
@pytest.fixture(scope="module")
def patient1_labels():
    return pvcmf.filters.segment(pvcmf.datasets.phantom(patient=1, spacing=2.0).ct)


def _above(labels, z_mm):
    """The labels above height ``z_mm`` (a scan cut there)."""
    k = int(np.ceil((z_mm - labels.origin[2]) / labels.spacing[2]))
    d = labels.dimensions
    return labels.extract_subset((0, d[0] - 1, 0, d[1] - 1, k, d[2] - 1))


def _teeth_top(labels):
    t = np.asarray(labels[arrays.TISSUE]).reshape(labels.dimensions, order="F")
    k = np.flatnonzero((t == arrays.TEETH).any(axis=(0, 1))).max()
    return labels.origin[2] + labels.spacing[2] * k


@pytest.mark.parametrize("segment", ["maxilla", "mandible"])
def test_a_head_cut_above_the_jaws_gives_no_segment_to_move(patient1_labels, segment):
    cut = _above(patient1_labels, _teeth_top(patient1_labels) + 30.0)
    assert not np.any(np.asarray(cut[arrays.TISSUE]) == arrays.TEETH)
    plan = Plan((Osteotomy(segment, (0.0, 0.0, 2.0)),))
    with pytest.raises(ValueError, match=rf"moves segment '{segment}'.*(anatomy|cut planes)"):
        pvcmf.filters.cut_bones(cut, plan)
    with pytest.raises(ValueError, match="tooth voxels"):
        pvcmf.filters.find_jaws(cut)


def test_a_head_cut_between_the_arches_has_no_mandible(patient1_labels):
    """Cut just above the occlusal level: the upper teeth only; the mandible is not found
    (no voxel of air or soft tissue labelled mandible), and a plan that moves it fails."""
    t = np.asarray(patient1_labels[arrays.TISSUE]).reshape(patient1_labels.dimensions,
                                                            order="F")
    z = np.flatnonzero((t == arrays.TEETH).any(axis=(0, 1)))
    profile = (t == arrays.TEETH).sum(axis=(0, 1))[z[0]:z[-1] + 1]
    k = z[0] + int(np.argmin(profile[1:-1])) + 2  # just above the fewest-teeth slice
    cut = _above(patient1_labels, patient1_labels.origin[2] + patient1_labels.spacing[2] * k)
    bone = np.asarray(pvcmf.filters.find_jaws(cut)[arrays.BONE])
    hard = np.isin(np.asarray(cut[arrays.TISSUE]), arrays.HARD_LABELS)
    assert np.array_equal(bone > 0, hard)
    assert not np.any(bone == arrays.MANDIBLE)
    with pytest.raises(ValueError, match="moves segment 'mandible'"):
        pvcmf.filters.cut_bones(cut, Plan((Osteotomy("mandible", (0.0, 0.0, 2.0)),)))


# --------------------------------------------------------------------------- segment
@pytest.mark.parametrize("body_part, lungs", [(chest, True), (knee, False)])
def test_segment_refuses_a_body_part_naming_what_it_measured(body_part, lungs):
    """segment runs standardize's head check itself: a chest or a knee handed straight to
    it is refused with the cavity, teeth and inner air measured, and check=False is named."""
    ct = body_part()
    with pytest.raises(ValueError, match=r"segment: not a head CT: no cranial cavity.*no "
                                         r"teeth \(0\.0 mL.*mL of air inside the body.*"
                                         r"check=False") as err:
        pvcmf.filters.segment(ct)
    assert ("lungs" in str(err.value)) == lungs
    assert ct.array_names == [arrays.CT]  # nothing written on the input


def test_segment_check_false_labels_a_body_part():
    lab = pvcmf.filters.segment(knee(), check=False)
    assert np.count_nonzero(np.asarray(lab[arrays.TISSUE]) == arrays.BONE_TISSUE) > 0


def test_segment_check_head_is_the_filters_orientation_check():
    from pvcmf.filters.orientation import check_head as filters_check_head
    assert filters_check_head is check_head
