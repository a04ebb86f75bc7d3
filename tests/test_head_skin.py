"""The skin a prediction shows: the whole head, open where the scan ends, moved only where
the model reaches."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.skin_prediction import near_box, transfer_reach
from pvcmf.filters.surface_mapping import DEFAULT_BAND, Transfer, mesh_band
from pvcmf.pipeline import NECK_BELOW_BOX, TRANSFER_REACH, _skin, head_skin

RADII = np.array([60.0, 80.0, 90.0])


@pytest.fixture(scope="module")
def labels():
    """An ellipsoidal head of fat (semi-axes 60, 80, 90 mm) at 3 mm, the scan ending at
    z = -60 mm across the 'neck'."""
    img = pv.ImageData(dimensions=(46, 58, 53), spacing=(3.0, 3.0, 3.0), origin=(-69, -87, -60))
    inside = ((img.points / RADII) ** 2).sum(axis=1) < 1
    img[arrays.TISSUE] = np.where(inside, arrays.FAT, arrays.AIR).astype(np.uint8)
    return img


#: the model's box: the front of the head, above z = -30
BOX = (-70.0, 70.0, 20.0, 90.0, -30.0, 100.0)


@pytest.fixture(scope="module")
def post():
    """A tetrahedral 'face model' filling BOX with a smooth displacement field."""
    grid = pv.ImageData(dimensions=(15, 8, 14), spacing=(10.0, 10.0, 10.0),
                        origin=(-70.0, 20.0, -30.0)).cast_to_unstructured_grid().triangulate()
    p = np.asarray(grid.points)
    u = np.column_stack([0.01 * p[:, 2], 2.0 + 0.02 * p[:, 0], 0.03 * (p[:, 1] - 20.0)])
    grid.point_data[arrays.DISPLACEMENT] = u
    return grid


def test_head_skin_is_the_whole_head_open_at_the_scan_end(labels):
    skin = head_skin(labels)
    p = np.asarray(skin.points)
    assert p[:, 1].min() < -75.0 and p[:, 1].max() > 75.0  # the back and the front
    assert p[:, 2].min() >= -60.0 - 1e-3  # no cap beyond the scan's end
    assert skin.n_open_edges > 0  # left open there
    assert set(skin.point_data.keys()) == {arrays.NORMALS}
    # with the box: the neck more than NECK_BELOW_BOX under it is left out, openly
    cut = head_skin(labels, BOX)
    assert np.asarray(cut.points)[:, 2].min() == pytest.approx(BOX[4] - NECK_BELOW_BOX)
    assert np.asarray(cut.points)[:, 1].min() < -75.0  # the back of the head stays


def test_skin_moves_as_the_transfer_over_the_whole_head(labels, post):
    pre, moved = _skin(labels, post, None, BOX)
    whole = head_skin(labels, BOX)
    # the model's 10 mm mesh models the skin farther out than the smallest band
    band = mesh_band(post)
    assert band == pytest.approx(10.0) and TRANSFER_REACH == transfer_reach(DEFAULT_BAND)
    # the skin within reach of the model is the head's, point for point; farther, coarser
    tri = whole.faces.reshape(-1, 4)[:, 1:]
    near = near_box(whole.points, BOX, transfer_reach(band))
    reach = np.asarray(whole.points)[np.unique(tri[near[tri].all(axis=1)])]
    pts = {tuple(x) for x in np.asarray(pre.points).round(6)}
    assert all(tuple(x) in pts for x in reach.round(6))
    assert pre.n_points < whole.n_points - 0.5 * (len(whole.points) - len(reach))
    # no crack where the coarse part joins: the only open edges are the neck's cut
    edges = pre.extract_feature_edges(boundary_edges=True, feature_edges=False,
                                      manifold_edges=False, non_manifold_edges=False)
    assert edges.n_cells and np.allclose(np.asarray(edges.points)[:, 2], BOX[4] - NECK_BELOW_BOX)
    u = np.asarray(pre.point_data[arrays.DISPLACEMENT])
    # an independent transfer over every skin point: zero beyond the reach left out
    full = Transfer(post, np.asarray(pre.points))
    assert np.allclose(u, full(post[arrays.DISPLACEMENT]), atol=1e-9)
    assert np.array_equal(pre.point_data[arrays.SKIN_MODELLED].astype(bool), full.modelled)
    assert np.allclose(np.asarray(moved.points), np.asarray(pre.points) + u)
    # the back of the head does not move and is not modelled
    back = np.asarray(pre.points)[:, 1] < BOX[2] - transfer_reach(band)
    assert back.sum() > 100
    assert not u[back].any() and not pre.point_data[arrays.SKIN_MODELLED][back].any()
    # the face moves (2 mm forward at x = 0)
    front = np.asarray(pre.points)[:, 1] > 60.0
    assert np.median(u[front, 1]) == pytest.approx(2.0, abs=0.3)
    assert moved.field_data[arrays.SKIN_MODELLED_POINTS][0] == full.modelled.sum()
