"""A head cut by the scan (flat, or along its round field of view): where, and which skin.

:func:`cut_planes` counts, per image plane, the head voxels whose outward neighbour is not
head (numpy counts along each axis, no loop over voxels) and reports a side whose plane
holds more of that exposed surface than the pole of a sphere of the head's volume could,
with the plane and the extent of the cut; :func:`clipped_sides` gives their messages.
:func:`pvcmf.filters.segment` warns with them and keeps the planes in the labels' field
data (``arrays.SCAN_CUTS``, :func:`cuts_array`); :func:`on_scan_cuts` marks the skin
points that lie on a cut (the skin there is the scan's edge, not the patient's), and
those behind a flat cut that look out through an opening in it (a sinus or a nostril the
cut opened), which :func:`pvcmf.filters.skin_prediction.predict_skin` writes as
``arrays.SKIN_CUT``.

A scanner reconstructs a round field of view and pads the corners of every slice with
one value, often that of its clipped air. :func:`fov_circles` finds that circle in every
axial slice from the image alone: the voxels at the image's minimum that a 3x3 opening
keeps (clipped-air speckle does not survive it) and that connect to the slice's border,
a circle fitted to the rim of that region (an algebraic least-squares fit, all slices at
once), kept where it fits within a voxel and most of its rim is air (a head outlined on
padding-valued air is all head). :func:`fov_cuts` keeps the slices whose circle cuts the
head (``arrays.SCAN_FOV``), which :func:`on_scan_cuts` marks as it marks the planes;
:func:`cut_points` reads a skin's marks back (figures, registration and statistics leave
those points out).
Index axis 2 is the axial axis; the patient frame (x left, y anterior, z superior) is
assumed for the side names. Delegates to numpy and ``scipy.ndimage`` (minimum and
maximum filters, labelling, hole filling).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .. import arrays

__all__ = ["clipped_sides", "cut_planes", "cut_points", "cuts_array", "fov_circles",
           "fov_cuts", "on_scan_cuts"]

#: a slice's padding region is a round field of view when the circle fitted to its rim
#: leaves at most this RMS residual (voxels) ...
CIRCLE_RMS = 1.0
#: ... and at least this share of the rim is air (not above the skin threshold)
CIRCLE_AIR_RIM = 0.5
#: the fewest rim voxels a slice's circle is fitted to
_MIN_RIM = 24
#: skin within this many voxels of a cut (a plane, the field of view's circle) is on it
REACH = 1.5
#: the head voxels within :data:`REACH` of a slice's circle count as a cut when their outer
#: faces cover this much (mm^2, a patch about a centimetre across): the scanner saw nothing
#: beyond its circle, so any head on it is cut there or may be
MIN_FOV_CUT = 100.0

_SIDES = {(0, 1): "left (+x)", (0, -1): "right (-x)", (1, 1): "anterior (+y, face)",
          (1, -1): "posterior (-y)", (2, 1): "superior (+z, vertex)"}


def clipped_sides(head, spacing, origin=(0.0, 0.0, 0.0), vol=None, pad_fraction=0.8):
    """Messages of :func:`cut_planes`: one per side where the head is cut flat.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.field_of_view import clipped_sides
    >>> head = np.zeros((40, 40, 40), bool)
    >>> head[5:35, 5:40, 5:35] = True          # cut at the +y border
    >>> [m.split(" at ")[0] for m in clipped_sides(head, (1.0, 1.0, 1.0))]
    ['the head is cut flat on the anterior (+y, face) side']
    """
    return [c["message"] for c in cut_planes(head, spacing, origin, vol, pad_fraction)]


def cut_planes(head, spacing, origin=(0.0, 0.0, 0.0), vol=None, pad_fraction=0.8):
    """Sides where the head is cut flat (by the field of view or the scan's end).

    On each side (not the inferior one: the neck always leaves the scan), the head voxels
    whose outward neighbour is not head are counted per plane. A side is cut when one plane
    holds more of this exposed surface than the pole of a sphere of the head's volume can
    (``2 pi R`` mm^2 per mm) and the plane is the image's end or, with ``vol``, at least
    ``pad_fraction`` of the voxels beyond it hold the image's minimum value (the padding
    outside the reconstructed field of view), which a skin flattened on a headrest does not.

    Returns
    -------
    list of dict
        One per cut side: ``axis`` (0-2), ``sign`` (+1: the cut faces +axis), ``at`` the
        plane's coordinate (mm, the centres of the last head voxels), ``lo`` and ``hi``
        the extent of the cut along the two other axes (mm, in axis order), ``edge``
        (True: the field of view's edge, False: the image's end) and ``message`` naming
        the side and the extent.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.field_of_view import cut_planes
    >>> head = np.zeros((40, 40, 40), bool)
    >>> head[5:35, 5:40, 5:35] = True          # cut at the +y border
    >>> c, = cut_planes(head, (1.0, 1.0, 1.0))
    >>> c["axis"], c["sign"], c["at"], c["lo"], c["hi"]
    (1, 1, 39.0, (5.0, 5.0), (34.0, 34.0))
    """
    out = []
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    radius = (3.0 * head.sum() * np.prod(spacing) / (4.0 * np.pi)) ** (1.0 / 3.0)
    floor = None if vol is None else float(vol.min()) + 1e-3 * float(np.ptp(vol))
    counts = {}  # per axis: head voxels per plane, and those whose next plane is head too
    for (axis, sign), name in _SIDES.items():
        other = tuple(a for a in range(3) if a != axis)
        if axis not in counts:
            lo, hi = [slice(None)] * 3, [slice(None)] * 3
            lo[axis], hi[axis] = slice(0, -1), slice(1, None)
            counts[axis] = (np.count_nonzero(head, axis=other),
                            np.count_nonzero(head[tuple(lo)] & head[tuple(hi)], axis=other))
        per_plane, both = counts[axis]
        exposed = per_plane.copy()  # head voxels whose outward neighbour is not head
        if sign > 0:
            exposed[:-1] -= both
        else:
            exposed[1:] -= both
            exposed = exposed[::-1]  # outward = increasing index
        area = exposed * float(np.prod(spacing[list(other)]))
        plane = int(np.argmax(area))
        if area[plane] < 2.0 * np.pi * radius * spacing[axis]:
            continue
        index = plane if sign > 0 else head.shape[axis] - 1 - plane
        face = np.take(head, index, axis=axis)
        if plane < len(area) - 1:  # the head voxels of the plane with no head beyond
            face = face & ~np.take(head, index + sign, axis=axis)
        if plane < len(area) - 1 and floor is not None:
            beyond = np.take(vol, index + sign, axis=axis)[face]
            if np.mean(beyond <= floor) < pad_fraction:
                continue
        elif plane < len(area) - 1:
            continue
        ij = np.nonzero(face)
        lo = tuple(float(origin[a] + spacing[a] * ij[k].min()) for k, a in enumerate(other))
        hi = tuple(float(origin[a] + spacing[a] * ij[k].max()) for k, a in enumerate(other))
        ext = ", ".join(f"{'xyz'[a]} {lo[k]:.0f} to {hi[k]:.0f} mm" for k, a in enumerate(other))
        where = "the image's end" if plane == len(area) - 1 else "the field of view's edge"
        at = float(origin[axis] + spacing[axis] * index)
        out.append({"axis": axis, "sign": sign, "at": at, "lo": lo, "hi": hi,
                    "edge": plane != len(area) - 1, "message":
                    f"the head is cut flat on the {name} side at {'xyz'[axis]} = {at:.0f} mm "
                    f"by {where} ({area[plane]:.0f} mm^2; {ext}): the skin there is not "
                    "the patient's"})
    return out


def _in_slice(connectivity):
    """A 3x3x3 structure that connects voxels within an axial slice only."""
    st = np.zeros((3, 3, 3), bool)
    st[:, :, 1] = ndimage.generate_binary_structure(2, connectivity)
    return st


def _padding_rim(vol):
    """Rim voxels (i, j, k) of each axial slice's padding region: the voxels at the image's
    minimum that survive a 3x3 in-slice opening and connect to the slice's border, and the
    voxels next to them that are not padding."""
    pad = (vol == vol.min()).view(np.uint8)
    # the 3x3 opening as separable minimum and maximum filters (several times faster than
    # a binary opening with the same square)
    pad = ndimage.maximum_filter(ndimage.minimum_filter(pad, size=(3, 3, 1)), size=(3, 3, 1))
    lab, n = ndimage.label(pad, structure=_in_slice(1))
    keep = np.zeros(n + 1, bool)
    keep[np.concatenate([lab[0].ravel(), lab[-1].ravel(), lab[:, 0].ravel(),
                         lab[:, -1].ravel()])] = True
    keep[0] = False
    outside = keep[lab]
    del lab
    near = np.zeros_like(outside)  # next to the outside region within the slice
    near[1:] |= outside[:-1]
    near[:-1] |= outside[1:]
    near[:, 1:] |= outside[:, :-1]
    near[:, :-1] |= outside[:, 1:]
    return np.nonzero(near & ~outside)


def fov_circles(vol, air_below, spacing=(1.0, 1.0, 1.0), max_rms=CIRCLE_RMS,
                min_air=CIRCLE_AIR_RIM):
    """The round field of view of every axial slice of a CT.

    Parameters
    ----------
    vol : numpy.ndarray, shape (nx, ny, nz)
        The CT's values, index axis 2 axial.
    air_below : float
        Values below this are air (the skin threshold).
    spacing : sequence of 3 floats
        Voxel size (mm).
    max_rms, min_air : float
        A slice's circle is kept where it fits its padding region's rim to ``max_rms``
        voxels (RMS) and at least ``min_air`` of the rim is air.

    Returns
    -------
    numpy.ndarray, shape (nz, 3)
        Centre (mm along index axes 0 and 1, from the image's first voxel) and radius (mm)
        per slice; NaN where the slice has no padding region, or one that is not a circle.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.field_of_view import fov_circles
    >>> i, j = np.mgrid[:64, :64]
    >>> inside = (i - 30.0) ** 2 + (j - 33.0) ** 2 <= 25.0 ** 2
    >>> noise = np.random.default_rng(0).normal(-1000.0, 20.0, (64, 64, 4))
    >>> vol = np.where(inside[:, :, None], np.maximum(noise, -1024.0), -1024.0)
    >>> np.round(fov_circles(vol, -400.0)[0]).tolist()
    [30.0, 33.0, 25.0]
    """
    vol = np.asarray(vol)
    nz = vol.shape[2]
    out = np.full((nz, 3), np.nan)
    i, j, k = _padding_rim(vol)
    if i.size == 0:
        return out
    air = vol[i, j, k] < air_below
    h = np.asarray(spacing, float)
    x0, y0 = 0.5 * h[0] * vol.shape[0], 0.5 * h[1] * vol.shape[1]
    x = h[0] * i - x0  # centred: a well-conditioned fit
    y = h[1] * j - y0
    s = x * x + y * y

    def total(w):
        return np.bincount(k, weights=w, minlength=nz)

    n = np.bincount(k, minlength=nz).astype(float)
    sx, sy, sxx, syy, sxy = total(x), total(y), total(x * x), total(y * y), total(x * y)
    m = np.stack([np.stack([4 * sxx, 4 * sxy, 2 * sx], -1), np.stack([4 * sxy, 4 * syy, 2 * sy], -1),
                  np.stack([2 * sx, 2 * sy, n], -1)], -2)  # normal equations of
    rhs = np.stack([2 * total(x * s), 2 * total(y * s), total(s)], -1)  # 2ax + 2by + c = s
    ok = n >= _MIN_RIM
    m[~ok] = np.eye(3)
    ok &= np.linalg.cond(m) < 1e12  # a straight rim (padding beyond a flat edge) is no circle
    m[~ok] = np.eye(3)
    abc = np.linalg.solve(m, rhs[..., None])[..., 0]
    r = np.sqrt(np.maximum(abc[:, 2] + abc[:, 0] ** 2 + abc[:, 1] ** 2, 0.0))
    res = np.hypot(x - abc[k, 0], y - abc[k, 1]) - r[k]
    rms = np.sqrt(total(res * res) / np.maximum(n, 1.0))
    ok &= (rms <= max_rms * min(h[0], h[1])) & (total(air.astype(float)) >= min_air * n)
    # the rim's centres lie half a voxel inside the boundary between rim and padding
    out[ok] = np.column_stack([abc[:, 0] + x0, abc[:, 1] + y0, r + 0.5 * np.sqrt(h[0] * h[1])])[ok]
    return out


def fov_cuts(circles, head, spacing, origin=(0.0, 0.0, 0.0), offset=(0, 0, 0)):
    """The slices whose field of view cuts the head, and the warning that says so.

    A slice's circle (:func:`fov_circles`) cuts the head where head voxels lie within
    :data:`REACH` voxels inside it; the cut counts when those voxels' outer faces cover
    :data:`MIN_FOV_CUT` mm^2 or more.

    Parameters
    ----------
    circles : numpy.ndarray, shape (nz, 3)
        :func:`fov_circles` of the whole image.
    head : numpy.ndarray of bool
        The head mask of a crop of that image starting at index ``offset``.
    spacing, origin : sequence of 3 floats
        The image's spacing and the origin of the crop (mm).

    Returns
    -------
    rows : numpy.ndarray, shape (m, 4)
        ``z, centre x, centre y, radius`` (mm) of every slice where the circle cuts the
        head (empty when it does not count).
    message : str or None
    """
    spacing, origin = np.asarray(spacing, float), np.asarray(origin, float)
    offset = np.asarray(offset, int)
    i, j, k = np.nonzero(head)
    if i.size == 0:
        return np.zeros((0, 4)), None
    c = circles[k + offset[2]]
    rho = np.hypot(spacing[0] * (i + offset[0]) - c[:, 0], spacing[1] * (j + offset[1]) - c[:, 1])
    near = np.isfinite(c[:, 2]) & (rho >= c[:, 2] - REACH * min(spacing[0], spacing[1]))
    if not near.any():
        return np.zeros((0, 4)), None
    area = near.sum() * float(np.sqrt(spacing[0] * spacing[1]) * spacing[2])
    if area < MIN_FOV_CUT:
        return np.zeros((0, 4)), None
    ks = np.unique(k[near])
    start = origin - spacing * offset  # the whole image's origin
    cc = circles[ks + offset[2]]
    rows = np.column_stack([origin[2] + spacing[2] * ks, start[0] + cc[:, 0],
                            start[1] + cc[:, 1], cc[:, 2]])
    radii = f"{rows[:, 3].min():.0f}" + (f" to {rows[:, 3].max():.0f}"
                                        if np.ptp(rows[:, 3]) >= 1 else "")
    message = (f"the head is cut by the round field of view (radius {radii} mm) from "
               f"z = {rows[0, 0]:.0f} to {rows[-1, 0]:.0f} mm ({area:.0f} mm^2): the skin "
               "there is not the patient's")
    return rows, message


def cuts_array(cuts):
    """:func:`cut_planes`'s planes as the flat float64 field array ``arrays.SCAN_CUTS``:
    per cut ``axis, sign, at, lo_1, hi_1, lo_2, hi_2, edge`` (the two other axes in
    order; edge 1 for the field of view's edge, 0 for the image's end)."""
    return np.array([[c["axis"], c["sign"], c["at"], c["lo"][0], c["hi"][0], c["lo"][1],
                      c["hi"][1], float(c["edge"])] for c in cuts],
                    dtype=np.float64).reshape(-1)


def on_scan_cuts(points, labels):
    """Which ``points`` (a skin) lie on a plane where the scan cut the head.

    A point is on a cut when it lies within one and a half voxels (:data:`REACH`) inside
    the cut's plane (or beyond it) and of the cut's extent, or within as much inside the
    round field of view of its axial slice where that circle cuts the head
    (``arrays.SCAN_FOV``, :func:`fov_cuts`): the skin there is the scan's edge, not the
    patient's (a face cut by the field of view, a vertex cut by the scan's end). With the
    labels' ``arrays.TISSUE``, skin behind a flat cut that looks out through an opening in
    it (a sinus or a nostril the cut opened) is marked too.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Points in the labels' frame (mm).
    labels : pyvista.ImageData
        Labels of :func:`pvcmf.filters.segment`; without ``arrays.SCAN_CUTS`` or
        ``arrays.SCAN_FOV`` in its field data nothing is on a cut.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` bool.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.field_of_view import cuts_array, on_scan_cuts
    >>> labels = pv.ImageData(dimensions=(10, 10, 10))
    >>> labels.field_data[arrays.SCAN_CUTS] = cuts_array(
    ...     [{"axis": 1, "sign": 1, "at": 9.0, "lo": (2.0, 2.0), "hi": (6.0, 6.0), "edge": False}])
    >>> on_scan_cuts([[4, 9, 4], [4, 7, 4], [9, 9, 4], [4, 8.2, 5]], labels).tolist()
    [True, False, False, True]
    """
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    on = np.zeros(len(p), dtype=bool)
    reach = REACH * np.asarray(labels.spacing, dtype=np.float64)  # mm
    if arrays.SCAN_FOV in labels.field_data:
        on |= _on_circles(p, np.asarray(labels.field_data[arrays.SCAN_FOV], np.float64),
                          labels.spacing, min(reach[0], reach[1]))
    if arrays.SCAN_CUTS not in labels.field_data:
        return on
    cuts = np.asarray(labels.field_data[arrays.SCAN_CUTS], dtype=np.float64).reshape(-1, 8)
    head = None  # the labels' head mask, made once for every cut
    if arrays.TISSUE in labels.point_data:
        head = (np.asarray(labels.point_data[arrays.TISSUE]) != arrays.AIR).reshape(
            labels.dimensions, order="F")
    for axis, sign, at, lo1, hi1, lo2, hi2, _ in cuts:
        a = int(axis)
        b, c = (k for k in range(3) if k != a)
        near = sign * (p[:, a] - at) >= -reach[a]
        within = ((p[:, b] >= lo1 - reach[b]) & (p[:, b] <= hi1 + reach[b])
                  & (p[:, c] >= lo2 - reach[c]) & (p[:, c] <= hi2 + reach[c]))
        on |= near & within
        if head is not None:
            on |= _seen_through(p, head, labels, a, sign, at)
    return on


def _seen_through(p, head, labels, axis, sign, at):
    """Points behind a flat cut that look out through an opening in it (a sinus or a
    nostril the cut opened): the ray from the point along the cut's outward normal meets
    no head voxel up to the plane and crosses it in a hole of the cut face (the head
    voxels of the plane's slice, holes filled: ``scipy.ndimage.binary_fill_holes``);
    ``head``: the labels' non-air voxels, index order x, y, z."""
    sign = int(sign)
    origin, h = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    n = head.shape[axis]
    plane = int(np.clip(np.rint((at - origin[axis]) / h[axis]), 0, n - 1))
    face = np.take(head, plane, axis=axis)
    hole = ndimage.binary_fill_holes(face) & ~face
    out = np.zeros(len(p), dtype=bool)
    ijk = np.rint((p - origin) / h).astype(np.int64)
    other = [k for k in range(3) if k != axis]
    inside = np.all((ijk[:, other] >= 0) & (ijk[:, other] < np.asarray(head.shape)[other]), axis=1)
    depth = sign * (plane - ijk[:, axis])  # voxels from the point to the plane
    cand = np.flatnonzero(inside & (depth > 0))
    cand = cand[hole[ijk[cand, other[0]], ijk[cand, other[1]]]]
    if not cand.size:
        return out
    steps = np.arange(1, int(depth[cand].max()) + 1)
    along = ijk[cand, axis][:, None] + sign * steps[None, :]  # (points, steps)
    idx = [None] * 3
    idx[axis] = np.clip(along, 0, n - 1)
    for k in other:
        idx[k] = np.broadcast_to(ijk[cand, k][:, None], along.shape)
    blocked = head[tuple(idx)] & (steps[None, :] < depth[cand][:, None])
    out[cand[~blocked.any(axis=1)]] = True
    return out


def _on_circles(p, rows, spacing, reach):
    """Points within ``reach`` (mm) inside the field-of-view circle of their nearest slice
    among ``rows`` (:func:`fov_cuts`: z, centre x, centre y, radius), that slice within
    half a slice of them."""
    rows = rows.reshape(-1, 4)
    on = np.zeros(len(p), dtype=bool)
    if not len(rows):
        return on
    rows = rows[np.argsort(rows[:, 0])]
    z = rows[:, 0]
    above = np.clip(np.searchsorted(z, p[:, 2]), 0, len(z) - 1)
    below = np.maximum(above - 1, 0)
    r = rows[np.where(np.abs(z[below] - p[:, 2]) < np.abs(z[above] - p[:, 2]), below, above)]
    same = np.abs(r[:, 0] - p[:, 2]) <= 0.5 * float(spacing[2]) + 1e-9
    return same & (np.hypot(p[:, 0] - r[:, 1], p[:, 1] - r[:, 2]) >= r[:, 3] - reach)


def cut_points(skin):
    """The points of ``skin`` on a cut of the scan: its ``arrays.SKIN_CUT`` array (as
    :func:`on_scan_cuts` marks them), none without it.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> skin = pv.PolyData(np.zeros((3, 3)))
    >>> cut_points(skin).tolist()
    [False, False, False]
    >>> skin.point_data[arrays.SKIN_CUT] = np.array([0, 1, 0], np.uint8)
    >>> cut_points(skin).tolist()
    [False, True, False]
    """
    if arrays.SKIN_CUT in skin.point_data:
        return np.asarray(skin.point_data[arrays.SKIN_CUT]).reshape(-1).astype(bool)
    return np.zeros(skin.n_points, dtype=bool)
