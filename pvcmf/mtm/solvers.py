"""Solvers of the MTM rest position: direct, cg, relaxation and an optional GPU path.

The rest position of the free vertices makes every elastic force ``K_jj u_j + sum K_jk u_k``
zero (paper 001 eq. 2). After eliminating the constraints (:mod:`pvcmf.mtm.constraints`) this
is one sparse symmetric positive definite system ``K_ff y = -K_fp y_p``.

Methods
-------
``direct``
    Sparse Cholesky: CHOLMOD through scikit-sparse when importable, else MKL PARDISO
    through pypardiso (``pip install pvcmf[fast]``), else scipy's SuperLU with a symmetric
    ordering (sound but ~10x slower on large meshes). With CHOLMOD the unknowns are numbered
    by an AMD or METIS order of the node graph (:func:`_node_order`, ``Solver(ordering=)``)
    and CHOLMOD factors the lower triangle in that natural order: the analysis is 6x cheaper
    than METIS on the dof graph for the same fill. CHOLMOD and PARDISO store only that
    triangle (``K_ff`` is then a symmetric operator on it). Wheel-only alternatives for CI (sksparse-minimal, cholespy, qdldl) were
    measured no faster than SuperLU at 30k tetrahedra, so none is used. One step of iterative
    refinement estimates the forward error; an :class:`IllConditionedWarning` says how many
    digits the answer lost when that estimate is large. PARDISO is called through ctypes on
    pypardiso's MKL (:class:`_Pardiso`): the same node order passed as its permutation, and
    by default (``precision='auto'``/``'mixed'``) a single-precision numeric factor refined
    in double by conjugate gradient to the double answer's accuracy (:meth:`Solver._solve_mixed`:
    about 40 % less time per factorisation, 2-3 triangular solve pairs more), with a double
    factor when single precision stalls or cannot estimate the lost digits (nu -> 0.5 with
    extreme stiffness contrasts; ``info['precision']`` says so). A Poisson sweep
    (:meth:`Solver.update_materials` refactoring for new materials) switches a solver whose
    backend the user did not choose from CHOLMOD to mixed-precision PARDISO: at 30k
    tetrahedra a 20-value sweep took 1.5-1.8 s on one thread (another job on the other core)
    against 2.2-2.9 s with CHOLMOD in the same runs, 1.19 s on two threads against 2.51 s
    with the other core free (see ``benchmarks/mtm.py``).
``cg``
    Conjugate gradient (scipy) preconditioned by one V-cycle of smoothed-aggregation
    algebraic multigrid (pyamg, rigid motions as near-null space, options measured in
    :data:`_AMG_OPTIONS`) or by block Jacobi; warm-startable.
``relaxation``
    The paper's local iteration ``u_j <- -K_jj^-1 sum_k K_jk u_k``, vectorised as a
    multicolour block Gauss-Seidel (one colour at a time, all vertices of a colour at once).
    Kept to measure what the other methods gain; slow and it stalls for nu near 0.5.
``gpu``
    Jacobi-preconditioned conjugate gradient on the GPU through CuPy (only when CuPy and a
    CUDA device are present; not verified on a GPU yet).
``auto``
    ``direct`` up to :data:`AUTO_DIRECT_MAX_POINTS` points, ``cg`` above (memory).

Iterative methods and triangular solves run with one BLAS thread (threadpoolctl, when
installed): they are memory bound, and threaded BLAS calls on short vectors only spin.
CHOLMOD factorisations of fewer than 100k unknowns run with one thread too (measured no
slower up to 69k); larger ones keep the BLAS default unless the machine is busy (load >=
cores). PARDISO plans its analysis, factorisations and solves for the idle cores
(:func:`_pardiso_threads`): a second thread pays there (its parallelism is over the
elimination tree), unless another process holds that core.

:class:`Solver` keeps everything that does not depend on the material (geometry, sparsity
pattern, elimination maps, the symbolic factorisation), so a Poisson-ratio sweep only refactors
numerically (re-assembling through the cached linear map of
:meth:`~pvcmf.mtm.Assembler.linear_upper_blocks`), or, with ``refactor=False``, reuses the
factor as a CG preconditioner when a condition-number bound says that pays; a new bone move
only re-solves. Delegates to scikit-sparse / pypardiso /
scipy.sparse.linalg, pyamg and CuPy.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import time
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .. import arrays
from .assembly import Assembler, _merge_pairs, grid_materials, tetrahedra
from .constraints import Constraints

log = logging.getLogger(__name__)

__all__ = [
    "Solver",
    "solve",
    "ConvergenceError",
    "IllConditionedWarning",
    "direct_backends",
    "gpu_available",
    "METHODS",
    "ORDERINGS",
    "PRECISIONS",
    "AUTO_DIRECT_MAX_POINTS",
    "FIELD_METHOD",
    "FIELD_BACKEND",
    "FIELD_RESIDUAL",
    "FIELD_ITERATIONS",
    "FIELD_TIME",
    "FIELD_ERROR_ESTIMATE",
    "FIELD_LOST_DIGITS",
]

METHODS = ("direct", "cg", "relaxation", "gpu", "auto")
#: node-graph orderings of :class:`Solver` (CHOLMOD backend)
ORDERINGS = ("auto", "amd", "metis", "nesdis")
#: numeric factor precisions of :class:`Solver` (``mixed``: PARDISO backend only)
PRECISIONS = ("auto", "double", "mixed")
#: ``method="auto"`` uses ``direct`` up to this many points, else ``cg`` (a sparse Cholesky of a
#: 3D mesh grows faster than linearly: at 1M tetrahedra / 213k points, METIS order, L has 363M
#: entries, 2.9 GB of values, and the process peaked at 9.8 GB; cg stayed at 3.45 GB)
AUTO_DIRECT_MAX_POINTS = 100_000
#: field-data names written by :func:`solve`
FIELD_METHOD = "mtm_method"
FIELD_BACKEND = "mtm_backend"
FIELD_RESIDUAL = "mtm_residual"  #: relative residual ||K_ff y - b|| / ||b||
FIELD_ITERATIONS = "mtm_iterations"
FIELD_TIME = "mtm_time"  #: seconds: assembly + factorisation/setup + solve
FIELD_ERROR_ESTIMATE = "mtm_error_estimate"  #: estimated relative forward error (direct)
FIELD_LOST_DIGITS = "mtm_lost_digits"  #: estimated significant digits lost (direct)

_EPS = np.finfo(float).eps
_EPS32 = float(np.finfo(np.float32).eps)
#: the automatic CHOLMOD -> PARDISO switch of a sweep (Solver._switch_to_pardiso) needs at
#: least this many unknowns: conservative (20-value sweeps, load ~1.7: 4940 tetrahedra /
#: 2412 unknowns 176 ms with the switch against 257 ms CHOLMOD; at 1080 unknowns PARDISO
#: from the start 85 ms against 110 ms, the switch not tried there)
_SWEEP_PARDISO_MIN = 2_000
#: relative residual the mixed-precision refinement aims at (stops earlier once below tol
#: and stagnating); about what one double factor plus one refinement step reaches
_MIXED_TARGET = 1e-14


_CONTROLLER = []


def _single_threaded_blas():
    """Context limiting BLAS to one thread (threadpoolctl, when installed).

    Iterative methods and triangular solves are memory bound: a threaded BLAS only spins,
    and on a busy 2-core machine it made CG 4x slower in CPU time. Factorisations keep
    their threads.
    """
    if not _CONTROLLER:
        try:
            from threadpoolctl import ThreadpoolController

            _CONTROLLER.append(ThreadpoolController())
        except ImportError:
            _CONTROLLER.append(None)
    ctl = _CONTROLLER[0]
    return contextlib.nullcontext() if ctl is None else ctl.limit(limits=1, user_api="blas")


#: direct factorisations of fewer unknowns run with one BLAS thread (see _factor_threads)
_THREADED_FACTOR_MIN = 100_000


def _factor_threads(n_unknowns=None):
    """BLAS threads for a factorisation: one thread below :data:`_THREADED_FACTOR_MIN`
    unknowns or when the machine is already busy (load average >= cores), else the
    library's default.

    A second OpenBLAS thread never paid in these measurements (its waiting thread spins on
    the other core): CHOLMOD numeric factorisation, one vs two threads,
    interleaved runs (load 2.2-3): 30k tetrahedra (14k unknowns) median 144 vs 269 ms wall,
    best 105 vs 113 ms; 50k (23k) 392 vs 491 ms, best 294 vs 383 ms; 150k (69k) 2.9 vs 3.8 s,
    best 2.1 vs 2.6 s; CPU time doubled with two threads. Session 2: at 30k under load 8,
    CHOLMOD + solve took 0.36 s CPU single-threaded against 0.73 s with two threads."""
    if n_unknowns is not None and n_unknowns < _THREADED_FACTOR_MIN:
        return _single_threaded_blas()
    try:
        busy = os.getloadavg()[0] >= (os.cpu_count() or 1)
    except OSError:  # no load average on this platform
        busy = False
    return _single_threaded_blas() if busy else contextlib.nullcontext()


def _norm(x):
    """2-norm without BLAS (a threaded ddot stalls on a busy 2-core machine)."""
    x = np.asarray(x)
    return float(np.sqrt(np.einsum("i,i->", x, x)))


class ConvergenceError(RuntimeError):
    """An MTM solve did not reach its tolerance."""


class IllConditionedWarning(UserWarning):
    """The MTM system is so ill conditioned that the solution lost many digits."""


def direct_backends():
    """Names of the importable direct backends, fastest first (``'superlu'`` always).

    Examples
    --------
    >>> from pvcmf.mtm import direct_backends
    >>> direct_backends()[-1]
    'superlu'
    """
    out = []
    try:
        import sksparse.cholmod  # noqa: F401

        out.append("cholmod")
    except ImportError:
        pass
    try:
        import pypardiso  # noqa: F401

        out.append("pardiso")
    except ImportError:
        pass
    return out + ["superlu"]


def gpu_available():
    """True when CuPy imports and sees a CUDA device."""
    try:
        import cupy

        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # ImportError, CUDARuntimeError, ...
        return False


# ---------------------------------------------------------------------- direct backends
class _Cholmod:
    """CHOLMOD supernodal Cholesky of the lower triangle (CSC) of a pre-ordered matrix.

    The fill-reducing ordering is computed once on the node graph (:func:`_node_order`) and
    applied to the unknowns, so the dof matrix is analysed with the natural ordering: the
    analysis is about 6x cheaper than METIS on the dof graph (9x the entries) for the same
    fill, and every node's dofs stay adjacent (3x3 blocks inside the supernodes). Supernodal,
    not simplicial: at 30k tetrahedra the numeric factorisation took 115 ms against 460-800 ms
    (same orderings). scikit-sparse 0.4 has no single-precision factor to try.
    """

    name = "cholmod"

    def __init__(self, pattern, ordering="natural"):
        from sksparse.cholmod import analyze

        self._factor = analyze(pattern, mode="supernodal", ordering_method=ordering)

    def factor(self, K):
        from sksparse.cholmod import CholmodNotPositiveDefiniteError

        try:
            self._factor.cholesky_inplace(K)
        except CholmodNotPositiveDefiniteError as err:
            raise _not_pd(err) from err

    def solve(self, b):
        return self._factor(b)


_MKL = []


def _mkl():
    """pypardiso's MKL runtime (a ctypes handle) with PARDISO's and the thread setter's C
    signatures. (The lowercase ``mkl_set_num_threads*`` are the Fortran entry points, which
    take pointers: calling them by value crashes the next PARDISO call.)"""
    if not _MKL:
        from pypardiso import PyPardisoSolver

        lib = PyPardisoSolver().libmkl
        lib.pardiso.argtypes = [ctypes.c_void_p] * 16
        lib.pardiso.restype = None
        lib.MKL_Set_Num_Threads_Local.argtypes = [ctypes.c_int]
        lib.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        _MKL.append(lib)
    return _MKL[0]


def _cores():
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


#: PARDISO factorisations of fewer unknowns run on one thread (see _pardiso_threads; the
#: threshold is a guess, not measured: 2 threads paid from 13 932 unknowns up)
_PARDISO_THREADED_MIN = 5_000


def _pardiso_threads(n_unknowns, cores=None, load=None, current=None):
    """MKL threads for a PARDISO analysis (and its factorisations and solves): the idle cores.

    ``cores - load`` (the other processes' busy cores, :func:`_others_load`) rounded, between
    1 and ``cores``; one thread
    below :data:`_PARDISO_THREADED_MIN` unknowns. With ``current`` (the count the analysis
    planned for) the answer changes only when the idle cores reach ``current + 0.85`` (one
    more thread: the other processes left a core nearly free) or fall below ``current -
    0.4`` (fewer): each change costs a new analysis, so a load near a rounding boundary
    must not make the count flip back and forth, and a thread sharing its core costs more
    (2.8x on the sweep below) than a free core left unused (1.8x), hence the asymmetry.
    (A competing job that got only its fair share of a contested core would still show as
    about 0.5 busy, past the 0.4; MKL's idle threads spun only 9 ms in the 300 ms after a
    2-thread factorisation here, so they do not hide it.) PARDISO parallelises over the
    elimination tree, so unlike CHOLMOD's supernodal BLAS calls (:func:`_factor_threads`) a
    second thread pays on an idle machine, but a thread that has to share its core with
    another process makes the whole factorisation wait for it at every synchronisation.
    Every phase uses the analysis's thread count (:class:`_Pardiso` re-analyses when this
    answer changes). Wall time of 2 threads over 1, paired, interleaved, median of 7, one
    process (``python benchmarks/mtm.py --sizes 30000 50000 150000 --threads
    --only-threads``, METIS node order), double / single precision, CHOLMOD alongside:
    with another engineer's job on one core (load 2.0-2.2) 30k tetrahedra (13 932 unknowns)
    1.78 / 2.17 (CHOLMOD 1.00); moments later with that core free, 50k (23 170) 0.61 / 0.55
    (129 / 65 ms against 211 / 121 ms; CHOLMOD 0.83) and 150k (69 406) 0.56 / 0.55
    (1.01 / 0.49 s against 1.68 / 0.85 s; CHOLMOD 1.02). A later run at load 1.2-1.9 with
    the other core free: 0.57 / 0.56 at 30k (42 / 25 ms against 73 / 46 ms), 0.58 / 0.54 at
    50k, 0.54 / 0.56 at 150k (CHOLMOD 0.79-0.92); the 1-minute load average still counted
    the benchmark's own finished processes there, hence :func:`_others_load`. The whole
    30k 20-value sweep with another job on one core (others' load 1.00, interleaved, median
    of 4): forced to 2 threads 5.9 s, 1 thread 2.1 s, this policy (1 thread) 2.0 s.
    """
    if n_unknowns < _PARDISO_THREADED_MIN:
        return 1
    cores = _cores() if cores is None else int(cores)
    if load is None:
        load = _others_load()
        if load is None:  # nothing to tell: use the cores
            return cores
    idle = cores - load
    shift = 0.5
    if current is not None:
        if current - 0.4 <= idle < current + 0.85:
            return int(current)
        shift = 0.15 if idle > current else 0.4
    return int(min(cores, max(1, np.floor(idle + shift))))


_PROC_STAT = "/proc/stat"


def _cpu_busy():
    """Seconds the CPUs this process may run on spent busy (neither idle nor waiting for
    I/O) since boot, from the per-CPU lines of ``/proc/stat``; None where there is none."""
    try:
        mine = os.sched_getaffinity(0)
        busy = 0
        with open(_PROC_STAT, "rb") as f:
            for line in f:
                if not line.startswith(b"cpu"):
                    break
                name, *t = line.split()
                if name == b"cpu" or int(name[3:]) not in mine:
                    continue
                t = [int(x) for x in t[:8]]
                busy += sum(t) - t[3] - t[4]
        return busy / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, AttributeError, IndexError):
        return None


#: time constant (s) of the other processes' CPU use seen by _others_load
_OTHERS_TAU = 5.0
_STAT = {"prev": (time.monotonic(), _cpu_busy(), time.process_time()), "load": None}


def _others_load():
    """Cores kept busy by other processes lately, or None when unknown.

    From ``/proc/stat``: the busy time of the CPUs it may run on less this process's own CPU
    time (all threads) since the previous call (the first: since this module's import),
    averaged over about :data:`_OTHERS_TAU` seconds (exponential decay): it follows another
    job starting or stopping within seconds, and does not count this process (nor its
    finished predecessors, which the 1-minute load average keeps for a minute). Elsewhere
    the 1-minute load average less this process's share (:func:`_own_load`).
    """
    now, own, busy = time.monotonic(), time.process_time(), _cpu_busy()
    t0, busy0, own0 = _STAT["prev"]
    dt = now - t0
    if busy is None or busy0 is None or (dt < 0.05 and _STAT["load"] is None):
        try:
            return max(0.0, os.getloadavg()[0] - _own_load())
        except OSError:  # no load average on this platform
            return None
    if dt < 0.05:  # too short for the clock ticks: keep the last estimate
        return _STAT["load"]
    rate = max(0.0, (busy - busy0) - (own - own0)) / dt
    keep = float(np.exp(-dt / _OTHERS_TAU))
    old = _STAT["load"]
    _STAT["load"] = rate if old is None else old * keep + rate * (1.0 - keep)
    _STAT["prev"] = (now, busy, own)
    return _STAT["load"]


_OWN = {"t": time.monotonic(), "cpu": time.process_time(), "load": 0.0}


def _own_load():
    """This process's share of the 1-minute load average: its CPU use (all threads, cores)
    averaged like the kernel's load average (exponential decay, 60 s), updated per call
    from the CPU time since the previous call (the first since this module's import)."""
    now, cpu = time.monotonic(), time.process_time()
    dt = now - _OWN["t"]
    if dt > 0:
        keep = float(np.exp(-dt / 60.0))
        _OWN["load"] = _OWN["load"] * keep + (cpu - _OWN["cpu"]) / dt * (1.0 - keep)
        _OWN.update(t=now, cpu=cpu)
    return _OWN["load"]


class _Pardiso:
    """MKL PARDISO (real symmetric positive definite, ``mtype=2``) through ctypes.

    Called directly on pypardiso's MKL runtime (pypardiso's own wrapper passes float64 only,
    converts the indices to one-based on every call and cannot set threads): the upper
    triangle in CSR with zero-based indices (``iparm[34]``) converted once, an optional user
    permutation (the unknowns already numbered in a fill-reducing order: ``natural=True``
    skips PARDISO's own METIS), ``precision='single'`` for a float32 numeric factor
    (``iparm[27]``; answers then need refinement against the double matrix, see
    :meth:`Solver._solve_mixed`), and the threads chosen by :func:`_pardiso_threads` for the
    analysis and used by every later phase (factorisations and solves: MKL 2026.2 crashed
    when they differed; a new answer of the policy at a factorisation re-analyses). No
    refinement inside PARDISO.
    """

    name = "pardiso"

    def __init__(self, upper, precision="double", natural=False):
        self._lib = _mkl()
        n = self.n = upper.shape[0]
        self.precision = precision
        self._dtype = np.float32 if precision == "single" else np.float64
        self._pt = np.zeros(64, dtype=np.int64)
        ip = self._iparm = np.zeros(64, dtype=np.int32)
        ip[0] = 1  # iparm set here, zeros are defaults
        ip[1] = 2  # METIS nested dissection (unless a permutation is given)
        ip[4] = 1 if natural else 0  # perm holds the user's fill-reducing permutation
        ip[27] = 1 if precision == "single" else 0
        ip[34] = 1  # zero-based ia, ja
        self._ia = np.ascontiguousarray(upper.indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(upper.indices, dtype=np.int32)
        self._perm = np.arange(n, dtype=np.int32) if natural else np.zeros(n, dtype=np.int32)
        self._a = np.ascontiguousarray(upper.data, dtype=self._dtype)
        self._analyse(_pardiso_threads(n))

    def _analyse(self, threads):
        """Symbolic analysis for ``threads`` threads (every later phase must use as many:
        MKL 2026.2 crashed in the next numeric factorisation after an analysis or a solve
        with another thread count)."""
        if getattr(self, "threads", None) is not None:
            self._call(-1)  # release the previous analysis and factor
            self._pt[:] = 0
        self.threads = int(threads)
        self._call(11)

    def _call(self, phase, b=None):
        P = ctypes.c_void_p

        def i32(v):
            return ctypes.byref(ctypes.c_int32(v))

        if b is None:
            b = x = np.zeros(self.n, dtype=self._dtype)
        else:
            b = np.ascontiguousarray(b, dtype=self._dtype)
            x = np.empty_like(b)
        err = ctypes.c_int32(0)
        lib = self._lib
        previous = lib.MKL_Set_Num_Threads_Local(self.threads)  # this thread only
        try:
            lib.pardiso(self._pt.ctypes.data_as(P), i32(1), i32(1), i32(2), i32(phase),
                        i32(self.n), self._a.ctypes.data_as(P), self._ia.ctypes.data_as(P),
                        self._ja.ctypes.data_as(P), self._perm.ctypes.data_as(P), i32(1),
                        self._iparm.ctypes.data_as(P), i32(0), b.ctypes.data_as(P),
                        x.ctypes.data_as(P), ctypes.byref(err))
        finally:
            lib.MKL_Set_Num_Threads_Local(previous)
        if err.value == -4:
            raise _not_pd(f"PARDISO error -4, zero or negative pivot ({self.precision})")
        if err.value != 0:
            raise RuntimeError(f"PARDISO phase {phase} failed with error {err.value}")
        return x

    def factor(self, upper):
        self._a = np.ascontiguousarray(upper.data, dtype=self._dtype)
        threads = _pardiso_threads(self.n, current=self.threads)
        if threads != self.threads:  # the machine got busier or idler: plan again
            log.debug("PARDISO: %d -> %d threads (new analysis)", self.threads, threads)
            self._analyse(threads)
        self._call(22)

    def solve(self, b):
        if self._dtype == np.float64:
            return self._call(33, b)
        scale = float(np.abs(b).max())  # float32 range: solve for b / max|b|
        if scale == 0.0:
            return np.zeros(self.n)
        return self._call(33, b / scale).astype(np.float64) * scale

    def __del__(self):
        try:  # release PARDISO's memory (phase -1)
            self._call(-1)
        except Exception:  # noqa: BLE001 - interpreter shutdown, failed __init__
            pass


class _SuperLU:
    name = "superlu"

    def __init__(self, pattern):
        self._lu = None

    def factor(self, K):
        try:
            self._lu = spla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        except RuntimeError as err:
            raise _not_pd(err) from err

    def solve(self, b):
        return self._lu.solve(b)


def _not_pd(err):
    return np.linalg.LinAlgError(
        f"the reduced MTM stiffness is not positive definite ({err}): a part of the mesh may be "
        "held only through one edge or one vertex (a mechanism), or a material is indefinite"
    )


_BACKENDS = {"cholmod": _Cholmod, "pardiso": _Pardiso, "superlu": _SuperLU}


# ---------------------------------------------------------------------- helpers
#: below this many unknown nodes AMD orders the node graph, above it METIS (see _node_order)
_AMD_MAX_NODES = 30_000


def _node_order(indptr, indices, free, ordering="auto"):
    """Fill-reducing order of the nodes with unknowns, from an ordering of the node graph.

    ``indptr, indices`` is the node adjacency (block pattern), ``free`` the (3 n,) mask of
    unknown dofs, ``ordering`` ``'amd'``, ``'metis'``, ``'nesdis'`` or ``'auto'`` (AMD below
    ``_AMD_MAX_NODES`` nodes, METIS above). Returns the nodes with an unknown in elimination
    order and the ordering used, or ``None`` when CHOLMOD (which brings METIS) is not
    importable. Ordering the node graph (n nodes) instead of the
    dof graph (3 n rows, 9x the entries) costs a fraction of the time for the same fill: at
    30k tetrahedra METIS on the nodes + natural analysis of the dofs took 31 ms against 47 ms
    for METIS on the dofs, with 2.30M vs 2.27M entries in L. Below
    ``_AMD_MAX_NODES`` active nodes AMD orders the node graph instead: on a quiet machine
    (load < 1, same runs) 30k tetrahedra assembled + solved in 196-200 ms with AMD against
    210-232 ms with METIS, 50k in 390-397 ms against 429-444 ms (METIS costs ~25 ms at 30k
    and its smaller fill only pays on larger meshes: at 150k the two were equal,
    1.8-2.4 s each).
    """
    try:
        from sksparse.cholmod import analyze
    except ImportError:
        return None
    n = len(indptr) - 1
    fm = free.reshape(n, 3)
    active = np.flatnonzero(fm.any(axis=1))
    if active.size < 2:
        return None
    graph = sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n))
    sub = graph[active][:, active].tocsc()
    if ordering == "auto":
        ordering = "amd" if active.size < _AMD_MAX_NODES else "metis"
    return active[analyze(sub, mode="simplicial", ordering_method=ordering).P()], ordering


def _rigid_modes(points):
    """(3 n, 6) translations and small rotations about the centroid."""
    x = points - points.mean(axis=0)
    n = len(points)
    B = np.zeros((n, 3, 6))
    B[:, [0, 1, 2], [0, 1, 2]] = 1.0
    for k, w in enumerate(np.eye(3)):
        B[:, :, 3 + k] = np.cross(w, x)
    return B.reshape(3 * n, 6)


def _colour(indptr, indices, active, seed=0):
    """Vectorised Jones-Plassmann colouring of the node graph (only ``active`` nodes)."""
    n = len(indptr) - 1
    rng = np.random.default_rng(seed)
    weight = rng.random(n)
    colour = np.full(n, -1)
    colour[~active] = -2
    rows = np.repeat(np.arange(n), np.diff(indptr))
    off = rows != indices
    rows, cols = rows[off], indices[off]
    c = 0
    while np.any(colour == -1):
        todo = colour == -1
        w = np.where(todo, weight, -1.0)
        nb = np.full(n, -1.0)
        np.maximum.at(nb, rows, w[cols])
        pick = todo & (w > nb)
        colour[pick] = c
        c += 1
    return colour


#: pyamg smoothed aggregation for the MTM, chosen by measurement on the benchmark shell (CPU
#: seconds, one thread, CG to 1e-8; 150k / 1M tetrahedra, with all 6 rigid modes):
#: energy-minimising prolongation (degree 1, 2 iterations) instead of one Jacobi step
#: halves the CG iterations (59 vs 102 at 150k, 75 vs 152 at 1M) for a dearer setup (total
#: 29.5 s vs 38 s at 1M); no candidate improvement (saves 10 % of the setup for 10 % more
#: iterations); one forward Gauss-Seidel sweep before and one backward after the coarse
#: correction instead of a symmetric sweep on each side (same symmetric preconditioner, 25 %
#: cheaper cycles, 1.4x the iterations). Chebyshev smoothing needed 7x the iterations and a
#: strength threshold 0.1 made the hierarchy 8x denser.
#: near-null space of the AMG: the first 3 rigid modes (translations) or all 6 (+ rotations).
#: Translations only halve the coarse levels (operator complexity 1.33 vs 2.31) for 1.65x the
#: iterations: 1M tetrahedra, same session, CPU: setup 8.1 s + CG 16.9 s (124 it) = 25.0 s and
#: 2.15 GB against 16 s + 13.5 s (75 it) = 29.5 s and 2.73 GB with 6 modes; 150k: 2.8 s vs
#: 3.6 s. The MTM soft tissue is held on the bone side, so bending (the rotations) is not its
#: slow mode; the tests at nu 0.4999 and E ratio 1000 still converge.
_AMG_NEAR_NULL = 3
_AMG_OPTIONS = dict(
    symmetry="symmetric",
    improve_candidates=None,
    smooth=("energy", {"degree": 1, "maxiter": 2}),
    presmoother=("gauss_seidel", {"sweep": "forward"}),
    postsmoother=("gauss_seidel", {"sweep": "backward"}),
)


class _VCycle(spla.LinearOperator):
    """One V-cycle of a pyamg hierarchy as a preconditioner, from a zero initial guess.

    ``MultilevelSolver.aspreconditioner`` runs ``solve(maxiter=1)``, which also computes
    ``||b - A x||`` before and after the cycle: two extra products with the fine matrix per
    CG iteration (12-15 % of the time). This is the same cycle without them.
    """

    def __init__(self, ml):
        A = ml.levels[0].A
        super().__init__(dtype=A.dtype, shape=A.shape)
        self.ml = ml

    def _cycle(self, lvl, b):
        levels = self.ml.levels
        level = levels[lvl]
        x = np.zeros_like(b)
        level.presmoother(level.A, x, b)
        coarse_b = level.R @ (b - level.A @ x)
        if lvl == len(levels) - 2:
            coarse_x = self.ml.coarse_solver(levels[-1].A, coarse_b)
        else:
            coarse_x = self._cycle(lvl + 1, coarse_b)
        x += level.P @ coarse_x
        level.postsmoother(level.A, x, b)
        return x

    def _matvec(self, b):
        b = np.ravel(b)
        if len(self.ml.levels) == 1:
            return self.ml.coarse_solver(self.ml.levels[0].A, b)
        return self._cycle(0, b)


class _SymmetricFromTriangle(spla.LinearOperator):
    """``K_ff`` from one stored triangle: ``K y = L y + L^T y - diag(L) y``.

    ``data, indices, indptr`` are the upper triangle in CSR, which is also the lower
    triangle in CSC (:attr:`lower` for CHOLMOD, :attr:`upper` for PARDISO share the arrays).
    A product costs the same as one with the full matrix, which is then neither built nor
    updated (half the values to write per new material).
    """

    def __init__(self, data, indices, indptr, n):
        super().__init__(dtype=np.float64, shape=(n, n))
        self.lower = sp.csc_matrix((data, indices, indptr), shape=(n, n))
        self.upper = sp.csr_matrix((data, indices, indptr), shape=(n, n))
        # the diagonal is the first stored entry of each row of the upper triangle
        self._diag = data[indptr[:-1]] if n else np.zeros(0)

    def _matvec(self, y):
        y = np.ravel(y)
        return self.upper @ y + self.lower @ y - self._diag * y

    def _adjoint(self):
        return self

    def diagonal(self):
        return self._diag.copy()

    def toarray(self):
        return (self.upper + self.lower).toarray() - np.diag(self._diag)


class _Progress:
    def __init__(self, enabled, total, desc):
        self.bar = None
        if enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc=desc)
            except ImportError:
                log.info("progress_bar=True needs tqdm; logging progress instead")

    def update(self, k):
        if self.bar is not None:
            self.bar.update(k)

    def close(self):
        if self.bar is not None:
            self.bar.close()


# ---------------------------------------------------------------------- the solver
class Solver:
    """Reusable MTM solver for one mesh and one set of boundary-condition types.

    Keeps the geometry, the block sparsity pattern, the elimination maps and the symbolic
    factorisation (``direct``); :meth:`update_materials` re-assembles and refactors
    numerically only, and :meth:`solve` accepts new prescribed displacements without any
    refactorisation.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with materials (cell ``E_fiber``, ``nu``, optional ``E_cross``,
        ``fiber``) and boundary conditions (point ``bc``, ``bc_displacement``, ``bc_normal``).
    method : {'direct', 'cg', 'relaxation', 'gpu', 'auto'}
        ``auto``: ``direct`` up to :data:`AUTO_DIRECT_MAX_POINTS` points, else ``cg``.
    tol : float
        Relative residual ``||K_ff y - b|| / ||b||`` to reach (iterative methods) or to check
        (``direct``, which raises :class:`ConvergenceError` above it after refinement).
    backend : {'cholmod', 'pardiso', 'superlu'}, optional
        Direct backend; default the first of :func:`direct_backends`, and then, at the
        first :meth:`update_materials` that refactors (a sweep), PARDISO with a
        mixed-precision factor when pypardiso is importable and the system has at least
        2000 unknowns (:attr:`backend_name` says which is in use).
    precision : {'auto', 'double', 'mixed'}
        Numeric factor of the PARDISO backend: ``mixed`` (and ``auto``) factor in single
        precision and refine in double to round-off (:meth:`_solve_mixed`), falling back to
        a double factor when that stalls; ``double`` always factors in double. CHOLMOD and
        SuperLU factor in double (``mixed`` needs ``backend='pardiso'``).
        ``info['precision']`` is ``'mixed'``, ``'double'`` or ``'double (mixed stalled)'``.
    maxiter : int, optional
        Iteration cap (default 2000 for cg/gpu, 20000 sweeps for relaxation).
    preconditioner : {'amg', 'jacobi'}, optional
        For ``cg``; default AMG when pyamg imports.
    omega : float
        Over-relaxation factor of ``relaxation`` (1 = Gauss-Seidel).
    warn_lost_digits : float
        ``direct`` warns (:class:`IllConditionedWarning`) when the estimated number of lost
        significant digits reaches this.
    progress_bar : bool
        Show a tqdm bar for iterative methods (when tqdm is installed).
    ordering : {'auto', 'amd', 'metis', 'nesdis'}
        Fill-reducing ordering of the node graph for the CHOLMOD and PARDISO backends (the
        latter gets it as its permutation; needs scikit-sparse, else PARDISO orders with
        its own METIS; the one used is :attr:`node_ordering`). ``auto``: AMD below 30k nodes with
        unknowns, METIS above (cheapest for one solve), and METIS from the first
        :meth:`update_materials` that refactors (a sweep: METIS costs ~20 ms more once at
        30k tetrahedra and a third fewer flops in every numeric factorisation).
    E_fiber, E_cross, nu, fiber : optional
        Override the grid's materials (scalars or per-cell arrays).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(5, 5, 5)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.46)
    >>> z = grid.points[:, 2]
    >>> grid.point_data[arrays.BC] = np.where((z == 0) | (z == 4), arrays.BC_JOINT,
    ...                                       arrays.BC_FREE).astype(np.int8)
    >>> d = np.zeros((grid.n_points, 3)); d[z == 4, 2] = -0.4
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = d
    >>> solver = pvcmf.mtm.Solver(grid)
    >>> u = solver.solve()
    >>> solver.update_materials(nu=0.3)      # numeric refactorisation only
    >>> u2 = solver.solve()
    >>> bool(np.allclose(u[z == 4], d[z == 4]))
    True
    """

    def __init__(self, grid, method="direct", *, tol=1e-10, backend=None, maxiter=None,
                 preconditioner=None, omega=1.0, warn_lost_digits=8.0, progress_bar=False,
                 ordering="auto", precision="auto", E_fiber=None, E_cross=None, nu=None,
                 fiber=None):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if method == "auto":
            method = "direct" if grid.n_points <= AUTO_DIRECT_MAX_POINTS else "cg"
        tol = float(tol)
        if not 0 < tol < 1:
            raise ValueError(f"tol must be in (0, 1), got {tol}")
        if method == "gpu" and not gpu_available():
            raise RuntimeError(
                "method='gpu' needs CuPy and a CUDA device, and none was found; "
                "use method='direct' or 'cg'"
            )
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self._auto_backend = method == "direct" and backend is None
        if method == "direct":
            names = direct_backends()
            backend = names[0] if backend is None else backend
            if backend not in _BACKENDS:
                raise ValueError(f"backend must be one of {sorted(_BACKENDS)}, got {backend!r}")
            if backend not in names:
                raise ValueError(f"backend {backend!r} is not importable here; available: {names}")
        elif backend is not None:
            raise ValueError(f"backend applies to method='direct' only, got method={method!r}")
        if precision == "mixed" and backend != "pardiso":
            raise ValueError(
                f"precision='mixed' needs method='direct' with backend='pardiso' (a single-"
                f"precision factor), got method={method!r}, backend={backend!r}"
            )
        self.precision = precision
        self._mixed_stalled = False
        if ordering not in ORDERINGS:
            raise ValueError(f"ordering must be one of {ORDERINGS}, got {ordering!r}")
        self.ordering = ordering
        if preconditioner not in (None, "amg", "jacobi"):
            raise ValueError(f"preconditioner must be 'amg' or 'jacobi', got {preconditioner!r}")
        self.method, self.tol, self.backend_name = method, tol, backend
        self.maxiter = maxiter
        self.preconditioner = preconditioner
        self.omega = float(omega)
        self.warn_lost_digits = float(warn_lost_digits)
        self.progress_bar = progress_bar
        self.grid = grid
        t0 = time.perf_counter()
        self.points, cells = tetrahedra(grid)
        self.assembler = asm = Assembler(self.points, cells)
        self.constraints = cons = Constraints(grid, used=asm.used)
        cons.check_rigid_modes(self.points, asm.indptr, asm.indices)
        if np.any(~asm.used):
            log.warning("%d point(s) belong to no tetrahedron; they keep their prescribed "
                        "displacement (0 if free)", int(np.sum(~asm.used)))
        self.materials = grid_materials(grid, E_fiber=E_fiber, E_cross=E_cross, nu=nu, fiber=fiber)
        self._build_maps()
        self.timings = {"setup": time.perf_counter() - t0}
        self._backend = None
        self._assemble_and_factor()

    # ------------------------------------------------------------------ structure
    def _build_maps(self, ordering=None):
        """Where each entry of ``K_ff``, ``K_fp`` (and the factored triangle) sits in the blocks.

        The unknowns are numbered node by node in elimination order (CHOLMOD: the node-graph
        ordering; otherwise the natural order). The block pattern is permuted to that node
        order once (a sort of the blocks, 9x fewer than the entries); every dof row then lists
        its blocks' entries already sorted, so the dof-level maps are built with no sort.
        """
        asm, cons = self.assembler, self.constraints
        n = asm.n_points
        free = cons.free.reshape(n, 3)
        self._ordering, self.node_ordering = "default", None
        nodes = None
        if self._triangular:  # CHOLMOD, PARDISO
            found = _node_order(asm.indptr, asm.indices, cons.free,
                                self.ordering if ordering is None else ordering)
            if found is not None:  # the unknowns numbered in elimination order
                nodes, self.node_ordering = found
                self._ordering = "natural"
        if nodes is None:
            rank = np.arange(n)
            node_of = rank
            bptr, bpos = asm.indptr.astype(np.int64), np.arange(asm.nnzb)
        else:
            rest = np.ones(n, dtype=bool)
            rest[nodes] = False
            node_of = np.concatenate([nodes, np.flatnonzero(rest)])
            rank = np.empty(n, dtype=np.int64)
            rank[node_of] = np.arange(n)
            bptr, _, bpos = _merge_pairs(rank[asm.rows], rank[asm.indices], n)
            order = np.empty_like(bpos)
            order[bpos] = np.arange(bpos.size)
            bpos = order  # the blocks sorted by (rank of row, rank of column)
        dof_of = (3 * node_of[:, None] + np.arange(3)).ravel()  # dofs in rank order
        fr = free.ravel()[dof_of]
        self.F = dof_of[fr]
        self.P = dof_of[~fr]
        pos = np.full(3 * n, -1, dtype=np.int64)  # position in F (>= 0) or in P (< 0: -1 - k)
        pos[self.F] = np.arange(self.F.size)
        pos[self.P] = -1 - np.arange(self.P.size)
        # the entries of dof row (rank r, i): block k of block row r, then j = 0..2
        seg = np.repeat(np.diff(bptr), 3)[fr]  # blocks per row of an unknown, in rank order
        starts = np.repeat(bptr[:-1], 3)[fr]
        first = np.cumsum(seg) - seg
        blk = bpos[np.repeat(starts - first, seg) + np.arange(seg.sum())]  # (row, block) pairs
        comp = np.repeat(np.tile(np.arange(3), n)[fr], seg)
        itype = np.int32 if 9 * asm.nnzb < 2**31 else np.int64
        j = np.arange(3, dtype=itype)
        where = ((9 * blk.astype(itype) + 3 * comp.astype(itype))[:, None] + j).ravel()
        col = pos.astype(np.int32)[(3 * asm.indices[blk].astype(itype))[:, None] + j].ravel()
        nrow = self.F.size
        row_end = np.cumsum(3 * seg)

        def parts(mask, cols):
            ptr = np.zeros(nrow + 1, dtype=np.int32)
            if nrow:
                ptr[1:] = np.cumsum(mask, dtype=np.int32)[row_end - 1]
            return ptr, cols[mask], where[mask]

        isf = col >= 0
        self._fp = parts(~isf, -1 - col)
        if self._triangular:
            # the upper triangle in CSR is also the lower triangle in CSC (K is symmetric):
            # PARDISO reads the former, CHOLMOD the latter, neither needs a conversion
            row = np.repeat(np.arange(nrow, dtype=np.int32), 3 * seg)
            self._ffu = parts(col >= row, col)  # prescribed columns (< 0) drop out too
        else:
            self._ff = parts(isf, col)
        log.debug("MTM system: %d unknowns of %d dofs", nrow, 3 * n)

    # ------------------------------------------------------------------ materials
    def update_materials(self, *, E_fiber=None, E_cross=None, nu=None, fiber=None,
                         refactor=True):
        """Re-assemble with new materials and refactor numerically (symbolic analysis kept).

        Each argument is a scalar or a per-cell array; omitted ones keep their value.

        With ``refactor=True`` the first call switches a CHOLMOD solver whose backend the
        user did not choose to PARDISO with a mixed-precision factor (when pypardiso is
        importable and there are at least 2000 unknowns): every value of a sweep is then a
        numeric refactorisation at about half the cost (one PARDISO analysis once).

        ``refactor=False`` (``direct`` only) keeps the previous numeric factorisation and
        makes the next :meth:`solve` a conjugate gradient preconditioned by it (a few
        triangular solves when the materials changed little, e.g. the next value of a
        Poisson sweep); when that needs more than ``max_reuse_iterations`` (30) iterations
        the solve refactors and answers directly, and when it cost more than half a
        factorisation the next update refactors. The answer meets ``tol`` either way.
        """
        ef, ec, nu_, a = self.materials
        m = self.assembler.n_cells

        def pick(new, old):
            if new is None:
                return old
            v = np.asarray(new, dtype=float)
            if v.ndim == 0:
                return np.full(m, float(v))
            if v.shape != (m,):
                raise ValueError(f"material arrays must be scalars or have shape ({m},), got {v.shape}")
            return v.copy()

        ef2 = pick(E_fiber, ef)
        ec2 = ef2 if (E_cross is None and E_fiber is not None and np.array_equal(ec, ef)) \
            else pick(E_cross, ec)
        nu2 = pick(nu, nu_)
        if fiber is not None:
            a = np.broadcast_to(np.asarray(fiber, dtype=float), (m, 3)).copy()
            nrm = np.linalg.norm(a, axis=1)
            a[nrm > 0] /= nrm[nrm > 0, None]
        missing = (ef2 != ec2) & ~(np.linalg.norm(a, axis=1) > 0)
        if np.any(missing):
            raise ValueError(
                f"fiber must be a nonzero vector where E_fiber != E_cross; {int(missing.sum())} "
                f"cell(s) have none, e.g. cell {int(np.flatnonzero(missing)[0])}"
            )
        from .materials import check_positive_definite

        check_positive_definite(ef2, ec2, nu2)
        self.materials = (ef2, ec2, nu2, a)
        if refactor and self._switch_to_pardiso():
            self._backend, self._groups = None, None
        if refactor and self.ordering == "auto" and self.node_ordering == "amd":
            # refactoring for new materials: a sweep. METIS costs ~20 ms more once (30k
            # tetrahedra) and a third fewer flops in every factorisation from now on
            t = time.perf_counter()
            self._build_maps(ordering="metis")
            self._backend, self._groups = None, None
            log.debug("sweep: node ordering AMD -> METIS (%.3f s)", time.perf_counter() - t)
        self._assemble_and_factor(refactor=refactor or self.method != "direct")

    def _assemble_and_factor(self, refactor=True):
        asm, cons = self.assembler, self.constraints
        t0 = time.perf_counter()
        vals = self._group_values() if hasattr(self, "_vals") else None
        if vals is None:
            ef, ec, nu, a = self.materials
            # the first assembly scatters directly; re-assemblies (sweeps) use the linear map
            assemble = asm.linear_upper_blocks if hasattr(self, "_vals") else asm.upper_blocks
            data = asm.full_blocks(assemble(ef, ec, nu, a))
            cons.rotate_blocks(data, asm.rows, asm.indices)
            self._data = data
            flat = data.reshape(-1)
            tri = self._triangular
            vals = {"fp": flat[self._fp[2]], "ff": flat[(self._ffu if tri else self._ff)[2]]}
        self._vals = vals
        self._set_matrices(vals)
        nf = self.F.size
        t1 = time.perf_counter()
        self.timings["assembly"] = t1 - t0
        self._stale = (bool(nf) and not refactor and self._backend is not None
                       and not getattr(self, "_refactor_next", False)
                       and self._reuse_pays())
        if nf and not self._stale:
            threads = (_factor_threads(nf) if self.method == "direct"
                       else _single_threaded_blas())
            with threads:
                getattr(self, f"_setup_{self.method}")()
            self._factored_moduli = self._moduli()
            self._refactor_next = False
            self._t_factor = time.perf_counter() - t1
        self.timings["factor"] = time.perf_counter() - t1
        log.debug("assembly %.3f s, factor/setup %.3f s", t1 - t0, self.timings["factor"])

    @property
    def _triangular(self):
        """Whether only the triangle of ``K_ff`` is kept (CHOLMOD, PARDISO)."""
        return self.method == "direct" and self.backend_name in ("cholmod", "pardiso")

    def _set_matrices(self, vals):
        nf, npres = self.F.size, self.P.size
        self.K_fp = sp.csr_matrix((vals["fp"], *self._fp[1::-1]), shape=(nf, npres))
        if self._triangular:
            indptr, indices, _ = self._ffu
            # CSR of the upper triangle == CSC of the lower one (K is symmetric)
            self.K_ff = _SymmetricFromTriangle(vals["ff"], indices, indptr, nf)
        else:
            self.K_ff = sp.csr_matrix((vals["ff"], *self._ff[1::-1]), shape=(nf, nf))

    def _direct_matrix(self):
        """The matrix the direct backend reads, without a format conversion."""
        ff = self._vals["ff"]
        if self.backend_name == "pardiso":
            return self.K_ff.upper
        if self.backend_name == "cholmod":
            return self.K_ff.lower
        indptr, indices, _ = self._ff  # K_ff's CSR arrays read as CSC (K_ff is symmetric)
        return sp.csc_matrix((ff, indices, indptr), shape=self.K_ff.shape)

    #: :meth:`update_materials` combines cached per-material matrices when the cells carry at
    #: most this many distinct materials (tables: fat and muscle), else it re-assembles
    max_material_groups = 8

    def _group_values(self):
        """``K_ff`` triangle and ``K_fp`` values for piecewise-constant materials, or None.

        The blocks are linear in each cell's coefficients ``(lambda, mu_T, alpha,
        mu_L - mu_T, beta)``, so with the cells grouped by material (``g``) the values the
        backend reads are ``sum_g sum_c coef_gc B_gc``: the ``B_gc`` (assembled, rotated at
        sliding nodes and gathered into the eliminated system once per grouping, fibres and
        constraints) turn a sweep's re-assembly into one small dense product instead of a
        sparse product, a symmetric copy, rotations and gathers (at 30k tetrahedra with two
        materials about 3 ms instead of 17 ms). Only for the direct CHOLMOD / PARDISO
        backends (which read the triangle) up to ``_LINEAR_CELLS`` cells; None (re-assemble)
        otherwise or when the materials have more than :attr:`max_material_groups` values.
        """
        from .assembly import _LINEAR_CELLS
        from .materials import elastic_coefficients

        asm = self.assembler
        if not self._triangular or asm.n_cells > _LINEAR_CELLS or not self.F.size:
            return None
        ef, ec, nu, a = self.materials
        ani = np.flatnonzero(ef != ec)
        g = getattr(self, "_groups", None)
        if g is not None:
            label, rep = g["label"], g["rep"]
            if not (np.array_equal(ani, g["ani"]) and np.array_equal(a[ani], g["fiber"])
                    and all(np.array_equal(x, x[rep][label]) for x in (ef, ec, nu))):
                g = None
        if g is None:
            table = np.stack([ef, ec, nu], axis=1)
            # per-cell materials (e.g. mixed by muscle fraction) show in a sample of the cells
            # at once: skip the full np.unique (22 ms at 30k) for them
            sample = table[:: max(1, len(table) // 256)]
            if len(np.unique(sample, axis=0)) > self.max_material_groups:
                self._groups = None
                return None
            mats, rep, label = np.unique(table, axis=0, return_index=True, return_inverse=True)
            if len(mats) > self.max_material_groups:
                self._groups = None
                return None
            g = self._groups = self._group_basis(label.ravel(), rep, ani, a[ani])
        lam, muT, alpha, muL, beta = elastic_coefficients(ef[g["rep"]], ec[g["rep"]],
                                                          nu[g["rep"]])
        coef = np.stack([lam, muT, alpha, muL - muT, beta])[g["kind"], g["group"]]
        # einsum, not BLAS: a threaded dgemv here leaves numpy's BLAS threads spinning on the
        # second core while CHOLMOD factorises (measured: 40 % slower factorisations under load)
        vals = np.einsum("vk,k->v", g["basis"], coef)
        ntri = self._ffu[2].size
        return {"ff": vals[:ntri], "fp": vals[ntri:]}

    def _group_basis(self, label, rep, ani, fiber):
        t = time.perf_counter()
        asm, cons = self.assembler, self.constraints
        U, group, kind = asm.group_upper_blocks(label, len(rep), ani, fiber)
        K = len(group)
        blocks = np.ascontiguousarray(U.transpose(2, 1, 0)).reshape(asm.n_upper, 3, 3, K)
        full = np.empty((asm.nnzb, 3, 3, K))
        full[asm._upper_pos] = blocks
        full[asm._lower_pos] = np.swapaxes(blocks[asm._off], 1, 2)
        for k in range(K):
            cons.rotate_blocks(full[..., k], asm.rows, asm.indices)
        flat = full.reshape(-1, K)
        basis = np.concatenate([flat[self._ffu[2]], flat[self._fp[2]]])  # (values, K)
        log.debug("material-group basis: %d groups, %d matrices, %.3f s", len(rep), len(group),
                  time.perf_counter() - t)
        return {"label": label, "rep": rep, "ani": ani, "fiber": np.array(fiber),
                "group": np.array(group), "kind": np.array(kind), "basis": basis}

    @property
    def _factor_precision(self):
        """'single' or 'double': the PARDISO numeric factor of the current materials."""
        return "double" if self.precision == "double" or self._mixed_stalled else "single"

    _switched = False

    def _switch_to_pardiso(self):
        """At the first refactoring update of a CHOLMOD solver whose backend was not chosen
        by the user: switch to PARDISO with a mixed-precision factor (a sweep; see
        :meth:`update_materials`). Returns whether it switched."""
        if not (self._auto_backend and self.backend_name == "cholmod" and not self._switched
                and self.F.size >= _SWEEP_PARDISO_MIN and "pardiso" in direct_backends()):
            return False
        self.backend_name, self._switched = "pardiso", True
        log.debug("sweep: direct backend CHOLMOD -> PARDISO (%s precision)",
                  self._factor_precision)
        return True

    def _setup_direct(self):
        A = self._direct_matrix()
        if self._backend is None:
            t = time.perf_counter()
            if self.backend_name == "pardiso":
                self._backend = _Pardiso(A, self._factor_precision,
                                         natural=self._ordering == "natural")
            elif self.backend_name == "cholmod":
                self._backend = _Cholmod(A, ordering=self._ordering)
            else:
                self._backend = _SuperLU(A)
            self.timings["analysis"] = time.perf_counter() - t
        try:
            self._backend.factor(A)
        except np.linalg.LinAlgError:
            if getattr(self._backend, "precision", "double") != "single":
                raise
            # positive definite in double but not in single precision (cond(K) >~ 1e7)
            log.info("mixed precision: the single-precision factor broke down (not positive "
                     "definite in float32): refactoring in double")
            self._mixed_stalled, self._backend = True, None
            self._setup_direct()

    def _setup_cg(self):
        use_amg = self.preconditioner == "amg"
        if self.preconditioner is None:
            try:
                import pyamg  # noqa: F401

                use_amg = True
            except ImportError:
                use_amg = False
        if use_amg:
            import pyamg

            modes = _rigid_modes(self.points)[:, :_AMG_NEAR_NULL]
            B = np.stack([self.constraints.to_local(c.reshape(-1, 3)) for c in modes.T],
                         axis=1)[self.F]
            self._ml = pyamg.smoothed_aggregation_solver(self.K_ff, B=B, **_AMG_OPTIONS)
            self._M = _VCycle(self._ml)
            self._prec_name = "amg"
        else:
            dinv = self._masked_diag_inverse()
            n = self.assembler.n_points
            D = sp.bsr_matrix((dinv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()
            self._M = D[self.F][:, self.F]
            self._prec_name = "jacobi"

    def _setup_gpu(self):
        import cupyx.scipy.sparse as csp

        self._gpu_K = csp.csr_matrix(self.K_ff)
        self._gpu_dinv = 1.0 / self.K_ff.diagonal()

    def _masked_diag_inverse(self):
        """Inverses of the node blocks of K (local frame), identity-scaled on prescribed dofs."""
        asm = self.assembler
        n = asm.n_points
        diag_pos = np.flatnonzero(asm.rows == asm.indices)
        D = np.zeros((n, 3, 3))
        D[asm.rows[diag_pos]] = self._data[diag_pos]
        fm = self.constraints.free.reshape(n, 3)
        D *= fm[:, :, None] & fm[:, None, :]
        scale = np.where(fm, 0.0, np.maximum(np.abs(np.trace(D, axis1=1, axis2=2)) / 3, 1.0)[:, None])
        scale[~asm.used] = 1.0
        D[:, [0, 1, 2], [0, 1, 2]] += scale
        return np.linalg.inv(D)

    def _setup_relaxation(self):
        asm, cons = self.assembler, self.constraints
        n = asm.n_points
        fm = cons.free.reshape(n, 3)
        A = self._data * (fm[asm.rows][:, :, None] & fm[asm.indices][:, None, :])
        A = asm.bsr(A).tocsr()
        self._A = A
        self._dinv = self._masked_diag_inverse()
        if not hasattr(self, "_colours"):
            active = asm.used & fm.any(axis=1)
            colour = _colour(asm.indptr, asm.indices, active)
            self._colours = [np.flatnonzero(colour == c) for c in range(colour.max() + 1)]
            log.debug("relaxation: %d colours", len(self._colours))
        self._rows = []
        for nodes in self._colours:
            r = (3 * nodes[:, None] + np.arange(3)).ravel()
            self._rows.append((nodes, r, A[r]))

    # ------------------------------------------------------------------ solve
    def solve(self, bc_displacement=None, *, x0=None):
        """Solve for the displacement of every point, shape ``(n, 3)``.

        Parameters
        ----------
        bc_displacement : (n, 3) array, optional
            New prescribed displacements (same ``bc`` codes and normals); no refactorisation.
        x0 : (n, 3) array, optional
            Initial guess for ``cg``, ``gpu`` and ``relaxation`` (warm start).

        Returns
        -------
        numpy.ndarray (n, 3)
            Also sets :attr:`info` (method, backend, residual, iterations, times, error estimate).
        """
        cons = self.constraints
        if bc_displacement is not None:
            cons.set_displacement(bc_displacement)
        t0 = time.perf_counter()
        yp = cons.prescribed[self.P]
        b = -(self.K_fp @ yp)
        nb = _norm(b)
        info = {"method": self.method, "backend": self.backend_name or "", "iterations": 0,
                "error_estimate": np.nan, "lost_digits": np.nan}
        if self.F.size == 0 or nb == 0:
            y = np.zeros(self.F.size)
            info["residual"] = 0.0
        else:
            y0 = None
            if x0 is not None:
                x0 = np.asarray(x0, dtype=float)
                if x0.shape != (cons.n_points, 3):
                    raise ValueError(f"x0 must have shape ({cons.n_points}, 3), got {x0.shape}")
                y0 = cons.to_local(x0)[self.F]
            with _single_threaded_blas():
                y = getattr(self, f"_solve_{self.method}")(b, nb, y0, info)
        if not np.all(np.isfinite(y)):
            raise ConvergenceError(f"method={self.method!r} produced non-finite values")
        full = cons.prescribed.copy()
        full[self.F] = y
        u = cons.to_global(full)
        self.timings["solve"] = time.perf_counter() - t0
        info["assembly_time"] = self.timings["assembly"]
        info["factor_time"] = self.timings["factor"]
        info["solve_time"] = self.timings["solve"]
        info["time"] = info["assembly_time"] + info["factor_time"] + info["solve_time"]
        self.info = info
        return u

    def _residual(self, y, b, nb):
        return float(_norm(b - self.K_ff @ y) / nb)

    #: a stale-factor CG solve gives up (and refactors) after this many iterations
    max_reuse_iterations = 30
    #: also weigh the measured cost of an iteration against a factorisation (set False for a
    #: decision that depends on the materials only, e.g. in tests)
    adaptive_reuse = True

    def _moduli(self):
        """Per-cell moduli ``(mu_T, mu_L, lambda + 2 mu_T / 3)`` of the current materials."""
        from .materials import elastic_coefficients

        lam, muT, _, muL, _ = elastic_coefficients(*self.materials[:3])
        return np.stack([muT, muL, lam + 2.0 * muT / 3.0])

    def _reuse_pays(self):
        """Whether CG preconditioned by the current factor is predicted to beat refactoring.

        For an isotropic cell the energy ``lambda tr(e)^2 + 2 mu e:e`` (with
        ``0 <= tr(e)^2 <= 3 e:e``) changes by a factor between the ratios of the shear
        moduli and of the bulk moduli ``lambda + 2 mu / 3``, so the condition number of the
        preconditioned system is at most ``kappa = max ratio / min ratio`` over cells (used as
        an estimate for the fibre terms) and CG needs about
        ``ln(2 / tol) / ln((sqrt(kappa) + 1) / (sqrt(kappa) - 1))`` iterations. Reuse when that
        many iterations (timed: one triangular solve pair and one product) cost less than the last numeric
        factorisation. A nu 0.46 -> 0 change predicts thousands (refactor at once), one step
        of 0.026 in a Poisson sweep 8-17 (reuse).
        """
        old = getattr(self, "_factored_moduli", None)
        if old is None:
            return True  # nothing to compare with: try, the solve falls back when it stalls
        new = self._moduli()
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(old > 0, new / old, np.inf)
        kappa = float(ratio.max() / ratio.min()) if ratio.min() > 0 else np.inf
        if not np.isfinite(kappa):
            return False
        root = np.sqrt(max(kappa, 1.0 + 1e-12))
        iterations = np.log(2.0 / self.tol) / np.log((root + 1.0) / (root - 1.0))
        t_iter, t_factor = getattr(self, "_t_iter", None), getattr(self, "_t_factor", None)
        timed = self.adaptive_reuse and t_iter and t_factor
        cheaper = iterations * t_iter < t_factor if timed else True
        return iterations <= self.max_reuse_iterations and cheaper

    def _solve_stale(self, b, nb, info):
        """CG preconditioned by the factorisation of earlier materials; None if too slow.

        Each iteration costs one pair of triangular solves and one product with ``K_ff``
        (at 30k tetrahedra about 3.5 ms against 100 ms for a numeric factorisation). When
        this solve spent more than half a factorisation, the next :meth:`update_materials`
        refactors: the materials drift away from the factored ones along a sweep, so the
        iteration count only grows (measured at 30k: 9 iterations one Poisson step of 0.026
        away, 40 iterations from nu 0.46 to 0).
        """
        t0 = time.perf_counter()
        n = self.K_ff.shape[0]
        M = spla.LinearOperator((n, n), matvec=self._backend.solve, dtype=float)
        count = [0]

        def cb(_):
            count[0] += 1

        y, flag = spla.cg(self.K_ff, b, x0=self._backend.solve(b), rtol=self.tol, atol=0.0,
                          maxiter=self.max_reuse_iterations, M=M, callback=cb)
        res = self._residual(y, b, nb)
        elapsed = time.perf_counter() - t0
        self._t_iter = elapsed / (count[0] + 1)
        if self.adaptive_reuse and elapsed > 0.5 * getattr(self, "_t_factor", np.inf):
            self._refactor_next = True
        if flag != 0 or not res <= self.tol:
            return None
        info.update(residual=res, iterations=count[0], reused_factor=True)
        return y

    #: mixed precision: CG iterations preconditioned by the single-precision factor before
    #: it falls back to a double factor (stalls: nu -> 0.5, large stiffness ratios)
    max_mixed_iterations = 25
    #: mixed precision: above this estimated error of a single-precision solve (about
    #: ``cond(K) * eps32``, i.e. 5 digits lost) the estimate saturates (it cannot see the 8
    #: digits that warn), so the solver refactors in double to estimate from a double solve
    max_mixed_error = 1e-2

    def _solve_mixed(self, b, nb, info):
        """Solve with the single-precision factor, refined in double; None if stalled.

        A single-precision solve, then conjugate gradient on the double ``K_ff``
        preconditioned by the single factor, to a relative residual of
        :data:`_MIXED_TARGET` (what a double factor plus one refinement step reaches; a
        1e-10 residual alone left 1e-7 relative error at nu 0.4999), stopping early once
        the residual is below ``tol`` and no longer halves. The first correction estimates
        the forward error of one single-precision solve (about ``cond(K) * eps32``); each
        iteration divides the residual by about that much. Returns ``(None, err32)`` when
        ``tol`` is not reached in :attr:`max_mixed_iterations` or when ``err32`` exceeds
        :attr:`max_mixed_error` (the caller refactors in double).
        """
        solve32, K = self._backend.solve, self.K_ff
        y = solve32(b)
        r = b - K @ y
        z = solve32(r)
        ny = _norm(y)
        err32 = _norm(z) / ny if ny > 0 else 0.0
        if err32 > self.max_mixed_error:
            log.info("mixed precision: the single-precision factor's error %.1e estimates more "
                     "than %.0f lost digits: refactoring in double for a reliable estimate",
                     err32, np.log10(max(self.max_mixed_error, _EPS32) / _EPS32))
            return None, err32
        target = min(self.tol, _MIXED_TARGET)
        p, rz = z, float(np.dot(r, z))
        res = _norm(r) / nb
        steps = 0
        while res > target and steps < self.max_mixed_iterations and np.isfinite(res):
            Kp = K @ p
            alpha = rz / float(np.dot(p, Kp))
            y = y + alpha * p
            r = r - alpha * Kp
            steps += 1
            previous, res = res, _norm(r) / nb
            if res <= self.tol and res > 0.5 * previous:
                break  # converged to tol and stagnating near round-off
            z = solve32(r)
            rz, rz_old = float(np.dot(r, z)), rz
            p = z + (rz / rz_old) * p
        res = self._residual(y, b, nb)  # the true residual, not the recurrence
        if not (np.isfinite(res) and res <= self.tol):
            log.info("mixed precision stalled (relative residual %.1e after %d CG iterations, "
                     "estimated single-precision error %.1e): refactoring in double",
                     res, steps, err32)
            return None, err32
        return (y, res, steps), err32

    def _solve_direct(self, b, nb, y0, info):
        if self._stale:
            y = self._solve_stale(b, nb, info)
            if y is not None:
                return y
            t = time.perf_counter()
            with _factor_threads(self.F.size):
                self._setup_direct()
            self._stale = self._refactor_next = False
            self._t_factor = time.perf_counter() - t
            self._factored_moduli = self._moduli()
            self.timings["factor"] += self._t_factor
        info["precision"] = self._factor_precision if self.backend_name == "pardiso" else "double"
        if info["precision"] == "single":
            t0 = time.perf_counter()
            found, err32 = self._solve_mixed(b, nb, info)
            self._t_iter = (time.perf_counter() - t0) / 4
            if found is not None:
                y, res, steps = found
                # the same digits are lost with a double factor: cond(K) * eps
                lost = float(np.log10(max(err32, _EPS32) / _EPS32))
                info.update(residual=res, iterations=steps, precision="mixed",
                            error_estimate=err32 * _EPS / _EPS32, lost_digits=lost,
                            threads=self._backend.threads)
                self._warn_lost(err32 * _EPS / _EPS32, lost)
                return y
            # stalled: a double factor from now on (say so in info)
            t = time.perf_counter()
            self._mixed_stalled = True
            self._backend = None
            with _factor_threads(self.F.size):
                self._setup_direct()
            self._t_factor = time.perf_counter() - t
            self.timings["factor"] += self._t_factor
        if self._mixed_stalled:
            info["precision"] = "double (mixed stalled)"
        if self.backend_name == "pardiso":
            info["threads"] = self._backend.threads
        t0 = time.perf_counter()
        y = self._backend.solve(b)
        # one refinement step: its size estimates the forward error of the first solve
        d = self._backend.solve(b - self.K_ff @ y)
        self._t_iter = (time.perf_counter() - t0) / 2  # ~ one CG iteration with this factor
        ny = _norm(y)
        err = _norm(d) / ny if ny > 0 else 0.0
        y = y + d
        res = self._residual(y, b, nb)
        steps = 1
        while res > self.tol and steps < 4 and np.isfinite(res):
            y = y + self._backend.solve(b - self.K_ff @ y)
            res, steps = self._residual(y, b, nb), steps + 1
        lost = float(np.log10(max(err, _EPS) / _EPS))
        info.update(residual=res, iterations=steps, error_estimate=err, lost_digits=lost)
        if not np.isfinite(res) or res > max(self.tol, 1e-8):
            raise ConvergenceError(
                f"direct solve ({self.backend_name}) left a relative residual {res:.2e} > tol "
                f"{self.tol:.0e} after {steps} refinement steps: the system is numerically singular"
            )
        self._warn_lost(err, lost)
        return y

    def _warn_lost(self, err, lost):
        if lost >= self.warn_lost_digits:
            warnings.warn(
                f"the MTM system is ill conditioned: estimated relative error of the solution "
                f"{err:.1e}, about {lost:.0f} of 16 significant digits lost "
                "(extreme stiffness ratios, nu near 0.5 or degenerate tetrahedra?)",
                IllConditionedWarning, stacklevel=4,
            )

    def _solve_cg(self, b, nb, y0, info):
        maxiter = 2000 if self.maxiter is None else int(self.maxiter)
        count = [0]
        bar = _Progress(self.progress_bar, maxiter, "MTM cg")

        def cb(_):
            count[0] += 1
            bar.update(1)

        y, flag = spla.cg(self.K_ff, b, x0=y0, rtol=self.tol, atol=0.0, maxiter=maxiter,
                          M=self._M, callback=cb)
        bar.close()
        res = self._residual(y, b, nb)
        info.update(residual=res, iterations=count[0], preconditioner=self._prec_name)
        if flag != 0 or not np.isfinite(res) or res > 10 * self.tol:
            raise ConvergenceError(
                f"cg ({self._prec_name}) did not reach tol {self.tol:.0e} in {count[0]} "
                f"iterations (relative residual {res:.2e}); raise maxiter or use method='direct'"
            )
        return y

    def _solve_gpu(self, b, nb, y0, info):
        import cupy as cp
        import cupyx.scipy.sparse.linalg as cla

        maxiter = 5000 if self.maxiter is None else int(self.maxiter)
        dinv = cp.asarray(self._gpu_dinv)
        M = cla.LinearOperator(self._gpu_K.shape, matvec=lambda x: dinv * x, dtype=float)
        count = [0]

        def cb(_):
            count[0] += 1

        bg = cp.asarray(b)
        x0 = None if y0 is None else cp.asarray(y0)
        try:  # newer CuPy names the relative tolerance rtol (keyword-only), older ones tol
            yg, flag = cla.cg(self._gpu_K, bg, x0=x0, rtol=self.tol, atol=0.0, maxiter=maxiter,
                              M=M, callback=cb)
        except TypeError:
            yg, flag = cla.cg(self._gpu_K, bg, x0=x0, tol=self.tol, atol=0.0, maxiter=maxiter,
                              M=M, callback=cb)
        y = cp.asnumpy(yg)
        res = self._residual(y, b, nb)
        info.update(residual=res, iterations=count[0])
        if not np.isfinite(res) or res > 10 * self.tol:
            raise ConvergenceError(
                f"gpu cg did not reach tol {self.tol:.0e} in {count[0]} iterations "
                f"(relative residual {res:.2e}); raise maxiter or use method='direct'"
            )
        return y

    def _solve_relaxation(self, b, nb, y0, info):
        cons = self.constraints
        n = cons.n_points
        maxiter = 20000 if self.maxiter is None else int(self.maxiter)
        bfull = np.zeros(3 * n)
        bfull[self.F] = b
        y = cons.prescribed.copy()
        if y0 is not None:
            y[self.F] = y0
        # the masked A has no coupling to prescribed dofs (that is in b) and the residual is
        # masked to the unknowns, so prescribed values stay where they start
        dinv = self._dinv
        omega = self.omega
        check = 10
        bar = _Progress(self.progress_bar, maxiter, "MTM relaxation")
        res = np.inf
        sweeps = 0
        free = cons.free
        while sweeps < maxiter:
            for nodes, rows, Ar in self._rows:
                r = (bfull[rows] - Ar @ y).reshape(-1, 3)
                r *= free[rows].reshape(-1, 3)
                y[rows] += omega * np.einsum("nij,nj->ni", dinv[nodes], r).ravel()
            sweeps += 1
            bar.update(1)
            if sweeps % check == 0 or sweeps == maxiter:
                res = self._residual(y[self.F], b, nb)
                if not np.isfinite(res):
                    break
                if res <= self.tol:
                    break
        bar.close()
        info.update(residual=float(res), iterations=sweeps)
        if not res <= self.tol:
            raise ConvergenceError(
                f"relaxation did not reach tol {self.tol:.0e} in {sweeps} sweeps (relative "
                f"residual {res:.2e}); the paper's local method converges slowly, and not at all "
                "usefully for nu near 0.5: use method='direct' or 'cg'"
            )
        return y[self.F]

    # ------------------------------------------------------------------ output
    def to_grid(self, u, grid=None):
        """Copy of ``grid`` (default the solver's) with point ``displacement`` and field data."""
        grid = self.grid if grid is None else grid
        out = grid.copy(deep=False)
        out.point_data[arrays.DISPLACEMENT] = np.asarray(u, dtype=float)
        info = getattr(self, "info", {})
        for key, name in ((FIELD_METHOD, "method"), (FIELD_BACKEND, "backend")):
            out.field_data[key] = np.array([str(info.get(name, ""))])
        for key, name in ((FIELD_RESIDUAL, "residual"), (FIELD_ITERATIONS, "iterations"),
                          (FIELD_TIME, "time"), (FIELD_ERROR_ESTIMATE, "error_estimate"),
                          (FIELD_LOST_DIGITS, "lost_digits")):
            out.field_data[key] = np.array([float(info.get(name, np.nan))])
        return out


def solve(grid, method="direct", tol=1e-10, progress_bar=False, **kwargs):
    """Rest position of the MTM under the grid's boundary conditions.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with cell materials (``E_fiber``, ``nu``, optional ``E_cross``,
        ``fiber``; see :func:`pvcmf.filters.assign_materials`) and point ``bc``,
        ``bc_displacement``, ``bc_normal`` (see :func:`pvcmf.filters.apply_plan`).
    method : {'direct', 'cg', 'relaxation', 'gpu', 'auto'}
        See :mod:`pvcmf.mtm.solvers`; ``auto`` picks ``cg`` above
        :data:`AUTO_DIRECT_MAX_POINTS` points (about 400k tetrahedra), where a direct
        factorisation no longer fits a few GB.
    tol : float
        Relative residual tolerance.
    progress_bar : bool
        Show progress for iterative methods.
    **kwargs
        Passed to :class:`Solver` (``backend``, ``precision``, ``ordering``, ``maxiter``,
        ``preconditioner``, ``omega``, ``warn_lost_digits``, material overrides) except
        ``x0`` (warm start, (n, 3)).

    Returns
    -------
    pyvista.UnstructuredGrid
        A copy with point array ``displacement`` (n, 3) and field data ``mtm_method``,
        ``mtm_backend``, ``mtm_residual``, ``mtm_iterations``, ``mtm_time``,
        ``mtm_error_estimate``, ``mtm_lost_digits``.

    Raises
    ------
    ValueError
        Missing or invalid arrays, indefinite materials, or a part of the mesh with rigid
        motions left (:class:`pvcmf.mtm.RigidModeError`).
    ConvergenceError
        The method did not reach ``tol``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(4, 4, 4)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.3)
    >>> boundary = np.any((grid.points == 0) | (grid.points == 3), axis=1)
    >>> grid.point_data[arrays.BC] = np.where(boundary, arrays.BC_JOINT,
    ...                                       arrays.BC_FREE).astype(np.int8)
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = 0.01 * grid.points   # a linear field
    >>> post = grid.cmf.solve()
    >>> bool(np.allclose(post[arrays.DISPLACEMENT], 0.01 * grid.points))
    True
    """
    x0 = kwargs.pop("x0", None)
    if not hasattr(grid, "point_data") or arrays.BC not in grid.point_data.keys():
        name = type(grid).__name__
        raise ValueError(
            f"solve needs point array {arrays.BC!r} (boundary conditions; it is produced by "
            f"apply_plan); the {name} has point arrays "
            f"{sorted(grid.point_data.keys()) if hasattr(grid, 'point_data') else []}"
        )
    solver = Solver(grid, method=method, tol=tol, progress_bar=progress_bar, **kwargs)
    u = solver.solve(x0=x0)
    log.info("MTM %s: residual %.1e, %d iterations, %.3f s", method, solver.info["residual"],
             solver.info["iterations"], solver.info["time"])
    return solver.to_grid(u)
