"""Large-deformation physics of the truth (:func:`pvcmf.truth.solve_reference`) against
analytic answers that a small-strain model cannot reproduce.

* a large rigid rotation imposed on one face of a block: the whole block rotates rigidly
  (zero strain, zero stress); small-strain linear elasticity is not rotation invariant and
  strains it;
* a large uniaxial stretch (ends sliding, sides free): the lateral stretch of the
  compressible neo-Hookean energy ``W = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2``
  (the truth's energy, read from :mod:`pvcmf.truth.solver`), the root of
  ``mu (b^2 - 1) + lambda ln(a b^2) = 0`` (zero lateral Cauchy stress, derived below),
  and the axial nominal stress ``P11 = mu (a - 1/a) + lambda ln(J) / a``.

Each test runs with the truth's law and with the control ``law="linear"`` (the same
solver with a small-strain energy), which must fail it: the tests can tell the two apart.
Small P2 blocks (a few hundred tetrahedra), a second or two each.
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy.optimize import brentq
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pvcmf import arrays

pytest.importorskip("ngsolve")
from pvcmf.truth import solve_reference  # noqa: E402

E, NU = 0.003, 0.46  # Table I fat
MU, LAM = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))


def block(n=(4, 4, 4), size=(10.0, 10.0, 10.0), origin=(0.0, 0.0, 0.0)):
    """Tetrahedral block with free nodes and fat materials."""
    spacing = np.asarray(size) / np.asarray(n)
    g = pv.ImageData(dimensions=np.asarray(n) + 1, spacing=spacing, origin=origin)
    g = g.cast_to_unstructured_grid().triangulate()
    g[arrays.BC] = np.full(g.n_points, arrays.BC_FREE, np.int8)
    g[arrays.BC_DISPLACEMENT] = np.zeros((g.n_points, 3))
    g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, E)
    g.cell_data[arrays.NU] = np.full(g.n_cells, NU)
    return g


def rigid_rotation_error(law, degrees=60.0):
    """Largest deviation (mm) from the rigid rotation, and largest |C - I| of the elements
    (from the vertex displacements), of a block whose face x = 0 is rotated by ``degrees``
    about the z axis through the block's centre, every other face free."""
    g = block()
    rot = Rotation.from_euler("z", degrees, degrees=True).as_matrix()
    centre = np.array([5.0, 5.0, 5.0])
    rigid = (g.points - centre) @ rot.T + centre - g.points
    face = np.isclose(g.points[:, 0], 0.0)
    g[arrays.BC] = np.where(face, arrays.BC_JOINT, arrays.BC_FREE).astype(np.int8)
    g[arrays.BC_DISPLACEMENT] = np.where(face[:, None], rigid, 0.0)
    u = solve_reference(g, law=law, steps=4)[arrays.DISPLACEMENT]
    tets = g.cells_dict[pv.CellType.TETRA]
    x0, x1 = g.points[tets], (g.points + u)[tets]
    d0 = (x0[:, 1:] - x0[:, :1]).transpose(0, 2, 1)
    d1 = (x1[:, 1:] - x1[:, :1]).transpose(0, 2, 1)
    f = d1 @ np.linalg.inv(d0)
    strain = np.abs(f.transpose(0, 2, 1) @ f - np.eye(3)).max()
    return float(np.abs(u - rigid).max()), float(strain)


def lateral_stretch(a):
    """Lateral stretch ``b`` of the neo-Hookean energy under uniaxial stretch ``a``.

    ``F = diag(a, b, b)``, ``I1 = a^2 + 2 b^2``, ``J = a b^2``;
    ``dW/db = 2 mu (b - 1/b) + 2 lambda ln(J) / b = 0`` (free sides), i.e.
    ``mu (b^2 - 1) + lambda ln(a b^2) = 0``: one root in (0, 1] for ``a >= 1``.
    """
    return brentq(lambda b: MU * (b * b - 1) + LAM * np.log(a * b * b), 1e-3, 1.0)


def uniaxial_error(law, a=1.5, length=10.0, width=6.0):
    """Largest deviation (mm) of the solved block from the analytic homogeneous
    uniaxial stretch ``diag(a, b, b)``.

    The ends x = 0 and x = length slide (normal displacement 0 and ``(a - 1) length``,
    tangential motion free), the sides are free. The gauge (translation and rotation
    about the axis, free in this problem) is fixed by the node at the centre of the end
    x = 0 (held) and the node at (0, width/2, 0) (given its analytic displacement); every
    other node, in particular the whole far end, follows from the solve."""
    half = width / 2
    g = block(n=(4, 4, 4), size=(length, width, width), origin=(0.0, -half, -half))
    b = lateral_stretch(a)
    exact = g.points * np.array([a - 1, b - 1, b - 1])
    bc = np.full(g.n_points, arrays.BC_FREE, np.int8)
    ends = np.isclose(g.points[:, 0], 0.0) | np.isclose(g.points[:, 0], length)
    bc[ends] = arrays.BC_SLIDING
    g[arrays.BC_NORMAL] = np.tile([1.0, 0.0, 0.0], (g.n_points, 1))
    disp = np.zeros((g.n_points, 3))
    disp[ends, 0] = exact[ends, 0]
    gauge = [int(np.argmin(np.linalg.norm(g.points - p, axis=1)))
             for p in ((0.0, 0.0, 0.0), (0.0, half, 0.0))]
    bc[gauge] = arrays.BC_JOINT
    disp[gauge] = exact[gauge]
    g[arrays.BC] = bc
    g[arrays.BC_DISPLACEMENT] = disp
    u = solve_reference(g, law=law, steps=4)[arrays.DISPLACEMENT]
    return float(np.abs(u - exact).max()), b


def test_lateral_stretch_solves_the_zero_lateral_stress_condition():
    a = 1.5
    b = lateral_stretch(a)
    j = a * b * b
    # Cauchy stress of this energy: sigma = mu/J (B - I) + lambda ln(J)/J I
    sigma_lateral = MU / j * (b * b - 1) + LAM * np.log(j) / j
    assert abs(sigma_lateral) < 1e-12
    # nearly incompressible (nu 0.46): between the small-strain 1 - nu (a - 1) and the
    # incompressible 1 / sqrt(a)
    assert 1 - NU * (a - 1) < b < 1 / np.sqrt(a) + 0.02


def test_large_rigid_rotation_is_stress_free():
    err, strain = rigid_rotation_error("neo-hookean")
    assert err < 1e-6 and strain < 1e-6


def test_small_strain_control_fails_the_rigid_rotation():
    err, strain = rigid_rotation_error("linear")
    assert err > 0.5 and strain > 0.1  # far from 1e-6: the test above can fail


def test_large_uniaxial_stretch_matches_the_analytic_neo_hookean_answer():
    err, b = uniaxial_error("neo-hookean")
    # the sliding ends are a penalty (traction / penalty stiffness: ~1e-4 mm here)
    assert err < 2e-3
    assert 0.8 < b < 0.85  # a 50 % stretch narrows the block by ~17 % (not 23 %: linear)


def test_small_strain_control_fails_the_uniaxial_stretch():
    err, _ = uniaxial_error("linear")
    assert err > 0.05


def test_law_is_checked():
    with pytest.raises(ValueError, match="law must be one of"):
        solve_reference(block(n=(1, 1, 1)), law="hooke")


# --------------------------------------------------------------------------- independent truth
# its mesh and boundary model (CI-fast, no solve): the solve is solve_reference's, tested
# above; a solved 7k-tetrahedra truth takes minutes (benchmarks/study.py --refinement)

@pytest.fixture(scope="module")
def independent_mesh():
    import pvcmf
    from pvcmf.truth.independent import _boundary_conditions, soft_tissue_mesh

    case = pvcmf.datasets.phantom(1, spacing=3.0)
    return case, _boundary_conditions(case, soft_tissue_mesh(case, n_tets=8000))


def test_independent_truth_mesh_follows_the_exact_anatomy(independent_mesh):
    from pvcmf.datasets import template
    from pvcmf.truth.independent import _BOUNDARY, _fields, _region

    case, grid = independent_mesh
    x = np.asarray(grid.points)
    q = x[grid.cells_dict[pv.CellType.TETRA]]
    vol = np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), q[:, 3] - q[:, 0])
    assert vol.min() > 0
    kind = np.asarray(grid["boundary"])
    surface = (kind > 0) & (kind <= len(_BOUNDARY))
    r, _ = _region(_fields(template.patient_warp(1), x[surface]))
    # almost every boundary node lies on the exact surfaces (flattened caps are dropped
    # rather than unsnapped)
    assert np.mean(np.abs(r) < 0.05) > 0.9
    # every facial muscle, and generic muscle tissue (tongue, temporalis, neck)
    assert set(np.unique(grid.cell_data[arrays.MUSCLE])) == set(range(len(arrays.MUSCLES) + 1))
    generic = (grid.cell_data[arrays.TISSUE] == arrays.MUSCLE_TISSUE) & (
        grid.cell_data[arrays.MUSCLE] == 0)
    assert generic.sum() > 50


def test_independent_truth_ties_soft_tissue_to_the_moved_bones(independent_mesh):
    from pvcmf.filters.osteotomy import cut_bones, segment_transforms, voxel_points
    from pvcmf.truth.independent import _BOUNDARY, BLEND_MM

    case, grid = independent_mesh
    kind = np.asarray(grid["boundary"])
    bc, g, x = np.asarray(grid[arrays.BC]), np.asarray(grid[arrays.BC_DISPLACEMENT]), grid.points
    on_bone = kind == 1 + _BOUNDARY.index("bone")
    assert np.all(bc[on_bone] == arrays.BC_JOINT)  # every bone node tied, none detached
    plane = kind == len(_BOUNDARY) + 1  # held, except near a moved bone
    assert np.all(np.isin(bc[plane], (arrays.BC_FIXED, arrays.BC_FREE)))
    assert 0.5 < np.mean(bc[plane] == arrays.BC_FIXED) < 1
    assert np.all(bc[~on_bone & ~plane] == arrays.BC_FREE)  # no contact
    labels = cut_bones(case.truth, case.plan)
    moves = segment_transforms(labels, case.plan)
    assert len(moves) == 1  # patient 1: the maxilla alone
    (segment, m), = moves.items()
    p = x[on_bone]
    u = p @ m[:3, :3].T + m[:3, 3] - p  # the moved segment's rigid move
    # the data is a share w of that move, w in [0, 1]
    w = np.einsum("ij,ij->i", g[on_bone], u) / np.einsum("ij,ij->i", u, u)
    np.testing.assert_allclose(g[on_bone], w[:, None] * u, atol=1e-9)
    assert w.min() > -1e-9 and w.max() < 1 + 1e-9
    bone = np.asarray(labels[arrays.BONE])
    moving = cKDTree(voxel_points(labels, np.flatnonzero(bone == segment))).query(p)[0]
    others = np.flatnonzero((bone > 0) & (bone != segment))
    still = cKDTree(voxel_points(labels, others)).query(p)[0]
    # away from the midway between the segments' voxels the share tends to that of the
    # nearer segment (a Gaussian blend: over 90 % 1.5 BLEND_MM from the midway on the
    # moved side, under 2 % 2.5 BLEND_MM from it on the unmoved side)
    inner, outer = still - moving > 3 * BLEND_MM, moving - still > 5 * BLEND_MM
    assert np.all(w[inner] > 0.9) and np.all(w[outer] < 0.02)
    assert inner.sum() > 20 and outer.sum() > 20
    # blended across the cut: intermediate shares, no jump between neighbouring tied nodes
    assert np.count_nonzero((w > 0.1) & (w < 0.9)) > 10
    tets = grid.cells_dict[pv.CellType.TETRA]
    edges = np.unique(np.sort(tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]]
                              .reshape(-1, 2), axis=1), axis=0)
    share = np.full(len(x), np.nan)
    share[on_bone] = w
    e = edges[on_bone[edges].all(axis=1)]
    slope = np.abs(share[e[:, 0]] - share[e[:, 1]]) / np.linalg.norm(x[e[:, 0]] - x[e[:, 1]],
                                                                      axis=1)
    # a unit step smoothed by a Gaussian of sigma has slope <= 1 / (sigma sqrt(2 pi))
    assert slope.max() < 1.5 / (BLEND_MM * np.sqrt(2 * np.pi))


def test_independent_truth_holds_the_plane_away_from_moved_bone(independent_mesh):
    """No held plane node within CLEARANCE_MM of a moved bone (distances to the cut labels'
    voxels, computed here by brute force); the tongue is not meshed."""
    from pvcmf.filters.osteotomy import cut_bones, segment_transforms, voxel_points
    from pvcmf.truth.anatomy import true_level_set
    from pvcmf.truth.independent import CLEARANCE_MM

    case, grid = independent_mesh
    labels = cut_bones(case.truth, case.plan)
    moved = set(segment_transforms(labels, case.plan))
    bone = np.asarray(labels[arrays.BONE])
    bc, x = np.asarray(grid[arrays.BC]), np.asarray(grid.points)
    moving = voxel_points(labels, np.flatnonzero(np.isin(bone, list(moved))))

    def dist(p, q):  # brute force, in chunks of 64 points
        return np.concatenate([np.sqrt(((c[:, None, :] - q[None, :, :]) ** 2).sum(-1)).min(1)
                               for c in np.array_split(p, max(1, len(p) // 64))])

    assert dist(x[bc == arrays.BC_FIXED], moving).min() >= CLEARANCE_MM
    centres = np.asarray(grid.cell_centers().points)
    assert np.all(true_level_set(case, "tongue", centres) > -1.0)


def test_independent_truth_mixes_materials_by_muscle_fraction(independent_mesh):
    """A muscle sheet thinner than the elements keeps its share of the stiffness: cells
    straddle muscle and fat with fractions strictly between 0 and 1, and the modulus is
    the rule of mixtures of Table I."""
    from pvcmf import filters

    _, grid = independent_mesh
    f = np.asarray(grid.cell_data[arrays.MUSCLE_FRACTION])
    assert f.min() >= 0 and f.max() <= 1 and np.mean((f > 0) & (f < 1)) > 0.1
    e = filters.assign_materials(grid, default_fiber=(0.0, 0.0, 1.0))[arrays.E_CROSS]
    np.testing.assert_allclose(e, (1 - f) * 0.003 + f * 0.79)


def test_independent_truth_mesh_is_one_face_connected_solid(independent_mesh):
    """No piece hangs on the body by an edge or a vertex (it would hinge freely)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    _, grid = independent_mesh
    tets = grid.cells_dict[pv.CellType.TETRA]
    faces = {}
    for i, t in enumerate(tets):  # brute force over a few thousand cells, test only
        for f in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)):
            faces.setdefault(tuple(sorted(t[list(f)])), []).append(i)
    pairs = np.array([v for v in faces.values() if len(v) == 2])
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(tets), len(tets)))
    _, part = connected_components(graph, directed=False)
    assert np.bincount(part).min() >= 0.02 * len(tets)


def test_truth_problem_is_the_unsolved_truth(independent_mesh):
    """What independent_truth_grid solves, from the same mesher and boundary model: the
    planned grid with materials and no solution; a material field only with 'field'."""
    from pvcmf.truth.independent import truth_problem

    case, planned = independent_mesh
    grid, field, params = truth_problem(case, n_tets=8000)
    assert field is None and params.startswith("independent|order=2|steps=4")
    assert arrays.DISPLACEMENT not in grid.point_data
    np.testing.assert_array_equal(grid.points, planned.points)
    np.testing.assert_array_equal(grid[arrays.BC], planned[arrays.BC])
    np.testing.assert_allclose(grid[arrays.BC_DISPLACEMENT], planned[arrays.BC_DISPLACEMENT])
    assert np.all(grid.cell_data[arrays.E_CROSS] > 0)
    with pytest.raises(ValueError, match="materials must be 'cells' or 'field', got 'voxels'"):
        truth_problem(case, materials="voxels")
