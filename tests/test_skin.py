"""Image skin: sub-voxel accurate against an analytic surface, no voxel terraces."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.skin import SLIVER_FRACTION, extract_skin

RADII = np.array([40.0, 50.0, 45.0])


@pytest.fixture(scope="module")
def head():
    """A voxelised ellipsoid 'head' (semi-axes 40, 50, 45 mm) at 2 mm spacing."""
    img = pv.ImageData(dimensions=(56, 60, 56), spacing=(2.0, 2.0, 2.0), origin=(-55, -59, -55))
    img[arrays.TISSUE] = (((img.points / RADII) ** 2).sum(axis=1) < 1).astype(np.uint8)
    return img


def _distance(points):
    """Distance to the ellipsoid, by Newton on the foot parameter (exact to round-off)."""
    x = np.asarray(points, float)
    t = np.zeros(len(x))
    a2 = RADII ** 2
    for _ in range(60):  # f(t) = sum (a x / (a^2 + t))^2 - 1 = 0
        q = a2 + t[:, None]
        f = (a2 * x ** 2 / q ** 2).sum(axis=1) - 1
        df = (-2 * a2 * x ** 2 / q ** 3).sum(axis=1)
        t = t - f / df
    foot = a2 * x / (a2 + t[:, None])
    return np.linalg.norm(x - foot, axis=1)


def _terrace(surface):
    """95th percentile of the angle (degrees) between the normals of neighbouring faces."""
    s = surface.compute_normals(cell_normals=True, point_normals=False)
    n, f = s.cell_data["Normals"], s.faces.reshape(-1, 4)[:, 1:]
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    fid = np.tile(np.arange(len(f)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, fid = e[order], fid[order]
    pair = (e[1:] == e[:-1]).all(axis=1)
    cos = np.einsum("ij,ij->i", n[fid[1:][pair]], n[fid[:-1][pair]])
    return float(np.percentile(np.degrees(np.arccos(np.clip(cos, -1, 1))), 95))


def test_sinc_removes_terraces_and_keeps_the_surface(head):
    raw = extract_skin(head, sinc=0)
    smooth = extract_skin(head)
    err_raw, err = _distance(raw.points), _distance(smooth.points)
    assert err.mean() < 0.25 * 2.0  # sub-voxel: a quarter of the 2 mm spacing
    assert err.mean() < err_raw.mean()
    assert _terrace(smooth) < 0.7 * _terrace(raw)
    assert _terrace(smooth) < 6.0
    # no shrinkage: the enclosed volume stays that of the ellipsoid within 2 %
    assert abs(smooth.volume / (4 / 3 * np.pi * RADII.prod()) - 1) < 0.02


def test_sinc_validated(head):
    with pytest.raises(ValueError, match="sinc"):
        extract_skin(head, sinc=-1)


@pytest.fixture(scope="module")
def cut_head():
    """The ellipsoid of ``head`` with the image ending at z = -30 mm (a scan that ends
    across the neck) and at y = 40 mm (a field of view that cuts the face)."""
    img = pv.ImageData(dimensions=(56, 50, 40), spacing=(2.0, 2.0, 2.0), origin=(-55, -58, -30))
    img[arrays.TISSUE] = (((img.points / RADII) ** 2).sum(axis=1) < 1).astype(np.uint8)
    return img


def test_open_boundary_leaves_the_scan_end_open(cut_head):
    closed = extract_skin(cut_head)
    skin = extract_skin(cut_head, open_boundary=True)
    lo, hi = np.asarray(cut_head.bounds)[0::2], np.asarray(cut_head.bounds)[1::2]
    p = np.asarray(skin.points)
    assert ((p >= lo - 1e-3) & (p <= hi + 1e-3)).all()  # nothing beyond the image
    # the closed skin caps the cuts with faces half a voxel beyond the image
    assert (np.asarray(closed.points)[:, 2] < -30.5).any()
    assert (np.asarray(closed.points)[:, 1] > 40.5).any()
    # the open skin ends on the cuts: its boundary edges lie in the planes z = -30, y = 40
    edges = skin.extract_feature_edges(boundary_edges=True, feature_edges=False,
                                       manifold_edges=False, non_manifold_edges=False)
    e = np.asarray(edges.points)
    assert edges.n_cells > 50
    on_cut = (np.abs(e[:, 2] + 30.0) < 1e-3) | (np.abs(e[:, 1] - 40.0) < 1e-3)
    assert on_cut.all()
    # a flat cap would put points inside the ellipsoid at the cut: none here
    assert np.abs(_distance(p)).max() < 1.0
    # outward normals, one piece
    n = np.asarray(skin.point_data[arrays.NORMALS])
    assert (np.einsum("ij,ij->i", n, p / RADII ** 2) > 0).mean() > 0.99
    assert skin.connectivity().point_data["RegionId"].max() == 0


@pytest.mark.parametrize("shift", [0.0, 0.3, 0.7, 1.1, 1.6])
def test_open_cut_leaves_no_sliver_edges(cut_head, shift):
    """Contour points just beyond an image plane give no edges of a few micrometres at the
    cut (whose displacement jumps would be measured as crumpling)."""
    img = cut_head.copy()
    centre = np.array([0.3 * shift, shift, 0.7 * shift])  # the planes cross the contour anew
    img[arrays.TISSUE] = ((((img.points - centre) / RADII) ** 2).sum(axis=1) < 1).astype(np.uint8)
    skin = extract_skin(img, open_boundary=True)
    edges = skin.extract_all_edges()
    seg = np.asarray(edges.points)[edges.lines.reshape(-1, 3)[:, 1:]]
    shortest = np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1).min()
    assert shortest >= SLIVER_FRACTION * min(cut_head.spacing) * (1 - 1e-6)


def test_open_boundary_of_a_head_inside_the_image_is_the_closed_skin(head):
    closed, skin = extract_skin(head), extract_skin(head, open_boundary=True)
    assert skin.n_points == closed.n_points
    assert np.allclose(skin.points, closed.points, atol=1e-4)
    assert skin.n_open_edges == 0


def _sorted_points(surface):
    p = np.asarray(surface.points, dtype=float)
    return p[np.lexsort(p.T[::-1])]


def _contour_of_whole_image(mask, spacing, origin, sigma):
    """The reference: holes filled, smoothed and contoured over the whole padded image."""
    from scipy import ndimage

    vol = ndimage.gaussian_filter(ndimage.binary_fill_holes(np.pad(mask, 2)).astype(np.float32),
                                  sigma)
    grid = pv.ImageData(dimensions=vol.shape, spacing=spacing,
                        origin=np.asarray(origin) - 2 * np.asarray(spacing))
    grid["f"] = vol.ravel(order="F")
    surf = grid.contour([0.5], scalars="f", method="flying_edges")
    return surf.connectivity("largest").extract_surface(algorithm="dataset_surface").clean()


@pytest.mark.parametrize("touch", [False, True], ids=["inside", "cut by the image's end"])
def test_skin_made_on_the_head_s_box_is_that_of_the_whole_image(touch):
    """The skin is contoured on the head's box (plus a margin of air) to spare the air of a
    scan's field of view: its points are those of the whole image, bit for bit, for a head
    well inside the image and for one the image's end cuts."""
    img = pv.ImageData(dimensions=(90, 80, 60), spacing=(1.0, 1.2, 1.5), origin=(-40, -50, -30))
    p = np.asarray(img.points)
    head = ((p[:, 0] - 5) / 22) ** 2 + (p[:, 1] / 18) ** 2 + ((p[:, 2] - 5) / 20) ** 2 <= 1
    head &= ~(((p[:, 0] - 5) / 6) ** 2 + (p[:, 1] / 5) ** 2 + ((p[:, 2] - 5) / 5) ** 2 <= 1)
    if touch:
        head |= (np.hypot(p[:, 0] - 5, p[:, 1]) <= 9) & (p[:, 2] < 0)  # a neck to the end
    img[arrays.TISSUE] = np.where(head, arrays.FAT, arrays.AIR).astype(np.uint8)
    mask = head.reshape(img.dimensions, order="F")
    ours = extract_skin(img, sinc=0)
    reference = _contour_of_whole_image(mask, img.spacing, img.origin, 1.0)
    assert ours.n_points == reference.n_points
    np.testing.assert_array_equal(_sorted_points(ours), _sorted_points(reference))
