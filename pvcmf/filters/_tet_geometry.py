"""Geometry of linear tetrahedra for the mesh -> skin transfer: cells, gradients, closest points.

Used by :mod:`pvcmf.filters.surface_mapping`. Delegates to numpy and scipy.sparse.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
import scipy.sparse as sp


def _tetra(grid):
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


def _gradients(points, tets):
    """Per tetrahedron: ``E^-1`` (m, 3, 3) with ``grad u = E^-1 (u_a - u_0)_a`` and volumes."""
    edges = points[tets[:, 1:]] - points[tets[:, :1]]
    det = np.linalg.det(edges)
    ok = np.abs(det) > 1e-300
    inv = np.zeros_like(edges)
    inv[ok] = np.linalg.inv(edges[ok])
    return inv, np.abs(det) / 6.0


def _gradient_operators(points, tets, rows):
    """Sparse ``(len(rows), n)`` operators ``D_c`` (c = x, y, z): the volume-weighted mean
    of the displacement gradients of the tetrahedra around each node ``rows``."""
    n, m = len(points), len(tets)
    inv, vol = _gradients(points, tets)
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


def _closest_on_triangles(p, a, b, c):
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
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), lambda: np.stack([0 * t_bc, 1 - t_bc, t_bc], 1)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), lambda: np.stack([1 - t_ac, 0 * t_ac, t_ac], 1)),
        ((d6 >= 0) & (d5 <= d6), lambda: np.tile([0.0, 0.0, 1.0], (len(p), 1))),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), lambda: np.stack([1 - t_ab, t_ab, 0 * t_ab], 1)),
        ((d3 >= 0) & (d4 <= d3), lambda: np.tile([0.0, 1.0, 0.0], (len(p), 1))),
        ((d1 <= 0) & (d2 <= 0), lambda: np.tile([1.0, 0.0, 0.0], (len(p), 1))),
    ]
    for mask, value in cases:
        if mask.any():
            bary[mask] = value()[mask]
    bary = np.nan_to_num(bary, nan=1.0 / 3.0)
    q = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
    return q, bary
