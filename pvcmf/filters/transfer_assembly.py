"""The transfer's rows before its smoothing steps as one sparse product.

A row of the transfer (:class:`pvcmf.filters.surface_mapping.Transfer`) is, inside the
mesh, the barycentric coordinates of the point's tetrahedron; outside, the feet's affine
fit weights on their triangles' nodes plus the gradient term: a blend of the nodal
gradients at the point's nearest boundary nodes times an offset. All of it is one product
``A @ [I; D]`` (``D`` the stacked nodal gradient operators at the boundary nodes,
:func:`~pvcmf.filters.transfer_locate.stacked_gradients`), with ``A`` written as CSR from
its known row structure; scipy's sparse product sums each node's entries in the row's
order and drops zeros, so the only sort left is the one of each row's indices.
"""

import numpy as np
import scipy.sparse as sp

from .transfer_locate import stacked_gradients

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
    out, kk = loc.outside, loc.near.shape[1]
    ins = np.flatnonzero(loc.inside)
    ptr = np.zeros(n + 1, dtype=np.int64)
    ptr[1:] = np.cumsum(loc.inside * 4)
    T = sp.csr_matrix((loc.bary[ins].ravel(), loc.tets[loc.cell[ins]].ravel(), ptr), shape=(n, m))
    ptr = np.zeros(n + 1, dtype=np.int64)  # pair rows are sorted: CSR directly
    ptr[1:] = np.cumsum(np.bincount(loc.pair_row, minlength=n) * 3)
    face = sp.csr_matrix(((scale[:, None] * loc.face_bary).ravel(), loc.face.ravel(), ptr),
                         shape=(n, m))
    local = T + face  # the feet's duplicates summed in order, per row
    width = np.diff(local.indptr)
    guided = np.zeros(n, dtype=np.int64)
    guided[out] = 3 * kk
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(width + guided, out=ptr[1:])
    data = np.empty(ptr[-1])
    cols = np.empty(ptr[-1], dtype=np.int64)
    at = ptr[out][:, None, None] + np.arange(3 * kk).reshape(3, kk)
    data[at] = offsets[:, :, None] * loc.near_w[:, None, :]
    cols[at] = m + loc.near[:, None, :] + nb * np.arange(3)[None, :, None]
    at = np.arange(local.nnz) + np.repeat(ptr[:-1] + guided - local.indptr[:-1], width)
    data[at], cols[at] = local.data, local.indices
    A = sp.csr_matrix((data, cols, ptr), shape=(n, m + 3 * nb))
    T = A @ _nodes_and_gradients(loc)
    T.sort_indices()
    return T
