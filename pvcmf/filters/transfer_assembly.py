"""The transfer's rows before its smoothing steps as one sparse product.

A row of the transfer (:class:`pvcmf.filters.surface_mapping.Transfer`) is, inside the
mesh, the barycentric coordinates of the point's tetrahedron; outside, the feet's affine
fit weights on their triangles' nodes plus the gradient term: a blend of the nodal
gradients at the point's nearest boundary nodes times an offset. All of it is one product
``A @ [I; D]`` (``D`` the stacked nodal gradient operators at the boundary nodes,
:func:`~pvcmf.filters.transfer_locate.stacked_gradients`), with ``A`` written as CSR from
its known row structure; scipy's sparse product sums each node's entries in the row's
order and drops zeros, so the only sort left is the one of each row's indices. The
compiled kernels are called directly where scipy provides them (the sum of the feet's
duplicates, the product into arrays sized by a bound read off the row lengths instead
of a counting pass): the same kernels as the operators ``+`` and ``@``, so the same
sums, without the index conversions and checks around them; each row's indices are
then sorted by transposing the product twice (two linear passes; the values only move).
"""

import numpy as np
import scipy.sparse as sp

from .transfer_locate import stacked_gradients

try:  # scipy's compiled CSR kernels (the ones its operators call)
    from scipy.sparse._sparsetools import csr_matmat, csr_plus_csr, csr_tocsc
except ImportError:  # pragma: no cover - other scipy layouts: the operators instead
    csr_matmat = csr_plus_csr = csr_tocsc = None

__all__ = ["rows_operator"]


def _nodes_and_gradients(loc):
    """``[I; D]`` (CSR, ``(m + 3 n_boundary, m)``): the nodal values over the stacked nodal
    gradients at the boundary nodes, kept on the mesh's index where ``loc`` has one."""
    index = getattr(loc, "index", None)
    S = getattr(index, "nodes_and_gradients", None)
    if S is None:
        S = sp.vstack([sp.identity(len(loc.points), format="csr"), stacked_gradients(loc)],
                      format="csr")
        if index is not None:
            index.nodes_and_gradients = S
    return S


def rows_operator(loc, scale, offsets):
    """The rows before the smoothing steps as one product ``A @ [I; D]`` (CSR, sorted
    indices, no explicit zeros). ``A`` is built in place from its known row structure: on
    an outside row the blend of its nearest boundary nodes' gradients times ``offsets``
    (as :func:`pvcmf.filters.surface_mapping._guided`), then its feet's weights ``scale`` times their triangles'
    coordinates, summed per node in the feet's order; on an inside row its barycentric
    coordinates. Each node's value is the sum of its gradient terms plus its feet's sum:
    the same floating-point sums as adding the three parts.

    Parameters
    ----------
    loc : pvcmf.filters.transfer_locate.Located
        The located points (with their feet and nearest boundary nodes).
    scale : ndarray, shape (n_pairs,)
        Weight of each foot (its fit weight times the decay).
    offsets : ndarray, shape (n_outside, 3)
        Offset of each outside point that the gradient blend multiplies.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n_points, n_mesh_points)
    """
    n, m, nb = len(loc.p), len(loc.points), len(loc.boundary)
    S = _nodes_and_gradients(loc)
    # the largest index or count an index array holds (A's entries times the longest row
    # of [I; D] bounds the product's)
    entries = 3 * len(loc.pair_row) + 4 * n + 3 * loc.near.shape[1] * len(loc.outside)
    top = max(m + 3 * nb, S.nnz, entries * int(np.diff(S.indptr).max(initial=1)))
    if (csr_matmat is None or top >= 2**31 or S.indices.dtype != np.int32
            or S.indptr.dtype != np.int32):
        return _rows_operator(loc, scale, offsets, S, sp.csr_matrix, np.int64)
    return _rows_operator(loc, scale, offsets, S, _Kernels, np.int32)


def _rows_operator(loc, scale, offsets, S, kernels, itype):
    """:func:`rows_operator` with ``kernels`` (:class:`_Kernels`, or
    :class:`scipy.sparse.csr_matrix`: its operators) and index type ``itype``."""
    n, m, nb = len(loc.p), len(loc.points), len(loc.boundary)
    out, kk = loc.outside, loc.near.shape[1]
    ins = np.flatnonzero(loc.inside)
    ptr = np.zeros(n + 1, dtype=itype)
    np.cumsum(loc.inside * 4, out=ptr[1:])
    T = kernels((loc.bary[ins].ravel(), loc.tets[loc.cell[ins]].ravel().astype(itype), ptr),
                shape=(n, m))
    ptr = np.zeros(n + 1, dtype=itype)  # pair rows are sorted: CSR directly
    np.cumsum(np.bincount(loc.pair_row, minlength=n) * 3, out=ptr[1:])
    face = kernels(((scale[:, None] * loc.face_bary).ravel(), loc.face.ravel().astype(itype),
                    ptr), shape=(n, m))
    local = T + face  # the feet's duplicates summed in order, per row
    width = np.diff(local.indptr)
    guided = np.zeros(n, dtype=itype)
    guided[out] = 3 * kk
    ptr = np.zeros(n + 1, dtype=itype)
    np.cumsum(width + guided, out=ptr[1:])
    data = np.empty(ptr[-1])
    cols = np.empty(ptr[-1], dtype=itype)
    at = ptr[out][:, None, None] + np.arange(3 * kk).reshape(3, kk)
    data[at] = offsets[:, :, None] * loc.near_w[:, None, :]
    cols[at] = m + loc.near[:, None, :] + nb * np.arange(3)[None, :, None]
    at = np.arange(local.nnz) + np.repeat(ptr[:-1] + guided - local.indptr[:-1], width)
    data[at], cols[at] = local.data, local.indices
    T = kernels((data, cols, ptr), shape=(n, m + 3 * nb)) @ S
    T.sort_indices()
    return T if isinstance(T, sp.csr_matrix) else T.csr()


class _Kernels:
    """A CSR matrix ``(data, indices, indptr)`` with the operations :func:`rows_operator`
    makes (``+``, ``@`` a CSR matrix, ``sort_indices``) as scipy's kernels, called directly
    on int32 indices."""

    def __init__(self, arrays, shape):
        self.data, self.indices, self.indptr = arrays
        self.shape = shape

    @property
    def nnz(self):
        return int(self.indptr[-1])

    def __add__(self, other):  # (scipy's `+`: the general kernel where unsorted)
        n, m = self.shape
        top = self.nnz + other.nnz
        ptr, idx, val = np.empty(n + 1, np.int32), np.empty(top, np.int32), np.empty(top)
        csr_plus_csr(n, m, self.indptr, self.indices, self.data,
                     other.indptr, other.indices, other.data, ptr, idx, val)
        return _Kernels((val[:ptr[-1]], idx[:ptr[-1]], ptr), self.shape)

    def __matmul__(self, other):  # (scipy's `@` without its counting pass)
        n = self.shape[0]
        top = int(np.diff(other.indptr)[self.indices].sum())
        ptr, idx, val = np.empty(n + 1, np.int32), np.empty(top, np.int32), np.empty(top)
        csr_matmat(n, other.shape[1], self.indptr, self.indices, self.data,
                   other.indptr, other.indices, other.data, ptr, idx, val)
        return _Kernels((val[:ptr[-1]], idx[:ptr[-1]], ptr), (n, other.shape[1]))

    def sort_indices(self):
        """Each row's indices sorted: the matrix transposed twice (two counting passes,
        which list each row's entries by column; no entry repeats)."""
        n, m = self.shape
        nnz = self.nnz
        ptr, idx, val = np.empty(m + 1, np.int32), np.empty(nnz, np.int32), np.empty(nnz)
        csr_tocsc(n, m, self.indptr, self.indices, self.data, ptr, idx, val)
        csr_tocsc(m, n, ptr, idx, val, self.indptr, self.indices, self.data)

    def csr(self):
        """A :class:`scipy.sparse.csr_matrix` of its own copies (sorted indices)."""
        T = sp.csr_matrix((self.data.copy(), self.indices.copy(), self.indptr),
                          shape=self.shape)
        T.has_sorted_indices = True
        return T
