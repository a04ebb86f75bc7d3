"""Carry a tetrahedral mesh's displacement onto a dense skin surface.

Two mappings, both linear sparse operators (skin points x mesh points) built once per mesh
and skin:

``method="interpolate"`` (default, :func:`transfer_operator`, :class:`Transfer`)
    A skin point inside the tetrahedral mesh takes the finite-element (barycentric)
    interpolation of its tetrahedron. A point ``p`` outside takes ``c``, the value at
    ``p`` of a local affine fit ``c + A (x - p)`` to its *feet*: ``q_f``, the closest points
    of the boundary triangles that are nearly as close as the closest (weights ``w_f``
    that fall smoothly to zero at the edge of the window, so nothing jumps at a concave
    boundary), with the values ``u_h(q_f)`` of the linear interpolation on their
    triangles. ``(c, A)`` minimise ``sum_f w_f |u_h(q_f) - c - A (q_f - p)|^2 + lam
    (sum_f w_f) |A - G(q)|^2``: the slope is pulled towards ``G(q)``, a smooth convex
    combination of the nodal displacement gradients (volume-weighted means of the
    gradients of the tetrahedra around a node) at the ``k`` boundary nodes nearest to the
    blended foot ``q = sum_f w_f q_f``, with weights ``(1 - (d_j / d_(k+1))^2)^2`` that
    vanish as a node leaves the ``k`` nearest; ``lam = (FIT_STIFFNESS (d + h))^2`` (``d``
    the distance, ``h`` the median mesh edge). Where the feet's values follow one affine
    field the fit returns it; where they do not (a concave boundary, whose feet sweep
    faster than ``p`` moves), the fit follows the feet's own slope rather than adding a
    foreign gradient to their variation. As ``lam`` grows the value tends to
    ``sum_f w_f u_h(q_f) + G(q) (p - q)``. Properties: an affine field is reproduced
    exactly within ``band`` of the mesh, the *modelled* skin (every foot value and every
    gradient is the field's); farther out (skin the mesh does not model, e.g. behind a
    face model's posterior cut) the extension is multiplied by a smooth step that reaches
    zero, the value on the fixed posterior plane, at ``2 band`` (point array
    ``arrays.SKIN_MODELLED`` tells the two apart); the extension is continuous across the
    mesh boundary (the window and the offsets ``q_f - p`` shrink to zero with ``d``); the
    operator is linear in the nodal displacements. No nearest-node copy, so no steps.
    Where the boundary is concave (a crack between the lips, a fold) the feet of
    neighbouring points lie far apart and the fit alone can stretch a skin edge beyond
    the mesh's gradients; ``smoothing`` explicit steps
    (:func:`pvcmf.filters.transfer_smoothing.smooth_outside`) then move each point
    outside the mesh and within ``band`` towards the mean of its nearest skin points'
    values, each carried to it by the fit's gradient ``G(q)`` (``u_q + G (x_p - x_q)``):
    the points inside keep their interpolation, an affine field stays exact, and the
    operator stays sparse (its outside rows take their neighbours' supports).
    :func:`crumple_metric` checks, per skin edge, that the mapped field stretches it no
    more than the steepest tetrahedron around it (for a point outside: around its feet's
    triangles and its ``k`` boundary nodes, the tetrahedra whose values and gradients
    enter the fit); :func:`pvcmf.filters.crumple_bound.unavoidable_crumples` bounds
    from below the violations that no extension outside the mesh could avoid.
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

Delegates the geometry (containing tetrahedra, feet on the boundary, nearest boundary
nodes: tetrahedron bounding boxes binned on a grid with vectorised barycentric checks,
:class:`scipy.spatial.cKDTree`, vectorised closest points) to
:mod:`pvcmf.filters.transfer_locate`, the gradients to batched :func:`numpy.linalg.inv`, the fits to batched
:func:`numpy.linalg.solve` (4 x 4 per point), the smoothing outside the mesh to
:mod:`pvcmf.filters.transfer_smoothing`, the rows before it to
:mod:`pvcmf.filters.transfer_assembly` and the operators to :mod:`scipy.sparse`.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
import scipy.sparse as sp

from .. import arrays
from ..progress import Progress
from .gaussian_mapping import SurfaceMapping  # noqa: F401  (re-exported)
from .transfer_assembly import rows_operator
from .transfer_locate import Located as _Located
from .transfer_locate import DEFAULT_BAND, MeshIndex, mesh_band  # noqa: F401  (re-exported)
from .transfer_locate import resolve_band as _resolve_band
from .transfer_locate import gradient_operators as _gradient_operators  # noqa: F401
from .transfer_locate import stacked_gradients as _stacked_gradients
from .transfer_smoothing import DEFAULT_ITERATIONS, smoothing_steps

log = logging.getLogger(__name__)

#: point array written by :func:`map_to_surface`: sum of the Gaussian weights (0 = no grid
#: node within the radius, displacement set to zero)
SUPPORT = arrays.MAPPING_SUPPORT


#: ``map_to_surface`` methods
METHODS = ("interpolate", "gaussian")
#: default number of boundary nodes whose gradients extend the field outside the mesh
DEFAULT_K = 8
#: weight of the nodal gradients against the feet's values in the extension's affine fit
#: (:func:`_fit_weights`): a length in units of the distance plus the mesh's edge
FIT_STIFFNESS = 0.2
#: default stretch (displacement jump over edge length) below which a skin edge never
#: counts as crumpled: 1e-4 is a tenth of a micrometre per millimetre, where both the
#: stretch and the mesh's gradients are round-off of a region that does not move
DEFAULT_FLOOR = 1e-4


def transfer_operator(grid, points, *, k=DEFAULT_K, band=None,
                      smoothing=DEFAULT_ITERATIONS, progress_bar=False):
    """Sparse operator ``T`` (points x grid points) with ``u_points = T @ u_nodes``.

    Inside the mesh: barycentric interpolation in the containing tetrahedron. Outside: a
    local affine fit to the values on the nearly closest boundary triangles, its slope
    pulled towards the nodal gradients there (see the module docs): exact for affine
    fields, continuous across the boundary.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh (rest positions, mm).
    points : array_like or pyvista.DataSet
        ``(n, 3)`` points (e.g. a dense skin's points) in the grid's frame.
    k : int, default 8
        Boundary nodes whose gradients extend the field outside the mesh.
    band : float, optional
        Distance (mm) from the mesh within which the extension is exactly affine: the
        *modelled* skin (default :func:`mesh_band`: the larger of 4 mm and the mesh's
        median boundary edge, as far as the mesh's surface strays from the skin).
        Farther points (skin that is not simulated, e.g. behind a face model's posterior
        cut) take the extension times a smooth step that falls to zero at ``2 band``, the
        value on the fixed posterior plane; beyond ``2 band`` their rows are empty.
        ``numpy.inf`` extrapolates linearly everywhere.
    smoothing : int, default 3
        Gradient-guided smoothing steps of the extension outside the mesh
        (:func:`pvcmf.filters.transfer_smoothing.smooth_outside`; 0: none): they remove
        the stretch of feet that sweep along a concave boundary, keep affine fields
        exact and leave the points inside the mesh as they are.
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, grid.n_points)
        Rows of modelled points sum to one (a constant field is kept there).

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
    return Transfer(grid, pts, k=k, band=band, smoothing=smoothing,
                    progress_bar=progress_bar).W


def _decay(d, band):
    """Weight of the extension at distance ``d`` from the mesh: 1 up to ``band``, a smooth
    step (C1) down to 0 at ``2 band``, 0 beyond (the value on the fixed posterior plane)."""
    if not np.isfinite(band):
        return np.ones_like(d)
    t = np.clip((d - band) / band, 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)


def _guided(loc, rows, offsets, D, factors=False):
    """Sparse ``(n, m)``: row ``p`` (of the outside points ``rows``) is ``G(q_p) o_p`` (the
    blend of the nodal gradients ``D`` (stacked x, y, z) at its nearest boundary nodes
    times ``offsets``) as weights on the nodal displacements (``factors=True``: the
    factors ``(BW, D)`` of that product, ``BW`` of shape ``(n, 3 n_boundary)``)."""
    n, nb, kk = len(loc.p), len(loc.boundary), loc.near.shape[1]
    slot = np.full(n, -1)
    slot[loc.outside] = np.arange(len(loc.outside))
    r = slot[rows]
    # [diag(o_x) W, diag(o_y) W, diag(o_z) W] in one matrix, 3 kk entries per row
    order = np.argsort(rows, kind="stable")
    rows, r, offsets = rows[order], r[order], np.asarray(offsets)[order]
    ptr = np.zeros(n + 1, dtype=np.int64)
    ptr[1:] = np.cumsum(np.bincount(rows, minlength=n) * 3 * kk)
    BW = sp.csr_matrix(((offsets[:, :, None] * loc.near_w[r][:, None, :]).ravel(),
                        (loc.near[r][:, None, :] + nb * np.arange(3)[None, :, None]).ravel(),
                        ptr), shape=(n, 3 * nb))
    return (BW, D) if factors else BW @ D


def _median_edge(loc):
    """Median edge length of the mesh's tetrahedra (mm), kept on ``loc``."""
    if getattr(loc, "median_edge", None) is None and getattr(loc, "index", None) is not None:
        loc.median_edge = loc.index.median_edge
    if getattr(loc, "median_edge", None) is None:
        tets = loc.tets
        e = loc.points[tets[:, [1, 2, 3, 2, 3, 3]]] - loc.points[tets[:, [0, 0, 0, 1, 1, 2]]]
        loc.median_edge = float(np.median(np.linalg.norm(e, axis=2)))
    return loc.median_edge


def _assemble(loc, band=DEFAULT_BAND, iterations=DEFAULT_ITERATIONS):
    """The operator from :class:`Located`, built row-sorted as CSR where the rows come
    sorted (inside points; feet, grouped by point; the outside points' gradient terms),
    then smoothed outside the mesh (:func:`~pvcmf.filters.transfer_smoothing.smooth_outside`,
    ``iterations`` steps)."""
    T, steps = _assemble_parts(loc, band, iterations)
    return T if steps is None else steps.apply(T)


def _tidy(T):
    T = T.tocsr()
    T.sum_duplicates()
    T.eliminate_zeros()
    return T


def _assemble_parts(loc, band=DEFAULT_BAND, iterations=DEFAULT_ITERATIONS):
    """The operator before the smoothing steps and the steps
    (:func:`~pvcmf.filters.transfer_smoothing.smoothing_steps`, None where none)."""
    steps = None
    n, m = len(loc.p), len(loc.points)
    npair = len(loc.pair_row)
    if not npair:
        ins = np.flatnonzero(loc.inside)
        ptr = np.zeros(n + 1, dtype=np.int64)
        ptr[1:] = np.cumsum(loc.inside * 4)
        T = sp.csr_matrix((loc.bary[ins].ravel(), loc.tets[loc.cell[ins]].ravel(), ptr),
                          shape=(n, m))
        return _tidy(T), steps
    # the feet's local affine fit (see _fit_weights), times the decay
    decay = _decay(loc.dist, band)
    alpha, offset = _fit_weights(loc)
    out = loc.outside
    T = rows_operator(loc, alpha * decay[loc.pair_row], offset * decay[out][:, None])
    if iterations:
        D = _stacked_gradients(loc)
        guide = lambda rows, o: _guided(loc, rows, o, D, factors=True)  # noqa: E731
        steps = smoothing_steps(loc.p, loc.dist, band, _median_edge(loc), guide,
                                iterations=iterations)
    return T, steps


def _fit_weights(loc, stiffness=None):
    """The extension at an outside point ``p`` as weights: ``c = sum_f alpha_f u_h(q_f) +
    G(q) o``, where ``(c, A)`` minimise ``sum_f w_f |u_h(q_f) - c - A (q_f - p)|^2 +
    lam (sum_f w_f) |A - G(q)|^2`` (the feet's weights ``w_f``, ``G(q)`` the nodal
    gradients' blend, ``lam = (stiffness (d + h))^2``, ``d`` the distance, ``h`` the
    median mesh edge). Returns ``alpha`` (per foot) and ``o`` (per outside point, (n, 3))."""
    stiffness = FIT_STIFFNESS if stiffness is None else stiffness
    out, p, w = loc.outside, loc.p, loc.pair_w
    slot = np.full(len(p), -1)
    slot[out] = np.arange(len(out))
    r = slot[loc.pair_row]
    # B = [1, q_f - p] (pairs, 4), from its columns (contiguous rows of the feet)
    cols = np.asarray(loc.q).T - np.take(np.ascontiguousarray(p.T), loc.pair_row, axis=1)
    B = np.empty((len(r), 4))
    B[:, 0] = 1.0
    B[:, 1:] = cols.T
    M = np.empty((len(out), 4, 4))  # (B[:, 0] is 1: w B_0 B_b is w B_b)
    for a in range(4):
        wa = w if a == 0 else w * cols[a - 1]
        for b in range(a, 4):
            M[:, a, b] = M[:, b, a] = np.bincount(r, wa if b == 0 else wa * cols[b - 1],
                                                  minlength=len(out))
    h = _median_edge(loc)
    reg = (stiffness * (loc.dist[out] + h)) ** 2 * M[:, 0, 0]  # M[:, 0, 0]: sum of w_f
    M[:, 1:, 1:] += reg[:, None, None] * np.eye(3)
    first = np.linalg.solve(M, np.broadcast_to(np.eye(4)[0], (len(out), 4))[..., None])[..., 0]
    alpha = w * np.einsum("pa,pa->p", B, first[r])
    return alpha, first[:, 1:] * reg[:, None]


class Transfer:
    """:func:`transfer_operator` as a callable mapping (the interface of
    :class:`SurfaceMapping`): ``Transfer(grid, points)(u)`` is ``T @ u``.

    Attributes
    ----------
    W : scipy.sparse.csr_matrix
        The operator ``T`` (``steps`` applied to ``W0``, made on first use and kept).
    W0 : scipy.sparse.csr_matrix
        The operator before the smoothing steps.
    steps : pvcmf.filters.transfer_smoothing.Steps or None
        The smoothing steps as sparse matrices (None: none move a point): ``T @ X`` is
        ``W0 @ X`` with the rows ``steps.rows`` replaced by ``steps.moved_rows(W0, X)``.
    inside : ndarray of bool
        Points inside a tetrahedron.
    distance : ndarray
        Distance (mm) of each point to the mesh (0 inside, ``inf`` beyond ``2 band``).
    modelled : ndarray of bool
        Points within ``band`` of the mesh (:data:`pvcmf.arrays.SKIN_MODELLED`).
    band : float
    smoothing : int
        Smoothing steps outside the mesh (:func:`transfer_operator`).
    """

    def __init__(self, grid, points, k=DEFAULT_K, band=None, smoothing=DEFAULT_ITERATIONS,
                 progress_bar=False):
        pts = np.asarray(points.points if isinstance(points, pv.DataSet) else points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
            raise ValueError(f"points must have shape (n, 3) with n > 0, got {pts.shape}")
        if isinstance(k, bool) or int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer, got {k!r}")
        if isinstance(smoothing, bool) or int(smoothing) != smoothing or smoothing < 0:
            raise ValueError(f"smoothing must be an integer >= 0, got {smoothing!r}")
        self.smoothing = int(smoothing)
        with Progress(total=2, desc="transfer_operator", enabled=progress_bar, logger=log) as bar:
            index = MeshIndex(grid)
            self.band = _resolve_band(band, index)
            self._loc = loc = _Located(grid, pts, int(k), reach=2.0 * self.band, index=index)
            bar.step(f"{int(loc.inside.sum())} of {len(pts)} points inside the mesh")
            self.W0, self.steps = _assemble_parts(loc, self.band, self.smoothing)
            self._W = None if self.steps is not None else self.W0
            bar.step("operator assembled")
        self.inside = loc.inside
        self.distance = loc.dist
        self.modelled = loc.dist <= self.band
        log.info("transfer_operator: %d points, %d inside tetrahedra, %d extended from the "
                 "boundary, %d not modelled (farther than %.3g mm)", len(pts),
                 int(loc.inside.sum()), int((~loc.inside & self.modelled).sum()),
                 int((~self.modelled).sum()), self.band)

    @property
    def W(self):
        if self._W is None:
            self._W = self.steps.apply(self.W0)
        return self._W

    def __call__(self, u):
        return np.asarray(self.W @ np.asarray(u, dtype=float))


def map_to_surface(grid, skin, *, method="interpolate", sigma=2.0, radius=None, k=DEFAULT_K,
                   band=None, warp=True, progress_bar=False):
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
    band : float, optional
        ``'interpolate'`` only: the modelled skin's distance from the mesh (default
        :func:`mesh_band`; see :func:`transfer_operator`).
    warp : bool, default True
        Move the skin points by the mapped displacement (the predicted dense skin).
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.DataSet
        Copy of ``skin`` with point array ``arrays.DISPLACEMENT`` (float64 (n, 3), mm),
        and ``arrays.TRANSFER_INSIDE`` (``'interpolate'``: 1 inside a tetrahedron) and
        ``arrays.SKIN_MODELLED`` (``'interpolate'``: 1 within ``band`` of the mesh) or
        ``SUPPORT`` (``'gaussian'``); points moved when ``warp``.

    Raises
    ------
    ValueError
        Missing ``displacement``, empty inputs, an unknown ``method``, ``sigma`` /
        ``radius`` not positive, or a skin of which no point lies near the grid.

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
            mapping = Transfer(grid, skin.points, k=k, band=band)
            disp = mapping(u)
            bar.step(f"{skin.n_points} skin points")
        out.point_data[arrays.TRANSFER_INSIDE] = mapping.inside.astype(np.uint8)
        out.point_data[arrays.SKIN_MODELLED] = mapping.modelled.astype(np.uint8)
        reached = mapping.modelled
    else:
        disp = _gaussian(grid, skin, u, sigma, radius, progress_bar, out)
        reached = np.asarray(out.point_data[SUPPORT]) > 0
    if not reached.any():
        far = float(np.linalg.norm(np.asarray(skin.center) - np.asarray(grid.center)))
        raise ValueError(
            f"skin: none of its {skin.n_points} points lies near the grid (centres {far:.0f} "
            f"mm apart; method={method!r}): are the skin and the grid in the same frame?")
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
    a, b = np.minimum(e[:, 0], e[:, 1]).astype(np.int64), np.maximum(e[:, 0], e[:, 1])
    n = int(b.max(initial=-1)) + 1  # one int64 key per edge: a flat sort, not a row sort
    key = np.unique(a * n + b)
    return np.column_stack([key // n, key % n])


def crumple_metric(skin_pre, u_skin, grid, u_nodes, *, k=DEFAULT_K, band=None,
                   slack=0.1, floor=DEFAULT_FLOOR, transfer=None, modelled=None):
    """Check that a skin displacement stretches no skin edge beyond the mesh's gradients.

    Only the modelled skin is checked: edges whose two points lie inside the mesh or within
    ``band`` of it (skin farther away, e.g. behind a face model's posterior cut, is not
    predicted by the model). For every such edge ``(a, b)`` of ``skin_pre`` the stretch ``|u_a - u_b| / |x_a - x_b|`` is
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
    band : float, optional
        Modelled skin: within this distance (mm) of the mesh (as :func:`transfer_operator`;
        default :func:`mesh_band`).
    slack : float, default 0.1
        An edge violates the bound when its stretch exceeds ``(1 + slack)`` times it.
    floor : float, default 1e-4
        ... and exceeds ``floor`` (a stretch below it is no visible crumple: in a region
        that does not move, both the stretch and the bound are round-off).
    transfer : Transfer, optional
        The :class:`Transfer` of ``grid`` onto ``skin_pre``'s points, reused instead of
        locating the points again (its ``k`` and ``band`` apply).
    modelled : array_like of bool, optional
        The skin points the model predicts (default: within ``band`` of the mesh, the
        transfer's ``modelled``); only edges between two of them are checked.

    Returns
    -------
    dict
        ``ratio`` (per modelled edge: stretch / bound, 0 where both vanish or the stretch
        is at most ``floor``), ``edges``
        ((e, 2), the modelled edges), ``modelled`` (per point, bool), and the summary
        values under ``arrays.CRUMPLE_EDGES``, ``arrays.CRUMPLE_VIOLATIONS``
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
    if u_skin.shape != (skin_pre.n_points, 3):
        raise ValueError(f"u_skin must have shape ({skin_pre.n_points}, 3), got {u_skin.shape}")
    e, length, limit, modelled, gmax = _edge_limits(skin_pre, grid, u_nodes, k, band, transfer,
                                                   modelled)
    stretch = np.linalg.norm(u_skin[e[:, 0]] - u_skin[e[:, 1]], axis=1) / np.maximum(length, 1e-300)
    tiny = 1e-9 * max(gmax, 1e-12)
    ratio = np.where(limit > tiny, stretch / np.maximum(limit, tiny), np.where(stretch > tiny, np.inf, 0.0))
    ratio = np.where(stretch > floor, ratio, 0.0)
    return {"ratio": ratio, "edges": e, "modelled": modelled.copy(),
            arrays.SKIN_MODELLED_POINTS: int(modelled.sum()),
            arrays.CRUMPLE_EDGES: int(len(e)),
            arrays.CRUMPLE_VIOLATIONS: int(np.sum(ratio > 1.0 + slack)),
            arrays.CRUMPLE_MAX_RATIO: float(ratio.max(initial=0.0))}


def _edge_limits(skin_pre, grid, u_nodes, k, band, transfer, modelled):
    """The modelled edges of ``skin_pre``, their lengths and bounds (the steepest gradient
    of the tetrahedra around either end, see :func:`crumple_metric`), the modelled mask
    and the steepest gradient of the mesh."""
    u_nodes = np.asarray(u_nodes, dtype=float)
    if u_nodes.shape != (grid.n_points, 3):
        raise ValueError(f"u_nodes must have shape ({grid.n_points}, 3), got {u_nodes.shape}")
    if transfer is None:
        transfer = Transfer(grid, skin_pre.points, k=k, band=band)
    elif len(transfer.inside) != skin_pre.n_points:
        raise ValueError(f"transfer maps {len(transfer.inside)} points, skin_pre has "
                         f"{skin_pre.n_points}")
    loc = transfer._loc
    inv, _ = loc.gradients
    du = u_nodes[loc.tets[:, 1:]] - u_nodes[loc.tets[:, :1]]  # (m, 3 edges, 3 comps)
    grad = np.einsum("tca,tai->tic", inv, du)  # d u_i / d x_c
    gnorm = np.linalg.norm(grad, ord=2, axis=(1, 2))
    node_max = np.zeros(len(loc.points))
    np.maximum.at(node_max, loc.tets.ravel(), np.repeat(gnorm, 4))
    bound = np.zeros(len(loc.p))
    ins = np.flatnonzero(loc.inside)
    bound[ins] = node_max[loc.tets[loc.cell[ins]]].max(axis=1)
    if len(loc.pair_row):
        np.maximum.at(bound, loc.pair_row, node_max[loc.face].max(axis=1))
        np.maximum.at(bound, loc.outside, node_max[loc.boundary[loc.near]].max(axis=1))
    if modelled is None:
        modelled = transfer.modelled
    modelled = np.asarray(modelled, dtype=bool)
    if modelled.shape != (skin_pre.n_points,):
        raise ValueError(f"modelled must be a mask of shape ({skin_pre.n_points},), got "
                         f"{modelled.shape}")
    e = _edges(skin_pre)
    e = e[modelled[e].all(axis=1)]
    x = np.asarray(skin_pre.points, dtype=float)
    length = np.linalg.norm(x[e[:, 0]] - x[e[:, 1]], axis=1)
    limit = np.maximum(bound[e[:, 0]], bound[e[:, 1]])
    return e, length, limit, modelled, float(gnorm.max(initial=0.0))

