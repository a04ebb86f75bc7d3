"""The linear algebra of the truth's Newton solves: the cores NGSolve may use and the
sparse systems of each Newton step.

:func:`cores_free` decides whether NGSolve's threads pay (they spin while they wait, so
on contended cores they cost CPU time without a speed-up); :class:`_Linear` solves the
Newton systems with a sparse direct factorisation, reused as the preconditioner of
conjugate gradients between refactorisations. Delegates to NGSolve (sparse direct
solvers, ``ngsolve.krylovspace.CGSolver``) and Linux's CPU pressure information
(:func:`pvcmf.mtm.response_transfer.cpu_pressure`).
"""

from __future__ import annotations

import logging
import os
import time

import numpy as np

from ..mtm.response_transfer import CPU_PRESSURE_LIMIT, cpu_pressure

log = logging.getLogger("pvcmf.reference")

__all__ = ["cores_free"]


def cores_free():
    """Whether the cores are free for NGSolve's threads: runnable tasks waited for a core
    less than :data:`~pvcmf.mtm.response_transfer.CPU_PRESSURE_LIMIT` percent of the last
    ten seconds (:func:`~pvcmf.mtm.response_transfer.cpu_pressure`), or, where the kernel
    gives no pressure information, the 1-minute load average (which counts this process
    too) is below the number of cores.

    Examples
    --------
    >>> from pvcmf.truth.solver import cores_free
    >>> isinstance(cores_free(), bool)
    True
    """
    pressure = cpu_pressure()
    if pressure is not None:
        return bool(pressure < CPU_PRESSURE_LIMIT)
    return bool(os.getloadavg()[0] < (os.cpu_count() or 1))


class _Linear:
    """The Newton systems' linear solver, with wall-time bookkeeping.

    ``inverse`` names an NGSolve sparse direct solver ("sparsecholesky", "pardiso",
    "umfpack"). The factorisation is the expensive part (P2 in 3-D: its cost grows about
    as the square of the dofs), so with ``reuse`` a later system is solved by conjugate
    gradients preconditioned with the last factor (the Hessians of successive Newton
    iterates differ little), and refactored only when that needs more than ``max_cg``
    iterations (a fresh factor also speeds up the solves after it: letting CG run as
    long as a factorisation would take made a 379k-dof truth 1.6 times slower)."""

    def __init__(self, ngs, form, freedofs, inverse, reuse=True, max_cg=25, cg_tol=1e-8):
        self.ngs, self.form, self.freedofs, self.inverse = ngs, form, freedofs, inverse
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
