"""Rigid transforms from planning tools: ITK / 3D Slicer files and 4x4 matrices.

Frames
------
pvcmf's patient frame has x toward the patient's left, y anterior, z superior (the frame of
``read_ct(..., frame="patient")`` and of the virtual patients). ITK files and DICOM use
**LPS** (x left, y *posterior*, z superior); 3D Slicer's scene and its JSON markups may use
**RAS** (x *right*, y anterior, z superior). A point maps to the patient frame by
``p = F q`` with ``F = diag(1, -1, 1)`` from LPS and ``diag(-1, 1, 1)`` from RAS
(:data:`FRAMES`), so a 4x4 transform maps by ``F M F`` (:func:`to_patient`).

Direction
---------
An ITK transform file holds the transform used to **resample**: it maps points of the
fixed (output) space to the moving (input) space. 3D Slicer writes a linear transform node
that *moves* a model by ``M`` ("to parent") as the ITK transform ``M^-1`` ("from parent"),
so the bone move of a Slicer/ITK file is the *inverse* of the file's transform
(:func:`read_transform` with ``itk_direction="resampling"``, the default); pass
``itk_direction="moving"`` for a file that already holds the bone's move.

Files
-----
``.tfm`` / ``.txt``: ITK's text format (``#Insight Transform File V1.0``) with
``AffineTransform``, ``MatrixOffsetTransformBase``, ``Rigid3DTransform``,
``Euler3DTransform``, ``VersorRigid3DTransform``, ``QuaternionRigidTransform``,
``Similarity3DTransform``, ``ScaleVersor3DTransform``, ``TranslationTransform``,
``IdentityTransform`` (``_double_3_3`` or ``_float_3_3``) and ``CompositeTransform`` of
these. ``.h5`` / ``.hdf5``: ITK's HDF5 transform format (needs ``h5py``).
``.json`` / ``.toml``: ``{"matrix": [[...] x4], "frame": "RAS" | "LPS" | "patient"}``.
Plans of transforms (:func:`read_plan_file`): a plan file (TOML/JSON) whose osteotomies
give ``matrix`` (4x4, with an optional ``frame``) or ``transform = "maxilla.tfm"`` (a path
relative to the plan) instead of ``translation``/``rotation``. A transform that is not
rigid (scaling, shear, reflection) is refused with its deviation. Pure numpy; the TOML
and JSON parsing is :mod:`pvcmf.plan`'s.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..plan import _OSTEOTOMY_KEYS as OSTEOTOMY_KEYS
from ..plan import Plan, _toml_loads

log = logging.getLogger(__name__)

__all__ = ["FRAMES", "to_patient", "from_patient", "check_rigid", "read_itk_transform",
           "write_itk_transform", "read_transform", "read_plan_file", "ITK_TRANSFORM_TYPES"]

#: point coordinates in a frame -> pvcmf patient frame (x left, y anterior, z superior)
FRAMES = {"patient": np.eye(3), "LPS": np.diag([1.0, -1.0, 1.0]),
          "RAS": np.diag([-1.0, 1.0, 1.0])}
_TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5", ".json", ".toml")


def _frame(frame, what="frame"):
    key = str(frame).upper() if str(frame).lower() != "patient" else "patient"
    if key not in FRAMES:
        raise ValueError(f"{what} must be one of {list(FRAMES)}, got {frame!r}")
    return FRAMES[key]


def _homogeneous(F):
    out = np.eye(4)
    out[:3, :3] = F
    return out


def to_patient(matrix, frame):
    """A 4x4 transform of ``frame`` coordinates as a transform of patient coordinates.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.io.transforms import to_patient
    >>> shift = np.eye(4); shift[:3, 3] = [1.0, 2.0, 3.0]      # 2 mm posterior in LPS
    >>> to_patient(shift, "LPS")[:3, 3].tolist()               # = 2 mm anterior-negative
    [1.0, -2.0, 3.0]
    """
    F = _homogeneous(_frame(frame))
    return F @ np.asarray(matrix, dtype=float) @ F


def from_patient(matrix, frame):
    """Inverse of :func:`to_patient` (the frame flips are their own inverses)."""
    return to_patient(matrix, frame)


def check_rigid(matrix, tol=1e-5, what="transform"):
    """Return ``matrix`` (4x4 float) after checking it is a proper rigid transform.

    Raises
    ------
    ValueError
        Naming ``what``: not 4x4/finite, last row not ``0 0 0 1``, or a 3x3 part that is
        not a rotation (its largest deviation from orthonormal, its determinant, and the
        scale factors found).
    """
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise ValueError(f"{what} must be a finite 4x4 matrix, got shape {m.shape}")
    if not np.allclose(m[3], [0, 0, 0, 1], atol=tol):
        raise ValueError(f"{what} must have last row [0, 0, 0, 1], got {m[3].tolist()}")
    rot = m[:3, :3]
    dev = float(np.abs(rot.T @ rot - np.eye(3)).max())
    det = float(np.linalg.det(rot))
    if dev > tol or det < 0:
        scales = np.linalg.svd(rot, compute_uv=False)
        raise ValueError(
            f"{what} is not rigid: its 3x3 part deviates from a rotation by {dev:.3g} "
            f"(determinant {det:.6g}, scale factors {np.round(scales, 6).tolist()}); pvcmf "
            f"moves bone segments rigidly (no scaling, shear or mirroring)")
    return m


# --------------------------------------------------------------------------- ITK
def _rx(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _quaternion(x, y, z, w):
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _versor(v):
    v = np.asarray(v, dtype=float)
    w2 = 1.0 - float(v @ v)
    if w2 < -1e-9:
        raise ValueError(f"versor {v.tolist()} has norm > 1")
    return _quaternion(*v, np.sqrt(max(w2, 0.0)))


def _euler(p, fixed):
    zyx = len(fixed) > 3 and fixed[3] != 0  # ITK's ComputeZYX flag (4th fixed parameter)
    rx, ry, rz = _rx(p[0]), _ry(p[1]), _rz(p[2])
    return (rz @ ry @ rx) if zyx else (rz @ rx @ ry), p[3:6]


#: ITK transform class -> (number of parameters, function params -> (3x3, translation))
ITK_TRANSFORM_TYPES = {
    "AffineTransform": (12, lambda p, f: (p[:9].reshape(3, 3), p[9:12])),
    "MatrixOffsetTransformBase": (12, lambda p, f: (p[:9].reshape(3, 3), p[9:12])),
    "Rigid3DTransform": (12, lambda p, f: (p[:9].reshape(3, 3), p[9:12])),
    "Euler3DTransform": (6, _euler),
    "VersorRigid3DTransform": (6, lambda p, f: (_versor(p[:3]), p[3:6])),
    "QuaternionRigidTransform": (7, lambda p, f: (_quaternion(*p[:4]), p[4:7])),
    "Similarity3DTransform": (7, lambda p, f: (p[6] * _versor(p[:3]), p[3:6])),
    "ScaleVersor3DTransform": (9, lambda p, f: (_versor(p[:3]) @ np.diag(p[6:9]), p[3:6])),
    "TranslationTransform": (3, lambda p, f: (np.eye(3), p[:3])),
    "IdentityTransform": (0, lambda p, f: (np.eye(3), np.zeros(3))),
}


def _itk_matrix(kind, params, fixed, where):
    base = kind.split("_")[0]
    if base not in ITK_TRANSFORM_TYPES:
        raise ValueError(f"{where}: ITK transform type {kind!r} is not supported; supported: "
                         f"{sorted(ITK_TRANSFORM_TYPES)} and CompositeTransform of them")
    count, build = ITK_TRANSFORM_TYPES[base]
    params = np.asarray(params, dtype=float).ravel()
    fixed = np.asarray(fixed, dtype=float).ravel()
    if params.size != count:
        raise ValueError(f"{where}: {kind} needs {count} parameters, got {params.size}")
    rot, t = build(params, fixed)
    centre = fixed[:3] if base != "TranslationTransform" and fixed.size >= 3 else np.zeros(3)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = np.asarray(t) + centre - rot @ centre  # y = R (x - c) + t + c
    return out


def _compose(items, where):
    """ITK's composite applies its last transform first: M = M_1 @ M_2 @ ... @ M_n."""
    if not items:
        raise ValueError(f"{where}: no transform found")
    if items[0][0].startswith("CompositeTransform"):
        items = items[1:]
        if not items:
            raise ValueError(f"{where}: empty CompositeTransform")
    out = np.eye(4)
    for i, (kind, params, fixed) in enumerate(items):
        if kind.startswith("CompositeTransform"):
            raise ValueError(f"{where}: nested CompositeTransform is not supported")
        out = out @ _itk_matrix(kind, params, fixed, f"{where} transform {i}")
    return out


def _read_itk_text(path):
    text = Path(path).read_text(encoding="latin-1")
    if not text.lstrip().startswith("#Insight Transform File"):
        raise ValueError(f"{path}: not an ITK transform file (first line must be "
                         f"'#Insight Transform File V1.0', got {text.splitlines()[:1]!r})")
    items, current = [], None
    for number, line in enumerate(text.splitlines(), start=1):
        key, _, value = line.partition(":")
        key = key.strip()
        try:
            if key == "Transform":
                current = [value.strip(), [], []]
                items.append(current)
            elif key == "Parameters" and current is not None:
                current[1] = [float(v) for v in value.split()]
            elif key == "FixedParameters" and current is not None:
                current[2] = [float(v) for v in value.split()]
        except ValueError:
            raise ValueError(f"{path}, line {number}: not numbers: {value.strip()!r}") from None
    return items


def _read_itk_hdf5(path):
    try:
        import h5py
    except ModuleNotFoundError:
        raise ModuleNotFoundError(f"reading the ITK HDF5 transform {str(path)!r} needs h5py "
                                  "(pip install h5py), or save it from Slicer as .tfm") from None
    items = []
    with h5py.File(path, "r") as f:
        if "TransformGroup" not in f:
            raise ValueError(f"{path}: no /TransformGroup: not an ITK HDF5 transform")
        group = f["TransformGroup"]
        for key in sorted(group, key=int):
            g = group[key]
            kind = np.asarray(g["TransformType"]).ravel()[0]
            kind = kind.decode() if isinstance(kind, bytes) else str(kind)
            params = np.asarray(g["TransformParameters"]) if "TransformParameters" in g else []
            fixed = (np.asarray(g["TransformFixedParameters"])
                     if "TransformFixedParameters" in g else [])
            items.append((kind, params, fixed))
    return items


def read_itk_transform(path):
    """The 4x4 matrix (LPS, fixed -> moving, as ITK applies it) of an ITK transform file.

    Parameters
    ----------
    path : str or pathlib.Path
        ``.tfm``/``.txt`` (ITK text) or ``.h5``/``.hdf5`` (ITK HDF5, needs h5py).

    Returns
    -------
    numpy.ndarray, (4, 4)
        Not checked for rigidity (see :func:`check_rigid`).

    Examples
    --------
    >>> import os, tempfile
    >>> from pvcmf.io.transforms import read_itk_transform
    >>> path = os.path.join(tempfile.mkdtemp(), "t.tfm")
    >>> _ = open(path, "w").write("#Insight Transform File V1.0\\n#Transform 0\\n"
    ...     "Transform: TranslationTransform_double_3_3\\nParameters: 1 2 3\\n"
    ...     "FixedParameters:\\n")
    >>> read_itk_transform(path)[:3, 3].tolist()
    [1.0, 2.0, 3.0]
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"transform file {str(path)!r} does not exist")
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        items = _read_itk_hdf5(path)
    elif suffix in (".tfm", ".txt"):
        items = _read_itk_text(path)
    else:
        raise ValueError(f"ITK transform file must end in .tfm, .txt, .h5 or .hdf5, got "
                         f"{path.name!r}")
    return _compose([(k, p, f) for k, p, f in items], str(path))


def write_itk_transform(matrix, path, *, frame="patient", itk_direction="resampling"):
    """Write a 4x4 bone move (in ``frame``) as an ITK text transform Slicer reads.

    The inverse of :func:`read_transform`: the matrix is converted to LPS and, with
    ``itk_direction="resampling"``, inverted (ITK's fixed -> moving); written as
    ``AffineTransform_double_3_3`` with a zero centre. Returns the path.
    """
    from .._atomic import write_text

    m = to_patient(check_rigid(matrix, what="matrix"), frame)  # frame -> patient
    lps = from_patient(m, "LPS")
    if itk_direction == "resampling":
        lps = np.linalg.inv(lps)
    elif itk_direction != "moving":
        raise ValueError(f"itk_direction must be 'resampling' or 'moving', got {itk_direction!r}")
    values = " ".join(repr(float(v)) for v in (*lps[:3, :3].ravel(), *lps[:3, 3]))
    text = ("#Insight Transform File V1.0\n#Transform 0\n"
            "Transform: AffineTransform_double_3_3\n"
            f"Parameters: {values}\nFixedParameters: 0 0 0\n")
    return write_text(path, text)


# --------------------------------------------------------------------------- entry points
def _read_matrix_file(path):
    text = Path(path).read_text(encoding="utf-8")
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else _toml_loads(text)
    except ValueError as err:
        raise ValueError(f"{path}: not valid {path.suffix[1:].upper()}: {err}") from None
    if not isinstance(data, dict) or "matrix" not in data:
        raise ValueError(f"{path}: needs a 'matrix' (4x4) entry, got keys "
                         f"{sorted(data) if isinstance(data, dict) else type(data).__name__}")
    unknown = sorted(set(data) - {"matrix", "frame"})
    if unknown:
        raise ValueError(f"{path}: unknown key(s) {unknown}; allowed: ['matrix', 'frame']")
    return np.asarray(data["matrix"], dtype=float), data.get("frame", "patient")


def read_transform(path, *, frame=None, itk_direction="resampling", tol=1e-5):
    """Read one rigid bone move from a file, as a 4x4 matrix in the patient frame.

    Parameters
    ----------
    path : str or pathlib.Path
        ``.tfm``/``.txt``/``.h5`` (ITK, LPS) or ``.json``/``.toml`` (``matrix`` and an
        optional ``frame``, default ``"patient"``).
    frame : {'patient', 'LPS', 'RAS'}, optional
        The file's frame, overriding the default (LPS for ITK files, the ``frame`` key
        for JSON/TOML).
    itk_direction : {'resampling', 'moving'}
        ITK files only: ``'resampling'`` (Slicer's and ITK's convention) means the file
        maps fixed to moving points and the bone move is its inverse.
    tol : float
        Rigidity tolerance (:func:`check_rigid`).

    Returns
    -------
    numpy.ndarray, (4, 4)

    Raises
    ------
    ValueError
        Unknown extension, unsupported ITK type, or a transform that is not rigid.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _TRANSFORM_SUFFIXES:
        raise ValueError(f"transform file {str(path)!r}: unknown extension {path.suffix!r}; "
                         f"known: {list(_TRANSFORM_SUFFIXES)}")
    if suffix in (".json", ".toml"):
        if not path.exists():
            raise FileNotFoundError(f"transform file {str(path)!r} does not exist")
        matrix, file_frame = _read_matrix_file(path)
        matrix = check_rigid(matrix, tol, what=f"transform in {path.name}")
        return to_patient(matrix, frame or file_frame)
    matrix = check_rigid(read_itk_transform(path), tol, what=f"ITK transform {path.name}")
    if itk_direction == "resampling":
        matrix = np.linalg.inv(matrix)
    elif itk_direction != "moving":
        raise ValueError(f"itk_direction must be 'resampling' or 'moving', got {itk_direction!r}")
    return to_patient(matrix, frame or "LPS")


def read_plan_file(path, *, itk_direction="resampling"):
    """Read a plan (TOML/JSON) whose osteotomies may be given as transforms.

    Each ``[[osteotomy]]`` may hold, instead of ``translation``/``rotation``:
    ``matrix`` (4x4) with an optional ``frame`` (``patient`` default, ``LPS``, ``RAS``), or
    ``transform`` (a file read by :func:`read_transform`, relative to the plan's folder)
    with an optional ``frame`` overriding the file's. A plain plan reads as
    :func:`pvcmf.plan.read_plan` reads it.

    Examples
    --------
    >>> import os, tempfile
    >>> from pvcmf.io.transforms import read_plan_file
    >>> folder = tempfile.mkdtemp()
    >>> _ = open(os.path.join(folder, "plan.toml"), "w").write(
    ...     '[[osteotomy]]\\nsegment = "mandible"\\nframe = "RAS"\\n'
    ...     'matrix = [[1, 0, 0, 2], [0, 1, 0, 5], [0, 0, 1, 0], [0, 0, 0, 1]]\\n')
    >>> read_plan_file(os.path.join(folder, "plan.toml")).osteotomies[0].translation
    (-2.0, 0.0, 5.0)
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise ValueError(f"plan file must be .toml or .json, got {path.name!r}")
    if not path.is_file():
        what = "is a folder" if path.is_dir() else "does not exist"
        raise FileNotFoundError(f"plan file {str(path)!r} {what} (expected a .toml or .json "
                                "plan)")
    text = path.read_text(encoding="utf-8")
    try:
        data = json.loads(text) if suffix == ".json" else _toml_loads(text)
    except ValueError as err:
        raise ValueError(f"{path}: not a valid {suffix[1:].upper()} plan file: {err}") from None
    items = data.get("osteotomy", []) if isinstance(data, dict) else []
    items = [items] if isinstance(items, dict) else items
    converted = []
    for i, item in enumerate(items if isinstance(items, list) else []):
        if not isinstance(item, dict):
            converted.append(item)
            continue
        item = dict(item)
        where = f"{path.name}: osteotomy[{i}]"
        allowed = [*OSTEOTOMY_KEYS, "transform", "frame"]  # the file's keys, before conversion
        unknown = sorted(set(item) - set(allowed))
        if unknown:
            raise ValueError(f"{where} has unknown key(s) {unknown}; allowed keys are {allowed}")
        frame = item.pop("frame", None)
        if "transform" in item:
            if "matrix" in item:
                raise ValueError(f"{where} gives both 'transform' and 'matrix'")
            source = Path(item.pop("transform"))
            source = source if source.is_absolute() else path.parent / source
            item["matrix"] = read_transform(source, frame=frame,
                                            itk_direction=itk_direction).tolist()
        elif "matrix" in item and frame is not None:
            m = check_rigid(item["matrix"], what=f"{where}.matrix")
            item["matrix"] = to_patient(m, frame).tolist()
        elif frame is not None:
            raise ValueError(f"{where}: 'frame' only applies to 'matrix' or 'transform'")
        converted.append(item)
    if isinstance(data, dict) and "osteotomy" in data:
        data = {**data, "osteotomy": converted}
    try:
        return Plan.from_dict(data)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{path}: {err}") from None
