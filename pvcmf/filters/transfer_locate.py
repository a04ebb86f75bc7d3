"""Where points lie relative to a tetrahedral mesh: containing tetrahedra and boundary feet.

The geometric half of :func:`pvcmf.filters.surface_mapping.transfer_operator` (which turns
:class:`Located` into the sparse operator) and of its crumple metric. Every step is one
vectorised call over all points: VTK's probe filter (:meth:`pyvista.DataSet.sample`) finds
the tetrahedron holding a point, precomputed inverse edge matrices give the barycentric
coordinates, :class:`scipy.spatial.cKDTree` gives candidate tetrahedra, boundary triangles
and boundary nodes, and the closest points on the candidate triangles are computed for all
(point, triangle) pairs at once (Ericson's region test, vectorised).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from .. import arrays
from .skin import _boundary_faces

__all__ = ["Located", "closest_on_triangles", "tetra", "tet_gradients"]

#: barycentric coordinates down to this (negative) value still count as inside a tetrahedron
INSIDE_TOL = 1e-6
#: width of the foot blend (in units of d h / (d + h), d the distance, h the median boundary edge)
WINDOW = 10.0


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


def closest_on_triangles(p, a, b, c):
    """Closest points of triangles ``abc`` to ``p`` and their barycentric coordinates
    (vectorised form of Ericson's region test)."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)  # noqa: E731
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
        bary = np.stack([1 - v - w, v, w], axis=1)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        t_ac = d2 / (d2 - d6)
        t_ab = d1 / (d1 - d3)
    cases = [  # lowest priority first: the first true test of Ericson's order wins
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda m: [0 * t_bc[m], 1 - t_bc[m], t_bc[m]]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda m: [1 - t_ac[m], 0 * t_ac[m], t_ac[m]]),
        ((d6 >= 0) & (d5 <= d6), lambda m: [0.0, 0.0, 1.0]),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda m: [1 - t_ab[m], t_ab[m], 0 * t_ab[m]]),
        ((d3 >= 0) & (d4 <= d3), lambda m: [0.0, 1.0, 0.0]),
        ((d1 <= 0) & (d2 <= 0), lambda m: [1.0, 0.0, 0.0]),
    ]
    for mask, value in cases:
        m = np.flatnonzero(mask)
        if m.size:
            v = value(m)
            for col in range(3):
                bary[m, col] = v[col]
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary


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
    """

    def __init__(self, grid, points, k=8, n_triangles=24, reach=np.inf):
        self.points, self.tets = tetra(grid)
        p = np.asarray(points, dtype=float)
        self.p = p
        src = pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)
        self._find_cells(src)
        tri = _boundary_faces(src)
        self.boundary = np.unique(tri)
        self.dist = np.where(self.inside, 0.0, np.inf)
        out = np.flatnonzero(~self.inside)
        btree = cKDTree(self.points[self.boundary])
        if out.size and np.isfinite(reach):  # cheap reject: far from every boundary node
            e = self.points[tri[:, [0, 1, 2]]] - self.points[tri[:, [1, 2, 0]]]
            h_max = float(np.linalg.norm(e, axis=2).max())
            dn = btree.query(p[out], distance_upper_bound=reach + h_max)[0]
            out = out[dn - h_max <= reach]
        self.outside = out
        n_pairs = 0
        if out.size:
            rows, q, bary, face = self._feet(tri, out, n_triangles)
            n_pairs = len(rows)
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

    def _find_cells(self, src):
        """Containing tetrahedra. Points farther from every tetrahedron's centroid than the
        largest centroid-vertex distance lie in none; the others go to VTK's probe, then
        to the tetrahedra with the nearest centroids for the points it misses (on shared
        faces, within round-off)."""
        p, pts, tets = self.p, self.points, self.tets
        n = len(p)
        corners = pts[tets]
        centre = corners.mean(axis=1)
        r_max = float(np.linalg.norm(corners - centre[:, None, :], axis=2).max())
        inv, vol = tet_gradients(pts, tets)
        flat = vol <= 1e-300 / 6.0  # degenerate: holds no point
        kc = min(8, len(tets))
        cdist, cand = cKDTree(centre).query(p, k=kc, distance_upper_bound=r_max * (1 + 1e-9))
        cdist, cand = cdist.reshape(n, kc), cand.reshape(n, kc)
        near = np.flatnonzero(cdist[:, 0] < np.inf)
        cell = np.full(n, -1, dtype=np.int64)
        bary = np.full((n, 4), -np.inf)
        if near.size:
            src.cell_data[arrays.SCRATCH_CELL_ID] = np.arange(len(tets), dtype=np.int64)
            probe = pv.PolyData(p[near]).sample(src, pass_point_data=False, progress_bar=False)
            cell[near] = np.where(np.asarray(probe[arrays.VALID_POINT_MASK]).astype(bool),
                                  np.asarray(probe[arrays.SCRATCH_CELL_ID]).astype(np.int64), -1)

        def barycentric(idx, cells):
            lam = np.einsum("nia,ni->na", inv[cells], p[idx] - pts[tets[cells, 0]])
            b = np.column_stack([1 - lam.sum(axis=1), lam])
            b[flat[cells]] = -np.inf
            return b

        hit = np.flatnonzero(cell >= 0)
        bary[hit] = barycentric(hit, cell[hit])
        miss = near[bary[near].min(axis=1) < -INSIDE_TOL]
        for j in range(kc):
            valid = miss[cand[miss, j] < len(tets)]
            if not valid.size:
                break
            b = barycentric(valid, cand[valid, j])
            better = b.min(axis=1) > bary[valid].min(axis=1)
            bary[valid[better]], cell[valid[better]] = b[better], cand[valid[better], j]
        self.inside = bary.min(axis=1) >= -INSIDE_TOL
        self.cell = np.where(self.inside, cell, -1)
        self.bary = np.where(self.inside[:, None], bary, 0.0)

    def _feet(self, tri, out, n_triangles, exact=6):
        """Blended feet of the outside points on the boundary triangles ``tri``.

        The ``exact`` nearest candidates (by centroid) are measured for every point; a
        farther candidate only where its centroid distance less its radius could fall
        inside the blend window of the nearest of those (elsewhere its weight is zero:
        the window only shrinks with the nearest distance)."""
        p, pts = self.p[out], self.points
        kt = min(n_triangles, len(tri))
        corners = pts[tri]
        centre = corners.mean(axis=1)
        radius = np.linalg.norm(corners - centre[:, None, :], axis=2).max(axis=1)
        cdist, cand = cKDTree(centre).query(p, k=kt)
        cdist, cand = cdist.reshape(len(out), kt), cand.reshape(len(out), kt)
        e = corners[:, [0, 1, 2]] - corners[:, [1, 2, 0]]
        h = float(np.median(np.linalg.norm(e, axis=2)))
        n = len(out)
        d = np.full((n, kt), np.inf)
        slot = np.full((n, kt), -1, dtype=np.int64)  # (point, candidate) -> measured pair
        found = []

        def measure(r, j):  # (point, candidate) pairs, one vectorised call
            t = cand[r, j]
            q, b = closest_on_triangles(p[r], corners[t, 0], corners[t, 1], corners[t, 2])
            d[r, j] = np.linalg.norm(q - p[r], axis=1)
            slot[r, j] = sum(len(f[0]) for f in found) + np.arange(len(r))
            found.append((q, b))

        ex = min(exact, kt)
        measure(np.repeat(np.arange(n), ex), np.tile(np.arange(ex), n))
        d1 = d[:, :ex].min(axis=1)
        reach = d1 + WINDOW * d1 * h / (d1 + h)
        r, j = np.nonzero(cdist[:, ex:] - radius[cand[:, ex:]] < reach[:, None])
        if r.size:
            measure(r, j + ex)
        d1 = d.min(axis=1)[:, None]
        self.dist[out] = d1[:, 0]
        window = WINDOW * d1 * h / (d1 + h)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(window > 0, (d - d1) / window, np.where(d > d1, np.inf, 0.0))
        w = np.where(s < 1, (1 - np.minimum(s, 1) ** 2) ** 2, 0.0)
        w /= w.sum(axis=1, keepdims=True)
        r, j = np.nonzero(w > 0)
        self.pair_w = w[r, j]
        pair = slot[r, j]
        q_all = np.concatenate([f[0] for f in found])
        b_all = np.concatenate([f[1] for f in found])
        return out[r], q_all[pair], b_all[pair], tri[cand[r, j]]
