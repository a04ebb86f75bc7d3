"""Units and orientation of a head CT found from the image (pvcmf.filters.orientation).

A virtual patient (pvcmf.datasets.phantom, in HU and in the patient frame) is stored in
scanner units and with its axes turned; standardize must give the original back. Volumes that
are no head CT (uniform, MR-like, a limb: a soft-tissue cylinder with a bone rod) are refused.
"""

from __future__ import annotations

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays
from pvcmf.filters.orientation import check_units, orient_head, reorient, standardize

from ct_helpers import image_of, stored_as, volume


@pytest.fixture(scope="module")
def head():
    ct = pvcmf.datasets.phantom(patient=1, spacing=3.0).ct.copy()
    ct[arrays.CT] = np.round(ct[arrays.CT])  # integer values, as a scanner stores them
    return ct


# --------------------------------------------------------------------------- units
@pytest.mark.parametrize("add", [0.0, 1000.0, 1024.0])
def test_scanner_units_found_from_the_histogram(head, add):
    out, report = check_units(stored_as(head, "LAS", add))
    assert report["offset"] == -add
    assert report["units"] == ("hu" if add == 0 else "scanner")
    np.testing.assert_array_equal(out[arrays.CT], head[arrays.CT])


def test_units_given(head):
    out, report = check_units(stored_as(head, "LAS", 500.0), -500.0)
    np.testing.assert_array_equal(out[arrays.CT], head[arrays.CT])
    assert check_units(head, "hu")[1]["offset"] == 0.0
    with pytest.raises(ValueError, match="units must be"):
        check_units(head, "kelvin")


def test_an_unusual_offset_puts_soft_tissue_at_its_hu(head):
    out, report = check_units(stored_as(head, "LAS", 3000.0))
    assert abs(report["offset"] + 3000.0) <= 60
    assert "fit no usual convention" in report["how"]


def test_not_a_ct_refused():
    uniform = image_of(np.full((30, 30, 30), 40.0))
    with pytest.raises(ValueError, match="not a CT"):
        check_units(uniform)
    # MR-like: dark background, smooth tissue intensities, nothing like bone
    g = np.indices((40, 40, 40)).astype(float) - 19.5
    r = np.sqrt((g ** 2).sum(axis=0))
    mr = np.where(r < 16, 400.0 + 15.0 * g[2], 0.0) + np.random.default_rng(0).normal(0, 5, r.shape)
    with pytest.raises(ValueError, match="not a CT"):
        check_units(image_of(mr))


def test_a_limb_is_not_a_head():
    """A cylinder of soft tissue with a bone rod (a knee or an arm) passes the units check
    but is refused by the orientation check, and by standardize as no head at all."""
    g = np.indices((50, 50, 60)).astype(float)
    rr = np.hypot(g[0] - 24.5, g[1] - 24.5)
    limb = np.where(rr < 20, 40.0, -1000.0)
    limb[rr < 5] = 1200.0
    limb += np.random.default_rng(1).normal(0, 10, limb.shape)
    img = image_of(limb, (2.0, 2.0, 2.0))
    hu, report = check_units(img)
    assert report["units"] == "hu"
    with pytest.raises(ValueError, match="cannot tell the head's orientation"):
        orient_head(hu)
    with pytest.raises(ValueError, match="not a head CT: no cranial cavity"):
        standardize(img)


# --------------------------------------------------------------------------- orientation
@pytest.mark.parametrize("code", ["LAS", "LPI", "RPS", "SLA", "PIL", "IRA"])
def test_turned_head_comes_back(head, code):
    out, report = standardize(stored_as(head, code, 1000.0))
    assert report["orientation"]["code"] == code
    assert report["orientation"]["reoriented"] == (code != "LAS")
    assert report["units"]["offset"] == -1000.0
    assert out.dimensions == head.dimensions
    np.testing.assert_allclose(out.spacing, head.spacing)
    np.testing.assert_array_equal(out[arrays.CT], head[arrays.CT])


def test_a_mirrored_file_stays_mirrored(head):
    """Left/right comes from the file: a mirrored store is turned, not un-mirrored."""
    out, report = standardize(stored_as(head, "ALS"))  # det -1: y and x swapped
    assert report["orientation"]["code"] == "ARS"
    assert "left/right taken from the file" in report["orientation"]["left_right"]
    np.testing.assert_array_equal(volume(out), volume(head)[::-1])


def test_given_code_and_none(head):
    turned = stored_as(head, "LPI")
    out, report = orient_head(turned, "lpi")
    assert report["mode"] == "given"
    np.testing.assert_array_equal(out[arrays.CT], head[arrays.CT])
    kept, report = orient_head(turned, "none")
    np.testing.assert_array_equal(kept[arrays.CT], turned[arrays.CT])
    assert not np.shares_memory(kept[arrays.CT], turned[arrays.CT])
    for bad in ("LAX", "LLS", "LA"):
        with pytest.raises(ValueError, match="3-letter code"):
            reorient(head, bad)


def test_pure_and_json_report(head):
    import json

    turned = stored_as(head, "SLA", 1024.0)
    before = np.array(turned[arrays.CT])
    out, report = standardize(turned)
    np.testing.assert_array_equal(turned[arrays.CT], before)
    assert not np.shares_memory(out[arrays.CT], turned[arrays.CT])
    json.dumps(report)
    with pytest.raises(TypeError, match="pyvista.ImageData"):
        standardize(np.zeros((4, 4, 4)))


def test_units_given_that_leave_the_peaks_far_from_hu_are_refused(head):
    """Scanner units read as HU ('hu', or a wrong offset) are refused naming the offset the
    peaks ask for; given units that leave one peak within reach (a cone-beam scan's grey
    values) are kept."""
    scanner = stored_as(head, "LAS", 1024.0)
    for given in ("hu", 1000.0):
        with pytest.raises(ValueError, match=r"not in HU under these units.*HU = value -1024"):
            check_units(scanner, given)
    out, report = check_units(stored_as(head, "LAS", 300.0), "hu")  # soft tissue ~340 HU
    assert report["offset"] == 0.0
    np.testing.assert_array_equal(out[arrays.CT], head[arrays.CT] + 300.0)
