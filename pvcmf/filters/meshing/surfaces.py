"""Conforming multi-label surfaces of the working grid, placed on the image interfaces.

VTK's SurfaceNets (PyVista's :meth:`pyvista.ImageDataFilters.contour_labels`, unsmoothed)
builds one set of triangles per interface between two regions, shared by both. Coincident
sheet vertices are merged and every vertex is snapped onto the full-resolution image
interface of its two regions (the mean of the nearest voxel faces between them that face
the same way, ``scipy.spatial.cKDTree``; moves clipped to ``0.75 s``, folded triangles
pulled back, vertices relaxed along the surface), so the surfaces follow the image rather
than the working grid. The surface is then lightly smoothed with VTK's
``vtkConstrainedSmoothingFilter``: SurfaceNets' own smoothing pulls coincident sheets
through each other. Before volume meshing every region's boundary is checked to be
closed and the triangles are split into patches (``scipy.sparse.csgraph``).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import spatial
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from vtkmodules.vtkFiltersCore import vtkConstrainedSmoothingFilter

from ... import arrays
from .grid import _FAT, _MUSCLE0, SurfaceError, _code_name
from .subvoxel import project_onto_indicators

log = logging.getLogger(__name__)

_FINE_TARGETS = True
#: how far (in working spacings, per axis) a vertex may move from its cell centre
_TARGET_REACH = 0.75
#: a vertex goes to the mean of this many nearest same-facing fine interface faces,
#: chosen among this many candidates
_SNAP_NEIGHBOURS = 8
_SNAP_CANDIDATES = 24
_SNAP_PASSES = 1
#: tangential relaxation of the placed surface (steps, relaxation factor)
_TANGENTIAL_ITERATIONS = 3
_TANGENTIAL_RELAXATION = 0.5
#: a placed triangle whose normal turned by more than arccos(this) is a fold
_FOLD_COS = 0.3
_FOLD_ITERATIONS = 8
#: also place the sheets of the named muscles on the image interfaces
_PLACE_NAMED_MUSCLES = True


def _surfaces(comp, origin, s, smoothing_scale, comp_code=None, fine=None, reach=_TARGET_REACH,
              indicators=None):
    """Multi-label SurfaceNets surfaces: (points, triangles, side labels (n, 2)).

    SurfaceNets runs unsmoothed: where three regions meet in one cell without sharing a
    face (a muscle touching the skin diagonally), it makes one vertex per sheet at the
    same place, and its own smoothing then pulls the sheets through each other. Here the
    coincident vertices are merged first; with ``fine`` (the full-resolution code volume)
    every vertex is moved to the mean of the full-resolution interfaces between its
    regions inside its SurfaceNets cell (:func:`_fine_targets`), so the surfaces follow
    the image, not the working grid; the surface is then smoothed with VTK's
    ``vtkConstrainedSmoothingFilter`` (every vertex stays within
    ``smoothing_scale * s * sqrt(3) / 2`` of that position). With ``indicators``
    (:class:`~pvcmf.filters.meshing.subvoxel.MuscleIndicators`) and ``reach > 0``, the
    named muscles' sheets are then moved onto their sub-voxel interfaces
    (:func:`_subvoxel`).
    """
    img = pv.ImageData(dimensions=comp.shape[::-1], spacing=(s, s, s), origin=origin)
    img.point_data[arrays.MESH_COMPONENT] = comp.ravel()
    surf = img.contour_labels(
        "all", smoothing=False, output_mesh_type="triangles", pad_background=True
    )
    sides = np.asarray(surf.cell_data["boundary_labels"]).astype(np.int64)
    keep = (sides >= 2).any(axis=1)  # at least one side is a meshed region
    grid_ijk = np.rint((np.asarray(surf.points, float) - origin) / (0.5 * s)).astype(np.int64)
    uniq, merged = np.unique(grid_ijk, axis=0, return_inverse=True)
    tri = merged.ravel()[surf.regular_faces]
    points = uniq * (0.5 * s) + origin
    if fine is not None and fine[3] is not None and reach > 0:
        points = _fine_targets(points, s, tri, comp_code[sides], fine, reach)
    if smoothing_scale > 0:
        poly = pv.PolyData.from_regular_faces(points, tri)
        f = vtkConstrainedSmoothingFilter()
        f.SetInputData(poly)
        f.SetConstraintDistance(smoothing_scale * s * np.sqrt(3.0) / 2.0)
        f.SetNumberOfIterations(16)
        f.SetRelaxationFactor(0.5)
        f.Update()
        points = np.asarray(pv.wrap(f.GetOutput()).points, float)
    if indicators is not None and comp_code is not None and reach > 0:
        points = _subvoxel(points, tri, comp_code[sides], indicators)
    tri, sides = tri[keep], sides[keep]
    used, inverse = np.unique(tri, return_inverse=True)
    return points[used], inverse.reshape(-1, 3), sides


def _halve_folding_moves(points, move, tri, side_codes, n0):
    """``move`` (a copy) with the moves of the vertices of every triangle that turns by
    more than ~73 degrees from its unit normal ``n0`` halved, until none does (at most
    :data:`_FOLD_ITERATIONS` times)."""
    move = move.copy()
    for _ in range(_FOLD_ITERATIONS):
        n1 = _oriented_normals(points + move, tri, side_codes)
        cos = np.einsum("ij,ij->i", n0, n1) / np.maximum(np.linalg.norm(n1, axis=1), 1e-30)
        fold = cos < _FOLD_COS
        if not fold.any():
            break
        move[np.unique(tri[fold])] *= 0.5
    return move


def _subvoxel(points, tri, side_codes, indicators):
    """The muscle sheets' vertices on their smoothed indicators' half level
    (:func:`~pvcmf.filters.meshing.subvoxel.project_onto_indicators`), the moves of the
    vertices of a triangle that turned by more than ~73 degrees halved until none does."""
    target, n_moved = project_onto_indicators(points, tri, side_codes, indicators)
    move = target - points
    n0 = _oriented_normals(points, tri, side_codes)
    n0 /= np.maximum(np.linalg.norm(n0, axis=1), 1e-30)[:, None]
    move = _halve_folding_moves(points, move, tri, side_codes, n0)
    log.debug("tetrahedralize: %d muscle surface vertices on the sub-voxel interfaces", n_moved)
    return points + move


def _fine_faces(fine):
    """Midpoints (n, 3), code pairs ``lo * 256 + hi`` and normals of the fine interfaces.

    Only interfaces with soft tissue on one side (the meshed surfaces) are returned. The
    normal of a voxel face is the unit axis vector pointing from its lower code to its
    higher code.
    """
    code, origin, sp = fine[:3]
    mids, pairs, normals = [], [], []
    for ax in range(3):  # array axes z, y, x
        lo_sl = tuple(slice(0, -1) if k == ax else slice(None) for k in range(3))
        hi_sl = tuple(slice(1, None) if k == ax else slice(None) for k in range(3))
        a, b = code[lo_sl], code[hi_sl]  # views
        hit = (a != b) & ((a >= _FAT) | (b >= _FAT))
        flat = np.flatnonzero(hit)
        iz, iy, ix = np.unravel_index(flat, hit.shape)
        xyz = np.stack([ix, iy, iz], axis=1).astype(float)
        xyz[:, 2 - ax] += 0.5
        mids.append(origin + xyz * sp)
        # the same faces as flat indices of the full volume: a at (iz, iy, ix), b one on
        idx_a = np.ravel_multi_index((iz, iy, ix), code.shape)
        ah = code.ravel()[idx_a]
        bh = code.ravel()[idx_a + code.strides[ax] // code.itemsize]
        lo, hi = np.minimum(ah, bh), np.maximum(ah, bh)
        pairs.append(lo.astype(np.int64) * 256 + hi)
        nrm = np.zeros((len(lo), 3), np.int8)
        nrm[:, 2 - ax] = np.where(ah < bh, 1, -1)
        normals.append(nrm)
    return np.concatenate(mids), np.concatenate(pairs), np.concatenate(normals)


def _oriented_normals(points, tri, side_codes):
    """Triangle normals (not normalised) pointing from the lower code to the higher one.

    VTK's SurfaceNets orients every triangle towards its second boundary label.
    """
    n = np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]])
    return n * np.where(side_codes[:, 1] > side_codes[:, 0], 1.0, -1.0)[:, None]


def _interface_points(query, qpair, qnormal, fine, cache):
    """Points of the image interface near ``query``: (targets (n, 3), found (n,) bool).

    For every query point, the mean of the :data:`_SNAP_NEIGHBOURS` nearest midpoints of
    full-resolution voxel faces between the code pair ``qpair`` (``lo * 256 + hi``, -1:
    none) that face the way of ``qnormal`` (pointing from the lower code to the higher
    one), among :data:`_SNAP_CANDIDATES` candidates: a local average of the voxel
    staircase, i.e. a point of the smooth interface. ``cache`` keeps one
    ``scipy.spatial.cKDTree`` per code pair between calls.
    """
    mids, pairs, fnorm = fine[3], fine[4], fine[5]
    if "order" not in cache:
        # the keys fit in 16 bits: numpy's stable sort is then a radix sort
        cache["order"] = np.argsort(pairs.astype(np.uint16), kind="stable")
        cache["sorted"] = pairs[cache["order"]]
    order, sorted_pairs = cache["order"], cache["sorted"]
    # the face midpoints lie on a lattice the vertices often share: equal distances would
    # leave the choice of the nearest faces to the KD-tree's build order
    tie_break = np.asarray(fine[2], float) * np.sqrt([2.0, 3.0, 5.0]) * 1e-3
    out = np.zeros((len(query), 3))
    found = np.zeros(len(query), bool)
    for p in np.unique(qpair):  # one KD-tree per code pair (a few dozen)
        if p < 0:
            continue
        if p not in cache:
            a, b = np.searchsorted(sorted_pairs, [p, p + 1])
            faces = order[a:b]
            tree = spatial.cKDTree(mids[faces], leafsize=32, balanced_tree=False, compact_nodes=False) if b > a else None
            cache[p] = (faces, tree)
        faces, tree = cache[p]
        if tree is None:
            continue
        sel = np.flatnonzero(qpair == p)
        k = min(_SNAP_CANDIDATES, len(faces))
        _, j = tree.query(query[sel] + tie_break, k=k)
        j = faces[np.asarray(j).reshape(len(sel), k)]
        same = np.einsum("vkc,vc->vk", fnorm[j].astype(float), qnormal[sel]) > 0
        same &= np.cumsum(same, axis=1) <= _SNAP_NEIGHBOURS
        cnt = same.sum(axis=1)
        ok = cnt > 0
        out[sel[ok]] = np.einsum("vk,vkc->vc", same[ok].astype(float), mids[j[ok]]) / cnt[ok, None]
        found[sel[ok]] = True
    return out, found


def _pair_keys(side_codes):
    lo = np.minimum(side_codes[:, 0], side_codes[:, 1])
    hi = np.maximum(side_codes[:, 0], side_codes[:, 1])
    tpair = lo * 256 + hi
    if not _PLACE_NAMED_MUSCLES:
        tpair = np.where(hi > _MUSCLE0, -1, tpair)
    return tpair


def _fine_targets(points, s, tri, side_codes, fine, reach=_TARGET_REACH, cache=None):
    """Move every surface vertex onto the full-resolution interfaces of its regions.

    A vertex of the sheet between the regions of codes ``a`` and ``b`` goes to the
    interface point :func:`_interface_points` finds for it (the mean of the nearest
    voxel faces between codes ``a`` and ``b`` that face the same way as the sheet;
    facing the same way keeps the two sheets of a thin muscle apart); a junction vertex
    goes to the mean of its sheets' targets. Every move is clipped to ``reach * s`` per
    axis; the vertices of a single sheet are then relaxed along the surface (tangential
    Laplacian, :data:`_TANGENTIAL_ITERATIONS` steps; the triangles get better shapes
    without leaving the interface) and the moves of the vertices of a triangle that
    turned by more than ~73 degrees are halved until none does (no folds). No loop over
    vertices.
    """
    cache = {} if cache is None else cache
    tpair = _pair_keys(side_codes)
    n_pts = len(points)
    tnorm = _oriented_normals(points, tri, side_codes)
    # (vertex, pair) incidences and the sheet normal at each
    n_keys = 256 * 256 + 1
    inc_key, inv = np.unique(tri.ravel() * n_keys + np.repeat(tpair, 3) + 1, return_inverse=True)
    inc = np.stack([inc_key // n_keys, inc_key % n_keys - 1], axis=1)
    inv = inv.ravel()
    inc_n = np.stack(
        [np.bincount(inv, weights=np.repeat(tnorm[:, k], 3), minlength=len(inc)) for k in range(3)], axis=1
    )
    move = np.zeros_like(points)
    has = np.zeros(n_pts, bool)
    for _ in range(_SNAP_PASSES):  # a further pass queries from the placed position
        target, ok = _interface_points(points[inc[:, 0]] + move[inc[:, 0]], inc[:, 1], inc_n, fine, cache)
        vcnt = np.bincount(inc[ok, 0], minlength=n_pts).astype(float)
        vsum = np.stack([np.bincount(inc[ok, 0], weights=target[ok, k], minlength=n_pts) for k in range(3)], axis=1)
        has = vcnt > 0
        move[has] = np.clip(vsum[has] / vcnt[has, None] - points[has], -reach * s, reach * s)
    if _TANGENTIAL_ITERATIONS:
        e = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        e = np.unique(e[:, 0] * n_pts + e[:, 1])
        edges = np.stack([e // n_pts, e % n_pts], axis=1)
        adj = coo_matrix(
            (np.ones(2 * len(edges)), (edges.ravel(), edges[:, ::-1].ravel())), shape=(n_pts, n_pts)
        ).tocsr()
        degree = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1.0)
        single = np.bincount(inc[:, 0], minlength=n_pts) == 1  # not on a junction line
        for _ in range(_TANGENTIAL_ITERATIONS):
            q = points + move
            tn = _oriented_normals(q, tri, side_codes)
            vn = np.stack([np.bincount(tri.ravel(), weights=np.repeat(tn[:, k], 3), minlength=n_pts) for k in range(3)], axis=1)
            vn /= np.maximum(np.linalg.norm(vn, axis=1), 1e-30)[:, None]
            lap = adj @ q / degree[:, None] - q
            lap -= np.einsum("ij,ij->i", lap, vn)[:, None] * vn
            move[single] += _TANGENTIAL_RELAXATION * lap[single]
    n0 = tnorm / np.maximum(np.linalg.norm(tnorm, axis=1), 1e-30)[:, None]
    move = _halve_folding_moves(points, move, tri, side_codes, n0)
    log.debug("tetrahedralize: %d of %d surface vertices placed on the fine interfaces", int(has.sum()), n_pts)
    return points + move


def _check_surfaces(tri, sides, comp_code):
    """Raise :class:`SurfaceError` unless every region's boundary is closed."""
    n_pts = int(tri.max()) + 1
    edges = np.sort(tri[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    rows = []
    for side in range(2):
        reg = np.repeat(sides[:, side], 3)
        ok = reg >= 2
        rows.append((reg[ok] * n_pts + edges[ok, 0]) * n_pts + edges[ok, 1])
    keys, counts = np.unique(np.concatenate(rows), return_counts=True)
    bad = counts % 2 == 1  # open; an even count > 2 is a pinch, which gmsh accepts
    if bad.any():
        regs = np.unique(keys[bad] // (n_pts * n_pts))
        names = sorted({_code_name(comp_code[r]) for r in regs})
        raise SurfaceError(
            f"{int(bad.sum())} surface edge(s) are open on the boundary of {', '.join(names)}"
        )
    n_pinch = int(np.count_nonzero(counts > 2))
    if n_pinch:
        log.debug("tetrahedralize: %d surface edge(s) where a region touches itself", n_pinch)


def _split_patches(tri, sides, n_pts):
    """Split the triangles into patches: one per (side pair, connected piece)."""
    pair_keys, pair_id = np.unique(sides, axis=0, return_inverse=True)
    pair_id = pair_id.ravel()
    # vertices are shared between patches of different pairs: connect per pair by
    # making (pair, vertex) graph nodes
    node = pair_id[:, None] * n_pts + tri
    e = np.concatenate([node[:, [0, 1]], node[:, [1, 2]]])
    uniq, inv = np.unique(e, return_inverse=True)
    inv = inv.reshape(-1, 2)
    graph = coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(len(uniq),) * 2)
    _, comp = connected_components(graph, directed=False)
    tri_comp = comp[inv[: len(tri), 0]]
    patch_ids, patch = np.unique(tri_comp, return_inverse=True)
    patch = patch.ravel()
    first = np.zeros(len(patch_ids), dtype=np.int64)
    first[patch[::-1]] = np.arange(len(patch))[::-1]
    return patch, sides[first]

