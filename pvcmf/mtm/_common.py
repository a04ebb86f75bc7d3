"""Pieces shared by the MTM solver and its backends: errors, norms, operators, field data.

Delegates to numpy and scipy.sparse.
"""

from __future__ import annotations

import contextlib
import logging
import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .. import arrays

log = logging.getLogger(__name__)

EPS = np.finfo(float).eps
EPS32 = float(np.finfo(np.float32).eps)

#: field-data names written by :func:`pvcmf.mtm.solve`
FIELD_METHOD = "mtm_method"
FIELD_BACKEND = "mtm_backend"
FIELD_RESIDUAL = "mtm_residual"  #: relative residual ||K_ff y - b|| / ||b||
FIELD_ITERATIONS = "mtm_iterations"
FIELD_TIME = "mtm_time"  #: time in s of assembly + factorisation/setup + solve
FIELD_ERROR_ESTIMATE = "mtm_error_estimate"  #: estimated relative forward error (direct)
FIELD_LOST_DIGITS = "mtm_lost_digits"  #: estimated significant digits lost (direct)


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


def dot(x, y):
    """Inner product without BLAS (einsum), as :func:`norm`.

    OpenBLAS splits a ``ddot`` of more than 10 000 entries over its threads, which then
    keep spinning on the cores that MKL PARDISO's threads need for the next triangular
    solve.
    """
    return float(np.einsum("i,i->", np.asarray(x), np.asarray(y)))


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


_CONTROLLER = []


def blas_threads(threads):
    """Context limiting the BLAS thread pools to ``threads`` (threadpoolctl); None: no limit.

    The thread-pool controller (a scan of the loaded libraries, milliseconds) is made once
    per process and reused."""
    if threads is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        log.debug("threads=%s: threadpoolctl is not installed, BLAS keeps its threads", threads)
        return contextlib.nullcontext()
    if not _CONTROLLER:
        _CONTROLLER.append(ThreadpoolController())
    return _CONTROLLER[0].limit(limits=int(threads), user_api="blas")


def solution_grid(grid, u, info):
    """Copy of ``grid`` with point ``displacement`` ``u`` and the solve's ``info`` as field data."""
    out = grid.copy()  # deep: the result shares no memory with the input
    out.point_data[arrays.DISPLACEMENT] = np.array(u, dtype=float)
    out.field_data[arrays.MTM_INVERTED] = np.array([int(info.get("inverted", -1))])
    out.field_data[arrays.MTM_FREE_RATIO] = np.array([float(info.get("free_ratio", np.nan))])
    for key, name in ((FIELD_METHOD, "method"), (FIELD_BACKEND, "backend")):
        out.field_data[key] = np.array([str(info.get(name, ""))])
    for key, name in ((FIELD_RESIDUAL, "residual"), (FIELD_ITERATIONS, "iterations"),
                      (FIELD_TIME, "time"), (FIELD_ERROR_ESTIMATE, "error_estimate"),
                      (FIELD_LOST_DIGITS, "lost_digits")):
        out.field_data[key] = np.array([float(info.get(name, np.nan))])
    return out
