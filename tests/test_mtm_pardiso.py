"""MTM PARDISO backend: thread policy, mixed precision, the sweep's automatic switch."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from mtm_helpers import jittered_box, set_bc

from pvcmf import arrays
from pvcmf.mtm import Solver, direct_backends
from pvcmf.mtm import solvers as S

BACKENDS = direct_backends()
needs_pardiso = pytest.mark.skipif("pardiso" not in BACKENDS,
                                   reason="needs pypardiso (MKL PARDISO): pip install pvcmf[fast]")


@pytest.mark.parametrize("cores,load,n,expected", [
    (2, 0.0, 14_000, 2),    # idle: both cores
    (2, 0.4, 14_000, 2),    # 1.6 idle cores round to 2
    (2, 0.6, 14_000, 1),    # 1.4 idle cores round to 1
    (2, 1.3, 14_000, 1),    # one core busy elsewhere: a second thread would wait for it
    (2, 7.0, 14_000, 1),    # overloaded: never fewer than one
    (8, 2.2, 14_000, 6),
    (8, 0.0, 1_000, 1),     # small systems: one thread
])
def test_pardiso_thread_policy(cores, load, n, expected):
    assert S._pardiso_threads(n, cores=cores, load=load) == expected


@pytest.mark.parametrize("cores,load,current,expected", [
    (2, 0.3, 2, 2), (2, 0.4, 2, 2), (2, 0.5, 2, 1),  # 2 planned: dropped when > 0.4 busy
    (2, 0.2, 1, 1), (2, 0.15, 1, 2),                 # 1 planned: raised when <= 0.15 busy
    (2, 1.9, 2, 1), (2, 0.0, 1, 2), (2, 0.6, 2, 1),
    (8, 2.5, 6, 5), (8, 2.3, 6, 6), (8, 0.1, 6, 8), (8, 1.2, 6, 6),  # more cores
])
def test_pardiso_thread_policy_hysteresis(cores, load, current, expected):
    assert S._pardiso_threads(14_000, cores=cores, load=load, current=current) == expected


def test_pardiso_threads_without_load_information(monkeypatch):
    monkeypatch.setattr(S, "_others_load", lambda: None)
    assert S._pardiso_threads(50_000, cores=4) == 4
    monkeypatch.setattr(S, "_others_load", lambda: 0.1)
    assert S._pardiso_threads(50_000, cores=4) == 4
    monkeypatch.setattr(S, "_others_load", lambda: 3.2)
    assert S._pardiso_threads(50_000, cores=4) == 1


def test_others_load_from_proc_stat_less_this_process(monkeypatch):
    clock = {"t": 1000.0, "cpu": 50.0, "busy": 9000.0}
    monkeypatch.setattr(S.time, "monotonic", lambda: clock["t"])
    monkeypatch.setattr(S.time, "process_time", lambda: clock["cpu"])
    monkeypatch.setattr(S, "_cpu_busy", lambda: clock["busy"])
    monkeypatch.setattr(S, "_STAT", {"prev": (1000.0, 9000.0, 50.0), "load": None})

    def run(seconds, ours, others, step=0.1):
        for _ in range(int(round(seconds / step))):
            clock["t"] += step
            clock["cpu"] += ours * step
            clock["busy"] += (ours + others) * step
            out = S._others_load()
        return out

    # this process alone on both cores: nobody else
    assert run(10.0, ours=2.0, others=0.0) == pytest.approx(0.0, abs=1e-9)
    # another job takes one core: seen within a few time constants
    assert run(5 * S._OTHERS_TAU, ours=1.0, others=1.0) == pytest.approx(1.0, abs=0.01)
    monkeypatch.setattr(S, "_cpu_busy", lambda: clock["busy"])
    assert S._pardiso_threads(50_000, cores=2) == 1
    # it stops: both cores are ours again
    assert run(5 * S._OTHERS_TAU, ours=0.5, others=0.0) == pytest.approx(0.0, abs=0.01)
    assert S._pardiso_threads(50_000, cores=2) == 2
    # calls closer than the clock ticks keep the estimate
    clock["t"] += 0.01
    clock["busy"] += 0.02
    assert S._others_load() == pytest.approx(0.0, abs=0.01)


def test_cpu_busy_sums_the_cpus_of_this_process(tmp_path, monkeypatch):
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal (clock ticks)
    stat.write_text("cpu  600 0 60 900 30 0 6 0 0 0\n"
                    "cpu0 100 0 10 300 10 0 1 0 0 0\n"
                    "cpu1 200 0 20 300 10 0 2 0 0 0\n"
                    "cpu2 300 0 30 300 10 0 3 0 0 0\n"
                    "intr 12345\n")
    monkeypatch.setattr(S, "_PROC_STAT", str(stat))
    monkeypatch.setattr(S.os, "sched_getaffinity", lambda pid: {0, 2})
    hz = S.os.sysconf("SC_CLK_TCK")
    assert S._cpu_busy() == pytest.approx((111 + 333) / hz)  # idle and iowait left out
    monkeypatch.setattr(S, "_PROC_STAT", str(tmp_path / "missing"))
    assert S._cpu_busy() is None


def test_others_load_without_proc_stat_uses_the_load_average(monkeypatch):
    monkeypatch.setattr(S, "_cpu_busy", lambda: None)
    monkeypatch.setattr(S, "_own_load", lambda: 0.9)
    monkeypatch.setattr(S.os, "getloadavg", lambda: (1.5, 1.0, 1.0))
    assert S._others_load() == pytest.approx(0.6)

    def no_load():
        raise OSError("no load average")

    monkeypatch.setattr(S.os, "getloadavg", no_load)
    assert S._others_load() is None


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
    s = Solver(box, backend="pardiso")  # precision 'auto': mixed with PARDISO
    s.solve()
    assert s.info["precision"] == "mixed" and s._backend.precision == "single"
    s.max_mixed_iterations = 0  # the single factor alone cannot reach 1e-14: a stall
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
    s = Solver(box, backend="pardiso")
    s.max_mixed_error = 0.0  # any single-precision error counts as too large to estimate from
    u = s.solve()
    assert s.info["precision"] == "double (mixed stalled)"
    assert np.abs(u - _reference(box)).max() <= 1e-10 * np.abs(u).max()


@needs_pardiso
def test_thread_count_changes_replan_the_factorisation(box, monkeypatch):
    """MKL PARDISO crashed when a factorisation or solve used another thread count than the
    analysis: a change of the policy's answer must re-analyse, and the answers stay exact."""
    counts = itertools.cycle([2, 2, 1, 2, 1, 1])
    monkeypatch.setattr(S, "_pardiso_threads", lambda n, **kw: next(counts))
    s = Solver(box, backend="pardiso", precision="double")  # analysis with 2 threads
    s.solve()
    seen = set()
    for nu in (0.1, 0.2, 0.3, 0.4, 0.45):
        s.update_materials(nu=nu)
        u = s.solve()
        seen.add(s._backend.threads)
        assert s.info["threads"] == s._backend.threads
        ref = _reference(box, nu=nu)
        assert np.abs(u - ref).max() <= 1e-10 * np.abs(ref).max(), nu
    assert seen == {1, 2}


@needs_pardiso
def test_sweep_switches_cholmod_to_mixed_pardiso(box, monkeypatch):
    if "cholmod" not in BACKENDS:
        pytest.skip("the automatic switch starts from CHOLMOD")
    monkeypatch.setattr(S, "_SWEEP_PARDISO_MIN", 0)  # the box is below the real threshold
    s = Solver(box)  # backend chosen by the solver
    s.solve()
    assert s.backend_name == "cholmod" and s.info["precision"] == "double"
    s.update_materials(nu=0.3, refactor=False)  # factor reuse: no switch
    s.solve()
    assert s.backend_name == "cholmod"
    for nu in (0.2, 0.49):
        s.update_materials(nu=nu)  # refactors: a sweep
        u = s.solve()
        assert s.backend_name == "pardiso" and s.info["precision"] == "mixed"
        ref = _reference(box, nu=nu)
        assert np.abs(u - ref).max() <= 1e-8 * np.abs(ref).max()
    # a backend the user chose is kept
    t = Solver(box, backend="cholmod")
    t.update_materials(nu=0.2)
    assert t.backend_name == "cholmod"


def test_precision_validation(box):
    with pytest.raises(ValueError, match="precision must be one of"):
        Solver(box, precision="half")
    with pytest.raises(ValueError, match="precision='mixed' needs method='direct' with "
                                         "backend='pardiso'.*backend='superlu'"):
        Solver(box, backend="superlu", precision="mixed")
    with pytest.raises(ValueError, match="method='cg'"):
        Solver(box, method="cg", precision="mixed")


def test_own_load_is_this_process_cpu_averaged_like_the_load_average(monkeypatch):
    clock = {"t": 1000.0, "cpu": 50.0}
    monkeypatch.setattr(S.time, "monotonic", lambda: clock["t"])
    monkeypatch.setattr(S.time, "process_time", lambda: clock["cpu"])
    monkeypatch.setattr(S, "_OWN", {"t": 1000.0, "cpu": 50.0, "load": 0.0})
    for _ in range(600):  # 10 minutes at 1.5 cores: converges to 1.5
        clock["t"] += 1.0
        clock["cpu"] += 1.5
        S._own_load()
    converged = 1.5 * (1 - np.exp(-10.0))  # 1 - e^(-600 s / 60 s) of the way from 0
    assert abs(S._own_load() - converged) < 1e-9
    clock["t"] += 60.0  # one idle minute: decays by e
    assert abs(S._own_load() - converged / np.e) < 1e-9
    # without /proc/stat the policy subtracts it from the load average: 1.6, 1.5 of it ours
    monkeypatch.setattr(S, "_cpu_busy", lambda: None)
    monkeypatch.setattr(S, "_OWN", {"t": clock["t"], "cpu": clock["cpu"], "load": 1.5})
    monkeypatch.setattr(S.os, "getloadavg", lambda: (1.6, 1.0, 1.0))
    assert S._pardiso_threads(50_000, cores=2) == 2
    monkeypatch.setattr(S, "_OWN", {"t": clock["t"], "cpu": clock["cpu"], "load": 0.0})
    assert S._pardiso_threads(50_000, cores=2) == 1
