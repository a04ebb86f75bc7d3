"""The tilt of the dental arches, and label grids turned level with them and back.

:func:`pvcmf.filters.find_jaws` works on axial slices: the occlusal level, the Le Fort I
level above the nasal floor, the footprint of the arches seen from above. A head scanned
tilted (chin down to keep the orbits out of the beam, chin up on a headrest) tilts the
arches against those slices, and a tilt of 20 degrees moves the occlusal plane by 15 mm
from the front teeth to the last molars, more than a crown's height. :func:`occlusal_tilt`
finds the plane of the teeth, the axis of least spread of the tooth voxels (an arch, or two
in occlusion, is a broad flat horseshoe: 45-55 mm wide and deep, the crowns 8-20 mm high),
and :class:`Level` turns a voxel grid so that plane is axial (nearest voxel) and the labels
found there back onto the grid (a voxel the round trip misses takes the label of the
nearest labelled level voxel around its point). :func:`arch_pose` takes the plane of the
upper arch, fixed to the skull (the lower jaw may hang open), split off on the axial
slices and again on the slices turned by that first estimate. The Le Fort I level is then
parallel to the occlusal plane, as the osteotomy is cut (Bell, J Oral Surg 1975).

Delegates to :func:`numpy.linalg.eigh` (principal axes), :func:`scipy.ndimage.affine_transform`
(order 0: labels stay labels).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from .. import arrays
from .dental_arches import dental_arches

log = logging.getLogger(__name__)

__all__ = ["Level", "MIN_ARCH_SPAN_MM", "arch_pose", "arch_span", "check_pose", "occlusal_tilt",
           "pitch"]

#: tilt (degrees) below which the grid is left as it is: the occlusal plane then rises
#: less than 4 mm (half a crown's height) over the arch's 45 mm depth, which the axial
#: occlusal slice tolerates
MIN_TILT_DEG = 5.0
#: tilt (degrees) above which the teeth's plane is not the occlusal plane: a head lies in a
#: scanner at most this far from its axial plane, while a row of front teeth alone stands
#: upright, its plane near vertical
MAX_TILT_DEG = 45.0
#: cant (degrees) of the occlusal plane to the Frankfort horizontal, descending anteriorly,
#: and its spread among adults (Downs, Am J Orthod 1948: mean 9.3, range 1.5-14)
OCCLUSAL_CANT = 9.3
OCCLUSAL_CANT_SD = 3.8
#: smallest spread (mm, standard deviation) of the teeth across their row, in their plane,
#: that defines a plane to plan in: an arch 45-55 mm wide and deep spreads 12-15 mm both
#: ways, a row of front teeth (the rest missing, or below the teeth level) a few mm, and
#: the plane of a row may turn about it
MIN_ARCH_SPAN_MM = 8.0
#: pitch and roll (degrees) searched for the first estimate of the arches' plane
SEARCH_PITCH = 40.0
SEARCH_ROLL = 20.0
#: an arch is flat: its second spread (standard deviation) at least this times its least
#: (a few front teeth alone are a short row, not a plane)
FLAT = 2.0


def occlusal_tilt(teeth, spacing):
    """Rotation that makes the plane of the tooth voxels axial, and its angle (degrees).

    Parameters
    ----------
    teeth : numpy.ndarray
        3-D boolean mask of the tooth voxels.
    spacing : sequence of 3 float
        Voxel size (mm).

    Returns
    -------
    (numpy.ndarray or None, float)
        The 3x3 rotation (the least rotation taking the plane's normal to +z; None where
        the teeth are not a flat arch, fewer than 10 voxels, or tilted less than
        ``MIN_TILT_DEG`` or more than ``MAX_TILT_DEG``) and the tilt in degrees (0 where
        there is no plane).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.jaw_pose import occlusal_tilt
    >>> teeth = np.zeros((40, 40, 40), bool)
    >>> i, j = np.meshgrid(np.arange(5, 35), np.arange(5, 35), indexing="ij")
    >>> teeth[i, j, (20 + 0.3 * (j - 20)).round().astype(int)] = True   # 16.7 degrees
    >>> turn, deg = occlusal_tilt(teeth, (1.0, 1.0, 1.0))
    >>> round(deg)
    17
    """
    normal = _plane_normal(teeth, spacing)
    if normal is None:
        return None, 0.0
    deg = _tilt(normal)
    if deg < MIN_TILT_DEG or deg > MAX_TILT_DEG:
        log.debug("jaw_pose: the teeth's plane tilts %.1f degrees: left as it is", deg)
        return None, deg
    return _onto_z(normal), deg


def arch_pose(teeth, hard, spacing):
    """The rotation that levels the dental arches of a box, its tilt, and the arches.

    A first estimate is the direction, within ``SEARCH_PITCH`` degrees of pitch and
    ``SEARCH_ROLL`` of roll from the axial normal, along which the tooth voxels' heights
    bunch most (:func:`_densest_normal`: two arches apart or in occlusion are each a thin
    layer along their common normal); without one (the axial normal itself), the plane of
    the upper arch split on the axial slices. The plane is then that of the upper arch
    (:func:`~pvcmf.filters.dental_arches.dental_arches`; all the teeth where it has fewer
    than 10 voxels) split on the box turned by the first estimate: the upper arch is fixed
    to the skull, while the lower jaw may hang open.

    Returns
    -------
    (numpy.ndarray or None, float, tuple or None, numpy.ndarray or None)
        The rotation (None: leave the box as it is: the teeth are no flat arch, or tilt
        less than ``MIN_TILT_DEG`` or more than ``MAX_TILT_DEG``), the tilt (degrees),
        when the box stays its :func:`~pvcmf.filters.dental_arches.dental_arches`, and the
        plane's unit normal (None where the teeth are no flat arch).
    """
    spacing = np.asarray(spacing, dtype=float)
    first = _onto_z(_densest_normal(np.argwhere(teeth) * spacing, float(spacing.max())))
    if _tilt(first[2]) < MIN_TILT_DEG:
        arches = dental_arches(teeth, hard, spacing)
        normal = _plane_normal(_plane_teeth(arches, teeth), spacing)
        if normal is None or not MIN_TILT_DEG <= _tilt(normal) <= MAX_TILT_DEG:
            return None, 0.0 if normal is None else _tilt(normal), arches, normal
        first = _onto_z(normal)
    level = Level(teeth.shape, spacing, first)
    teeth1 = level.forward(teeth.view(np.uint8)) > 0
    arches1 = dental_arches(teeth1, level.forward(hard.view(np.uint8)) > 0, spacing,
                            quiet=True)
    normal = _plane_normal(_plane_teeth(arches1, teeth1), spacing)
    turn = None if normal is None else _onto_z(normal) @ first
    tilt = 0.0 if turn is None else _tilt(turn[2])
    if turn is None or not MIN_TILT_DEG <= tilt <= MAX_TILT_DEG:
        return None, tilt, dental_arches(teeth, hard, spacing), \
            None if turn is None else turn[2].copy()
    return turn, tilt, None, turn[2].copy()


def arch_span(teeth, spacing, normal):
    """Spread (mm, standard deviation) of the tooth voxels ``teeth`` across their row within
    the plane of unit ``normal``: the smaller principal spread of their projection on it."""
    points = np.argwhere(teeth) * np.asarray(spacing, dtype=float)
    if len(points) < 3:
        return 0.0
    points = points - points.mean(axis=0)
    normal = np.asarray(normal, dtype=float)
    flat = points - np.outer(points @ normal, normal)
    spread = np.linalg.eigvalsh(np.cov(flat.T))  # (the normal's own is ~0)
    return float(np.sqrt(max(spread[1], 0.0)))


def pitch(normal):
    """Pitch (degrees) of a plane of unit ``normal`` from the axial plane: positive where it
    descends anteriorly (+y)."""
    return float(np.degrees(np.arctan2(normal[1], normal[2])))


def check_pose(labels, axes="image"):
    """Warn where the upper dental arch (``arrays.ARCH_PITCH`` of ``labels``) pitches
    outside the occlusal plane's usual cant to the Frankfort horizontal, ``OCCLUSAL_CANT``
    +- three ``OCCLUSAL_CANT_SD``: the head lies tilted in the scan, and a plan's directions
    (forward, up) are the image's axes, not the face's. A plan in the face's ``axes``
    (``"occlusal"``, ``"frankfort"``: :mod:`pvcmf.filters.face_axes`) follows the head: the
    tilt is then only logged. Returns the warning, or None."""
    if arrays.ARCH_PITCH not in labels.field_data:
        return None
    angle = float(np.asarray(labels.field_data[arrays.ARCH_PITCH]).ravel()[0])
    off = angle - OCCLUSAL_CANT
    if abs(off) <= 3.0 * OCCLUSAL_CANT_SD:
        return None
    message = (f"find_jaws: the upper dental arch pitches {angle:.0f} degrees from the image's "
               f"axial plane, {abs(off):.0f} degrees {'chin down' if off > 0 else 'chin up'} "
               f"of its usual cant to the Frankfort horizontal ({OCCLUSAL_CANT:g} +- "
               f"{OCCLUSAL_CANT_SD:g} degrees): the head lies tilted in the scan, and the "
               "plan's directions (forward, up) are the image's axes, not the face's")
    if axes != "image":
        log.info("check_pose: the head lies %.0f degrees %s of the usual occlusal cant; the "
                 "plan's moves are in its %s axes, which follow the face", abs(off),
                 "chin down" if off > 0 else "chin up", axes)
        return None
    message += ' (a plan with axes = "occlusal" or "frankfort" follows the face)'
    log.warning(message)
    return message


def _plane_teeth(arches, teeth):
    """The upper arch's teeth, or all the teeth where it has fewer than 10 voxels."""
    upper = arches[1]
    return upper if np.count_nonzero(upper) >= 10 else teeth


def _plane_normal(teeth, spacing):
    """Unit normal (n_z >= 0) of the tooth voxels' plane: their axis of least spread; None
    where they are fewer than 10 or not flat (``FLAT``)."""
    points = np.argwhere(teeth) * np.asarray(spacing, dtype=float)
    if len(points) < 10:
        return None
    spread, axes = np.linalg.eigh(np.cov((points - points.mean(axis=0)).T))
    spread = np.sqrt(np.maximum(spread, 0.0))
    if spread[1] < FLAT * spread[0]:
        return None
    return axes[:, 0] * (1.0 if axes[2, 0] >= 0 else -1.0)


def _tilt(normal):
    """Angle (degrees) of a unit vector from +z (a rotation's last row: of its pre-image)."""
    return float(np.degrees(np.arccos(np.clip(normal[2], -1.0, 1.0))))


def _densest_normal(points, bin_mm):
    """The candidate normal (pitch and roll on a 2.5 degree grid) along which the points'
    heights fall into the fewest ``bin_mm`` bins: the largest sum of squared bin counts
    (the least tilted among equals). At most 5000 points are used."""
    points = points[::max(1, len(points) // 5000)]
    pitch = np.radians(np.arange(-SEARCH_PITCH, SEARCH_PITCH + 1e-9, 2.5))
    roll = np.radians(np.arange(-SEARCH_ROLL, SEARCH_ROLL + 1e-9, 2.5))
    p, r = (a.ravel() for a in np.meshgrid(pitch, roll, indexing="ij"))
    normals = np.column_stack([np.cos(p) * np.sin(r), -np.sin(p), np.cos(p) * np.cos(r)])
    heights = (points - points.mean(axis=0)) @ normals.T
    bins = np.floor((heights - heights.min(axis=0)) / bin_mm).astype(np.int64)
    width = int(bins.max()) + 1
    counts = np.bincount((bins + width * np.arange(len(normals))).ravel(),
                         minlength=width * len(normals)).reshape(len(normals), width)
    score = (counts.astype(float) ** 2).sum(axis=1)
    best = np.flatnonzero(score >= score.max() * (1 - 1e-9))
    return normals[best[np.argmax(normals[best, 2])]]


def _onto_z(n):
    """The least rotation taking the unit vector ``n`` (n_z > 0) onto +z (Rodrigues)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(n, z), float(n @ z)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


class Level:
    """A voxel grid of ``shape`` and ``spacing`` turned by ``rotation`` about its centre onto
    a grid of the same spacing that holds all of it.

    >>> import numpy as np
    >>> from pvcmf.filters.jaw_pose import Level
    >>> turn = np.array([[1.0, 0, 0], [0, 0.8, -0.6], [0, 0.6, 0.8]])
    >>> grid = np.zeros((20, 30, 10), np.uint8)
    >>> grid[5:15, 5:25, 3:7] = 2
    >>> level = Level(grid.shape, (1.0, 1.0, 1.0), turn)
    >>> back = level.back(level.forward(grid), grid > 0)
    >>> bool(np.array_equal(back, grid))
    True
    """

    def __init__(self, shape, spacing, rotation):
        self.shape = tuple(int(n) for n in shape)
        self.spacing = np.asarray(spacing, dtype=float)
        self.rotation = np.asarray(rotation, dtype=float)
        self.centre = (np.asarray(self.shape) - 1) * self.spacing / 2.0
        corners = np.array(np.meshgrid(*[[0, n - 1] for n in self.shape], indexing="ij"))
        corners = corners.reshape(3, -1).T * self.spacing
        turned = (corners - self.centre) @ self.rotation.T + self.centre
        self.low = turned.min(axis=0)
        self.level_shape = tuple(int(n) for n in
                                 np.ceil((turned.max(axis=0) - self.low) / self.spacing) + 1)

    def forward(self, grid, cval=0):
        """``grid`` (labels or a mask) on the level grid, nearest voxel; ``cval`` outside."""
        s, r = self.spacing, self.rotation
        # level index j -> point q = low + j s -> grid point p = R^T (q - c) + c -> index p / s
        matrix = (r.T * s[None, :]) / s[:, None]
        offset = (r.T @ (self.low - self.centre) + self.centre) / s
        return ndimage.affine_transform(np.asarray(grid), matrix, offset=offset,
                                        output_shape=self.level_shape, order=0, cval=cval,
                                        mode="constant")

    def back(self, labels, keep):
        """Level-grid ``labels`` back on the grid, nearest voxel, on the voxels of ``keep``
        only (0 elsewhere); a voxel of ``keep`` whose nearest level voxel is 0 (the round
        trip's rounding at a surface) takes the label of the nearest non-zero voxel of the
        eight level voxels around its point (0 if none is)."""
        s, r = self.spacing, self.rotation
        matrix = (r * s[None, :]) / s[:, None]
        offset = (self.centre - r @ self.centre - self.low) / s
        labels = np.asarray(labels)
        out = ndimage.affine_transform(labels, matrix, offset=offset, output_shape=self.shape,
                                       order=0, cval=0, mode="constant")
        out[~keep] = 0
        missed = np.argwhere(keep & (out == 0))
        if len(missed):
            at = missed @ matrix.T + offset  # their points on the level grid (index units)
            base = np.floor(at).astype(np.int64)
            best = np.full(len(at), np.inf)
            found = np.zeros(len(at), dtype=labels.dtype)
            for corner in np.ndindex(2, 2, 2):  # eight neighbours, each vectorised
                idx = base + np.asarray(corner)
                inside = np.all((idx >= 0) & (idx < np.asarray(self.level_shape)), axis=1)
                value = np.zeros(len(at), dtype=labels.dtype)
                value[inside] = labels[tuple(idx[inside].T)]
                dist = (((idx - at) * s) ** 2).sum(axis=1)
                take = (value > 0) & (dist < best)
                best[take], found[take] = dist[take], value[take]
            out[tuple(missed.T)] = found
        log.debug("jaw_pose: %d of %d voxels took a neighbour's label", len(missed),
                  int(keep.sum()))
        return out
