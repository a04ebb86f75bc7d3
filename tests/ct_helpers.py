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
