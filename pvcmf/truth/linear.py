"""The linear algebra of the truth's Newton solves: the cores NGSolve may use and the
sparse systems of each Newton step.

:func:`cores_free` decides whether NGSolve's threads pay (they spin while they wait, so
on contended cores they cost CPU time without a speed-up); :class:`_Linear` solves the
Newton systems with a sparse direct factorisation, reused as the preconditioner of
conjugate gradients between refactorisations. Delegates to NGSolve (sparse direct
solvers, ``ngsolve.krylovspace.CGSolver``), MKL PARDISO through
:class:`pvcmf.mtm.backends.pardiso.Pardiso` (``inverse='mkl'``: METIS ordering, the
analysis done once per pattern, a numeric factorisation per system) and Linux's CPU
accounting (``/proc/stat``).
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

log = logging.getLogger("pvcmf.reference")

__all__ = ["cores_free", "others_busy"]


#: other processes may use up to this many cores for the cores to count as free
OTHERS_LIMIT = 0.5
#: how long (s) :func:`others_busy` watches the cores
WATCH_S = 0.25


def _snapshot():
    """The machine's busy CPU time and this process's own (s), from ``/proc/stat`` (all
    cores: user, nice, system, irq, softirq; not the time a hypervisor gave to other
    machines, which the threads do not take from anyone here) and :func:`os.times`."""
    with open("/proc/stat", encoding="ascii") as fh:
        user, nice, system, _idle, _iowait, irq, softirq = (
            float(x) for x in fh.readline().split()[1:8])
    own = os.times()
    busy = (user + nice + system + irq + softirq) / float(os.sysconf("SC_CLK_TCK"))
    return busy, own.user + own.system


def others_busy(interval=WATCH_S):
    """Cores (a float) that other processes kept busy over ``interval`` seconds: the
    machine's busy time less this process's own CPU time (all its threads), or None where
    ``/proc/stat`` cannot be read. Unlike the load average or the CPU pressure, it does
    not count the load this process makes itself (its own threads waiting for each
    other's core).

    Examples
    --------
    >>> from pvcmf.truth.linear import others_busy
    >>> b = others_busy(0.05)
    >>> b is None or b >= -0.5
    True
    """
    try:
        busy0, own0 = _snapshot()
        time.sleep(interval)
        busy1, own1 = _snapshot()
    except (OSError, ValueError, IndexError):
        return None
    return ((busy1 - busy0) - (own1 - own0)) / interval


def cores_free():
    """Whether the cores are free for NGSolve's threads: other processes keep less than
    :data:`OTHERS_LIMIT` of a core busy (:func:`others_busy`), or, where that cannot be
    measured, the 1-minute load average (which counts this process too) is below the
    number of cores.

    Examples
    --------
    >>> from pvcmf.truth.solver import cores_free
    >>> isinstance(cores_free(), bool)
    True
    """
    busy = others_busy()
    if busy is not None:
        free = bool(busy < OTHERS_LIMIT)
        log.info("reference: other processes kept %.2f cores busy: NGSolve threads %s", busy,
                 "on" if free else "off")
        return free
    load = os.getloadavg()[0]
    free = bool(load < (os.cpu_count() or 1))
    log.info("reference: load average %.2f on %s cores: NGSolve threads %s", load,
             os.cpu_count(), "on" if free else "off")
    return free


class _Linear:
    """The Newton systems' linear solver, with wall-time bookkeeping.

    ``inverse`` names an NGSolve sparse direct solver ("sparsecholesky", "pardiso",
    "umfpack"). The factorisation is the expensive part (P2 in 3-D: its cost grows about
    as the square of the dofs), so with ``reuse`` a later system is solved by conjugate
    gradients preconditioned with the last factor (the Hessians of successive Newton
    iterates differ little), and refactored only when that needs more than ``max_cg``
    iterations (a fresh factor also speeds up the solves after it: letting CG run as
    long as a factorisation would take made a 379k-dof truth 1.6 times slower)."""

    def __init__(self, ngs, form, freedofs, inverse, reuse=True, max_cg=25, cg_tol=1e-8,
                 threads=1):
        self.ngs, self.form, self.freedofs, self.inverse = ngs, form, freedofs, inverse
        self.threads = threads
        self.mkl = None
        self.reuse, self.max_cg, self.cg_tol = reuse, max_cg, cg_tol
        self.times = {"energy": 0.0, "assemble": 0.0, "factor": 0.0, "solve": 0.0}
        self.factorizations = self.solves = self.cg_iterations = 0
        self.factor = None

    def timed(self, key, fn, *args):
        t = time.perf_counter()
        out = fn(*args)
        self.times[key] += time.perf_counter() - t
        return out

    def linearize(self, x):
        self.timed("assemble", self.form.AssembleLinearization, x)
        self.fresh = False

    def _factorize(self):
        if self.inverse == "mkl":
            if self.mkl is None:
                self.mkl = _MklFactor(self.ngs, self.form.mat, self.freedofs, self.threads)
            try:
                self.factor = self.timed("factor", self.mkl.factor, self.form.mat)
            except np.linalg.LinAlgError:  # PARDISO's SPD factorisation refuses a Hessian
                # that is indefinite away from equilibrium: NGSolve's LDL^T takes it
                log.debug("reference: indefinite Hessian, factorised by sparsecholesky")
                self.factor = self.timed("factor", self.form.mat.Inverse, self.freedofs,
                                         "sparsecholesky")
        else:
            self.factor = self.timed("factor", self.form.mat.Inverse, self.freedofs,
                                     self.inverse)
        self.factorizations += 1
        self.fresh = True

    def solve(self, rhs, out):
        """out = K^-1 rhs on the free dofs (zero on the others), K the last linearisation."""
        self.solves += 1
        if self.factor is not None and self.reuse and not self.fresh:
            from ngsolve.krylovspace import CGSolver

            t = time.perf_counter()
            cg = CGSolver(self.form.mat, self.factor, tol=self.cg_tol, maxiter=self.max_cg)
            out.data = cg * rhs
            self.times["solve"] += time.perf_counter() - t
            self.cg_iterations += cg.iterations
            if cg.iterations < self.max_cg and np.all(np.isfinite(out.FV().NumPy())):
                return
            log.debug("reference: CG with the old factor needed > %d iterations: refactor",
                      self.max_cg)
        if not self.fresh:
            self._factorize()
        t = time.perf_counter()
        out.data = self.factor * rhs
        self.times["solve"] += time.perf_counter() - t


class _MklFactor:
    """MKL PARDISO on the free block of an NGSolve sparse matrix of fixed pattern: the
    upper triangle of the free rows and columns is gathered from NGSolve's CSR by an index
    computed once, analysed (METIS) once, and factorised numerically per matrix;
    :meth:`factor` returns an NGSolve operator (free dofs solved, the others zero) for
    ``*`` and for ``ngsolve.krylovspace.CGSolver``."""

    def __init__(self, ngs, mat, freedofs, threads):
        import scipy.sparse as sp

        from ..mtm.backends.pardiso import Pardiso

        _values, cols, indptr = mat.CSR()
        cols = np.asarray(cols, dtype=np.int64)
        indptr = np.asarray(indptr, dtype=np.int64)
        self.free = np.array(freedofs, dtype=bool)
        rows = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
        keep = self.free[rows] & self.free[cols] & (cols >= rows)
        number = np.cumsum(self.free) - 1  # free dof -> row of the free block
        r, c = number[rows[keep]], number[cols[keep]]
        order = np.lexsort((c, r))  # CSR order, sorted columns
        self.take = np.flatnonzero(keep)[order]
        m = int(self.free.sum())
        start = np.searchsorted(r[order], np.arange(m + 1))
        self.pattern = sp.csr_matrix((np.ones(len(order)), c[order], start), shape=(m, m))
        self.solver = Pardiso(self.pattern, threads=threads) if m else None  # m = 0: all prescribed
        self.ngs = ngs

    def factor(self, mat):
        if self.solver is None:
            return _operator(self.ngs, self.free, np.zeros_like, mat.CreateColVector)
        self.pattern.data = np.asarray(mat.CSR()[0])[self.take]  # the new values, same pattern
        self.solver.factor(self.pattern)
        return _operator(self.ngs, self.free, self.solver.solve, mat.CreateColVector)


def _operator(ngs, free, solve, create):
    """An NGSolve operator that applies ``solve`` to the free values of a vector."""

    class FreeSolve(ngs.BaseMatrix):
        def IsComplex(self):
            return False

        def Height(self):
            return len(free)

        def Width(self):
            return len(free)

        def CreateRowVector(self):
            return create()

        def CreateColVector(self):
            return create()

        def Mult(self, x, y):
            out = np.zeros(len(free))
            out[free] = solve(x.FV().NumPy()[free])
            y.FV().NumPy()[:] = out

    return FreeSolve()
