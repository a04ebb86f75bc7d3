"""Exact signed point-to-surface distance: predicted skin against the actual skin.

Paper 000 Fig. 6 colours the predicted face by its distance to the post-operative face.
:func:`distance_to` measures, for every point of the prediction, the distance to the
*closest point on the triangles* of the truth (not to its nearest vertex), signed
positive where the prediction lies anterior to (outside of) the truth.

Delegates the closest points to libigl's AABB tree (``igl.point_mesh_squared_distance``,
C++, multithreaded; optional dependency ``pvcmf[fast]``) and signs them in numpy with
the pseudo-normal of the closest feature (face, edge or vertex; Baerentzen & Aanaes
2005). Without libigl it delegates to VTK's ``vtkImplicitPolyDataDistance`` (closest
point on the cells through a cell locator, the whole point array at once via
``FunctionValue``). The sign follows the truth's winding, which is first made outward
here (closed surface: positive volume; open face scan: consistent winding facing away
from its centroid, ``vtkPolyDataNormals``). ``benchmarks/registration_distance.py``
measures both against each other and the nearest vertex (scipy ``cKDTree``).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ._checks import MAX_COORDINATE, check_finite_points  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)


def _check_surface(surface, name):
    if not isinstance(surface, pv.PolyData):
        raise TypeError(f"{name} must be a pyvista.PolyData surface, got {type(surface).__name__}")
    if surface.n_points == 0 or surface.faces.size == 0:
        raise ValueError(
            f"{name} must be a non-empty surface with polygons, got {surface.n_points} "
            f"points and {surface.faces.size // 4 if surface.faces.size else 0} polygons"
        )
    check_finite_points(surface, name)


def _edge_counts(tris, n_points):
    """(winding consistent?, surface closed?) from directed-edge counts (numpy)."""
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    key = np.sort(directed[:, 0] * n_points + directed[:, 1])
    consistent = not (key[1:] == key[:-1]).any()  # no directed edge used twice
    lo, hi = np.minimum(directed[:, 0], directed[:, 1]), np.maximum(directed[:, 0], directed[:, 1])
    und = np.sort(lo * n_points + hi)
    starts = np.flatnonzero(np.r_[True, und[1:] != und[:-1]])
    count = np.diff(np.r_[starts, und.size])
    return consistent, bool((count == 2).all())


def _outward(surface):
    """Triangulated, data-free copy of ``surface`` whose winding points outward.

    Closed surfaces: the winding with positive signed volume. Open surfaces (a face scan):
    consistent winding turned to point away from the centroid. The winding is made
    consistent by ``vtkPolyDataNormals`` only when a numpy edge count finds it is not.
    """
    surf = surface.triangulate() if not surface.is_all_triangles else surface.copy()
    surf.clear_data()
    tris = surf.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    consistent, closed = _edge_counts(tris, surf.n_points)
    if not consistent:
        surf = surf.compute_normals(
            cell_normals=False, point_normals=True, consistent_normals=True,
            auto_orient_normals=False, split_vertices=False,
        )
        surf.clear_data()
        tris = surf.faces.reshape(-1, 4)[:, 1:].astype(np.int64)
    points = np.asarray(surf.points, float)
    a, b, c = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    cross = np.cross(b - a, c - a)
    centre = points[np.unique(tris)].mean(axis=0)  # of the triangles' vertices only
    if not np.all(np.isfinite(centre)):
        raise ValueError(f"actual must have finite point coordinates, got centre {centre}")
    if closed:
        outward = np.einsum("ij,ij->", a - centre, cross) > 0  # 6 x volume
    else:
        outward = np.einsum("ij,ij->", (a + b + c) / 3 - centre, cross) > 0
    if not outward:
        surf.faces = np.column_stack([np.full(len(tris), 3), tris[:, ::-1]]).ravel()
    return surf


def _igl():
    try:
        import igl
    except ImportError:
        return None
    return igl


def _unit_face_normals(points, tris):
    a = points[tris[:, 0]]
    n = np.cross(points[tris[:, 1]] - a, points[tris[:, 2]] - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def _lookup(sorted_keys, keys):
    """Position of each of ``keys`` in ``sorted_keys`` and whether it is there (numpy)."""
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return pos, sorted_keys[pos] == keys


def _edge_pseudonormals(points, tris, fid, k):
    """Sum of the unit normals of the triangles sharing local edge ``k`` of triangles ``fid``.

    Local edge ``k`` is opposite vertex ``k``. Only the needed edges are looked up: the
    edge keys of every triangle are matched against them (``np.searchsorted``).
    """
    n_pts = len(points)
    i, j = tris[fid, (k + 1) % 3], tris[fid, (k + 2) % 3]
    need = np.minimum(i, j) * n_pts + np.maximum(i, j)
    uniq, inv = np.unique(need, return_inverse=True)
    lo = np.minimum(tris[:, [1, 2, 0]], tris[:, [2, 0, 1]])
    hi = np.maximum(tris[:, [1, 2, 0]], tris[:, [2, 0, 1]])
    pos, hit = _lookup(uniq, (lo * n_pts + hi).ravel())
    faces = np.flatnonzero(hit) // 3
    fn = _unit_face_normals(points, tris[faces])
    total = np.column_stack([np.bincount(pos[hit], fn[:, c], minlength=len(uniq))
                             for c in range(3)])
    return total[inv]


def _vertex_pseudonormals(points, tris, vid):
    """Angle-weighted sums of the unit normals of the triangles around vertices ``vid``."""
    uniq, inv = np.unique(vid, return_inverse=True)
    pos, hit = _lookup(uniq, tris.ravel())
    rows = np.flatnonzero(hit)
    faces, corner = rows // 3, rows % 3
    t = tris[faces]
    fn = _unit_face_normals(points, t)
    p0 = points[t[np.arange(len(t)), corner]]
    e1 = points[t[np.arange(len(t)), (corner + 1) % 3]] - p0
    e2 = points[t[np.arange(len(t)), (corner + 2) % 3]] - p0
    cosang = np.einsum("ij,ij->i", e1, e2) / np.maximum(
        np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-300)
    w = np.arccos(np.clip(cosang, -1.0, 1.0))
    total = np.column_stack([np.bincount(pos[hit], w * fn[:, c], minlength=len(uniq))
                             for c in range(3)])
    return total[inv]


def _pseudonormal_sign(query, points, tris, fid, closest):
    """+1 / -1: side of ``query`` along the pseudo-normal of its closest feature.

    Baerentzen & Aanaes (2005): the closest point lies inside a triangle (its normal), on
    an edge (sum of the normals of the edge's triangles) or on a vertex (angle-weighted
    sum of its triangles' normals); the sign of the dot product with that pseudo-normal
    is the side of a closed, consistently wound surface (and locally of an open one). The
    feature comes from the barycentric coordinates of the closest point in its triangle
    ``fid``; edge and vertex pseudo-normals are computed only for the features that are
    closest to some query (about 1 % of a skin's queries). All numpy.
    """
    ta, tb, tc = points[tris[fid, 0]], points[tris[fid, 1]], points[tris[fid, 2]]
    v0, v1, v2 = tb - ta, tc - ta, closest - ta
    d00 = np.einsum("ij,ij->i", v0, v0)
    d01 = np.einsum("ij,ij->i", v0, v1)
    d11 = np.einsum("ij,ij->i", v1, v1)
    d20 = np.einsum("ij,ij->i", v2, v0)
    d21 = np.einsum("ij,ij->i", v2, v1)
    den = d00 * d11 - d01 * d01
    den = np.where(den != 0, den, 1.0)
    bv = (d11 * d20 - d01 * d21) / den
    bw = (d00 * d21 - d01 * d20) / den
    bary = np.column_stack([1.0 - bv - bw, bv, bw])
    small = bary <= 1e-9
    n_small = small.sum(axis=1)
    normal = np.cross(v0, v1)  # the triangle's normal (length immaterial for the sign)
    edge = n_small == 1  # on the edge opposite the vertex whose coordinate vanishes
    if edge.any():
        normal[edge] = _edge_pseudonormals(points, tris, fid[edge],
                                           np.argmax(small[edge], axis=1))
    vert = n_small >= 2  # on the vertex whose coordinate does not vanish
    if vert.any():
        k = np.argmax(bary[vert], axis=1)
        normal[vert] = _vertex_pseudonormals(points, tris, tris[fid[vert], k])
    side = np.einsum("ij,ij->i", query - closest, normal)
    return np.where(side < 0, -1.0, 1.0)


class SurfaceDistance:
    """Exact signed distance to one triangle surface, built once for repeated queries.

    With libigl (``method='igl'``, or ``'auto'`` when installed) the AABB tree
    (``igl.AABB``) is built once; each call finds the closest points on the triangles and
    signs them by the closest feature's pseudo-normal. With
    ``method='vtk'`` VTK's ``vtkImplicitPolyDataDistance`` (its cell locator) is built once.
    Positive on the side the winding's normals point to; orient the surface first
    (:func:`distance_to` does).

    Parameters
    ----------
    surface : pyvista.PolyData
        Surface with polygons (triangulated if needed).
    method : {'auto', 'igl', 'vtk'}, default 'auto'
        Closest-point engine (see :func:`signed_distance`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.distance import SurfaceDistance
    >>> dist = SurfaceDistance(pv.Cube())  # [-0.5, 0.5]^3, outward winding
    >>> dist(np.array([[0.0, 0.0, 2.0], [0.0, 0.1, 0.0]])).round(3).tolist()
    [1.5, -0.4]
    """

    def __init__(self, surface, *, method="auto"):
        if method not in ("auto", "igl", "vtk"):
            raise ValueError(f"method must be 'auto', 'igl' or 'vtk', got {method!r}")
        _check_surface(surface, "surface")
        surf = surface.triangulate() if not surface.is_all_triangles else surface.copy()
        surf.clear_data()  # VTK would sign by a stale 'Normals' array
        igl = _igl() if method != "vtk" else None
        if method == "igl" and igl is None:
            raise ImportError("method='igl' needs libigl: pip install 'pvcmf[fast]' (or libigl)")
        self.method = "igl" if igl is not None else "vtk"
        if igl is not None:
            self._points = np.ascontiguousarray(surf.points, dtype=np.float64)
            self._tris = np.ascontiguousarray(surf.faces.reshape(-1, 4)[:, 1:], dtype=np.int64)
            self._tree = igl.AABB()
            self._tree.init(self._points, self._tris)
        else:
            import vtk

            self._implicit = vtk.vtkImplicitPolyDataDistance()
            self._implicit.SetInput(surf)
            self._surface = surf  # keep the input alive with the locator

    def __call__(self, query):
        """Signed distances (mm) of ``(n, 3)`` points."""
        q = np.asarray(query, dtype=np.float64)
        if q.size % 3 or (q.ndim == 2 and q.shape[1] != 3):
            raise ValueError(f"query must be an (n, 3) array of points, got shape {q.shape}")
        q = q.reshape(-1, 3)
        bad = ~(np.abs(q) <= MAX_COORDINATE).all(axis=1)
        if bad.any():
            raise ValueError(f"query must have finite coordinates within +-{MAX_COORDINATE:g} "
                             f"mm, got {int(bad.sum())} of {len(q)} points with NaN/inf or beyond")
        q = np.ascontiguousarray(q)
        if self.method == "igl":
            d2, fid, closest = self._tree.squared_distance(self._points, self._tris, q)
            sign = _pseudonormal_sign(q, self._points, self._tris, fid, closest)
            return sign * np.sqrt(d2)
        from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy
        import vtk

        out = vtk.vtkDoubleArray()
        self._implicit.FunctionValue(numpy_to_vtk(q, deep=True), out)
        return vtk_to_numpy(out).astype(np.float64, copy=True)


def signed_distance(query, surface, *, method="auto"):
    """Exact signed distance of points to a triangle surface, by its winding.

    Positive on the side the winding's normals point to.

    Parameters
    ----------
    query : array_like
        ``(n, 3)`` points.
    surface : pyvista.PolyData
        Surface with polygons (triangulated if needed); its winding gives the sign.
    method : {'auto', 'igl', 'vtk'}, default 'auto'
        ``'igl'``: closest points on the triangles by libigl's AABB tree
        (``igl.AABB``, optional dependency ``pvcmf[fast]``), sign from the pseudo-normal
        of the closest feature (face, edge or vertex; numpy). ``'vtk'``: VTK's
        ``vtkImplicitPolyDataDistance.FunctionValue`` (one call for all points; sign from
        the closest cell's normal). ``'auto'``: igl when installed. Both are exact
        (closest point on the triangles, not the nearest vertex). For many queries
        against one surface, build a :class:`SurfaceDistance` once.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` signed distances (mm).

    Raises
    ------
    ValueError
        For an unknown ``method``; ImportError for ``'igl'`` without libigl.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.distance import signed_distance
    >>> cube = pv.Cube()  # [-0.5, 0.5]^3, outward winding
    >>> signed_distance(np.array([[0.0, 0.0, 2.0], [0.0, 0.1, 0.0]]), cube).round(3).tolist()
    [1.5, -0.4]
    """
    return SurfaceDistance(surface, method=method)(query)


def distance_to(pred, actual, *, orient=True, max_distance=None, method="auto"):
    """Signed distance from each point of the predicted skin to the actual skin.

    Parameters
    ----------
    pred : pyvista.DataSet
        Predicted skin (any dataset; its points are measured).
    actual : pyvista.PolyData
        Actual (e.g. registered post-operative) skin surface; triangulated if needed.
    orient : bool, default True
        Orient ``actual`` outward first (closed: positive volume; open: consistent
        winding facing away from its centroid). Pass ``False`` to use its winding as is.
    max_distance : float, optional
        If given, raise ``ValueError`` when the median unsigned distance exceeds it
        (surfaces that do not overlap, e.g. not registered).
    method : {'auto', 'igl', 'vtk'}, default 'auto'
        Closest-point engine, see :func:`signed_distance` (libigl when installed, else
        VTK; both exact).

    Returns
    -------
    pyvista.DataSet
        Copy of ``pred`` with point array ``arrays.DISTANCE`` (float64, mm): positive
        where the prediction lies outside (anterior to) the truth, negative posterior.

    Raises
    ------
    TypeError
        If ``actual`` is not a PolyData or ``pred`` not a dataset.
    ValueError
        If either surface is empty or has NaN/inf points (their count is named), or the
        surfaces are further apart than ``max_distance``.

    Examples
    --------
    >>> import pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> pred = pv.Sphere(radius=11.0)
    >>> out = pred.cmf.distance_to(pv.Sphere(radius=10.0, theta_resolution=60, phi_resolution=60))
    >>> bool(abs(out[arrays.DISTANCE].mean() - 1.0) < 0.02)
    True
    """
    if not isinstance(pred, pv.DataSet):
        raise TypeError(f"pred must be a pyvista dataset, got {type(pred).__name__}")
    if pred.n_points == 0:
        raise ValueError("pred must have points, got an empty dataset")
    check_finite_points(pred, "pred")
    _check_surface(actual, "actual")
    target = _outward(actual) if orient else actual
    d = signed_distance(pred.points, target, method=method)
    if max_distance is not None:
        med = float(np.median(np.abs(d)))
        if med > max_distance:
            raise ValueError(
                f"pred and actual do not overlap: median distance {med:.3g} mm exceeds "
                f"max_distance={max_distance} mm (register them first)"
            )
    out = pred.copy()
    out.point_data[arrays.DISTANCE] = d
    return out
