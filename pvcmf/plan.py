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

Cuts
----
``cut`` says where the segment is in the bone label image. Empty (the default) means
the image already labels it (``bone == segment id``, as the virtual patients do). Otherwise
it is a list of planes ``(point, normal)``: the segment is the bone on the side every
normal points to (a Le Fort I plane above the upper tooth apices with its normal
pointing down for the maxilla; the two sagittal split planes of a bilateral sagittal split
with normals pointing forward for the mandible's tooth-bearing part). See
:func:`pvcmf.filters.cut_bones`.

Files
-----
Plans are read and written as TOML or JSON (:meth:`Plan.from_file`, :meth:`Plan.to_file`,
:func:`read_plan`, :func:`write_plan`)::

    name = "patient 1"

    [[osteotomy]]
    segment = "maxilla"              # "maxilla" (Le Fort I) or "mandible" (BSSO)
    translation = [6.0, 5.0, -4.0]   # mm, (horizontal, vertical, anterior-posterior)
    rotation = [0.0, 2.0, 5.0]       # degrees about the same axes
    # pivot = [0.0, 60.0, -30.0]     # optional, patient xyz in mm (default: centroid)

    [[osteotomy.cut]]                # optional planes; none = use the bone label
    point = [0.0, 0.0, -20.0]
    normal = [0.0, 0.0, -1.0]

Axes
----
``axes`` says which three directions the numbers are in. ``"image"`` (the default): the
image's own axes, as above. A head the scanner holds tilted (chin down, rolled) then gets
its moves in the scanner's directions, not the face's; ``"occlusal"`` puts them in the
plane of the upper dental arch found in the image (vertical: its normal; horizontal: the
image's left-right direction in that plane; anterior-posterior: the third), and
``"frankfort"`` in the Frankfort horizontal through the porions and the orbitales (the
landmarks of the label image). :func:`pvcmf.filters.plan_axes` turns them into the image's
axes; a pivot and the cut planes stay points and planes of the image::

    name = "advancement along the occlusal plane"
    axes = "occlusal"

Unknown keys, non-finite numbers, rotations over :data:`MAX_ROTATION_DEG`, translations
over :data:`MAX_TRANSLATION_MM` and segments
the bone label image does not contain (:meth:`Plan.check_segments`) raise
:class:`ValueError` naming the key and the value. Reading delegates to :mod:`tomllib`
(``tomli`` on Python 3.10) and :mod:`json`; writing is atomic (temp file + ``os.replace``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import arrays
from ._atomic import write_text

#: largest rotation (degrees, about any one axis) a plan may ask for
MAX_ROTATION_DEG = 30.0
#: largest translation (mm, along any one axis) a plan may ask for
MAX_TRANSLATION_MM = 50.0
#: segments a plan may move
MOVABLE_SEGMENTS = tuple(k for k in arrays.BONE_LABELS if k not in ("none", "cranium"))
_PLAN_KEYS = ("name", "axes", "osteotomy")
#: directions a plan's translations and rotations can be given in (:attr:`Plan.axes`)
AXES = ("image", "occlusal", "frankfort")
_OSTEOTOMY_KEYS = ("segment", "translation", "rotation", "pivot", "cut", "matrix")
_CUT_KEYS = ("point", "normal")


def _check_keys(data, allowed, where, required=()):
    """Raise a ValueError naming ``where`` if ``data`` is no dict or has unknown keys."""
    if not isinstance(data, dict):
        raise ValueError(f"{where} must be a table/object, got {data!r}")
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ValueError(f"{where} has unknown key(s) {unknown}; allowed keys are {list(allowed)}")
    missing = [k for k in required if k not in data]
    if missing:
        raise ValueError(f"{where} is missing key(s) {missing}")


def _rotation3(value):
    """``value`` as a 3x3 rotation, or a ValueError."""
    m = np.asarray(value, dtype=float)
    if (m.shape != (3, 3) or not np.all(np.isfinite(m))
            or not np.allclose(m.T @ m, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0):
        raise ValueError(f"axes must be a 3x3 rotation matrix, got {value!r}")
    return m


def _vector3(value, name):
    """Return ``value`` as 3 finite floats or raise a ValueError naming ``name``."""
    try:
        vec = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}") from None
    if vec.shape != (3,) or not np.all(np.isfinite(vec)):
        raise ValueError(f"{name} must be 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in vec)


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
    cut : tuple of (point, normal) pairs
        Planes that cut the segment out of the bone label (see the module docstring);
        empty means the bone label already holds the segment.

    Raises
    ------
    ValueError
        Unknown segment, non-finite numbers, a rotation above :data:`MAX_ROTATION_DEG`,
        a translation above :data:`MAX_TRANSLATION_MM`
        or a zero-length cut normal.

    Examples
    --------
    >>> from pvcmf.plan import Osteotomy
    >>> o = Osteotomy("mandible", translation=(0.0, 0.0, 5.0))
    >>> o.matrix()[:3, 3].tolist()   # 5 mm anterior = +y
    [0.0, 5.0, 0.0]
    """

    segment: str
    translation: tuple = (0.0, 0.0, 0.0)
    rotation: tuple = (0.0, 0.0, 0.0)
    pivot: tuple | None = None
    cut: tuple = ()

    def __post_init__(self):
        if self.segment not in MOVABLE_SEGMENTS:
            raise ValueError(
                f"segment must be one of {list(MOVABLE_SEGMENTS)}, got {self.segment!r}"
            )
        for name in ("translation", "rotation"):
            object.__setattr__(self, name, _vector3(getattr(self, name), name))
        big = [r for r in self.rotation if abs(r) > MAX_ROTATION_DEG]
        if big:
            raise ValueError(
                f"rotation must be within +-{MAX_ROTATION_DEG:g} degrees about each axis "
                f"(a larger angle is almost surely a unit error: degrees are expected), "
                f"got {self.rotation!r} for segment {self.segment!r}"
            )
        far = [t for t in self.translation if abs(t) > MAX_TRANSLATION_MM]
        if far:
            raise ValueError(
                f"translation must be within +-{MAX_TRANSLATION_MM:g} mm along each axis "
                f"(MAX_TRANSLATION_MM; a larger move is almost surely a unit error: mm are "
                f"expected), got {self.translation!r} for segment {self.segment!r}"
            )
        if self.pivot is not None:
            try:
                pivot = _vector3(self.pivot, "pivot")
            except ValueError:
                raise ValueError(
                    f"pivot must be None or 3 finite numbers, got {self.pivot!r}"
                ) from None
            object.__setattr__(self, "pivot", pivot)
        planes = []
        for i, plane in enumerate(self.cut):
            try:
                point, normal = plane
            except (TypeError, ValueError):
                raise ValueError(
                    f"cut[{i}] must be a (point, normal) pair, got {plane!r}"
                ) from None
            point = _vector3(point, f"cut[{i}].point")
            normal = np.asarray(_vector3(normal, f"cut[{i}].normal"))
            length = float(np.linalg.norm(normal))
            if length < 1e-12:
                raise ValueError(f"cut[{i}].normal must be non-zero, got {tuple(normal)!r}")
            planes.append((point, tuple(float(v) for v in normal / length)))
        object.__setattr__(self, "cut", tuple(planes))

    def to_dict(self):
        """Return the osteotomy as plain Python data (the file format)."""
        out = {"segment": self.segment, "translation": list(self.translation),
               "rotation": list(self.rotation)}
        if self.pivot is not None:
            out["pivot"] = list(self.pivot)
        if self.cut:
            out["cut"] = [{"point": list(p), "normal": list(n)} for p, n in self.cut]
        return out

    @classmethod
    def from_dict(cls, data, where="osteotomy"):
        """Build an osteotomy from plain data, rejecting unknown keys."""
        _check_keys(data, _OSTEOTOMY_KEYS, where)
        if "segment" not in data:
            raise ValueError(f"{where} needs a 'segment' (one of {list(MOVABLE_SEGMENTS)})")
        cut = data.get("cut", ())
        if not isinstance(cut, (list, tuple)):
            raise ValueError(f"{where}.cut must be a list of planes, got {cut!r}")
        planes = []
        for i, plane in enumerate(cut):
            _check_keys(plane, _CUT_KEYS, f"{where}.cut[{i}]", required=_CUT_KEYS)
            planes.append((plane["point"], plane["normal"]))
        if "matrix" in data:  # a 4x4 rigid transform instead of translation + rotation
            both = sorted({"translation", "rotation"} & set(data))
            if both:
                raise ValueError(f"{where} gives 'matrix' and {both}: use one or the other")
            try:
                return cls.from_matrix(data["segment"], data["matrix"], pivot=data.get("pivot"),
                                       cut=tuple(planes))
            except ValueError as err:
                raise ValueError(f"{where}: {err}") from None
        try:
            return cls(
                segment=data["segment"],
                translation=data.get("translation", (0.0, 0.0, 0.0)),
                rotation=data.get("rotation", (0.0, 0.0, 0.0)),
                pivot=data.get("pivot"),
                cut=tuple(planes),
            )
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None

    @classmethod
    def from_matrix(cls, segment, matrix, *, pivot=None, cut=(), tol=1e-6):
        """An osteotomy from a 4x4 rigid transform in the patient frame (mm).

        The rotation is decomposed into the plan's angles (about x, then z, then y) and
        ``pivot`` (default the origin) is kept, so :meth:`matrix` gives ``matrix`` back.

        Raises
        ------
        ValueError
            ``matrix`` is not 4x4 and finite, its last row is not ``0 0 0 1``, or its 3x3
            part is not a rotation (orthonormal, determinant +1, within ``tol``).

        Examples
        --------
        >>> import numpy as np
        >>> from pvcmf.plan import Osteotomy
        >>> m = Osteotomy("maxilla", (1.0, 2.0, 3.0), (4.0, -5.0, 6.0)).matrix()
        >>> bool(np.allclose(Osteotomy.from_matrix("maxilla", m).matrix(), m))
        True
        """
        from scipy.spatial.transform import Rotation

        m = np.asarray(matrix, dtype=float) if np.ndim(matrix) else np.full(0, np.nan)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"matrix must be 4x4 finite numbers, got {matrix!r}")
        if not np.allclose(m[3], [0, 0, 0, 1], atol=tol):
            raise ValueError(f"matrix must have last row [0, 0, 0, 1], got {m[3].tolist()}")
        rot = m[:3, :3]
        dev = float(np.abs(rot.T @ rot - np.eye(3)).max())
        if dev > tol or np.linalg.det(rot) < 0:
            raise ValueError(
                f"matrix must be rigid (a rotation and a translation): its 3x3 part deviates "
                f"from orthonormal by {dev:.3g} and has determinant {np.linalg.det(rot):.6g}")
        pivot_ = np.zeros(3) if pivot is None else np.asarray(_vector3(pivot, "pivot"))
        angles = Rotation.from_matrix(rot).as_euler("xzy", degrees=True)  # R = Ry Rz Rx
        shift = m[:3, 3] - pivot_ + rot @ pivot_
        return cls(segment, translation=tuple(shift[list(arrays.PLAN_AXES)]),
                   rotation=tuple(angles), pivot=tuple(pivot_), cut=tuple(cut))

    @property
    def segment_id(self):
        """Bone label id of the moved segment."""
        return arrays.BONE_LABELS[self.segment]

    def matrix(self, centroid=None, axes=None):
        """Return the 4x4 rigid transform in the patient frame (mm).

        Parameters
        ----------
        centroid : array_like, optional
            Pivot to use when ``pivot`` is ``None``; defaults to the origin.
        axes : array_like, optional
            3x3 rotation whose columns are the plan's (x, y, z) directions in the image
            (:func:`pvcmf.filters.plan_axes`): the translation and the rotation are given in
            them; default the image's own axes.
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
        if axes is not None:
            frame = _rotation3(axes)
            rot, shift = frame @ rot @ frame.T, frame @ shift
        out = np.eye(4)
        out[:3, :3] = rot
        out[:3, 3] = pivot - rot @ pivot + shift
        return out


@dataclass(frozen=True)
class Plan:
    """A surgical plan: one or more osteotomies, their moves given in ``axes``
    (:data:`AXES`: ``"image"``, ``"occlusal"`` or ``"frankfort"``; see the module docs).

    Examples
    --------
    >>> import os, tempfile
    >>> from pvcmf.plan import Plan, TABLE_II
    >>> path = os.path.join(tempfile.mkdtemp(), "plan.toml")
    >>> _ = TABLE_II[1].to_file(path)
    >>> Plan.from_file(path) == TABLE_II[1]
    True
    """

    osteotomies: tuple = field(default_factory=tuple)
    name: str = ""
    axes: str = "image"

    def __post_init__(self):
        if self.axes not in AXES:
            raise ValueError(f"axes must be one of {list(AXES)}, got {self.axes!r}")
        osteotomies = tuple(self.osteotomies)
        for o in osteotomies:
            if not isinstance(o, Osteotomy):
                raise TypeError(f"osteotomies must be Osteotomy objects, got {type(o).__name__}")
        segments = [o.segment for o in osteotomies]
        if len(set(segments)) != len(segments):
            raise ValueError(f"each segment may move once per plan, got {segments}")
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a str, got {type(self.name).__name__}")
        object.__setattr__(self, "osteotomies", osteotomies)

    @property
    def segments(self):
        """Names of the moved segments, in plan order."""
        return tuple(o.segment for o in self.osteotomies)

    # ------------------------------------------------------------------ plain data
    def to_dict(self):
        """Return the plan as plain Python data (what the TOML/JSON files hold)."""
        out = {"name": self.name} if self.name else {}
        if self.axes != "image":
            out["axes"] = self.axes
        out["osteotomy"] = [o.to_dict() for o in self.osteotomies]
        return out

    @classmethod
    def from_dict(cls, data):
        """Build a plan from plain data, rejecting unknown keys and bad values.

        Raises
        ------
        ValueError
            Naming the offending key (``osteotomy[1].rotation``) and its value.
        """
        _check_keys(data, _PLAN_KEYS, "plan")
        items = data.get("osteotomy", [])
        if isinstance(items, dict):
            items = [items]
        if not isinstance(items, list) or not items:
            raise ValueError(
                f"plan needs at least one [[osteotomy]] table, got {data.get('osteotomy')!r}"
            )
        name = data.get("name", "")
        if not isinstance(name, str):
            raise ValueError(f"plan name must be a string, got {name!r}")
        axes = data.get("axes", "image")
        if axes not in AXES:
            raise ValueError(f"plan axes must be one of {list(AXES)}, got {axes!r}")
        if axes != "image" and any(isinstance(i, dict) and "matrix" in i for i in items):
            raise ValueError(f"plan axes = {axes!r} with an osteotomy given as a matrix: a "
                             "matrix is in the image's frame; use axes = 'image'")
        osteotomies = tuple(Osteotomy.from_dict(item, f"osteotomy[{i}]")
                            for i, item in enumerate(items))
        return cls(osteotomies, name=name, axes=axes)

    # ------------------------------------------------------------------ files
    @classmethod
    def from_file(cls, path, format=None):
        """Read a plan from a TOML or JSON file (format from the suffix unless given).

        Raises
        ------
        FileNotFoundError
            If ``path`` does not exist.
        ValueError
            If the file is not valid TOML/JSON or the plan is invalid; the message names
            the file.
        """
        path = Path(path)
        fmt = _format(path, format)
        text = path.read_text(encoding="utf-8")
        try:
            if fmt == "json":
                data = json.loads(text, parse_constant=_reject_constant)
            else:
                data = _toml_loads(text)
        except ValueError as err:  # JSONDecodeError and TOMLDecodeError are ValueErrors
            raise ValueError(f"{path}: not a valid {fmt.upper()} plan file: {err}") from None
        try:
            return cls.from_dict(data)
        except (ValueError, TypeError) as err:
            raise ValueError(f"{path}: {err}") from None

    def to_file(self, path, format=None):
        """Write the plan as TOML or JSON (format from the suffix unless given), atomically.

        Returns
        -------
        pathlib.Path
            The written file.
        """
        path = Path(path)
        fmt = _format(path, format)
        text = (json.dumps(self.to_dict(), indent=2) + "\n") if fmt == "json" else _toml_dumps(
            self.to_dict())
        return write_text(path, text)

    # ------------------------------------------------------------------ checks
    def check_segments(self, bones):
        """Check every segment can be found in a bone label image.

        A segment without cut planes must be labelled in ``bones``'s ``bone`` array; one
        with cut planes needs some bone inside its planes.

        Parameters
        ----------
        bones : pyvista.ImageData
            Label image with a point array ``bone`` (from ``segment`` or a phantom's truth).

        Raises
        ------
        ValueError
            Naming the missing segment and the labels the image has.
        """
        labels = np.asarray(arrays.require_array(bones, arrays.BONE, "point", dtype="iu",
                                                 producer="segment"))
        ids = labels.ravel()
        if ids.size and (ids.dtype.kind == "u" or ids.min() >= 0):
            values = np.flatnonzero(np.bincount(ids))  # one pass, no sort
        else:
            values = np.unique(ids)
        points = None
        for o in self.osteotomies:
            if not o.cut:
                if o.segment_id not in values:
                    present = {arrays.BONE_NAMES.get(int(v), int(v)) for v in values} - {"none"}
                    raise ValueError(
                        f"plan {self.name!r} moves segment {o.segment!r} but the bone label "
                        f"image has only {sorted(map(str, present))}; give cut planes for "
                        f"it or a label image that has it"
                    )
                continue
            if points is None:
                points = arrays.voxel_points(bones, np.flatnonzero(labels > 0))
            inside = np.ones(len(points), dtype=bool)
            for p, n in o.cut:
                inside &= (points - np.asarray(p)) @ np.asarray(n) >= 0
            if not inside.any():
                raise ValueError(
                    f"plan {self.name!r}: the cut planes of segment {o.segment!r} contain "
                    f"no bone of the label image"
                )
        return self


#: paper 000 Table II, one plan per patient
TABLE_II = {
    1: Plan((Osteotomy("maxilla", (6.0, 5.0, -4.0), (0.0, 2.0, 5.0)),), name="patient 1"),
    2: Plan((Osteotomy("maxilla", (-0.27, 0.13, 4.98), (0.0, 0.0, 1.31)),), name="patient 2"),
    3: Plan((Osteotomy("mandible", (1.07, -0.74, 5.47), (0.0, 2.71, 0.0)),), name="patient 3"),
    4: Plan((Osteotomy("mandible", (0.67, 0.61, -3.24), (0.0, 0.0, 0.0)),), name="patient 4"),
}


def _format(path, format):
    fmt = format or Path(path).suffix.lower().lstrip(".")
    if fmt not in ("toml", "json"):
        raise ValueError(
            f"plan file format must be 'toml' or 'json' (from the suffix or format=), "
            f"got {fmt!r} for {str(path)!r}"
        )
    return fmt


def _reject_constant(name):
    raise ValueError(f"non-finite number {name} is not allowed in a plan")


def _toml_loads(text):
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise ModuleNotFoundError(
                "reading TOML plans on Python 3.10 needs 'tomli' (pip install tomli)"
            ) from None
    return tomllib.loads(text)


def _toml_value(value):
    if isinstance(value, str):
        return json.dumps(value)  # a JSON string is a valid TOML basic string
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    return str(value)


def _toml_dumps(data):
    """Serialise a plan dict (the structure of :meth:`Plan.to_dict`) as TOML."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in data.items() if k != "osteotomy"]
    for ost in data.get("osteotomy", []):
        lines += ["", "[[osteotomy]]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in ost.items() if k != "cut"]
        for plane in ost.get("cut", []):
            lines += ["", "[[osteotomy.cut]]"]
            lines += [f"{k} = {_toml_value(v)}" for k, v in plane.items()]
    return "\n".join(lines).lstrip("\n") + "\n"


def read_plan(path, bones=None, format=None):
    """Read a plan file (TOML or JSON); with ``bones``, check its segments exist there.

    Parameters
    ----------
    path : str or pathlib.Path
        ``.toml`` or ``.json`` file (see the module docstring for the format).
    bones : pyvista.ImageData, optional
        Bone label image (point array ``bone``) the plan will be applied to.
    format : {'toml', 'json'}, optional
        Overrides the suffix.

    Returns
    -------
    Plan

    Examples
    --------
    >>> import os, tempfile
    >>> from pvcmf.plan import read_plan, write_plan, TABLE_II
    >>> path = write_plan(TABLE_II[3], os.path.join(tempfile.mkdtemp(), "p3.json"))
    >>> read_plan(path).osteotomies[0].segment
    'mandible'
    """
    plan = Plan.from_file(path, format=format)
    if bones is not None:
        plan.check_segments(bones)
    return plan


def write_plan(plan, path, format=None):
    """Write ``plan`` to ``path`` (TOML or JSON by suffix), atomically; return the path."""
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan, got {type(plan).__name__}")
    return plan.to_file(path, format=format)
