"""Gradient-guided smoothing of the mesh -> skin transfer outside the mesh.

:func:`pvcmf.filters.surface_mapping.transfer_operator` extends the mesh's field to a skin
point ``p`` outside the mesh by a local affine fit to the values on its nearest boundary
triangles (its *feet*). Where the boundary is concave (a crack between the lips where a
thin soft layer is not meshed, a fold) the feet of neighbouring skin points lie far apart
on the boundary: they sweep faster than ``p`` moves, and the extension can stretch a skin
edge beyond the steepest displacement gradient of the tetrahedra around it. This module
damps that with a few explicit, linear smoothing steps on the skin points themselves:

``u_p <- (1 - a_p) u_p + a_p sum_q w_pq [u_q + G_p (x_p - x_q)]``

over the ``neighbours`` nearest skin points ``q`` of ``p`` (weights ``w_pq = (1 -
(r_pq / rho_p)^2)^2`` normalised, ``rho_p`` the distance of the next neighbour, at most
``NEIGHBOUR_REACH`` median mesh edges), where ``G_p`` is the gradient of the extension's
fit at ``p`` (the blend of the nodal displacement gradients at its nearest boundary
nodes, exact for an affine field). Properties:

* only points outside the mesh and within ``band`` of it move (``a_p > 0``), and only
  points inside the mesh or within ``band`` are neighbours, so the finite-element
  interpolation inside the mesh is unchanged;
* an affine field is kept exactly: its values satisfy ``u_q + G (x_p - x_q) = u_p``;
* an edge's jump is pulled towards ``G_p e``, whose norm is within the gradients of the
  tetrahedra around the point; feet that sweep no longer show as a crumple;
* the strength ``a_p`` rises smoothly from 0 at the mesh boundary to ``STRENGTH`` at
  ``RAMP`` median mesh edges out, and falls smoothly to 0 over the last quarter of the
  band, so the transfer stays continuous across the mesh boundary and where the band
  ends;
* each step is one sparse matrix product: with ``S`` the step's matrix and ``T`` the
  transfer, ``T <- S T + F`` (``F`` the guidance term; both on the rows of the moving
  points and their neighbours only), so the transfer stays a
  :mod:`scipy.sparse` matrix (skin points x mesh nodes) whose rows widen by the
  neighbours' supports. :func:`smoothing_steps` returns ``S`` and ``F`` themselves
  (:class:`Steps`): the steps are linear and do not depend on the field, so a product
  ``T X`` with a few dense columns (the plan response's nodal basis) can be smoothed
  after the product (:meth:`Steps.moved_rows`), where the rows stay narrow.

The neighbours depend on the points only (not on a surface's connectivity), so a transfer
built from a skin's points equals the one built from the skin. Delegates the neighbour
search to :class:`scipy.spatial.cKDTree` and the steps to :mod:`scipy.sparse`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

try:  # scipy's compiled kernel ``y += A x`` for a CSR matrix and several vectors
    from scipy.sparse._sparsetools import csr_matvecs as _csr_matvecs
except ImportError:  # pragma: no cover - older or newer scipy layouts
    _csr_matvecs = None

__all__ = ["smooth_outside", "smoothing_steps", "Steps", "DEFAULT_ITERATIONS", "STRENGTH",
           "NEIGHBOURS", "rows_product"]

#: default number of smoothing steps (0: the plain extension)
DEFAULT_ITERATIONS = 3
#: largest weight of the neighbours' mean in one step
STRENGTH = 0.8
#: skin points whose mean a point moves towards
NEIGHBOURS = 16
#: distance from the mesh (in median mesh edges) over which the strength rises from 0
RAMP = 0.05
#: farthest neighbour (in median mesh edges)
NEIGHBOUR_REACH = 2.0
#: fraction of the band over which the strength falls back to 0 at its outer edge
BAND_TAPER = 0.25


#: fewest rows per thread of :func:`rows_product` (smaller products stay on one thread)
ROWS_PER_THREAD = 4096


def rows_product(A, X, threads=1, out=None, add=None):
    """``A @ X`` (sparse times dense, ``(rows, columns)``; plus ``add`` where given) with the
    rows split among ``threads`` threads: scipy's CSR kernel releases the GIL, and each row
    is the same sum in any split, so the result does not depend on ``threads``.

    Each thread writes its rows straight into ``out`` (a C-contiguous float64 ``(rows,
    columns)`` array, overwritten; made where None) with scipy's compiled kernel, which
    sums a row's products in the order of its entries onto zeros, as ``A @ X`` does:
    no row slices of ``A``, no temporaries, no copy into the result. ``add`` (same shape)
    is added to each row range by its thread, as ``A @ X + add`` would add it.

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> A = sp.random(20000, 50, density=0.1, format="csr", random_state=0)
    >>> X = np.random.default_rng(0).normal(size=(50, 4))
    >>> bool(np.array_equal(rows_product(A, X, threads=2), A @ X))
    True
    """
    A = sp.csr_matrix(A)
    X = np.asarray(X)
    n = A.shape[0]
    threads = max(1, min(int(threads), n // ROWS_PER_THREAD))
    if not _kernel_fits(A, X, out):
        result = np.asarray(A @ X) if threads == 1 else _split_product(A, X, threads)
        if add is not None:
            result = result + add
        if out is None:
            return result
        out[...] = result
        return out
    X = np.ascontiguousarray(X)
    if out is None:
        out = np.empty((n, X.shape[1]))
    bounds = np.linspace(0, n, threads + 1).astype(np.int64)
    flat_x = X.reshape(-1)

    def part(i):
        a, b = int(bounds[i]), int(bounds[i + 1])
        rows = out[a:b]
        rows.fill(0.0)
        _csr_matvecs(b - a, A.shape[1], X.shape[1], A.indptr[a:b + 1], A.indices, A.data,
                     flat_x, rows.reshape(-1))
        if add is not None:
            rows += add[a:b]

    _on_threads(part, threads)
    return out


def _kernel_fits(A, X, out):
    """Whether :func:`rows_product` can run scipy's kernel into ``out`` (float64 values,
    one index type, two-dimensional ``X``, a C-contiguous float64 ``out`` of the shape)."""
    if _csr_matvecs is None or X.ndim != 2 or A.dtype != np.float64 or X.dtype != np.float64:
        return False
    if A.indptr.dtype != A.indices.dtype:
        return False
    return out is None or (out.dtype == np.float64 and out.flags.c_contiguous
                           and out.shape == (A.shape[0], X.shape[1]))


def _split_product(A, X, threads):
    out = np.empty((A.shape[0],) + X.shape[1:], dtype=np.result_type(A.dtype, X.dtype))
    bounds = np.linspace(0, A.shape[0], threads + 1).astype(np.int64)

    def part(i):
        a, b = bounds[i], bounds[i + 1]
        out[a:b] = A[a:b] @ X

    _on_threads(part, threads)
    return out


def _on_threads(part, threads):
    """``part(i)`` for ``i < threads``, on that many threads (the calling one included)."""
    if threads == 1:
        part(0)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads - 1, thread_name_prefix="pvcmf-rows") as pool:
        done = [pool.submit(part, i) for i in range(1, threads)]
        part(0)
        for f in done:
            f.result()


def _smoothstep(t):
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def strength(dist, band, h, top=STRENGTH):
    """Step weight ``a_p`` per point from its distance ``dist`` to the mesh (0 inside and
    beyond ``band``), ``h`` the median mesh edge."""
    dist = np.asarray(dist, dtype=float)
    a = top * (_smoothstep(dist / (RAMP * h)) if RAMP > 0 else np.ones_like(dist))
    if np.isfinite(band):
        a = a * _smoothstep((band - dist) / (BAND_TAPER * band))
    return np.where((dist > 0) & (dist <= band), a, 0.0)


def _neighbours(x, moving, fixed_ok, k, reach, threads=1):
    """Per point of ``moving`` that has one: its ``k`` nearest points among ``fixed_ok``
    (not itself) within ``reach`` and their normalised weights ``w_pq``. Returns the rows
    (points), the neighbours ``(r, k)`` and the weights ``(r, k)`` (0 where none);
    ``threads``: threads of the search."""
    cand = np.flatnonzero(fixed_ok)
    kk = min(k + 2, len(cand))
    if kk < 3 or not len(moving):
        return np.zeros(0, dtype=np.int64), np.zeros((0, 1), dtype=np.int64), np.zeros((0, 1))
    tree = cKDTree(x[cand], balanced_tree=False, compact_nodes=False)
    dist, idx = tree.query(x[moving], k=kk, distance_upper_bound=reach, workers=threads)
    dist, idx = dist.reshape(len(moving), kk), idx.reshape(len(moving), kk)
    nb = np.where(idx < len(cand), cand[np.minimum(idx, len(cand) - 1)], 0)
    me = (nb == moving[:, None]) & (idx < len(cand))  # the point itself (first, but for a
    first = me[:, 0]                                   # duplicate point)
    dist = np.where(first[:, None], np.roll(dist, -1, axis=1), dist)
    nb = np.where(first[:, None], np.roll(nb, -1, axis=1), nb)
    rest = np.flatnonzero(~first & me.any(axis=1))  # itself elsewhere: moved to the end
    if rest.size:
        order = np.argsort(me[rest], axis=1, kind="stable")
        dist[rest] = np.take_along_axis(dist[rest], order, 1)
        nb[rest] = np.take_along_axis(nb[rest], order, 1)
    dist, nb = dist[:, :kk - 1], nb[:, :kk - 2]  # k neighbours and the next one's distance
    rho = np.minimum(dist[:, -1:], reach)  # the next neighbour's distance, at most reach
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(dist[:, :-1] < rho, (1.0 - (dist[:, :-1] / rho) ** 2) ** 2, 0.0)
    total = w.sum(axis=1)
    has = total > 0
    return moving[has], nb[has], w[has] / total[has, None]


def smoothing_steps(x, dist, band, h, guide, *, iterations=DEFAULT_ITERATIONS, top=None,
                    neighbours=None, threads=1):
    """The ``iterations`` gradient-guided smoothing steps (module docs) as sparse matrices
    (:class:`Steps`), or None where no point moves.

    The parameters are those of :func:`smooth_outside` (without ``T``); ``guide``'s matrix
    is built once here. ``smoothing_steps(...).apply(T)`` is ``smooth_outside(T, ...)``.
    ``threads``: threads of the neighbour search (the same neighbours for any number).

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> x = np.column_stack([np.linspace(0, 3, 7), np.zeros(7), np.zeros(7)])
    >>> guide = lambda rows, o: sp.csr_matrix((o[:, 0] * 2 * x[rows, 0], (rows, 0 * rows)),
    ...                                        shape=(7, 2))
    >>> steps = smoothing_steps(x, np.array([0, 0, 1, 1, 1, 0, 0.0]), 4.0, 1.0, guide)
    >>> steps.rows.tolist(), steps.step.shape
    ([2, 3, 4], (7, 7))
    """
    if iterations <= 0:
        return None
    dist = np.asarray(dist, dtype=float)
    n = len(dist)
    a = strength(dist, band, h, STRENGTH if top is None else top)
    moving = np.flatnonzero(a > 0)
    rows, nb, w = _neighbours(x, moving, dist <= band,
                              NEIGHBOURS if neighbours is None else neighbours,
                              NEIGHBOUR_REACH * h, threads)
    if not len(rows):
        return None
    # the steps act on the block of the moving points and their neighbours only
    member = np.zeros(n, dtype=bool)  # the block, sorted, and each point's place in it
    member[rows] = True
    member[nb[w > 0]] = True
    block = np.flatnonzero(member)
    slot = np.zeros(n, dtype=np.int64)
    slot[block] = np.arange(len(block))
    pos = slot[rows]
    local = np.where(w > 0, slot[nb], pos[:, None])
    ar = a[rows]
    stay = np.ones(len(block))  # the step: 1 - a on a moving point, 1 on a fixed one
    stay[pos] = 1.0 - ar
    diag = np.arange(len(block))
    step = sp.csr_matrix((np.concatenate([stay, (ar[:, None] * w).ravel()]),
                          (np.concatenate([diag, np.repeat(pos, w.shape[1])]),
                           np.concatenate([diag, local.ravel()]))),
                         shape=(len(block), len(block)))  # (duplicates are summed)
    offsets = x[rows] - np.einsum("rk,rkc->rc", w, x[nb])  # p less its neighbours' mean
    F = guide(rows, ar[:, None] * offsets)
    if isinstance(F, tuple):  # (B, G) with F = B @ G: kept as factors, the block's rows of B
        F = (sp.csr_matrix(F[0])[block], sp.csr_matrix(F[1]))
    else:
        F = sp.csr_matrix(F)[block]
    return Steps(n, block, rows, pos, step, F, int(iterations))


class Steps:
    """Smoothing steps as sparse matrices: on the rows ``block`` of a transfer ``T``
    (skin points x mesh nodes), ``T_block <- step @ T_block + F``, ``iterations`` times;
    the rows ``rows`` (the moving points, at ``pos`` in ``block``) then replace those of
    ``T`` (the block's other rows do not change).

    The steps are linear and independent of the field, so they commute with any product
    on the right: ``apply(T) @ X`` equals ``T @ X`` with the moved rows replaced by
    :meth:`moved_rows` ``(T, X)``, which smooths the dense ``T_block @ X`` (a few columns)
    instead of the sparse ``T_block`` (whose rows widen by the neighbours' supports).

    Attributes
    ----------
    n : int
        Rows of the transfer.
    block, rows, pos : ndarray of int
    step : scipy.sparse.csr_matrix, shape (len(block), len(block))
    F : scipy.sparse.csr_matrix, shape (len(block), m)
        The guidance term (zero on the fixed rows); made on first use where ``guide`` gave
        it as factors ``(B, G)`` (then ``F X`` is ``B (G X)``: narrower rows).
    iterations : int
    """

    def __init__(self, n, block, rows, pos, step, F, iterations):
        self.n, self.block, self.rows, self.pos = n, block, rows, pos
        self.step, self.iterations = step, iterations
        self._F, self._factors = (None, F) if isinstance(F, tuple) else (F, None)

    @property
    def F(self):
        if self._F is None:
            B, G = self._factors
            self._F = B @ G
        return self._F

    def _times_F(self, X, threads=1, GX=None):
        if self._factors is None:
            return rows_product(self._F, X, threads)
        B, G = self._factors
        return rows_product(B, rows_product(G, X, threads) if GX is None else GX, threads)

    def apply(self, T):
        """The smoothed transfer (CSR, shape of ``T``, sorted indices, no explicit zeros)."""
        T = sp.csr_matrix(T)
        Tb = T[self.block]
        for _ in range(self.iterations):
            Tb = self.step @ Tb + self.F
        source = np.arange(self.n)  # every row from T, the moved ones from Tb
        source[self.rows] = self.n + self.pos
        out = sp.vstack([T, Tb], format="csr")[source]
        out.sum_duplicates()
        out.eliminate_zeros()
        return out

    def moved_rows(self, T, X, threads=1, product=None):
        """Rows ``rows`` of ``apply(T) @ X`` (dense ``(len(rows), X.shape[1])``): the steps
        applied to ``T_block @ X`` and ``F @ X`` (``threads``: :func:`rows_product`; the
        same result for any number).

        ``product``: ``T @ X`` over every row of ``T``, where the caller has it (the same
        numbers as the block's rows of it): the first step then reads its block's rows
        in place (the step's columns mapped to rows of ``T``) instead of a product of
        its own. The steps write into two buffers in turn, each thread adding the
        guidance term to its own rows."""
        Y, at = self.smoothed_block(T, X, threads, product)
        return Y[at]

    def smoothed_block(self, T, X, threads=1, product=None):
        """``(Y, at)``: the block's rows after the steps (:meth:`moved_rows`'s arguments)
        and where the moved rows lie in it (:meth:`moved_rows` is ``Y[at]``, here without
        that copy)."""
        X = np.asarray(X)
        if product is None:
            Y = rows_product(sp.csr_matrix(T)[self.block], X, threads)
            first = self.step
        else:
            Y = np.asarray(product)
            step = self.step  # its columns as rows of T: the block's rows read in place
            first = sp.csr_matrix((step.data, self.block[step.indices], step.indptr),
                                  shape=(step.shape[0], len(Y)))
        if not self.iterations:  # (the block's rows of T X as they are)
            return Y, (self.pos if product is None else self.block[self.pos])
        FX = self._times_F(X, threads)
        buffers = [None, None]  # written in turn: a step never writes what it reads
        for it in range(self.iterations):
            Y = rows_product(first if it == 0 else self.step, Y, threads,
                             out=buffers[it % 2], add=FX)
            buffers[it % 2] = Y
        return Y, self.pos


def smooth_outside(T, x, dist, band, h, guide, *, iterations=DEFAULT_ITERATIONS,
                   top=None, neighbours=None):
    """The transfer ``T`` after ``iterations`` gradient-guided smoothing steps (module docs).

    Parameters
    ----------
    T : scipy.sparse.csr_matrix, shape (n, m)
        The transfer (points x mesh nodes).
    x : ndarray, shape (n, 3)
        The points.
    dist : ndarray, shape (n,)
        Distance of each point to the mesh (0 inside, ``inf`` where it has no row).
    band : float
        Points within this distance carry the exact (affine-reproducing) extension; only
        they move and only they (and the inside points) are neighbours.
    h : float
        Median mesh edge (mm): the scale of the ramp and of the neighbours' reach.
    guide : callable
        ``guide(rows, offsets)`` -> sparse ``(n, m)`` matrix whose row ``p`` (in ``rows``)
        is ``G_p offsets_p`` as weights on the nodal displacements, or the factors
        ``(B, G)`` of that matrix ``B @ G``.
    iterations : int
        Smoothing steps (0 returns ``T``).
    top : float, optional
        Largest step weight, in (0, 1] (default :data:`STRENGTH`).
    neighbours : int, optional
        Neighbours per point (default :data:`NEIGHBOURS`).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, m)

    Examples
    --------
    >>> import numpy as np, scipy.sparse as sp
    >>> x = np.column_stack([np.linspace(0, 3, 7), np.zeros(7), np.zeros(7)])
    >>> T = sp.csr_matrix(np.column_stack([x[:, 0] ** 2, np.ones(7)]))  # u = x^2 (node 0)
    >>> dist = np.array([0, 0, 1, 1, 1, 0, 0.0])
    >>> guide = lambda rows, o: sp.csr_matrix((o[:, 0] * 2 * x[rows, 0], (rows, 0 * rows)),
    ...                                        shape=(7, 2))  # G = du/dx = 2 x
    >>> S = smooth_outside(T, x, dist, 4.0, 1.0, guide, iterations=3)
    >>> bool(np.allclose(S[[0, 1, 5, 6]].toarray(), T[[0, 1, 5, 6]].toarray()))
    True
    """
    steps = smoothing_steps(x, dist, band, h, guide, iterations=iterations, top=top,
                            neighbours=neighbours)
    return sp.csr_matrix(T) if steps is None else steps.apply(T)
