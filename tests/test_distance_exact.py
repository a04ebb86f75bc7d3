"""Exact signed distance (distance_to / signed_distance): against brute force and geometry.

The brute force here is independent of both engines: the distance to a triangle is the
plane distance when the projection falls inside it, else the smallest distance to its
three edges (clamped segment projection), evaluated for every point x triangle pair.
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

import pvcmf  # noqa: F401  (cmf accessor)
from pvcmf import arrays
from pvcmf.filters.distance import signed_distance



def _segment_distance(p, a, b):
    ab = b - a
    t = np.clip(np.einsum("...j,...j->...", p - a, ab) / np.einsum("...j,...j->...", ab, ab),
                0.0, 1.0)
    return np.linalg.norm(p - (a + t[..., None] * ab), axis=-1)


def brute_force(points, surface):
    """Unsigned distance of every point to every triangle, minimum over triangles."""
    tri = surface.faces.reshape(-1, 4)[:, 1:]
    a, b, c = (np.asarray(surface.points, dtype=float)[tri[:, k]][None] for k in range(3))
    p = np.asarray(points, dtype=float)[:, None]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    h = np.einsum("...j,...j->...", p - a, n)
    proj = p - h[..., None] * n
    # inside test: same-side signs of the three edge cross products
    s0 = np.einsum("...j,...j->...", np.cross(b - a, proj - a), n)
    s1 = np.einsum("...j,...j->...", np.cross(c - b, proj - b), n)
    s2 = np.einsum("...j,...j->...", np.cross(a - c, proj - c), n)
    inside = (s0 >= 0) & (s1 >= 0) & (s2 >= 0)
    edges = np.minimum(np.minimum(_segment_distance(p, a, b), _segment_distance(p, b, c)),
                       _segment_distance(p, c, a))
    return np.where(inside, np.abs(h), edges).min(axis=1)


def random_mesh(seed, n=60):
    """A random, bumpy, open triangle surface (a height field with random heights)."""
    rng = np.random.default_rng(seed)
    grid = pv.Plane(i_resolution=8, j_resolution=8, i_size=10, j_size=10).triangulate()
    pts = np.asarray(grid.points, dtype=float)
    pts[:, 2] = rng.normal(0, 1.5, len(pts))
    pts[:, :2] += rng.uniform(-0.4, 0.4, (len(pts), 2))
    grid.points = pts
    return grid, rng.uniform(-7, 7, (n * 5, 3))


@pytest.mark.parametrize("method", ["igl", "vtk"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_unsigned_matches_brute_force(method, seed):
    if method == "igl":
        pytest.importorskip("igl")
    surface, points = random_mesh(seed)
    d = signed_distance(points, surface, method=method)
    ref = brute_force(points, surface)
    assert np.abs(np.abs(d) - ref).max() < 1e-9


@pytest.mark.parametrize("method", ["igl", "vtk"])
def test_concentric_spheres_radius_difference_and_sign(method):
    if method == "igl":
        pytest.importorskip("igl")
    truth = pv.Sphere(radius=10.0, theta_resolution=120, phi_resolution=120)
    outer = pv.Sphere(radius=11.0, theta_resolution=40, phi_resolution=40)
    inner = pv.Sphere(radius=9.0, theta_resolution=40, phi_resolution=40)
    d_out = outer.cmf.distance_to(truth, method=method)[arrays.DISTANCE]
    d_in = inner.cmf.distance_to(truth, method=method)[arrays.DISTANCE]
    # the polyhedron lies inside the sphere by at most its sagitta
    sagitta = 10.0 * (1 - np.cos(np.pi / 120))
    assert np.all(d_out > 0) and np.all(d_in < 0)
    assert np.abs(d_out - 1.0).max() <= sagitta + 1e-9
    assert np.abs(d_in + 1.0).max() <= sagitta + 1e-9


def test_sign_at_edges_and_vertices_of_a_cube():
    """Closest features that are edges and corners take the pseudo-normal's sign."""
    pytest.importorskip("igl")
    cube = pv.Cube().triangulate()  # [-0.5, 0.5]^3
    pts = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.9], [0.3, 0.3, 0.3],
                    [0.5, 0.5, 0.5], [-0.8, 0.0, -0.8], [0.45, 0.45, 0.0]])
    expected = [np.sqrt(3) / 2, np.sqrt(2) / 2, 0.4, -0.2, 0.0, 0.3 * np.sqrt(2), -0.05]
    for method in ("igl", "vtk"):
        d = signed_distance(pts, cube, method=method)
        np.testing.assert_allclose(d, expected, atol=1e-12, err_msg=method)


def test_engines_agree_on_a_head_like_surface():
    pytest.importorskip("igl")
    truth = pv.ParametricEllipsoid(70, 90, 110, u_res=80, v_res=60).triangulate().clean()
    rng = np.random.default_rng(3)
    pts = np.asarray(truth.points)[rng.choice(truth.n_points, 2000)] * rng.uniform(
        0.97, 1.03, (2000, 1))
    pred = pv.PolyData(pts)
    a = pred.cmf.distance_to(truth, method="igl")[arrays.DISTANCE]
    b = pred.cmf.distance_to(truth, method="vtk")[arrays.DISTANCE]
    assert np.abs(a - b).max() < 1e-9


def test_open_surface_sign_follows_outward_orientation():
    """An open face-like cap: points in front read positive whatever its winding."""
    cap = pv.Sphere(radius=50.0, theta_resolution=60, phi_resolution=60).clip(
        normal=(0, -1, 0), origin=(0, 20, 0)).triangulate()
    flipped = cap.copy()
    faces = flipped.faces.reshape(-1, 4)
    flipped.faces = np.column_stack([faces[:, 0], faces[:, 1:][:, ::-1]]).ravel()
    front = pv.PolyData(np.array([[0.0, 52.0, 0.0], [5.0, 48.0, 3.0]]))
    for surface in (cap, flipped):
        d = front.cmf.distance_to(surface)[arrays.DISTANCE]
        assert d[0] > 1.9 and d[1] < 0


def test_bad_method_and_inputs():
    s = pv.Sphere()
    with pytest.raises(ValueError, match="method"):
        signed_distance(s.points, s, method="kdtree")
    with pytest.raises(ValueError, match="non-empty"):
        s.cmf.distance_to(pv.PolyData())
    with pytest.raises(TypeError, match="PolyData"):
        s.cmf.distance_to(pv.ImageData(dimensions=(2, 2, 2)))
    with pytest.raises(ValueError, match="do not overlap"):
        s.translate((100, 0, 0)).cmf.distance_to(s, max_distance=5.0)


@pytest.mark.parametrize("method", ["igl", "vtk"])
def test_surface_distance_reused_matches_brute_force(method):
    """One SurfaceDistance, several query batches: each batch exact."""
    if method == "igl":
        pytest.importorskip("igl")
    from pvcmf.filters.distance import SurfaceDistance

    surface, points = random_mesh(5)
    dist = SurfaceDistance(surface, method=method)
    for batch in np.array_split(points, 3):
        assert np.abs(np.abs(dist(batch)) - brute_force(batch, surface)).max() < 1e-9


def test_sign_when_edges_and_vertices_are_closest():
    """A coarse convex polyhedron and far points: most closest features are edges and
    vertices; every outside point reads positive, every inside point negative."""
    pytest.importorskip("igl")
    poly = pv.Sphere(radius=1.0, theta_resolution=7, phi_resolution=6).triangulate().clean()
    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    outside = dirs * rng.uniform(1.2, 4.0, (3000, 1))
    inside = dirs * rng.uniform(0.0, 0.6, (3000, 1))
    d_out = signed_distance(outside, poly, method="igl")
    d_in = signed_distance(inside, poly, method="igl")
    assert np.all(d_out > 0) and np.all(d_in < 0)
    ref = brute_force(np.vstack([outside, inside]), poly)
    assert np.abs(np.abs(np.r_[d_out, d_in]) - ref).max() < 1e-9


@pytest.mark.parametrize("method", ["igl", "vtk"])
def test_sign_matches_an_inside_test_on_a_bumpy_closed_surface(method):
    """Concave edges and vertices too: the sign agrees with VTK's enclosed-points test
    (ray parity, independent of closest points) for points not on the surface."""
    if method == "igl":
        pytest.importorskip("igl")
    s = pv.Sphere(radius=10.0, theta_resolution=14, phi_resolution=12).triangulate().clean()
    rng = np.random.default_rng(11)
    p = np.asarray(s.points, dtype=float)
    s.points = p * rng.uniform(0.7, 1.3, (len(p), 1))  # star-shaped, many concave edges
    pts = rng.uniform(-13, 13, (4000, 3))
    d = signed_distance(pts, s, method=method)
    inside = np.asarray(pv.PolyData(pts).select_interior_points(s)["selected_points"]
                        if hasattr(pv.PolyData, "select_interior_points") else
                        pv.PolyData(pts).select_enclosed_points(s)["SelectedPoints"], bool)
    clear = np.abs(d) > 1e-3
    assert clear.sum() > 3900
    assert np.array_equal(d[clear] < 0, inside[clear])
