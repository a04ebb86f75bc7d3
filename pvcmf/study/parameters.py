"""The parameters a sweep may vary, their checks, and the grid of values.

:data:`PARAMETERS` names every sweepable parameter with its level: *mesh*-level
parameters (image spacing, tetrahedra count, region of interest, ...) change the mesh and
make a new task; *solve*-level ones (Poisson ratios, Young's moduli, solver tolerance,
...) only change the material and are looped over inside a task.
:func:`validate_grid` checks a grid before anything runs; :func:`parse_grid` reads one
from ``NAME=V1,V2`` or ``NAME=START:STOP:NUM`` strings (the command line).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence

import numpy as np

from .. import arrays
from ..plan import MAX_ROTATION_DEG, MAX_TRANSLATION_MM, MOVABLE_SEGMENTS

__all__ = ["METRICS", "PARAMETERS", "PLAN_PARAMETERS", "TIMES", "parse_grid", "plan_values",
           "validate_grid"]


def _poisson(name, value):
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"grid[{name!r}] values must be numbers in [0, 0.5), got {value!r}")
    if not (0.0 <= float(value) < 0.5):
        raise ValueError(
            f"grid[{name!r}] values must lie in [0, 0.5) (a linear elastic Poisson ratio; "
            f"0.5 is incompressible and not representable), got {value!r}"
        )
    return float(value)


def _positive(name, value):
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"grid[{name!r}] values must be positive numbers, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise ValueError(f"grid[{name!r}] values must be finite and > 0, got {value!r}")
    return float(value)


def _positive_int(name, value):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) <= 0:
        raise ValueError(f"grid[{name!r}] values must be positive integers, got {value!r}")
    return int(value)


def _optional_nonnegative(name, value):
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (
        math.isfinite(float(value)) and float(value) >= 0
    ):
        raise ValueError(f"grid[{name!r}] values must be None or finite numbers >= 0, got {value!r}")
    return float(value)


def _boolean(name, value):
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"grid[{name!r}] values must be True or False, got {value!r}")
    return bool(value)


def _solver_method(name, value):
    allowed = ("direct", "cg", "relaxation", "gpu")
    if value not in allowed:
        raise ValueError(f"grid[{name!r}] values must be one of {allowed}, got {value!r}")
    return str(value)


def _translation(name, value):
    return _bounded(name, value, MAX_TRANSLATION_MM, "mm")


def _rotation(name, value):
    return _bounded(name, value, MAX_ROTATION_DEG, "degrees")


def _bounded(name, value, limit, unit):
    if isinstance(value, bool) or not isinstance(value, numbers.Real) \
            or not math.isfinite(float(value)) or abs(float(value)) > limit:
        raise ValueError(f"grid[{name!r}] values must be finite numbers within +-{limit:g} "
                         f"{unit}, got {value!r}")
    return float(value)


_AXES = {"h": "horizontal (+ patient-left)", "v": "vertical (+ superior)",
         "ap": "anterior-posterior (+ anterior)"}

#: Plan parameters ``<segment>_<t|r>_<h|v|ap>`` (the planner's slider names,
#: :func:`pvcmf.planner.state.slider_key`): one component of a segment's translation (mm)
#: or rotation (degrees) in the plan's (horizontal, vertical, anterior-posterior) terms
#: (:mod:`pvcmf.plan`). A component the grid does not name keeps the case's own plan value.
#: Rotations may also name their axis as an angle: ``_r_pitch`` (= ``_r_h``), ``_r_yaw``
#: (= ``_r_v``), ``_r_roll`` (= ``_r_ap``).
PLAN_PARAMETERS = {
    f"{segment}_{kind}_{axis}": (
        "plan", _translation if kind == "t" else _rotation,
        f"{segment} {'translation, mm' if kind == 't' else 'rotation, degrees'}, {meaning}")
    for segment in MOVABLE_SEGMENTS for kind in ("t", "r") for axis, meaning in _AXES.items()
}
_ANGLES = {"pitch": "h", "yaw": "v", "roll": "ap"}
PLAN_PARAMETERS.update({
    f"{segment}_r_{angle}": ("plan", _rotation, f"{segment} rotation, degrees, {angle} "
                             f"(= {segment}_r_{axis})")
    for segment in MOVABLE_SEGMENTS for angle, axis in _ANGLES.items()
})


def _plan_component(name):
    """(segment, 'translation'|'rotation', axis index) of a plan parameter."""
    segment, kind, axis = name.rsplit("_", 2)
    return (segment, "translation" if kind == "t" else "rotation",
            list(_AXES).index(_ANGLES.get(axis, axis)))


def plan_values(params):
    """The plan parameters of ``params`` as {segment: {"translation"|"rotation": {axis
    index: value}}}.

    Examples
    --------
    >>> from pvcmf.study.parameters import plan_values
    >>> plan_values({"maxilla_t_ap": 4.0, "nu": 0.4})
    {'maxilla': {'translation': {2: 4.0}}}
    """
    out = {}
    for name, value in params.items():
        if name in PLAN_PARAMETERS:
            segment, attr, axis = _plan_component(name)
            out.setdefault(segment, {}).setdefault(attr, {})[axis] = float(value)
    return out


#: Sweepable parameters: name -> (level, validator, meaning). ``mesh``-level parameters
#: make a new task (new mesh); ``solve``-level ones are looped over inside a task;
#: ``plan``-level ones (:data:`PLAN_PARAMETERS`) too, predicted by one plan-response
#: operator per case and material (:func:`pvcmf.mtm.response.plan_response`).
PARAMETERS = {
    "spacing": ("mesh", _positive, "image resolution of the virtual patient, mm"),
    "n_tets": ("mesh", _positive_int, "requested number of tetrahedra"),
    "roi": ("mesh", _optional_nonnegative,
            "region of interest: soft tissue within this distance (mm) of the moved bone; None = all"),
    "conforming": ("mesh", _boolean, "muscle-conforming mesh (True) or homogeneous mesh (False)"),
    "n_points": ("mesh", _positive_int, "random sampling points per tetrahedron (baseline)"),
    "nu": ("solve", _poisson, "homogeneous Poisson ratio (paper 001 sec. 2.1)"),
    "nu_fat": ("solve", _poisson, "Poisson ratio of fat (paper 001 sec. 2.2)"),
    "nu_muscle": ("solve", _poisson, "Poisson ratio of muscle (paper 001 sec. 2.2)"),
    "E_ratio": ("solve", _positive, "E_muscle / E_fat (paper 001 sec. 2.2)"),
    "E_fat": ("solve", _positive, "Young's modulus of fat, MPa"),
    "E_muscle": ("solve", _positive, "Young's modulus of muscle, MPa"),
    "tol": ("solve", _positive, "iterative solver tolerance (relative residual)"),
    "method": ("solve", _solver_method, "MTM solver"),
    "sigma": ("solve", _optional_nonnegative, "Gaussian smoothing of the tet -> skin mapping, mm"),
    **PLAN_PARAMETERS,
}

#: Metric columns every evaluation returns (|distance| statistics, mm and %).
METRICS = arrays.SWEEP_METRICS
#: Timing columns (s): ``t_prepare`` is the task's shared cost (mesh, structure), once per
#: task and repeated on each of its rows (a prepared case loaded from
#: ``PipelineEvaluation(cache_dir=...)`` reports what preparing it cost when it was made);
#: ``t_eval`` the cost of this row's parameter set; ``cpu_*`` the same as CPU time of the
#: process that ran the task (wall time includes waiting for a core on a busy machine).
TIMES = arrays.SWEEP_TIMES


def validate_grid(grid):
    """Check a parameter grid and return it normalised (name -> tuple of values).

    Parameters
    ----------
    grid : mapping
        Parameter name (a key of :data:`PARAMETERS`) -> non-empty sequence of values (a
        scalar is taken as a one-value list).

    Returns
    -------
    dict
        Name -> tuple of validated values (floats / ints), insertion order kept.

    Raises
    ------
    ValueError
        Unknown name, empty list, duplicated value, Poisson ratio outside [0, 0.5),
        non-positive Young's modulus or count; the message names the parameter and value.
    TypeError
        If ``grid`` is not a mapping.

    Examples
    --------
    >>> from pvcmf.study.parameters import validate_grid
    >>> validate_grid({"nu": [0.3, 0.46], "n_tets": 30000})
    {'nu': (0.3, 0.46), 'n_tets': (30000,)}
    """
    if not isinstance(grid, Mapping):
        raise TypeError(f"grid must be a mapping name -> list of values, got {type(grid).__name__}")
    if not grid:
        raise ValueError("grid must name at least one parameter, got an empty mapping")
    out = {}
    for name, values in grid.items():
        if name not in PARAMETERS:
            raise ValueError(
                f"grid has unknown parameter {name!r}; known parameters are {sorted(PARAMETERS)}"
            )
        if isinstance(values, (str, bytes)) or not isinstance(values, (Sequence, np.ndarray)):
            values = [values]
        values = list(values)
        if not values:
            raise ValueError(f"grid[{name!r}] must hold at least one value, got an empty list")
        check = PARAMETERS[name][1]
        clean = tuple(check(name, v.item() if isinstance(v, np.generic) else v) for v in values)
        if len(set(clean)) != len(clean):
            raise ValueError(f"grid[{name!r}] has duplicated values: {list(values)}")
        out[name] = clean
    components = {}
    for name in out:
        if name in PLAN_PARAMETERS:
            components.setdefault(_plan_component(name), []).append(name)
    twice = [names for names in components.values() if len(names) > 1]
    if twice:
        raise ValueError(f"grid names one plan component twice: {twice[0]}; keep one name")
    if "nu" in out and ({"nu_fat", "nu_muscle"} & set(out)):
        raise ValueError(
            "grid may sweep either the homogeneous 'nu' or the per-tissue 'nu_fat'/'nu_muscle', "
            f"not both; got {sorted(out)}"
        )
    return out



def parse_grid(items):
    """Parse ``NAME=V1,V2,...`` or ``NAME=START:STOP:NUM`` (inclusive linspace) strings.

    Raises
    ------
    ValueError
        An item that is not ``NAME=VALUES``, or a range whose START/STOP are not numbers
        or whose NUM is not a positive integer; the message names the item.

    Examples
    --------
    >>> from pvcmf.study.parameters import parse_grid
    >>> parse_grid(["nu=0:0.4:3", "n_tets=10000,30000"])
    {'nu': (0.0, 0.2, 0.4), 'n_tets': (10000, 30000)}
    >>> parse_grid(["nu=0:0.4:abc"])
    Traceback (most recent call last):
    ...
    ValueError: grid item 'nu=0:0.4:abc': NUM must be a positive integer (START:STOP:NUM), got 'abc'
    """
    if isinstance(items, (str, bytes)):
        items = [items]
    grid = {}
    for item in items:
        name, sep, text = str(item).partition("=")
        name = name.strip()
        if not sep or not name or not text.strip():
            raise ValueError(f"grid items must look like NAME=V1,V2 or NAME=START:STOP:NUM, got {item!r}")
        if name in grid:
            raise ValueError(f"grid item {item!r}: {name!r} is given twice")
        if ":" in text:
            values = _parse_range(item, text)
        else:
            values = [_parse_value(v.strip()) for v in text.split(",") if v.strip()]
        grid[name] = values
    return validate_grid(grid)


def _parse_range(item, text):
    """The values of ``START:STOP:NUM`` (inclusive linspace); errors name ``item``."""
    parts = [p.strip() for p in text.split(":")]
    if len(parts) != 3:
        raise ValueError(f"grid item {item!r}: a range must be START:STOP:NUM (three parts), "
                         f"got {len(parts)} parts")
    bounds = []
    for label, part in zip(("START", "STOP"), parts[:2]):
        try:
            bounds.append(float(part))
        except ValueError:
            raise ValueError(f"grid item {item!r}: {label} must be a number (START:STOP:NUM), "
                             f"got {part!r}") from None
        if not math.isfinite(bounds[-1]):
            raise ValueError(f"grid item {item!r}: {label} must be finite, got {part!r}")
    try:
        num = int(parts[2])
    except ValueError:
        num = 0
    if num <= 0:
        raise ValueError(f"grid item {item!r}: NUM must be a positive integer (START:STOP:NUM), "
                         f"got {parts[2]!r}")
    return [round(float(v), 10) for v in np.linspace(bounds[0], bounds[1], num)]


def _parse_value(text):
    if text.lower() in ("none",):
        return None
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text
