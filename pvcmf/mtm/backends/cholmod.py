"""CHOLMOD supernodal Cholesky (scikit-sparse, needs a system SuiteSparse) for the MTM.

The fill-reducing ordering is computed once on the node graph (:func:`node_order`) and
applied to the unknowns, so the dof matrix is analysed in its natural order and every node's
three dofs stay adjacent (3x3 blocks inside the supernodes). CHOLMOD reads the lower triangle
in CSC. Delegates to :mod:`sksparse.cholmod`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .._common import not_positive_definite

#: node-graph orderings (``Solver(ordering=)``) when scikit-sparse is installed
ORDERINGS = ("auto", "amd", "metis", "nesdis")
#: ``ordering='auto'``: AMD below this many nodes with unknowns, METIS from there on
AMD_MAX_NODES = 30_000


def available():
    """True when scikit-sparse's CHOLMOD imports."""
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


class Cholmod:
    """CHOLMOD supernodal Cholesky of the lower triangle (CSC) of a pre-ordered matrix."""

    name = "cholmod"
    reads = "lower"
    precision = "double"

    def __init__(self, matrix, *, precision="double", threads=None, natural=False):
        from sksparse.cholmod import analyze

        self.threads = threads
        ordering = "natural" if natural else "default"
        self._factor = analyze(matrix, mode="supernodal", ordering_method=ordering)

    def factor(self, K):
        from sksparse.cholmod import CholmodNotPositiveDefiniteError

        try:
            self._factor.cholesky_inplace(K)
        except CholmodNotPositiveDefiniteError as err:
            raise not_positive_definite(err) from err

    def solve(self, b):
        return self._factor(b)


def node_order(indptr, indices, free, ordering="auto"):
    """Fill-reducing order of the nodes with unknowns, from an ordering of the node graph.

    ``indptr, indices`` is the node adjacency (block pattern), ``free`` the (3 n,) mask of
    unknown dofs, ``ordering`` ``'amd'``, ``'metis'``, ``'nesdis'`` or ``'auto'`` (AMD below
    :data:`AMD_MAX_NODES` nodes with unknowns, METIS above: a fixed rule on the size).
    Returns ``(nodes, ordering)``: the nodes with an unknown in elimination order and the
    ordering used, or None when scikit-sparse is not importable or there is nothing to order.
    """
    try:
        from sksparse.cholmod import analyze
    except ImportError:
        return None
    n = len(indptr) - 1
    active = np.flatnonzero(free.reshape(n, 3).any(axis=1))
    if active.size < 2:
        return None
    graph = sp.csr_matrix((np.ones(indices.size), indices, indptr), shape=(n, n))
    sub = graph[active][:, active].tocsc()
    if ordering == "auto":
        ordering = "amd" if active.size < AMD_MAX_NODES else "metis"
    return active[analyze(sub, mode="simplicial", ordering_method=ordering).P()], ordering
