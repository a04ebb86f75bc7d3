"""The facial muscle atlas: a canonical head, its muscles and landmarks, and fitting (paper 000, sec. II).

An :class:`Atlas` holds a head's landmarks, its twelve facial muscles (the six of paper
000 Fig. 2a on both sides, closed surfaces named as :data:`pvcmf.arrays.MUSCLES`) and its
skin and skull surfaces, all in the atlas frame (mm, patient axes). :func:`default` builds
the project's atlas from the canonical head this package owns:

- :mod:`pvcmf.atlas.shapes`: signed-distance primitives;
- :mod:`pvcmf.atlas.skull` and :mod:`pvcmf.atlas.soft_tissue`: the head's anatomy;
- :mod:`pvcmf.atlas.muscles` and :mod:`pvcmf.atlas.landmarks`: muscles and landmarks;
- :mod:`pvcmf.atlas.raster`: label images of the head through a point map;
- :mod:`pvcmf.atlas.fit` and :mod:`pvcmf.atlas.surfaces`: fitting the atlas to a patient.

The virtual patients of :mod:`pvcmf.datasets` are built from this head plus perturbations.
"""

from __future__ import annotations

import functools

import numpy as np

from ..tps import landmark_arrays
from .fit import Atlas, FitInfo
from .landmarks import landmarks as _head_landmarks
from .muscles import muscle_surfaces as _head_muscle_surfaces
from .raster import label_image as _head_label_image
from .surfaces import FIT_SPACING, label_surfaces

#: spacing (mm) at which the head's muscles are contoured (0.5 costs 6x the time for a
#: ~0.1 mm gain on 3-5 mm thick muscles)
MUSCLE_SPACING = 1.0


@functools.lru_cache(maxsize=1)
def _default_parts():
    lms = _head_landmarks()
    muscles = _head_muscle_surfaces(spacing=MUSCLE_SPACING)
    labels = _head_label_image(FIT_SPACING)
    skin, skull = label_surfaces(labels, spacing=FIT_SPACING)
    return Atlas(lms, muscles, skin, skull)


def default():
    """The project's facial muscle atlas, built from the canonical head of this package.

    The head is built once per process and cached; each call returns an independent copy
    (a few milliseconds).

    Returns
    -------
    Atlas

    Examples
    --------
    >>> import pvcmf.atlas
    >>> at = pvcmf.atlas.default()
    >>> len(at.muscles)
    12
    """
    return _default_parts().copy()


def dice(a, b):
    """Dice overlap ``2|A & B| / (|A| + |B|)`` of two boolean masks (1.0 if both empty)."""
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    n = a.sum() + b.sum()
    return 1.0 if n == 0 else float(2.0 * (a & b).sum() / n)


__all__ = ["Atlas", "FIT_SPACING", "FitInfo", "MUSCLE_SPACING", "default", "dice",
           "label_surfaces", "landmark_arrays"]
