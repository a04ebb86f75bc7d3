"""Vectorised assembly of the Mass Tensor Model as one 3x3-block sparse matrix.

The MTM tensors of paper 001 (eqs. 1-4) are the 3x3 blocks of the linear-tetrahedron
stiffness: ``K_jj`` (diagonal blocks) and ``K_jk`` (one per edge). They are built here from
the invariant form of the transversely isotropic stiffness (see :mod:`pvcmf.mtm.materials`)
with no Python loop over cells, and stored as a :class:`scipy.sparse.bsr_matrix`.
What does not depend on the material (shape-function gradients, volumes, the block sparsity
pattern and the scatter map) is computed once by :class:`Assembler`, so re-assembling with new
materials costs a few numpy passes. Delegates to numpy (products, ``bincount``) and
scipy.sparse (the BSR container).
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import pyvista as pv
import scipy.sparse as sp

from .. import arrays
from .materials import check_positive_definite, elastic_coefficients

log = logging.getLogger(__name__)

__all__ = ["Assembler", "stiffness", "tetrahedra", "grid_materials", "InvertedTetrahedraWarning"]


class InvertedTetrahedraWarning(UserWarning):
    """Some tetrahedra have the opposite orientation of the rest: the mesh folds."""

#: the 10 node pairs (a <= b) of a tetrahedron
PAIR_A = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2, 3])
PAIR_B = np.array([0, 1, 2, 3, 1, 2, 3, 2, 3, 3])
_CHUNK = 1 << 17  # cells per assembly chunk (bounds the temporaries to ~200 MB)
_CACHE_CELLS = 400_000  # keep the geometric products (800 B per cell) up to this many cells
#: build the sparse coefficient -> blocks map up to this many cells: it holds 2.2 kB per cell
#: (4.9 kB per cell peak while built: +735 MB at 150k), and above ~60k cells the saved
#: assembly time (15 ms at 30k) is small next to the numeric factorisation
_LINEAR_CELLS = 60_000


def _merge_pairs(rows, cols, n):
    """Sort ``(rows, cols)`` pairs by row, then column, and merge repeated pairs.

    Returns ``(indptr, indices, inverse)``: the CSR pattern of the distinct pairs and, for each
    input pair, the index of its distinct pair. A counting sort by row and short sorts inside
    the rows (scipy's compiled COO -> CSR conversion and index sort): at 30k tetrahedra 3 ms
    for the 300k cell pairs against 12 ms for ``np.unique(..., return_inverse=True)``.
    """
    try:  # scipy's compiled kernels behind coo -> csr (a private module, kept for decades)
        from scipy.sparse import _sparsetools
    except ImportError:  # pragma: no cover - same result, 4x slower
        return _merge_pairs_numpy(rows, cols, n)
    k = rows.size
    itype = np.int32 if max(n, k) < 2**31 - 1 else np.int64
    indptr = np.empty(n + 1, dtype=itype)
    indices = np.empty(k, dtype=itype)
    ids = np.empty(k, dtype=itype)
    _sparsetools.coo_tocsr(n, n, k, rows.astype(itype), cols.astype(itype),
                           np.arange(k, dtype=itype), indptr, indices, ids)
    _sparsetools.csr_sort_indices(n, indptr, indices, ids)
    new = np.ones(k, dtype=bool)
    new[1:] = indices[1:] != indices[:-1]
    starts = indptr[:-1]
    new[starts[starts < k]] = True  # a row's first pair is new even if the column repeats
    uid = np.cumsum(new) - 1
    inverse = np.empty(k, dtype=np.int64)
    inverse[ids] = uid
    out_ptr = np.zeros(n + 1, dtype=np.int64)
    out_ptr[1:] = uid[indptr[1:] - 1] + 1 if k else 0  # distinct pairs up to each row's end
    out_ptr[1:][indptr[1:] == 0] = 0  # rows before the first pair
    return out_ptr, indices[new].astype(np.int64), inverse


def _merge_pairs_numpy(rows, cols, n):
    """:func:`_merge_pairs` with ``np.unique`` (the reference, and the fallback)."""
    keys, inverse = np.unique(np.asarray(rows, np.int64) * n + cols, return_inverse=True)
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(keys // n, minlength=n), out=indptr[1:])
    return indptr, keys % n, inverse.ravel().astype(np.int64)


def tetrahedra(grid):
    """Return ``(points, cells)`` of an UnstructuredGrid made only of linear tetrahedra.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.mtm import tetrahedra
    >>> pts, cells = tetrahedra(pv.ImageData(dimensions=(3, 3, 3)).triangulate())
    >>> cells.shape[1]
    4
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(
            f"grid must be a pyvista.UnstructuredGrid of linear tetrahedra, got {type(grid).__name__}"
        )
    if grid.n_cells == 0:
        raise ValueError("grid must have at least one tetrahedron, got 0 cells")
    types = np.asarray(grid.celltypes)
    if np.any(types != pv.CellType.TETRA):
        bad = np.unique(types[types != pv.CellType.TETRA])
        raise ValueError(
            f"grid must contain only linear tetrahedra (VTK type {int(pv.CellType.TETRA)}), "
            f"got cell types {bad.tolist()}; triangulate or re-mesh it first"
        )
    cells = np.asarray(grid.cell_connectivity, dtype=np.int64).reshape(-1, 4)
    return np.asarray(grid.points, dtype=float), cells


def grid_materials(grid, *, E_fiber=None, E_cross=None, nu=None, fiber=None):
    """Per-cell ``(E_fiber, E_cross, nu, fiber)`` from the grid's cell arrays, with overrides.

    ``E_cross`` defaults to ``E_fiber`` and ``fiber`` to zero (isotropic) when absent. An
    override may be a scalar or a per-cell array. Checks positive definiteness and that
    anisotropic cells have a fibre.
    """
    m = grid.n_cells

    def get(name, value, default=None):
        if value is not None:
            v = np.asarray(value, dtype=float)
            if v.ndim == 0:
                return np.full(m, float(v))
            if v.shape != (m,):
                raise ValueError(f"{name} must be a scalar or have shape ({m},), got {v.shape}")
            return v.astype(float, copy=True)
        if name in grid.cell_data.keys() or default is None:
            return np.asarray(
                arrays.require_array(grid, name, "cell", dtype="f", ncomp=1,
                                     producer="assign_materials"), dtype=float)
        return default

    ef = get(arrays.E_FIBER, E_fiber)
    ec = get(arrays.E_CROSS, E_cross, default=ef)
    nu_ = get(arrays.NU, nu)
    check_positive_definite(ef, ec, nu_)
    if fiber is not None:
        a = np.asarray(fiber, dtype=float)
        a = np.broadcast_to(a, (m, 3)) if a.shape == (3,) else a
        if a.shape != (m, 3):
            raise ValueError(f"fiber must have shape (3,) or ({m}, 3), got {a.shape}")
    elif arrays.FIBER in grid.cell_data.keys():
        a = np.asarray(arrays.require_array(grid, arrays.FIBER, "cell", dtype="f", ncomp=3,
                                            producer="assign_materials"), dtype=float)
    else:
        a = np.zeros((m, 3))
    norm = np.linalg.norm(a, axis=1)
    aniso = ef != ec
    missing = np.flatnonzero(aniso & ~(norm > 0))
    if missing.size:
        raise ValueError(
            f"fiber must be a nonzero vector where E_fiber != E_cross; {missing.size} cell(s) "
            f"have none, e.g. cell {missing[0]} (run fiber_directions or pass fiber=)"
        )
    unit = np.zeros_like(a)
    unit[aniso] = a[aniso] / norm[aniso, None]
    return ef, ec, nu_, unit


class Assembler:
    """Material-independent part of the MTM assembly for one tetrahedral mesh.

    Parameters
    ----------
    points : (n, 3) float array
    cells : (m, 4) int array

    Attributes
    ----------
    cells : (m, 4) the cells with each cell's nodes in increasing order (same tetrahedra)
    volumes : (m,) cell volumes (mm^3)
    gradients : (m, 4, 3) gradients of the barycentric shape functions (of ``cells``)
    indptr, indices : the full block-sparsity pattern (CSR of 3x3 blocks)
    rows : (nnzb,) block row of each stored block

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.mtm import Assembler, tetrahedra
    >>> asm = Assembler(*tetrahedra(pv.ImageData(dimensions=(3, 3, 3)).triangulate()))
    >>> K = asm.matrix(1.0, 1.0, 0.3)
    >>> K.blocksize, K.shape
    ((3, 3), (81, 81))
    """

    def __init__(self, points, cells):
        pts = np.asarray(points, dtype=float)
        cells = np.asarray(cells, dtype=np.int64)
        if cells.ndim != 2 or cells.shape[1] != 4:
            raise ValueError(f"cells must have shape (m, 4), got {cells.shape}")
        n = pts.shape[0]
        if cells.size and (cells.min() < 0 or cells.max() >= n):
            raise ValueError(f"cells must index points 0..{n - 1}, got {cells.min()}..{cells.max()}")
        self.n_points, self.n_cells = n, cells.shape[0]
        # number each cell's nodes in increasing global order: every local pair a <= b is
        # then a global pair, and its block lands in the upper triangle as computed, with no
        # transposed copies; an odd permutation flips the sign of the volume
        sorted_cells = np.sort(cells, axis=1)
        odd = np.zeros(self.n_cells, dtype=bool)
        for a, b in zip(PAIR_A, PAIR_B):
            if a < b:
                odd ^= cells[:, a] > cells[:, b]
        # geometry on coordinate rows (3, m): contiguous products, no np.cross
        P = np.ascontiguousarray(pts.T)
        x = [P[:, sorted_cells[:, k]] for k in range(4)]
        e1, e2, e3 = x[1] - x[0], x[2] - x[0], x[3] - x[0]

        def cross(u, v):
            return np.stack([u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                             u[0] * v[1] - u[1] * v[0]])

        c23, c31, c12 = cross(e2, e3), cross(e3, e1), cross(e1, e2)
        det = (e1 * c23).sum(axis=0)
        scale = np.maximum.reduce([(e * e).sum(axis=0) for e in (e1, e2, e3)]) ** 1.5
        degenerate = np.flatnonzero(~(np.abs(det) > 1e-13 * scale))
        if degenerate.size:
            raise ValueError(
                f"grid has {degenerate.size} degenerate (zero-volume) tetrahedra, "
                f"e.g. cell {degenerate[0]} with nodes {cells[degenerate[0]].tolist()}"
            )
        neg = (det < 0) != odd  # orientation in the grid's own node order
        n_neg = int(neg.sum())
        if 0 < n_neg < self.n_cells:
            minority = neg if n_neg <= self.n_cells - n_neg else ~neg
            warnings.warn(
                f"{int(minority.sum())} of {self.n_cells} tetrahedra are inverted relative to the "
                f"others (e.g. cell {int(np.flatnonzero(minority)[0])}): the mesh folds over "
                "itself and the MTM answer is not meaningful there; untangle or re-mesh it",
                InvertedTetrahedraWarning, stacklevel=2,
            )
        self.cells = cells = sorted_cells
        gt = np.empty((4, 3, self.n_cells))  # gradients, node-major rows of contiguous cells
        np.divide(c23, det, out=gt[1])
        np.divide(c31, det, out=gt[2])
        np.divide(c12, det, out=gt[3])
        np.negative(gt[1] + gt[2] + gt[3], out=gt[0])
        self._gt = gt
        self.volumes = np.abs(det) / 6.0

        # the upper-triangle blocks (node pairs lo <= hi) and where each cell pair adds to
        lo, hi = cells[:, PAIR_A].ravel(), cells[:, PAIR_B].ravel()
        up_ptr, up_c, inv = _merge_pairs(lo, hi, n)
        self._scatter = np.ascontiguousarray(inv.reshape(self.n_cells, 10).T)  # (10, m)
        up_r = np.repeat(np.arange(n), np.diff(up_ptr))
        self.n_upper = up_c.size
        off = up_r != up_c
        self._off = np.flatnonzero(off)
        # the full pattern: the upper blocks and the transposes of the off-diagonal ones
        rows = np.concatenate([up_r, up_c[off]])
        cols = np.concatenate([up_c, up_r[off]])
        self.indptr, indices, where = _merge_pairs(rows, cols, n)
        self.indices = indices.astype(np.int32)
        self.indptr = self.indptr.astype(np.int32)
        self.rows = np.repeat(np.arange(n), np.diff(self.indptr))
        self._upper_pos = where[: up_c.size]  # position of upper block k in the full pattern
        self._lower_pos = where[up_c.size:]  # position of the transpose of upper block off[k]
        self.nnzb = rows.size
        self.used = np.zeros(n, dtype=bool)
        self.used[cells.ravel()] = True
        log.debug("Assembler: %d points, %d cells, %d blocks", n, self.n_cells, self.nnzb)

    @property
    def gradients(self):
        """Gradients of the barycentric shape functions, ``(m, 4, 3)`` (a view)."""
        return np.moveaxis(self._gt, 2, 0)

    # ------------------------------------------------------------------ assembly
    def _geometry_products(self, e):
        """Material-independent ``Q_ij = V g_row_i g_col_j`` (9, 10, k) and ``V g_row.g_col``.

        Pair-major layout (pair, cell) so every product below runs on contiguous rows.
        """
        cached = getattr(self, "_q_cache", None)
        if cached is not None and e == slice(0, self.n_cells):
            return cached
        gt = self._gt[:, :, e]
        ga = gt[PAIR_A] * self.volumes[e]  # (10, 3, k), V-weighted
        gb = gt[PAIR_B]
        q = np.empty((9, 10, ga.shape[2]))
        for i in range(3):
            for j in range(3):
                np.multiply(ga[:, i], gb[:, j], out=q[3 * i + j])
        dot = q[0] + q[4] + q[8]
        out = (q, dot)
        if e == slice(0, self.n_cells) and self.n_cells <= _CACHE_CELLS:
            self._q_cache = out
        return out

    def upper_blocks(self, E_fiber, E_cross, nu, fiber=None):
        """Assembled blocks of the upper triangle, shape ``(n_upper, 3, 3)``."""
        m = self.n_cells
        ef, ec, nu = (np.broadcast_to(np.asarray(x, dtype=float), (m,)) for x in (E_fiber, E_cross, nu))
        check_positive_definite(ef, ec, nu)
        lam, muT, alpha, muL, beta = elastic_coefficients(ef, ec, nu)
        aniso = ef != ec
        if np.any(aniso):
            if fiber is None:
                raise ValueError("fiber is required where E_fiber != E_cross")
            a_all = np.broadcast_to(np.asarray(fiber, dtype=float), (m, 3))
        out = np.zeros((9, self.n_upper))
        chunk = m if m <= _CACHE_CELLS else _CHUNK
        for s in range(0, m, chunk):
            e = slice(s, min(s + chunk, m))
            ani = np.flatnonzero(aniso[e])
            fibre = None
            if ani.size:
                cells = ani + s
                fibre = self._aniso_terms(cells, a_all[cells], alpha[cells], (muL - muT)[cells],
                                          beta[cells])
            k = self._isotropic_blocks(e, lam[e], muT[e])
            if fibre is not None:
                k[:, :, ani] += fibre
            idx = self._scatter[:, e].ravel()
            for c in range(9):
                out[c] += np.bincount(idx, weights=k[c].ravel(), minlength=self.n_upper)
        return out.T.reshape(-1, 3, 3)

    #: cells per pass of :meth:`_isotropic_blocks` (its temporaries stay in the cache: at 30k
    #: tetrahedra 15 ms CPU against 27 ms in one pass)
    _PASS = 4096

    def _isotropic_blocks(self, e, lam, mu):
        """The 9 entries ``(9, 10, k)`` of ``V (lam g_a g_b^T + mu g_b g_a^T + mu g_a.g_b I)``.

        From the cached geometric products when :meth:`linear_upper_blocks` built them, else
        straight from the gradients, :attr:`_PASS` cells at a time.
        """
        cached = getattr(self, "_q_cache", None)
        if cached is not None and e == slice(0, self.n_cells):
            q, dot = cached
            k = np.empty_like(q)
            mudot = mu * dot
            for i in range(3):
                for j in range(3):
                    c = np.multiply(lam, q[3 * i + j], out=k[3 * i + j])
                    c += mu * q[3 * j + i]
                    if i == j:
                        c += mudot
            return k
        start, stop = e.indices(self.n_cells)[:2]
        k = np.empty((9, 10, stop - start))
        for s in range(start, stop, self._PASS):
            f = slice(s, min(s + self._PASS, stop))
            o = slice(f.start - start, f.stop - start)
            gt = self._gt[:, :, f]  # (4, 3, p)
            ga, gb = gt[PAIR_A], gt[PAIR_B]  # (10, 3, p): rows of p contiguous values
            vol = self.volumes[f]
            la_ga = ga * (lam[o] * vol)
            mu_ga = ga * (mu[o] * vol)
            mudot = mu_ga[:, 0] * gb[:, 0]
            mudot += mu_ga[:, 1] * gb[:, 1]
            mudot += mu_ga[:, 2] * gb[:, 2]
            tmp = np.empty_like(mudot)
            for i in range(3):
                for j in range(3):
                    c = np.multiply(la_ga[:, i], gb[:, j], out=k[3 * i + j, :, o])
                    c += np.multiply(mu_ga[:, j], gb[:, i], out=tmp)
                    if i == j:
                        c += mudot
        return k

    def linear_upper_blocks(self, E_fiber, E_cross, nu, fiber=None):
        """:meth:`upper_blocks` as one sparse matrix-vector product (for repeated assembly).

        The assembled blocks are linear in the per-cell coefficients ``(lambda, mu_T)`` (every
        cell) and ``(alpha, mu_L - mu_T, beta)`` (anisotropic cells). The first call builds
        the sparse map ``S`` (90 entries per cell and coefficient) from the cached geometric
        products; afterwards a new material costs one CSR product instead of nine scatters
        (at 30k tetrahedra 6 ms instead of 21 ms CPU; building it costs about 80 ms). The map is rebuilt when the anisotropic
        cells or their fibres change. Falls back to :meth:`upper_blocks` above
        ``_LINEAR_CELLS`` cells (memory).
        """
        m = self.n_cells
        if m > _LINEAR_CELLS:
            return self.upper_blocks(E_fiber, E_cross, nu, fiber)
        ef, ec, nu = (np.broadcast_to(np.asarray(x, dtype=float), (m,)) for x in (E_fiber, E_cross, nu))
        check_positive_definite(ef, ec, nu)
        lam, muT, alpha, muL, beta = elastic_coefficients(ef, ec, nu)
        ani = np.flatnonzero(ef != ec)
        if ani.size:
            if fiber is None:
                raise ValueError("fiber is required where E_fiber != E_cross")
            a = np.array(np.broadcast_to(np.asarray(fiber, dtype=float), (m, 3))[ani])
        else:
            a = np.zeros((0, 3))
        x = np.concatenate([lam, muT, alpha[ani], (muL - muT)[ani], beta[ani]])
        return (self.linear_map(ani, a) @ x).reshape(9, self.n_upper).T.reshape(-1, 3, 3)

    def group_upper_blocks(self, label, n_groups, ani, a):
        """Upper blocks per (material group, coefficient), entry-major, for a sweep's basis.

        ``label`` (m,) numbers each cell's material group; ``ani`` are the anisotropic cells
        with fibres ``a``. Returns ``(U, group, kind)``: ``U[k]`` holds the blocks of the cells of group ``group[k]`` for a unit value of coefficient
        ``kind[k]`` (0 lambda, 1 mu_T, 2 alpha, 3 mu_L - mu_T, 4 beta; 2-4 only for groups with
        anisotropic cells) and zero for every other coefficient, so the stiffness of any
        materials that are constant on the groups is ``sum_k coef_k U[k]``; ``U`` has shape
        ``(K, 9, n_upper)`` (entry-major blocks). Scatters straight from the cached geometric
        products, all groups in one ``bincount`` per entry (no :meth:`linear_map`).
        """
        q, dot = self._geometry_products(slice(0, self.n_cells))
        transpose = [3 * (c % 3) + c // 3 for c in range(9)]
        aniso_group = np.zeros(n_groups, dtype=bool)
        aniso_group[label[ani]] = True
        group, kind = [], []
        for gi in range(n_groups):
            group += [gi] * (5 if aniso_group[gi] else 2)
            kind += [0, 1, 2, 3, 4] if aniso_group[gi] else [0, 1]
        group, kind = np.array(group), np.array(kind)
        nu_ = self.n_upper
        U = np.zeros((len(group), 9, nu_))
        # one scatter per entry for all groups at once: block index + n_upper * group
        idx = (self._scatter + nu_ * label[None, :]).ravel()
        col = {(g, c): k for k, (g, c) in enumerate(zip(group, kind))}
        lam_cols = [col[g, 0] for g in range(n_groups)]
        mu_cols = [col[g, 1] for g in range(n_groups)]
        for c in range(9):
            U[lam_cols, c] = np.bincount(idx, weights=q[c].ravel(),
                                         minlength=nu_ * n_groups).reshape(n_groups, nu_)
            w = q[transpose[c]] + dot if c in (0, 4, 8) else q[transpose[c]]
            U[mu_cols, c] = np.bincount(idx, weights=w.ravel(),
                                        minlength=nu_ * n_groups).reshape(n_groups, nu_)
        for gi in np.flatnonzero(aniso_group):
            sel = label[ani] == gi
            cg, ag = ani[sel], a[sel]
            gidx = self._scatter[:, cg].ravel()
            one, zero = np.ones(cg.size), np.zeros(cg.size)
            for c, coef in enumerate(((one, zero, zero), (zero, one, zero), (zero, zero, one))):
                t = self._aniso_terms(cg, ag, *coef)
                for e in range(9):
                    U[col[gi, 2 + c], e] = np.bincount(gidx, weights=t[e].ravel(), minlength=nu_)
        return U, group, kind

    def linear_map(self, ani, a):
        """The sparse map ``S`` from per-cell coefficients to the upper blocks (cached).

        Columns: ``lambda`` and ``mu_T`` of every cell, then ``alpha``, ``mu_L - mu_T`` and
        ``beta`` of the anisotropic cells ``ani`` (fibres ``a``, one row per cell of ``ani``);
        rows: the 9 entries of every upper block, entry-major (``9 x n_upper``). Rebuilt when
        ``ani`` or ``a`` change.
        """
        key = getattr(self, "_linear_key", None)
        if key is None or not (np.array_equal(key[0], ani) and np.array_equal(key[1], a)):
            self._linear = self._build_linear(ani, a)
            self._linear_key = (np.array(ani), np.array(a))
        return self._linear

    def _build_linear(self, ani, a):
        t = time.perf_counter()
        m, nu_ = self.n_cells, self.n_upper
        q, dot = self._geometry_products(slice(0, m))
        transpose = [3 * (c % 3) + c // 3 for c in range(9)]
        qmu = q[transpose]
        qmu[[0, 4, 8]] += dot
        parts = [q, qmu]
        if ani.size:
            one, zero = np.ones(ani.size), np.zeros(ani.size)
            for coef in ((one, zero, zero), (zero, one, zero), (zero, zero, one)):
                parts.append(self._aniso_terms(ani, a, *coef))
        # column j of S holds the 90 block entries one cell contributes per unit coefficient
        data = np.concatenate([np.ascontiguousarray(p.transpose(2, 0, 1)).ravel() for p in parts])
        itype = np.int32 if 9 * nu_ < 2**31 else np.int64
        rows_cell = (np.arange(9, dtype=itype)[None, :, None] * itype(nu_)
                     + self._scatter.T.astype(itype)[:, None, :]).reshape(m, 90)  # (m, 9 x 10)
        rows = [rows_cell] * 2 + [rows_cell[ani]] * (3 if ani.size else 0)
        rows = np.concatenate(rows).ravel()
        ncol = rows.size // 90
        # CSC as built (no conversion: a CSR copy costs 80 ms at 30k and multiplies as fast)
        S = sp.csc_matrix((data, rows, np.arange(0, rows.size + 1, 90)), shape=(9 * nu_, ncol))
        log.debug("linear assembly map: %d x %d, %d entries, %.3f s", S.shape[0], ncol, S.nnz,
                  time.perf_counter() - t)
        return S

    def _aniso_terms(self, cells, a, alpha, dmu, beta):
        """Fibre terms of the invariant form, (9, 10, k) in the oriented pair layout.

        ``alpha (p_a a g_b^T + p_b g_a a^T) + (muL - muT) ((g_a.g_b) a a^T + p_b a g_a^T
        + p_a g_b a^T + p_a p_b I) + beta p_a p_b a a^T`` with ``p = a . g`` (times V).
        """
        gt = self._gt[:, :, cells]  # (4, 3, k)
        ga = gt[PAIR_A] * self.volumes[cells]  # (10, 3, k)
        gb = gt[PAIR_B]
        a = np.ascontiguousarray(a.T)  # (3, k)
        pa = ga[:, 0] * a[0] + ga[:, 1] * a[1] + ga[:, 2] * a[2]  # (10, k)
        pb = gb[:, 0] * a[0] + gb[:, 1] * a[1] + gb[:, 2] * a[2]
        dot = ga[:, 0] * gb[:, 0] + ga[:, 1] * gb[:, 1] + ga[:, 2] * gb[:, 2]
        pab = pa * pb
        # term_ij = a_i P_j + a_j R_i (+ dmu p_a p_b on the diagonal) with
        # P_j = alpha p_a g_b_j + dmu p_b g_a_j and R_i = alpha p_b g_a_i + dmu p_a g_b_i
        # + (dmu g_a.g_b + beta p_a p_b) a_i
        ap, bp, dq, dp = alpha * pa, alpha * pb, dmu * pa, dmu * pb
        c = dmu * dot + beta * pab
        P = [ap * gb[:, j] + dp * ga[:, j] for j in range(3)]
        R = [bp * ga[:, i] + dq * gb[:, i] + c * a[i] for i in range(3)]
        diag = dmu * pab
        t = np.empty((9, 10, len(cells)))
        for i in range(3):
            for j in range(3):
                v = t[3 * i + j]
                np.multiply(a[i], P[j], out=v)
                v += a[j] * R[i]
                if i == j:
                    v += diag
        return t

    def full_blocks(self, upper):
        """Full (symmetric) block data in the order of :attr:`indices`."""
        data = np.empty((self.nnzb, 3, 3))
        data[self._upper_pos] = upper
        data[self._lower_pos] = np.swapaxes(upper[self._off], 1, 2)
        return data

    def bsr(self, data):
        """Wrap full block data in a :class:`scipy.sparse.bsr_matrix`."""
        n3 = 3 * self.n_points
        return sp.bsr_matrix((data, self.indices, self.indptr), shape=(n3, n3))

    def matrix(self, E_fiber, E_cross, nu, fiber=None):
        """The stiffness (MTM tensors) for the given per-cell materials."""
        return self.bsr(self.full_blocks(self.upper_blocks(E_fiber, E_cross, nu, fiber)))


def stiffness(grid, *, E_fiber=None, E_cross=None, nu=None, fiber=None, progress_bar=False):
    """Assemble the MTM tensors of a tetrahedral grid as one 3x3-block sparse matrix.

    Diagonal blocks are paper 001's ``K_jj``, off-diagonal blocks its ``K_jk``; the elastic
    force at the nodes is ``K @ u.ravel()``. Symmetric (the lower triangle is the transpose of
    the upper), rigid motions in its null space.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with cell arrays ``E_fiber``, ``nu`` and optionally ``E_cross``
        (default ``E_fiber``) and ``fiber`` (see :func:`pvcmf.filters.assign_materials`).
    E_fiber, E_cross, nu, fiber : scalar or per-cell array, optional
        Override the grid's arrays.
    progress_bar : bool
        Accepted for uniformity; assembly is a few vectorised passes.

    Returns
    -------
    scipy.sparse.bsr_matrix
        Shape ``(3 n, 3 n)`` with blocksize ``(3, 3)``; units MPa mm = N/mm.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> grid = pv.ImageData(dimensions=(4, 4, 4)).triangulate()
    >>> K = pvcmf.mtm.stiffness(grid, E_fiber=1.0, nu=0.3)
    >>> u = np.tile([1.0, 2.0, 3.0], grid.n_points)     # a translation
    >>> bool(np.abs(K @ u).max() < 1e-12)
    True
    """
    points, cells = tetrahedra(grid)
    ef, ec, nu_, a = grid_materials(grid, E_fiber=E_fiber, E_cross=E_cross, nu=nu, fiber=fiber)
    return Assembler(points, cells).matrix(ef, ec, nu_, a)
