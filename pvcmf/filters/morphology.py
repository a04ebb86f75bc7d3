"""Binary morphology on label volumes for :func:`pvcmf.filters.segment`: largest component,
hole filling, balls of a physical radius, closing/dilation/opening by a ball, bounding boxes
and block down/up-sampling of masks, and dilations/erosions by a 3x3x3 element on masks
packed eight voxels a byte (:func:`numpy.packbits`: eight times fewer bytes to OR or AND).
Delegates to :mod:`scipy.ndimage`, and the Euclidean
distance transforms to SimpleITK's ``SignedMaurerDistanceMap`` (an exact transform, about
twice as fast as :func:`scipy.ndimage.distance_transform_edt`, which is the fallback).

The masks are C-ordered: :func:`scipy.ndimage.label` and numpy's elementwise operations run
several times slower on Fortran-ordered or mixed-order arrays.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

#: smallest ball radius in voxels (a radius below it would be a single voxel)
MIN_BALL_VOXELS = 1.5


def _largest_component(mask, structure):
    lab, n = ndimage.label(mask, structure=structure)
    if n == 0:
        return None
    if n == 1:
        return lab.astype(bool)
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return lab == int(np.argmax(sizes))


def _fill(mask, structure, z_open=False):
    """Fill holes: background not connected to the array border (through ``structure``).

    With ``z_open`` the first and last slices do not count as border (for a slice-wise fill
    with an in-slice structure, every slice is then filled on its own).
    """
    lab, _ = ndimage.label(~mask, structure=structure)
    faces = [lab[0], lab[-1], lab[:, 0], lab[:, -1]]
    if not z_open:
        faces += [lab[:, :, 0], lab[:, :, -1]]
    outside = np.unique(np.concatenate([f.ravel() for f in faces]))
    keep = np.ones(lab.max() + 1, dtype=bool)
    keep[outside] = False
    keep[0] = False
    return mask | keep[lab]


def _ball(spacing, radius, minimum=MIN_BALL_VOXELS):
    """Ellipsoidal structuring element: the ball of ``radius`` mm (>= ``minimum`` voxels)."""
    r_vox = np.maximum(radius / np.maximum(np.asarray(spacing, float), 1e-12), minimum)
    half = np.floor(r_vox).astype(int)
    grid = np.meshgrid(*(np.arange(-h, h + 1) for h in half), indexing="ij")
    return sum((g / r) ** 2 for g, r in zip(grid, r_vox)) <= 1.0 + 1e-9


def _sq_edt(mask, sampling):
    """Squared Euclidean distance (mm^2) from every voxel of ``mask`` to the nearest voxel
    outside it (0 outside), as :func:`scipy.ndimage.distance_transform_edt` squared.

    SimpleITK's exact ``SignedMaurerDistanceMap`` (float32) where it is installed and the
    mask has background; else scipy."""
    mask = np.asarray(mask, dtype=bool)
    sampling = np.broadcast_to(np.asarray(sampling, dtype=float), (mask.ndim,))
    try:
        import SimpleITK as sitk
    except ImportError:  # optional at run time: scipy's transform
        sitk = None
    if sitk is None or mask.ndim != 3 or mask.all() or not mask.any():
        return ndimage.distance_transform_edt(mask, sampling=sampling) ** 2
    # the background is the object whose outside distances are wanted; no transposition:
    # the array's last axis is the image's first, so the spacing is reversed
    img = sitk.GetImageFromArray(np.ascontiguousarray(~mask).view(np.uint8))
    img.SetSpacing([float(s) for s in sampling[::-1]])
    f = sitk.SignedMaurerDistanceMapImageFilter()
    f.SetSquaredDistance(True)
    f.SetUseImageSpacing(True)
    f.SetInsideIsPositive(False)
    f.SetBackgroundValue(0)
    out = sitk.GetArrayFromImage(f.Execute(img))
    np.maximum(out, 0, out=out)  # the background's own (negative) values
    return out


def _within(mask, sampling, radius):
    """Voxels within ``radius`` (mm) of ``mask``: ``edt(~mask) <= radius``."""
    return _sq_edt(~np.asarray(mask, dtype=bool), sampling) <= _sq_tol(radius)


def _beyond(mask, sampling, radius):
    """Voxels of ``mask`` farther than ``radius`` (mm) from its outside: ``edt(mask) >
    radius``."""
    return _sq_edt(mask, sampling) > _sq_tol(radius)


def _sq_tol(radius):
    """``(radius + 1e-6)^2`` with room for the float32 round-off of the squared distance
    (a few 1e-6 relative)."""
    r = float(radius) + 1e-6
    return r * r * (1.0 + 1e-5)


def _closing(mask, spacing, radius):
    """Binary closing with a ball of ``radius`` mm (the ellipsoid of :func:`_ball`), padded
    so the border does not erode: a dilation and an erosion thresholding distance
    transforms in units of the ball's radii (the same voxels as the structuring element)."""
    r_vox = np.maximum(radius / np.maximum(np.asarray(spacing, float), 1e-12), MIN_BALL_VOXELS)
    half = np.floor(r_vox).astype(int)
    pad = [(int(h) + 1, int(h) + 1) for h in half]
    unit = 1.0 / r_vox  # the ball is the unit ball in these units
    padded = np.pad(np.asarray(mask, dtype=bool), pad)
    if np.all(half <= 1):  # a ball within 3x3x3 voxels: ORs and ANDs of shifted copies
        ball = _ball(spacing, radius)
        closed = _shifted(_shifted(padded, ball, np.logical_or), ball, np.logical_and)
        return closed[tuple(slice(a, -b) for a, b in pad)]
    dilated = _sq_edt(~padded, unit) <= 1.0 + 1e-4  # float32 round-off; no offset of a
    closed = _sq_edt(dilated, unit) > 1.0 + 1e-4  # ball lies that close outside it
    return closed[tuple(slice(a, -b) for a, b in pad)]


def _shifted(a, ball, op):
    """Dilation (``op`` OR) or erosion (AND) of ``a`` by a symmetric 3x3x3 ``ball``, on the
    voxels one away from the array's border; the border keeps its values (the callers pad
    by two empty layers: the dilation cannot reach the outer one, which erodes anyway)."""
    out = a.copy()
    inner = (slice(1, -1),) * 3
    for offset in zip(*np.nonzero(ball)):  # at most 27 shifts of the whole array
        if offset == (1, 1, 1):
            continue
        src = tuple(slice(o, n - 2 + o) for o, n in zip(offset, a.shape))
        op(out[inner], a[src], out=out[inner])
    return out


def _dilate_ball(mask, spacing, radius):
    """Dilation by a ball of ``radius`` mm: the voxels within ``radius`` of ``mask`` (a
    distance transform, far cheaper than ``binary_dilation`` with a large ball)."""
    return _within(mask, spacing, radius)


def _open_ball(mask, spacing, radius):
    """Opening by a ball of ``radius`` mm (outside the array counts as background)."""
    pad = np.pad(mask, 1)
    core = _beyond(pad, spacing, radius)
    return _dilate_ball(core, spacing, radius)[1:-1, 1:-1, 1:-1] & mask


def _c_copy(a):
    """C-ordered copy of a 3-D array (a view of a Fortran-ordered image): slab by slab along
    the last axis, so that the reads of each slab stay in cache (``np.ascontiguousarray`` of
    a Fortran-ordered array reads memory with a stride of a whole slice)."""
    if a.flags.c_contiguous:
        return a.copy()
    out = np.empty(a.shape, dtype=a.dtype)
    block = max(8, 32 // a.dtype.itemsize)
    for k in range(0, a.shape[2], block):  # a few dozen slabs, not a voxel loop
        out[:, :, k:k + block] = a[:, :, k:k + block]
    return out


def _smoothing_margin(sigma):
    """Voxels of zeros beyond an object that keep :func:`scipy.ndimage.gaussian_filter`
    (``sigma`` voxels, its default truncation at 4 sigma) the same near the object as on
    the whole image, plus two."""
    return int(4.0 * max(float(sigma or 0.0), 0.0) + 0.5) + 2


def _box(mask, margin):
    idx = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != ax)))
           for ax in range(3)]
    return tuple(slice(max(int(i[0]) - margin, 0), min(int(i[-1]) + margin + 1, n))
                 for i, n in zip(idx, mask.shape))


def _down(mask, factor, how="any"):
    """Block-reduce a boolean volume by integer ``factor`` per axis (``any`` or ``mean``):
    one axis at a time, in-place ORs or sums of strided views (a partial block at the end
    counts its missing voxels as False)."""
    f = [int(v) for v in factor]
    a = mask if how == "any" else mask.view(np.uint8)
    for axis, k in enumerate(f):
        if k == 1:
            continue
        index = [slice(None)] * 3
        index[axis] = slice(0, None, k)
        out = a[tuple(index)].astype(bool if how == "any" else np.uint16)
        for offset in range(1, k):
            index[axis] = slice(offset, None, k)
            part = a[tuple(index)]
            target = [slice(None)] * 3
            target[axis] = slice(0, part.shape[axis])
            view = out[tuple(target)]
            (np.logical_or if how == "any" else np.add)(view, part, out=view)
        a = out
    if how == "any":
        return a if a is not mask else a.copy()
    return 2 * a.astype(np.uint32) >= int(np.prod(f))


def _up(mask, factor, shape):
    """Nearest upsampling of a block-reduced volume back to ``shape``."""
    out = mask
    for ax, k in enumerate(factor):
        out = np.repeat(out, int(k), axis=ax)
    return out[tuple(slice(0, n) for n in shape)]


# --------------------------------------------------------------------------- packed bits
# Masks packed 8 voxels a byte along the last axis (numpy.packbits, first voxel in the
# high bit): a dilation or erosion by a 3x3x3 element is then a few dozen ORs/ANDs of
# byte arrays eight times smaller than the boolean mask.

def _pack(mask):
    """``mask`` (3-D bool) packed along its last axis, padded with False to a multiple of
    8 voxels there (:func:`_unpack` takes the length back)."""
    return np.packbits(np.asarray(mask, dtype=bool), axis=2)


def _unpack(packed, n):
    """The boolean mask of the first ``n`` voxels of the last axis of ``packed``."""
    return np.unpackbits(packed, axis=2, count=n).view(bool)


def _shift_z(packed, dz):
    """``out[..., z] = mask[..., z + dz]`` for ``dz`` in (-1, 0, 1): bit shifts of the flat
    bytes, so a bit carries between neighbouring rows at their ends (the callers keep
    empty layers at both ends of the last axis, at least one more than the steps taken)."""
    if dz == 0:
        return packed
    flat = packed.reshape(-1)
    out = np.empty_like(flat)
    if dz > 0:
        np.left_shift(flat, 1, out=out)
        out[:-1] |= flat[1:] >> 7
    else:
        np.right_shift(flat, 1, out=out)
        out[1:] |= flat[:-1] << 7
    return out.reshape(packed.shape)


def _packed_step(packed, element, op):
    """Dilation (``op`` ``np.bitwise_or``) or erosion (``np.bitwise_and``) of a packed mask
    by a symmetric 3x3x3 ``element``: for every offset, the mask shifted along the packed
    axis by bit shifts, along the others by slices. The outermost rows and columns of the
    first two axes keep their values (the callers pad the mask with empty layers)."""
    shifted = {dz: _shift_z(packed, dz) for dz in (-1, 0, 1) if element[:, :, dz + 1].any()}
    out = packed.copy()
    nx, ny = packed.shape[:2]
    for dx, dy, dz in zip(*np.nonzero(element)):
        dx, dy, dz = int(dx) - 1, int(dy) - 1, int(dz) - 1
        if dx == dy == dz == 0:
            continue
        src = shifted[dz][1 + dx:nx - 1 + dx, 1 + dy:ny - 1 + dy]
        op(out[1:-1, 1:-1], src, out=out[1:-1, 1:-1])
    return out
