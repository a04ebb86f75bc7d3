"""Skin operator of the plan response: ``T R`` stored as sparse rows plus dense rows.

The skin displacement of a plan is ``T R a``: ``T`` the sparse mesh -> skin transfer
(scalar weights applied to each component), ``R`` the nodal response ``(n, 3, K)``, ``a``
the plan's ``K`` parameters. A skin row with few transfer weights (a point inside a
tetrahedron: four barycentric weights) is cheaper to evaluate from the nodal displacement
of the nodes it uses than from a dense row of ``3 K`` numbers; a row with many weights (a
point outside the mesh, fitted to many nodes) is cheaper as a dense row. Which form a row
takes is decided by its number of nonzeros alone (:data:`SPARSE_MAX_NNZ`), so any sparse
``T`` is handled. A plan then costs

1. ``x_n = R_used a``: the displacement of the nodes the sparse rows use (a small dense
   matrix-vector product, point-major);
2. ``x_d = a D``: the dense rows, stored parameter-major ``(K, 3 n_dense)`` so that one
   vector-matrix product on one BLAS thread streams them once;
3. ``out = H [x_n; x_d]``: one CSR product that applies the sparse rows' weights to
   ``x_n`` and places each dense row's result (a single weight 1) at its skin point; rows
   the transfer does not reach have no entry and stay zero. The product accumulates
   straight into the caller's output (scipy's compiled CSR kernel), no scatter or copy.

A transfer smoothed outside the mesh (``T = S(W0)``: a few linear steps on the rows of
points outside it, :class:`pvcmf.filters.transfer_smoothing.Steps`) is folded as ``W0 R``
with the steps applied to those dense rows (``3 K`` columns) afterwards: the steps widen
sparse rows (each takes its neighbours' supports), not dense ones.

Many plans (statistics, batched displacements) go through blocked matrix products over
the same parts, in any order of the rows. ``float32`` storage applies to ``R_used`` and
``D`` (``H`` stays float64 and ``x`` is cast exactly), with the rounding bound
``(K + 2) u |row| s`` for a dense row and ``(K + 2) u |T_row| |R| s`` for a sparse one
(:func:`float32_bound`, :meth:`SkinOperator.float32_error`).

Delegates to numpy (BLAS), :mod:`scipy.sparse` (its compiled CSR kernels) and threadpoolctl
(one BLAS thread for the products).
"""

from __future__ import annotations

import contextlib

import numpy as np
import scipy.sparse as sp

from ..filters.transfer_smoothing import rows_product
from ._common import blas_threads

try:  # scipy's compiled kernel ``y += A x`` for a CSR matrix and several vectors
    from scipy.sparse._sparsetools import csr_matvecs as _csr_matvecs
except ImportError:  # pragma: no cover - older or newer scipy layouts
    _csr_matvecs = None

__all__ = ["SkinOperator", "float32_bound", "SPARSE_MAX_NNZ"]

#: plan range of the float32 bound: largest ``|M - I|`` entry of a rotation (30 degrees)
FLOAT32_ROTATION = 0.5
#: plan range of the float32 bound: largest centroid shift component (mm)
FLOAT32_SHIFT = 20.0

#: a skin row with at most this many transfer weights is evaluated from the nodal
#: displacement of its nodes (a CSR row costs a few ns per weight, a dense row of 3 K
#: numbers about as much as 10 to 15 weights: it is read from memory)
SPARSE_MAX_NNZ = 8
#: skin points per block of the many-plan products (the block's product stays in cache)
BLOCK = 256

_controller = None


def one_thread(threads):
    """Context limiting BLAS to ``threads`` threads through a cached threadpoolctl
    controller (entering it costs about 0.1 ms; a fresh one several ms)."""
    global _controller
    if threads is None:
        return contextlib.nullcontext()
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:
        return blas_threads(threads)
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=int(threads), user_api="blas")


def _rounding_factor(K):
    u = np.finfo(np.float32).eps / 2
    return (K + 2) * u / (1 - (K + 2) * u)


def _plan_range(K, rotation, shift):
    return np.tile(np.r_[rotation, rotation, rotation, shift], K // 4)


def float32_bound(R, n_segments, rotation=FLOAT32_ROTATION, shift=FLOAT32_SHIFT):
    """Rounding bound (mm) of the float32 product ``R a`` against the exact one, over every
    parameter vector ``a`` with rotation entries up to ``rotation`` and centroid shifts up
    to ``shift`` mm: ``max_rows g |R| s``, ``g = (K + 2) u / (1 - (K + 2) u)`` (``K`` terms,
    one rounding of the stored ``R`` and one of ``a``), ``s`` the largest ``|a|``.

    Examples
    --------
    >>> import numpy as np
    >>> R = np.ones((5, 12))
    >>> b = float32_bound(R, 1, rotation=0.5, shift=20.0)
    >>> bool(np.isclose(b, 14 * 2.0**-24 / (1 - 14 * 2.0**-24) * (9 * 0.5 + 3 * 20.0)))
    True
    """
    K = R.shape[-1]
    if K != 12 * n_segments:
        raise ValueError(f"R must have 12 columns per segment ({12 * n_segments}), got {K}")
    s = _plan_range(K, rotation, shift)
    peak = 0.0
    for b in range(0, len(R), 65536):  # blocks: no full-size |R| temporary
        peak = max(peak, float((np.abs(R[b:b + 65536]) @ s).max(initial=0.0)))
    return _rounding_factor(K) * peak


class SkinOperator:
    """``T R`` as sparse rows on the nodal response plus dense rows (see the module docs).

    Parameters
    ----------
    W : scipy.sparse matrix, shape (n_skin, n_nodes)
        The transfer (scalar weights per component).
    nodal : ndarray, shape (n_nodes, 3, K)
        Nodal response, point-major.
    sparse_max_nnz : int
        Rows with at most this many weights are sparse rows.
    steps : pvcmf.filters.transfer_smoothing.Steps, optional
        Smoothing steps of the transfer: ``W`` is the transfer before them, and the rows
        they move are dense rows made by smoothing ``W_block R`` (a few dense columns,
        :meth:`~pvcmf.filters.transfer_smoothing.Steps.moved_rows`) rather than from the
        smoothed sparse rows (whose supports widen step by step).
    threads : int, default 1
        Threads of the fold's sparse products (split by rows: the same numbers for any
        number).

    Attributes
    ----------
    reached : ndarray of int
        Skin points with a non-empty transfer row.
    sparse_rows, dense_rows : ndarray of int
        Skin points evaluated through the nodal displacement, and through dense rows.
    """

    def __init__(self, W, nodal, sparse_max_nnz=SPARSE_MAX_NNZ, steps=None, threads=1,
                 product=None):
        W = sp.csr_matrix(W, dtype=np.float64)
        tidy = W.has_canonical_format and bool(np.all(W.data))
        if not tidy:  # the caller's W stays as it is
            W = W.copy()
            W.sum_duplicates()
            W.eliminate_zeros()
        n, m = W.shape
        if nodal.ndim != 3 or nodal.shape[:2] != (m, 3):
            raise ValueError(f"nodal must have shape ({m}, 3, K), got {nodal.shape}")
        if steps is not None and steps.n != n:
            raise ValueError(f"steps must act on {n} rows, got {steps.n}")
        self.n, self.K = n, nodal.shape[2]
        if product is not None and (not tidy or not isinstance(product, (list, tuple))
                                    or [np.shape(x) for x in product] != [(n, self.K)] * 3):
            product = None  # made for another W (or one that was not tidy): not used
        count = np.diff(W.indptr)
        moved = np.zeros(n, dtype=bool)
        if steps is not None:
            moved[steps.rows] = True
        self.reached = np.flatnonzero((count > 0) | moved)
        sparse = (count > 0) & (count <= sparse_max_nnz) & ~moved
        self.sparse_rows = np.flatnonzero(sparse)
        self.dense_rows = np.flatnonzero((count > sparse_max_nnz) | moved)
        Ws = W[self.sparse_rows]
        self.used, local = np.unique(Ws.indices, return_inverse=True)
        self.S = sp.csr_matrix((Ws.data, local.ravel().astype(np.int32), Ws.indptr),
                               shape=(len(self.sparse_rows), len(self.used)))
        self.Ru = np.ascontiguousarray(nodal[self.used].reshape(-1, self.K))  # (3 n_u, K)
        self.D = self._dense(W, nodal, moved, steps, threads, product)  # (K, 3 n_d)
        self.H = self._placement(sparse)
        self._x = None

    def _dense(self, W, nodal, moved, steps, threads=1, product=None):
        """The dense rows ``W R`` (the moved ones smoothed by ``steps``), parameter-major
        ``(K, 3 n_d)``, one displacement component (``K`` columns) at a time, so that the
        steps' buffers stay small: the rows' products (``product``: ``W R_c`` over every
        row for each component ``c``, where the caller has them), then each block of rows
        transposed while it is in cache (``threads`` threads share the products, which
        release the GIL, and the blocks: the same numbers for any number of threads)."""
        K, n_d = self.K, len(self.dense_rows)
        plain = ~moved[self.dense_rows]  # among the dense rows
        Wp = W[self.dense_rows[plain]] if product is None else None
        # per dense row: its row in the plain or the moved rows' products
        source = np.empty(n_d, dtype=np.int64)
        source[plain] = np.arange(plain.sum()) if product is None else self.dense_rows[plain]
        D = np.empty((K, n_d, 3))
        for c in range(3):
            Xc = np.ascontiguousarray(nodal[:, c, :])  # (m, K)
            rows_plain = rows_product(Wp, Xc, threads) if product is None else product[c]
            rows_moved = None
            if steps is not None:
                rows_moved, pos = steps.smoothed_block(
                    W, Xc, threads, product=None if product is None else product[c])
                source[~plain] = pos[np.searchsorted(steps.rows, self.dense_rows[~plain])]
            self._lay_out(D[:, :, c], plain, source, rows_plain, rows_moved, threads)
        return D.reshape(K, 3 * n_d)

    @staticmethod
    def _lay_out(Dc, plain, source, rows_plain, rows_moved, threads, step=2048):
        """``Dc`` (``(K, n_d)``, a component of the dense rows) from the rows of the plain
        and moved rows' products, in blocks of ``step`` rows shared among ``threads``."""
        from ..filters.transfer_smoothing import _on_threads

        n_d = Dc.shape[1]
        starts = list(range(0, n_d, step))

        def put(i):
            for b in starts[i::max(1, threads)]:
                e = min(b + step, n_d)
                block = np.empty((e - b, Dc.shape[0]))
                mask = plain[b:e]
                block[mask] = rows_plain[source[b:e][mask]]
                if rows_moved is not None:
                    block[~mask] = rows_moved[source[b:e][~mask]]
                Dc[:, b:e] = block.T

        _on_threads(put, max(1, min(int(threads), len(starts))))

    def _placement(self, sparse):
        """CSR ``H`` (n_skin, n_u + n_d): the sparse rows' weights on the used nodes, and a
        weight 1 placing each dense row's result at its skin point."""
        n_u, n_d = len(self.used), len(self.dense_rows)
        count = np.zeros(self.n, dtype=np.int64)
        count[self.sparse_rows] = np.diff(self.S.indptr)
        count[self.dense_rows] = 1
        indptr = np.zeros(self.n + 1, dtype=np.int64)
        np.cumsum(count, out=indptr[1:])
        index = np.int32 if indptr[-1] < np.iinfo(np.int32).max else np.int64
        indices = np.empty(indptr[-1], dtype=index)
        data = np.ones(indptr[-1])
        starts = indptr[self.sparse_rows]
        within = np.arange(self.S.nnz) - np.repeat(self.S.indptr[:-1], np.diff(self.S.indptr))
        pos = np.repeat(starts, np.diff(self.S.indptr)) + within
        indices[pos], data[pos] = self.S.indices, self.S.data
        indices[indptr[self.dense_rows]] = n_u + np.arange(n_d)
        H = sp.csr_matrix((data, indices, indptr.astype(index)), shape=(self.n, n_u + n_d))
        if H.indptr.dtype != H.indices.dtype:  # pragma: no cover - the kernel needs one type
            H.indptr, H.indices = H.indptr.astype(np.int64), H.indices.astype(np.int64)
        return H

    # ------------------------------------------------------------------ storage
    @property
    def dtype(self):
        return self.D.dtype

    @property
    def nbytes(self):
        """Bytes one plan's product reads (its parts, without the output)."""
        H = self.H
        return int(self.Ru.nbytes + self.D.nbytes + H.data.nbytes + H.indices.nbytes
                   + H.indptr.nbytes)

    def astype(self, dtype):
        """A copy whose ``R_used`` and dense rows are stored as ``dtype``."""
        import copy

        other = copy.copy(self)
        other.Ru, other.D = self.Ru.astype(dtype), self.D.astype(dtype)
        other._x = None
        return other

    def float32_error(self, n_segments, rotation=FLOAT32_ROTATION, shift=FLOAT32_SHIFT):
        """Rounding bound (mm) of the float32 product: :func:`float32_bound` of the dense
        rows, and ``g |T_row| |R| s`` for the sparse rows."""
        dense = float32_bound(self.D.reshape(self.K, -1).T, n_segments, rotation, shift)
        s = _plan_range(self.K, rotation, shift)
        nodes = np.abs(self.Ru.astype(np.float64)) @ s  # (3 n_u,)
        rows = abs(self.S) @ nodes.reshape(-1, 3) if self.S.nnz else np.zeros((0, 3))
        return max(dense, _rounding_factor(self.K) * float(np.max(rows, initial=0.0)))

    # ------------------------------------------------------------------ one plan
    def apply(self, a, dest, threads=1, zeroed=False):
        """Write ``T R a`` into ``dest`` (flat float64, ``3 n_skin``; overwritten;
        ``zeroed=True``: ``dest`` holds zeros already, e.g. fresh from :func:`numpy.zeros`)."""
        n_u3 = self.Ru.shape[0]
        x = self.__dict__.pop("_x", None)  # the kept scratch; a concurrent call makes its own
        if x is None or x.dtype != self.dtype:
            x = np.empty(n_u3 + self.D.shape[1], dtype=self.dtype)
        self._apply(a, x, dest, n_u3, threads, zeroed)
        self._x = x
        return dest

    def _apply(self, a, x, dest, n_u3, threads, zeroed):
        with one_thread(threads):
            if self.dtype == np.float64:
                np.dot(self.Ru, a, out=x[:n_u3])
                np.dot(a, self.D, out=x[n_u3:])
            else:
                a32 = a.astype(self.dtype)
                np.dot(self.Ru, a32, out=x[:n_u3])
                np.dot(a32, self.D, out=x[n_u3:])
                x = x.astype(np.float64)
        H = self.H
        if _csr_matvecs is None:  # pragma: no cover
            dest[:] = (H @ x.reshape(-1, 3)).ravel()
            return
        if not zeroed:
            dest.fill(0.0)
        _csr_matvecs(H.shape[0], H.shape[1], 3, H.indptr, H.indices, H.data, x, dest)

    def nodes(self, A):
        """Displacement of the used nodes for the plans' parameters ``A`` (K, P):
        ``(n_u, 3 P)``, column ``c P + p``."""
        return (self.Ru @ A.astype(self.dtype, copy=False)).reshape(len(self.used), -1)

    # ------------------------------------------------------------------ rows
    def rows(self, ids):
        """Dense operator of skin points ``ids``: ``(K, len(ids), 3)`` in the storage dtype
        (zero for unreached points)."""
        ids = np.asarray(ids, dtype=np.int64)
        out = np.zeros((self.K, len(ids), 3), dtype=self.dtype)
        rank = np.full(self.n, -1, dtype=np.int64)
        rank[self.dense_rows] = np.arange(len(self.dense_rows))
        pick = rank[ids] >= 0
        if pick.any():
            out[:, pick] = self.D.reshape(self.K, -1, 3)[:, rank[ids[pick]]]
        rank[:] = -1
        rank[self.sparse_rows] = np.arange(len(self.sparse_rows))
        pick = rank[ids] >= 0
        if pick.any():
            Ru = self.Ru.reshape(len(self.used), 3 * self.K)
            block = np.asarray(self.S[rank[ids[pick]]] @ Ru).reshape(-1, 3, self.K)
            out[:, pick] = block.transpose(2, 0, 1)
        return out

    def blocks(self, A):
        """Skin displacements of the plans ``A`` (K, P) block by block, in the order of the
        stored rows: yields ``(ids, U)`` with ``U`` of shape ``(len(ids), 3, P)``, over the
        reached points."""
        A = A.astype(self.dtype, copy=False)
        P = A.shape[1]
        d_ids = self.dense_rows
        for b in range(0, len(d_ids), BLOCK):
            ids = d_ids[b:b + BLOCK]
            yield ids, (self.D[:, 3 * b:3 * (b + len(ids))].T @ A).reshape(-1, 3, P)
        if not len(self.sparse_rows):
            return
        X = self.nodes(A)  # (n_u, 3 P)
        step = 4 * BLOCK
        for b in range(0, len(self.sparse_rows), step):
            ids = self.sparse_rows[b:b + step]
            yield ids, np.asarray(self.S[b:b + step] @ X).reshape(len(ids), 3, P)
