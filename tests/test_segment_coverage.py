"""A scan that does not hold a planned bone segment whole (a face scan ending inside the
jaw): warned about, and the image's inferior end then marked as the scan's edge."""

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.field_of_view import cuts_array, on_scan_cuts
from pvcmf.filters.segment_coverage import (check_coverage, coverage_message,
                                            segment_coverage, with_inferior_cut)
from pvcmf.plan import Osteotomy, Plan


def _labels(bone_box, dims=(12, 12, 12), spacing=(2.0, 2.0, 2.0)):
    img = pv.ImageData(dimensions=dims, spacing=spacing, origin=(10.0, -40.0, 100.0))
    tissue = np.full(dims, arrays.AIR, np.uint8)
    tissue[1:11, 1:11, :] = arrays.FAT  # a head leaving the image at both z ends
    bone = np.zeros(dims, np.uint8)
    bone[bone_box] = arrays.MANDIBLE
    img[arrays.TISSUE] = tissue.ravel(order="F")
    img[arrays.BONE] = bone.ravel(order="F")
    return img


PLAN = Plan((Osteotomy("mandible", translation=(0.0, 2.0, 0.0)),))


def test_a_segment_inside_the_scan_is_whole_and_nothing_is_added(caplog):
    labels = _labels((slice(3, 8), slice(3, 8), slice(2, 6)))
    assert segment_coverage(labels, [arrays.MANDIBLE]) == {
        arrays.MANDIBLE: {"ends": [], "on_cuts": 0, "voxels": 100}}
    assert coverage_message("mandible", segment_coverage(labels, [3])[3], labels) is None
    with caplog.at_level("WARNING", logger="pvcmf"):
        out = check_coverage(labels, PLAN)
    assert not caplog.records
    assert arrays.SCAN_CUTS not in out.field_data
    assert out is not labels and not np.shares_memory(out[arrays.BONE], labels[arrays.BONE])


def test_a_segment_reaching_the_inferior_end_is_warned_about_and_that_end_becomes_a_cut(caplog):
    labels = _labels((slice(3, 8), slice(3, 8), slice(0, 4)))
    before = labels.copy()
    entry = segment_coverage(labels, [arrays.MANDIBLE])[arrays.MANDIBLE]
    assert entry["ends"] == [(2, -1, 25, 100.0)]
    with caplog.at_level("WARNING", logger="pvcmf"):
        out = check_coverage(labels, PLAN)
    (record,) = caplog.records
    assert "the scan does not hold the whole mandible" in record.getMessage()
    assert "inferior (-z) end at z = 100 mm (100 mm^2" in record.getMessage()
    assert arrays.SCAN_CUTS not in labels.field_data and labels == before  # input unchanged
    cuts = np.asarray(out.field_data[arrays.SCAN_CUTS]).reshape(-1, 8)
    assert cuts.tolist() == [[2.0, -1.0, 100.0, 12.0, 30.0, -38.0, -20.0, 0.0]]
    # the skin on the inferior end is the scan's edge; above it, it is the patient's
    on = on_scan_cuts([[20.0, -30.0, 100.0], [20.0, -30.0, 102.0], [20.0, -30.0, 106.0],
                       [50.0, -30.0, 100.0]], out)
    assert on.tolist() == [True, True, False, False]


def test_the_inferior_end_is_added_once_next_to_the_cuts_the_segmentation_found():
    labels = _labels((slice(3, 8), slice(3, 8), slice(0, 4)))
    top = {"axis": 2, "sign": 1, "at": 122.0, "lo": (12.0, -38.0), "hi": (28.0, -22.0),
           "edge": False}
    labels.field_data[arrays.SCAN_CUTS] = cuts_array([top])
    once = with_inferior_cut(labels)
    twice = with_inferior_cut(once)
    rows = np.asarray(twice.field_data[arrays.SCAN_CUTS]).reshape(-1, 8)
    assert rows[:, :3].tolist() == [[2.0, 1.0, 122.0], [2.0, -1.0, 100.0]]


def test_a_segment_on_a_cut_the_segmentation_found_is_warned_about():
    labels = _labels((slice(3, 8), slice(8, 12), slice(3, 7)))  # out through the +y end
    front = {"axis": 1, "sign": 1, "at": -18.0, "lo": (10.0, 100.0), "hi": (32.0, 122.0),
             "edge": True}
    labels.field_data[arrays.SCAN_CUTS] = cuts_array([front])
    entry = segment_coverage(labels, [arrays.MANDIBLE])[arrays.MANDIBLE]
    assert [e[:2] for e in entry["ends"]] == [(1, 1)] and entry["on_cuts"] == 40
    message = coverage_message("mandible", entry, labels)
    assert "anterior (+y) end at y = -18 mm" in message and "scan's cut (50.0 %" in message
    assert arrays.SCAN_CUTS in check_coverage(labels, PLAN).field_data


def test_segment_coverage_checks_its_labels():
    with pytest.raises(TypeError, match="labels must be a pyvista.ImageData, got dict"):
        segment_coverage({}, [arrays.MANDIBLE])
    with pytest.raises(ValueError, match="bone"):
        segment_coverage(pv.ImageData(dimensions=(3, 3, 3)), [arrays.MANDIBLE])


@pytest.fixture(scope="module")
def jaw_cut_run():
    """A virtual patient's CT whose image ends through the chin (a face scan)."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    ct = case.ct
    z = np.asarray(case.truth.points)[np.asarray(case.truth[arrays.BONE]) == arrays.MANDIBLE, 2]
    k = int((z.min() + 0.15 * (z.max() - z.min()) - ct.origin[2]) / ct.spacing[2])
    voi = [0, ct.dimensions[0] - 1, 0, ct.dimensions[1] - 1, k, ct.dimensions[2] - 1]
    res = simulate(ct.extract_subset(voi), PLAN, predict=False, figures=False)
    return res, ct.origin[2] + k * ct.spacing[2], case


def test_a_face_scan_ending_in_the_jaw_is_warned_about_and_its_end_marked(jaw_cut_run):
    res, end, case = jaw_cut_run
    warned = [w for w in res.warnings if "the scan does not hold the whole mandible" in w]
    assert len(warned) == 1 and f"inferior (-z) end at z = {end:.0f} mm" in warned[0], \
        res.warnings
    cuts = np.asarray(res.labels.field_data[arrays.SCAN_CUTS]).reshape(-1, 8)
    assert [2.0, -1.0] in cuts[:, :2].tolist()
    skin = res.skin_pre
    cut = np.asarray(skin[arrays.SKIN_CUT]).astype(bool)
    z = np.asarray(skin.points)[:, 2]
    low = z <= end + 0.5 * res.labels.spacing[2]
    assert low.sum() > 50 and np.all(cut[low])


def test_the_whole_virtual_patient_is_not_warned_about():
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    res = simulate(case.ct, PLAN, predict=False, figures=False)
    assert "mandible from the anatomy" in res.skipped["bone segments"]
    assert not [w for w in res.warnings if "bone segments" in w], res.warnings
