"""Dense objects lying on the skin, for :func:`pvcmf.filters.segment`: cords, tubes, straps,
plastic sheets, skin markers and earrings that touch the head along their length, so that
no opening of the head mask detaches them, and that would otherwise stand as ridges on the
skin surface.

An object is a connected piece of the head mask denser than any soft tissue (skin, fat,
muscle and cartilage stay below ``dense`` in the image's own units, see
:data:`DENSE_STEPS`) that reaches the head's surface and lies entirely within ``depth`` mm
of the air outside the head: bone, teeth and calcified cartilage inside the head always have a part
deeper than that (the skull, the jaws, the teeth in their sockets), an object on the skin
does not. The object is removed with its partial-volume rim: the voxels within ``radius``
mm of it that the opening of the rest of the head by a ball of ``radius`` mm does not keep
(the thin bump the object and its blur raise on the skin; the skin under it stays).

Each object is processed in its own box (``scipy.ndimage.find_objects``): the distance
transforms (SimpleITK's exact Maurer transform, see :mod:`pvcmf.filters.morphology`) run on
a few hundred thousand voxels, not on the whole head. The depth test runs on the coarse copy
of the head.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from .morphology import _beyond, _down, _fill, _largest_component, _up, _within

log = logging.getLogger(__name__)

#: level above which a voxel is denser than any soft tissue, in air -> soft-tissue steps
#: above the soft-tissue peak: about 240 HU on a calibrated scan (skin, fat, muscle, blood
#: and cartilage stay below; plastic cords and tubes, markers and metal lie above)
DENSE_STEPS = 0.2
#: radius (mm) of the opening that takes an object's partial-volume rim off the skin: the
#: rim of a cord or sheet a few millimetres across
RIM_MM = 4.0
#: length (voxels) of the stretches a long object is processed in (tight boxes)
PART_VOXELS = 24

_FACES = ndimage.generate_binary_structure(3, 1)
_ALL = np.ones((3, 3, 3), dtype=bool)


def drop_surface_objects(head, vol, spacing, factor, dense, depth, radius=RIM_MM):
    """The head mask without the dense objects lying on its surface.

    Parameters
    ----------
    head : numpy.ndarray of bool
        The head mask (one connected piece), axes as ``vol``.
    vol : numpy.ndarray
        The image values.
    spacing : array-like of 3 float
        Voxel size (mm).
    factor : array-like of 3 int
        Block size of the coarse copy the depth test runs on.
    dense : float
        Value (image units) above which a voxel is denser than soft tissue.
    depth : float
        An object lies entirely within this distance (mm) of the air outside the head.
    radius : float
        Radius (mm) of the opening that removes the object's rim (at least 1.5 voxels).

    Returns
    -------
    head : numpy.ndarray of bool
        A new mask: ``head`` without the objects and their rims, its largest piece.
    removed_ml : float
        Volume removed (mL).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.surface_objects import drop_surface_objects
    >>> x, y, z = np.mgrid[:40, :40, :40]
    >>> ball = (x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2 < 15 ** 2
    >>> cord = (abs(x - 20) <= 1) & (abs(y - 36) <= 1) & (z > 8) & (z < 32)
    >>> vol = np.where(cord, 400.0, np.where(ball, 40.0, -1000.0))
    >>> head, ml = drop_surface_objects(ball | cord, vol, (1.0,) * 3, (2, 2, 2), 240.0, 5.0)
    >>> bool(head[20, 36, 20]), bool(head[20, 20, 20]), int((ball & ~head).sum()) < 20
    (False, True, True)
    """
    spacing = np.asarray(spacing, dtype=float)
    objects = head & (vol >= dense)
    if not objects.any() or depth <= 0:
        return head.copy(), 0.0
    lab, n = ndimage.label(objects, structure=_ALL)
    keep = np.zeros(n + 1, dtype=bool)
    # not an object: a piece with a part deeper than ``depth`` (coarse distance to the air)
    cspace = spacing * np.asarray(factor)
    inside = _fill(_down(head, factor, "any"), _FACES)
    # (the image's end is no air: the padding repeats the last slices of a head cut there)
    deep = _beyond(np.pad(inside, 1, mode="edge"), cspace,
                   depth + float(np.max(cspace)))[1:-1, 1:-1, 1:-1]
    keep[_labels_in_blocks(lab, deep, factor)] = True
    # ... or one that does not reach the head's surface (a vessel under the skin)
    on_skin = np.zeros(n + 1, dtype=bool)
    on_skin[np.unique(lab[_surface(head) & objects])] = True
    keep |= ~on_skin
    keep[0] = True
    if keep.all():
        return head.copy(), 0.0
    out = head.copy()
    r = max(float(radius), 1.5 * float(np.max(spacing)))
    margin = np.ceil(2.0 * r / spacing).astype(int) + 2
    for i, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None or keep[i]:
            continue
        for part in _parts(lab[sl] == i, sl):  # a long cord: a tight box per stretch
            box = tuple(slice(max(s.start - m, 0), min(s.stop + m, k))
                        for s, m, k in zip(part, margin, head.shape))
            obj = lab[box] == i
            inner = tuple(slice(p.start - b.start, p.stop - b.start) for p, b in zip(part, box))
            seed = np.zeros_like(obj)
            seed[inner] = obj[inner]  # this stretch; the rest of the object is no tissue
            out[box] &= ~(seed | _rim(head[box] & ~obj, seed, spacing, r))
    largest = _largest_component(out, _FACES)
    if largest is None:  # everything was an object: keep the mask as it was
        return head.copy(), 0.0
    removed = float(np.count_nonzero(head & ~largest)) * float(np.prod(spacing)) / 1e3
    log.debug("segment: removed %d dense object(s) on the skin (%.2f mL with their rims)",
              int(np.count_nonzero(~keep)), removed)
    return largest, removed


def _labels_in_blocks(lab, coarse, factor):
    """The labels of ``lab`` in the blocks of the full grid that the block-reduced mask
    ``coarse`` marks (one strided view per offset in the block: no upsampled copy)."""
    f = [int(v) for v in factor]
    found = [np.zeros(1, dtype=lab.dtype)]
    for offset in np.ndindex(*f):
        view = lab[tuple(slice(o, None, k) for o, k in zip(offset, f))]
        mask = coarse[tuple(slice(0, n) for n in view.shape)]
        found.append(np.unique(view[mask]))
    return np.unique(np.concatenate(found))


def _surface(mask):
    """Voxels of ``mask`` with a face neighbour outside it (the array's border is inside):
    ``mask & ~binary_erosion(mask, faces, border_value=1)`` by shifted slices."""
    inner = mask.copy()
    for axis in range(mask.ndim):
        lo = [slice(None)] * mask.ndim
        hi = [slice(None)] * mask.ndim
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        inner[tuple(lo)] &= mask[tuple(hi)]
        inner[tuple(hi)] &= mask[tuple(lo)]
    return mask & ~inner


def _parts(obj, sl, length=PART_VOXELS):
    """Boxes (index slices of the whole image) of the stretches of ``obj`` (the object
    cropped to its box ``sl``) along its longest axis, ``length`` voxels each."""
    axis = int(np.argmax(obj.shape))
    out = []
    for start in range(0, obj.shape[axis], length):
        index = [slice(None)] * 3
        index[axis] = slice(start, start + length)
        found = ndimage.find_objects(obj[tuple(index)].astype(np.uint8))
        if not found or found[0] is None:
            continue
        box = [slice(s.start + o.start, s.stop + o.start) for s, o in zip(found[0], sl)]
        box[axis] = slice(box[axis].start + start, box[axis].stop + start)
        out.append(tuple(box))
    return out


def _rim(rest, obj, spacing, radius):
    """Voxels of ``rest`` within ``radius`` of ``obj`` that the opening of ``rest`` by a ball
    of ``radius`` does not keep."""
    pad = np.pad(rest, 1)
    core = _beyond(pad, spacing, radius)
    near = _within(obj, spacing, radius)
    if not core.any():
        return rest & near
    opened = _within(core, spacing, radius)[1:-1, 1:-1, 1:-1]
    return rest & near & ~opened
