"""CT volumes for the tests: the voxel array of an image, an image of an array, an image
stored as a file with turned axes and scanner units would hold it, labels turned, and the
real heads as cone-beam fields (each head read once per test run)."""

from __future__ import annotations

import functools

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
                    cupping=0.0, beside=0.0, noise=0.0):
    """The real head CT ``name`` of the data folder (skipped where it lacks it) as a cone-beam
    scanner holds a face (:func:`pvcmf.datasets.cone_beam_field`): a cylinder of ``radius``
    mm about a vertical axis ``behind`` mm behind the teeth's centre, from ``below`` to
    ``above`` mm about it (no cranial cavity), in grey values 0.6 HU + 200, the lowest
    inside the field outside it; ``cupping`` as there; ``beside``: the axis that far (mm)
    toward +x of the teeth's centre; ``noise``: Gaussian noise (grey values, seed 0). The
    teeth are found on a 2 mm copy (``segment``)."""
    import pytest

    import pvcmf

    path = data_dir / name
    if not path.exists():
        pytest.skip(f"{path} not in the data folder")
    ct, teeth = _head_and_teeth(str(path))
    return pvcmf.datasets.cone_beam_field(ct, teeth + (beside, 0.0, 0.0), radius=radius,
                                          below=below, above=above, behind=behind,
                                          cupping=cupping, noise=noise)


@functools.lru_cache(maxsize=2)
def _head_and_teeth(path):
    """The CT at ``path`` in HU and the patient frame, and its teeth's centre (mm), read once
    per test run (the fields of :func:`cone_beam_field` are cut from it)."""
    import pvcmf
    from pvcmf.filters.orientation import standardize

    ct, _ = standardize(pvcmf.read_ct(path))
    half = image_of(volume(ct)[::2, ::2, ::2], np.asarray(ct.spacing) * 2)
    half.origin = ct.origin
    labels = half.cmf.segment()
    teeth = np.asarray(labels.points)[np.asarray(labels[arrays.TISSUE]) == arrays.TEETH]
    return ct, np.median(teeth, axis=0)
