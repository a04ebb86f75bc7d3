"""Face proportions of a virtual patient, to compare with a real face's.

:func:`face_proportions` measures, on a virtual patient's truth labels and soft-tissue
landmarks, the proportions that :data:`pvcmf.datasets.template.face.REAL_FACE` gives for a
real face (ArtiSynth face mesh, Visible Human female skin): nose and lip projection, forehead
slope, face height over width, lower over middle face height, vault breadth over face width
and the length of neck below the chin. Delegates to numpy.
"""

from __future__ import annotations

import numpy as np

from .. import arrays
from .template.face import REAL_FACE

__all__ = ["REAL_FACE", "face_proportions", "outside_real"]


def _head(case):
    t = case.truth
    return (np.asarray(t[arrays.TISSUE]) != arrays.AIR).reshape(t.dimensions[::-1])


def _index(case, value, axis):
    t = case.truth
    return int(np.clip(round((value - t.origin[axis]) / t.spacing[axis]), 0,
                       t.dimensions[axis] - 1))


def face_proportions(case):
    """Proportions of a virtual patient's face (mm and ratios; keys of ``REAL_FACE``).

    Parameters
    ----------
    case : pvcmf.datasets.Case
        A virtual patient (its ``truth`` labels and soft-tissue ``landmarks``).

    Returns
    -------
    dict
        ``nose`` (pronasale ahead of subnasale, mm), ``upper_lip`` (labrale superius ahead
        of subnasale, mm), ``lower_lip`` (labrale inferius ahead of soft pogonion, mm),
        ``forehead`` (soft glabella ahead of the skin 20 mm above it, mm), ``neck`` (head
        below the soft menton, mm), ``height_width`` (soft nasion-menton height over the
        soft bizygomatic width), ``lower_face`` (subnasale-menton over nasion-subnasale
        height), ``vault_width`` (head breadth 60 mm above the tragion over the soft
        bizygomatic width).

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.datasets.phantom_face import face_proportions
    >>> p = face_proportions(pvcmf.datasets.phantom(patient=1, spacing=3.0))
    >>> sorted(p) == sorted(pvcmf.datasets.phantom_face.REAL_FACE)
    True
    """
    lm = case.landmarks
    head = _head(case)  # (z, y, x)
    t = case.truth
    ix0 = _index(case, 0.0, 0)
    ys = t.origin[1] + t.spacing[1] * np.arange(t.dimensions[1])
    xs = t.origin[0] + t.spacing[0] * np.arange(t.dimensions[0])
    zs = t.origin[2] + t.spacing[2] * np.arange(t.dimensions[2])

    def front(z):  # most anterior skin at the midline, height z
        row = head[_index(case, z, 2), :, ix0]
        return float(ys[np.flatnonzero(row)].max()) if row.any() else np.nan

    def breadth(z):
        sl = head[_index(case, z, 2)].any(axis=0)
        return float(np.ptp(xs[np.flatnonzero(sl)])) if sl.any() else np.nan

    g, n, sn = lm["soft_tissue_glabella"], lm["soft_tissue_nasion"], lm["subnasale"]
    me = lm["soft_tissue_menton"]
    width = float(lm["soft_tissue_zygion_left"][0] - lm["soft_tissue_zygion_right"][0])
    bottom = float(zs[np.flatnonzero(head.any(axis=(1, 2)))].min())
    return {
        "nose": float(lm["pronasale"][1] - sn[1]),
        "upper_lip": float(lm["labrale_superius"][1] - sn[1]),
        "lower_lip": float(lm["labrale_inferius"][1] - lm["soft_tissue_pogonion"][1]),
        "forehead": float(g[1] - front(g[2] + 20.0)),
        "neck": float(me[2] - bottom),
        "height_width": float((n[2] - me[2]) / width),
        "lower_face": float((sn[2] - me[2]) / (n[2] - sn[2])),
        "vault_width": breadth(lm["tragion_left"][2] + 60.0) / width,
    }


def outside_real(proportions):
    """The proportions outside the real face's ranges: name -> (value, (lo, hi))."""
    return {k: (v, REAL_FACE[k]) for k, v in proportions.items()
            if not REAL_FACE[k][0] <= v <= REAL_FACE[k][1]}
