"""MTM solvers: patch test, analytic bars, scikit-fem, rigid motion, sliding, extremes, errors."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import pyvista as pv
from mtm_helpers import (boundary_nodes, delaunay_box, jittered_box, set_bc, set_materials,
                         skfem_stiffness)

import pvcmf
from pvcmf import arrays
from pvcmf.mtm import (ConvergenceError, IllConditionedWarning, RigidModeError, Solver,
                       direct_backends, gpu_available, solve, stiffness)

BACKENDS = direct_backends()


def _patch_grid(nu=0.46, ef=1.0, ec=1.0, fiber=None, seed=1):
    grid = delaunay_box(seed=seed)
    set_materials(grid, ef, ec, nu, fiber)
    rng = np.random.default_rng(seed)
    A = rng.normal(scale=0.01, size=(3, 3))
    c = rng.normal(scale=0.1, size=3)
    exact = grid.points @ A.T + c
    bnd = boundary_nodes(grid)
    set_bc(grid, np.where(bnd, arrays.BC_JOINT, arrays.BC_FREE), exact)
    assert (~bnd).sum() > 100
    return grid, exact


@pytest.mark.parametrize("method,backend", [("direct", b) for b in BACKENDS] + [("cg", None)])
def test_patch_test_linear_field_reproduced_inside(method, backend):
    grid, exact = _patch_grid(ef=0.5, ec=0.79, nu=0.43, fiber=[1.0, 2.0, 0.5])
    kw = {"backend": backend} if backend else {}
    out = solve(grid, method=method, tol=1e-12, **kw)
    u = out[arrays.DISPLACEMENT]
    assert np.abs(u - exact).max() <= 1e-9 * np.abs(exact).max()
    assert out.field_data[pvcmf.mtm.FIELD_RESIDUAL][0] <= 1e-10
    assert str(out.field_data[pvcmf.mtm.FIELD_METHOD][0]) == method


def _bar(fiber=None, ef=1.0, ec=1.0, nu=0.3, strain=0.01):
    L, W, H = 6.0, 4.0, 4.0
    grid = jittered_box(shape=(7, 5, 5), size=(L, W, H), seed=4)
    set_materials(grid, ef, ec, nu, fiber)
    p = grid.points
    n = grid.n_points
    bc = np.zeros(n, np.int8)
    normal = np.zeros((n, 3))
    disp = np.zeros((n, 3))
    x0, x1 = np.isclose(p[:, 0], 0), np.isclose(p[:, 0], L)
    bc[x0 | x1] = arrays.BC_SLIDING
    normal[x0 | x1] = (1.0, 0, 0)
    disp[x1, 0] = strain * L
    # 3-2-1 support on x = 0: origin fixed, (0, W, 0) held at the exact answer
    origin = np.flatnonzero(np.all(np.isclose(p, 0), axis=1))[0]
    corner = np.flatnonzero(np.all(np.isclose(p, [0, W, 0]), axis=1))[0]
    bc[origin] = arrays.BC_FIXED
    return grid, bc, disp, normal, corner, x1, (L, W, H)


@pytest.mark.parametrize("case", ["isotropic", "fibre_along", "fibre_across_y", "fibre_across_z"])
def test_uniaxial_bar_matches_analytic(case):
    ef, ec, nu, strain = 0.5, 0.79, 0.43, 0.01
    fiber = {"isotropic": None, "fibre_along": [1, 0, 0], "fibre_across_y": [0, 1, 0],
             "fibre_across_z": [0, 0, 1]}[case]
    if case == "isotropic":
        ef = ec = 0.79
    grid, bc, disp, normal, corner, x1, (L, W, H) = _bar(fiber, ef, ec, nu, strain)
    # lateral contraction: nu * Ef / Ec along the fibre, nu across it
    nu_lat = nu * ef / ec if case == "fibre_along" else nu
    e_axial = ef if case == "fibre_along" else ec
    bc[corner] = arrays.BC_JOINT
    disp[corner] = (0.0, -nu_lat * strain * W, 0.0)
    set_bc(grid, bc, disp, normal)
    u = solve(grid)[arrays.DISPLACEMENT]
    p = grid.points
    exact = np.column_stack([strain * p[:, 0], -nu_lat * strain * p[:, 1], -nu_lat * strain * p[:, 2]])
    assert np.abs(u - exact).max() <= 1e-10 * strain * L
    # reaction on the loaded face = E_axial * strain * area
    f = (stiffness(grid) @ u.ravel()).reshape(-1, 3)
    np.testing.assert_allclose(f[x1, 0].sum(), e_axial * strain * W * H, rtol=1e-10)


@pytest.fixture(scope="module")
def mixed():
    """Irregular mesh, mixed fat / transversely isotropic muscle, fixed + joint boundary."""
    grid = jittered_box(shape=(8, 6, 5), size=(7.0, 5.0, 4.0), seed=7)
    rng = np.random.default_rng(7)
    m = grid.n_cells
    musc = grid.cell_centers().points[:, 2] > 2.0
    fib = rng.normal(size=(m, 3))
    grid.cell_data[arrays.TISSUE] = np.where(musc, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    grid.cell_data[arrays.FIBER] = fib
    grid = grid.cmf.assign_materials(table="paper000")
    p = grid.points
    bc = np.zeros(grid.n_points, np.int8)
    bc[np.isclose(p[:, 0], 0)] = arrays.BC_FIXED
    moved = np.isclose(p[:, 0], 7.0)
    bc[moved] = arrays.BC_JOINT
    disp = np.zeros((grid.n_points, 3))
    disp[moved] = np.column_stack([0.2 + 0.05 * p[moved, 1], 0.3 * np.ones(moved.sum()), -0.1 * p[moved, 2]])
    return set_bc(grid, bc, disp)


def test_agrees_with_scikit_fem(mixed):
    from skfem import condense
    from skfem import solve as sksolve

    K, dofs = skfem_stiffness(mixed)
    bc = mixed[arrays.BC]
    D = dofs[:, bc != arrays.BC_FREE].ravel()
    x = np.zeros(K.shape[0])
    x[dofs.T.ravel()] = mixed[arrays.BC_DISPLACEMENT].ravel()
    ref = sksolve(*condense(K, np.zeros(K.shape[0]), x=x, D=D))[dofs.T.ravel()].reshape(-1, 3)
    for backend in BACKENDS:
        u = solve(mixed, backend=backend)[arrays.DISPLACEMENT]
        assert np.abs(u - ref).max() <= 1e-8 * np.abs(ref).max(), backend


def test_methods_agree_to_their_tolerance(mixed):
    grid = mixed.cmf.assign_materials(table="paper001_homogeneous", fat={"nu": 0.3}, muscle={"nu": 0.3})
    ref = solve(grid)[arrays.DISPLACEMENT]
    scale = np.abs(ref).max()
    cg = solve(grid, method="cg", tol=1e-10)
    assert np.abs(cg[arrays.DISPLACEMENT] - ref).max() <= 1e-6 * scale
    jac = Solver(grid, method="cg", preconditioner="jacobi", tol=1e-10)
    assert np.abs(jac.solve() - ref).max() <= 1e-6 * scale
    rel = solve(grid, method="relaxation", tol=1e-9)
    assert rel.field_data[pvcmf.mtm.FIELD_ITERATIONS][0] > 10
    assert np.abs(rel[arrays.DISPLACEMENT] - ref).max() <= 1e-5 * scale


def test_amg_preconditioner_is_symmetric_positive_definite():
    """CG needs an SPD preconditioner: forward Gauss-Seidel before the coarse correction and
    backward after make the V-cycle symmetric (a change of smoother could silently break it)."""
    pytest.importorskip("pyamg")
    grid = jittered_box(shape=(13, 9, 9), size=(12.0, 8.0, 8.0), jitter=0.2, seed=4)
    set_materials(grid, 1.0, 1.0, 0.45)
    x = grid.points[:, 0]
    bc = np.where(x < 1e-9, arrays.BC_FIXED, np.where(x > 12 - 1e-9, arrays.BC_JOINT, arrays.BC_FREE))
    set_bc(grid, bc, np.where((bc == arrays.BC_JOINT)[:, None], [0.1, 0.0, 0.0], 0.0))
    s = Solver(grid, method="cg", tol=1e-10)
    assert s._method.name == "amg" and len(s._method.ml.levels) >= 2  # a real multilevel cycle
    rng = np.random.default_rng(0)
    n = s.K_ff.shape[0]
    X = rng.normal(size=(n, 3))
    MX = np.stack([s._method.M.matvec(X[:, k]) for k in range(3)], axis=1)
    G = X.T @ MX
    assert np.abs(G - G.T).max() <= 1e-10 * np.abs(G).max()
    assert np.all(np.linalg.eigvalsh(0.5 * (G + G.T)) > 0)


def test_cg_warm_start_and_solver_reuse(mixed):
    s = Solver(mixed, method="cg", tol=1e-10)
    u = s.solve()
    cold = s.info["iterations"]
    s.solve(x0=u)
    assert s.info["iterations"] < cold / 2
    # reusable direct solver: new materials (numeric refactorisation), new bone move (no refactor)
    d = Solver(mixed)
    d.update_materials(nu=0.3)
    fresh = solve(mixed, nu=0.3)[arrays.DISPLACEMENT]
    u1 = d.solve()
    np.testing.assert_allclose(u1, fresh, rtol=0, atol=1e-12 * np.abs(fresh).max())
    g2 = mixed.copy()
    g2.point_data[arrays.BC_DISPLACEMENT] = 2 * mixed[arrays.BC_DISPLACEMENT]
    np.testing.assert_allclose(d.solve(2 * mixed[arrays.BC_DISPLACEMENT]),
                               solve(g2, nu=0.3)[arrays.DISPLACEMENT], atol=1e-12 * np.abs(fresh).max())


def test_poisson_sweep_reusing_the_factorisation(mixed):
    s = Solver(mixed, nu=0.40)
    for nu, reused in ((0.41, True), (0.42, True), (0.4999, False)):
        s.update_materials(nu=nu, refactor=False)
        u = s.solve()
        ref = solve(mixed, nu=nu)[arrays.DISPLACEMENT]
        assert s.info["residual"] <= 1e-10
        assert np.abs(u - ref).max() <= 1e-8 * np.abs(ref).max()
        # a small step reuses the old factor; the jump to 0.4999 needs a refactorisation
        assert bool(s.info.get("reused_factor")) == reused, nu
        if reused:
            assert 0 < s.info["iterations"] <= s._method.max_reuse_iterations


def _sliding_mixed(mixed):
    """The mixed fixture with sliding nodes on z = 0 (rotated frames in the eliminated system)."""
    bc = np.array(mixed[arrays.BC])
    p = mixed.points
    z0 = np.isclose(p[:, 2], 0) & (bc == arrays.BC_FREE)
    bc[z0] = arrays.BC_SLIDING
    normal = np.zeros((mixed.n_points, 3))
    normal[z0] = (0.1, 0.2, -1.0)
    disp = np.array(mixed[arrays.BC_DISPLACEMENT])
    disp[z0] = 0.05 * np.array([0.1, 0.2, -1.0])
    return set_bc(mixed.copy(), bc, disp, normal)


@pytest.mark.parametrize("backend", BACKENDS)
def test_material_group_updates_equal_a_fresh_solver(mixed, backend):
    """A sweep's cached per-material matrices give the system a fresh assembly gives."""
    grid = _sliding_mixed(mixed)
    musc = np.asarray(grid[arrays.TISSUE]) == arrays.MUSCLE_TISSUE
    ef0, ec0 = np.array(grid[arrays.E_FIBER]), np.array(grid[arrays.E_CROSS])
    s = Solver(grid, backend=backend)
    # the node-graph ordering (CHOLMOD's AMD/METIS) numbers the unknowns of both triangle backends
    if "cholmod" in BACKENDS and backend in ("cholmod", "pardiso"):
        expected = "amd"  # a small mesh: AMD
    else:  # without scikit-sparse PARDISO orders the node graph itself
        expected = "pardiso-metis" if backend == "pardiso" else None
    assert s.node_ordering == expected
    rng = np.random.default_rng(5)
    steps = [  # (materials, whether the grouped path applies)
        (dict(nu=0.3), True),  # Poisson sweep, two materials
        (dict(nu=np.where(musc, 0.43, 0.485)), True),  # paper 001 inhomogeneous
        (dict(E_fiber=3 * ef0, E_cross=3 * ec0), True),  # stiffer everywhere, same grouping
        (dict(nu=rng.uniform(0.1, 0.45, grid.n_cells)), False),  # per-cell values: re-assembly
        (dict(nu=0.49), True),  # back to grouped materials
    ]
    for step, grouped in steps:
        s.update_materials(**step)
        u = s.solve()
        ef, ec, nu, _ = s.materials
        ref = Solver(grid, backend="superlu", E_fiber=ef, E_cross=ec, nu=nu).solve()
        assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max(), step
        # the grouped path only serves the backends that read one triangle
        uses = getattr(s, "_groups", None) is not None
        assert uses == (grouped and backend in ("cholmod", "pardiso")), step
        # refactoring for new materials keeps the ordering (no switch on update)
        assert s.node_ordering == expected


def test_triangle_operator_is_the_full_reduced_stiffness(mixed):
    if "cholmod" not in BACKENDS and "pardiso" not in BACKENDS:
        pytest.skip("needs a backend that stores one triangle (CHOLMOD or PARDISO)")
    s = Solver(mixed, backend=BACKENDS[0])
    K = stiffness(mixed).tocsr()[s.F][:, s.F]  # no sliding nodes: no local frames
    y = np.random.default_rng(2).normal(size=s.F.size)
    np.testing.assert_allclose(s.K_ff @ y, K @ y, rtol=0, atol=1e-13 * abs(K).max() * np.abs(y).sum())
    np.testing.assert_allclose(s.K_ff.diagonal(), K.diagonal())


@pytest.mark.parametrize("ordering", ["amd", "metis", "nesdis"])
def test_orderings_give_the_same_answer(mixed, ordering):
    if "cholmod" not in BACKENDS:
        pytest.skip("the node-graph ordering applies to the CHOLMOD backend only")
    ref = Solver(mixed, backend="superlu").solve()
    u = Solver(mixed, ordering=ordering).solve()
    assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max()


def test_rigid_motion_of_all_constraints_moves_everything_rigidly(mixed):
    p = mixed.points
    W = np.array([[0, -0.002, 0.001], [0.002, 0, -0.003], [-0.001, 0.003, 0]])
    t = np.array([0.1, -0.2, 0.05])
    rigid = p @ W.T + t
    bc = np.array(mixed[arrays.BC])
    normal = np.zeros_like(rigid)
    z0 = np.isclose(p[:, 2], 0) & (bc == arrays.BC_FREE)
    bc[z0] = arrays.BC_SLIDING
    normal[z0] = (0.1, 0.2, -1.0)
    grid = set_bc(mixed.copy(), np.where(bc == arrays.BC_FIXED, arrays.BC_JOINT, bc), rigid, normal)
    for method in ("direct", "cg"):
        u = solve(grid, method=method, tol=1e-12)[arrays.DISPLACEMENT]
        assert np.abs(u - rigid).max() <= 1e-9 * np.abs(rigid).max(), method


def test_sliding_nodes_keep_normal_and_slide_freely():
    grid = jittered_box(shape=(6, 6, 4), size=(5.0, 5.0, 3.0), seed=11)
    set_materials(grid, 1.0, 1.0, 0.45)
    p = grid.points
    n = grid.n_points
    bc = np.zeros(n, np.int8)
    disp = np.zeros((n, 3))
    normal = np.zeros((n, 3))
    bottom, top = np.isclose(p[:, 2], 0), np.isclose(p[:, 2], 3.0)
    nrm = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    bc[bottom] = arrays.BC_SLIDING
    normal[bottom] = nrm
    disp[bottom] = 0.05 * nrm + np.array([9.0, -9.0, 0.0]) - (np.array([9.0, -9.0, 0.0]) @ nrm) * nrm
    bc[top] = arrays.BC_JOINT
    disp[top] = (0.3, 0.1, -0.2)
    set_bc(grid, bc, disp, normal)
    u = solve(grid)[arrays.DISPLACEMENT]
    # the normal part is prescribed (the tangential part of bc_displacement is ignored) ...
    np.testing.assert_allclose(u[bottom] @ nrm, 0.05, rtol=0, atol=1e-12)
    # ... the tangential part is free: it moves, with no tangential reaction
    tang = u[bottom] - np.outer(u[bottom] @ nrm, nrm)
    assert np.abs(tang).max() > 0.05
    f = (stiffness(grid) @ u.ravel()).reshape(-1, 3)
    scale = np.abs(f[top]).max()
    ft = f[bottom] - np.outer(f[bottom] @ nrm, nrm)
    assert np.abs(ft).max() <= 1e-10 * scale
    assert np.abs(f[bc == arrays.BC_FREE]).max() <= 1e-10 * scale


NUS = [0.0, 0.3, 0.45, 0.49, 0.495, 0.499, 0.4999]


@pytest.mark.parametrize("nu", NUS)
def test_extreme_poisson_ratios_direct_is_accurate_or_warns(nu):
    grid, exact = _patch_grid(nu=nu, seed=2)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = solve(grid)
    u = out[arrays.DISPLACEMENT]
    assert np.all(np.isfinite(u))
    assert out.field_data[pvcmf.mtm.FIELD_RESIDUAL][0] <= 1e-8
    err = np.abs(u - exact).max() / np.abs(exact).max()
    est = out.field_data[pvcmf.mtm.FIELD_ERROR_ESTIMATE][0]
    # never a silent wrong answer: accurate, or the estimate (and warning) says so
    assert err <= max(1e-8, 100 * est)
    if err > 1e-8:
        assert any(issubclass(x.category, IllConditionedWarning) for x in w)


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.4999])
def test_extreme_poisson_ratios_iterative_converge_or_raise(nu, mixed):
    grid = mixed.cmf.assign_materials(table="paper001_homogeneous", fat={"nu": nu}, muscle={"nu": nu})
    ref = solve(grid)[arrays.DISPLACEMENT]
    for method, maxiter in (("cg", 300), ("relaxation", 300)):
        try:
            out = solve(grid, method=method, tol=1e-8, maxiter=maxiter)
        except ConvergenceError as err:
            assert "did not reach tol" in str(err) and method in str(err)
            continue
        assert out.field_data[pvcmf.mtm.FIELD_RESIDUAL][0] <= 1e-7
        assert np.all(np.isfinite(out[arrays.DISPLACEMENT]))
        # a 1e-8 residual bounds the error by the condition number: loose check only
        assert np.abs(out[arrays.DISPLACEMENT] - ref).max() <= 1e-3 * np.abs(ref).max()


@pytest.mark.parametrize("ratio", [1, 10, 100, 1000])
def test_stiffness_ratios_muscle_over_fat(ratio, mixed):
    grid = mixed.cmf.assign_materials(table="paper001_inhomogeneous", e_ratio=ratio)
    out = solve(grid)
    u = out[arrays.DISPLACEMENT]
    assert np.all(np.isfinite(u)) and out.field_data[pvcmf.mtm.FIELD_RESIDUAL][0] <= 1e-8
    # equilibrium at the free nodes, checked on the unreduced MTM
    f = (stiffness(grid) @ u.ravel()).reshape(-1, 3)
    free = grid[arrays.BC] == arrays.BC_FREE
    assert np.abs(f[free]).max() <= 1e-9 * np.abs(f).max()
    cg = solve(grid, method="cg", tol=1e-10, maxiter=1000)
    assert np.abs(cg[arrays.DISPLACEMENT] - u).max() <= 1e-5 * np.abs(u).max()


@pytest.mark.parametrize("shape,size", [((30, 4, 4), (300.0, 3.0, 3.0)),   # needles
                                        ((5, 5, 3), (4.0, 4.0, 0.004))])    # slivers
def test_needle_and_sliver_tetrahedra(shape, size):
    grid = jittered_box(shape=shape, size=size, jitter=0.3, seed=5)
    set_materials(grid, 1.0, 1.0, 0.46)
    p = grid.points
    exact = 1e-3 * p @ np.array([[1.0, 0.2, 0.0], [0.1, -0.5, 0.3], [0.0, 0.4, 2.0]]).T
    set_bc(grid, np.where(boundary_nodes(grid), arrays.BC_JOINT, arrays.BC_FREE), exact)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        out = solve(grid)
    u = out[arrays.DISPLACEMENT]
    assert np.all(np.isfinite(u)) and out.field_data[pvcmf.mtm.FIELD_RESIDUAL][0] <= 1e-8
    err = np.abs(u - exact).max() / np.abs(exact).max()
    assert err <= 1e-8 or any(issubclass(x.category, IllConditionedWarning) for x in w)


def test_folded_mesh_warns():
    grid = jittered_box(shape=(30, 4, 4), size=(300.0, 3.0, 3.0), jitter=0.45, seed=5)
    set_materials(grid, 1.0, 1.0, 0.46)
    with pytest.warns(pvcmf.mtm.InvertedTetrahedraWarning, match=r"1\d of 1305 tetrahedra are inverted"):
        stiffness(grid)


def test_ill_conditioning_warns_with_lost_digits():
    """A free block held only through a very soft layer: nearly a rigid mode left."""
    grid = jittered_box(shape=(9, 4, 4), size=(8.0, 3.0, 3.0), seed=3)
    p = grid.points
    d = p @ np.array([[0.01, 0.002, 0], [0, 0.003, 0.001], [0.002, 0, -0.004]]).T + [0.1, 0.2, 0.3]
    set_bc(grid, np.where(np.isclose(p[:, 0], 0), arrays.BC_JOINT, arrays.BC_FREE), d)
    cx = grid.cell_centers().points[:, 0]
    layer = (cx > 3) & (cx < 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = solve(grid, E_fiber=np.where(layer, 1e-3, 1.0), nu=0.3)  # 4 digits lost: no warning
    assert out.field_data[pvcmf.mtm.FIELD_LOST_DIGITS][0] < 8
    answers = []
    for backend in BACKENDS:
        with pytest.warns(IllConditionedWarning, match=r"about 1\d of 16 significant digits lost"):
            s = Solver(grid, E_fiber=np.where(layer, 1e-12, 1.0), nu=0.3, backend=backend)
            answers.append(s.solve())
        # the residual is tiny, the answer is not: only the estimate tells
        assert s.info["residual"] < 1e-12 and s.info["lost_digits"] >= 10
    if len(answers) > 1:
        spread = np.abs(answers[0] - answers[1]).max() / np.abs(answers[0]).max()
        assert spread <= 100 * s.info["error_estimate"]


def test_unconstrained_component_is_named():
    a = jittered_box(shape=(4, 4, 4), size=(3.0, 3.0, 3.0), seed=1)
    b = jittered_box(shape=(3, 3, 3), size=(2.0, 2.0, 2.0), seed=2)
    b.points = b.points + np.array([10.0, 0, 0])
    grid = a.merge(b, merge_points=False)
    grid.points = np.asarray(grid.points, float)
    set_materials(grid, 1.0, 1.0, 0.3)
    bc = np.zeros(grid.n_points, np.int8)
    bc[grid.points[:, 0] < 0.01] = arrays.BC_FIXED
    set_bc(grid, bc)
    first_b = int(np.flatnonzero(grid.points[:, 0] > 5)[0])
    with pytest.raises(RigidModeError, match=rf"component 1 .*\(27 nodes, e.g. node {first_b}\) keeps 6 rigid"):
        solve(grid)


def test_constraints_on_a_line_or_sliding_plane_leave_rigid_modes():
    grid = jittered_box(shape=(4, 4, 4), size=(3.0, 3.0, 3.0))
    set_materials(grid, 1.0, 1.0, 0.3)
    p = grid.points
    line = np.isclose(p[:, 1], 0) & np.isclose(p[:, 2], 0)
    set_bc(grid, np.where(line, arrays.BC_FIXED, arrays.BC_FREE))
    with pytest.raises(RigidModeError, match="keeps 1 rigid motion"):
        solve(grid)
    plane = np.isclose(p[:, 2], 0)
    normal = np.tile([0, 0, 1.0], (grid.n_points, 1))
    set_bc(grid, np.where(plane, arrays.BC_SLIDING, arrays.BC_FREE), None, normal)
    with pytest.raises(RigidModeError, match="keeps 3 rigid motion.*0 fixed/joint and 16 sliding"):
        solve(grid)


def test_solve_input_validation_and_no_mutation(mixed):
    bare = jittered_box(shape=(3, 3, 3))
    set_materials(bare, 1.0, 1.0, 0.3)
    with pytest.raises(ValueError, match="needs point array 'bc'.*apply_plan"):
        bare.cmf.solve()
    before = {k: np.array(mixed.point_data[k]) for k in mixed.point_data.keys()}
    out = mixed.cmf.solve()
    assert arrays.DISPLACEMENT not in mixed.point_data.keys()
    assert set(mixed.point_data.keys()) == set(before)
    assert out[arrays.DISPLACEMENT].shape == (mixed.n_points, 3)
    for key in (pvcmf.mtm.FIELD_RESIDUAL, pvcmf.mtm.FIELD_ITERATIONS, pvcmf.mtm.FIELD_TIME):
        assert key in out.field_data.keys()
    with pytest.raises(ValueError, match="method must be one of"):
        solve(mixed, method="lu")
    with pytest.raises(ValueError, match="ordering must be one of .* got 'rcm'"):
        solve(mixed, ordering="rcm")
    assert str(solve(mixed, method="auto").field_data[pvcmf.mtm.FIELD_METHOD][0]) == "direct"
    bad = mixed.copy()
    bad.point_data[arrays.BC][0] = 7
    with pytest.raises(ValueError, match="codes .* got value 7 at point 0"):
        solve(bad)
    bad = mixed.copy()
    bad.point_data[arrays.BC][0] = arrays.BC_SLIDING
    with pytest.raises(ValueError, match="'bc_normal' must be a nonzero finite vector.*point 0"):
        solve(bad)
    del bad.point_data[arrays.BC_NORMAL]
    with pytest.raises(ValueError, match="no point array 'bc_normal'.*apply_plan"):
        solve(bad)
    with pytest.raises(ValueError, match="not positive definite.*cell 0"):
        solve(mixed, E_fiber=10.0, E_cross=0.79, nu=0.43, fiber=[0, 0, 1])


def test_relaxation_reports_non_convergence(mixed):
    with pytest.raises(ConvergenceError, match=r"relaxation did not reach tol 1e-10 in 5 sweeps"):
        solve(mixed, method="relaxation", maxiter=5)


@pytest.mark.gpu
@pytest.mark.skipif(not gpu_available(), reason="needs CuPy and a CUDA device (none here)")
def test_gpu_agrees_with_direct(mixed):
    grid = mixed.cmf.assign_materials(table="paper001_homogeneous")
    ref = solve(grid)[arrays.DISPLACEMENT]
    u = solve(grid, method="gpu", tol=1e-10)[arrays.DISPLACEMENT]
    assert np.abs(u - ref).max() <= 1e-6 * np.abs(ref).max()


def test_gpu_without_device_is_a_clear_error(mixed):
    if gpu_available():
        pytest.skip("a GPU is present")
    with pytest.raises(RuntimeError, match="needs CuPy and a CUDA device"):
        solve(mixed, method="gpu")
