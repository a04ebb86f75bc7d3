"""Small unmodelled islands that modelled skin encloses count as modelled
(:mod:`pvcmf.filters.skin_islands`), in :func:`map_to_surface` too."""

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.skin_islands import (fill_enclosed, island_area_limit, modelled_skin,
                                        skin_triangles, undo_decay)
from pvcmf.filters.skin import head_skin
from pvcmf.filters.skin_prediction import predict_skin
from pvcmf.filters.surface_mapping import Transfer, map_to_surface


def _sphere():
    return pv.Sphere(radius=20.0, theta_resolution=40, phi_resolution=40)


def test_hole_in_the_cap_filled_rest_kept():
    """A modelled cap (z > -5) with an unmodelled hole of a few points near its top; the
    rest (z <= -5, ~1900 mm^2) is unmodelled and stays so."""
    skin = _sphere()
    p = skin.points
    top = np.array([0.0, 0.0, 20.0])
    hole = np.linalg.norm(p - (top + [8.0, 0.0, -2.0]), axis=1) < 2.5
    rest = p[:, 2] <= -5.0
    assert 2 <= hole.sum() <= 10 and rest.sum() > 200
    modelled = ~rest & ~hole
    tri = skin_triangles(skin)
    out = fill_enclosed(p, tri, modelled, 200.0)
    assert out[hole].all()
    assert not out[rest].any()
    assert np.array_equal(out[~hole], modelled[~hole])
    assert not np.shares_memory(out, modelled) and not modelled[hole].any()  # input kept
    # a limit below the hole's area leaves it; a limit above the rest's fills all
    area = fill_enclosed(p, tri, modelled, 1e-6)
    assert not area[hole].any()
    assert fill_enclosed(p, tri, modelled, 1e5).all()
    # a skin that nothing models is no island, however small
    none = np.zeros(len(p), dtype=bool)
    assert not fill_enclosed(p, tri, none, 1e5).any()
    tiny = pv.Sphere(radius=1.0, center=(50.0, 0.0, 0.0))  # a separate piece, unmodelled
    both = (skin + tiny).clean()
    first = np.linalg.norm(both.points, axis=1) < 30.0  # the big sphere, modelled
    assert first.sum() == skin.n_points
    assert np.array_equal(fill_enclosed(both.points, skin_triangles(both), first, 1e5), first)


def test_islands_at_an_open_border_kept():
    """On an open surface an unmodelled patch touching the border is not enclosed."""
    skin = pv.Plane(i_size=40.0, j_size=40.0, i_resolution=40, j_resolution=40).triangulate()
    p = skin.points
    inner = np.linalg.norm(p[:, :2] - [0.0, 0.0], axis=1) < 2.5
    edge = np.linalg.norm(p[:, :2] - [20.0, 0.0], axis=1) < 2.5
    out = fill_enclosed(p, skin_triangles(skin), ~inner & ~edge, 200.0)
    assert out[inner].all() and not out[edge].any()


def test_point_cloud_and_inputs():
    cloud = pv.PolyData(np.random.default_rng(0).normal(size=(50, 3)))
    assert skin_triangles(cloud).shape == (0, 3)
    m = np.arange(50) % 2 == 0
    assert np.array_equal(fill_enclosed(cloud.points, skin_triangles(cloud), m, 1e9), m)
    with pytest.raises(ValueError, match="max_area"):
        fill_enclosed(cloud.points, np.zeros((0, 3), int), m, -1.0)
    with pytest.raises(ValueError, match="modelled"):
        fill_enclosed(cloud.points, np.zeros((0, 3), int), m[:-1], 1.0)
    with pytest.raises(ValueError, match="triangles"):
        fill_enclosed(cloud.points, [[0, 1, 50]], m, 1.0)


def test_area_limit_from_the_mesh_edge():
    grid = pv.ImageData(dimensions=(4, 4, 4), spacing=(3.0, 3.0, 3.0)).triangulate()
    pts, cells = grid.points, grid.cells_dict[pv.CellType.TETRA]
    e = np.concatenate([np.linalg.norm(pts[cells[:, i]] - pts[cells[:, j]], axis=1)
                        for i in range(4) for j in range(i + 1, 4)])
    h = np.median(e)
    assert island_area_limit(grid) == pytest.approx(np.pi * (2.0 * h) ** 2)
    assert island_area_limit(grid, 1.0) == pytest.approx(np.pi * h**2)
    with pytest.raises(ValueError, match="edges"):
        island_area_limit(grid, 0.0)


def _bumped():
    """A cube of tetrahedra (-5 .. 5 mm), a sphere whose left part lies within the band
    (4 mm) of it and right cap beyond, and a point on its top near x = 6 (about 1 mm
    from the cube, 3 mm from the cap) pushed 5 mm out: an island of one point beyond
    the band in the modelled skin."""
    grid = pv.ImageData(dimensions=(11, 11, 11), origin=(-5.0, -5.0, -5.0)).triangulate()
    grid[arrays.DISPLACEMENT] = 0.1 * grid.points
    skin = pv.Sphere(radius=5.5, center=(8.0, 0.0, 0.0), theta_resolution=30,
                     phi_resolution=30)
    p = np.asarray(skin.points)
    i = int(np.argmin(np.abs(p[:, 0] - 6.0) + np.abs(p[:, 2]) + 10.0 * (p[:, 1] < 0)))
    assert p[i, 1] > 4.5  # about (6, 5.1, 0): about 1 mm from the cube
    p = p.copy()
    p[i, 1] += 5.0
    skin.points = p
    return grid, skin, i


def test_map_to_surface_fills_the_bump():
    grid, skin, i = _bumped()
    tr = Transfer(grid, skin.points)
    assert not tr.modelled[i] and tr.distance[i] > tr.band  # beyond the band
    far = tr.distance > tr.band
    far[i] = False
    assert far.sum() > 50  # the large unmodelled cap
    out = map_to_surface(grid, skin)
    got = np.asarray(out[arrays.SKIN_MODELLED]).astype(bool)
    assert got[i]
    assert not got[far].any()
    assert np.array_equal(got, modelled_skin(skin, tr.modelled, grid))
    # the filled point takes the extension without the fade: the affine field exactly
    u = np.asarray(out[arrays.DISPLACEMENT])
    assert np.allclose(u[got], 0.1 * np.asarray(skin.points)[got], atol=1e-9)
    assert np.linalg.norm(tr(grid[arrays.DISPLACEMENT])[i] - u[i]) > 0.05  # faded there


def test_undo_decay():
    u = np.ones((4, 3))
    got = undo_decay(u, [True, True, False, True], [0.25, 1.0, 0.5, 0.0])
    assert np.allclose(got[:, 0], [4.0, 1.0, 1.0, 1.0]) and not np.shares_memory(got, u)
    with pytest.raises(ValueError, match="u_skin"):
        undo_decay(u, [True], [1.0])


def test_predict_skin_fills_a_bump_on_the_face():
    """An ellipsoidal head (semi-axes 60, 80, 90 mm; the front at y = 80) whose face lies in
    a box of tetrahedra reaching y = 82, with one skin point on the front pushed 8 mm out
    (6 mm beyond the mesh, beyond the 4 mm band): it is modelled and moves with the
    affine field; the back of the head is not modelled."""
    radii = np.array([60.0, 80.0, 90.0])
    img = pv.ImageData(dimensions=(46, 58, 53), spacing=(3.0, 3.0, 3.0), origin=(-69, -87, -60))
    inside = ((img.points / radii) ** 2).sum(axis=1) < 1
    img[arrays.TISSUE] = np.where(inside, arrays.FAT, arrays.AIR).astype(np.uint8)
    box = (-70.0, 70.0, 20.0, 82.0, -30.0, 100.0)
    grid = pv.ImageData(dimensions=(15, 8, 14), spacing=(10.0, 62.0 / 7.0, 10.0),
                        origin=(-70.0, 20.0, -30.0)).cast_to_unstructured_grid().triangulate()
    B = np.array([[0.0, 0.0, 0.01], [0.02, 0.0, 0.0], [0.0, 0.03, 0.0]])
    c = np.array([0.0, 2.0, -0.6])
    grid.point_data[arrays.DISPLACEMENT] = np.asarray(grid.points) @ B.T + c
    pre = head_skin(img, box)
    p = np.asarray(pre.points).copy()
    i = int(np.argmax(p[:, 1] - np.abs(p[:, 0]) - np.abs(p[:, 2])))
    assert p[i, 1] > 78.0
    p[i, 1] += 8.0
    pre.points = p
    assert Transfer(grid, p[i:i + 1]).distance[0] > 5.0
    out, moved = predict_skin(img, grid, pre=pre, box=box)  # the back is coarsened
    q = np.asarray(out.points)
    j = int(np.argmin(np.linalg.norm(q - p[i], axis=1)))
    assert np.allclose(q[j], p[i])
    m = np.asarray(out.point_data[arrays.SKIN_MODELLED]).astype(bool)
    u = np.asarray(out.point_data[arrays.DISPLACEMENT])
    assert m[j]
    assert np.allclose(u[j], q[j] @ B.T + c, atol=1e-9)
    assert (q[:, 1] < 0.0).sum() > 100 and not m[q[:, 1] < 0.0].any()
    assert moved.field_data[arrays.SKIN_MODELLED_POINTS][0] == m.sum()
