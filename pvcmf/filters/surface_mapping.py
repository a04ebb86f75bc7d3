"""Carry a tetrahedral mesh's displacement onto a dense skin surface.

Two mappings, both linear sparse operators (skin points x mesh points) built once per mesh
and skin:

``method="interpolate"`` (default, :func:`transfer_operator`, :class:`Transfer`)
    A skin point inside the tetrahedral mesh takes the finite-element (barycentric)
    interpolation of its tetrahedron. A point outside takes
    ``u(p) = u_h(q) + G(q) (p - q)``: ``q`` is the closest point of the mesh's boundary
    surface (blended over the boundary triangles that are nearly as close, so that ``q``
    does not jump at a concave boundary), ``u_h(q)`` the linear interpolation on its boundary triangle and ``G(q)`` a
    smooth convex combination of the nodal displacement gradients (volume-weighted means
    of the gradients of the tetrahedra around a node) at the ``k`` boundary nodes nearest
    to ``q``, with weights ``(1 - (d_j / d_(k+1))^2)^2`` that vanish as a node leaves the
    ``k`` nearest (continuous in ``q``). Properties: an affine field is reproduced exactly
    within ``band`` of the mesh (every gradient is its gradient; farther out the offset
    ``p - q`` saturates smoothly, so unsimulated skin far behind a face model is not
    extrapolated without bound); the extension is continuous across the
    mesh boundary (``p -> q``); ``|G|`` is at most the largest gradient of the tetrahedra
    involved (a convex combination of them). No nearest-node copy, so no steps.
    :func:`crumple_metric` checks, per skin edge, that the mapped field stretches it no
    more than the steepest tetrahedron around it.
``method="gaussian"`` (paper 001, :class:`SurfaceMapping`)
    Paper 001 maps the coarse tetrahedral deformation to a dense skin "with some kind of
    Gaussian smoothing" (its reference [3] gives no formula). pvcmf uses a
    Gaussian-weighted *moving least-squares* fit: for each skin point ``p`` the
    displacements ``u_j`` of the grid nodes ``x_j`` within ``radius`` (default
    ``3 sigma``) are fitted by an affine field ``u(x) = c + G (x - p)`` minimising
    ``sum_j w_j |u(x_j) - u_j|^2`` with ``w_j = max(exp(-|x_j - p|^2 / 2 sigma^2) -
    exp(-radius^2 / 2 sigma^2), 0)``, and ``p`` moves by ``c``. An affine field is
    reproduced where the point lies among its neighbours; where the moment matrix is
    singular the Gaussian-weighted mean is used; the result is clamped per component to
    the neighbours' range (no new extrema), and points with no node within ``radius`` get
    zero displacement (point array ``SUPPORT`` holds the weight sums). Kept for the
    paper's figures; the clamp can tear a step at the edge of the mesh.

Delegates to VTK's probe filter (:meth:`pyvista.DataSet.sample`: the tetrahedron holding
each point), VTK's surface extraction (the mesh's boundary triangles),
:class:`scipy.spatial.cKDTree` (nearest boundary triangles and nodes), batched
:func:`numpy.linalg.solve` / :func:`numpy.linalg.inv` (barycentric coordinates, gradients)
and :mod:`scipy.sparse` (the operators).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
import scipy.sparse as sp
from scipy.spatial import cKDTree

from .. import arrays
from ..progress import Progress
from .skin import _boundary_faces

log = logging.getLogger(__name__)

#: point array written by :func:`map_to_surface`: sum of the Gaussian weights (0 = no grid
#: node within the radius, displacement set to zero)
SUPPORT = arrays.MAPPING_SUPPORT


#: ``map_to_surface`` methods
METHODS = ("interpolate", "gaussian")
#: default number of boundary nodes whose gradients extend the field outside the mesh
DEFAULT_K = 8
#: default distance (mm) from the mesh within which the extension is exactly affine; beyond
#: it the offset along which the boundary gradient extrapolates saturates (at twice this)
DEFAULT_BAND = 4.0
#: barycentric coordinates down to this (negative) value still count as inside a tetrahedron
_INSIDE_TOL = 1e-6


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


class _Located:
    """Where skin points lie relative to a tetrahedral mesh (shared by the transfer and the
    crumple metric).

    Inside: the containing tetrahedron and barycentric coordinates. Outside: "feet" on the
    boundary, one per nearby boundary triangle whose distance is within a window of the
    smallest (width ``d_1 h / (d_1 + h)``, ``h`` the median boundary edge), each with its
    closest point, the ``k`` boundary nodes nearest to it and their smooth weights; the
    feet are blended with weights ``(1 - s^2)^2`` (``s`` the excess distance over the
    window), so the foot point never jumps where the closest triangle changes (concave
    boundary), and the blend shrinks to the closest point as the point nears the boundary.
    """

    def __init__(self, grid, points, k=DEFAULT_K, n_triangles=6):
        self.points, self.tets = _tetra(grid)
        p = np.asarray(points, dtype=float)
        self.p = p
        src = pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)
        self._find_cells(src)
        self.outside = out = np.flatnonzero(~self.inside)
        tri = _boundary_faces(src)
        self.boundary = np.unique(tri)
        n_pairs = 0
        if out.size:
            rows, q, bary, face = self._feet(tri, out, n_triangles)
            n_pairs = len(rows)
            kk = max(1, min(k, len(self.boundary) - 1))
            dist, idx = cKDTree(self.points[self.boundary]).query(q, k=kk + 1)
            dist, idx = dist.reshape(n_pairs, -1), idx.reshape(n_pairs, -1)
            h = dist[:, -1:]
            s = np.where(h > 0, dist[:, :-1] / np.where(h > 0, h, 1.0), 0.0)
            w = (1.0 - s**2) ** 2
            w /= w.sum(axis=1, keepdims=True)
            self.near, self.near_w = idx[:, :-1], w  # indices into self.boundary
            self.pair_row, self.q, self.face_bary, self.face = rows, q, bary, face
        if not n_pairs:
            self.pair_row, self.pair_w = np.zeros(0, dtype=np.int64), np.zeros(0)
            self.q = np.zeros((0, 3))
            self.face_bary, self.face = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
            self.near, self.near_w = np.zeros((0, 1), dtype=np.int64), np.zeros((0, 1))

    def _find_cells(self, src):
        """Containing tetrahedra: VTK's probe, then the tetrahedra with the nearest
        centroids for the points it misses (on shared faces, within round-off)."""
        p, pts, tets = self.p, self.points, self.tets
        src.cell_data[arrays.SCRATCH_CELL_ID] = np.arange(len(tets), dtype=np.int64)
        probe = pv.PolyData(p).sample(src, pass_point_data=False, progress_bar=False)
        cell = np.where(np.asarray(probe[arrays.VALID_POINT_MASK]).astype(bool),
                        np.asarray(probe[arrays.SCRATCH_CELL_ID]).astype(np.int64), -1)
        bary = np.full((len(p), 4), -np.inf)

        def barycentric(idx, cells):
            t = tets[cells]
            x0 = pts[t[:, 0]]
            edges = pts[t[:, 1:]] - x0[:, None, :]
            ok = np.abs(np.linalg.det(edges)) > 1e-300
            lam = np.full((len(idx), 3), -np.inf)
            if ok.any():
                lam[ok] = np.linalg.solve(np.swapaxes(edges[ok], 1, 2),
                                          (p[idx[ok]] - x0[ok])[:, :, None])[:, :, 0]
            return np.column_stack([1 - lam.sum(axis=1), lam])

        hit = np.flatnonzero(cell >= 0)
        bary[hit] = barycentric(hit, cell[hit])
        miss = np.flatnonzero(bary.min(axis=1) < -_INSIDE_TOL)
        if miss.size:
            kc = min(8, len(tets))
            cand = cKDTree(pts[tets].mean(axis=1)).query(p[miss], k=kc)[1].reshape(len(miss), kc)
            for j in range(kc):
                b = barycentric(miss, cand[:, j])
                better = b.min(axis=1) > bary[miss].min(axis=1)
                bary[miss[better]], cell[miss[better]] = b[better], cand[better, j]
        self.inside = bary.min(axis=1) >= -_INSIDE_TOL
        self.cell = np.where(self.inside, cell, -1)
        self.bary = np.where(self.inside[:, None], bary, 0.0)

    def _feet(self, tri, out, n_triangles):
        """Blended feet of the outside points on the boundary triangles ``tri``."""
        p, pts = self.p[out], self.points
        kt = min(n_triangles, len(tri))
        cand = cKDTree(pts[tri].mean(axis=1)).query(p, k=kt)[1].reshape(len(out), kt)
        qs, bs, ds = [], [], []
        for j in range(kt):  # a few candidate triangles per point, each vectorised
            tj = tri[cand[:, j]]
            q, b = _closest_on_triangles(p, pts[tj[:, 0]], pts[tj[:, 1]], pts[tj[:, 2]])
            qs.append(q), bs.append(b), ds.append(np.linalg.norm(q - p, axis=1))
        d = np.stack(ds, axis=1)
        d1 = d.min(axis=1, keepdims=True)
        e = pts[tri[:, [0, 1, 2]]] - pts[tri[:, [1, 2, 0]]]
        h = float(np.median(np.linalg.norm(e, axis=2)))
        window = d1 * h / (d1 + h)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(window > 0, (d - d1) / window, np.where(d > d1, np.inf, 0.0))
        w = np.where(s < 1, (1 - np.minimum(s, 1) ** 2) ** 2, 0.0)
        w /= w.sum(axis=1, keepdims=True)
        r, j = np.nonzero(w > 0)
        self.pair_w = w[r, j]
        q = np.stack(qs, axis=1)[r, j]
        bary = np.stack(bs, axis=1)[r, j]
        return out[r], q, bary, tri[cand[r, j]]


def transfer_operator(grid, points, *, k=DEFAULT_K, band=DEFAULT_BAND, progress_bar=False):
    """Sparse operator ``T`` (points x grid points) with ``u_points = T @ u_nodes``.

    Inside the mesh: barycentric interpolation in the containing tetrahedron. Outside:
    ``u_h(q) + G(q) (p - q)`` with ``q`` the closest boundary point, blended over the
    nearly closest boundary triangles (see the module docs): exact for affine fields, continuous across the boundary, gradient bounded by
    the tetrahedra involved.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh (rest positions, mm).
    points : array_like or pyvista.DataSet
        ``(n, 3)`` points (e.g. a dense skin's points) in the grid's frame.
    k : int, default 8
        Boundary nodes whose gradients extend the field outside the mesh.
    band : float, default 4.0
        Distance (mm) from the mesh within which the extension is exactly affine (the
        skin the mesh models lies within a voxel or two). Farther points (skin that is
        not simulated, e.g. behind a face model) extrapolate the boundary gradient over
        an offset that saturates smoothly at ``2 band``, so their displacement stays
        bounded; ``numpy.inf`` extrapolates linearly everywhere.
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, grid.n_points)
        Rows sum to one (a constant field is kept).

    Raises
    ------
    TypeError, ValueError
        ``grid`` not all-tetrahedral, ``points`` not ``(n, 3)``, ``k < 1``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.surface_mapping import transfer_operator
    >>> grid = pv.ImageData(dimensions=(4, 4, 4)).triangulate()
    >>> pts = np.array([[1.2, 1.5, 0.7], [5.0, 1.0, 1.0]])     # inside, outside
    >>> u = 0.1 * grid.points + 1.0                              # an affine field
    >>> bool(np.allclose(transfer_operator(grid, pts) @ u, 0.1 * pts + 1.0))
    True
    """
    pts = np.asarray(points.points if isinstance(points, pv.DataSet) else points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"points must have shape (n, 3) with n > 0, got {pts.shape}")
    if isinstance(k, bool) or int(k) != k or k < 1:
        raise ValueError(f"k must be a positive integer, got {k!r}")
    with Progress(total=2, desc="transfer_operator", enabled=progress_bar, logger=log) as bar:
        loc = _Located(grid, pts, int(k))
        bar.step(f"{int(loc.inside.sum())} of {len(pts)} points inside the mesh")
        T = _assemble(loc, float(band))
        bar.step("operator assembled")
    log.info("transfer_operator: %d points, %d inside tetrahedra, %d extended from the "
             "boundary", len(pts), int(loc.inside.sum()), loc.outside.size)
    return T


def _saturate(d, band):
    """Factor ``l(d) / d``: ``l = d`` up to ``band``, then ``band (1 + tanh((d - band) /
    band))`` (smooth, slope <= 1, at most ``2 band``)."""
    if not np.isfinite(band):
        return np.ones_like(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        ell = np.where(d <= band, d, band * (1.0 + np.tanh((d - band) / band)))
        return np.where(d > 0, ell / d, 1.0)


def _assemble(loc, band=DEFAULT_BAND):
    n, m = len(loc.p), len(loc.points)
    ins = np.flatnonzero(loc.inside)
    T = sp.csr_matrix((loc.bary[ins].ravel(), (np.repeat(ins, 4), loc.tets[loc.cell[ins]].ravel())),
                      shape=(n, m))
    npair = len(loc.pair_row)
    if npair:  # one row per foot: u_h(q) + G(q) (p - q); then blended per point
        face = sp.csr_matrix((loc.face_bary.ravel(), (np.repeat(np.arange(npair), 3),
                                                      loc.face.ravel())), shape=(npair, m))
        used, inverse = np.unique(loc.near, return_inverse=True)
        kk = loc.near.shape[1]
        W = sp.csr_matrix((loc.near_w.ravel(), (np.repeat(np.arange(npair), kk),
                                                inverse.ravel())), shape=(npair, len(used)))
        D = _gradient_operators(loc.points, loc.tets, loc.boundary[used])
        offset = loc.p[loc.pair_row] - loc.q
        offset *= _saturate(np.linalg.norm(offset, axis=1), band)[:, None]
        feet = face
        for c in range(3):
            feet = feet + sp.diags(offset[:, c]) @ (W @ D[c])
        blend = sp.csr_matrix((loc.pair_w, (loc.pair_row, np.arange(npair))), shape=(n, npair))
        T = T + blend @ feet
    T = T.tocsr()
    T.sum_duplicates()
    T.eliminate_zeros()
    return T


class Transfer:
    """:func:`transfer_operator` as a callable mapping (the interface of
    :class:`SurfaceMapping`): ``Transfer(grid, points)(u)`` is ``T @ u``.

    Attributes
    ----------
    W : scipy.sparse.csr_matrix
        The operator ``T``.
    inside : ndarray of bool
        Points inside a tetrahedron.
    """

    def __init__(self, grid, points, k=DEFAULT_K, band=DEFAULT_BAND):
        loc = _Located(grid, points, k)
        self.W = _assemble(loc, band)
        self.inside = loc.inside

    def __call__(self, u):
        return np.asarray(self.W @ np.asarray(u, dtype=float))


def map_to_surface(grid, skin, *, method="interpolate", sigma=2.0, radius=None, k=DEFAULT_K,
                   warp=True, progress_bar=False):
    """Map the grid's point ``displacement`` onto a dense skin surface.

    Parameters
    ----------
    grid : pyvista.DataSet
        Tetrahedral grid with point array ``arrays.DISPLACEMENT`` (any point set for
        ``method="gaussian"``).
    skin : pyvista.DataSet
        Dense skin surface (e.g. :func:`pvcmf.filters.extract_skin` of the label image),
        in the grid's rest frame.
    method : {'interpolate', 'gaussian'}, default 'interpolate'
        ``'interpolate'``: :func:`transfer_operator` (finite-element interpolation inside,
        an exact-for-affine smooth extension outside). ``'gaussian'``: paper 001's
        Gaussian moving least-squares (:class:`SurfaceMapping`).
    sigma : float, default 2.0
        ``'gaussian'`` only: Gaussian width (mm); larger smooths more.
    radius : float, optional
        ``'gaussian'`` only: neighbourhood radius (mm); default ``3 * sigma``.
    k : int, default 8
        ``'interpolate'`` only: boundary nodes of the extension outside the mesh.
    warp : bool, default True
        Move the skin points by the mapped displacement (the predicted dense skin).
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.DataSet
        Copy of ``skin`` with point array ``arrays.DISPLACEMENT`` (float64 (n, 3), mm),
        and ``arrays.TRANSFER_INSIDE`` (``'interpolate'``: 1 inside a tetrahedron) or
        ``SUPPORT`` (``'gaussian'``); points moved when ``warp``.

    Raises
    ------
    ValueError
        Missing ``displacement``, empty inputs, an unknown ``method``, or ``sigma`` /
        ``radius`` not positive.

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(11, 11, 11), origin=(-5, -5, -5)).triangulate()
    >>> grid[arrays.DISPLACEMENT] = 0.1 * grid.points          # a linear field
    >>> skin = pv.Sphere(radius=6.0)                            # partly outside the grid
    >>> out = grid.cmf.map_to_surface(skin)
    >>> bool(np.allclose(out[arrays.DISPLACEMENT], 0.1 * skin.points))
    True
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(grid, pv.DataSet) or not isinstance(skin, pv.DataSet):
        raise TypeError(
            f"grid and skin must be pyvista datasets, got {type(grid).__name__} and "
            f"{type(skin).__name__}"
        )
    u = arrays.require_array(grid, arrays.DISPLACEMENT, "point", dtype="f", ncomp=3,
                             producer="pvcmf.mtm.solve")
    if grid.n_points == 0 or skin.n_points == 0:
        raise ValueError(
            f"grid and skin must have points, got {grid.n_points} and {skin.n_points}"
        )
    out = skin.copy()
    if method == "interpolate":
        with Progress(total=1, desc="map_to_surface", enabled=progress_bar, logger=log) as bar:
            mapping = Transfer(grid, skin.points, k=k)
            disp = mapping(u)
            bar.step(f"{skin.n_points} skin points")
        out.point_data[arrays.TRANSFER_INSIDE] = mapping.inside.astype(np.uint8)
    else:
        disp = _gaussian(grid, skin, u, sigma, radius, progress_bar, out)
    out.point_data[arrays.DISPLACEMENT] = disp
    if warp:
        out.points = np.asarray(skin.points, float) + disp
    return out


def _gaussian(grid, skin, u, sigma, radius, progress_bar, out):
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 mm, got {sigma}")
    radius = 3.0 * sigma if radius is None else float(radius)
    if not radius > 0:
        raise ValueError(f"radius must be > 0 mm, got {radius}")
    with Progress(total=2, desc="map_to_surface", enabled=progress_bar, logger=log) as bar:
        mapping = SurfaceMapping(grid.points, skin.points, sigma, radius)
        bar.step(f"weights of {skin.n_points} skin points")
        disp, support = mapping(u), mapping.support
        bar.step("displacement mapped")
    out.point_data[SUPPORT] = support
    n_out = int((support == 0).sum())
    if n_out:
        log.info("map_to_surface: %d of %d skin points have no grid node within %.3g mm",
                 n_out, skin.n_points, radius)
    return disp


def _edges(surface):
    """Unique edges ``(e, 2)`` of a surface's polygons."""
    poly = surface if isinstance(surface, pv.PolyData) else surface.extract_surface()
    faces = poly.faces
    if poly.n_cells and poly.is_all_triangles:
        tri = faces.reshape(-1, 4)[:, 1:]
        e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
    else:
        lines = poly.extract_all_edges(use_all_points=True).lines.reshape(-1, 3)
        e = lines[:, 1:]
    return np.unique(np.sort(e, axis=1), axis=0)


def crumple_metric(skin_pre, u_skin, grid, u_nodes, *, k=DEFAULT_K, slack=0.1):
    """Check that a skin displacement stretches no skin edge beyond the mesh's gradients.

    For every edge ``(a, b)`` of ``skin_pre`` the stretch ``|u_a - u_b| / |x_a - x_b|`` is
    compared with the largest displacement-gradient norm (spectral) of the tetrahedra
    around it: the tetrahedra sharing a node with the tetrahedron that holds an endpoint,
    or, for an endpoint outside the mesh, those sharing a node with its nearest boundary
    triangles (the feet of :func:`transfer_operator`) or with the ``k`` boundary nodes
    nearest to those feet. A smooth
    transfer stays within that bound; a step (a nearest-node copy, a clamp) exceeds it.

    Parameters
    ----------
    skin_pre : pyvista.PolyData
        The skin at rest (its edges are checked).
    u_skin : array_like, shape (n, 3)
        Skin displacement (mm).
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh at rest.
    u_nodes : array_like, shape (grid.n_points, 3)
        The mesh displacement (mm).
    k : int, default 8
        Boundary nodes around an outside point (as :func:`transfer_operator`).
    slack : float, default 0.1
        An edge violates the bound when its stretch exceeds ``(1 + slack)`` times it.

    Returns
    -------
    dict
        ``ratio`` (per edge: stretch / bound, 0 where both vanish), ``edges`` ((e, 2)),
        and the summary values under ``arrays.CRUMPLE_EDGES``, ``arrays.CRUMPLE_VIOLATIONS``
        and ``arrays.CRUMPLE_MAX_RATIO``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.surface_mapping import crumple_metric, transfer_operator
    >>> grid = pv.ImageData(dimensions=(6, 6, 6)).triangulate()
    >>> u = np.column_stack([np.sin(grid.points[:, 0]), np.zeros((grid.n_points, 2))])
    >>> skin = pv.Sphere(radius=2.0, center=(2.5, 2.5, 2.5))
    >>> m = crumple_metric(skin, transfer_operator(grid, skin) @ u, grid, u)
    >>> m[arrays.CRUMPLE_VIOLATIONS]
    0
    """
    u_skin = np.asarray(u_skin, dtype=float)
    u_nodes = np.asarray(u_nodes, dtype=float)
    if u_skin.shape != (skin_pre.n_points, 3):
        raise ValueError(f"u_skin must have shape ({skin_pre.n_points}, 3), got {u_skin.shape}")
    if u_nodes.shape != (grid.n_points, 3):
        raise ValueError(f"u_nodes must have shape ({grid.n_points}, 3), got {u_nodes.shape}")
    loc = _Located(grid, skin_pre.points, k)
    inv, _ = _gradients(loc.points, loc.tets)
    du = u_nodes[loc.tets[:, 1:]] - u_nodes[loc.tets[:, :1]]  # (m, 3 edges, 3 comps)
    grad = np.einsum("tca,tai->tic", inv, du)  # d u_i / d x_c
    gnorm = np.linalg.norm(grad, ord=2, axis=(1, 2))
    node_max = np.zeros(len(loc.points))
    np.maximum.at(node_max, loc.tets.ravel(), np.repeat(gnorm, 4))
    bound = np.zeros(len(loc.p))
    ins = np.flatnonzero(loc.inside)
    bound[ins] = node_max[loc.tets[loc.cell[ins]]].max(axis=1)
    if len(loc.pair_row):
        around = np.concatenate([loc.face, loc.boundary[loc.near]], axis=1)
        np.maximum.at(bound, loc.pair_row, node_max[around].max(axis=1))
    e = _edges(skin_pre)
    x = np.asarray(skin_pre.points, dtype=float)
    length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
    stretch = np.linalg.norm(u_skin[e[:, 0]] - u_skin[e[:, 1]], axis=1) / np.maximum(length, 1e-300)
    limit = np.maximum(bound[e[:, 0]], bound[e[:, 1]])
    tiny = 1e-9 * max(float(gnorm.max(initial=0.0)), 1e-12)
    ratio = np.where(limit > tiny, stretch / np.maximum(limit, tiny), np.where(stretch > tiny, np.inf, 0.0))
    return {"ratio": ratio, "edges": e, arrays.CRUMPLE_EDGES: int(len(e)),
            arrays.CRUMPLE_VIOLATIONS: int(np.sum(ratio > 1.0 + slack)),
            arrays.CRUMPLE_MAX_RATIO: float(ratio.max(initial=0.0))}


class SurfaceMapping:
    """The Gaussian moving least-squares mapping as a precomputed sparse operator.

    The affine fit is linear in the grid displacement (only the final clamp to the
    neighbours' range is not) and its weights depend only on the grid and skin points, so
    the mapping is a sparse matrix ``W`` (skin points x grid points) built once; each field
    then costs one sparse product and a vectorised clamp (``numpy.minimum.reduceat``). The
    fit's value at ``p``, ``c = e0 . M^-1 r``, is ``(M^-1 e0) . r`` because the moment
    matrix ``M`` is symmetric, so row ``i`` of ``W`` is
    ``w_ij (1, (x_j - p_i) / sigma) . M_i^-1 e0``; rows whose moment matrix is singular
    (condition > 1e8 after scaling) hold the Gaussian-weighted mean. Used by
    :func:`map_to_surface` and by parameter sweeps that map many fields on one mesh
    (:class:`pvcmf.sweeps.PipelineEvaluation`).

    Parameters
    ----------
    grid_points, skin_points : array_like, shape (m, 3) and (n, 3)
        Grid nodes and skin points (mm).
    sigma, radius : float
        Gaussian width and neighbourhood radius (mm), both > 0.

    Attributes
    ----------
    W : scipy.sparse.csr_matrix, shape (n, m)
    support : ndarray, shape (n,)
        Sum of the Gaussian weights of each skin point (0: no grid node within ``radius``).
    """

    def __init__(self, grid_points, skin_points, sigma, radius):
        x = np.asarray(grid_points, float)
        p = np.asarray(skin_points, float)
        n, m = len(p), len(x)
        pairs = cKDTree(p).sparse_distance_matrix(cKDTree(x), radius, output_type="ndarray")
        w = np.exp(-0.5 * (pairs["v"] / sigma) ** 2) - np.exp(-0.5 * (radius / sigma) ** 2)
        keep = w > 0
        i, j, w = pairs["i"][keep], pairs["j"][keep], w[keep]
        order = np.lexsort((j, i))
        i, j, w = i[order], j[order], w[order]
        basis = np.column_stack([np.ones(len(i)), (x[j] - p[i]) / sigma])  # well conditioned
        moments = np.empty((n, 4, 4))
        for a in range(4):  # 10 unique moments by bincount, not a loop over points
            for b in range(a, 4):
                moments[:, a, b] = moments[:, b, a] = np.bincount(i, w * basis[:, a] * basis[:, b],
                                                                  minlength=n)
        self.support = moments[:, 0, 0].copy()
        has = self.support > 0
        coef = np.zeros((n, 4))
        idx = np.flatnonzero(has)
        cond_ok = np.linalg.cond(moments[idx] / self.support[idx][:, None, None]) < 1e8
        fit, mean = idx[cond_ok], idx[~cond_ok]
        if fit.size:  # affine fit where well conditioned
            e0 = np.zeros((fit.size, 4, 1))
            e0[:, 0] = 1.0
            coef[fit] = np.linalg.solve(moments[fit], e0)[:, :, 0]
        coef[mean, 0] = 1.0 / self.support[mean]  # weighted mean elsewhere
        values = w * np.einsum("ij,ij->i", basis, coef[i])
        self.W = sp.csr_matrix((values, (i, j)), shape=(n, m))
        self._neighbours = j
        self._has = has
        self._starts = np.searchsorted(i, np.arange(n))[has]

    def __call__(self, u):
        """Skin displacement ``(n, 3)`` for the grid displacement ``u`` ``(m, 3)``."""
        u = np.asarray(u, float)
        disp = np.asarray(self.W @ u)
        if self._starts.size:
            # no new extrema: where the skin point lies outside its neighbours' cloud (the
            # edge of the mesh) the affine fit extrapolates; clamp each component to the
            # neighbours' range
            v = u[self._neighbours]
            lo = np.minimum.reduceat(v, self._starts, axis=0)
            hi = np.maximum.reduceat(v, self._starts, axis=0)
            disp[self._has] = np.clip(disp[self._has], lo, hi)
        return disp
