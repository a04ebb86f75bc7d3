"""CT volumes for the orientation tests: the voxel array of an image, an image of an array,
and an image stored as a file with turned axes and scanner units would hold it."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from pvcmf import arrays


def volume(image):
    return np.asarray(image[arrays.CT]).reshape(image.dimensions, order="F")


def image_of(vol, spacing=(1.0, 1.0, 1.0)):
    img = pv.ImageData(dimensions=vol.shape, spacing=spacing)
    img[arrays.CT] = np.asarray(vol, dtype=np.float32).ravel(order="F")
    return img


def stored_as(image, code, add=0.0):
    """The image as a file would hold it if its axes pointed as ``code`` (inverse of
    reorient), plus ``add`` (scanner units)."""
    letters = {"L": (0, 1), "R": (0, -1), "A": (1, 1), "P": (1, -1), "S": (2, 1), "I": (2, -1)}
    picks = [letters[c] for c in code]
    order = [p[0] for p in picks]
    vol = np.transpose(volume(image), order)
    for i, (_, sign) in enumerate(picks):
        if sign < 0:
            vol = np.flip(vol, i)
    return image_of(vol + add, np.asarray(image.spacing)[order])


def turned_labels(labels, R, pad=12):
    """``labels``'s tissue turned by the rotation ``R`` about the grid's centre (nearest
    voxel), on a grid ``pad`` voxels wider each way so that nothing leaves it."""
    from scipy import ndimage

    v = np.pad(np.asarray(labels[arrays.TISSUE]).reshape(labels.dimensions, order="F"), pad)
    s = np.asarray(labels.spacing, float)
    c = (np.asarray(v.shape) - 1) / 2
    matrix = (R.T * s[None, :]) / s[:, None]
    out = ndimage.affine_transform(v, matrix, offset=c - matrix @ c, order=0, cval=0)
    img = pv.ImageData(dimensions=v.shape, spacing=labels.spacing,
                       origin=np.asarray(labels.origin) - pad * s)
    img[arrays.TISSUE] = out.ravel(order="F")
    return img


def cone_beam_field(data_dir, name, radius=80.0, below=60.0, above=80.0, behind=10.0,
                    cupping=0.0):
    """The real head CT ``name`` of the data folder (skipped where it lacks it) as a cone-beam
    scanner holds a face: a cylinder of ``radius`` mm about a vertical axis ``behind`` mm
    behind the teeth's centre, from ``below`` to ``above`` mm about it (no cranial cavity),
    in grey values that are not HU (0.6 HU + 200), the minimum outside the field, on the
    field's box; ``cupping``: the attenuation (HU + 1000) darkened by this share on the
    field's axis, less toward its edge (``1 - cupping (1 - r^2 / radius^2)``). The teeth are
    found on a 2 mm copy (``segment``)."""
    import pytest

    import pvcmf
    from pvcmf.filters.orientation import standardize

    path = data_dir / name
    if not path.exists():
        pytest.skip(f"{path} not in the data folder")
    ct, _ = standardize(pvcmf.read_ct(path))
    half = image_of(volume(ct)[::2, ::2, ::2], np.asarray(ct.spacing) * 2)
    half.origin = ct.origin
    labels = half.cmf.segment()
    teeth = np.asarray(labels.points)[np.asarray(labels[arrays.TISSUE]) == arrays.TEETH]
    return _field(ct, np.median(teeth, axis=0), radius, below, above, behind, cupping)


def _field(ct, teeth, radius, below, above, behind, cupping=0.0):
    """``ct`` (HU) in the field of :func:`cone_beam_field` about the teeth's centre
    ``teeth`` (mm)."""
    vol = volume(ct)
    sp, org = np.asarray(ct.spacing), np.asarray(ct.origin)
    axis = np.asarray(teeth) - (0.0, behind, 0.0)
    lo = np.maximum(np.floor((axis - (radius, radius, below) - org) / sp).astype(int), 0)
    hi = np.minimum(np.ceil((axis + (radius, radius, above) - org) / sp).astype(int) + 1,
                    vol.shape)
    box = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    gx, gy = np.meshgrid(org[0] + sp[0] * np.arange(lo[0], hi[0]),
                         org[1] + sp[1] * np.arange(lo[1], hi[1]), indexing="ij")
    r2 = ((gx - axis[0]) ** 2 + (gy - axis[1]) ** 2) / radius**2
    inside = r2 <= 1.0
    shade = 1.0 - cupping * (1.0 - np.minimum(r2, 1.0))
    grey = 0.6 * ((box + 1000.0) * shade[:, :, None] - 1000.0) + 200.0
    grey = np.where(inside[:, :, None], grey, grey[inside].min())
    out = image_of(grey, sp)
    out.origin = org + lo * sp
    return out
