"""Fit a tetrahedral mesh's outer skin around a dense skin surface.

A mesh of the soft tissue follows the skin at the resolution of its working grid; the
dense skin a prediction is drawn on (:func:`pvcmf.filters.extract_skin` of the label
image, sub-voxel) lies partly outside it, by up to a few millimetres in concave places
(the lip slit, a pocket of air beside the mouth). The mesh -> skin transfer
(:mod:`pvcmf.filters.surface_mapping`) has to extend the field outside the mesh there;
inside, it is the finite-element interpolation itself. :func:`fit_to_skin` moves the
mesh's skin nodes outward until the mesh contains the dense skin, so that (almost) every
skin point interpolates inside a tetrahedron:

1. the skin nodes: the boundary nodes, less those on the bone interface (a voxel of
   hard tissue or of the intracranial volume within a voxel spacing, the contact rule of
   :func:`pvcmf.filters.apply_plan`, in the label image; or, for a
   grid with boundary conditions, every node that is not free), those on the planes of
   the region of interest's ``box`` that cut the head and those listed in ``fixed``;
2. the dense skin points outside the mesh within ``reach`` are located
   (:class:`pvcmf.filters.transfer_locate.Located`): each asks the nodes of its closest
   boundary triangle for a push of its distance plus ``margin`` along their outward
   normals (the largest request per node); given the skin's normals, only where the
   skin faces the way the triangle does;
3. the push is spread over the skin by a few rounds of ``s <- max(s_0, mean of the
   neighbours)`` (a bump instead of a spike) and carried into the interior by a
   harmonic extension (graph Laplacian of the mesh edges, the boundary prescribed: the
   push on the skin nodes, zero on every other boundary node; one sparse solve,
   :func:`scipy.sparse.linalg.splu`);
4. no element may invert or lose more than half its radius ratio (below
   ``min_quality``): the push of the nodes of such an element is halved until none does
   (after ``MAX_HALVINGS`` they keep no push, with a warning); no node moves more than
   ``reach`` in all;
5. steps 2-4 repeat (``iterations``) on the moved mesh; the points still outside are
   counted. Skin over a part of the head the mesh lacks (thin tissue the mesher lost,
   leaving a crater or a crack down to the bone) cannot be reached by moving skin nodes
   and stays outside; where the fit narrows such a gap, points in it end inside the
   mesh, which the transfer needs.

:func:`dense_skin` gives the dense skin within a box (the model's face box):
:func:`pvcmf.filters.extract_skin` of the whole label image (so that the skin in the box
is the same as the whole head's), less the triangles with a corner outside the box.
:func:`on_hard_tissue` tells the skin points on bare teeth or bone (an open mouth), which
the soft tissue model neither holds nor predicts.

Delegates the geometry to :mod:`pvcmf.filters.transfer_locate`, the element quality to
:func:`pvcmf.filters.meshing.tet_quality`, the outward boundary faces to
:mod:`pvcmf.filters.skin` (``vtkDataSetSurfaceFilter``) and the solves to :mod:`scipy.sparse`.
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import pyvista as pv
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ... import arrays
from ...progress import Progress
from ..skin import _boundary_faces, extract_skin
from ..transfer_locate import Located, tetra
from .quality import tet_quality

log = logging.getLogger(__name__)

__all__ = ["fit_to_skin", "dense_skin", "on_hard_tissue", "DEFAULT_MARGIN", "DEFAULT_REACH"]

#: default depth (mm) at which a dense skin point ends inside the fitted mesh
DEFAULT_MARGIN = 0.1
#: default distance (mm) from the mesh within which dense skin points are fitted (the
#: transfer's band: farther skin is not modelled)
DEFAULT_REACH = 4.0
#: default rounds of spreading of the push over the skin (about one node ring each)
DEFAULT_SPREAD = 3
#: default rounds of locate -> push -> extend
DEFAULT_ITERATIONS = 4
#: an element whose radius ratio falls below this and below half its value before the
#: fit counts as degraded (as an inverted one)
DEFAULT_MIN_QUALITY = 0.05
#: halvings of a push that inverts or degrades an element before it is dropped
MAX_HALVINGS = 6
#: rings of nodes around such an element whose push is halved with its own
LIMIT_RINGS = 0


def fit_to_skin(grid, skin, *, labels=None, box=None, fixed=None, box_tolerance=None,
                margin=DEFAULT_MARGIN,
                reach=DEFAULT_REACH, spread=DEFAULT_SPREAD, iterations=DEFAULT_ITERATIONS,
                min_quality=DEFAULT_MIN_QUALITY, progress_bar=False):
    """Move a tetrahedral mesh's skin nodes outward so that it contains a dense skin.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        All-tetrahedral soft-tissue mesh (mm), e.g. from
        :func:`pvcmf.filters.tetrahedralize`.
    skin : pyvista.DataSet or array_like
        The dense skin (its points, ``(n, 3)``), in the grid's frame. With outward unit
        point normals (``arrays.NORMALS``, as :func:`pvcmf.filters.extract_skin` and
        :func:`dense_skin` give them) only the points whose normal agrees with the outward
        normal of their closest boundary triangle (cosine 0.5 or more) push: the skin
        over a crack of the mesh (tissue the mesher lost) does not push the crack's walls.
    labels : pyvista.ImageData, optional
        The label image the mesh was made from (point array ``tissue``): a boundary node
        within the largest voxel spacing of the centre of a voxel of neither soft tissue
        nor air (bone, teeth, metal, the intracranial volume) is on the bone interface
        and stays.
        Without it, a grid with a ``bc`` array keeps its nodes that are not free.
    box : tuple of 6 floats, optional
        The region of interest the mesh was cut to (``roi`` of
        :func:`~pvcmf.filters.tetrahedralize`): nodes within ``box_tolerance`` of a plane
        that cuts the head (the fixed posterior plane, the plane under the chin: with
        ``labels``, tissue lies beyond it) stay.
    fixed : array_like of bool or int, optional
        Further nodes that must not move (a mask over the grid's points, or indices).
    box_tolerance : float, optional
        Default: the largest voxel spacing of ``labels`` (1 mm without).
    margin : float, default 0.1
        Depth (mm) inside the mesh at which a pushed-out skin point ends.
    reach : float, default 4.0
        Only dense skin points within this distance (mm) of the mesh are fitted.
    spread : int, default 3
        Rounds of spreading of the push over the skin surface (0: none).
    iterations : int, default 4
        Rounds of locate -> push -> extend.
    min_quality : float, default 0.05
        An element whose radius ratio drops below this and below half its value before the
        fit is degraded: the push around it is reduced (as for an inverted element).
    progress_bar : bool, default False
        Show the rounds (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        A copy of ``grid`` with moved points, the point array ``arrays.SKIN_FIT_PUSH``
        (float64 (n, 3), mm: how far each node moved) and the field data
        ``arrays.SKIN_FIT_FIELDS`` (largest push, nodes moved, dense skin points outside the
        mesh within ``reach`` before and after, seconds).

    Raises
    ------
    TypeError, ValueError
        ``grid`` not all-tetrahedral, ``skin`` without points, a bad option (the message
        names it).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.meshing import fit_to_skin
    >>> grid = pv.ImageData(dimensions=(6, 6, 6), origin=(-2.5,) * 3).triangulate()
    >>> skin = pv.Sphere(radius=2.8, theta_resolution=12, phi_resolution=12)
    >>> fitted = fit_to_skin(grid, skin)
    >>> int(fitted.field_data[arrays.SKIN_FIT_OUTSIDE_AFTER][0])
    0
    """
    start = time.perf_counter()
    pts, tets = tetra(grid)
    skin_pts = _check(skin, margin, reach, spread, iterations, min_quality)
    skin_normals = None
    if isinstance(skin, pv.DataSet) and arrays.NORMALS in skin.point_data:
        skin_normals = np.asarray(skin.point_data[arrays.NORMALS], dtype=float)
        if skin_normals.shape != skin_pts.shape:
            raise ValueError(f"skin's point array {arrays.NORMALS!r} must have shape "
                             f"{skin_pts.shape}, got {skin_normals.shape}")
    movable, tri, normals_of, pinned = _skin_nodes(grid, pts, tets, labels, fixed, box,
                                                   box_tolerance)
    graph = _edge_graph(tets, len(pts))
    pinned[tri.ravel()] = True  # the extension's prescribed nodes: boundary and fixed
    extend = _Extension(graph, pinned)
    _, vol0, q0 = tet_quality(pts, tets)
    sign = np.where(vol0 < 0, -1.0, 1.0)
    floor = np.minimum(min_quality, 0.5 * q0)
    current = pts.copy()
    pushed = np.zeros(len(pts))
    before = after = 0
    with Progress(total=iterations + 1, desc="fit_to_skin", enabled=progress_bar,
                  logger=log) as bar:
        cand = np.arange(len(skin_pts))
        for it in range(iterations):
            need, outside = _demand(current, tets, skin_pts, cand, movable, reach, margin,
                                    skin_normals)
            if it == 0:
                before = len(outside)
            cand = outside
            if not need.any():
                bar.step(f"round {it + 1}: no point outside")
                break
            push = np.minimum(_spread(need, graph, movable, spread),
                              np.maximum(reach - pushed, 0.0))  # at most reach in all
            pushed += push
            step = push[:, None] * normals_of(current)
            move = _limit(current, tets, step, graph, extend, sign, floor)
            current = current + move
            bar.step(f"round {it + 1}: {len(outside)} points outside, push up to "
                     f"{push.max():.2f} mm")
        loc = Located(pv.UnstructuredGrid({pv.CellType.TETRA: tets}, current), skin_pts, 1,
                      n_triangles=8, reach=reach)
        after = int(np.sum(~loc.inside & (loc.dist <= reach)))
        bar.step(f"{after} points outside after the fit")
    disp = current - pts
    norm = np.linalg.norm(disp, axis=1)
    out = grid.copy()
    out.points = current
    out.point_data[arrays.SKIN_FIT_PUSH] = disp
    seconds = time.perf_counter() - start
    values = {arrays.SKIN_FIT_MAX_PUSH: float(norm.max(initial=0.0)),
              arrays.SKIN_FIT_NODES: int(np.sum(norm > 0)),
              arrays.SKIN_FIT_OUTSIDE_BEFORE: int(before),
              arrays.SKIN_FIT_OUTSIDE_AFTER: after, arrays.SKIN_FIT_SECONDS: seconds}
    for name, value in values.items():
        out.field_data[name] = np.array([value])
    log.info("fit_to_skin: %d nodes moved (up to %.2f mm), dense skin points outside the mesh "
             "within %.3g mm: %d before, %d after (%.1f s)", values[arrays.SKIN_FIT_NODES],
             values[arrays.SKIN_FIT_MAX_PUSH], reach, before, after, seconds)
    return out


def dense_skin(labels, box=None, grow=0.0):
    """The dense skin (:func:`pvcmf.filters.extract_skin` of the label image), within
    ``box`` when one is given.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image (point array ``tissue``).
    box : tuple of 6 floats, optional
        (xmin, xmax, ymin, ymax, zmin, zmax), e.g. the model's face box
        (:func:`pvcmf.filters.model_region.face_box`).
    grow : float, default 0.0
        Keep the skin within this distance (mm) beyond the box as well (e.g. the reach of
        the mesh -> skin transfer, so that the skin does not end on the model's cut).

    Returns
    -------
    pyvista.PolyData
        Triangle surface with its outward unit point normals (``arrays.NORMALS``) only.

    The whole image is contoured (the skin in the box is the whole head's, enclosed
    cavities filled) and the triangles with a corner outside the box are dropped: the skin
    the model covers, without the shoulders below it or the back of the head.
    """
    skin = extract_skin(labels)
    if box is not None:
        b = np.asarray(box, dtype=float)
        skin = _clip_to_box(skin, b + float(grow) * np.tile([-1.0, 1.0], 3))
    normals = skin.point_data.get(arrays.NORMALS)
    skin = skin.copy()
    skin.clear_data()
    if normals is not None:
        skin.point_data[arrays.NORMALS] = np.asarray(normals, dtype=float)
    return skin


def _clip_to_box(skin, box):
    """The triangles of ``skin`` whose three corners lie in ``box``."""
    p = np.asarray(skin.points)
    b = np.asarray(box, dtype=float)
    inside = ((p >= b[0::2]) & (p <= b[1::2])).all(axis=1)
    tri = skin.faces.reshape(-1, 4)[:, 1:]
    tri = tri[inside[tri].all(axis=1)]
    if not len(tri):
        raise ValueError(f"the skin has no triangle within the model's box {tuple(b)}")
    ids, local = np.unique(tri, return_inverse=True)
    faces = np.column_stack([np.full(len(tri), 3), local.reshape(-1, 3)]).ravel()
    out = pv.PolyData(p[ids], faces)
    if arrays.NORMALS in skin.point_data:
        out.point_data[arrays.NORMALS] = np.asarray(skin.point_data[arrays.NORMALS])[ids]
    return out


def on_hard_tissue(points, labels):
    """Skin points on bare hard tissue (teeth or bone that air touches, e.g. in an open
    mouth): hard tissue and no soft tissue among the 27 image points around them. The soft
    tissue model does not predict them."""
    dims = np.asarray(labels.dimensions)
    tissue = np.asarray(labels[arrays.TISSUE])
    ijk = np.rint((np.asarray(points) - np.asarray(labels.origin)) / np.asarray(labels.spacing))
    ijk = ijk.astype(np.int64)
    hard = np.zeros(len(ijk), dtype=bool)
    soft = np.zeros(len(ijk), dtype=bool)
    for off in np.ndindex(3, 3, 3):
        q = ijk + np.asarray(off) - 1
        ok = np.flatnonzero(((q >= 0) & (q < dims)).all(axis=1))
        t = tissue[q[ok, 0] + dims[0] * (q[ok, 1] + dims[1] * q[ok, 2])]
        hard[ok[np.isin(t, arrays.HARD_LABELS)]] = True
        soft[ok[np.isin(t, arrays.SOFT_LABELS)]] = True
    return hard & ~soft


def _check(skin, margin, reach, spread, iterations, min_quality):
    pts = np.asarray(skin.points if isinstance(skin, pv.DataSet) else skin, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts):
        raise ValueError(f"skin must have points, shape (n, 3) with n > 0, got {pts.shape}")
    if not np.isfinite(pts).all():
        raise ValueError("skin has non-finite point coordinates")
    for name, value in (("margin", margin), ("reach", reach)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)) \
                or not np.isfinite(value) or value < 0 or (name == "reach" and value == 0):
            raise ValueError(f"{name} must be a finite number {'> 0' if name == 'reach' else '>= 0'}"
                             f" (mm), got {value!r}")
    for name, value, low in (("spread", spread, 0), ("iterations", iterations, 1)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if not (isinstance(min_quality, (int, float, np.number)) and 0 <= min_quality < 1):
        raise ValueError(f"min_quality must be a number in [0, 1), got {min_quality!r}")
    return pts


def _skin_nodes(grid, pts, tets, labels, fixed, box, box_tolerance):
    """The movable skin nodes (bool mask), the boundary triangles (outward), a function of
    the current points giving the unit outward normals of the boundary nodes, and the
    nodes that must not move (bool mask)."""
    tri = _boundary_faces(pv.UnstructuredGrid({pv.CellType.TETRA: tets}, pts))
    n = len(pts)
    movable = np.zeros(n, dtype=bool)
    movable[tri.ravel()] = True
    pinned = np.zeros(n, dtype=bool)
    if labels is not None:
        pinned |= movable & _touches_hard(pts, labels)
    elif arrays.BC in grid.point_data:
        bc = arrays.require_array(grid, arrays.BC, "point", dtype="iu", ncomp=1)
        pinned |= np.asarray(bc) != arrays.BC_FREE
    if box is not None:
        b = np.asarray(box, dtype=float)
        if b.shape != (6,) or np.any(b[1::2] <= b[0::2]):
            raise ValueError(f"box must be (xmin, xmax, ymin, ymax, zmin, zmax), got {box!r}")
        tol = box_tolerance
        if tol is None:
            tol = float(max(labels.spacing)) if labels is not None else 1.0
        pinned |= movable & _on_cut(pts, b, tol, labels)
    if fixed is not None:
        fixed = np.asarray(fixed)
        if fixed.dtype == bool:
            if fixed.shape != (n,):
                raise ValueError(f"fixed must be a mask of shape ({n},) or node indices, got "
                                 f"shape {fixed.shape}")
            pinned |= fixed
        elif fixed.dtype.kind in "iu" and fixed.ndim == 1:
            if fixed.size and (fixed.min() < 0 or fixed.max() >= n):
                raise ValueError(f"fixed indices must lie in [0, {n}), got {fixed.min()}.."
                                 f"{fixed.max()}")
            pinned[fixed] = True
        else:
            raise ValueError(f"fixed must be a boolean mask or integer indices, got dtype "
                             f"{fixed.dtype} shape {fixed.shape}")
    movable &= ~pinned

    def normals_of(points):
        a, b, c = (points[tri[:, i]] for i in range(3))
        fn = np.cross(b - a, c - a)  # area-weighted, outward (the faces are wound outward)
        acc = np.zeros((n, 3))
        for i in range(3):
            np.add.at(acc, tri[:, i], fn)
        length = np.linalg.norm(acc, axis=1, keepdims=True)
        return np.where(length > 0, acc / np.where(length > 0, length, 1.0), 0.0)

    return movable, tri, normals_of, pinned


def _on_cut(points, box, tol, labels):
    """Points within ``tol`` of a plane of ``box`` that cuts the head: with ``labels``, a
    plane beyond which (one and a half voxels, within the box's other extents) the image
    holds tissue; a plane at the edge of the head or of the field of view cuts nothing.
    Without ``labels``, every plane."""
    out = np.zeros(len(points), dtype=bool)
    for axis in range(3):
        for side, plane in ((-1.0, box[2 * axis]), (1.0, box[2 * axis + 1])):
            if labels is None or _cuts_tissue(labels, box, axis, plane + side * 1.5 * float(
                    labels.spacing[axis])):
                out |= np.abs(points[:, axis] - plane) <= tol
    return out


def _cuts_tissue(labels, box, axis, at):
    """Whether the image's slice ``axis = at`` holds tissue within the box's other
    extents (False outside the image)."""
    dims = np.asarray(labels.dimensions)
    origin, spacing = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    k = int(np.rint((at - origin[axis]) / spacing[axis]))
    if not 0 <= k < dims[axis]:
        return False
    index = []
    for a in range(3):
        if a == axis:
            index.append(slice(k, k + 1))
            continue
        lo = int(np.clip(np.ceil((box[2 * a] - origin[a]) / spacing[a]), 0, dims[a]))
        hi = int(np.clip(np.floor((box[2 * a + 1] - origin[a]) / spacing[a]) + 1, 0, dims[a]))
        index.append(slice(lo, hi))
    vol = np.asarray(labels[arrays.TISSUE]).reshape(tuple(dims[::-1]))  # (z, y, x)
    return bool(np.any(vol[tuple(index[::-1])] != arrays.AIR))


def _touches_hard(points, labels):
    """Points within one voxel spacing (the largest) of the centre of a voxel of neither
    soft tissue nor air (bone, teeth, metal, the intracranial volume): the bone interface,
    as :func:`pvcmf.filters.apply_plan` finds it with its default contact distance."""
    arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu", ncomp=1, producer="segment")
    dims = np.asarray(labels.dimensions)
    origin, spacing = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    contact = float(spacing.max()) * (1 + 1e-9)
    hard = ~np.isin(np.asarray(labels[arrays.TISSUE]), (arrays.AIR, *arrays.SOFT_LABELS))
    ijk = np.floor((points - origin) / spacing).astype(np.int64)
    reach = np.ceil(contact / spacing).astype(np.int64)
    out = np.zeros(len(points), dtype=bool)
    for off in np.ndindex(*(2 * reach + 2)):
        q = ijk + np.asarray(off) - reach
        ok = ((q >= 0) & (q < dims)).all(axis=1)
        ok[ok] &= np.linalg.norm(points[ok] - (origin + q[ok] * spacing), axis=1) <= contact
        flat = q[ok, 0] + dims[0] * (q[ok, 1] + dims[1] * q[ok, 2])
        out[np.flatnonzero(ok)[hard[flat]]] = True
    return out


def _edge_graph(tets, n):
    """Symmetric adjacency (csr, ones) of the mesh edges."""
    i = np.concatenate([tets[:, [0, 0, 0, 1, 1, 2]].ravel(), tets[:, [1, 2, 3, 2, 3, 3]].ravel()])
    j = np.concatenate([tets[:, [1, 2, 3, 2, 3, 3]].ravel(), tets[:, [0, 0, 0, 1, 1, 2]].ravel()])
    g = sp.csr_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    g.data[:] = 1.0
    return g


def _demand(points, tets, skin_pts, cand, movable, reach, margin, skin_normals=None,
            min_cos=0.5):
    """Push (mm, per node) that the dense skin points ``cand`` outside the mesh ask of the
    movable nodes of their closest boundary triangle, and those points. With the skin's
    normals, only a point whose normal and the triangle's outward normal agree (cosine of
    at least ``min_cos``) asks: the skin over a crack of the mesh faces the crack's walls
    sideways, and pushing the walls would only sharpen the crack."""
    need = np.zeros(len(points))
    if not len(cand):
        return need, cand
    loc = Located(pv.UnstructuredGrid({pv.CellType.TETRA: tets}, points), skin_pts[cand], 1,
                  n_triangles=8, reach=reach)
    outside = np.flatnonzero(~loc.inside & (loc.dist <= reach))
    if not len(loc.pair_row) or not len(outside):
        return need, cand[outside]
    gap = np.linalg.norm(loc.p[loc.pair_row] - loc.q, axis=1)
    order = np.lexsort((gap, loc.pair_row))  # per point, its closest foot first
    first = order[np.unique(loc.pair_row[order], return_index=True)[1]]
    first = first[loc.dist[loc.pair_row[first]] <= reach]
    face, bary = loc.face[first], loc.face_bary[first]
    rows = loc.pair_row[first]
    if skin_normals is not None:
        a, b, c = (points[face[:, i]] for i in range(3))
        fn = np.cross(b - a, c - a)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        keep = np.einsum("ij,ij->i", fn, skin_normals[cand[rows]]) >= min_cos
        face, bary, rows = face[keep], bary[keep], rows[keep]
    ask = loc.dist[rows] + margin
    can = movable[face]
    share = np.where(can, bary, 0.0).sum(axis=1)
    ask = ask / np.maximum(share, 0.5)  # a triangle with fixed corners: its free ones do more
    for c in range(3):
        sel = can[:, c]
        np.maximum.at(need, face[sel, c], ask[sel])
    return need, cand[outside]


def _spread(need, graph, movable, rounds):
    """``s <- max(need, mean of s over the node and its movable neighbours)``, ``rounds``
    times, on the movable nodes (a bump around each request; the requests are kept)."""
    sub = graph[movable][:, movable]
    s0 = need[movable]
    s = s0.copy()
    deg = np.asarray(sub.sum(axis=1)).ravel() + 1.0
    for _ in range(rounds):
        s = np.maximum(s0, (sub @ s + s) / deg)
    out = np.zeros_like(need)
    out[movable] = s
    return out


class _Extension:
    """Harmonic extension of a field given on the ``pinned`` nodes (the boundary and the
    fixed nodes) into the others: graph Laplacian of the mesh edges, factorised once
    (:func:`scipy.sparse.linalg.splu`)."""

    def __init__(self, graph, pinned):
        self.pinned, self.inner = pinned, ~pinned
        lap = sp.diags(np.asarray(graph.sum(axis=1)).ravel()) - graph
        self.coupling = lap[self.inner][:, pinned].tocsr()
        self.lu = splu(lap[self.inner][:, self.inner].tocsc()) if self.inner.any() else None

    def __call__(self, step):
        move = np.zeros_like(step)
        move[self.pinned] = step[self.pinned]
        if self.lu is not None:
            move[self.inner] = self.lu.solve(-(self.coupling @ move[self.pinned]))
        return move


def _limit(points, tets, step, graph, extend, sign, floor):
    """The harmonic extension of ``step``, with the push halved around every element it
    would invert or degrade (radius ratio below ``floor``), the extension solved again;
    after :data:`MAX_HALVINGS` halvings such nodes keep no push (at worst no node moves,
    which inverts nothing)."""
    scale = np.ones(len(points))
    dropped = 0
    while True:
        move = extend(step * scale[:, None])
        _, vol, q = tet_quality(points + move, tets)
        bad = (vol * sign <= 0) | (q < floor)
        if not bad.any():
            break
        near = np.zeros(len(points), dtype=bool)
        near[tets[bad].ravel()] = True
        for _ in range(LIMIT_RINGS):  # the nodes of the element and rings around them
            near |= (graph @ near.astype(float)) > 0
        near &= scale > 0
        if not near.any():  # only nodes that do not move are left: nothing to reduce
            break
        halved = scale[near] > 0.5 ** (MAX_HALVINGS - 0.5)
        scale[np.flatnonzero(near)[halved]] *= 0.5
        gone = np.flatnonzero(near)[~halved]
        scale[gone] = 0.0
        dropped += len(gone)
    if dropped:
        warnings.warn(f"fit_to_skin: {dropped} nodes keep their place: any push of theirs "
                      f"would invert or degrade an element (radius ratio below "
                      f"min_quality), and the dense skin may stay outside the mesh there",
                      UserWarning, stacklevel=3)
    return move
