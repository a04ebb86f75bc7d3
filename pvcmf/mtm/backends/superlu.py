"""scipy's SuperLU (``scipy.sparse.linalg.splu``) as the MTM's always-available direct backend.

The reduced stiffness is symmetric positive definite, so SuperLU runs in symmetric mode with a
symmetric (minimum degree on ``A^T + A``) column ordering and no pivoting.
"""

from __future__ import annotations

import scipy.sparse.linalg as spla

from .._common import not_positive_definite


class SuperLU:
    """LU factorisation of the full reduced stiffness (CSC) by scipy's SuperLU."""

    name = "superlu"
    #: which part of ``K_ff`` the backend reads: ``'full'``, ``'upper'`` (CSR) or ``'lower'`` (CSC)
    reads = "full"
    precision = "double"
    threads = None

    def __init__(self, matrix, *, precision="double", threads=None, natural=False):
        self._lu = None

    def factor(self, K):
        try:
            self._lu = spla.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                 options={"SymmetricMode": True})
        except RuntimeError as err:
            raise not_positive_definite(err) from err

    def solve(self, b):
        return self._lu.solve(b)
