"""The face box (the region of interest the pipeline meshes) from the label image."""

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.model_region import BELOW_MANDIBLE_MM
from pvcmf.pipeline import face_box


def _labels(direction=None):
    img = pv.ImageData(dimensions=(20, 30, 25), spacing=(1.0, 2.0, 1.5), origin=(-5.0, 3.0, 7.0))
    if direction is not None:
        img.direction_matrix = direction
    tissue = np.zeros(img.dimensions[::-1], dtype=np.uint8)  # (z, y, x)
    tissue[4:20, 6:27, 3:15] = arrays.FAT
    tissue[10, 27, 8] = arrays.BONE_TISSUE  # one voxel sticking out in +y
    img[arrays.TISSUE] = tissue.ravel()
    return img


def _brute(img, fraction):
    pts = np.asarray(img.points)[np.asarray(img[arrays.TISSUE]) != arrays.AIR]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = np.asarray(img.spacing)
    y0 = hi[1] - fraction * (hi[1] - lo[1])
    return (lo[0] - pad[0], hi[0] + pad[0], y0, hi[1] + pad[1], lo[2] - pad[2], hi[2] + pad[2])


@pytest.mark.parametrize("fraction", [0.25, 0.5, 1.0])
def test_face_box_matches_the_tissue_points(fraction):
    img = _labels()
    np.testing.assert_allclose(face_box(img, fraction), _brute(img, fraction))
    # the anterior fraction starts where the y extent says
    box = face_box(img, fraction)
    y_lo, y_hi = 3.0 + 2.0 * 6, 3.0 + 2.0 * 27
    assert box[2] == pytest.approx(y_hi - fraction * (y_hi - y_lo))


def test_face_box_rotated_image_uses_the_physical_points():
    c, s = np.cos(0.3), np.sin(0.3)
    img = _labels(direction=np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]))
    np.testing.assert_allclose(face_box(img, 0.5), _brute(img, 0.5))


@pytest.mark.parametrize("fraction", [0, -0.1, 1.5, "half", None])
def test_face_box_rejects_bad_fraction(fraction):
    with pytest.raises(ValueError, match="face_fraction"):
        face_box(_labels(), fraction)


def test_face_box_rejects_all_air():
    img = _labels()
    img[arrays.TISSUE] = np.zeros(img.n_points, dtype=np.uint8)
    with pytest.raises(ValueError, match="all air"):
        face_box(img, 0.5)


def _with_mandible(z_slices):
    img = _labels()
    bone = np.zeros(img.dimensions[::-1], dtype=np.uint8)  # (z, y, x)
    bone[z_slices, 10:20, 5:10] = arrays.MANDIBLE
    img[arrays.BONE] = bone.ravel()
    return img


def test_face_box_stops_under_the_mandible():
    """The box's floor lies ``below_mandible`` mm under the mandible's lowest voxel (here z
    index 14 of a 1.5 mm grid starting at 7 mm: z 28 mm), never under the tissue's."""
    img = _with_mandible(slice(14, 18))
    z_jaw = 7.0 + 1.5 * 14
    assert face_box(img, 0.5, below_mandible=10.0)[4] == pytest.approx(z_jaw - 10.0)
    assert face_box(img, 0.5)[4] == pytest.approx(max(z_jaw - BELOW_MANDIBLE_MM, 7.0 + 1.5 * 3))
    # no cut without the margin, none deeper than the tissue, none without a mandible
    whole = _brute(img, 0.5)[4]
    assert face_box(img, 0.5, below_mandible=None)[4] == pytest.approx(whole)
    assert face_box(img, 0.5, below_mandible=100.0)[4] == pytest.approx(whole)
    np.testing.assert_allclose(face_box(_labels(), 0.5, below_mandible=1.0), _brute(_labels(), 0.5))
    # the other five bounds do not change
    np.testing.assert_allclose(np.delete(face_box(img, 0.5, below_mandible=10.0), 4),
                               np.delete(_brute(img, 0.5), 4))


def test_face_box_under_the_mandible_of_a_rotated_image():
    c, s = np.cos(0.3), np.sin(0.3)
    img = _with_mandible(slice(14, 18))
    img.direction_matrix = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    z_jaw = np.asarray(img.points)[np.asarray(img[arrays.BONE]) == arrays.MANDIBLE, 2].min()
    assert face_box(img, 0.5, below_mandible=10.0)[4] == pytest.approx(z_jaw - 10.0)


@pytest.mark.parametrize("margin", [-1.0, "deep"])
def test_face_box_rejects_bad_margin(margin):
    with pytest.raises(ValueError, match="below_mandible"):
        face_box(_labels(), 0.5, below_mandible=margin)


def test_face_box_finds_the_mandible_from_the_teeth():
    """Labels without the mandible (segment's output: every hard voxel cranium) but with
    teeth: the mandible comes from the anatomy and the box stops under it, as with the
    virtual patient's true mandible."""
    import pvcmf

    case = pvcmf.datasets.phantom(patient=2, spacing=2.0)
    lab = pvcmf.filters.segment(case.ct)
    assert not np.any(np.asarray(lab[arrays.BONE]) == arrays.MANDIBLE)
    truth = lab.copy()
    truth[arrays.BONE] = np.asarray(case.truth[arrays.BONE])
    z_true = face_box(truth, 0.5)[4]
    assert face_box(lab, 0.5)[4] == pytest.approx(z_true, abs=2 * lab.spacing[2])
    assert z_true > face_box(lab, 0.5, below_mandible=None)[4] + 5.0  # the neck is cut
