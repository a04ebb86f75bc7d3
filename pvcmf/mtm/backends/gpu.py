"""Jacobi-preconditioned conjugate gradient for the MTM on a CUDA GPU through CuPy.

Only when CuPy imports and sees a device (:func:`pvcmf.mtm.gpu_available`). Delegates to
:mod:`cupyx.scipy.sparse.linalg`.
"""

from __future__ import annotations

import numpy as np

from .._common import ConvergenceError


class GPU:
    """CuPy CG of one :class:`~pvcmf.mtm.Solver` (``K_ff`` and its diagonal on the device)."""

    def __init__(self, solver):
        self.s = solver

    def setup(self, refactor=True):
        import cupyx.scipy.sparse as csp

        self.K = csp.csr_matrix(self.s.K_ff)
        self.dinv = 1.0 / self.s.K_ff.diagonal()

    def solve(self, b, nb, y0, info):
        import cupy as cp
        import cupyx.scipy.sparse.linalg as cla

        s = self.s
        maxiter = 5000 if s.maxiter is None else int(s.maxiter)
        dinv = cp.asarray(self.dinv)
        M = cla.LinearOperator(self.K.shape, matvec=lambda x: dinv * x, dtype=float)
        count = [0]

        def cb(_):
            count[0] += 1

        bg = cp.asarray(b)
        x0 = None if y0 is None else cp.asarray(y0)
        try:  # newer CuPy names the relative tolerance rtol (keyword-only), older ones tol
            yg, _ = cla.cg(self.K, bg, x0=x0, rtol=s.tol, atol=0.0, maxiter=maxiter, M=M,
                           callback=cb)
        except TypeError:
            yg, _ = cla.cg(self.K, bg, x0=x0, tol=s.tol, atol=0.0, maxiter=maxiter, M=M,
                           callback=cb)
        y = cp.asnumpy(yg)
        res = s._residual(y, b, nb)
        info.update(residual=res, iterations=count[0])
        if not np.isfinite(res) or res > 10 * s.tol:
            raise ConvergenceError(
                f"gpu cg did not reach tol {s.tol:.0e} in {count[0]} iterations "
                f"(relative residual {res:.2e}); raise maxiter or use method='direct'"
            )
        return y
