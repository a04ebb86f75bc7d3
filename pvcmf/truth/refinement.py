"""Refinement of the independent truth: its skin displacement on the exact skin.

Two truths on different meshes are compared where they mean the same thing: at material
points of the *exact* skin (the zero set of the patient's skin level set, not a voxel
contour, which lies up to half a voxel outside every mesh and would be compared only
where it happens to fall inside both):

* :func:`exact_skin_samples` - points of the exact skin of the meshed face (the voxel
  skin of the true labels, each point projected onto the exact soft-tissue boundary by
  Newton steps, kept where that boundary is the skin);
* :func:`skin_displacement` - a solved truth's displacement at those points: the closest
  point of the truth's boundary triangles (VTK cell locator), its displacement the P2
  field there (quadratic on the triangle: vertex and edge-midpoint values; the linear
  interpolation of the vertex values of a truth without midpoint values);
* :func:`refinement_change` - the per-point change of that displacement between two
  truths (p50 / p90 / max), over the points both meshes reach within a tolerance.

Delegates to pyvista / VTK (closest cell), numpy, and :mod:`pvcmf.truth.exact` (the
exact anatomy).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .. import arrays, filters
from ..filters.model_region import face_box
from .anatomy import _warp
from .exact import _BOUNDARY, _fields, _project, _region

__all__ = ["exact_skin_samples", "refinement_change", "skin_displacement"]


def exact_skin_samples(case, *, face_fraction=0.5, tol=0.05):
    """Points of the exact skin of the meshed face of a virtual patient.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient.
    face_fraction : float, default 0.5
        Anterior share of the head (as the truth's mesh): points behind the face box's
        coronal plane are dropped.
    tol : float, default 0.05
        Largest level-set value (mm) of a kept point after the projection.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` patient-frame points on the exact skin.

    Examples
    --------
    >>> import pvcmf                                                            # doctest: +SKIP
    >>> from pvcmf.truth.refinement import exact_skin_samples                   # doctest: +SKIP
    >>> exact_skin_samples(pvcmf.datasets.phantom(1, spacing=3.0)).shape[1]     # doctest: +SKIP
    3
    """
    warp = _warp(case)
    y0 = face_box(case.truth, face_fraction)[2]
    p = np.asarray(filters.extract_skin(case.truth).points, dtype=float)
    p = _project(warp, p[p[:, 1] > y0])
    r, active = _region(_fields(warp, p))
    keep = (np.abs(r) < tol) & (active == _BOUNDARY.index("skin")) & (p[:, 1] > y0)
    return p[keep]


def _triangles(grid):
    """Boundary triangles of a tetrahedral grid, as grid point ids (m, 3)."""
    surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface").triangulate()
    pid = np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS], dtype=np.int64)
    return pid[surf.faces.reshape(-1, 4)[:, 1:]]


def skin_displacement(grid, points):
    """A solved truth's displacement at points on (or near) its boundary.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Solved tetrahedral grid with point array ``arrays.DISPLACEMENT``.
    points : array_like, shape (n, 3)
        Query points (e.g. :func:`exact_skin_samples`).

    Returns
    -------
    displacement : numpy.ndarray
        ``(n, 3)``: at each query point's closest boundary point, the displacement there:
        the quadratic field of a P2 truth (its vertex values and the edge-midpoint values of
        the field arrays ``arrays.REFERENCE_EDGES`` / ``REFERENCE_MIDPOINT_DISPLACEMENT``),
        else the linear interpolation of the triangle's vertex displacements.
    distance : numpy.ndarray
        ``(n,)`` distance (mm) of each query point to the grid's boundary.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.truth.refinement import skin_displacement
    >>> g = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid().triangulate()
    >>> g[arrays.DISPLACEMENT] = 0.1 * g.points
    >>> u, d = skin_displacement(g, [[0.5, 0.7, 2.2]])
    >>> np.round(u, 6).tolist(), np.round(d, 6).tolist()
    ([[0.05, 0.07, 0.2]], [0.2])
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    tri = _triangles(grid)
    x = np.asarray(grid.points, dtype=float)
    surf = pv.PolyData(x, np.column_stack([np.full(len(tri), 3), tri]).ravel())
    cell, closest = surf.find_closest_cell(points, return_closest_point=True)
    cell, closest = np.atleast_1d(cell), np.atleast_2d(closest)
    a, b, c = (x[tri[cell, k]] for k in range(3))
    # barycentric coordinates of the closest point (on the triangle, so in [0, 1])
    v0, v1, v2 = b - a, c - a, closest - a
    d00, d01, d11 = (np.einsum("ij,ij->i", s, t) for s, t in ((v0, v0), (v0, v1), (v1, v1)))
    d20, d21 = np.einsum("ij,ij->i", v2, v0), np.einsum("ij,ij->i", v2, v1)
    den = np.where(d00 * d11 - d01**2 == 0, np.finfo(float).tiny, d00 * d11 - d01**2)
    wb, wc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    u = np.asarray(grid.point_data[arrays.DISPLACEMENT], dtype=float)
    lam = np.column_stack([1 - wb - wc, wb, wc])
    t = tri[cell]
    if arrays.REFERENCE_MIDPOINT_DISPLACEMENT in grid.field_data:
        # quadratic (6-node) triangle: lam_i (2 lam_i - 1) at the vertices, 4 lam_i lam_j
        # at the edge midpoints
        mid = _midpoints(grid, t)
        disp = np.einsum("ik,ikd->id", lam * (2 * lam - 1), u[t])
        for k, (i, j) in enumerate(((0, 1), (1, 2), (0, 2))):
            disp += (4 * lam[:, i] * lam[:, j])[:, None] * mid[:, k]
    else:
        disp = np.einsum("ik,ikd->id", lam, u[t])
    return disp, np.linalg.norm(points - closest, axis=1)


def _midpoints(grid, tri):
    """The solution at the midpoints of the edges (0 1), (1 2), (0 2) of triangles ``tri``
    (k, 3): (k, 3, 3), from the field arrays of :func:`pvcmf.truth.solve_reference`."""
    edges = np.asarray(grid.field_data[arrays.REFERENCE_EDGES], dtype=np.int64).reshape(-1, 2)
    values = np.asarray(grid.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT],
                        dtype=float).reshape(-1, 3)
    n = int(grid.n_points)
    key = edges[:, 0] * n + edges[:, 1]
    order = np.argsort(key)
    pairs = tri[:, [0, 1, 1, 2, 0, 2]].reshape(-1, 3, 2)
    query = pairs.min(axis=2) * n + pairs.max(axis=2)
    pos = order[np.clip(np.searchsorted(key[order], query), 0, len(key) - 1)]
    if not np.array_equal(key[pos], query):
        raise ValueError("grid's reference_edges miss an edge of its boundary triangles")
    return values[pos]


def refinement_change(coarse, fine, points, *, reach=None):
    """Per-point change of the skin displacement between two solved truths.

    Parameters
    ----------
    coarse, fine : pyvista.UnstructuredGrid
        Solved truths (:func:`pvcmf.truth.independent.independent_truth_grid`).
    points : array_like, shape (n, 3)
        Exact skin points (:func:`exact_skin_samples`).
    reach : float, optional
        Points farther than this (mm) from either truth's boundary are left out (where a
        mesh does not reach the skin: a lattice too coarse for a thin part). Default: a
        quarter of the coarse truth's median edge length.

    Returns
    -------
    dict
        ``change`` (n,) mm (NaN where left out), ``compared`` share of the points,
        ``p50``, ``p90``, ``max`` (mm, over the compared points), ``fine`` the fine
        truth's displacement (n, 3).
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    if reach is None:
        e = coarse.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                          volume=False)["Length"]
        reach = 0.25 * float(np.median(e))
    uc, dc = skin_displacement(coarse, points)
    uf, df = skin_displacement(fine, points)
    ok = (dc <= reach) & (df <= reach)
    change = np.full(len(points), np.nan)
    change[ok] = np.linalg.norm(uf[ok] - uc[ok], axis=1)
    seen = change[ok] if ok.any() else np.full(1, np.nan)
    return {"change": change, "compared": float(ok.mean()), "p50": float(np.percentile(seen, 50)),
            "p90": float(np.percentile(seen, 90)), "max": float(np.max(seen)), "fine": uf}
