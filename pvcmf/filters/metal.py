"""Metal and its streak artefacts in a head CT (dental fillings, crowns, plates).

Metal (far above any tissue, :data:`pvcmf.arrays.METAL`) throws bright and dark streaks
across the axial slices it lies in. Within ``zone`` mm of the metal, in the same slices (the
streaks are in-plane), :func:`clean_streaks` keeps as hard tissue only what survives an
in-plane opening by a 3x3 square (streaks are one or two voxels wide, bone and teeth wider)
and is connected to the skeleton or to the metal; as air only what survives the same
opening of the air (dark streaks through the tongue and cheeks become soft tissue again).

Delegates to :mod:`scipy.ndimage` (opening, dilation, distance transform, labelling).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

log = logging.getLogger(__name__)

#: in-plane reach (mm) of the streaks handled around the metal
ZONE_MM = 30.0
_SQUARE = np.ones((3, 3, 1), dtype=bool)
_CUBE = np.ones((3, 3, 3), dtype=bool)


def streak_zone(metal, spacing, zone=ZONE_MM, dz=2.0):
    """Box and mask of the voxels within ``zone`` mm in-plane (``dz`` mm across) of metal.

    Returns
    -------
    (tuple of slice, numpy.ndarray)
        The bounding box (index slices) and the zone mask inside it.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.metal import streak_zone
    >>> m = np.zeros((50, 50, 10), bool); m[25, 25, 5] = True
    >>> box, zone = streak_zone(m, (1.0, 1.0, 1.0), zone=10.0, dz=1.0)
    >>> zone.shape, int(zone[:, :, 2].sum())
    ((21, 21, 3), 317)
    """
    spacing = np.asarray(spacing, float)
    reach = np.ceil(np.array([zone, zone, dz]) / spacing).astype(int)
    idx = np.nonzero(metal)
    box = tuple(slice(max(int(i.min()) - r, 0), min(int(i.max()) + r + 1, n))
                for i, r, n in zip(idx, reach, metal.shape))
    sub = metal[box]
    if reach[2] > 0:
        sub = ndimage.maximum_filter1d(sub.astype(np.uint8), 2 * reach[2] + 1, axis=2) > 0
    dist = ndimage.distance_transform_edt(~sub, sampling=(spacing[0], spacing[1], 1e6))
    return box, dist <= zone


def clean_streaks(vol, head, hard, metal, spacing, thresholds, zone=ZONE_MM):
    """Remove bright streaks from the hard tissue and dark streaks from the air near metal.

    Parameters
    ----------
    vol : numpy.ndarray
        CT values (3-D).
    head, hard, metal : numpy.ndarray of bool
        Head, hard-tissue and metal masks of ``vol``'s shape.
    spacing : sequence of float
        Voxel size (mm).
    thresholds : dict
        Unused keys aside, the segmentation thresholds (for the log).
    zone : float
        In-plane reach (mm) of the streaks.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        New head and hard masks (copies).
    """
    head, hard = head.copy(), hard.copy()
    box, near = streak_zone(metal, spacing, zone)
    h, k, m = head[box], hard[box], metal[box]
    # bright streaks: thin hard tissue, or hard tissue not joined to the skeleton / metal
    cand = k & near & ~m
    thick = ndimage.binary_opening(cand, _SQUARE)
    keep = cand & ndimage.binary_dilation(thick | m, _SQUARE)
    support = (k & ~near) | m
    lab, _ = ndimage.label(keep | support, _CUBE)
    joined = np.zeros(lab.max() + 1, dtype=bool)
    joined[np.unique(lab[support])] = True
    joined[0] = False
    keep &= joined[lab]
    bright = cand & ~keep
    # dark streaks: thin air inside the head's outline in the metal's slices
    outline = _fill_slices(h | k)
    air = ~h & near & outline
    open_air = ndimage.binary_opening(air, _SQUARE)
    dark = air & ~ndimage.binary_dilation(open_air, _SQUARE)
    k[bright] = False
    h |= dark
    hard[box], head[box] = k, h
    log.info("metal: %.1f mL (>= %.0f), %d bright and %d dark streak voxels relabelled "
             "soft tissue", float(metal.sum() * np.prod(spacing)) / 1000.0,
             thresholds.get("metal", np.nan), int(bright.sum()), int(dark.sum()))
    return head, hard


def _fill_slices(mask):
    """Per-slice (axis 2) hole filling."""
    st = np.zeros((3, 3, 3), dtype=bool)
    st[:, :, 1] = ndimage.generate_binary_structure(2, 1)
    lab, _ = ndimage.label(~mask, structure=st)
    border = np.unique(np.concatenate([lab[0].ravel(), lab[-1].ravel(), lab[:, 0].ravel(),
                                       lab[:, -1].ravel()]))
    inside = np.ones(lab.max() + 1, dtype=bool)
    inside[border] = False
    inside[0] = False
    return mask | inside[lab]


def report(metal, spacing):
    """Log where the metal is; return no warnings (metal is expected, e.g. fillings)."""
    idx = np.nonzero(metal)
    log.info("metal: %d voxels in slices %d..%d", int(metal.sum()), int(idx[2].min()),
             int(idx[2].max()))
    return []
