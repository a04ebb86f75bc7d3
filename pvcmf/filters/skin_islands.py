"""Small unmodelled islands of a skin that the modelled skin encloses count as modelled.

The transfer (:class:`pvcmf.filters.surface_mapping.Transfer`) models a skin point when
it lies within ``band`` of the tetrahedral mesh. Where the coarse mesh surface dips a few
mm under a local bump of the skin (forehead, cheek), a few skin points lie just beyond the
band and form small islands inside the modelled face; their displacement is the same
smooth extension as their neighbours', so the threshold alone would mark specks.
:func:`fill_enclosed` marks as modelled each connected component of unmodelled points
(over the skin's own triangle edges) whose area is at most ``max_area`` and that touches
no open border of the skin; the large unmodelled rest (the back of the head, the neck)
stays unmodelled. :func:`island_area_limit` derives ``max_area`` from the mesh's median
edge (:data:`ISLAND_EDGES` edges as a disc's radius). Beyond the band the transfer fades
its extension towards zero (``pvcmf.filters.surface_mapping._decay``);
:func:`undo_decay` takes that fade back at the filled points, so their displacement is the
extension that the modelled skin around them carries.

Delegates the components to :func:`scipy.sparse.csgraph.connected_components` and the
triangles to :meth:`pyvista.PolyData.triangulate`.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .transfer_locate import tetra

log = logging.getLogger(__name__)

__all__ = ["ISLAND_EDGES", "island_area_limit", "skin_triangles", "fill_enclosed", "modelled_skin",
           "undo_decay"]

#: radius, in median mesh edges, of the disc whose area bounds an island that is filled
ISLAND_EDGES = 2.0


def island_area_limit(grid, edges=ISLAND_EDGES):
    """Area (mm^2) of a disc of radius ``edges`` median tetrahedron edges of ``grid``:
    the largest unmodelled island :func:`fill_enclosed` fills.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    >>> bool(island_area_limit(grid) > np.pi * 4.0)   # median edge >= 1
    True
    """
    if not float(edges) > 0:
        raise ValueError(f"edges must be > 0, got {edges!r}")
    pts, tets = tetra(grid)
    e = pts[tets[:, [1, 2, 3, 2, 3, 3]]] - pts[tets[:, [0, 0, 0, 1, 1, 2]]]
    h = float(np.median(np.linalg.norm(e, axis=2)))
    return float(np.pi * (float(edges) * h) ** 2)


def skin_triangles(skin):
    """The triangles ``(m, 3)`` of a skin surface (polygons triangulated; none for a
    point cloud or a dataset that is not a :class:`pyvista.PolyData`).

    Examples
    --------
    >>> import pyvista as pv
    >>> skin_triangles(pv.Plane(i_resolution=2, j_resolution=1)).shape
    (4, 3)
    """
    if not isinstance(skin, pv.PolyData) or skin.n_cells == 0 or skin.n_faces == 0:
        return np.zeros((0, 3), dtype=np.int64)
    surf = skin if skin.is_all_triangles else skin.triangulate()
    faces = np.asarray(surf.faces).reshape(-1, 4)
    return faces[faces[:, 0] == 3, 1:].astype(np.int64)


def fill_enclosed(points, triangles, modelled, max_area):
    """``modelled`` with the small enclosed unmodelled islands set.

    An island is a connected component of unmodelled points over the edges of
    ``triangles`` (both ends unmodelled). It is filled when its area (a third of the area
    of each triangle around each of its points) is at most ``max_area``, an edge joins it
    to modelled skin and none of its points lies on an open border of the skin (an edge
    of one triangle only). Points in no triangle are left as they are.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Skin points (mm).
    triangles : array_like of int, shape (m, 3)
        Skin triangles (:func:`skin_triangles`).
    modelled : array_like of bool, shape (n,)
        Points the mesh models (within the transfer's band).
    max_area : float
        Largest island area (mm^2) filled (:func:`island_area_limit`); 0 fills nothing.

    Returns
    -------
    numpy.ndarray of bool, shape (n,)
        A new array: ``modelled`` or in a filled island.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> skin = pv.Sphere(radius=10.0, theta_resolution=30, phi_resolution=30)
    >>> z = skin.points[:, 2]
    >>> ring = (z > 4.5) & (z < 4.9)              # ~25 mm^2, unmodelled
    >>> modelled = (z > -3.0) & ~ring             # the rest below z = -3: ~440 mm^2
    >>> out = fill_enclosed(skin.points, skin_triangles(skin), modelled, 100.0)
    >>> bool(out[ring].all()), bool(out[z < -3.0].any())    # the ring only
    (True, False)
    """
    p = np.asarray(points, dtype=float)
    m = np.asarray(modelled).reshape(-1).astype(bool)
    tri = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    if p.ndim != 2 or p.shape[1] != 3 or len(m) != len(p):
        raise ValueError(f"points must have shape (n, 3) and modelled shape (n,), got "
                         f"{p.shape} and {m.shape}")
    if not float(max_area) >= 0:
        raise ValueError(f"max_area must be >= 0 mm^2, got {max_area!r}")
    out = m.copy()
    if not len(tri) or m.all() or not m.any() or float(max_area) == 0:
        return out
    if tri.min() < 0 or tri.max() >= len(p):
        raise ValueError(f"triangles must index the {len(p)} points, got ids "
                         f"{tri.min()} .. {tri.max()}")
    n = len(p)
    edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, uses = np.unique(edges, axis=0, return_counts=True)
    border = np.zeros(n, dtype=bool)
    border[edges[uses == 1].ravel()] = True
    free = ~m
    e = edges[free[edges].all(axis=1)]
    graph = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    a = 0.5 * np.linalg.norm(np.cross(p[tri[:, 1]] - p[tri[:, 0]], p[tri[:, 2]] - p[tri[:, 0]]),
                             axis=1)
    point_area = np.bincount(tri.ravel(), np.repeat(a / 3.0, 3), minlength=n)
    in_tri = np.bincount(tri.ravel(), minlength=n) > 0
    ncomp = int(comp.max()) + 1
    area = np.bincount(comp[free], point_area[free], minlength=ncomp)
    touches = np.bincount(comp[free & border], minlength=ncomp) > 0
    rim = edges[free[edges].sum(axis=1) == 1]  # one end modelled, one not
    rim = rim[free[rim]]
    enclosed = np.bincount(comp[rim], minlength=ncomp) > 0  # modelled skin around it
    small = (area <= float(max_area)) & ~touches & enclosed
    fill = free & in_tri & small[comp]
    out |= fill
    if fill.any():
        log.info("skin: %d unmodelled points in %d islands enclosed by modelled skin (each "
                 "at most %.3g mm^2) count as modelled", int(fill.sum()),
                 len(np.unique(comp[fill])), float(max_area))
    return out


def modelled_skin(skin, modelled, grid, edges=ISLAND_EDGES):
    """The modelled mask of ``skin`` (:data:`pvcmf.arrays.SKIN_MODELLED`): ``modelled``
    (points within the transfer's band of the tetrahedral ``grid``) with the enclosed
    islands of at most :func:`island_area_limit` ``(grid, edges)`` filled
    (:func:`fill_enclosed`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> grid = pv.ImageData(dimensions=(3, 3, 3), spacing=(2.0, 2.0, 2.0)).triangulate()
    >>> skin = pv.Sphere(radius=10.0, theta_resolution=30, phi_resolution=30)
    >>> z = skin.points[:, 2]
    >>> hole = (z > 4.5) & (z < 4.9)              # ~25 mm^2; the limit: ~100 mm^2
    >>> out = modelled_skin(skin, (z > -3.0) & ~hole, grid)
    >>> bool(out[hole].all()), bool(out[z < -3.0].any())
    (True, False)
    """
    return fill_enclosed(skin.points, skin_triangles(skin), modelled,
                         island_area_limit(grid, edges))


def undo_decay(u_skin, filled, decay):
    """The transferred displacement with the decay beyond the band taken back at the
    ``filled`` points (islands :func:`modelled_skin` fills): there the transfer's row is
    the extension times ``decay`` (in ``(0, 1]`` within ``2 band``; no smoothing step moves
    a point beyond the band), so ``u / decay`` is the extension itself, as for the
    modelled skin around it.

    Parameters
    ----------
    u_skin : array_like, shape (n, 3)
        Transferred displacement (mm).
    filled : array_like of bool, shape (n,)
        Points modelled only through a filled island.
    decay : array_like, shape (n,)
        The transfer's decay weight per point
        (:func:`pvcmf.filters.surface_mapping._decay` of its distance and band).

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        A new array; rows outside ``filled`` or with no decay weight left as they are.

    Examples
    --------
    >>> undo_decay([[1.0, 0, 0], [1.0, 0, 0]], [False, True], [0.5, 0.5]).tolist()
    [[1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]
    """
    u = np.array(u_skin, dtype=float)
    f = np.asarray(filled, dtype=bool).reshape(-1)
    w = np.asarray(decay, dtype=float).reshape(-1)
    if u.shape != (len(f), 3) or len(w) != len(f):
        raise ValueError(f"u_skin must have shape (n, 3) and filled, decay shape (n,), got "
                         f"{u.shape}, {f.shape} and {w.shape}")
    rows = f & (w > 0)
    u[rows] /= w[rows, None]
    return u
