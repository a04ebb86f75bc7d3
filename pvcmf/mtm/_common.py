"""Pieces shared by the MTM solver and its backends: errors, norms, the triangle operator.

Delegates to numpy and scipy.sparse.
"""

from __future__ import annotations

import contextlib
import logging
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

log = logging.getLogger(__name__)

EPS = np.finfo(float).eps
EPS32 = float(np.finfo(np.float32).eps)


class ConvergenceError(RuntimeError):
    """An MTM solve did not reach its tolerance."""


class IllConditionedWarning(UserWarning):
    """The MTM system is so ill conditioned that the solution lost many digits."""


class BackendUnavailableError(ValueError):
    """The requested direct backend is unknown or its package is not installed."""


def norm(x):
    """2-norm without BLAS (einsum: no BLAS thread pool is woken for a short vector)."""
    x = np.asarray(x)
    return float(np.sqrt(np.einsum("i,i->", x, x)))


def not_positive_definite(err):
    """The error raised when a factorisation finds a non-positive pivot."""
    return np.linalg.LinAlgError(
        f"the reduced MTM stiffness is not positive definite ({err}): a part of the mesh may be "
        "held only through one edge or one vertex (a mechanism), or a material is indefinite"
    )


def warn_lost_digits(err, lost, limit):
    """Warn (:class:`IllConditionedWarning`) when ``lost`` digits reach ``limit``."""
    if lost >= limit:
        warnings.warn(
            f"the MTM system is ill conditioned: estimated relative error of the solution "
            f"{err:.1e}, about {lost:.0f} of 16 significant digits lost "
            "(extreme stiffness ratios, nu near 0.5 or degenerate tetrahedra?)",
            IllConditionedWarning, stacklevel=5,
        )


class SymmetricFromTriangle(spla.LinearOperator):
    """``K_ff`` from one stored triangle: ``K y = L y + L^T y - diag(L) y``.

    ``data, indices, indptr`` are the upper triangle in CSR, which is also the lower
    triangle in CSC (:attr:`lower` for CHOLMOD, :attr:`upper` for PARDISO share the arrays).
    A product costs the same as one with the full matrix, which is then neither built nor
    updated.
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


def blas_threads(threads):
    """Context limiting the BLAS thread pools to ``threads`` (threadpoolctl); None: no limit."""
    if threads is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        log.debug("threads=%s: threadpoolctl is not installed, BLAS keeps its threads", threads)
        return contextlib.nullcontext()
    return threadpool_limits(limits=int(threads), user_api="blas")
