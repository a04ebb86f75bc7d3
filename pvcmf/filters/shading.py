"""Slow shading of a cone-beam CT flattened: the same tissue at the same value across the field.

A cone-beam scanner's reconstruction darkens the middle of its field (cupping: scatter and
beam hardening) and shades it from top to bottom, slowly across the head: the bone and
soft-tissue levels that :func:`pvcmf.filters.segment` places on the image's histogram then
hold at the edge of the field and miss in its middle, or the reverse. A CT scanner's HU do
not drift so; a cone-beam scan's grey values (``units='rescale'``) do.

:func:`flatten_shading` models the shading as a smooth multiplicative field on the
attenuation (``HU + 1000``) and divides it out: N4 (Tustison et al. 2010, SimpleITK's
``N4BiasFieldCorrectionImageFilter``), which finds the smooth field that makes the
histogram of the tissue (the voxels denser than half-way from air to water) sharpest, on a
copy pooled to about ``shrink_mm`` mm (coarser where that copy would exceed
``MAX_FIT_VOXELS``), the field then evaluated on the full grid. The field
is scaled to a median of 1 over the tissue, so the image keeps its overall level; its
spread is recorded in the field data :data:`~pvcmf.arrays.SHADING` (5th and 95th
percentiles over the tissue).

N4 sharpens the histogram of the anatomy as it is: where a region holds mostly fat and
another mostly muscle, part of that difference goes into the field too. It is therefore
run where the grey values are a cone-beam scanner's (:func:`pvcmf.pipeline.simulate`'s
``shading='auto'``), not on a CT's HU.

Delegates to SimpleITK (N4, shrinking) and numpy.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..progress import Progress

log = logging.getLogger(__name__)

__all__ = ["flatten_shading", "SHRINK_MM"]

#: voxel size (mm) of the pooled copy the field is fitted on: the shading changes over
#: centimetres
SHRINK_MM = 4.0
#: most voxels of the pooled copy (its voxels grow beyond ``shrink_mm`` for a larger image):
#: N4's time grows with them
MAX_FIT_VOXELS = 1 << 16
#: N4's iterations per fitting level (coarse to fine)
ITERATIONS = (50, 40, 30)
#: attenuation (HU + 1000) above which a voxel is tissue: half-way from air to water
TISSUE_ATTENUATION = 500.0


def _check(ct, shrink_mm):
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"ct must be a pyvista.ImageData, got {type(ct).__name__}")
    values = arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                  producer="pvcmf.read_ct")
    dims = tuple(int(d) for d in ct.dimensions)
    if min(dims) < 2:
        raise ValueError(f"ct must be a 3-D image (at least 2 voxels per axis), got "
                         f"dimensions {dims}")
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise ValueError(f"ct array 'ct' must be finite, got {bad} NaN/inf value(s)")
    try:
        shrink = float(shrink_mm)
    except (TypeError, ValueError):
        shrink = np.nan
    if isinstance(shrink_mm, bool) or not np.isfinite(shrink) or shrink <= 0:
        raise ValueError(f"shrink_mm must be a positive number of mm, got {shrink_mm!r}")
    return np.asarray(values, dtype=np.float32).reshape(dims, order="F"), shrink


def flatten_shading(ct, *, shrink_mm=SHRINK_MM, progress_bar=False):
    """The CT with its slow multiplicative shading divided out (module docs).

    Parameters
    ----------
    ct : pyvista.ImageData
        3-D image with a float point array ``ct`` in HU (finite values), e.g. a cone-beam
        scan after :func:`pvcmf.filters.standardize` with ``units='rescale'``.
    shrink_mm : float, default :data:`SHRINK_MM`
        Voxel size (mm) of the pooled copy the field is fitted on.
    progress_bar : bool, default False
        Show a progress bar over the fit and the full-grid division.

    Returns
    -------
    pyvista.ImageData
        A new image (``ct`` kept) on the same grid with the flattened ``ct`` (float32), the
        other point arrays dropped, the field data of ``ct`` plus
        :data:`~pvcmf.arrays.SHADING` (the field's 5th and 95th percentiles over the
        tissue: ``[1, 1]`` for no shading).

    Raises
    ------
    TypeError
        If ``ct`` is not an ImageData.
    ValueError
        If the ``ct`` array is missing, not float or not finite, the image is not 3-D, it
        holds no tissue (nothing denser than half-way from air to water), or ``shrink_mm``
        is not a positive number.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.shading import flatten_shading
    >>> img = pv.ImageData(dimensions=(40, 40, 20), spacing=(2, 2, 2))
    >>> x, y, _ = (img.points - img.center).T
    >>> cup = 1 - 0.15 * np.clip(1 - (x**2 + y**2) / 40**2, 0, 1)  # darker in the middle
    >>> img["ct"] = np.where(x**2 + y**2 < 36**2, 1040 * cup - 1000, -1000).astype("f4")
    >>> out = flatten_shading(img)
    >>> inner = (x**2 + y**2 < 8**2) & (abs(_) < 10)
    >>> rim = (x**2 + y**2 > 28**2) & (x**2 + y**2 < 32**2) & (abs(_) < 10)
    >>> def gap(a):
    ...     return float(np.mean(a[rim]) - np.mean(a[inner]))
    >>> round(gap(img["ct"])) > 50, abs(gap(out["ct"])) < 0.25 * gap(img["ct"])
    (True, True)
    """
    vol, shrink = _check(ct, shrink_mm)
    spacing = np.asarray(ct.spacing, dtype=float)
    with Progress(2, "flatten shading", enabled=progress_bar) as bar:
        out, spread = _flatten(ct, vol, shrink, spacing, bar)
    log.info("flatten_shading: a field from %.3f to %.3f (5th to 95th percentile over the "
             "tissue) divided out", *spread)
    return out


def _flatten(ct, vol, shrink, spacing, bar):
    """The flattened image and the field's spread (:func:`flatten_shading`)."""
    import SimpleITK as sitk

    attenuation = np.maximum(vol + 1000.0, 1.0)  # N4 works on positive values
    tissue = attenuation > TISSUE_ATTENUATION
    if not tissue.any():
        raise ValueError("flatten_shading: the image holds no tissue (nothing above -500 HU)")
    image = sitk.GetImageFromArray(np.ascontiguousarray(attenuation.transpose(2, 1, 0)))
    image.SetSpacing(tuple(float(s) for s in spacing))
    mask = sitk.GetImageFromArray(np.ascontiguousarray(tissue.transpose(2, 1, 0)).view(np.uint8))
    mask.CopyInformation(image)
    least = np.ceil(np.cbrt(vol.size / MAX_FIT_VOXELS))
    factors = [int(max(1, min(max(round(shrink / s), least), n // 4 or 1)))
               for s, n in zip(spacing, vol.shape)]
    n4 = sitk.N4BiasFieldCorrectionImageFilter()
    n4.SetMaximumNumberOfIterations(list(ITERATIONS))
    n4.Execute(sitk.Shrink(image, factors), sitk.Shrink(mask, factors))
    bar.step("fitted")
    field = np.exp(sitk.GetArrayFromImage(n4.GetLogBiasFieldAsImage(image))).transpose(2, 1, 0)
    field /= float(np.median(field[tissue]))
    flat = (attenuation / field - 1000.0).astype(np.float32)
    flat[vol <= -1000.0] = vol[vol <= -1000.0]  # padding and clipped air stay as they were
    out = pv.ImageData(dimensions=ct.dimensions, spacing=ct.spacing, origin=ct.origin)
    out.direction_matrix = ct.direction_matrix
    out[arrays.CT] = flat.ravel(order="F")
    for name in ct.field_data.keys():
        out.field_data[name] = np.array(ct.field_data[name], copy=True)
    spread = np.percentile(field[tissue], [5.0, 95.0])
    out.field_data[arrays.SHADING] = spread
    bar.step("divided")
    return out, spread
