"""A head cut flat by the field of view or the scan's end: which sides, and where.

:func:`clipped_sides` counts, per image plane, the head voxels whose outward neighbour is not
head (numpy counts along each axis, no loop over voxels) and reports a side whose plane
holds more of that exposed surface than the pole of a sphere of the head's volume could.
:func:`pvcmf.filters.segment` warns with its messages. Index axis 2 is the axial axis; the
patient frame (x left, y anterior, z superior) is assumed for the side names.
"""

from __future__ import annotations

import numpy as np

__all__ = ["clipped_sides"]

_SIDES = {(0, 1): "left (+x)", (0, -1): "right (-x)", (1, 1): "anterior (+y, face)",
          (1, -1): "posterior (-y)", (2, 1): "superior (+z, vertex)"}


def clipped_sides(head, spacing, origin=(0.0, 0.0, 0.0), vol=None, pad_fraction=0.8):
    """Sides where the head is cut flat (by the field of view or the scan's end).

    On each side (not the inferior one: the neck always leaves the scan), the head voxels
    whose outward neighbour is not head are counted per plane. A side is cut when one plane
    holds more of this exposed surface than the pole of a sphere of the head's volume can
    (``2 pi R`` mm^2 per mm) and the plane is the image's end or, with ``vol``, at least
    ``pad_fraction`` of the voxels beyond it hold the image's minimum value (the padding
    outside the reconstructed field of view), which a skin flattened on a headrest does not.

    Returns
    -------
    list of str
        One message per cut side, naming it and its extent in mm.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.field_of_view import clipped_sides
    >>> head = np.zeros((40, 40, 40), bool)
    >>> head[5:35, 5:40, 5:35] = True          # cut at the +y border
    >>> [m.split(" at ")[0] for m in clipped_sides(head, (1.0, 1.0, 1.0))]
    ['the head is cut flat on the anterior (+y, face) side']
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
        ext = ", ".join(
            f"{'xyz'[a]} {origin[a] + spacing[a] * ij[k].min():.0f} to "
            f"{origin[a] + spacing[a] * ij[k].max():.0f} mm" for k, a in enumerate(other))
        where = "the image's end" if plane == len(area) - 1 else "the field of view's edge"
        out.append(f"the head is cut flat on the {name} side at {'xyz'[axis]} = "
                   f"{origin[axis] + spacing[axis] * index:.0f} mm by {where} "
                   f"({area[plane]:.0f} mm^2; {ext}): the skin there is not the patient's")
    return out
