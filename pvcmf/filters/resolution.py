"""A working grid for very fine scans: the CT averaged over blocks of whole voxels.

Segmentation's memory and time grow with the number of voxels (about 50 bytes per voxel
at its peak: ``segment`` on a 1 mm head of 61 million voxels peaks near 3 GB), while a
cone-beam CT at 0.2-0.3 mm holds 100-500 million. :func:`working_grid` makes the image
the pipeline works on: each working voxel is the mean of a block of ``f_x x f_y x f_z``
scan voxels (whole numbers per axis), as a coarser detector would have averaged them, so
no value is interpolated, partial volume stays what a coarser scan shows, and the image's
histogram peaks (air, soft tissue), from which :func:`pvcmf.filters.segment` places its
thresholds, stay where they were.

Which blocks: ``spacing="auto"`` keeps the scan's grid up to ``max_voxels``
(:data:`MAX_VOXELS`) and above it grows the block, one voxel at a time along the axis
whose working voxel is then the finest, until the image fits (the working voxels as
near cubic as whole blocks allow); a number asks for working voxels of about that size
(mm); ``None`` keeps the scan's grid. A block at the image's far end that the image does
not fill averages the voxels it holds.

Geometry: a working voxel sits at the centre of its block, so the image covers the same
patient space (``origin + D ((f - 1) / 2) s``, ``D`` the image's direction matrix), and
the field data :data:`pvcmf.arrays.WORKING_FACTORS` and :data:`pvcmf.arrays.SCAN_SPACING`
record the blocks and the scan's own spacing.

Delegates to numpy: each axis's block sums are in-place adds of strided views of the
image (no copy of the whole scan, no loop over voxels).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pyvista as pv

from .. import arrays

log = logging.getLogger(__name__)

__all__ = ["working_grid", "working_factors", "describe_grid", "MAX_VOXELS",
           "BYTES_PER_VOXEL"]

#: voxels above which ``spacing="auto"`` averages the scan over blocks (2**27: about 134
#: million, which ``simulate`` models in about 5 GB besides the image itself)
MAX_VOXELS = 2**27
#: peak memory of the pipeline per voxel of the image it segments (bytes; measured on the
#: 1 mm female head: 3.0 GB for 61 million voxels, ``benchmarks/scan_size.py``)
BYTES_PER_VOXEL = 50


def working_factors(dimensions, spacing, working_spacing="auto", max_voxels=None,
                    name="working_spacing"):
    """Block size per axis (whole voxels) of :func:`working_grid` for an image of
    ``dimensions`` voxels of ``spacing`` mm (see the module docs for ``working_spacing``
    and ``max_voxels``; None: :data:`MAX_VOXELS`; ``name``: the parameter that gave
    ``working_spacing``, in the error).

    Examples
    --------
    >>> working_factors((512, 512, 400), (0.3, 0.3, 0.3), max_voxels=50_000_000)
    (2, 2, 1)
    >>> working_factors((512, 512, 400), (0.3, 0.3, 0.3), 1.0)
    (3, 3, 3)
    >>> working_factors((512, 512, 400), (0.3, 0.3, 0.3), None)
    (1, 1, 1)
    """
    dims = np.asarray(dimensions, dtype=np.int64)
    step = np.asarray(spacing, dtype=float)
    if dims.shape != (3,) or np.any(dims < 1):
        raise ValueError(f"dimensions must be 3 positive integers, got {tuple(dimensions)}")
    if step.shape != (3,) or not np.all(np.isfinite(step)) or np.any(step <= 0):
        raise ValueError(f"spacing must be 3 finite numbers > 0 (mm), got {tuple(spacing)}")
    max_voxels = MAX_VOXELS if max_voxels is None else max_voxels
    if (isinstance(max_voxels, bool) or not isinstance(max_voxels, (int, np.integer))
            or max_voxels < 1):
        raise ValueError(f"max_voxels must be a positive integer, got {max_voxels!r}")
    if working_spacing is None:
        return (1, 1, 1)
    if isinstance(working_spacing, str):
        if working_spacing != "auto":
            raise ValueError(f"{name} must be 'auto', a size in mm or None, got "
                             f"{working_spacing!r}")
        f = np.ones(3, dtype=np.int64)
        while np.prod(-(-dims // f)) > max_voxels and np.any(f < dims):
            size = np.where(f < dims, step * f, np.inf)  # an axis of one block is done
            ax = int(np.argmin(size))
            f[ax] += 1
        return tuple(int(v) for v in f)
    if (isinstance(working_spacing, bool) or not isinstance(working_spacing, (int, float))
            or not math.isfinite(working_spacing) or working_spacing <= 0):
        raise ValueError(f"{name} must be 'auto', a size in mm > 0 or None, got "
                         f"{working_spacing!r}")
    f = np.clip(np.round(float(working_spacing) / step), 1, dims)
    return tuple(int(v) for v in f)


def working_grid(ct, spacing="auto", *, max_voxels=None):
    """The CT on a working grid of blocks of whole scan voxels (module docs).

    Parameters
    ----------
    ct : pyvista.ImageData
        3-D image with a float point array ``ct`` (finite values).
    spacing : 'auto', float or None
        ``'auto'``: the scan's grid up to ``max_voxels``, blocks above it; a number: working
        voxels of about this size (mm), each axis's block the nearest whole number of scan
        voxels (at least 1); ``None``: the scan's grid.
    max_voxels : int, optional
        Most voxels ``'auto'`` keeps (default :data:`MAX_VOXELS`).

    Returns
    -------
    pyvista.ImageData
        A new image (``ct`` kept) with the block means of ``ct`` (float32; the other point
        arrays are not carried over) and the field data of ``ct`` plus
        :data:`~pvcmf.arrays.WORKING_FACTORS` (the blocks, int64) and
        :data:`~pvcmf.arrays.SCAN_SPACING` (the scan's spacing, mm). With blocks of one
        voxel it is a deep copy of ``ct`` with those two fields.

    Raises
    ------
    TypeError
        If ``ct`` is not an ImageData.
    ValueError
        If the ``ct`` array is missing, not float or not finite, or ``spacing`` or
        ``max_voxels`` is not one of the values above.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters import working_grid
    >>> img = pv.ImageData(dimensions=(8, 8, 8), spacing=(0.25, 0.25, 0.5))
    >>> img["ct"] = np.arange(img.n_points, dtype=np.float32)
    >>> out = working_grid(img, 0.5)
    >>> out.dimensions, out.spacing
    ((4, 4, 8), (0.5, 0.5, 0.5))
    >>> out.field_data["working_factors"].tolist()
    [2, 2, 1]
    """
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"ct must be a pyvista.ImageData, got {type(ct).__name__}")
    values = arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                  producer="pvcmf.read_ct")
    dims = tuple(int(d) for d in ct.dimensions)
    step = np.asarray(ct.spacing, dtype=float)
    factors = working_factors(dims, step, spacing, max_voxels, name="spacing")
    if factors == (1, 1, 1):
        out = ct.copy(deep=True)
    else:
        if not np.all(np.isfinite(values)):
            bad = int(np.count_nonzero(~np.isfinite(values)))
            raise ValueError(f"ct array 'ct' must be finite, got {bad} NaN/inf value(s)")
        vol = _block_means(np.asarray(values).reshape(dims, order="F"), factors)
        f = np.asarray(factors, dtype=float)
        direction = np.asarray(ct.direction_matrix, dtype=float)
        origin = np.asarray(ct.origin, dtype=float) + direction @ ((f - 1.0) / 2.0 * step)
        out = pv.ImageData(dimensions=vol.shape, spacing=tuple(step * f),
                           origin=tuple(origin), direction_matrix=direction)
        out.point_data[arrays.CT] = vol.ravel(order="F")
        for name in ct.field_data.keys():
            out.field_data[name] = np.array(ct.field_data[name], copy=True)
        log.info("working_grid: %s voxels of %s mm averaged in blocks of %s: %s voxels of "
                 "%s mm", "x".join(map(str, dims)), _mm(step), "x".join(map(str, factors)),
                 "x".join(map(str, vol.shape)), _mm(step * f))
    out.field_data[arrays.WORKING_FACTORS] = np.asarray(factors, dtype=np.int64)
    out.field_data[arrays.SCAN_SPACING] = step.copy()
    return out


def describe_grid(ct, work):
    """``(record, text)``: what :func:`working_grid` made of ``ct`` as ``work``: a dict
    (``factors``, ``scan_spacing_mm``, ``spacing_mm``, ``scan_voxels``, ``voxels``) and a
    sentence."""
    scan, step = np.asarray(ct.spacing, dtype=float), np.asarray(work.spacing, dtype=float)
    factors = [int(v) for v in work.field_data[arrays.WORKING_FACTORS]]
    record = {"factors": factors, "scan_spacing_mm": scan.round(6).tolist(),
              "spacing_mm": step.round(6).tolist(), "scan_voxels": int(ct.n_points),
              "voxels": int(work.n_points)}
    text = (f"the scan's {ct.n_points / 1e6:.0f} million voxels of {_mm(scan)} mm were "
            f"averaged in blocks of {'x'.join(map(str, factors))} voxels: the model is made "
            f"from {work.n_points / 1e6:.1f} million voxels of {_mm(step)} mm")
    return record, text


def _mm(values):
    return "x".join(f"{v:g}" for v in np.round(values, 4))


def _block_means(vol, factors):
    """Means over blocks of ``factors`` voxels (float32; a partial block at an axis's far
    end: the mean of the voxels it holds), one axis at a time, as sums of strided views."""
    out = vol
    for axis, f in enumerate(factors):
        if f == 1:
            continue
        n = out.shape[axis]
        m = -(-n // f)  # blocks along the axis
        index = [slice(None)] * 3
        index[axis] = slice(0, None, f)
        acc = np.array(out[tuple(index)], dtype=np.float64 if out.dtype == np.float64
                       else np.float32)  # (first voxel of every block)
        for k in range(1, f):
            index[axis] = slice(k, None, f)
            part = out[tuple(index)]
            head = [slice(None)] * 3
            head[axis] = slice(0, part.shape[axis])
            acc[tuple(head)] += part
        count = np.full(m, float(f), dtype=acc.dtype)
        count[-1] = n - f * (m - 1)
        shape = [1, 1, 1]
        shape[axis] = m
        acc /= count.reshape(shape)
        out = acc
    return np.asarray(out, dtype=np.float32)
