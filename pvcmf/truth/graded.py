"""A graded surface-conforming mesh of the virtual patient's soft tissue: fine where the
plan moves the face, the conforming mesh's size elsewhere.

:func:`pvcmf.truth.conform.conforming_mesh` samples the exact soft-tissue surface on one
regular grid, so its triangles (and the tetrahedra gmsh grows from them) have one size
everywhere. Remeshing that surface with a size field (gmsh reparametrisation) meshes the
two sides of a thin tissue shell independently, and where the shell is thinner than the
elements the two meshes cross. Here the surface is still one flying-edges contour (two
sides of a thin shell cannot cross), sampled on a grid that is regular in a *mapped*
space: the radial map

    ``x = c + rho(|xi - c|) (xi - c) / |xi - c|``,   ``rho'(r) = h(rho(r)) / h_face``,

(a diffeomorphism) takes a regular grid of spacing ``h_face`` to a grid that is
``h_face`` fine within the ball of centre ``c`` and radius ``R`` and grows by
:data:`GRADING` mm per mm beyond it, up to the conforming mesh's spacing ``h_base`` at the
count asked (so the rest of the head, the thin tissue over the skull vault included, is
meshed at least as finely as by the conforming mesh of that count: along the sphere the
grid is finer than along the radius). ``c`` and ``R`` come from the plan: the centroid of
the moved bone segments and the largest distance of their voxels from it, so the ball
holds all the moved bone and the tissue next to it (lips, chin, and for a moved maxilla
the nose). The tissue a bone move carries reaches farther than that ball where the moved
segment is compact: around a moved maxilla most of the skin 10-30 mm from the bone (the
upper cheeks) lies outside it, around a mandible almost none. ``face_margin_mm`` grows
the ball to hold every soft-tissue voxel within that distance of a moved bone voxel.
gmsh fills the contour with tetrahedra (sizes from the surface
inwards), the boundary nodes are projected onto the exact surfaces and labelled as in
:mod:`pvcmf.truth.conform`.

Delegates to VTK (flying edges), gmsh (volume mesh), :mod:`pvcmf.truth.conform` and numpy.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from .. import arrays
from ..filters.model_region import face_box
from ..filters.osteotomy import cut_bones, segment_transforms, voxel_points
from .anatomy import _warp
from .conform import _soft_points, _to_exact, _volume_mesh, surface_spacing
from .exact import _fields, _labelled_grid, _region, _volumes

log = logging.getLogger("pvcmf.reference")

__all__ = ["face_ball", "face_size", "face_size_text", "graded_mesh", "radial_map"]

#: growth (mm of element size per mm of distance) of the size beyond the refined ball
GRADING = 0.25


def face_size(face_mm, plan=None):
    """The face size (mm) of a graded truth for ``plan``: ``face_mm`` itself, or, for a
    mapping ``{segment: mm}`` (a size per moved segment: a truth converges at a coarser
    face where the mandible moves than where the maxilla does, ``truth_refinement.md``),
    the smallest size of the segments the plan moves.

    Examples
    --------
    >>> from pvcmf.plan import TABLE_II
    >>> from pvcmf.truth.graded import face_size
    >>> face_size(4.0), face_size({"maxilla": 3.2, "mandible": 4.0}, TABLE_II[3])
    (4.0, 4.0)
    """
    if not isinstance(face_mm, dict):
        return float(check_face_size(face_mm))
    sizes = check_face_size(face_mm)
    moved = sorted({o.segment for o in getattr(plan, "osteotomies", ())})
    missing = [s for s in moved if s not in sizes]
    if not moved or missing:
        raise ValueError(f"face_mm must give a size for every segment the plan moves "
                         f"({moved}), got {face_mm!r}")
    return min(sizes[s] for s in moved)


def check_face_size(face_mm):
    """``face_mm`` checked: a size > 0 mm, or a non-empty mapping of movable segments
    (:data:`pvcmf.plan.MOVABLE_SEGMENTS`) to sizes > 0 mm (returned as floats, sorted)."""
    from ..plan import MOVABLE_SEGMENTS

    def size(value):
        ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool) \
            and np.isfinite(value) and value > 0
        if not ok:
            raise ValueError(f"face_mm must be a size > 0 mm or a mapping of segments "
                             f"{list(MOVABLE_SEGMENTS)} to sizes > 0 mm, got {face_mm!r}")
        return float(value)

    if not isinstance(face_mm, dict):
        return size(face_mm)
    if not face_mm or any(k not in MOVABLE_SEGMENTS for k in face_mm):
        raise ValueError(f"face_mm must be a size > 0 mm or a mapping of segments "
                         f"{list(MOVABLE_SEGMENTS)} to sizes > 0 mm, got {face_mm!r}")
    return {k: size(face_mm[k]) for k in sorted(face_mm)}


def face_size_text(face_mm):
    """A face size, or one per moved segment, in words.

    Examples
    --------
    >>> from pvcmf.truth.graded import face_size_text
    >>> face_size_text(4.0), face_size_text({"mandible": 4, "maxilla": 3.2})
    ('4 mm', '3.2 mm where the maxilla moves, 4 mm where the mandible moves')
    """
    sizes = check_face_size(face_mm)
    if not isinstance(sizes, dict):
        return f"{sizes:g} mm"
    order = sorted(sizes, key=lambda k: (sizes[k], k))
    return ", ".join(f"{sizes[k]:g} mm where the {k} moves" for k in order)


def face_ball(case, margin_mm=0.0, soft=None):
    """Centre (3,) and radius (mm) of the ball holding the plan's moved bone segments:
    the centroid of their voxels and the largest distance of a voxel from it; with
    ``margin_mm`` > 0, grown to hold also the soft tissue within ``margin_mm`` of a moved
    bone voxel (``soft``: the soft-tissue points (n, 3) to consider; default every soft
    tissue voxel of ``case.truth``)."""
    _check_margin(margin_mm, "margin_mm")
    labels = cut_bones(case.truth, case.plan)
    moves = segment_transforms(labels, case.plan)
    moved = [s for s, m in moves.items() if not np.allclose(m, np.eye(4))]
    if not moved:
        raise ValueError("case.plan moves no bone segment: no face region to refine")
    bone = np.asarray(labels[arrays.BONE])
    ids = np.flatnonzero(np.isin(bone, moved))
    p = voxel_points(labels, ids)
    c = p.mean(axis=0)
    radius = float(np.linalg.norm(p - c, axis=1).max())
    if margin_mm > 0:
        if soft is None:
            tissue = np.asarray(case.truth[arrays.TISSUE])
            soft = voxel_points(case.truth, np.flatnonzero(np.isin(tissue, arrays.SOFT_LABELS)))
        soft = np.asarray(soft, dtype=float)
        near = cKDTree(p).query(soft, distance_upper_bound=margin_mm)[0] <= margin_mm
        if near.any():
            radius = max(radius, float(np.linalg.norm(soft[near] - c, axis=1).max()))
    return c, radius


def _check_margin(value, name):
    """Raise unless ``value`` is a finite distance >= 0 mm (``name``: the parameter)."""
    ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
    if not (ok and np.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be a non-negative distance in mm, got {value!r}")


def radial_map(centre, radius, h_face, h_base, grading=GRADING, extent=1000.0):
    """The radial map of the module doc as a function ``xi (n, 3) -> x (n, 3)`` and the
    local size ``h(rho)``: ``h_face`` within ``radius``, then growing by ``grading`` per
    mm up to ``h_base``.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.truth.graded import radial_map
    >>> phi, size = radial_map(np.zeros(3), 10.0, 2.0, 4.0)
    >>> np.round(phi(np.array([[5.0, 0, 0]])), 6).tolist()   # identity inside the ball
    [[5.0, 0.0, 0.0]]
    >>> float(size(100.0))
    4.0
    """
    if not 0 < h_face <= h_base:
        raise ValueError(f"need 0 < h_face <= h_base, got {h_face!r} and {h_base!r}")

    def size(rho):
        return np.minimum(h_base, h_face + grading * np.maximum(np.asarray(rho) - radius, 0))

    # rho(r) by integrating rho' = h(rho) / h_face on a fine table (explicit midpoint)
    dr = h_face / 20
    r = np.arange(0.0, extent + dr, dr)
    rho = np.empty_like(r)
    rho[0] = 0.0
    for i in range(1, len(r)):  # 1-D table (a few 10^4 steps), not a hot path over points
        k = size(rho[i - 1] + 0.5 * dr * size(rho[i - 1]) / h_face) / h_face
        rho[i] = rho[i - 1] + dr * k
    centre = np.asarray(centre, dtype=float)

    def phi(xi):
        d = np.asarray(xi, dtype=float) - centre
        n = np.linalg.norm(d, axis=1)
        scale = np.interp(n, r, rho) / np.maximum(n, np.finfo(float).tiny)
        return centre + d * np.where(n > 0, scale, 1.0)[:, None]

    phi.centre = centre
    return phi, size


def _graded_surface(warp, lo, hi, y0, phi, h_face):
    """Closed contour of the soft tissue's region function (closed by the plane ``y = y0``)
    sampled on the grid of spacing ``h_face`` in the mapped space of ``phi`` that covers the
    box ``lo``-``hi``; its points mapped back to the patient frame (the plane's points
    lie on it up to the linear interpolation of the contour in the mapped space)."""
    # the map moves every point away from the centre (rho(r) >= r), so the box's preimage
    # lies in the box when the centre does: the mapped grid spans the box
    a, b = np.minimum(lo, phi.centre) - h_face, np.maximum(hi, phi.centre) + h_face
    axes = [np.arange(a[i], b[i] + h_face, h_face) for i in range(3)]
    img = pv.ImageData(dimensions=[len(v) for v in axes], spacing=(h_face,) * 3, origin=a)
    p = phi(np.asarray(img.points))
    r = np.empty(len(p))
    for i in range(0, len(p), 250_000):  # chunks bound the memory of the level sets
        r[i:i + 250_000] = _region(_fields(warp, p[i:i + 250_000]))[0]
    outside = np.any((p < lo) | (p > hi), axis=1)
    r = np.where(outside, np.maximum(r, h_face), r)  # the box closes the domain
    r = np.maximum(r, y0 - p[:, 1])
    eps = 0.2 * h_face
    img["r"] = np.where(np.abs(r) < eps, np.where(r < 0, -eps, eps), r)
    surf = img.contour([0.0], scalars="r", method="flying_edges").connectivity("largest")
    return pv.PolyData(phi(np.asarray(surf.points)), faces=surf.faces)


def graded_mesh(case, *, n_tets=30_000, face_mm=3.0, face_fraction=0.5, face_margin_mm=0.0,
                progress_bar=False):
    """The patient's true soft tissue meshed conforming to its surfaces, ``face_mm`` fine
    in the ball of the moved bones (module doc).

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient with a plan that moves at least one bone segment.
    n_tets : int, default 30000
        Sets the size outside the ball: the surface spacing of
        :func:`pvcmf.truth.conform.conforming_mesh` at this count.
    face_mm : float, default 3.0
        Size (mm) of the surface sampling in the ball; at most the size outside it.
    face_fraction : float, default 0.5
        Anterior share of the head that is meshed.
    face_margin_mm : float, default 0.0
        The ball also holds the soft tissue within this distance (mm) of the moved bones
        (:func:`face_ball`): the tissue a small bone segment carries reaches beyond the
        ball of the segment itself.
    progress_bar : bool, default False
        Unused (a few vectorised passes); kept for the common signature.

    Returns
    -------
    pyvista.UnstructuredGrid
        As :func:`pvcmf.truth.conform.conforming_mesh`.
    """
    _check_margin(face_margin_mm, "face_margin_mm")
    warp = _warp(case)
    box = face_box(case.truth, face_fraction)
    pts, volume = _soft_points(case, box)
    h_base = surface_spacing(volume, n_tets)
    if not 0 < face_mm <= h_base:
        raise ValueError(f"face_mm must be in (0, {h_base:.2f}] (the size outside the "
                         f"face at n_tets={n_tets}), got {face_mm!r}")
    centre, radius = face_ball(case, face_margin_mm, pts)
    phi, _ = radial_map(centre, radius, face_mm, h_base)
    lo, hi = pts.min(axis=0) - h_base, pts.max(axis=0) + h_base
    lo[1] = box[2] - 0.5 * h_base
    x, tets, on = _volume_mesh(_graded_surface(warp, lo, hi, box[2], phi, face_mm))
    # the plane's nodes: where the plane is the active part of the region function, put
    # on it (each move undone where it would flatten an element, as the projection)
    plane = on[box[2] - x[on, 1] >= _region(_fields(warp, x[on]))[0]]
    y = x.copy()
    y[plane, 1] = box[2]
    bad = np.unique(tets[_volumes(y, tets) < 0.1 * _volumes(x, tets)])
    plane = np.setdiff1d(plane, bad)
    x[plane, 1] = box[2]
    free = np.setdiff1d(on, plane)
    x = _to_exact(warp, x, tets, free, h_base)
    grid = _labelled_grid(x, tets, free, plane, warp)
    log.info("graded truth mesh: %d tetrahedra, surface sampled at %.2f mm within %.0f mm "
             "of the moved bones' centre, %.2f mm beyond, %d boundary nodes", grid.n_cells,
             face_mm, radius, h_base, len(on))
    return grid
