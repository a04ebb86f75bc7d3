"""Where points lie relative to a tetrahedral mesh: containing tetrahedra and boundary feet.

The geometric half of :func:`pvcmf.filters.surface_mapping.transfer_operator` (which turns
:class:`Located` into the sparse operator) and of its crumple metric. Every step is one
vectorised call over all points: the tetrahedra's bounding boxes binned on a uniform grid
(one integer sort) give the candidate tetrahedra of a point (those whose box holds it, tested
one axis at a time), precomputed inverse edge matrices give the barycentric coordinates of
all candidates at once, :class:`scipy.spatial.cKDTree` nearest-neighbour queries give
boundary triangles and boundary nodes, and the
closest points on the candidate triangles are computed for all (point, triangle) pairs at
once (Ericson's region test, vectorised: two dot products per pair with each triangle's
Gram entries, in cache-sized chunks). :func:`mesh_band` gives the distance from the mesh
within which it models a skin (its surface spacing).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .skin import _boundary_faces

__all__ = ["DEFAULT_BAND", "Located", "MeshIndex", "closest_on_triangles", "gradient_operators",
           "mesh_band", "resolve_band", "stacked_gradients", "tetra", "tet_gradients"]

#: barycentric coordinates down to this (negative) value still count as inside a tetrahedron
INSIDE_TOL = 1e-6
#: width of the foot blend (in units of d h / (d + h), d the distance, h the median boundary edge)
WINDOW = 10.0
#: smallest distance (mm) from the mesh within which the extension is exactly affine (the
#: modelled skin; :func:`mesh_band`); beyond the band it falls smoothly to zero at twice it
DEFAULT_BAND = 4.0


def tetra(grid):
    """Points (float64) and tetrahedra (int64, (m, 4)) of an all-tetrahedral grid."""
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid of tetrahedra, got "
                        f"{type(grid).__name__}")
    cells = grid.cells_dict
    tet = cells.get(pv.CellType.TETRA, cells.get(int(pv.CellType.TETRA)))
    if tet is None or len(tet) != grid.n_cells or grid.n_cells == 0:
        raise ValueError(f"grid must hold tetrahedra only, got cell types {sorted(cells)} "
                         f"({grid.n_cells} cells)")
    return np.asarray(grid.points, dtype=float), np.asarray(tet, dtype=np.int64)


def tet_gradients(points, tets):
    """Per tetrahedron: ``E^-1`` (m, 3, 3) with ``grad u = E^-1 (u_a - u_0)_a`` (zero for a
    degenerate tetrahedron) and volumes."""
    edges = points[tets[:, 1:]] - points[tets[:, :1]]
    det = np.linalg.det(edges)
    ok = np.abs(det) > 1e-300
    inv = np.zeros_like(edges)
    inv[ok] = np.linalg.inv(edges[ok])
    return inv, np.abs(det) / 6.0


def gradient_operators(points, tets, rows, gradients=None):
    """Sparse ``(len(rows), n)`` operators ``D_c`` (c = x, y, z): the volume-weighted mean
    of the displacement gradients of the tetrahedra around each node ``rows``
    (``gradients``: :func:`~pvcmf.filters.transfer_locate.tet_gradients` if known)."""
    n, m = len(points), len(tets)
    inv, vol = tet_gradients(points, tets) if gradients is None else gradients
    coef = np.empty((m, 3, 4))  # d/dx_c of the linear interpolant: coefficient of node a
    coef[:, :, 1:] = inv
    coef[:, :, 0] = -inv.sum(axis=2)
    slot = np.full(n, -1)
    slot[rows] = np.arange(len(rows))
    t_of = np.repeat(np.arange(m), 4)
    node = tets.ravel()
    keep = slot[node] >= 0
    avg = sp.csr_matrix((vol[t_of[keep]], (slot[node[keep]], t_of[keep])), shape=(len(rows), m))
    total = np.asarray(avg.sum(axis=1)).ravel()
    avg = sp.diags(1.0 / np.where(total > 0, total, 1.0)) @ avg
    out = []
    for c in range(3):
        grad = sp.csr_matrix((coef[:, c, :].ravel(), (t_of, node)), shape=(m, n))
        out.append((avg @ grad).tocsr())
    return out


def stacked_gradients(loc):
    """The nodal gradient operators at the boundary nodes, stacked x, y, z (CSR), kept on
    the mesh's index where ``loc`` has one (points located in parts share them)."""
    index = getattr(loc, "index", None)
    D = getattr(index, "stacked_gradients", None)
    if D is None:
        D = sp.vstack(gradient_operators(loc.points, loc.tets, loc.boundary, loc.gradients),
                      format="csr")
        if index is not None:
            index.stacked_gradients = D
    return D


def closest_on_triangles(p, a, b, c):
    """Closest points of triangles ``abc`` to ``p`` and their barycentric coordinates
    (vectorised form of Ericson's region test)."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    bary = _regions(dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp))
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


class _TriangleSet:
    """Boundary triangles with what the feet need: circumradii about the centroids, a
    :class:`~scipy.spatial.cKDTree` of the centroids, the median edge ``h`` and
    :class:`_Triangles`."""

    def __init__(self, points, tri):
        corners = points[tri]
        centre = corners.mean(axis=1)
        self.radius = np.linalg.norm(corners - centre[:, None, :], axis=2).max(axis=1)
        self.tree = cKDTree(centre, balanced_tree=False)
        e = corners[:, [0, 1, 2]] - corners[:, [1, 2, 0]]
        self.h = float(np.median(np.linalg.norm(e, axis=2)))
        self.frames = _Triangles(corners)


def mesh_band(grid):
    """The band (mm) within which a mesh models the skin: the larger of
    :data:`DEFAULT_BAND` (a voxel or two of the scan) and the median edge of the mesh's
    boundary triangles. A mesh follows the skin at its surface spacing: it cuts bumps and
    loses tissue thinner than about an edge (the forehead over a coarse mesh), leaving
    skin up to about an edge outside it, which the mesh still models.

    ``grid``: a tetrahedral mesh or its :class:`~pvcmf.filters.transfer_locate.MeshIndex`.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.filters.transfer_locate import mesh_band
    >>> mesh_band(pv.ImageData(dimensions=(4, 4, 4), spacing=(1, 1, 1)).triangulate())
    4.0
    >>> round(mesh_band(pv.ImageData(dimensions=(4, 4, 4), spacing=(6, 6, 6)).triangulate()), 3)
    6.0
    """
    if isinstance(grid, MeshIndex):
        return max(DEFAULT_BAND, grid.boundary_edge)
    pts, tets = tetra(grid)  # the boundary only: no need for a whole MeshIndex
    src = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, pts)
    return max(DEFAULT_BAND, _triangle_edges(pts, _boundary_faces(src))[0])


def _triangle_edges(pts, tri):
    """``(median, max)`` edge length of the triangles ``tri`` (0 without any)."""
    if not len(tri):
        return 0.0, 0.0
    length = np.linalg.norm(pts[tri[:, [0, 1, 2]]] - pts[tri[:, [1, 2, 0]]], axis=2)
    return float(np.median(length)), float(length.max())


def resolve_band(band, index):
    """``band`` as a float (None: :func:`mesh_band` of ``index``), validated."""
    if band is None:
        return mesh_band(index)
    try:
        value = None if isinstance(band, bool) else float(band)
    except (TypeError, ValueError):
        value = None
    if value is None or not value > 0:
        raise ValueError(f"band must be > 0 mm, numpy.inf or None (from the mesh), got {band!r}")
    return value


class MeshIndex:
    """The mesh's half of :class:`Located`, made once and shared by the point sets located
    against it (``Located(grid, points, index=index)``): the tetrahedra's
    :func:`tet_gradients`, their bounding boxes binned on a grid, the boundary triangles
    and nodes (``boundary_edge``: their median edge) and a
    :class:`~scipy.spatial.cKDTree` of the nodes; the triangles' own tree
    (:class:`_TriangleSet`) and the median tetrahedron edge on first use. Points located
    with one index, in any split, get the same answers as all of them at once."""

    def __init__(self, grid):
        self.points, self.tets = pts, tets = tetra(grid)
        self.gradients = tet_gradients(pts, tets)
        vol = self.gradients[1]
        self.usable = usable = np.flatnonzero(vol > 1e-300 / 6.0)  # degenerate: holds nothing
        corners = pts[tets[usable]]
        radius = np.linalg.norm(corners - corners.mean(axis=1, keepdims=True), axis=2).max(axis=1)
        pad = (radius * 8 * INSIDE_TOL + 1e-9 * float(radius.max(initial=1.0)))[:, None]
        lo, hi = corners.min(axis=1) - pad, corners.max(axis=1) + pad
        self.box_rows = (np.ascontiguousarray(lo.T), np.ascontiguousarray(hi.T))
        self.bins = _BoxBins(lo, hi) if usable.size else None
        src = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, pts)
        self.tri = tri = _boundary_faces(src)
        self.boundary = np.unique(tri)
        self.btree = cKDTree(pts[self.boundary], balanced_tree=False)
        #: median edge of the boundary triangles (mm; 0 without a boundary)
        self.boundary_edge, self.h_max = _triangle_edges(pts, tri)
        self._triangles = self._median = None

    @property
    def triangles(self):
        """The boundary triangles' :class:`_TriangleSet` (made on first use)."""
        if self._triangles is None:
            self._triangles = _TriangleSet(self.points, self.tri)
        return self._triangles

    @property
    def median_edge(self):
        """Median edge length of the tetrahedra (mm)."""
        if self._median is None:
            tets = self.tets
            e = self.points[tets[:, [1, 2, 3, 2, 3, 3]]] - self.points[tets[:, [0, 0, 0, 1, 1, 2]]]
            self._median = float(np.median(np.linalg.norm(e, axis=2)))
        return self._median


class Located:
    """Where points lie relative to a tetrahedral mesh (shared by the transfer and the
    crumple metric).

    Inside: the containing tetrahedron and barycentric coordinates. Outside, within
    ``reach`` of the mesh: "feet" on the boundary, one per nearby boundary triangle whose
    distance is within a window of the smallest (width ``10 d_1 h / (d_1 + h)``, ``h`` the
    median boundary edge), each with its closest point; the feet are blended with weights
    ``(1 - s^2)^2`` (``s`` the excess distance over the window), so the blended foot
    ``q`` never jumps where the closest triangle changes (concave boundary), and the blend
    shrinks to the closest point as the point nears the boundary. The ``k`` boundary nodes
    nearest to ``q`` and their smooth weights give the gradient ``G(q)``. ``dist`` is the
    distance to the mesh (0 inside, ``inf`` beyond ``reach``: such points get no feet).
    ``gradients`` holds the tetrahedra's :func:`tet_gradients` (for the operator).
    """

    def __init__(self, grid, points, k=8, n_triangles=24, reach=np.inf, index=None):
        if index is None:
            index = MeshIndex(grid)
        self.index = index
        self.points, self.tets = index.points, index.tets
        p = np.asarray(points, dtype=float)
        self.p = p
        self._find_cells()
        tri = index.tri
        self.boundary = index.boundary
        self.dist = np.where(self.inside, 0.0, np.inf)
        out = np.flatnonzero(~self.inside)
        btree = index.btree
        if out.size and np.isfinite(reach):  # cheap reject: far from every boundary node
            h_max = index.h_max
            dn = btree.query(p[out], distance_upper_bound=reach + h_max)[0]
            out = out[dn - h_max <= reach]
        self.outside = out
        n_pairs = 0
        if out.size:
            rows, q, bary, face = self._feet(tri, out, n_triangles, reach=reach)
            n_pairs = len(rows)
            out = self.outside = rows[np.r_[True, rows[1:] != rows[:-1]]] if n_pairs else out
            slot = np.full(len(p), -1)
            slot[out] = np.arange(out.size)
            qbar = np.zeros((out.size, 3))  # blended foot: sum of the feet's weights is 1
            for c in range(3):
                qbar[:, c] = np.bincount(slot[rows], self.pair_w * q[:, c], minlength=out.size)
            kk = max(1, min(k, len(self.boundary) - 1))
            dist, idx = btree.query(qbar, k=kk + 1)
            dist, idx = dist.reshape(out.size, -1), idx.reshape(out.size, -1)
            h = dist[:, -1:]
            s = np.where(h > 0, dist[:, :-1] / np.where(h > 0, h, 1.0), 0.0)
            w = (1.0 - s**2) ** 2
            w /= w.sum(axis=1, keepdims=True)
            self.near, self.near_w = idx[:, :-1], w  # per outside point, into self.boundary
            self.pair_row, self.q, self.face_bary, self.face = rows, q, bary, face
            self.qbar = qbar
        if not n_pairs:
            self.outside = np.zeros(0, dtype=np.int64)
            self.pair_row, self.pair_w = np.zeros(0, dtype=np.int64), np.zeros(0)
            self.q, self.qbar = np.zeros((0, 3)), np.zeros((0, 3))
            self.face_bary, self.face = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
            self.near, self.near_w = np.zeros((0, 1), dtype=np.int64), np.zeros((0, 1))

    def _find_cells(self):
        """Containing tetrahedra. A point whose barycentric coordinates are all above
        ``-INSIDE_TOL`` lies in the tetrahedron's bounding box widened by ``8 INSIDE_TOL``
        times its largest centroid-corner distance, so binning the boxes on a uniform grid
        (spacing: half the median box size) lists every candidate of a point (the tetrahedra
        whose boxes share its bin); the barycentric coordinates of all candidate pairs
        (vectorised, in chunks) pick, per point, the tetrahedron whose smallest coordinate
        is largest (the one that holds it; on a shared face, either)."""
        p, pts, tets = self.p, self.points, self.tets
        n = len(p)
        self.gradients = inv, vol = self.index.gradients  # reused by the operator
        usable = self.index.usable
        cell = np.full(n, -1, dtype=np.int64)
        bary = np.zeros((n, 4))
        score = np.full(n, -np.inf)
        if usable.size:
            tet_of, start, stop, pkey = self.index.bins.of(p)
            axes, (lo_t, hi_t) = np.ascontiguousarray(p.T), self.index.box_rows
            count = stop - start
            bounds = np.searchsorted(np.cumsum(count), np.arange(0, count.sum(), 1 << 20))
            for a, b in zip(bounds, np.r_[bounds[1:], n]):  # ~1M pairs per chunk
                c = count[a:b]
                if not c.sum():
                    continue
                idx = np.repeat(np.arange(a, b), c)  # pairs grouped by point
                first = np.cumsum(c) - c
                pos = np.arange(c.sum()) - np.repeat(first, c) + np.repeat(start[a:b], c)
                box = tet_of[pos]
                for ax in range(3):  # one axis at a time: each test sees the survivors only
                    x = axes[ax][idx]
                    keep = (x >= lo_t[ax][box]) & (x <= hi_t[ax][box])
                    idx, box = idx[keep], box[keep]
                t = usable[box]
                c = np.bincount(idx - a, minlength=b - a)
                first = np.cumsum(c) - c
                lam = np.einsum("nia,ni->na", inv[t], p[idx] - pts[tets[t, 0]])
                bb = np.column_stack([1 - lam.sum(axis=1), lam])
                s = bb.min(axis=1)
                has = np.flatnonzero(c)
                best = np.maximum.reduceat(s, first[has])
                sel = np.flatnonzero(s == np.repeat(best, c[has]))
                sel = sel[np.unique(idx[sel], return_index=True)[1]]  # first best per point
                score[idx[sel]], cell[idx[sel]], bary[idx[sel]] = s[sel], t[sel], bb[sel]
        self.inside = score >= -INSIDE_TOL
        self.cell = np.where(self.inside, cell, -1)
        self.bary = np.where(self.inside[:, None], bary, 0.0)

    def _feet(self, tri, out, n_triangles, exact=6, reach=np.inf):
        """Blended feet of the outside points on the boundary triangles ``tri``.

        The candidates of a point are the ``n_triangles`` boundary triangles with the
        nearest centroids. The ``exact`` nearest are measured for every point; a farther
        one only where its centroid distance less its radius could fall inside the blend
        window of the nearest of those (elsewhere its weight is zero: the window only
        shrinks with the nearest distance). A point whose candidates all lie beyond
        ``reach`` (by that same lower bound) gets no feet and distance ``inf``. Returns the
        pairs' points, closest points, barycentric coordinates and triangles, grouped by
        point, each point's candidates in order of centroid distance."""
        p = self.p[out]
        kt = min(n_triangles, len(tri))
        index = getattr(self, "index", None)
        tset = index.triangles if index is not None and tri is index.tri else \
            _TriangleSet(self.points, tri)
        radius, h, frames = tset.radius, tset.h, tset.frames
        cdist, cand = tset.tree.query(p, k=kt)
        cdist, cand = cdist.reshape(len(out), kt), cand.reshape(len(out), kt)
        n, ex = len(out), min(exact, kt)
        # closest points and coordinates as rows, the ex nearest first (pages are touched
        # only as far as they are written)
        qs, bs = np.empty((3, n * kt)), np.empty((3, n * kt))
        d0 = frames.closest(p, np.repeat(np.arange(n), ex), cand[:, :ex].ravel(),
                            out=(qs[:, :n * ex], bs[:, :n * ex]))[0].reshape(n, ex)
        d1 = d0.min(axis=1)
        lower = cdist[:, ex:] - radius[cand[:, ex:]]  # no farther candidate is closer
        near = np.minimum(d1, lower.min(axis=1, initial=np.inf)) <= reach
        limit = d1 + WINDOW * d1 * h / (d1 + h)
        r, j = np.nonzero((lower < limit[:, None]) & near[:, None])
        used = slice(n * ex, n * ex + r.size)
        dx = frames.closest(p, r, cand[r, j + ex], out=(qs[:, used], bs[:, used]))[0]
        if r.size:
            np.minimum.at(d1, r, dx)
        self.dist[out] = np.where(near, d1, np.inf)
        window = WINDOW * d1 * h / (d1 + h)

        def weight(d, win, nearest):  # (1 - s^2)^2, s the excess over the window
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(win > 0, (d - nearest) / win, np.where(d > nearest, np.inf, 0.0))
            return np.where(s < 1, (1 - np.minimum(s, 1) ** 2) ** 2, 0.0)

        w0 = weight(d0, window[:, None], d1[:, None])
        w0[~near] = 0.0
        wx = weight(dx, window[r], d1[r])
        total = w0.sum(axis=1) + np.bincount(r, wx, minlength=n)
        total[total == 0] = 1.0  # (the points beyond reach)
        w0 /= total[:, None]
        wx /= total[r]
        # every pair in its final place: per point its ex nearest, then its farther ones
        cnt = ex + np.bincount(r, minlength=n)
        start = np.cumsum(cnt) - cnt
        first = np.cumsum(cnt - ex) - (cnt - ex)
        order = np.empty(n * ex + r.size, dtype=np.int64)
        order[(start[:, None] + np.arange(ex)).ravel()] = np.arange(n * ex)
        order[start[r] + ex + np.arange(r.size) - first[r]] = n * ex + np.arange(r.size)
        w = np.concatenate([w0.ravel(), wx])[order]
        keep = w > 0
        sel = order[keep]
        self.pair_w = w[keep]
        row = np.concatenate([np.repeat(out, ex), out[r]])
        tri_of = np.concatenate([cand[:, :ex].ravel(), cand[r, j + ex]])
        # (closest points and coordinates: transposed views of one gather of their rows)
        return (row[sel], np.take(qs, sel, axis=1).T, np.take(bs, sel, axis=1).T,
                np.take(tri, tri_of[sel], axis=0))


class _Triangles:
    """Triangles ``(a, ab, ac)`` with their Gram entries, for closest points of many
    (point, triangle) pairs: Ericson's region test with ``d3 .. d6`` from ``d1, d2`` and
    the Gram matrix (two dot products per pair), in cache-sized chunks."""

    #: pairs per chunk (the temporaries of a chunk stay in cache)
    CHUNK = 1 << 14

    def __init__(self, corners):
        a = corners[:, 0]
        ab, ac = corners[:, 1] - a, corners[:, 2] - a
        gram = np.column_stack([np.einsum("ij,ij->i", ab, ab), np.einsum("ij,ij->i", ac, ac),
                                np.einsum("ij,ij->i", ab, ac)])
        # one row per entry (a, ab, ac, Gram), one gather per chunk
        self.cols = np.ascontiguousarray(np.hstack([a, ab, ac, gram]).T)

    def closest(self, p, rows, tris, out=None):
        """Distances, closest points and barycentric coordinates (``(m,)``, ``(m, 3)``,
        ``(m, 3)``; the last two transposed views of coordinate rows) of the pairs
        ``(p[rows], triangle tris)``; ``out``: the ``(3, m)`` rows to write them into."""
        n = len(rows)
        dist = np.empty(n)
        q, bary = (np.empty((3, n)), np.empty((3, n))) if out is None else out
        px = np.ascontiguousarray(np.asarray(p, dtype=float).T)
        for s in range(0, n, self.CHUNK):  # coordinates as rows: contiguous 1-d arithmetic
            e = min(s + self.CHUNK, n)
            x, f = np.take(px, rows[s:e], axis=1), np.take(self.cols, tris[s:e], axis=1)
            a, ab, ac = f[0:3], f[3:6], f[6:9]
            ap = x - a
            d1 = ab[0] * ap[0] + ab[1] * ap[1] + ab[2] * ap[2]
            d2 = ac[0] * ap[0] + ac[1] * ap[1] + ac[2] * ap[2]
            bary[0, s:e], v, w = _region_bary(d1, d2, f[9], f[10], f[11])
            bary[1, s:e], bary[2, s:e] = v, w
            qq = q[:, s:e]
            np.multiply(v, ab, out=qq)
            np.add(a, qq, out=qq)
            qq += w * ac
            ap = qq - x
            dist[s:e] = np.sqrt(ap[0] * ap[0] + ap[1] * ap[1] + ap[2] * ap[2])
        return dist, q.T, bary.T


def _region_bary(d1, d2, g00, g11, g01):
    """Barycentric coordinates ``u, v, w`` of the closest point from ``d1 = ab.ap``,
    ``d2 = ac.ap`` and the Gram entries: Ericson's region test as one pass of selections
    over all pairs (the first true test of his order wins; degenerate triangles take
    the centroid)."""
    d3, d4, d5, d6 = d1 - g00, d2 - g01, d1 - g01, d2 - g11
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        e43, e56 = d4 - d3, d5 - d6
        m = (va <= 0) & (e43 >= 0) & (e56 >= 0)  # edge bc
        t = e43 / (e43 + e56)
        v, w = np.where(m, 1 - t, v), np.where(m, t, w)
        on_bc = m
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)  # edge ac
        v, w = np.where(m, 0.0, v), np.where(m, d2 / (d2 - d6), w)
        on_bc = on_bc & ~m
        m = (d6 >= 0) & (d5 <= d6)  # corner c
        v, w = np.where(m, 0.0, v), np.where(m, 1.0, w)
        on_bc = on_bc & ~m
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)  # edge ab
        v, w = np.where(m, d1 / (d1 - d3), v), np.where(m, 0.0, w)
        on_bc = on_bc & ~m
        m = (d3 >= 0) & (d4 <= d3)  # corner b
        v, w = np.where(m, 1.0, v), np.where(m, 0.0, w)
        on_bc = on_bc & ~m
        m = (d1 <= 0) & (d2 <= 0)  # corner a
        v, w = np.where(m, 0.0, v), np.where(m, 0.0, w)
        on_bc = on_bc & ~m
    u = np.where(on_bc, 0.0, 1.0 - v - w)
    bad = ~(np.isfinite(v) & np.isfinite(w))
    if bad.any():
        u, v, w = (np.where(bad, 1.0 / 3.0, c) for c in (u, v, w))
    return u, v, w


def _regions(d1, d2, d3, d4, d5, d6):
    """Barycentric coordinates of the closest point from Ericson's dot products
    (``d1 = ab.ap, d2 = ac.ap, d3 = ab.bp, d4 = ac.bp, d5 = ab.cp, d6 = ac.cp``)."""
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
    bary = np.stack([1 - v - w, v, w], axis=1)
    e43, e56 = d4 - d3, d5 - d6

    def on_edge(x, y, sign, cols):  # the point t = x / (x + sign y) along an edge
        def value(m):  # (on the pairs m only)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = x[m] / (x[m] + sign * y[m])
            out = [0 * t, 0 * t, 0 * t]
            out[cols[0]], out[cols[1]] = 1 - t, t
            return out
        return value

    cases = [  # lowest priority first: the first true test of Ericson's order wins
        ((va <= 0) & (e43 >= 0) & (e56 >= 0), on_edge(e43, e56, 1.0, (1, 2))),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), on_edge(d2, d6, -1.0, (0, 2))),
        ((d6 >= 0) & (d5 <= d6), lambda m: [0.0, 0.0, 1.0]),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), on_edge(d1, d3, -1.0, (0, 1))),
        ((d3 >= 0) & (d4 <= d3), lambda m: [0.0, 1.0, 0.0]),
        ((d1 <= 0) & (d2 <= 0), lambda m: [1.0, 0.0, 0.0]),
    ]
    for mask, value in cases:
        m = np.flatnonzero(mask)
        if m.size:
            v = value(m)
            for col in range(3):
                bary[m, col] = v[col]
    if not np.isfinite(bary).all():  # degenerate triangles
        bary = np.nan_to_num(bary, nan=1.0 / 3.0)
    return bary


def _bin_boxes(lo, hi, p):
    """Boxes ``[lo, hi]`` binned on a uniform grid (spacing: half the median box size): the box
    ids sorted by bin, and per point the range ``[start, stop)`` of the boxes sharing its
    bin (empty outside the grid), and the point's bin."""
    return _BoxBins(lo, hi).of(p)


class _BoxBins:
    """Boxes ``[lo, hi]`` binned on a uniform grid (spacing: half the median box size),
    sorted by bin (:meth:`of` lists the boxes sharing a point's bin)."""

    def __init__(self, lo, hi):
        h = 0.5 * float(np.median((hi - lo).max(axis=1)))
        h = h if h > 0 else 1.0
        origin = lo.min(axis=0)
        i0 = np.floor((lo - origin) / h).astype(np.int64)
        i1 = np.floor((hi - origin) / h).astype(np.int64)
        dims = i1.max(axis=0) + 1
        span = i1 - i0 + 1
        count = span.prod(axis=1)
        m = len(lo)
        box = np.repeat(np.arange(m), count)
        small = np.int32 if count.max(initial=0) < 2**31 else np.int64
        local = (np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)).astype(small)
        dz, rem = np.divmod(local, (span[:, 0] * span[:, 1]).astype(small)[box])
        dy, dx = np.divmod(rem, span[:, 0].astype(small)[box])
        base = ((i0[:, 2] * dims[1] + i0[:, 1]) * dims[0] + i0[:, 0])[box]
        key = base + (dz * dims[1] + dy) * dims[0] + dx
        if float(np.prod(dims.astype(float))) * m < 2.0**62:
            # one sort of (bin, box) pairs as a single integer: boxes by bin, then by id
            pair = np.sort(key * m + box)
            key = pair // m
            box = pair - key * m
        else:
            order = np.lexsort((box, key))
            key, box = key[order], box[order]
        self.h, self.origin, self.dims, self.key, self.box = h, origin, dims, key, box

    def of(self, p):
        """The box ids sorted by bin, and per point of ``p`` the range ``[start, stop)`` of
        the boxes sharing its bin (empty outside the grid), and the point's bin."""
        h, origin, dims, key = self.h, self.origin, self.dims, self.key
        ip = np.floor((p - origin) / h)
        valid = ((ip >= 0) & (ip < dims)).all(axis=1)
        ip = np.where(valid[:, None], ip, 0).astype(np.int64)
        pkey = np.where(valid, (ip[:, 2] * dims[1] + ip[:, 1]) * dims[0] + ip[:, 0], -1)
        first = self._first()
        if first is None:
            start = np.searchsorted(key, pkey, side="left")
            stop = np.where(valid, np.searchsorted(key, pkey, side="right"), start)
        else:  # (the keys are integers: a bin's boxes end where the next bin's begin)
            at = np.where(valid, pkey, 0)
            start = np.where(valid, first[at], 0)
            stop = np.where(valid, first[at + 1], start)
        return self.box, start, stop, pkey

    def _first(self):
        """Per bin, where its boxes begin in the sorted list (and the end after the last
        bin), made on first use where the grid has at most a few bins per box entry
        (else None: binary searches instead)."""
        first = getattr(self, "_first_box", None)
        n_bins = int(np.prod(self.dims.astype(float)))
        if first is None and n_bins <= 4 * len(self.key) + 1024:
            first = self._first_box = np.searchsorted(self.key, np.arange(n_bins + 1))
        return first
