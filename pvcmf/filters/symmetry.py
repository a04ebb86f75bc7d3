"""The head's mirror plane: its left-right direction from the symmetry of its bones.

A head lies turned about its vertical axis in a scanner as often as it lies tilted, so the
image's left-right axis is not the face's. The skull is close to mirror symmetric about its
midsagittal plane; :func:`mirror_plane` finds that plane as the one whose mirror image of
the hard tissue (bone, teeth, metal) overlaps the hard tissue most:

1. the hard tissue (without the mandible where the labels' ``bone`` names it: the lower jaw
   may hang open or deviated in the scan, and its asymmetry is often what the operation
   corrects) on a grid of about :data:`GRID_MM` (blocks of whole voxels averaged,
   the hard tissue's box only), blurred by a Gaussian of :data:`SIGMA_MM` so that the
   overlap is a smooth function of the plane;
2. up to :data:`SAMPLES` of its voxels (a fixed draw), mirrored about candidate planes
   that contain a given vertical direction (the upper dental arch's normal for a plan's
   ``axes = "occlusal"``): the plane turned by ``theta`` about that direction from the
   image's left-right axis and shifted by ``offset`` from the hard tissue's centroid;
3. the overlap (the mean blurred hard tissue at the mirrored voxels, those that fall where
   the scan saw: a head cut on one side by the image's end or its field of view is judged
   on what both sides hold) on a coarse grid of
   ``theta`` within ``max_turn`` and offsets within :data:`OFFSET_MM`, then refined from the
   best (Nelder-Mead).

The overlap is reported against the hard tissue's overlap with itself (``overlap``: 1 for
a perfectly symmetric head). A plane whose mirror image overlaps less than
:data:`MIN_OVERLAP` of that, or one found at the edge of the turns searched, is refused:
the hard tissue holds no mirror plane near the image's (half a head in the field of view,
a scan of something else).

Delegates to :func:`scipy.ndimage.gaussian_filter`, :func:`scipy.ndimage.map_coordinates`
and :func:`scipy.optimize.minimize`; the box and the block means to the helpers of
:mod:`pvcmf.filters.bone_segments` and :mod:`pvcmf.filters.resolution`.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
import pyvista as pv
from scipy import ndimage, optimize

from .. import arrays
from .bone_segments import _bounds
from .resolution import _block_means

log = logging.getLogger(__name__)

__all__ = ["GRID_MM", "MAX_TURN_DEG", "MIN_OVERLAP", "TURN_WARN_DEG", "MirrorPlane",
           "check_turn", "mirror_plane"]

#: spacing (mm) the hard tissue is averaged to before the search (a voxel coarser stays)
GRID_MM = 2.0
#: Gaussian blur (mm) of the averaged hard tissue: the overlap varies smoothly with the plane
SIGMA_MM = 2.0
#: hard-tissue voxels mirrored per candidate plane (a fixed draw where there are more)
SAMPLES = 8000
#: turns (degrees) about the vertical direction searched either side of the image's axis
MAX_TURN_DEG = 30.0
#: offsets (mm) of the plane from the hard tissue's centroid on the coarse grid
OFFSET_MM = 12.0
#: turn (degrees) of the head about its vertical axis beyond which a plan in the image's axes
#: is warned about: its "forward" then goes sideways by more than 9 % of the move
TURN_WARN_DEG = 5.0
#: least share of the mirrored voxels that must fall where the scan saw (inside the image
#: and its field of view) for a plane to count
MIN_SEEN = 0.5
#: least overlap of the mirror image, as a share of the hard tissue's overlap with itself (a
#: skull's bones, teeth and their metal, streaks included, are far more symmetric than this;
#: half a head is not)
MIN_OVERLAP = 0.6


class MirrorPlane(NamedTuple):
    """The head's mirror plane: ``direction``, its unit normal (the head's left-right
    direction, on the image's +x side); ``point``, a point on it (mm); ``turn``, degrees
    it turns about the vertical direction from the image's left-right axis; ``overlap``,
    the mirror image's overlap with the hard tissue as a share of the tissue's overlap
    with itself."""

    direction: np.ndarray
    point: np.ndarray
    turn: float
    overlap: float


def _unit_vertical(normal):
    n = np.asarray(normal, dtype=float)
    if n.shape != (3,) or not np.isfinite(n).all() or np.linalg.norm(n) == 0:
        raise ValueError(f"normal must be 3 finite numbers, not all zero; got {normal!r}")
    n = n / np.linalg.norm(n)
    across = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(across) < 0.5:
        raise ValueError(f"normal {np.round(n, 3).tolist()} is within 30 degrees of the "
                         "image's left-right axis: expected the head's vertical direction")
    return n, across / np.linalg.norm(across)


def _hard_grid(labels):
    """``(blurred, origin, spacing, voxels)``: the hard tissue's box averaged to about
    :data:`GRID_MM`, blurred, its grid, and the indices of its mostly-hard voxels."""
    tissue = np.asarray(arrays.require_array(labels, arrays.TISSUE, "point", dtype="u",
                                             producer="segment"))
    dims = tuple(int(d) for d in labels.dimensions)
    hard = np.isin(tissue, arrays.HARD_LABELS)
    if arrays.BONE in labels.point_data:  # the lower jaw may hang open or deviated
        hard &= np.asarray(labels.point_data[arrays.BONE]) != arrays.MANDIBLE
    hard = hard.reshape(dims, order="F")
    if not hard.any():
        raise ValueError("mirror_plane: labels hold no hard tissue (tissue BONE/TEETH/METAL)")
    spacing = np.asarray(labels.spacing, dtype=float)
    f = np.maximum(1, np.round(GRID_MM / spacing).astype(int))
    box = _bounds(hard, 0)
    mean = _block_means(hard[box], f)  # (a partial block at the far end: what it holds)
    lo = np.array([b.start for b in box])
    step = spacing * f
    origin = np.asarray(labels.origin, float) + (lo + (f - 1) / 2.0) * spacing
    pad = int(np.ceil(3 * SIGMA_MM / step.min())) + 1  # room for the blur
    mean = np.pad(mean, pad)
    origin = origin - pad * step
    blurred = ndimage.gaussian_filter(mean, SIGMA_MM / step, mode="constant")
    return blurred, origin, step, np.argwhere(mean >= 0.5)


def _known(labels):
    """Which points (n, 3) lie where the scan saw: inside the image, on the head's side of
    every plane where the scan cut it flat (``arrays.SCAN_CUTS``) and inside the round
    field of view of the slices where it cut the head (``arrays.SCAN_FOV``). A mirror
    image that falls beyond them says nothing about the head's symmetry."""
    spacing, origin = np.asarray(labels.spacing, float), np.asarray(labels.origin, float)
    lo = origin - 0.5 * spacing
    hi = origin + (np.asarray(labels.dimensions) - 0.5) * spacing
    fd = labels.field_data
    cuts = np.asarray(fd[arrays.SCAN_CUTS], float).reshape(-1, 8) if arrays.SCAN_CUTS in fd \
        else np.zeros((0, 8))
    fov = np.asarray(fd[arrays.SCAN_FOV], float).reshape(-1, 4) if arrays.SCAN_FOV in fd \
        else np.zeros((0, 4))

    def known(points):
        ok = ((points >= lo) & (points <= hi)).all(axis=1)
        for axis, sign, at in cuts[:, :3]:
            ok &= sign * (points[:, int(axis)] - at) <= 0.0
        if len(fov):
            row = np.abs(points[:, 2, None] - fov[None, :, 0]).argmin(axis=1)
            near = np.abs(points[:, 2] - fov[row, 0]) <= 0.5 * spacing[2]
            off = np.hypot(points[:, 0] - fov[row, 1], points[:, 1] - fov[row, 2]) > fov[row, 3]
            ok &= ~(near & off)
        return ok

    return known


def _checked_inputs(labels, max_turn):
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    if isinstance(max_turn, bool) or not np.isfinite(max_turn) or not 0 < max_turn < 90:
        raise ValueError(f"max_turn must be degrees in (0, 90), got {max_turn!r}")


def mirror_plane(labels, normal=(0.0, 0.0, 1.0), *, max_turn=MAX_TURN_DEG):
    """The mirror plane of the head's hard tissue that contains the direction ``normal``.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``tissue`` (:func:`pvcmf.filters.segment`); with ``bone`` (bone
        segments, :func:`pvcmf.filters.cut_bones`), the mandible is left out.
    normal : sequence of 3 floats
        The head's vertical direction in the image, which the plane contains (the upper
        dental arch's normal, :func:`pvcmf.filters.bone_segments.occlusal_normal`); the
        image's z by default.
    max_turn : float
        Degrees the plane may turn about ``normal`` from the image's left-right axis.

    Returns
    -------
    MirrorPlane
        Its normal (``direction``, the head's left-right direction), a point on it, its
        turn and its overlap.

    Raises
    ------
    ValueError
        No hard tissue, too little of it (fewer than 50 voxels of :data:`GRID_MM`), a
        ``normal`` near the left-right axis, or no mirror plane within ``max_turn``
        (found at its edge, or overlapping less than :data:`MIN_OVERLAP`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> labels = pv.ImageData(dimensions=(61, 61, 21), origin=(-30.0, -30.0, -10.0))
    >>> x, y, z = labels.points.T
    >>> a = np.radians(10.0)  # a mirror symmetric body turned 10 degrees
    >>> u, v = np.cos(a) * x + np.sin(a) * y, -np.sin(a) * x + np.cos(a) * y
    >>> body = ((u / 20) ** 2 + (v / 8) ** 2 < 1) | ((np.abs(u) - 8) ** 2 + (v - 10) ** 2 < 16)
    >>> labels[arrays.TISSUE] = np.where(body & (np.abs(z) < 6), arrays.BONE_TISSUE,
    ...                                  arrays.AIR).astype(np.uint8)
    >>> round(mirror_plane(labels).turn)  # the plane x = 0, turned 10 degrees
    10
    """
    _checked_inputs(labels, max_turn)
    n, e1 = _unit_vertical(normal)
    e2 = np.cross(n, e1)
    blurred, origin, step, voxels = _hard_grid(labels)
    if len(voxels) < 50:
        raise ValueError(f"mirror_plane: {len(voxels)} voxels of hard tissue at {GRID_MM:g} mm; "
                         "at least 50 are needed to find a mirror plane")
    if len(voxels) > SAMPLES:
        voxels = voxels[np.random.default_rng(0).choice(len(voxels), SAMPLES, replace=False)]
    points = origin + voxels * step
    centre = points.mean(axis=0)

    known = _known(labels)

    def overlap(theta_deg, offset):
        t = np.radians(theta_deg)
        m = np.cos(t) * e1 + np.sin(t) * e2
        mirrored = points - 2.0 * ((points - centre) @ m - offset)[:, None] * m
        seen = known(mirrored)
        if seen.mean() < MIN_SEEN:  # most of the mirror image beyond what the scan saw
            return 0.0
        return float(ndimage.map_coordinates(blurred, ((mirrored[seen] - origin) / step).T,
                                             order=1, mode="constant").mean())

    turns = np.arange(-max_turn, max_turn + 1e-9, 2.0)
    offsets = np.arange(-OFFSET_MM, OFFSET_MM + 1e-9, 3.0)
    grid = np.array([[overlap(t, d) for d in offsets] for t in turns])
    i, j = np.unravel_index(np.argmax(grid), grid.shape)
    start = np.array([turns[i], offsets[j]])
    found = optimize.minimize(lambda x: -overlap(*x), start, method="Nelder-Mead",
                              options={"xatol": 0.02, "fatol": 1e-7,
                                       "initial_simplex": [start, start + (1, 0), start + (0, 1)]})
    turn, offset = (float(v) for v in found.x)
    itself = float(ndimage.map_coordinates(blurred, ((points - origin) / step).T, order=1,
                                           mode="constant").mean())
    share = -float(found.fun) / itself
    if abs(turn) >= max_turn - 1.0 or share < MIN_OVERLAP:
        raise ValueError(
            f"mirror_plane: the hard tissue holds no mirror plane within {max_turn:g} degrees "
            f"of the image's left-right axis (best: turned {turn:.1f} degrees, its mirror "
            f"image overlapping {share:.0%} of the tissue's overlap with itself; at least "
            f"{MIN_OVERLAP:.0%}): half a head in the field of view, or no head")
    t = np.radians(turn)
    direction = np.cos(t) * e1 + np.sin(t) * e2
    log.debug("mirror_plane: turned %.2f degrees about the vertical, overlap %.2f", turn, share)
    return MirrorPlane(direction, centre + offset * direction, turn, share)


def check_turn(labels, axes="image"):
    """Warn where the head lies turned about its vertical axis (the upper dental arch's
    normal, ``arrays.ARCH_NORMAL``, where ``labels`` hold it; else the image's z) by more
    than :data:`TURN_WARN_DEG` from the image's axes, for a plan in the image's ``axes``:
    its forward then goes partly sideways. A plan in the face's axes follows the head
    (nothing is measured). Returns the warning, or None (also where the hard tissue holds
    no mirror plane, which is logged)."""
    if axes != "image":
        return None
    fd = labels.field_data
    vertical = (np.asarray(fd[arrays.ARCH_NORMAL], dtype=float).ravel()
                if arrays.ARCH_NORMAL in fd else (0.0, 0.0, 1.0))
    try:
        mirror = mirror_plane(labels, vertical)
    except ValueError as exc:
        log.info("check_turn: %s", exc)
        return None
    if abs(mirror.turn) <= TURN_WARN_DEG:
        return None
    side = 100.0 * np.sin(np.radians(abs(mirror.turn)))
    message = (f"check_turn: the head lies turned {mirror.turn:+.0f} degrees about its vertical "
               f"axis from the image's (its skull's mirror plane): the plan's forward, in the "
               f"image's axes, goes {side:.0f} % of the move sideways "
               '(a plan with axes = "occlusal" or "frankfort" follows the face)')
    log.warning(message)
    return message
