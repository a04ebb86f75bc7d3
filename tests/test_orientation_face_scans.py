"""Orientation of face-only scans: a cone-beam field around the jaws, without the cranial cavity.

Such a scan holds the skull base and the cervical spine behind a face of soft tissue, so
its bone share grows backward, not toward the face; the dental arch (teeth farther from the
midline lie farther back) tells the face side instead. Without the cranial cavity the vertex
side comes from a strong bone-share trend, else from the file where the anatomy does not
contradict it; otherwise the scan is refused. Never a wrong turn: each case below is either
the right orientation or a refusal naming ``orient``.
"""

from __future__ import annotations

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays
from pvcmf.filters.orientation import standardize
from pvcmf.io.orientation import _decide

from ct_helpers import cone_beam_field, image_of, stored_as, volume


# --------------------------------------------------------------------------- the decision
def _cues(trend, arch, cavity=False, air=None):
    cues = {"mirror": [0.6, 0.3, 0.3], "cut_area_mm2": [0, 0, 12000],
            "bone_share_trend": trend, "arch_trend": arch}
    if cavity:
        cues["body_below_cavity_mm"] = [0.0, -10.0, -60.0]
    if air is not None:
        cues["inner_air_offset_mm"] = air
    return cues


def test_the_arch_tells_the_face_side_without_a_cavity():
    """A face-only scan whose bone share grows backward (skull base, spine): the arch wins."""
    assert _decide(_cues([-0.16, -0.66, 0.66], [0.0, -0.75, 0.6]))[0] == "LAS"
    assert _decide(_cues([0.16, 0.66, 0.66], [0.0, 0.75, 0.6]))[0] == "RPS"
    # without teeth the bone share speaks, as for a whole head
    assert _decide(_cues([-0.16, -0.66, 0.66], None))[0] == "RPS"


def test_with_a_cavity_every_face_cue_must_agree():
    assert _decide(_cues([0.0, 0.6, 0.0], [0.0, -0.8, 0.0], cavity=True))[0] == "LAS"
    code, _, why = _decide(_cues([0.0, 0.6, 0.0], [0.0, 0.8, 0.0], cavity=True))
    assert code is None and "dental-arch trend" in why


@pytest.mark.parametrize("trend_z, expected, from_file", [
    (0.7, "LAS", False),   # a strong trend tells the vertex
    (-0.7, "RAI", False),  # ... also against the file
    (0.1, "LAS", True),    # a weak one leaves the file's vertex side
    (-0.2, "LAS", True),
    (-0.43, None, False),  # a weak one against the file: refused, not turned
])
def test_the_vertex_side_without_a_cavity(trend_z, expected, from_file):
    code, file_vertex, why = _decide(_cues([0.0, 0.0, trend_z], [0.0, -0.8, 0.0]))
    assert code == expected and file_vertex == from_file
    if code is None:
        assert "vertex side" in why


def test_a_body_axis_that_is_not_the_files_z_needs_a_strong_trend():
    cues = _cues([0.0, -0.4, 0.0], [0.0, 0.0, -0.8])
    cues["cut_area_mm2"] = [0, 12000, 0]  # the scan range cuts the body along y
    assert _decide(cues)[0] is None
    cues["bone_share_trend"] = [0.0, -0.7, 0.0]
    assert _decide(cues)[0] == "LIA"


# --------------------------------------------------------------------------- a virtual patient
@pytest.fixture(scope="module")
def lower_head():
    """Virtual patient 1 from the neck to 20 mm above its teeth: no cranial cavity."""
    ct = pvcmf.datasets.phantom(patient=1, spacing=3.0).ct
    labels = ct.cmf.segment()
    tissue = np.asarray(labels[arrays.TISSUE]).reshape(ct.dimensions, order="F")
    top = int(np.median(np.nonzero(tissue == arrays.TEETH)[2])) + 7
    return image_of(np.round(volume(ct)[:, :, :top]), ct.spacing)


@pytest.mark.parametrize("code", ["LAS", "RPS", "LPI"])
def test_a_lower_head_comes_back(lower_head, code):
    out, report = standardize(stored_as(lower_head, code, 1000.0))
    assert report["orientation"]["code"] == code
    assert report["orientation"]["cues"]["cavity_ml"] == 0
    np.testing.assert_array_equal(volume(out), volume(lower_head))


# --------------------------------------------------------------------------- real heads
@pytest.fixture(scope="module", params=["vhp_female_head", "vhp_male_head"])
def face_scan(request, data_dir):
    return cone_beam_field(data_dir, request.param)


def test_a_cone_beam_field_keeps_its_axes(face_scan):
    """The field holds the spine and skull base behind the face: the bone share grows
    backward, and the arch keeps the face toward +y."""
    out, report = standardize(face_scan, units="rescale")
    orientation = report["orientation"]
    assert orientation["code"] == "LAS", orientation
    assert "vertex" not in orientation or "from the file" in orientation["vertex"]
    assert orientation["cues"]["cavity_ml"] == 0
    assert orientation["cues"]["arch_trend"][1] < -0.5


def test_a_cone_beam_field_stored_face_back_comes_back(face_scan):
    upright, _ = standardize(face_scan, units="rescale")
    out, report = standardize(stored_as(face_scan, "RPS"), units="rescale")
    assert report["orientation"]["code"] == "RPS"
    np.testing.assert_array_equal(volume(out), volume(upright))


def test_a_cone_beam_field_stored_upside_down_is_turned_or_refused(face_scan):
    try:
        out, report = standardize(stored_as(face_scan, "RAI"), units="rescale")
    except ValueError as err:
        assert "orient=" in str(err)
        return
    assert report["orientation"]["code"] == "RAI"
    np.testing.assert_array_equal(volume(out), volume(standardize(face_scan, units="rescale")[0]))


@pytest.mark.parametrize("beside", [-12.0, 12.0])
def test_a_field_beside_the_midline_keeps_its_axes(data_dir, beside):
    """A smaller field centred 12 mm beside the male's midline cuts one side's bone more
    than the other's: the mirror plane is sought beside the bone's centre plane."""
    field = cone_beam_field(data_dir, "vhp_male_head", radius=60.0, below=45.0, above=60.0,
                            behind=30.0, beside=beside)
    _, report = standardize(field, units="rescale")
    assert report["orientation"]["code"] == "LAS", report["orientation"]


@pytest.mark.parametrize("name", ["vhp_female_head", "vhp_male_head"])
def test_a_noisy_field_keeps_its_scale_and_axes(data_dir, name):
    """The field with noise of 100 HU (60 grey values), stored as whole grey values
    clipped at the scanner's lowest value, three noise widths below air, which its outside
    holds too: the air's tail reaches that value (no gap), yet the outside is a fill, not
    the air peak, so the grey values map to HU as the field's own scale (0.6 HU + 200)
    says, the teeth stay tooth-dense, and the arch keeps the face toward +y."""
    field = cone_beam_field(data_dir, name, noise=60.0)
    lowest = 0.6 * -1000.0 + 200.0 - 3 * 60.0
    field[arrays.CT] = np.maximum(np.round(np.asarray(field[arrays.CT])), lowest)
    _, report = standardize(field, units="rescale")
    units = report["units"]
    assert units["fill"]["value"] == float(np.min(np.asarray(field[arrays.CT])))
    assert abs(units["slope"] * 0.6 - 1.0) < 0.1, units
    assert report["orientation"]["code"] == "LAS", report["orientation"]
    assert report["orientation"]["cues"]["teeth_ml"] > 1.0
