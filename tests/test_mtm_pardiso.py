"""MTM backends: explicit choice (no switch on update), PARDISO threads and mixed precision."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from mtm_helpers import jittered_box, set_bc

from pvcmf import arrays
from pvcmf.mtm import BackendUnavailableError, Solver, backends, direct_backends

BACKENDS = direct_backends()
needs_pardiso = pytest.mark.skipif("pardiso" not in BACKENDS,
                                   reason="needs pypardiso (MKL PARDISO): pip install pvcmf[fast]")


def _grid(nu=0.46, ratio=1.0):
    """Irregular box, a stiff 'muscle' half (E ratio ``ratio``), fixed end, moved end."""
    grid = jittered_box(shape=(10, 6, 6), size=(9.0, 5.0, 5.0), seed=11)
    musc = grid.cell_centers().points[:, 2] > 2.5
    e = np.where(musc, ratio, 1.0) * 0.003
    grid.cell_data[arrays.E_FIBER] = e
    grid.cell_data[arrays.E_CROSS] = e
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, nu)
    grid.cell_data[arrays.FIBER] = np.zeros((grid.n_cells, 3))
    p = grid.points
    bc = np.zeros(grid.n_points, np.int8)
    bc[np.isclose(p[:, 0], 0)] = arrays.BC_FIXED
    moved = np.isclose(p[:, 0], 9.0)
    bc[moved] = arrays.BC_JOINT
    disp = np.zeros((grid.n_points, 3))
    disp[moved] = np.column_stack([0.3 + 0.02 * p[moved, 1], 0.2 * np.ones(moved.sum()),
                                   -0.05 * p[moved, 2]])
    return set_bc(grid, bc, disp)


@pytest.fixture(scope="module")
def box():
    return _grid()


def _reference(grid, **materials):
    return Solver(grid, backend="superlu", **materials).solve()


@needs_pardiso
@pytest.mark.parametrize("nu,ratio", [(0.0, 1.0), (0.46, 1.0), (0.4999, 1.0), (0.46, 1000.0),
                                      (0.4999, 1000.0)])
def test_mixed_precision_agrees_with_double_at_the_extremes(nu, ratio):
    grid = _grid(nu, ratio)
    ref = _reference(grid)
    s = Solver(grid, backend="pardiso", precision="mixed", tol=1e-10)
    u = s.solve()
    assert s.info["residual"] <= 1e-10
    assert s.info["precision"] == "mixed"  # no fallback needed here (tested below)
    # as accurate as a double factor (measured 1e-15-1e-12, estimates 1e-15-5e-13); a
    # refinement stopped at the 1e-10 residual alone left 1e-7 at nu 0.4999
    bound = max(1e-13, 100 * s.info["error_estimate"])
    assert np.abs(u - ref).max() <= bound * np.abs(ref).max()
    d = Solver(grid, backend="pardiso", precision="double")
    np.testing.assert_allclose(d.solve(), ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    assert d.info["precision"] == "double"


@needs_pardiso
def test_mixed_precision_stall_falls_back_to_double(box, monkeypatch):
    ref = _reference(box)
    s = Solver(box, backend="pardiso", precision="mixed")
    s.solve()
    assert s.info["precision"] == "mixed" and s._backend.precision == "single"
    s._method.max_mixed_iterations = 0  # the single factor alone cannot reach 1e-14: a stall
    s.tol = 1e-14
    u = s.solve()
    assert s.info["precision"] == "double (mixed stalled)" and s._backend.precision == "double"
    assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max()
    s.update_materials(nu=0.3)  # stays in double from then on
    s.solve()
    assert s._backend.precision == "double"
    assert np.abs(s.solve() - _reference(box, nu=0.3)).max() <= 1e-10 * np.abs(ref).max()


@needs_pardiso
def test_mixed_precision_saturated_estimate_refactors_in_double(box):
    s = Solver(box, backend="pardiso", precision="mixed")
    s._method.max_mixed_error = 0.0  # any single-precision error counts as too large to estimate from
    u = s.solve()
    assert s.info["precision"] == "double (mixed stalled)"
    assert np.abs(u - _reference(box)).max() <= 1e-10 * np.abs(u).max()


@needs_pardiso
@pytest.mark.parametrize("threads", [1, 2])
def test_pardiso_threads_are_the_callers(box, threads):
    s = Solver(box, backend="pardiso", threads=threads)
    u = s.solve()
    assert s._backend.threads == threads and s.info["threads"] == threads
    for nu in (0.2, 0.45):
        s.update_materials(nu=nu)
        u = s.solve()
        assert s.info["threads"] == threads
        ref = _reference(box, nu=nu)
        assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max(), nu


def test_precision_validation(box):
    with pytest.raises(ValueError, match="precision must be one of"):
        Solver(box, precision="half")
    with pytest.raises(ValueError, match="precision='mixed' needs method='direct' with "
                                         "backend='pardiso'.*backend='superlu'"):
        Solver(box, backend="superlu", precision="mixed")
    with pytest.raises(ValueError, match="method='cg'"):
        Solver(box, method="cg", precision="mixed")
    with pytest.raises(ValueError, match="threads must be"):
        Solver(box, threads=0)


def test_default_precision_follows_the_backend_and_threads_are_one(box):
    s = Solver(box)
    s.solve()
    expected = "mixed" if s.backend_name == "pardiso" else "double"
    assert s.precision == expected and s.info["precision"] == expected
    assert Solver(box, precision="auto").precision == expected
    assert Solver(box, backend="superlu").precision == "double"
    assert s.threads == 1 and s.info["threads"] == 1


class _PhaseSpy:
    """Counts the PARDISO phases every :class:`Pardiso` of the test calls."""

    def __init__(self, monkeypatch):
        self.calls = []
        call = backends.pardiso.Pardiso._call

        def spy(factor, phase, b=None):
            self.calls.append((id(factor), phase))
            return call(factor, phase, b)

        monkeypatch.setattr(backends.pardiso.Pardiso, "_call", spy)

    def phases(self, factor):
        return [phase for key, phase in self.calls if key == id(factor)]


@needs_pardiso
@pytest.mark.parametrize("precision", ["mixed", "double"])
def test_update_with_the_same_pattern_is_a_numeric_factorisation_only(box, monkeypatch,
                                                                        precision):
    spy = _PhaseSpy(monkeypatch)
    s = Solver(box, backend="pardiso", precision=precision)
    s.solve()
    factor = s._backend
    assert spy.phases(factor).count(11) == 1 and spy.phases(factor).count(22) == 1
    for k, nu in enumerate((0.0, 0.3, 0.49), start=2):
        s.update_materials(nu=nu)
        u = s.solve()
        # the same factor object, no new analysis (phase 11) and no release (-1): one
        # numeric factorisation (phase 22) per update
        phases = spy.phases(factor)
        assert s._backend is factor
        assert phases.count(11) == 1 and -1 not in phases and phases.count(22) == k
        assert s.info["precision"] == precision and s.info["residual"] <= 1e-12
        ref = _reference(box, nu=nu)
        assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max(), nu


@needs_pardiso
def test_pardiso_node_order_numbers_the_unknowns_and_saves_fill(box):
    s = Solver(box, backend="pardiso")
    asm, free = s.assembler, s.constraints.free
    nodes, name = backends.pardiso.node_order(asm.indptr, asm.indices, free)
    active = np.flatnonzero(free.reshape(-1, 3).any(axis=1))
    assert name == "pardiso-metis"
    np.testing.assert_array_equal(np.sort(nodes), active)
    if "cholmod" not in BACKENDS:  # the solver numbers its unknowns node by node in that order
        assert s.node_ordering == "pardiso-metis" and s._natural_order
        node_of = s.F // 3
        first = np.sort(np.unique(node_of, return_index=True)[1])
        np.testing.assert_array_equal(node_of[first], nodes)
        assert s._backend._iparm[4] == 1  # analysed with that order: no METIS on the dofs
    # the order leaves less fill than a random one (PARDISO reports the factor's entries)
    upper = s.K_ff.upper
    full = (upper + s.K_ff.lower).tocsr()
    shuffle = np.random.default_rng(3).permutation(upper.shape[0])
    shuffled = sp.triu(full[shuffle][:, shuffle], format="csr")
    shuffled.sort_indices()
    ordered = backends.pardiso.Pardiso(upper, threads=1, natural=True)
    random = backends.pardiso.Pardiso(shuffled, threads=1, natural=True)
    assert 0 < ordered.factor_entries < 0.5 * random.factor_entries


@needs_pardiso
def test_pardiso_orderings_agree_with_superlu(box):
    ref = _reference(box)
    for ordering in ("auto", "amd"):  # the node-graph METIS order, or PARDISO's own METIS
        for precision in ("mixed", "double"):
            s = Solver(box, backend="pardiso", ordering=ordering, precision=precision)
            u = s.solve()
            assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max(), (ordering, precision)
            assert s.info["residual"] <= 1e-12


def test_auto_backend_follows_the_installed_packages_only(box, monkeypatch):
    assert Solver(box).backend_name == direct_backends()[0]
    assert Solver(box, backend="auto").backend_name == direct_backends()[0]
    monkeypatch.setattr(backends.pardiso, "available", lambda: False)
    monkeypatch.setattr(backends.cholmod, "available", lambda: False)
    assert direct_backends() == ["superlu"]
    assert Solver(box).backend_name == "superlu"
    monkeypatch.setattr(backends.pardiso, "available", lambda: True)
    assert direct_backends()[0] == "pardiso"
    assert backends.resolve("auto") == "pardiso"


@pytest.mark.parametrize("name", ["pardiso", "cholmod"])
def test_unavailable_backend_is_a_clear_error(box, monkeypatch, name):
    monkeypatch.setattr(getattr(backends, name), "available", lambda: False)
    with pytest.raises(BackendUnavailableError, match=f"backend {name!r} is not installed"):
        Solver(box, backend=name)
    with pytest.raises(ValueError, match="backend must be 'auto' or one of .*got 'umfpack'"):
        Solver(box, backend="umfpack")


def test_splu_is_an_alias_of_superlu(box):
    s = Solver(box, backend="splu")
    np.testing.assert_allclose(s.solve(), _reference(box), rtol=0, atol=1e-12)
    assert s.backend_name == "superlu"


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("refactor", [True, False])
def test_update_keeps_backend_precision_and_ordering(box, backend, refactor):
    precision = "mixed" if backend == "pardiso" else "double"
    s = Solver(box, backend=backend, precision=precision)
    s.solve()
    factor, ordering = s._backend, s.node_ordering
    for nu in (0.3, 0.2, 0.49):
        s.update_materials(nu=nu, refactor=refactor)
        u = s.solve()
        assert s.backend_name == backend and s._backend is factor  # no new analysis
        assert s._backend.precision == ("single" if precision == "mixed" else "double")
        assert s.node_ordering == ordering and s.precision == precision
        ref = _reference(box, nu=nu)
        assert np.abs(u - ref).max() <= 1e-8 * np.abs(ref).max(), (backend, nu)
