"""Fibre directions from oriented bounding boxes (paper 000, Fig. 3)."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

from pvcmf import arrays
from pvcmf.filters import fiber_directions, oriented_bounding_box
from pvcmf.filters.fibers import muscle_boxes, obb_polydata


def _angle(u, v):
    """Angle in degrees between two axes (sign ignored)."""
    c = abs(np.dot(u, v)) / np.linalg.norm(u) / np.linalg.norm(v)
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


ROT = Rotation.from_euler("zyx", [35, -20, 50], degrees=True).as_matrix()
SEMI = np.array([30.0, 10.0, 5.0])  # semi-axes, longest first
CENTER = np.array([12.0, -4.0, 30.0])


def _ellipsoid_points(n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1, 1, (4 * n, 3))
    p = p[(p**2).sum(1) <= 1][:n] * SEMI
    return CENTER + p @ ROT.T


def _ellipsoid_image(spacing=1.0, name="masseter_left"):
    n = int(np.ceil(2 * 34 / spacing)) + 1
    img = pv.ImageData(dimensions=(n, n, n), spacing=(spacing,) * 3, origin=CENTER - 34)
    local = (np.asarray(img.points) - CENTER) @ ROT  # coordinates in the ellipsoid frame
    inside = ((local / SEMI) ** 2).sum(1) <= 1
    img[arrays.MUSCLE] = np.where(inside, arrays.MUSCLE_IDS[name], 0).astype(np.uint8)
    return img, inside


def test_obb_recovers_ellipsoid_long_axis():
    center, axes, half = oriented_bounding_box(_ellipsoid_points())
    truth = ROT.T  # rows: the ellipsoid's axes, longest first
    for k in range(3):
        assert _angle(axes[k], truth[k]) < 2.0
    np.testing.assert_allclose(half, SEMI, rtol=0.03)
    np.testing.assert_allclose(center, CENTER, atol=0.5)
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)


def test_obb_sign_is_deterministic_and_box_holds_points():
    pts = _ellipsoid_points()
    _, a1, _ = oriented_bounding_box(pts)
    _, a2, _ = oriented_bounding_box(-(pts - CENTER) + CENTER)  # point-reflected copy
    assert (a1[:, 2] > 0).all()
    np.testing.assert_allclose(a1, a2, atol=1e-9)
    center, axes, half = oriented_bounding_box(pts)
    local = np.abs((pts - center) @ axes.T)
    assert (local <= half + 1e-9).all()
    box = obb_polydata(center, axes, half)
    assert box.n_open_edges == 0
    assert box.volume == pytest.approx(8 * np.prod(half), rel=1e-9)


def test_fiber_directions_image_single_box():
    img, inside = _ellipsoid_image(spacing=1.0)
    before = img.copy(deep=True)
    out = fiber_directions(img)
    fib = out.point_data[arrays.FIBER]
    assert fib.shape == (img.n_points, 3) and fib.dtype == np.float64
    assert np.all(fib[~inside] == 0)
    np.testing.assert_allclose(np.linalg.norm(fib[inside], axis=1), 1.0)
    assert _angle(fib[inside][0], ROT[:, 0]) < 2.0
    assert len(np.unique(fib[inside], axis=0)) == 1  # masseter: one box
    # the input is untouched
    assert arrays.FIBER not in img.point_data
    assert img == before


def test_two_level_boxes_follow_a_bent_muscle():
    """A V of two cylinders: level 1 would average them, level 2 finds each arm."""
    img = pv.ImageData(dimensions=(61, 61, 31), spacing=(1, 1, 1), origin=(-30, -30, -15))
    p = np.asarray(img.points)
    d1 = np.array([np.cos(np.radians(60)), np.sin(np.radians(60)), 0.0])
    d2 = np.array([np.cos(np.radians(120)), np.sin(np.radians(120)), 0.0])
    joint = np.array([0.0, -20.0, 0.0])

    def cylinder(d):
        t = (p - joint) @ d
        r = np.linalg.norm(p - joint - np.outer(t, d), axis=1)
        return (t >= 0) & (t <= 40) & (r <= 3)

    arm1, arm2 = cylinder(d1) & (p[:, 0] > 0), cylinder(d2) & (p[:, 0] <= 0)
    img[arrays.MUSCLE] = np.where(arm1 | arm2, arrays.MUSCLE_IDS["zygomaticus_major_left"], 0).astype(
        np.uint8
    )
    out = fiber_directions(img)  # zygomaticus: two-level boxes by default
    fib = out[arrays.FIBER]
    far1 = arm1 & ((p - joint) @ d1 > 12)
    far2 = arm2 & ((p - joint) @ d2 > 12)
    assert max(_angle(f, d1) for f in fib[far1]) < 5.0
    assert max(_angle(f, d2) for f in fib[far2]) < 5.0
    one = fiber_directions(img, levels=1)[arrays.FIBER]
    assert _angle(one[far1][0], d1) > 20.0  # a single box misses both arms
    boxes = muscle_boxes(img)
    assert [len(v) for v in boxes.values()] == [2]


def test_fiber_directions_tetrahedral_mesh():
    img, _ = _ellipsoid_image(spacing=2.0, name="levator_labii_superioris_right")
    grid = img.cast_to_unstructured_grid().triangulate()  # voxels -> tetrahedra
    centres = np.asarray(grid.cell_centers().points)
    local = (centres - CENTER) @ ROT
    inside = ((local / SEMI) ** 2).sum(1) <= 1
    grid.cell_data[arrays.MUSCLE] = np.where(
        inside, arrays.MUSCLE_IDS["levator_labii_superioris_right"], 0
    ).astype(np.uint8)
    grid.point_data.clear()
    out = fiber_directions(grid, levels=1)
    fib = out.cell_data[arrays.FIBER]
    assert fib.shape == (grid.n_cells, 3)
    assert np.all(fib[~inside] == 0)
    assert _angle(fib[inside][0], ROT[:, 0]) < 2.0
    two = fiber_directions(grid).cell_data[arrays.FIBER]  # two halves of a straight body
    assert max(_angle(f, ROT[:, 0]) for f in np.unique(two[inside], axis=0)) < 4.0


def test_bad_input():
    with pytest.raises(ValueError, match="muscle"):
        fiber_directions(pv.ImageData(dimensions=(3, 3, 3)))
    with pytest.raises(TypeError, match="ImageData"):
        fiber_directions(pv.Sphere())
    img, _ = _ellipsoid_image(spacing=3.0)
    with pytest.raises(ValueError, match="unknown muscle"):
        fiber_directions(img, levels={"biceps": 2})
    with pytest.raises(ValueError, match="levels"):
        fiber_directions(img, levels=0)
    img[arrays.MUSCLE][0] = 99
    with pytest.raises(ValueError, match="99"):
        fiber_directions(img)
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        oriented_bounding_box(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="finite"):
        oriented_bounding_box(np.full((5, 3), np.nan))
