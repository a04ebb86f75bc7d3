"""Surgical plans: which bone segment moves, and how (paper 000 Table II).

A :class:`Plan` is one or more :class:`Osteotomy`. Each moves one bone segment
(``"maxilla"``: Le Fort I, ``"mandible"``: bilateral sagittal split) rigidly by a
rotation about a pivot followed by a translation.

Conventions (as Table II states them)
-------------------------------------
``translation`` is (horizontal, vertical, anterior-posterior) in mm, mapped to patient
(x, z, y) by :data:`pvcmf.arrays.PLAN_AXES`: + is patient-left, superior, anterior.
``rotation`` is in degrees about the same three axes (horizontal x = pitch, vertical z =
yaw, anterior-posterior y = roll), right-handed, applied in that order (x, then z, then y)
about ``pivot`` (default: the segment's centroid).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import arrays


@dataclass(frozen=True)
class Osteotomy:
    """A rigid move of one bone segment.

    Parameters
    ----------
    segment : str
        Bone segment name, a key of :data:`pvcmf.arrays.BONE_LABELS` other than
        ``"none"`` and ``"cranium"``.
    translation : tuple of float
        (horizontal, vertical, anterior-posterior) in mm.
    rotation : tuple of float
        Degrees about the (horizontal, vertical, anterior-posterior) axes.
    pivot : tuple of float or None
        Patient-frame xyz in mm; ``None`` means the segment's centroid.
    """

    segment: str
    translation: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (0.0, 0.0, 0.0)
    pivot: tuple | None = None

    def __post_init__(self):
        movable = [k for k in arrays.BONE_LABELS if k not in ("none", "cranium")]
        if self.segment not in movable:
            raise ValueError(f"segment must be one of {movable}, got {self.segment!r}")
        for name in ("translation", "rotation"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(v) for v in value))
        if self.pivot is not None:
            pivot = np.asarray(self.pivot, dtype=float)
            if pivot.shape != (3,) or not np.all(np.isfinite(pivot)):
                raise ValueError(f"pivot must be None or 3 finite numbers, got {self.pivot!r}")
            object.__setattr__(self, "pivot", tuple(float(v) for v in pivot))

    @property
    def segment_id(self):
        """Bone label id of the moved segment."""
        return arrays.BONE_LABELS[self.segment]

    def matrix(self, centroid=None):
        """Return the 4x4 rigid transform in the patient frame (mm).

        Parameters
        ----------
        centroid : array_like, optional
            Pivot to use when ``pivot`` is ``None``; defaults to the origin.
        """
        pivot = np.asarray(self.pivot if self.pivot is not None else
                           (centroid if centroid is not None else (0.0, 0.0, 0.0)), dtype=float)
        rot = np.eye(3)
        for plan_axis, angle in zip(range(3), np.radians(self.rotation)):
            axis = arrays.PLAN_AXES[plan_axis]
            c, s = np.cos(angle), np.sin(angle)
            i, j = [k for k in range(3) if k != axis]
            r = np.eye(3)
            r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
            if axis == 1:  # keep right-handedness for rotation about y (z -> x)
                r[i, j], r[j, i] = s, -s
            rot = r @ rot
        shift = np.zeros(3)
        shift[list(arrays.PLAN_AXES)] = self.translation
        out = np.eye(4)
        out[:3, :3] = rot
        out[:3, 3] = pivot - rot @ pivot + shift
        return out


@dataclass(frozen=True)
class Plan:
    """A surgical plan: one or more osteotomies."""

    osteotomies: tuple = field(default_factory=tuple)
    name: str = ""

    def __post_init__(self):
        osteotomies = tuple(self.osteotomies)
        for o in osteotomies:
            if not isinstance(o, Osteotomy):
                raise TypeError(f"osteotomies must be Osteotomy objects, got {type(o).__name__}")
        segments = [o.segment for o in osteotomies]
        if len(set(segments)) != len(segments):
            raise ValueError(f"each segment may move once per plan, got {segments}")
        object.__setattr__(self, "osteotomies", osteotomies)


#: paper 000 Table II, one plan per patient
TABLE_II = {
    1: Plan((Osteotomy("maxilla", (6.0, 5.0, -4.0), (0.0, 2.0, 5.0)),), name="patient 1"),
    2: Plan((Osteotomy("maxilla", (-0.27, 0.13, 4.98), (0.0, 0.0, 1.31)),), name="patient 2"),
    3: Plan((Osteotomy("mandible", (1.07, -0.74, 5.47), (0.0, 2.71, 0.0)),), name="patient 3"),
    4: Plan((Osteotomy("mandible", (0.67, 0.61, -3.24), (0.0, 0.0, 0.0)),), name="patient 4"),
}
