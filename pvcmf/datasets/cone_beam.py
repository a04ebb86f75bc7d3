"""A real CT as a cone-beam scanner would hold the face: a round field around the jaws.

:func:`cone_beam_field` cuts a cylinder about a vertical axis out of a CT in HU and turns
its values into a cone-beam scanner's: grey values that are a line of the HU (not HU),
optionally the reconstruction's cupping (the attenuation darker on the field's axis) and
noise, and a constant outside the field. pvcmf's tests and ``benchmarks/cone_beam.py`` feed
such fields of the real heads to the pipeline: a cone-beam scan of the same head, with no
cranial cavity, whose truth is the whole CT.

Delegates to numpy.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .. import arrays

__all__ = ["cone_beam_field"]


def cone_beam_field(ct, centre, *, radius=80.0, below=60.0, above=80.0, behind=10.0,
                    cupping=0.0, noise=0.0, slope=0.6, offset=200.0, outside=None, seed=0):
    """``ct`` (HU) in a cone-beam scanner's field and grey values.

    Parameters
    ----------
    ct : pyvista.ImageData
        A CT in HU (point array ``ct``), in the patient frame (z superior).
    centre : sequence of 3 float
        Where the field is centred (mm), e.g. the teeth's centre.
    radius : float, default 80
        The field's radius (mm) about a vertical axis ``behind`` mm behind ``centre``.
    below, above : float, default 60, 80
        How far (mm) the field reaches below and above ``centre``.
    cupping : float, default 0
        The attenuation (HU + 1000) darkened by this share on the field's axis, less toward
        its edge: ``1 - cupping (1 - r^2 / radius^2)``.
    noise : float, default 0
        Standard deviation of Gaussian noise added to the grey values.
    slope, offset : float, default 0.6, 200
        Grey value = ``slope * HU + offset``.
    outside : float, optional
        The constant written outside the field (default: the lowest grey value inside it).
    seed : int, default 0
        Seed of the noise.

    Returns
    -------
    pyvista.ImageData
        A new image on the field's box of ``ct``'s grid, point array ``ct`` (float32).

    Raises
    ------
    TypeError
        If ``ct`` is not an ImageData.
    ValueError
        If the ``ct`` array is missing, a length is not positive, ``cupping`` is not in
        [0, 1), or the field misses the image.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.datasets.cone_beam import cone_beam_field
    >>> ct = pv.ImageData(dimensions=(60, 60, 40), spacing=(2, 2, 2))
    >>> ct["ct"] = np.full(ct.n_points, 40.0, dtype=np.float32)
    >>> field = cone_beam_field(ct, ct.center, radius=30, below=20, above=20, behind=0)
    >>> field.dimensions, float(field["ct"].max())
    ((32, 32, 22), 224.0)
    """
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"ct must be a pyvista.ImageData, got {type(ct).__name__}")
    values = arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                  producer="pvcmf.read_ct")
    for name, value in (("radius", radius), ("below", below), ("above", above)):
        if not float(value) > 0:
            raise ValueError(f"{name} must be > 0 mm, got {value!r}")
    if not 0.0 <= float(cupping) < 1.0:
        raise ValueError(f"cupping must be in [0, 1), got {cupping!r}")
    vol = np.asarray(values).reshape(ct.dimensions, order="F")
    sp, org = np.asarray(ct.spacing, dtype=float), np.asarray(ct.origin, dtype=float)
    axis = np.asarray(centre, dtype=float) - (0.0, float(behind), 0.0)
    reach = np.array([radius, radius, 0.0])
    lo = np.maximum(np.floor((axis - reach - (0, 0, below) - org) / sp).astype(int), 0)
    hi = np.minimum(np.ceil((axis + reach + (0, 0, above) - org) / sp).astype(int) + 1,
                    vol.shape)
    if np.any(hi - lo < 2):
        raise ValueError(f"the field about {tuple(np.round(axis, 1))} misses the image "
                         f"(bounds {ct.bounds})")
    box = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float64)
    gx, gy = np.meshgrid(org[0] + sp[0] * np.arange(lo[0], hi[0]),
                         org[1] + sp[1] * np.arange(lo[1], hi[1]), indexing="ij")
    r2 = ((gx - axis[0]) ** 2 + (gy - axis[1]) ** 2) / float(radius) ** 2
    inside = r2 <= 1.0
    shade = 1.0 - float(cupping) * (1.0 - np.minimum(r2, 1.0))
    grey = slope * ((box + 1000.0) * shade[:, :, None] - 1000.0) + offset
    if noise:
        grey = grey + np.random.default_rng(seed).normal(0.0, float(noise), grey.shape)
    fill = grey[inside].min() if outside is None else float(outside)
    grey = np.where(inside[:, :, None], grey, fill)
    out = pv.ImageData(dimensions=grey.shape, spacing=tuple(sp), origin=tuple(org + lo * sp))
    out[arrays.CT] = grey.astype(np.float32).ravel(order="F")
    return out
