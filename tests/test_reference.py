"""The virtual post-operative truth model (NGSolve neo-Hookean, P2): exactness, convergence,
sliding contact, bad input. Skipped without the optional extra ``pvcmf[reference]``."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays

pytest.importorskip("ngsolve")
from pvcmf.reference import solve_reference  # noqa: E402


def cube(n, size=10.0):
    """Tetrahedral cube [0, size]^3 with n cells per side, Table I fat."""
    g = pv.ImageData(dimensions=(n + 1,) * 3, spacing=(size / n,) * 3)
    g = g.cast_to_unstructured_grid().triangulate()
    g[arrays.BC] = np.zeros(g.n_points, np.int8)
    g[arrays.BC_DISPLACEMENT] = np.zeros((g.n_points, 3))
    g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, 0.003)
    g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    return g


def test_homogeneous_large_deformation_is_exact():
    """Any homogeneous hyperelastic body under affine boundary data deforms affinely."""
    g = cube(4)
    a = np.array([[0.3, 0.1, 0.0], [0.0, -0.2, 0.05], [0.03, 0.0, 0.25]])  # 30 % strains
    g[arrays.BC] = np.where(np.isin(g.points, [0.0, 10.0]).any(axis=1), arrays.BC_JOINT,
                            arrays.BC_FREE).astype(np.int8)
    g[arrays.BC_DISPLACEMENT] = g.points @ a.T
    # fibre-reinforced (E_fiber > E_cross) and still homogeneous
    g.cell_data[arrays.E_FIBER] = np.full(g.n_cells, 0.01)
    g.cell_data[arrays.FIBER] = np.tile([1.0, 0.0, 0.0], (g.n_cells, 1))
    before = g[arrays.BC_DISPLACEMENT].copy()
    out = solve_reference(g)
    np.testing.assert_allclose(out[arrays.DISPLACEMENT], g.points @ a.T, atol=1e-9)
    np.testing.assert_array_equal(g[arrays.BC_DISPLACEMENT], before)
    assert arrays.DISPLACEMENT not in g.point_data


def smooth_field(p, scale=1.0):
    """A smooth, non-affine displacement field (mm) on the cube [0, 10]^3."""
    x, y, z = (p / 10.0).T
    return scale * np.column_stack([
        1.5 * np.sin(np.pi * z) * x, 0.8 * np.sin(np.pi * x) * (1 + y), -1.0 * y**2 + 0.5 * x * z,
    ])


def two_materials(g):
    """Stiffer lower half (muscle-like), softer upper half: a non-trivial solution."""
    low = g.cell_centers().points[:, 2] < 5.0
    g.cell_data[arrays.E_CROSS] = np.where(low, 0.03, 0.003)
    g.cell_data[arrays.NU] = np.where(low, 0.43, 0.46)
    return g


def smooth_problem(n, scale=1.0, order=2, materials=two_materials, free=(1,)):
    """Cube with n cells a side, the smooth field prescribed on its faces except the
    pairs normal to the axes in ``free`` (traction free). Returns (grid, displacement)."""
    g = materials(cube(n))
    p = g.points
    on_face = np.isin(p, [0.0, 10.0])
    prescribed = on_face[:, [k for k in range(3) if k not in free]].any(axis=1)
    g[arrays.BC] = np.where(prescribed, arrays.BC_JOINT, arrays.BC_FREE).astype(np.int8)
    g[arrays.BC_DISPLACEMENT] = np.where(prescribed[:, None], smooth_field(p, scale), 0.0)
    return g, solve_reference(g, order=order)[arrays.DISPLACEMENT]


def at(g, u, point):
    i = np.flatnonzero(np.all(np.isclose(g.points, point), axis=1))
    assert len(i) == 1
    return u[i[0]]


def test_converges_under_refinement():
    """Large deformation (strains up to ~30 %) of a homogeneous cube with smooth data on
    its whole boundary: the displacement of the centre on meshes of 2, 4, 6 cells a side
    approaches the one on 8 with an observed order above 2 between 4 and 6 (P2 at a
    vertex: about 3 expected; linear elements give about 1 here), and the error on 6
    is below 1 % of the displacement."""
    centre = [5.0, 5.0, 5.0]
    u = {n: at(*smooth_problem(n, materials=lambda g: g, free=()), centre) for n in (2, 4, 6, 8)}
    assert np.linalg.norm(u[8]) > 1.0  # a real deformation
    err = {n: np.linalg.norm(u[n] - u[8]) for n in (2, 4, 6)}
    assert err[2] > err[4] > err[6]
    order = np.log(err[4] / err[6]) / np.log(6 / 4)
    assert order > 2.0, (err, order)
    assert err[6] < 0.01 * np.linalg.norm(u[8])


def test_small_strain_agrees_with_linear_elasticity_by_scikit_fem():
    """A tiny displacement (1e-4 of the smooth field): the neo-Hookean P2 solution equals
    the linear-elastic P2 solution of the same mesh, data and materials computed by
    scikit-fem (an independent implementation), to the size of the neglected quadratic
    terms."""
    skfem = pytest.importorskip("skfem")
    from skfem.helpers import ddot, sym_grad, trace

    scale = 1e-4
    g, u = smooth_problem(4, scale=scale)  # two materials, front and back free
    cells = np.asarray(g.cells_dict[pv.CellType.TETRA])
    mesh = skfem.MeshTet(np.array(g.points).T.copy(), cells.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVectorH1(skfem.ElementTetP2()), intorder=4)
    e, nu = g.cell_data[arrays.E_CROSS], g.cell_data[arrays.NU]
    nqp = basis.X.shape[1]
    lam_q = np.repeat((e * nu / ((1 + nu) * (1 - 2 * nu)))[:, None], nqp, axis=1)
    mu_q = np.repeat((e / (2 * (1 + nu)))[:, None], nqp, axis=1)

    @skfem.BilinearForm
    def elasticity(v, w, p):
        ev, ew = sym_grad(v), sym_grad(w)
        return 2 * p["mu"] * ddot(ev, ew) + p["lam"] * trace(ev) * trace(ew)

    K = skfem.asm(elasticity, basis, mu=mu_q, lam=lam_q)
    # Dirichlet data: vertex values, and the mean of the two ends at edge midpoints
    # (the P1 interpolant of the vertex data, as the reference model prescribes it)
    bc = g[arrays.BC] == arrays.BC_JOINT
    data = np.asarray(g[arrays.BC_DISPLACEMENT])
    x = basis.zeros()
    x[basis.nodal_dofs.T[bc].ravel()] = data[bc].ravel()
    edges = mesh.edges.T
    on = bc[edges].all(axis=1)
    # an edge between two prescribed vertices lies on a prescribed face only if a
    # boundary face holds it; boundary facets tell which
    facets = mesh.facets.T[mesh.boundary_facets()]
    pres_facets = facets[bc[facets].all(axis=1)]
    fe = {tuple(sorted(e)) for f in pres_facets for e in ((f[0], f[1]), (f[1], f[2]), (f[0], f[2]))}
    on &= np.array([tuple(sorted(e)) in fe for e in edges])
    x[basis.edge_dofs.T[on].ravel()] = 0.5 * (data[edges[on, 0]] + data[edges[on, 1]]).ravel()
    fixed = np.concatenate([basis.nodal_dofs.T[bc].ravel(), basis.edge_dofs.T[on].ravel()])
    lin = skfem.solve(*skfem.condense(K, x=x, D=fixed))
    u_lin = lin[basis.nodal_dofs].T
    assert np.abs(u_lin).max() > 0.5 * scale
    np.testing.assert_allclose(u, u_lin, atol=2e-3 * np.abs(u_lin).max())
    # and not by accident: an incompressible-ish change of material is seen
    g2 = g.copy()
    g2.cell_data[arrays.NU] = np.full(g.n_cells, 0.3)
    u2 = solve_reference(g2)[arrays.DISPLACEMENT]
    assert np.abs(u2 - u_lin).max() > 0.05 * np.abs(u_lin).max()


def test_sliding_contact_holds_the_normal_and_frees_the_tangent():
    g = cube(4)
    z = g.points[:, 2]
    bc = np.full(g.n_points, arrays.BC_FREE, np.int8)
    bc[z == 0] = arrays.BC_SLIDING
    bc[z == 10] = arrays.BC_FIXED
    g[arrays.BC] = bc
    g[arrays.BC_DISPLACEMENT] = np.where((z == 10)[:, None], [0.0, 0.0, -2.0], 0.0)
    g[arrays.BC_NORMAL] = np.tile([0.0, 0.0, 1.0], (g.n_points, 1))
    u = solve_reference(g)[arrays.DISPLACEMENT]
    bottom = z == 0
    assert np.abs(u[bottom, 2]).max() < 1e-3  # stays on the plane
    corner = bottom & (g.points[:, 0] == 10) & (g.points[:, 1] == 10)
    assert u[corner, 0] > 0.1 and u[corner, 1] > 0.1  # slides outward (bulges)


def test_bad_input():
    g = cube(2)
    with pytest.raises(TypeError, match="UnstructuredGrid"):
        solve_reference(pv.Sphere())
    bad = g.copy()
    del bad.cell_data[arrays.NU]
    with pytest.raises(ValueError, match="no cell array 'nu'.*assign_materials"):
        solve_reference(bad)
    bad = g.copy()
    bad.cell_data[arrays.NU] = np.full(g.n_cells, 0.5)
    with pytest.raises(ValueError, match="nu in"):
        solve_reference(bad)
    hexes = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    with pytest.raises(ValueError, match="tetrahedra"):
        solve_reference(hexes)
    with pytest.raises(ValueError, match="predictor must be 'tangent' or 'proportional'"):
        solve_reference(g, predictor="magic")


@pytest.mark.parametrize("reuse", [False, True])
def test_mkl_pardiso_reaches_the_ngsolve_cholesky_solution(reuse):
    """MKL PARDISO on the free block gathered from NGSolve's matrix (``inverse='mkl'``)
    gives NGSolve's sparse Cholesky solution: two materials, joint faces, a sliding face,
    strains of about 30 %; factorised every Newton iteration, or reused as the
    preconditioner of conjugate gradients."""
    pytest.importorskip("pypardiso")
    g, _ = smooth_problem(4)
    bc = np.asarray(g[arrays.BC]).copy()
    bc[g.points[:, 2] == 0] = arrays.BC_SLIDING
    g[arrays.BC] = bc
    g[arrays.BC_NORMAL] = np.tile([0.0, 0.0, 1.0], (g.n_points, 1))
    direct = solve_reference(g, inverse="sparsecholesky", reuse_factor=reuse)
    mkl = solve_reference(g, inverse="mkl", reuse_factor=reuse)
    u = direct[arrays.DISPLACEMENT]
    assert np.abs(u).max() > 1.0
    np.testing.assert_allclose(mkl[arrays.DISPLACEMENT], u, atol=1e-9 * np.abs(u).max())
    np.testing.assert_allclose(mkl.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT],
                               direct.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT],
                               atol=1e-9 * np.abs(u).max())


def test_predictors_agree():
    """The tangent load-step predictor (default) and the proportional one reach
    the same equilibrium (they only start Newton differently)."""
    g, u = smooth_problem(2)
    u_old = solve_reference(g, predictor="proportional")[arrays.DISPLACEMENT]
    np.testing.assert_allclose(u, u_old, atol=1e-6 * np.abs(u).max())


def one_tet(order_of_nodes=(0, 1, 2, 3)):
    """One tetrahedron: nodes 0-2 joint, moved 2 mm up through node 3 (fixed at z = 1):
    the prescribed data alone inverts it."""
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    g = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([order_of_nodes])}, pts)
    g[arrays.BC] = np.array([arrays.BC_JOINT] * 3 + [arrays.BC_FIXED], np.int8)
    g[arrays.BC_DISPLACEMENT] = np.array([[0.0, 0, 2]] * 3 + [[0.0, 0, 0]])
    g.cell_data[arrays.E_CROSS] = np.full(1, 0.003)
    g.cell_data[arrays.NU] = np.full(1, 0.46)
    return g


def test_released_nodes_pick_the_odd_node_of_crushed_elements():
    from pvcmf.reference import _released_nodes

    g = one_tet((0, 2, 1, 3))  # orientation does not matter
    tets = g.cells_dict[pv.CellType.TETRA]
    pres = np.ones(4, bool)
    data = np.asarray(g[arrays.BC_DISPLACEMENT])
    np.testing.assert_array_equal(_released_nodes(g.points, tets, pres, data, 0.2),
                                  [False, False, False, True])
    # a crush to 10 % of the volume (ratio 0.1) is released at 0.2, kept at 0.05
    squash = np.zeros((4, 3))
    squash[3] = [0.0, 0.0, -0.9]
    assert _released_nodes(g.points, tets, pres, squash, 0.2).sum() == 1
    assert not _released_nodes(g.points, tets, pres, squash, 0.05).any()
    # an element with a free node is never crushed by the data alone
    pres[0] = False
    assert not _released_nodes(g.points, tets, pres, data, 0.2).any()


@pytest.mark.parametrize("order", [1, 2])
def test_data_that_inverts_an_element_releases_its_odd_node(order):
    """Without the release no solution exists (the data inverts the element at 50 % of
    the load); with it, the released fixed node follows: a rigid translation, zero energy."""
    g = one_tet()
    out = solve_reference(g, order=order)
    np.testing.assert_array_equal(out.field_data["reference_released"], [3])
    np.testing.assert_allclose(out[arrays.DISPLACEMENT], np.tile([0.0, 0, 2], (4, 1)),
                               atol=1e-9)
    with pytest.raises(RuntimeError, match="did not converge at load 0.5"):
        solve_reference(g, order=order, release_below=None, steps=1)
    with pytest.raises(ValueError, match="release_below must be a volume ratio in \\[0, 1\\)"):
        solve_reference(g, release_below=1.5)


def test_every_fixed_and_joint_node_is_prescribed():
    """A fixed node alone on the boundary (no face of three constrained nodes) is held at
    0 and a joint one at its data, as in the MTM (the Dirichlet faces alone left them free)."""
    g = cube(3)
    z = g.points[:, 2]
    bc = np.where(z == 10, arrays.BC_JOINT, arrays.BC_FREE).astype(np.int8)
    lone_fixed = np.flatnonzero(np.all(np.isclose(g.points, [10.0 / 3, 10.0 / 3, 0]), axis=1))
    lone_joint = np.flatnonzero(np.all(np.isclose(g.points, [0.0, 10.0 / 3, 10.0 / 3]), axis=1))
    bc[lone_fixed] = arrays.BC_FIXED
    bc[lone_joint] = arrays.BC_JOINT
    g[arrays.BC] = bc
    data = np.zeros((g.n_points, 3))
    data[z == 10] = [0.0, 0.0, -1.5]
    data[lone_joint] = [0.5, 0.0, 0.0]
    g[arrays.BC_DISPLACEMENT] = data
    out = solve_reference(g)
    u = np.asarray(out[arrays.DISPLACEMENT])
    assert len(out.field_data["reference_released"]) == 0
    np.testing.assert_array_equal(u[lone_fixed], 0.0)
    np.testing.assert_allclose(u[lone_joint], [[0.5, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(u[z == 10], data[z == 10], atol=1e-12)
    assert np.abs(u[z == 0]).max() > 0.1  # the rest of the bottom face moves


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:muscle")  # thin muscles dropped at 3000 tetrahedra
def test_coarse_patient_truth_converges_with_the_crushed_element_released():
    """Virtual patient 1 at 4 mm, 3000 P1 tetrahedra: one element's four nodes are all
    prescribed (a fixed node ~10 mm from three joint nodes the plan moves 9-11 mm) and the
    data alone inverts it at 93.5 % of the load, where Newton failed before. Its fixed node
    is released; the solve converges with every other fixed node at 0, every joint node at
    its data and no inverted element."""
    import pvcmf
    from pvcmf import reference

    c = pvcmf.datasets.phantom(1, spacing=4.0)
    _, grid = reference._truth_grid(c, 3000, 0.5, False)
    with pytest.raises(RuntimeError, match=r"did not converge at load 0\.[0-9]+"):
        solve_reference(grid, order=1, steps=1, release_below=None, threads=False)
    out = solve_reference(grid, order=1, steps=1, threads=False)
    released = np.asarray(out.field_data["reference_released"])
    assert 1 <= len(released) <= 3
    bc = np.asarray(out[arrays.BC])
    u = np.asarray(out[arrays.DISPLACEMENT])
    data = np.asarray(out[arrays.BC_DISPLACEMENT])
    held = np.ones(len(bc), bool)
    held[released] = False
    fixed, joint = held & (bc == arrays.BC_FIXED), held & (bc == arrays.BC_JOINT)
    assert fixed.sum() > 100 and joint.sum() > 10
    np.testing.assert_array_equal(u[fixed], 0.0)
    np.testing.assert_allclose(u[joint], data[joint], atol=1e-9)
    # the released node moved away from its data (it was what inverted the element)
    assert np.linalg.norm(u[released] - data[released], axis=1).max() > 1.0
    tets = out.cells_dict[pv.CellType.TETRA]

    def volumes(x):
        q = x[tets]
        return np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]),
                         q[:, 3] - q[:, 0])

    assert np.all(volumes(out.points + u) / volumes(out.points) > 0)
    assert len(out.field_data["reference_folded"]) == 0
