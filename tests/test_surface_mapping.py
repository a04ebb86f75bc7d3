"""Mesh -> skin transfer: exact for affine fields, no steps (crumple metric), Gaussian kept."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters import map_to_surface
from pvcmf.filters.surface_mapping import (
    DEFAULT_BAND,
    SurfaceMapping,
    Transfer,
    crumple_metric,
    mesh_band,
    transfer_operator,
)
from pvcmf.filters.crumple_bound import unavoidable_crumples


@pytest.fixture(scope="module")
def ball():
    """A tetrahedral ball (radius 10 mm) and a skin sphere crossing its boundary."""
    src = pv.ImageData(dimensions=(23, 23, 23), spacing=(1.0, 1.0, 1.0), origin=(-11, -11, -11))
    grid = src.triangulate()
    keep = np.linalg.norm(grid.cell_centers().points, axis=1) < 10.0
    grid = grid.extract_cells(np.flatnonzero(keep)).clean()
    grid.clear_data()
    skin = pv.Sphere(radius=10.3, theta_resolution=80, phi_resolution=60)
    return grid, skin


def test_affine_exact_inside_and_outside(ball):
    grid, skin = ball
    rng = np.random.default_rng(0)
    B, c = rng.normal(size=(3, 3)) * 0.2, rng.normal(size=3)
    far = pv.PolyData(np.array([[30.0, 0, 0], [0, -25.0, 5.0], [0.0, 0.0, 60.0]]))
    for pts in (skin.points, np.asarray(grid.points)[:50] * 0.5, far.points):
        T = transfer_operator(grid, pts, band=np.inf)
        u = (T @ (grid.points @ B.T + c))
        assert np.abs(u - (pts @ B.T + c)).max() < 1e-9
    T = transfer_operator(grid, skin)  # default band: the skin lies within it
    assert np.abs(T @ (grid.points @ B.T + c) - (skin.points @ B.T + c)).max() < 1e-9
    assert np.allclose(np.asarray(T.sum(axis=1)).ravel(), 1.0)
    bounded = transfer_operator(grid, far.points) @ (grid.points @ B.T + c)
    assert np.abs(bounded).max() < np.abs(grid.points @ B.T + c).max() + 8 * np.abs(B).sum()


def test_inside_points_are_barycentric(ball):
    grid, _ = ball
    rng = np.random.default_rng(1)
    cells = grid.cells_dict[pv.CellType.TETRA]
    lam = rng.dirichlet(np.ones(4), size=40)
    ids = rng.choice(len(cells), 40, replace=False)
    pts = np.einsum("na,nai->ni", lam, np.asarray(grid.points)[cells[ids]])
    T = transfer_operator(grid, pts).toarray()
    want = np.zeros_like(T)
    for r, (t, l) in enumerate(zip(ids, lam)):
        want[r, cells[t]] = l
    assert np.abs(T - want).max() < 1e-9


def test_continuous_across_the_boundary(ball):
    """A curved field: points just in and just out of the mesh map to nearly equal values."""
    grid, _ = ball
    u = np.column_stack([np.sin(grid.points[:, 0] / 3), grid.points[:, 1] ** 2 / 20,
                         np.zeros(grid.n_points)])
    d = np.array([0.6, 0.5, 0.62])
    d /= np.linalg.norm(d)
    r = np.linspace(9.0, 11.0, 401)
    line = transfer_operator(grid, r[:, None] * d) @ u
    jumps = np.linalg.norm(np.diff(line, axis=0), axis=1)
    assert jumps.max() < 5 * np.median(jumps) + 1e-6  # no step where the line leaves the mesh


def test_crumple_metric_flags_nearest_copy(ball):
    grid, skin = ball
    u = np.column_stack([np.sin(grid.points[:, 0] / 2), np.cos(grid.points[:, 2] / 3),
                         0.1 * grid.points[:, 1]])
    good = transfer_operator(grid, skin) @ u
    m = crumple_metric(skin, good, grid, u)
    assert m[arrays.CRUMPLE_VIOLATIONS] == 0 and m[arrays.CRUMPLE_MAX_RATIO] <= 1.1
    from scipy.spatial import cKDTree
    near = cKDTree(grid.points).query(skin.points)[1]
    bad = crumple_metric(skin, u[near], grid, u)  # the nearest-node copy makes steps
    assert bad[arrays.CRUMPLE_VIOLATIONS] > 0


def test_crumple_metric_floor(ball):
    """A skin jump far beyond a vanishing mesh gradient counts unless it is below the
    floor (round-off of a region that does not move)."""
    grid, skin = ball
    u = np.zeros((grid.n_points, 3))
    u[:, 0] = 1e-7 * grid.points[:, 0]  # the mesh's gradient: 1e-7
    rng = np.random.default_rng(4)
    for scale, counted in ((1e-8, False), (1e-2, True)):  # jumps of ~scale mm
        noisy = transfer_operator(grid, skin) @ u + scale * rng.normal(size=(skin.n_points, 3))
        m = crumple_metric(skin, noisy, grid, u)
        assert (m[arrays.CRUMPLE_VIOLATIONS] > 0) == counted
        assert (m[arrays.CRUMPLE_MAX_RATIO] > 1.1) == counted
    assert crumple_metric(skin, noisy, grid, u, floor=1e3)[arrays.CRUMPLE_VIOLATIONS] == 0


def test_map_to_surface_methods(ball):
    grid, skin = ball
    g = grid.copy()
    g[arrays.DISPLACEMENT] = 0.05 * np.asarray(grid.points, float) + [1.0, 0.0, -2.0]
    out = map_to_surface(g, skin)
    want = 0.05 * np.asarray(skin.points, float) + [1, 0, -2]
    assert np.abs(out[arrays.DISPLACEMENT] - want).max() < 1e-9
    assert np.allclose(out.points, skin.points + out[arrays.DISPLACEMENT])
    assert set(np.unique(out[arrays.TRANSFER_INSIDE])) <= {0, 1}
    gauss = map_to_surface(g, skin, method="gaussian", sigma=1.5)
    ref = SurfaceMapping(grid.points, skin.points, 1.5, 4.5)(g[arrays.DISPLACEMENT])
    assert np.allclose(gauss[arrays.DISPLACEMENT], ref)
    assert arrays.MAPPING_SUPPORT in gauss.point_data
    assert np.allclose(Transfer(grid, skin.points)(g[arrays.DISPLACEMENT]),
                       out[arrays.DISPLACEMENT])
    with pytest.raises(ValueError, match="method"):
        map_to_surface(g, skin, method="nearest")
    with pytest.raises(ValueError, match="shape"):
        transfer_operator(grid, np.zeros((3, 2)))
    with pytest.raises(TypeError, match="UnstructuredGrid"):
        transfer_operator(skin, skin.points)


def test_modelled_skin_affine_and_unmodelled_decays(ball):
    """Points within ``band`` of the mesh are modelled and take an affine field exactly;
    points beyond ``2 band`` (skin the mesh does not model) take the fixed plane's zero."""
    grid, _ = ball
    rng = np.random.default_rng(3)
    B, c = rng.normal(size=(3, 3)) * 0.2, rng.normal(size=3)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    pts = d * rng.uniform(5.0, 22.0, size=(400, 1))  # inside, in the band, far out
    tr = Transfer(grid, pts, band=3.0)
    u = tr(grid.points @ B.T + c)
    want = pts @ B.T + c
    r = np.linalg.norm(pts, axis=1)
    assert tr.modelled.any() and (~tr.modelled).any()
    assert np.all(tr.modelled[r < 12.5]) and not np.any(tr.modelled[r > 14.5])
    assert np.abs(u - want)[tr.modelled].max() < 1e-9
    assert np.all(u[r > 17.0] == 0.0)
    assert np.allclose(tr.distance[tr.inside], 0.0)
    g = grid.copy()
    g[arrays.DISPLACEMENT] = grid.points @ B.T + c
    out = map_to_surface(g, pv.PolyData(pts), band=3.0)
    assert np.array_equal(out[arrays.SKIN_MODELLED].astype(bool), tr.modelled)


def test_coarse_mesh_models_skin_one_boundary_edge_out():
    """The band is the mesh's: a coarse mesh (8 mm boundary edges) that cuts the skin's
    bumps by 5-7 mm still models them (an affine field exactly), where the smallest band
    (4 mm) would fade them toward zero: dents in the predicted face."""
    grid = pv.ImageData(dimensions=(9, 9, 9), spacing=(8.0, 8.0, 8.0)).triangulate()
    fine = pv.ImageData(dimensions=(9, 9, 9), spacing=(2.0, 2.0, 2.0)).triangulate()
    band = mesh_band(grid)
    assert band == pytest.approx(8.0)  # the median boundary edge
    assert mesh_band(fine) == DEFAULT_BAND  # never below the smallest band
    xy = np.random.default_rng(5).uniform(8.0, 56.0, size=(300, 2))
    pts = np.column_stack([xy, 64.0 + np.linspace(5.0, 7.0, 300)])  # a bump over the top
    B, c = np.diag([0.02, -0.01, 0.03]), np.array([0.0, 4.0, 1.0])
    u = grid.points @ B.T + c
    want = pts @ B.T + c
    tr = Transfer(grid, pts)
    assert tr.band == band and tr.modelled.all()
    assert np.abs(tr(u) - want).max() < 1e-9
    narrow = Transfer(grid, pts, band=DEFAULT_BAND)  # faded: the dent
    assert not narrow.modelled.any()
    assert np.linalg.norm(narrow(u) - want, axis=1).max() > 3.0
    g = grid.copy()
    g[arrays.DISPLACEMENT] = u
    assert map_to_surface(g, pv.PolyData(pts))[arrays.SKIN_MODELLED].all()
    for bad in (0.0, -1.0, True, "x"):
        with pytest.raises(ValueError, match="band must be > 0"):
            Transfer(grid, pts, band=bad)


def test_pruned_feet_equal_every_candidate_measured(ball):
    """The feet measure far candidate triangles only where they could enter the blend
    window: the result equals measuring all of them."""
    from pvcmf.filters.transfer_locate import Located

    grid, skin = ball
    pts = np.asarray(skin.points) * np.r_[1.0, 1.1, 1.3]  # some points well outside
    pruned = Located(grid, pts, reach=8.0)
    full = Located.__new__(Located)
    full.__dict__.update({k: getattr(pruned, k) for k in ("points", "tets", "p")})
    full.dist = np.where(pruned.inside, 0.0, np.inf)
    from pvcmf.filters.skin import _boundary_faces

    src = pv.UnstructuredGrid({pv.CellType.TETRA: pruned.tets}, pruned.points)
    rows, q, bary, face = full._feet(_boundary_faces(src), pruned.outside, 24, exact=24)
    assert np.array_equal(rows, pruned.pair_row) and np.array_equal(face, pruned.face)
    assert np.allclose(q, pruned.q, rtol=0, atol=1e-12)
    assert np.allclose(full.pair_w, pruned.pair_w, rtol=0, atol=1e-12)
    assert np.array_equal(full.dist, pruned.dist)


def test_unavoidable_crumples_across_a_gap():
    """Two blocks 2 mm apart, each moved rigidly (no gradient), their 1 mm apart moves
    bridged by a skin plate across the gap: every transfer must stretch an edge there, so
    the lower bound counts the patch in the gap; moved together there is nothing to
    bridge and the bound is zero (as for any field the transfer already passes)."""
    src = pv.ImageData(dimensions=(9, 9, 5), origin=(-4.0, -4.0, 0.0)).triangulate()
    centres = src.cell_centers().points
    grid = src.extract_cells(np.flatnonzero(np.abs(centres[:, 0]) > 1.0)).clean()
    grid.clear_data()
    plate = pv.Plane(center=(0, 0, 2.0), direction=(0, 0, 1), i_size=7, j_size=7,
                     i_resolution=28, j_resolution=28).triangulate()
    x = np.asarray(grid.points)
    for shift, forced in ((1.0, True), (0.0, False)):
        u = np.zeros((grid.n_points, 3))
        u[x[:, 0] > 0, 2] = shift
        c = unavoidable_crumples(plate, grid, u)
        assert (c[arrays.CRUMPLE_UNAVOIDABLE] >= 1) == forced
        assert c["points"].any() == forced
        m = crumple_metric(plate, transfer_operator(grid, plate) @ u, grid, u)
        assert m[arrays.CRUMPLE_VIOLATIONS] >= c[arrays.CRUMPLE_UNAVOIDABLE]


def test_rows_kernels_and_bin_table_equal_the_plain_paths(ball, monkeypatch):
    """The rows' assembly on scipy's kernels (int32, bounded product, sort by double
    transpose) equals the one on scipy's operators bit for bit, and the boxes' bin table
    lists the same boxes as binary searches of the sorted bins."""
    from pvcmf.filters import transfer_assembly
    from pvcmf.filters.surface_mapping import _decay, _fit_weights
    from pvcmf.filters.transfer_locate import Located

    grid, skin = ball
    pts = np.vstack([np.asarray(skin.points) * np.r_[1.0, 1.1, 1.3],
                     np.asarray(grid.points)[::7] * 0.9])  # outside and inside
    loc = Located(grid, pts, reach=8.0)
    alpha, offset = _fit_weights(loc)
    decay = _decay(loc.dist, 4.0)
    args = (loc, alpha * decay[loc.pair_row], offset * decay[loc.outside][:, None])
    fast = transfer_assembly.rows_operator(*args)
    monkeypatch.setattr(transfer_assembly, "csr_matmat", None)
    plain = transfer_assembly.rows_operator(*args)
    assert fast.nnz > 10 * len(pts) and fast.has_sorted_indices
    within = np.ones(fast.nnz, dtype=bool)  # entries after the first of their row
    within[fast.indptr[:-1][np.diff(fast.indptr) > 0]] = False
    assert (np.diff(fast.indices)[within[1:]] > 0).all()  # each row's indices increase
    for a in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(fast, a), getattr(plain, a)), a
    bins = loc.index.bins
    probe = np.vstack([pts, np.random.default_rng(0).uniform(-15, 15, (500, 3))])
    table = bins.of(probe)
    monkeypatch.setattr(bins, "_first", lambda: None)
    searched = bins.of(probe)
    assert table[1].size and (table[2] > table[1]).any() and (table[2] == table[1]).any()
    for a, b in zip(table, searched):
        assert np.array_equal(a, b)
