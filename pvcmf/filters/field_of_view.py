"""A head cut flat by the field of view or the scan's end: which sides, and where.

:func:`cut_planes` counts, per image plane, the head voxels whose outward neighbour is not
head (numpy counts along each axis, no loop over voxels) and reports a side whose plane
holds more of that exposed surface than the pole of a sphere of the head's volume could,
with the plane and the extent of the cut; :func:`clipped_sides` gives their messages.
:func:`pvcmf.filters.segment` warns with them and keeps the planes in the labels' field
data (``arrays.SCAN_CUTS``, :func:`cuts_array`); :func:`on_scan_cuts` marks the skin
points that lie on a cut (the skin there is the scan's edge, not the patient's), which
:func:`pvcmf.filters.skin_prediction.predict_skin` writes as ``arrays.SKIN_CUT``. Index
axis 2 is the axial axis; the patient frame (x left, y anterior, z superior) is assumed
for the side names.
"""

from __future__ import annotations

import numpy as np

from .. import arrays

__all__ = ["clipped_sides", "cut_planes", "cuts_array", "on_scan_cuts"]

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


def cuts_array(cuts):
    """:func:`cut_planes`'s planes as the flat float64 field array ``arrays.SCAN_CUTS``:
    per cut ``axis, sign, at, lo_1, hi_1, lo_2, hi_2, edge`` (the two other axes in
    order; edge 1 for the field of view's edge, 0 for the image's end)."""
    return np.array([[c["axis"], c["sign"], c["at"], c["lo"][0], c["hi"][0], c["lo"][1],
                      c["hi"][1], float(c["edge"])] for c in cuts],
                    dtype=np.float64).reshape(-1)


def on_scan_cuts(points, labels):
    """Which ``points`` (a skin) lie on a plane where the scan cut the head.

    A point is on a cut when it lies within one and a half voxels inside the cut's plane
    (or beyond it) and of the cut's extent: the skin there is the scan's edge, not the
    patient's (a face cut by the field of view, a vertex cut by the scan's end). A circular field of view cuts a face along a cylinder that is flat only at its
    front: the cut's part that curves back more than that from the plane is not marked
    (a scan's padding outside its field of view often has the value of its clipped air,
    so it does not tell the two apart either).

    Parameters
    ----------
    points : array_like, shape (n, 3)
        Points in the labels' frame (mm).
    labels : pyvista.ImageData
        Labels of :func:`pvcmf.filters.segment`; without ``arrays.SCAN_CUTS`` in its
        field data nothing is on a cut.

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
    if arrays.SCAN_CUTS not in labels.field_data:
        return on
    reach = 1.5 * np.asarray(labels.spacing, dtype=np.float64)  # voxels and a half, mm
    cuts = np.asarray(labels.field_data[arrays.SCAN_CUTS], dtype=np.float64).reshape(-1, 8)
    for axis, sign, at, lo1, hi1, lo2, hi2, _ in cuts:
        a = int(axis)
        b, c = (k for k in range(3) if k != a)
        near = sign * (p[:, a] - at) >= -reach[a]
        within = ((p[:, b] >= lo1 - reach[b]) & (p[:, b] <= hi1 + reach[b])
                  & (p[:, c] >= lo2 - reach[c]) & (p[:, c] <= hi2 + reach[c]))
        on |= near & within
    return on

