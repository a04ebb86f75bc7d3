"""The head's mirror plane (:func:`pvcmf.filters.mirror_plane`): an analytic symmetric body
turned and shifted by known amounts, the virtual patient's skull turned about its vertical,
and the refusals."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

from pvcmf import arrays, datasets
from pvcmf.filters import find_jaws, mirror_plane
from pvcmf.filters.bone_segments import occlusal_normal
from pvcmf.filters.symmetry import MIN_OVERLAP, check_turn

from ct_helpers import turned_labels


def _body(turn_deg, offset, tilt_deg=0.0, spacing=1.0):
    """A body mirror symmetric about the plane u = offset, where (u, v, w) are the image's
    axes turned ``turn_deg`` about w after w is tilted ``tilt_deg`` about x: an ellipsoid
    and, on one side of its centre along v, two balls either side of the plane (left and
    right alike); the rotation from (u, v, w) to the image is returned with it."""
    labels = pv.ImageData(dimensions=(81, 81, 41), spacing=(spacing,) * 3,
                          origin=(-40.0 * spacing, -40.0 * spacing, -20.0 * spacing))
    R = Rotation.from_euler("XZ", [tilt_deg, turn_deg], degrees=True).as_matrix()
    u, v, w = (np.asarray(labels.points) @ R).T
    u = u - offset
    body = (u / 28) ** 2 + (v / 14) ** 2 + (w / 10) ** 2 < 1
    for side in (-1.0, 1.0):  # a pair of "orbits" in front
        body |= (u - side * 12) ** 2 + (v - 20) ** 2 + w**2 < 36
    labels[arrays.TISSUE] = np.where(body, arrays.BONE_TISSUE, arrays.AIR).astype(np.uint8)
    return labels, R


@pytest.mark.parametrize("turn,offset,tilt", [(11.3, 2.6, 0.0), (-6.4, -4.3, 0.0),
                                              (8.7, 1.4, 20.0)])
def test_the_plane_of_a_symmetric_body_is_found(turn, offset, tilt):
    """The plane is found to a fraction of a degree and of a millimetre: its normal is the
    body's u axis, a point on it lies at ``offset`` along u, its turn is the turn given, and
    the mirror image overlaps the body as much as the body itself (round-off of a 2 mm
    grid aside)."""
    labels, R = _body(turn, offset, tilt)
    found = mirror_plane(labels, R[:, 2])  # the vertical: the body's w
    angle = np.degrees(np.arccos(min(abs(found.direction @ R[:, 0]), 1.0)))
    assert angle < 0.5, angle
    assert found.direction[0] > 0  # on the image's +x side
    assert abs(found.point @ R[:, 0] - offset) < 0.3, found.point
    assert abs(found.turn - turn) < 0.5, found.turn
    assert found.overlap > 0.97, found.overlap
    assert abs(found.direction @ R[:, 2]) < 1e-12  # the plane holds the vertical given


def test_the_virtual_patients_skull_turned_about_its_vertical():
    """The virtual patient's labels turned 12 degrees one way, then 8 the other, about the
    upper arch's normal (nearest voxel): the direction found is the upright one turned
    (within 0.5 degrees), and its turn differs by the turn given."""
    case = datasets.phantom(patient=1, spacing=2.0)
    labels = case.truth
    upright = find_jaws(labels)
    normal = occlusal_normal(upright)
    level = mirror_plane(upright, normal)
    for degrees in (12.0, -8.0):
        R = Rotation.from_rotvec(np.radians(degrees) * normal).as_matrix()
        turned = turned_labels(labels, R)
        found = mirror_plane(turned, R @ normal)
        angle = np.degrees(np.arccos(min(abs(found.direction @ (R @ level.direction)), 1.0)))
        assert angle < 0.5, (degrees, angle)
        assert abs(found.turn - level.turn - degrees) < 1.0, (degrees, found.turn, level.turn)


def test_half_a_head_has_no_mirror_plane():
    """The virtual patient's left half cleared: no plane's mirror image overlaps the right
    half as a head's does, and it is refused rather than guessed."""
    labels = datasets.phantom(patient=1, spacing=2.0).truth.copy()
    tissue = np.asarray(labels[arrays.TISSUE]).copy()
    hard = np.isin(tissue, arrays.HARD_LABELS)
    middle = np.median(np.asarray(labels.points)[hard, 0])
    tissue[np.asarray(labels.points)[:, 0] > middle] = arrays.AIR
    labels[arrays.TISSUE] = tissue
    with pytest.raises(ValueError, match=f"no mirror plane.*at least {MIN_OVERLAP:.0%}"):
        mirror_plane(labels)


def test_refusals():
    labels, _ = _body(0.0, 0.0)
    with pytest.raises(TypeError, match="labels must be a pyvista.ImageData"):
        mirror_plane(labels.cast_to_unstructured_grid())
    with pytest.raises(ValueError, match="normal must be 3 finite numbers"):
        mirror_plane(labels, (0.0, np.nan, 1.0))
    with pytest.raises(ValueError, match="expected the head's vertical direction"):
        mirror_plane(labels, (1.0, 0.0, 0.1))
    with pytest.raises(ValueError, match=r"max_turn must be degrees in \(0, 90\), got 95"):
        mirror_plane(labels, max_turn=95)
    empty = labels.copy()
    empty[arrays.TISSUE] = np.zeros(empty.n_points, dtype=np.uint8)
    with pytest.raises(ValueError, match="no hard tissue"):
        mirror_plane(empty)
    speck = empty.copy()
    tissue = np.zeros(speck.n_points, dtype=np.uint8)
    tissue[:40] = arrays.BONE_TISSUE
    speck[arrays.TISSUE] = tissue
    with pytest.raises(ValueError, match="at least 50 are needed"):
        mirror_plane(speck)
    turned, _ = _body(40.0, 0.0)  # its plane lies beyond the turns searched
    with pytest.raises(ValueError, match="no mirror plane within 30 degrees"):
        mirror_plane(turned)
    assert mirror_plane(turned, max_turn=50).turn == pytest.approx(40.0, abs=0.5)


def test_a_turned_head_is_warned_for_a_plan_in_the_image_axes(caplog):
    """The virtual patient turned 12 degrees about its vertical: a plan in the image's axes
    is warned (its forward goes a fifth of the move sideways); the upright head is not, and
    a plan in the face's axes follows the head (nothing measured, nothing said)."""
    labels = datasets.phantom(patient=1, spacing=2.0).truth
    R = Rotation.from_euler("z", 12.0, degrees=True).as_matrix()
    turned = turned_labels(labels, R)
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        message = check_turn(turned)
    assert message is not None and "turned +12 degrees" in message, message
    assert "goes 21 % of the move sideways" in message
    assert any(r.getMessage() == message for r in caplog.records)
    assert check_turn(labels) is None
    assert check_turn(turned, "occlusal") is None
    assert check_turn(turned, "frankfort") is None


def test_a_deviated_lower_jaw_is_left_out_where_the_labels_name_it():
    """A symmetric body with a "lower jaw" pushed to one side below it: the jaw pulls the
    plane off where the labels do not say what it is, and not where ``bone`` names it the
    mandible (a jaw hanging deviated, or the asymmetry the operation corrects)."""
    labels, R = _body(6.3, 1.2)
    u, v, w = (np.asarray(labels.points) @ R).T
    t = np.radians(25.0)  # the jaw's own midline turned 25 degrees, 8 mm to the side
    ju, jv = np.cos(t) * (u - 9.2) + np.sin(t) * v, -np.sin(t) * (u - 9.2) + np.cos(t) * v
    jaw = (ju / 24) ** 2 + ((jv - 6) / 12) ** 2 + ((w + 15) / 5) ** 2 < 1
    tissue = np.asarray(labels[arrays.TISSUE]).copy()
    tissue[jaw] = arrays.BONE_TISSUE
    labels[arrays.TISSUE] = tissue
    unnamed = mirror_plane(labels, R[:, 2])
    assert abs(unnamed.turn - 6.3) > 0.8, unnamed  # (measured 1.1 degrees off)
    bone = np.where(jaw, arrays.MANDIBLE, np.where(tissue == arrays.BONE_TISSUE,
                                                   arrays.CRANIUM, arrays.BONE_NONE))
    labels[arrays.BONE] = bone.astype(np.uint8)
    named = mirror_plane(labels, R[:, 2])
    assert abs(named.turn - 6.3) < 0.4 and abs(named.point @ R[:, 0] - 1.2) < 0.3, named


def test_a_head_cut_on_one_side_by_the_image_is_judged_on_what_both_sides_hold():
    """The virtual patient's image ending on its left, 40 % of the skull's half width from
    its middle (a head off-centre in a small field of view): what the mirror image puts
    beyond the image is not counted as missing bone, so the plane is found (within 1.5
    degrees of the whole head's) and its overlap stays a whole head's."""
    labels = find_jaws(datasets.phantom(patient=1, spacing=2.0).truth)
    normal = occlusal_normal(labels)
    whole = mirror_plane(labels, normal)
    x = np.asarray(labels.points)[np.isin(np.asarray(labels[arrays.TISSUE]),
                                          arrays.HARD_LABELS), 0]
    end = np.median(x) + 0.4 * (np.percentile(x, 99) - np.percentile(x, 1)) / 2
    i = int(round((end - labels.origin[0]) / labels.spacing[0]))
    d = labels.dimensions
    cut = labels.extract_subset((0, i, 0, d[1] - 1, 0, d[2] - 1))
    found = mirror_plane(cut, normal)
    assert abs(found.turn - whole.turn) < 1.5, (found.turn, whole.turn)
    assert found.overlap > 0.9 * whole.overlap, (found.overlap, whole.overlap)


def test_where_the_scan_saw():
    """Inside the image, on the head's side of a flat cut (``arrays.SCAN_CUTS``: the cut
    faces +y at y = 9) and inside the round field of view of a slice where it cut the head
    (``arrays.SCAN_FOV``: radius 5 about the axis at z = 0)."""
    from pvcmf.filters.symmetry import _known

    labels = pv.ImageData(dimensions=(21, 21, 5), origin=(-10.0, -10.0, -2.0))
    labels.field_data[arrays.SCAN_CUTS] = [1.0, 1.0, 9.0, -5.0, 5.0, -2.0, 2.0, 1.0]
    labels.field_data[arrays.SCAN_FOV] = [0.0, 0.0, 0.0, 5.0]
    points = np.array([[0.0, 8.0, 2.0], [0.0, 9.5, 2.0], [4.0, 0.0, 0.0], [6.0, 0.0, 0.0],
                       [6.0, 0.0, 1.0], [0.0, 0.0, 2.6], [-10.4, 0.0, 1.0]])
    assert _known(labels)(points).tolist() == [True, False, True, False, True, False, True]
