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

__all__ = ["METRICS", "PARAMETERS", "TIMES", "parse_grid", "validate_grid"]


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


#: Sweepable parameters: name -> (level, validator, meaning). ``mesh``-level parameters
#: make a new task (new mesh); ``solve``-level ones are looped over inside a task.
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
}

#: Metric columns every evaluation returns (|distance| statistics, mm and %).
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
    if "nu" in out and ({"nu_fat", "nu_muscle"} & set(out)):
        raise ValueError(
            "grid may sweep either the homogeneous 'nu' or the per-tissue 'nu_fat'/'nu_muscle', "
            f"not both; got {sorted(out)}"
        )
    return out



def parse_grid(items):
    """Parse ``NAME=V1,V2,...`` or ``NAME=START:STOP:NUM`` (inclusive linspace) strings.

    Examples
    --------
    >>> from pvcmf.study.parameters import parse_grid
    >>> parse_grid(["nu=0:0.4:3", "n_tets=10000,30000"])
    {'nu': (0.0, 0.2, 0.4), 'n_tets': (10000, 30000)}
    """
    grid = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not text.strip():
            raise ValueError(f"grid items must look like NAME=V1,V2 or NAME=START:STOP:NUM, got {item!r}")
        if ":" in text:
            parts = text.split(":")
            if len(parts) != 3:
                raise ValueError(f"grid range must be START:STOP:NUM, got {item!r}")
            start, stop, num = float(parts[0]), float(parts[1]), int(parts[2])
            values = [round(float(v), 10) for v in np.linspace(start, stop, num)]
        else:
            values = [_parse_value(v.strip()) for v in text.split(",") if v.strip()]
        grid[name] = values
    return validate_grid(grid)


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

