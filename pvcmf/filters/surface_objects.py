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

A film (a plastic wrap, a drape), lighter than skin but blurred above the skin threshold
where it lies on the skin across an air gap of a voxel or two, is :func:`drop_film`'s: a
thickness test (an opening by a 3x3x3 ball) and a test of the air under it, on masks packed
eight voxels a byte.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from .morphology import (_ball, _beyond, _down, _fill, _largest_component, _pack,
                         _packed_step, _shifted, _unpack, _within)

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


#: smallest area (mm^2) of a film: a wrap film or a drape covers centimetres of the skin;
#: the thin edges of an ear near the scalp or a fold of skin are millimetre pieces
FILM_MIN_MM2 = 100.0
#: voxel steps (of the 3x3x3 element) within which a film lies on the body: its own
#: thickness and the air gap under it, each up to the two voxels the opening removes
FILM_STEPS = 3
#: largest voxel size (mm) the film test runs at: two voxels must be thinner than any
#: anatomy on the skin (the rims of the ears and nostrils are 3 mm and more); on coarser
#: scans a film hardly shows above the skin threshold anyway
FILM_VOXEL_MM = 1.25


def drop_film(head, vol, spacing, dense, factor=(2, 2, 2), radius=RIM_MM,
              min_area=FILM_MIN_MM2, largest=True):
    """The head mask without the thin sheets (wrap film, a drape) lying on the skin.

    A film is at most two voxels thick whatever its density (it blurs over the voxels it
    crosses) and lies on the skin across a thin air gap, touching it here and there, with
    the open air on its other side. The thin part of the head is what the opening by a
    ball of ``MIN_BALL_VOXELS`` (1.5) voxels removes (a 3x3x3 element, whatever the
    spacing). A thin voxel is film when

    - it lies across a one-voxel air gap from the opened head (the body): an air voxel
      touches both; or it is within ``FILM_STEPS`` steps of the body through any voxel
      but not through the head itself (a geodesic test: the film reaches the body only
      where it touches it);
    - it is below ``dense`` (thin bone stays: a septum, a nasal bone);
    - it lies within two coarse voxels of the open air: the air around the head that a
      ball of ``radius`` mm reaches (an opening of the air on the coarse copy of
      ``factor`` voxels). The walls of the nasal cavity, the turbinates, the mouth and the
      sinuses, as thin and as close to each other, are out of its reach.

    Pieces of such voxels smaller than ``min_area`` stay (the thin rim of an ear near the
    scalp, a fold of skin); the larger ones go with the thin voxels within ``FILM_STEPS``
    steps of them (the film's stubs where it touches the skin). Ears, nostrils and lips
    are thin only at rims that the body reaches directly: they stay. The steps run on
    masks packed eight voxels a byte (:mod:`pvcmf.filters.morphology`), the tests of the
    density and of the open air on the list of candidate voxels only.

    Parameters
    ----------
    head : numpy.ndarray of bool
        The head mask.
    vol : numpy.ndarray
        The image values, axes as ``head``.
    spacing : array-like of 3 float
        Voxel size (mm). Coarser than ``FILM_VOXEL_MM`` on an axis: nothing is removed.
    factor : array-like of 3 int
        Block size of the coarse copy the open air is found on.
    radius : float
        Radius (mm) of the ball that finds the open air.
    dense : float
        Value (image units) above which a voxel is denser than soft tissue.
    min_area : float
        Smallest area (mm^2) of a film piece.
    largest : bool
        Keep the largest piece of the mask only (``False``: the caller does, after more
        pieces are cut off).

    Returns
    -------
    head : numpy.ndarray of bool
        A new mask without the film (its largest piece with ``largest``).
    removed_ml : float
        Volume removed (mL).

    Examples
    --------
    A ball with a film one voxel above it, touching it along one line:

    >>> import numpy as np
    >>> from pvcmf.filters.surface_objects import drop_film
    >>> x, y, z = np.mgrid[:48, :48, :48]
    >>> r = np.sqrt((x - 24) ** 2 + (y - 24) ** 2 + (z - 24) ** 2)
    >>> ball, film = r < 17, (abs(r - 18.5) < 0.5) & (x < 20)
    >>> touch = (abs(z - 24) <= 0) & (r < 19) & (x < 20)
    >>> vol = np.where(ball | film | touch, 40.0, -1000.0)
    >>> head, ml = drop_film(ball | film | touch, vol, (1.0,) * 3, 240.0)
    >>> int(film.sum()), int((head & film).sum()), int((ball & ~head).sum()) < 20
    (1564, 0, True)
    """
    spacing = np.asarray(spacing, dtype=float)
    head = np.asarray(head, dtype=bool)
    if float(np.max(spacing)) > FILM_VOXEL_MM or not head.any():
        return head.copy(), 0.0
    element = _ball(spacing, 0.0)  # 1.5 voxels on every axis: the 3x3x3 neighbourhood
    # empty layers around: the packed steps carry bits between rows at the z ends
    margin = [(2, 2), (2, 2), (FILM_STEPS + 3, FILM_STEPS + 3)]
    pad = np.pad(head, margin)
    full = _pack(pad)

    def grow(mask):
        return _packed_step(mask, element, np.bitwise_or)

    core = grow(_packed_step(full, element, np.bitwise_and))
    thin = full & ~core
    if not thin.any():
        return head.copy(), 0.0
    gap = ~full & grow(core) & grow(thin)  # air touching both the body and a thin voxel
    seeds = thin & grow(gap)
    del gap
    near, reach = core, core
    for _ in range(FILM_STEPS):  # near the body through any voxel, not through the head
        near, reach = grow(near), grow(reach) & full
        seeds |= thin & near & ~reach
    del near, reach
    # the seeds' voxels: not dense, next to the open air, in large pieces
    idx = _packed_nonzero(seeds)
    idx = tuple(i - m for i, (m, _) in zip(idx, margin))
    keep = np.asarray(vol)[idx] < dense
    keep &= _open_air(head, spacing, factor, radius)[tuple(i // k for i, k in
                                                          zip(idx, factor))]
    idx = tuple(i[keep] for i in idx)
    idx = _large_pieces(idx, head.shape, spacing, min_area)
    if idx is None:
        return head.copy(), 0.0
    film = np.zeros_like(full)
    z = idx[2] + margin[2][0]
    np.bitwise_or.at(film, (idx[0] + 2, idx[1] + 2, z // 8),
                     np.right_shift(np.uint8(128), (z % 8).astype(np.uint8)))
    thin &= _pack(np.pad(np.asarray(vol) < dense, margin))  # no thin bone
    for _ in range(FILM_STEPS):  # the stubs: thin voxels the film reaches
        film = grow(film) & thin
    z = margin[2][0]
    out = np.ascontiguousarray(_unpack(full & ~film, pad.shape[2])[2:-2, 2:-2, z:-z])
    if largest:
        out = _largest_component(out, _FACES)
        if out is None:
            return head.copy(), 0.0
    removed = float(np.count_nonzero(head & ~out)) * float(np.prod(spacing)) / 1e3
    log.debug("segment: removed %.2f mL of film lying on the skin", removed)
    return out, removed


def _packed_nonzero(packed):
    """Indices (as :func:`numpy.nonzero`) of the set voxels of a packed mask: the bytes
    that are not zero, then their bits."""
    bx, by, bz = np.nonzero(packed)
    bits = np.unpackbits(packed[bx, by, bz][:, None], axis=1)
    row, bit = np.nonzero(bits)
    return bx[row], by[row], bz[row] * 8 + bit


def _open_air(head, spacing, factor, radius):
    """Voxels within two coarse voxels of the open air: the largest piece of the head's box
    (the air around the head) of the air that a ball of about ``radius`` mm reaches (an
    opening of the air on the coarse copy by ``radius / coarse voxel`` steps of the 3x3x3
    element), on the coarse copy. A sinus open at a face cut by the field of view, or a wide
    airway, is another piece."""
    f = np.asarray(factor, dtype=int)
    cspace = spacing * f
    k = max(1, int(round(radius / float(np.max(cspace)))))
    m = k + 1  # the erosion sees air beyond the box; one layer for the shifts
    air = np.pad(~_down(head, f, "any"), m, constant_values=True)
    element = _ball(cspace, 0.0)
    for _ in range(k):
        air = _shifted(air, element, np.logical_and)
    for _ in range(k):
        air = _shifted(air, element, np.logical_or)
    outside = _largest_component(air[m:-m, m:-m, m:-m], _FACES)
    if outside is None:
        return np.zeros(air[m:-m, m:-m, m:-m].shape, dtype=bool)
    outside = np.pad(outside, 3)
    for _ in range(2):
        outside = _shifted(outside, element, np.logical_or)
    return outside[3:-3, 3:-3, 3:-3]


def _large_pieces(idx, shape, spacing, min_area, block=2):
    """The voxels ``idx`` (indices into an array of ``shape``) in pieces of at least
    ``min_area`` mm^2 (a voxel of a sheet covers ``prod(spacing)^(2/3)``), or None. Pieces
    are labelled on blocks of ``block`` voxels (eight times fewer voxels to label): voxels
    a voxel apart are one piece."""
    if idx[0].size == 0:
        return None
    blocks = tuple(i // block for i in idx)
    coarse = np.zeros(tuple(-(-n // block) for n in shape), dtype=bool)
    coarse[blocks] = True
    lab, n = ndimage.label(coarse, structure=_ALL)
    piece = lab[blocks]
    face = float(np.prod(spacing)) ** (2.0 / 3.0)
    big = np.bincount(piece, minlength=n + 1) * face >= float(min_area)
    big[0] = False
    keep = big[piece]
    if not keep.any():
        return None
    return tuple(i[keep] for i in idx)
