"""The direct method of the MTM solver: factorise, solve, refine, estimate the lost digits.

One factorisation backend (:mod:`.pardiso`, :mod:`.cholmod`, :mod:`.superlu`) is analysed once
per :class:`~pvcmf.mtm.Solver` and refactored numerically for new materials. Every solve takes
one step of iterative refinement, whose size estimates the forward error of the first solve
(an :class:`~pvcmf.mtm.IllConditionedWarning` says how many digits were lost when that is
large). Two options trade a factorisation for iterations:

* ``precision='mixed'`` (PARDISO only, and its default through ``precision='auto'``): a
  single-precision numeric factor, refined in double by conjugate gradient preconditioned
  with it, to the accuracy of a double factor; a double factor replaces it when the
  refinement stalls or the single-precision error is too large to estimate the lost digits
  from (``info['precision']`` then says ``'double (mixed stalled)'``). Each solve costs two
  single-precision triangular solve pairs plus one per refinement iteration, against two
  double ones: for many solves per factorisation (many bone moves on one material)
  ``precision='double'`` is cheaper.
* ``update_materials(refactor=False)``: the previous factor preconditions a conjugate
  gradient on the new matrix when a bound on the condition number (from the materials only)
  predicts at most :attr:`Direct.max_reuse_iterations` iterations; else, or when the
  iteration does not reach ``tol`` in that many, the solver refactors.

Delegates to the backends and :func:`scipy.sparse.linalg.cg`.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse.linalg as spla

from .._common import EPS, EPS32, ConvergenceError, dot, norm, warn_lost_digits
from . import factorisation

log = logging.getLogger(__name__)

#: relative residual the mixed-precision refinement aims at (about what one double factor
#: plus one refinement step reaches); it stops earlier once below tol and stagnating
MIXED_TARGET = 1e-14


class Direct:
    """Direct method of one :class:`~pvcmf.mtm.Solver` (reads its matrices and options)."""

    #: CG iterations preconditioned by an earlier factor before the solver refactors
    max_reuse_iterations = 30
    #: mixed precision: CG iterations preconditioned by the single factor before a double one
    max_mixed_iterations = 25
    #: mixed precision: above this estimated error of a single-precision solve (about
    #: ``cond(K) * eps32``) the estimate saturates, so the solver refactors in double
    max_mixed_error = 1e-2

    def __init__(self, solver):
        self.s = solver
        self.factor = None
        self.mixed_stalled = False
        self.stale = False
        self.factored_moduli = None

    @property
    def factor_precision(self):
        """``'single'`` or ``'double'``: the numeric factor made for the current materials."""
        return "single" if self.s.precision == "mixed" and not self.mixed_stalled else "double"

    def setup(self, refactor=True):
        """Factorise the current matrix, or (``refactor=False``) keep the factor when reusing
        it is predicted to converge quickly."""
        self.stale = (not refactor and self.factor is not None and self.reuse_predicted())
        if not self.stale:
            self._factorise()

    def _factorise(self):
        s = self.s
        A = s._direct_matrix()
        if self.factor is None:
            t = time.perf_counter()
            cls = factorisation(s.backend_name)
            self.factor = cls(A, precision=self.factor_precision, threads=s.threads,
                              natural=s._natural_order)
            s.timings["analysis"] = time.perf_counter() - t
        try:
            self.factor.factor(A)
        except np.linalg.LinAlgError:
            if self.factor.precision != "single":
                raise
            # positive definite in double but not in single precision (cond(K) >~ 1e7)
            log.info("mixed precision: the single-precision factor broke down: refactoring "
                     "in double")
            self._fall_back_to_double()
            return
        self.factored_moduli = s._moduli()

    def _fall_back_to_double(self):
        self.mixed_stalled, self.factor = True, None
        self._factorise()

    def reuse_predicted(self):
        """Whether CG preconditioned by the current factor is predicted to converge in at most
        :attr:`max_reuse_iterations` iterations.

        For an isotropic cell the energy ``lambda tr(e)^2 + 2 mu e:e`` changes by a factor
        between the ratios of the shear moduli and of the bulk moduli ``lambda + 2 mu / 3``,
        so the condition number of the preconditioned system is at most ``kappa = max ratio /
        min ratio`` over cells (used as an estimate for the fibre terms), and CG needs about
        ``ln(2 / tol) / ln((sqrt(kappa) + 1) / (sqrt(kappa) - 1))`` iterations.
        """
        old = self.factored_moduli
        if old is None:
            return True
        new = self.s._moduli()
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(old > 0, new / old, np.inf)
        kappa = float(ratio.max() / ratio.min()) if ratio.min() > 0 else np.inf
        if not np.isfinite(kappa):
            return False
        root = np.sqrt(max(kappa, 1.0 + 1e-12))
        iterations = np.log(2.0 / self.s.tol) / np.log((root + 1.0) / (root - 1.0))
        return iterations <= self.max_reuse_iterations

    def _solve_stale(self, b, nb, info):
        """CG preconditioned by the factor of earlier materials; None when it does not reach
        ``tol`` in :attr:`max_reuse_iterations` iterations."""
        s = self.s
        n = s.K_ff.shape[0]
        M = spla.LinearOperator((n, n), matvec=self.factor.solve, dtype=float)
        count = [0]

        def cb(_):
            count[0] += 1

        y, flag = spla.cg(s.K_ff, b, x0=self.factor.solve(b), rtol=s.tol, atol=0.0,
                          maxiter=self.max_reuse_iterations, M=M, callback=cb)
        res = s._residual(y, b, nb)
        if flag != 0 or not res <= s.tol:
            return None
        info.update(residual=res, iterations=count[0], reused_factor=True)
        return y

    def _solve_mixed(self, b, nb):
        """Solve with the single-precision factor, refined in double by CG preconditioned
        with it, to :data:`MIXED_TARGET` (stopping once below ``tol`` and stagnating).

        Returns ``((y, residual, steps), err32)``, or ``(None, err32)`` when ``tol`` is not
        reached or the estimated single-precision error ``err32`` exceeds
        :attr:`max_mixed_error`.
        """
        s = self.s
        solve32, K = self.factor.solve, s.K_ff
        y = solve32(b)
        r = b - K @ y
        z = solve32(r)
        ny = norm(y)
        err32 = norm(z) / ny if ny > 0 else 0.0
        if err32 > self.max_mixed_error:
            log.info("mixed precision: single-precision error %.1e too large to estimate "
                     "from: refactoring in double", err32)
            return None, err32
        target = min(s.tol, MIXED_TARGET)
        p, rz = z, dot(r, z)
        res = norm(r) / nb
        steps = 0
        while res > target and steps < self.max_mixed_iterations and np.isfinite(res):
            Kp = K @ p
            alpha = rz / dot(p, Kp)
            y = y + alpha * p
            r = r - alpha * Kp
            steps += 1
            previous, res = res, norm(r) / nb
            if res <= s.tol and res > 0.5 * previous:
                break  # converged to tol and stagnating near round-off
            z = solve32(r)
            rz, rz_old = dot(r, z), rz
            p = z + (rz / rz_old) * p
        res = s._residual(y, b, nb)  # the true residual, not the recurrence
        if not (np.isfinite(res) and res <= s.tol):
            log.info("mixed precision stalled (relative residual %.1e after %d CG iterations): "
                     "refactoring in double", res, steps)
            return None, err32
        return (y, res, steps), err32

    def solve(self, b, nb, y0, info):
        s = self.s
        if self.stale:
            y = self._solve_stale(b, nb, info)
            if y is not None:
                return y
            t = time.perf_counter()
            self._factorise()
            self.stale = False
            s.timings["factor"] += time.perf_counter() - t
        info["threads"] = self.factor.threads
        if self.factor.precision == "single":
            found, err32 = self._solve_mixed(b, nb)
            if found is not None:
                y, res, steps = found
                err = err32 * EPS / EPS32  # the same digits are lost with a double factor
                lost = float(np.log10(max(err32, EPS32) / EPS32))
                info.update(residual=res, iterations=steps, precision="mixed",
                            error_estimate=err, lost_digits=lost)
                warn_lost_digits(err, lost, s.warn_lost_digits)
                return y
            t = time.perf_counter()
            self._fall_back_to_double()
            s.timings["factor"] += time.perf_counter() - t
            info["threads"] = self.factor.threads
        info["precision"] = "double (mixed stalled)" if self.mixed_stalled else "double"
        return self._solve_double(b, nb, info)

    def _solve_double(self, b, nb, info):
        s, solve = self.s, self.factor.solve
        y = solve(b)
        # one refinement step: its size estimates the forward error of the first solve
        d = solve(b - s.K_ff @ y)
        ny = norm(y)
        err = norm(d) / ny if ny > 0 else 0.0
        y = y + d
        res = s._residual(y, b, nb)
        steps = 1
        while res > s.tol and steps < 4 and np.isfinite(res):
            y = y + solve(b - s.K_ff @ y)
            res, steps = s._residual(y, b, nb), steps + 1
        lost = float(np.log10(max(err, EPS) / EPS))
        info.update(residual=res, iterations=steps, error_estimate=err, lost_digits=lost)
        if not np.isfinite(res) or res > max(s.tol, 1e-8):
            raise ConvergenceError(
                f"direct solve ({s.backend_name}) left a relative residual {res:.2e} > tol "
                f"{s.tol:.0e} after {steps} refinement steps: the system is numerically singular"
            )
        warn_lost_digits(err, lost, s.warn_lost_digits)
        return y
