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
* :func:`skin_state` - what the comparison needs of one truth (its skin displacement and
  distances, its median edge), so that a study of many truths need not hold their meshes;
* :func:`refinement_change` - the per-point change of that displacement between two
  truths (p50 / p90 / max), over the points both meshes reach within a tolerance.

With the exact skin's outward normals (:func:`exact_skin_normals`) the closest boundary
point is sought only on the boundary triangles that face the same way (outward normals at
less than 90 degrees): where two skin surfaces face each other across a gap (the lips,
a nostril) narrower than a coarse mesh's elements, the closest boundary point of a skin
point of the upper lip can lie on the lower lip, whose displacement is another's; the
triangle facing the same way is the upper lip's own.

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

__all__ = ["exact_skin_normals", "exact_skin_samples", "refinement_change",
           "skin_displacement", "skin_state"]


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


def exact_skin_normals(case, points, dh=0.2):
    """Outward unit normals (n, 3) of the exact skin at ``points`` (the gradient of the
    patient's skin level set, central differences of ``dh`` mm)."""
    warp = _warp(case)
    p = np.atleast_2d(np.asarray(points, dtype=float))
    g = np.column_stack([_fields(warp, p + dh * e)["skin"] - _fields(warp, p - dh * e)["skin"]
                         for e in np.eye(3)])
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), np.finfo(float).tiny)


def _closest_on_triangles(p, a, b, c):
    """Closest points of triangles (a, b, c) (..., 3) to points ``p`` (..., 3) (the
    Voronoi regions of the vertices, edges and face, all vectorised)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("...i,...i", ab, ap), np.einsum("...i,...i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("...i,...i", ab, bp), np.einsum("...i,...i", ac, bp)
    d5, d6 = np.einsum("...i,...i", ab, cp), np.einsum("...i,...i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    tiny = np.finfo(float).tiny
    den = np.where(va + vb + vc == 0, tiny, va + vb + vc)
    v, w = vb / den, vc / den
    out = a + v[..., None] * ab + w[..., None] * ac  # inside the face
    t_bc = (d4 - d3) / np.where((d4 - d3) + (d5 - d6) == 0, tiny, (d4 - d3) + (d5 - d6))
    cases = [  # (mask, point), the last true mask wins
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + t_bc[..., None] * (c - b)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / np.where(d2 - d6 == 0, tiny, d2 - d6))
         [..., None] * ac),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / np.where(d1 - d3 == 0, tiny, d1 - d3))
         [..., None] * ab),
        ((d6 >= 0) & (d5 <= d6), c), ((d3 >= 0) & (d4 <= d3), b), ((d1 <= 0) & (d2 <= 0), a)]
    for mask, q in cases:  # six Voronoi regions
        out = np.where(mask[..., None], q, out)
    return out


def _facing_closest(x, tri, points, normals, cell, closest, k=32):
    """Where the closest triangle ``cell`` faces away from ``normals``, the closest point
    among the ``k`` triangles nearest by centroid that face the same way (unchanged where
    none does)."""
    a, b, c = (x[tri[:, i]] for i in range(3))
    tn = np.cross(b - a, c - a)
    bad = np.flatnonzero(np.einsum("ij,ij->i", tn[cell], normals) <= 0)
    if not len(bad):
        return cell, closest
    from scipy.spatial import cKDTree

    _, cand = cKDTree((a + b + c) / 3).query(points[bad], k=min(k, len(tri)))
    cand = np.atleast_2d(cand)
    q = _closest_on_triangles(points[bad][:, None], a[cand], b[cand], c[cand])
    d = np.linalg.norm(q - points[bad][:, None], axis=2)
    d[np.einsum("ikj,ij->ik", tn[cand], normals[bad]) <= 0] = np.inf
    j = np.argmin(d, axis=1)
    ok = np.isfinite(d[np.arange(len(bad)), j])
    cell, closest = cell.copy(), closest.copy()
    cell[bad[ok]] = cand[ok, j[ok]]
    closest[bad[ok]] = q[ok, j[ok]]
    return cell, closest


def _triangles(grid):
    """Boundary triangles of a tetrahedral grid, as grid point ids (m, 3)."""
    surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface").triangulate()
    pid = np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS], dtype=np.int64)
    return pid[surf.faces.reshape(-1, 4)[:, 1:]]


def skin_displacement(grid, points, normals=None):
    """A solved truth's displacement at points on (or near) its boundary.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Solved tetrahedral grid with point array ``arrays.DISPLACEMENT``.
    points : array_like, shape (n, 3)
        Query points (e.g. :func:`exact_skin_samples`).
    normals : array_like, shape (n, 3), optional
        Outward normals at the points (:func:`exact_skin_normals`): the closest point is
        then sought on the boundary triangles facing the same way (module doc).

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
    if normals is not None:
        normals = np.atleast_2d(np.asarray(normals, dtype=float))
        if normals.shape != points.shape:
            raise ValueError(f"normals must have the points' shape {points.shape}, got "
                             f"{normals.shape}")
        cell, closest = _facing_closest(x, tri, points, normals, cell, closest)
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


def skin_state(grid, points, normals=None):
    """What :func:`refinement_change` needs of one solved truth, without the truth.

    A truth's mesh can hold hundreds of thousands of quadratic tetrahedra; a study that
    compares many truths keeps these few arrays per truth instead and lets each mesh go
    as soon as it is measured.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Solved truth (:func:`pvcmf.truth.independent.independent_truth_grid`).
    points, normals : array_like, shape (n, 3)
        Exact skin points and, optionally, their outward normals (:func:`skin_displacement`).

    Returns
    -------
    dict
        ``displacement`` (n, 3) and ``distance`` (n,) of :func:`skin_displacement`, and
        ``edge`` the median edge length of the grid (mm).
    """
    u, d = skin_displacement(grid, points, normals)
    e = grid.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                    volume=False)["Length"]
    return {"displacement": u, "distance": d, "edge": float(np.median(e))}


def refinement_change(coarse, fine, points, *, reach=None, normals=None):
    """Per-point change of the skin displacement between two solved truths.

    Parameters
    ----------
    coarse, fine : pyvista.UnstructuredGrid or dict
        Solved truths (:func:`pvcmf.truth.independent.independent_truth_grid`), or their
        :func:`skin_state` at the same ``points`` (and normals).
    points : array_like, shape (n, 3)
        Exact skin points (:func:`exact_skin_samples`).
    reach : float, optional
        Points farther than this (mm) from either truth's boundary are left out (where a
        mesh does not reach the skin: a lattice too coarse for a thin part). Default: a
        quarter of the coarse truth's median edge length.
    normals : array_like, shape (n, 3), optional
        Outward normals of the exact skin at the points (:func:`skin_displacement`).

    Returns
    -------
    dict
        ``change`` (n,) mm (NaN where left out), ``compared`` share of the points,
        ``p50``, ``p90``, ``max`` (mm, over the compared points), ``fine`` the fine
        truth's displacement (n, 3).
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    sc, sf = (s if isinstance(s, dict) else skin_state(s, points, normals)
              for s in (coarse, fine))
    for name, s in (("coarse", sc), ("fine", sf)):
        if len(s["distance"]) != len(points):
            raise ValueError(f"{name} skin state has {len(s['distance'])} points, expected "
                             f"the {len(points)} of points")
    if reach is None:
        reach = 0.25 * sc["edge"]
    uc, dc, uf, df = sc["displacement"], sc["distance"], sf["displacement"], sf["distance"]
    ok = (dc <= reach) & (df <= reach)
    change = np.full(len(points), np.nan)
    change[ok] = np.linalg.norm(uf[ok] - uc[ok], axis=1)
    seen = change[ok] if ok.any() else np.full(1, np.nan)
    return {"change": change, "compared": float(ok.mean()), "p50": float(np.percentile(seen, 50)),
            "p90": float(np.percentile(seen, 90)), "max": float(np.max(seen)), "fine": uf}
