"""Refinement of the independent truth (:mod:`pvcmf.truth.refinement`).

* the skin sampler: points on the exact skin (the patient's level set is zero there);
* the displacement at a boundary point: exact for an affine field (linear interpolation
  on the closest boundary triangle), and the distance to the boundary is the analytic one;
  with the exact skin's normals, the closest point of two lips facing each other across a
  gap is on the lip facing the same way (any closest triangle: the other lip), and the
  closest point on a triangle is a brute-force search's;
* the graded mesher: its radial map samples the size it is given (``h_face`` in the
  ball, growing by ``GRADING`` beyond it, never coarser along the sphere); on virtual
  patient 1 its skin triangles are about ``face_mm`` in the ball of the moved bones and no
  coarser than the conforming mesh's of the same count far from it, it meshes as much of
  the exact volume as that mesh (the thin tissue kept) and reaches the skin over the
  vault as often;
* convergence: the truth's mesher and boundary model on virtual patient 1 at three lattice
  sizes, solved with the small-strain control law on linear elements (seconds, where the
  P2 neo-Hookean truth takes minutes; the mesher and the boundary model are the same):
  the skin's change between successive refinements shrinks at a positive rate, in the
  median and in the 90th percentile. A model that moves with the lattice (tied nodes
  switched free node by node along a cut, muscle by the centroid of each element, a
  tongue hanging on bridges of tissue between the teeth, boundary nodes left off the
  surface) keeps the 90th percentile from shrinking. The target of the benchmark, a 90th
  percentile change of at most 0.1 mm, is a strict xfail: these lattices are far too coarse
  for it, and the P2 truth on the graded mesh reaches it on a patient with a moved mandible
  only (``docs/benchmarks/truth_refinement.md``).
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays

pytest.importorskip("ngsolve")


def test_skin_displacement_is_exact_for_an_affine_field():
    from pvcmf.truth.refinement import skin_displacement

    g = pv.ImageData(dimensions=(5, 5, 5), spacing=(2.5, 2.5, 2.5)).cast_to_unstructured_grid()
    g = g.triangulate()
    a = np.array([[0.1, 0.2, 0.0], [0.0, -0.3, 0.1], [0.05, 0.0, 0.2]])
    g[arrays.DISPLACEMENT] = g.points @ a.T + [1.0, 2.0, 3.0]
    rng = np.random.default_rng(0)
    # points above the top face z = 10 and beside the face x = 0
    top = np.column_stack([rng.uniform(0.5, 9.5, (50, 2)), rng.uniform(10.0, 12.0, 50)])
    side = np.column_stack([rng.uniform(-2.0, 0.0, 50), rng.uniform(0.5, 9.5, (50, 2))])
    pts = np.vstack([top, side])
    u, d = skin_displacement(g, pts)
    foot = pts.copy()
    foot[:50, 2] = 10.0
    foot[50:, 0] = 0.0
    np.testing.assert_allclose(d, np.linalg.norm(pts - foot, axis=1), atol=1e-9)
    np.testing.assert_allclose(u, foot @ a.T + [1.0, 2.0, 3.0], atol=1e-9)


def test_refinement_change_of_skin_states_equals_that_of_the_grids():
    """A study may keep each truth's skin state and drop its mesh: same change, same reach."""
    from pvcmf.truth.refinement import refinement_change, skin_state

    coarse = pv.ImageData(dimensions=(3, 3, 3), spacing=(5.0,) * 3).cast_to_unstructured_grid()
    fine = pv.ImageData(dimensions=(5, 5, 5), spacing=(2.5,) * 3).cast_to_unstructured_grid()
    coarse, fine = coarse.triangulate(), fine.triangulate()
    coarse[arrays.DISPLACEMENT] = 0.1 * coarse.points
    fine[arrays.DISPLACEMENT] = 0.1 * fine.points + np.sin(fine.points)
    rng = np.random.default_rng(1)
    # on the top face, and some above it by more than the default reach (1.25 mm)
    pts = np.column_stack([rng.uniform(0.5, 9.5, (60, 2)), np.r_[np.full(40, 10.0),
                                                                  np.full(20, 12.0)]])
    by_grid = refinement_change(coarse, fine, pts)
    states = [skin_state(g, pts) for g in (coarse, fine)]
    by_state = refinement_change(*states, pts)
    assert states[0]["edge"] == pytest.approx(5.0)
    assert by_grid["compared"] == pytest.approx(40 / 60)
    for key in ("change", "fine"):
        np.testing.assert_array_equal(by_state[key], by_grid[key])
    assert (by_state["p90"], by_state["compared"]) == (by_grid["p90"], by_grid["compared"])
    with pytest.raises(ValueError, match="coarse skin state has 60 points, expected the 10"):
        refinement_change(states[0], fine, pts[:10])


def test_skin_displacement_is_exact_for_a_quadratic_field_with_midpoint_values():
    from pvcmf.truth.refinement import skin_displacement

    g = pv.ImageData(dimensions=(4, 4, 4), spacing=(3.0, 3.0, 3.0)).cast_to_unstructured_grid()
    g = g.triangulate()

    def field(x):
        return np.column_stack([0.01 * x[:, 0] ** 2, 0.02 * x[:, 0] * x[:, 1],
                                0.03 * x[:, 2] ** 2 - 0.01 * x[:, 1]])

    tets = g.cells_dict[pv.CellType.TETRA]
    edges = np.unique(np.sort(tets[:, [0, 0, 0, 1, 1, 2, 1, 2, 3, 2, 3, 3]].reshape(-1, 2, 6)
                              .transpose(0, 2, 1).reshape(-1, 2), axis=1), axis=0)
    g[arrays.DISPLACEMENT] = field(g.points)
    g.field_data[arrays.REFERENCE_EDGES] = edges
    g.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT] = field(g.points[edges].mean(axis=1))
    rng = np.random.default_rng(1)
    top = np.column_stack([rng.uniform(0.5, 8.5, (60, 2)), rng.uniform(9.0, 11.0, 60)])
    foot = top.copy()
    foot[:, 2] = 9.0
    u, _ = skin_displacement(g, top)
    np.testing.assert_allclose(u, field(foot), atol=1e-9)
    # the vertex values alone (linear interpolation) miss the curvature of the field
    del g.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT]
    del g.field_data[arrays.REFERENCE_EDGES]
    assert np.abs(skin_displacement(g, top)[0] - field(foot)).max() > 1e-3


def test_solve_reference_keeps_the_p2_field_at_the_edge_midpoints():
    from pvcmf.truth import solve_reference

    g = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid().triangulate()
    g[arrays.BC] = np.full(g.n_points, arrays.BC_JOINT, dtype=np.int8)
    a = np.array([[0.02, 0.01, 0.0], [0.0, -0.03, 0.01], [0.01, 0.0, 0.02]])
    g[arrays.BC_DISPLACEMENT] = g.points @ a.T
    g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, 0.003)
    g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    out = solve_reference(g, law="linear", steps=1, threads=False)
    edges = out.field_data[arrays.REFERENCE_EDGES]
    mid = out.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT]
    tets = g.cells_dict[pv.CellType.TETRA]
    assert len(edges) == len({tuple(sorted(e)) for t in tets for e in
                              [(t[i], t[j]) for i in range(4) for j in range(i + 1, 4)]})
    np.testing.assert_allclose(mid, g.points[edges].mean(axis=1) @ a.T, atol=1e-9)


def test_conforming_mesh_fills_the_exact_soft_tissue(case):
    from pvcmf.filters.model_region import face_box
    from pvcmf.truth.anatomy import _warp
    from pvcmf.truth.conform import conforming_mesh
    from pvcmf.truth.exact import _BOUNDARY, _fields, _region

    grid = conforming_mesh(case, spacing=7.5)
    x = np.asarray(grid.points)
    q = x[grid.cells_dict[pv.CellType.TETRA]]
    assert np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]),
                     q[:, 3] - q[:, 0]).min() > 0
    # the exact volume of the meshed region (Monte Carlo over the mesh's bounding box)
    warp = _warp(case)
    y0 = face_box(case.truth, 0.5)[2]
    lo, hi = x.min(axis=0) - 5.0, x.max(axis=0) + 5.0
    lo[1] = y0
    p = np.random.default_rng(0).uniform(lo, hi, (200_000, 3))
    exact = np.mean(_region(_fields(warp, p))[0] < 0) * np.prod(hi - lo)
    # (the lattice mesher of about as many tetrahedra meshes some 85 % of it)
    assert abs(grid.volume / exact - 1) < 0.03, (grid.volume, exact)
    kind = np.asarray(grid["boundary"])
    surface = (kind > 0) & (kind <= len(_BOUNDARY))
    r, _ = _region(_fields(warp, x[surface]))
    # most boundary nodes on the exact surfaces; the others stay where the projection would
    # flatten an element (tissue about one element thick)
    assert np.mean(np.abs(r) < 0.05) > 0.75


@pytest.fixture(scope="module")
def case():
    import pvcmf

    return pvcmf.datasets.phantom(1, spacing=3.0)


def test_exact_skin_samples_lie_on_the_exact_skin(case):
    from pvcmf.filters.model_region import face_box
    from pvcmf.truth.anatomy import true_level_set
    from pvcmf.truth.refinement import exact_skin_samples

    p = exact_skin_samples(case)
    assert len(p) > 2000
    assert np.abs(true_level_set(case, "skin", p)).max() < 0.05
    assert p[:, 1].min() > face_box(case.truth, 0.5)[2]


def _refinement_changes(case):
    """Skin change between the 2k/4k and 4k/8k linear truths, and the mesh sizes."""
    from pvcmf import filters
    from pvcmf.truth.independent import _boundary_conditions, soft_tissue_mesh
    from pvcmf.truth.refinement import exact_skin_samples, refinement_change
    from pvcmf.truth.solver import solve_reference

    points = exact_skin_samples(case)
    solved, h = [], []
    for n in (2000, 4000, 8000):
        g = _boundary_conditions(case, soft_tissue_mesh(case, n_tets=n))
        g = filters.assign_materials(g, default_fiber=(0.0, 0.0, 1.0))
        solved.append(solve_reference(g, order=1, law="linear", steps=1, threads=False))
        h.append(n ** (-1 / 3))
    return refinement_change(solved[0], solved[1], points), \
        refinement_change(solved[1], solved[2], points), h


@pytest.fixture(scope="module")
def changes(case):
    return _refinement_changes(case)


@pytest.mark.slow
def test_truth_skin_median_converges_under_refinement(changes):
    first, second, h = changes
    rate = np.log(first["p50"] / second["p50"]) / np.log(h[1] / h[2])
    assert rate > 0.5, (first["p50"], second["p50"], rate)
    assert second["compared"] > first["compared"] > 0.3


@pytest.mark.slow
def test_truth_skin_p90_converges_under_refinement(changes):
    first, second, h = changes
    rate = np.log(first["p90"] / second["p90"]) / np.log(h[1] / h[2])
    assert rate > 1.0, (first["p90"], second["p90"], rate)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="this CI-sized truth (linear P1 on the lattice mesh, "
                   "4000 -> 8000 tetrahedra) is not converged: its skin changes by p90 more "
                   "than 0.1 mm; the converged truth is the P2 one on the graded mesh of "
                   "docs/benchmarks/truth_refinement.md (face 2.56 mm where the maxilla moves, "
                   "3.2 mm where the mandible does, the ball holding the tissue within 30 mm "
                   "of the moved bones: p90 0.04-0.09 mm between its two finest), minutes to "
                   "an hour per solve")
def test_truth_skin_p90_change_is_within_a_tenth_of_a_millimetre(changes):
    _, second, _ = changes
    assert second["p90"] <= 0.1, second["p90"]


def _two_lips():
    """Two blocks facing each other across a 0.4 mm gap (z 0-2 and 2.4-4.4): the lower
    one moved by -1 mm, the upper one by +1 mm along z."""
    lower = pv.ImageData(dimensions=(4, 4, 2), spacing=(2.0, 2.0, 2.0))
    upper = pv.ImageData(dimensions=(4, 4, 2), spacing=(2.0, 2.0, 2.0), origin=(0, 0, 2.4))
    g = lower.cast_to_unstructured_grid().triangulate().merge(
        upper.cast_to_unstructured_grid().triangulate(), merge_points=False)
    g[arrays.DISPLACEMENT] = np.where(g.points[:, 2:3] > 2.2, 1.0, -1.0) * [0.0, 0.0, 1.0]
    return g


def test_closest_point_on_the_facing_triangles_stays_on_its_own_lip():
    from pvcmf.truth.refinement import skin_displacement

    g = _two_lips()
    rng = np.random.default_rng(2)
    # points of the upper lip's lower surface (outward normal -z), seen by a mesh whose
    # surface lies 0.25 mm off: nearer the lower lip's upper surface (0.15 mm)
    p = np.column_stack([rng.uniform(0.5, 5.5, (40, 2)), np.full(40, 2.15)])
    down = np.tile([0.0, 0.0, -1.0], (40, 1))
    u_any, d_any = skin_displacement(g, p)
    np.testing.assert_allclose(u_any[:, 2], -1.0)  # any closest triangle: the other lip
    np.testing.assert_allclose(d_any, 0.15, atol=1e-9)
    u, d = skin_displacement(g, p, normals=down)
    np.testing.assert_allclose(u[:, 2], 1.0)  # its own lip
    np.testing.assert_allclose(d, 0.25, atol=1e-9)
    # where the closest triangle faces the same way, nothing changes
    up = -down
    np.testing.assert_allclose(skin_displacement(g, p, normals=up)[0], u_any)


def test_closest_point_on_triangles_matches_a_brute_force_search():
    from pvcmf.truth.refinement import _closest_on_triangles

    rng = np.random.default_rng(3)
    tri = rng.normal(size=(60, 3, 3))
    p = rng.normal(scale=2.0, size=(200, 3))
    q = _closest_on_triangles(p[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    d = np.linalg.norm(q - p[:, None], axis=2)
    # brute force: dense barycentric samples of each triangle
    s = np.array([(i, j) for i in range(41) for j in range(41 - i)]) / 40.0
    dense = (tri[:, None, 0] + s[None, :, :1] * (tri[:, None, 1] - tri[:, None, 0])
             + s[None, :, 1:] * (tri[:, None, 2] - tri[:, None, 0]))
    for k in range(0, 200, 25):  # chunks bound the memory
        brute = np.linalg.norm(dense[None] - p[k:k + 25, None, None], axis=3).min(axis=2)
        assert np.all(d[k:k + 25] <= brute + 1e-12)
        assert np.all(d[k:k + 25] >= brute - 0.1)


def test_radial_map_samples_the_size_it_is_given():
    from pvcmf.truth.graded import radial_map

    phi, size = radial_map(np.array([1.0, 2.0, 3.0]), 20.0, 2.0, 5.0, grading=0.25)
    ray = np.array([1.0, 2.0, 3.0]) + np.outer(np.arange(0.0, 200.0, 2.0), [0.6, 0.0, 0.8])
    x = phi(ray)
    rho = np.linalg.norm(x - [1.0, 2.0, 3.0], axis=1)
    np.testing.assert_allclose(rho[:11], np.arange(0.0, 21.0, 2.0), atol=1e-9)  # identity
    step = np.diff(rho)  # radial spacing of the mapped grid: the size at that radius
    mid = 0.5 * (rho[1:] + rho[:-1])
    np.testing.assert_allclose(step, size(mid), rtol=0.02)
    assert step[0] == pytest.approx(2.0) and step[-1] == pytest.approx(5.0)
    # along the sphere the grid is never coarser than the size
    assert np.all(rho[1:] / np.linalg.norm(ray[1:] - ray[0], axis=1) * 2.0 <= size(rho[1:]) + 1e-9)


def test_graded_mesh_is_fine_in_the_face_and_keeps_the_vault_shell(case):
    from pvcmf.filters.model_region import face_box
    from pvcmf.truth.anatomy import _warp
    from pvcmf.truth.conform import conforming_mesh
    from pvcmf.truth.exact import _fields, _region
    from pvcmf.truth.graded import GRADING, face_ball, graded_mesh
    from pvcmf.truth.refinement import exact_skin_samples, skin_displacement

    face, n = 4.0, 8000
    graded, uniform = graded_mesh(case, n_tets=n, face_mm=face), conforming_mesh(case, n_tets=n)
    centre, radius = face_ball(case)

    def skin_edges(grid):
        """Boundary edges on the skin: lengths and distances of their midpoints from the
        centre of the face ball."""
        kind = np.asarray(grid["boundary"])
        surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface")
        e = surf.extract_all_edges()
        ids = np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS])[
            e.lines.reshape(-1, 3)[:, 1:]]
        skin = (kind[ids] == 1).all(axis=1)
        x = np.asarray(grid.points)[ids[skin]]
        return (np.linalg.norm(x[:, 0] - x[:, 1], axis=1),
                np.linalg.norm(x.mean(axis=1) - centre, axis=1))

    h_base = np.median(skin_edges(uniform)[0])
    length, dist = skin_edges(graded)
    inner = dist < radius - face
    outer = dist > radius + (h_base - face) / GRADING + h_base
    assert inner.sum() > 500 and outer.sum() > 500
    assert np.median(length[inner]) < 0.6 * h_base, (np.median(length[inner]), h_base)
    assert np.median(length[inner]) < 1.1 * face
    # elsewhere at least as fine as the conforming mesh of the count
    ul, ud = skin_edges(uniform)
    assert np.median(length[outer]) <= 1.05 * np.median(ul[ud > radius + (h_base - face)
                                                            / GRADING + h_base])
    # as much of the exact volume as the conforming mesh (the thin tissue kept), and the
    # skin over the vault reached as often
    warp = _warp(case)
    x = np.asarray(graded.points)
    lo, hi = x.min(axis=0) - 5.0, x.max(axis=0) + 5.0
    lo[1] = face_box(case.truth, 0.5)[2]
    p = np.random.default_rng(0).uniform(lo, hi, (200_000, 3))
    exact = np.mean(_region(_fields(warp, p))[0] < 0) * np.prod(hi - lo)
    assert abs(graded.volume / exact - 1) < 0.05, (graded.volume, exact)
    assert abs(graded.volume / exact - 1) <= abs(uniform.volume / exact - 1) + 0.005
    skin = exact_skin_samples(case)
    vault = skin[skin[:, 2] > skin[:, 2].max() - 40.0]
    reach = 0.25 * h_base

    def reached(grid):
        grid = grid.copy()
        grid[arrays.DISPLACEMENT] = np.zeros((grid.n_points, 3))
        return np.mean(skin_displacement(grid, vault)[1] < reach)

    assert reached(graded) >= 0.95 * reached(uniform) > 0.5


def _moved_and_soft(case):
    from pvcmf.filters.osteotomy import cut_bones, segment_transforms, voxel_points

    labels = cut_bones(case.truth, case.plan)
    moved = [s for s, m in segment_transforms(labels, case.plan).items()
             if not np.allclose(m, np.eye(4))]
    bone = np.asarray(labels[arrays.BONE])
    soft = np.isin(np.asarray(case.truth[arrays.TISSUE]), arrays.SOFT_LABELS)
    return (voxel_points(labels, np.flatnonzero(np.isin(bone, moved))),
            voxel_points(case.truth, np.flatnonzero(soft)))


def test_face_ball_margin_holds_the_soft_tissue_near_the_moved_bone(case):
    from scipy.spatial import cKDTree

    from pvcmf.truth.graded import face_ball

    centre, radius = face_ball(case)
    grown_centre, grown = face_ball(case, 20.0)
    np.testing.assert_array_equal(grown_centre, centre)
    assert face_ball(case, 0.0)[1] == radius
    bone, soft = _moved_and_soft(case)
    near = soft[cKDTree(bone).query(soft)[0] <= 20.0]
    dist = np.linalg.norm(near - centre, axis=1)
    # the maxilla is compact: much of the tissue it carries lies outside its own ball
    assert np.mean(dist > radius) > 0.2
    assert dist.max() <= grown + 1e-9
    assert radius + 5.0 < grown <= radius + 20.0 + 1e-9  # every such voxel is that close
    for bad in (-1.0, np.nan, np.inf, "30", True):
        with pytest.raises(ValueError, match="margin_mm must be a non-negative"):
            face_ball(case, bad)


def test_face_margin_is_checked_before_anything_is_meshed(case):
    from pvcmf.truth.graded import graded_mesh
    from pvcmf.truth.independent import independent_truth_grid

    with pytest.raises(ValueError, match="face_margin_mm must be a non-negative distance "
                                         "in mm, got -1.0"):
        graded_mesh(case, face_mm=4.0, face_margin_mm=-1.0)
    with pytest.raises(ValueError, match="face_margin_mm applies to mesher 'graded' only "
                                         r"\(0 with mesher 'conforming'\), got 30"):
        independent_truth_grid(case, mesher="conforming", face_margin_mm=30, cache=False)


def test_graded_mesh_margin_refines_the_tissue_around_the_moved_bone(case):
    from pvcmf.truth.graded import face_ball, graded_mesh

    face, n, margin = 4.0, 8000, 20.0
    centre, radius = face_ball(case)
    grown = face_ball(case, margin)[1]

    def shell_edges(grid):
        """Lengths (mm) of the skin's boundary edges between the plain and the grown ball."""
        kind = np.asarray(grid["boundary"])
        surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface")
        e = surf.extract_all_edges()
        ids = np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS])[
            e.lines.reshape(-1, 3)[:, 1:]]
        x = np.asarray(grid.points)[ids[(kind[ids] == 1).all(axis=1)]]
        d = np.linalg.norm(x.mean(axis=1) - centre, axis=1)
        shell = (d > radius + face) & (d < grown - face)
        assert shell.sum() > 100
        return np.linalg.norm(x[shell, 0] - x[shell, 1], axis=1)

    plain = shell_edges(graded_mesh(case, n_tets=n, face_mm=face))
    wide = shell_edges(graded_mesh(case, n_tets=n, face_mm=face, face_margin_mm=margin))
    # sampled at the face size (edges up to its diagonal) where the plain mesh grows coarser
    assert np.percentile(wide, 99) < np.sqrt(2) * face * 1.1
    assert np.percentile(wide, 75) < 0.9 * np.percentile(plain, 75)
    assert len(wide) > 1.15 * len(plain)
