"""Landmarks from 3D Slicer markups, for :func:`pvcmf.filters.embed_muscles`.

``embed_muscles(labels, landmarks=...)`` takes landmarks as ``{name: (x, y, z)}`` in mm in
the patient frame (x patient's left, y anterior, z superior). :func:`read_landmarks` reads
them from

* Slicer's markups JSON (``.mrk.json``, or any ``.json`` with a ``markups`` list): every
  ``controlPoints`` entry with a ``label`` and a ``position``, in the markup's
  ``coordinateSystem`` (``"LPS"`` or ``"RAS"``; LPS when absent, as Slicer writes it);
  points whose ``positionStatus`` is ``"undefined"`` are skipped;
* Slicer's fiducial CSV (``.fcsv``): the ``# CoordinateSystem = LPS | RAS | 0 | 1`` header
  (``0`` is RAS, ``1`` LPS; RAS when absent, the old default), the ``# columns =`` header
  (else Slicer's ``id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``), and
  each row's ``label``;

and converts them with :data:`pvcmf.io.transforms.FRAMES`. :func:`write_landmarks` writes
either format (LPS by default), so landmarks found by pvcmf open in Slicer. Files without
points, with repeated or empty labels, or with non-finite coordinates are refused naming
the file. Delegates to :mod:`json` and :mod:`csv`.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from pathlib import Path

import numpy as np

from .transforms import FRAMES, _frame

log = logging.getLogger(__name__)

__all__ = ["read_landmarks", "write_landmarks", "FCSV_COLUMNS"]

#: Slicer's fiducial CSV columns (markups fiducial file version 4.11 and later)
FCSV_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label",
                "desc", "associatedNodeID")
_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
           "Resources/Schema/markups-schema-v1.0.3.json#")


def _kind(path):
    name = path.name.lower()
    if name.endswith(".fcsv"):
        return "fcsv"
    if name.endswith(".json"):
        return "json"
    raise ValueError(f"landmark file {str(path)!r}: unknown extension; expected Slicer "
                     f"markups '.mrk.json' (or '.json') or '.fcsv'")


def _points_json(path):
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as err:
        raise ValueError(f"{path}: not valid JSON: {err}") from None
    markups = data.get("markups") if isinstance(data, dict) else None
    if not isinstance(markups, list):
        raise ValueError(f"{path}: not a Slicer markups file (no 'markups' list)")
    out = []
    for k, markup in enumerate(markups):
        system = markup.get("coordinateSystem", "LPS")
        _frame(system, f"{path.name}: markups[{k}].coordinateSystem")
        for j, point in enumerate(markup.get("controlPoints") or []):
            if point.get("positionStatus", "defined") == "undefined":
                continue
            if "position" not in point:
                raise ValueError(f"{path}: markups[{k}].controlPoints[{j}] has no 'position'")
            label = point.get("label") or point.get("id")
            out.append((str(label or ""), point["position"], system))
    return out


def _points_fcsv(path):
    system, columns, rows = "RAS", list(FCSV_COLUMNS), []
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            key, _, value = line[1:].partition("=")
            key, value = key.strip().lower(), value.strip()
            if key == "coordinatesystem":
                system = {"0": "RAS", "1": "LPS"}.get(value, value)
            elif key == "columns":
                columns = [c.strip() for c in value.split(",")]
        elif line.strip():
            rows.append(line)
    _frame(system, f"{path.name}: CoordinateSystem")
    for need in ("x", "y", "z", "label"):
        if need not in columns:
            raise ValueError(f"{path}: the '# columns' header has no {need!r} column")
    out = []
    for row in csv.reader(rows):
        record = dict(zip(columns, row))
        out.append((record.get("label", ""), [record.get(c) for c in "xyz"], system))
    return out


def read_landmarks(path, *, frame="patient"):
    """Read named landmarks from a Slicer markups file into a frame (default: patient).

    Parameters
    ----------
    path : str or pathlib.Path
        ``.mrk.json`` / ``.json`` (Slicer markups) or ``.fcsv`` (Slicer fiducial CSV).
    frame : {'patient', 'LPS', 'RAS'}
        Frame of the returned coordinates.

    Returns
    -------
    dict[str, numpy.ndarray]
        Label -> (3,) position in mm, in file order; what ``embed_muscles(landmarks=)``
        takes.

    Raises
    ------
    ValueError
        Unknown extension or coordinate system, no points, empty or repeated labels,
        non-numeric or non-finite coordinates.

    Examples
    --------
    >>> import os, tempfile
    >>> from pvcmf.io.landmarks import read_landmarks
    >>> path = os.path.join(tempfile.mkdtemp(), "lm.fcsv")
    >>> _ = open(path, "w").write("# CoordinateSystem = RAS\\n"
    ...                           "vtkMRMLMarkupsFiducialNode_0,10,20,30,0,0,0,1,1,1,0,nasion,,\\n")
    >>> read_landmarks(path)["nasion"].tolist()         # RAS -> patient: x flips
    [-10.0, 20.0, 30.0]
    """
    path = Path(path)
    kind = _kind(path)
    if not path.exists():
        raise FileNotFoundError(f"landmark file {str(path)!r} does not exist")
    points = _points_json(path) if kind == "json" else _points_fcsv(path)
    if not points:
        raise ValueError(f"{path}: no landmark points in the file")
    target = _frame(frame)
    out = {}
    for label, position, system in points:
        if not label.strip():
            raise ValueError(f"{path}: a point has an empty label; every landmark needs a name")
        if label in out:
            raise ValueError(f"{path}: landmark label {label!r} appears more than once")
        try:
            p = np.asarray(position, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: landmark {label!r} has no 3 numbers: {position!r}") from None
        if not np.all(np.isfinite(p)):
            raise ValueError(f"{path}: landmark {label!r} is not finite: {p.tolist()}")
        out[label] = target @ (FRAMES[system.upper()] @ p)  # FRAMES are their own inverses
    log.info("read %d landmarks from %s", len(out), path)
    return out


def write_landmarks(landmarks, path, *, frame="patient", coordinate_system="LPS"):
    """Write ``{name: (x, y, z)}`` (in ``frame``) as a Slicer ``.mrk.json`` or ``.fcsv``.

    ``coordinate_system`` ('LPS' or 'RAS') is the file's. Returns the path.
    """
    from .._atomic import write_text

    path = Path(path)
    kind = _kind(path)
    system = str(coordinate_system).upper()
    to_file = FRAMES[system] @ _frame(frame)
    if not landmarks:
        raise ValueError("landmarks must hold at least one point")
    names = [str(k) for k in landmarks]
    pts = np.array([np.asarray(landmarks[k], dtype=float).reshape(3) for k in landmarks])
    pts = pts @ to_file.T
    if kind == "json":
        control = [{"id": str(i + 1), "label": n, "position": p.tolist(),
                    "positionStatus": "defined"} for i, (n, p) in enumerate(zip(names, pts))]
        data = {"@schema": _SCHEMA, "markups": [{"type": "Fiducial",
                                                 "coordinateSystem": system,
                                                 "coordinateUnits": "mm",
                                                 "controlPoints": control}]}
        return write_text(path, json.dumps(data, indent=2) + "\n")
    buf = io.StringIO()
    buf.write(f"# Markups fiducial file version = 4.11\n# CoordinateSystem = {system}\n"
              f"# columns = {','.join(FCSV_COLUMNS)}\n")
    writer = csv.writer(buf, lineterminator="\n")
    for i, (n, p) in enumerate(zip(names, pts)):
        writer.writerow([f"vtkMRMLMarkupsFiducialNode_{i}", *map(repr, map(float, p)),
                         0, 0, 0, 1, 1, 1, 0, n, "", ""])
    return write_text(path, buf.getvalue())
