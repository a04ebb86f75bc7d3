"""Parameter sweeps over cases and model parameters, run on Dask, cached on disk.

Paper 001 is a parameter study: Poisson ratio 0..0.495, mesh size, E_muscle/E_fat and
(nu_fat, nu_muscle) grids over many patients, judged by the 50/90/95 % percentiles of the
prediction error. :func:`sweep` runs such a study and returns a tidy
:class:`pandas.DataFrame` (one row per case and parameter set).

What is evaluated is pluggable (``evaluate=``):

* the default, :class:`PipelineEvaluation`: virtual patient -> segmentation -> muscles ->
  labelled mesh -> materials -> plan -> MTM solve -> signed distance to the case's
  post-operative skin (the pvcmf pipeline);
* any ``f(case, **params) -> dict`` (one call per case and parameter set), or an object
  with ``prepare(case, **group_params) -> state`` and ``evaluate(state, **params) -> dict``
  (see :class:`Evaluation`), for which the expensive ``prepare`` runs once per task;
* :func:`synthetic_evaluate`, a cheap deterministic pure-numpy stand-in with the shape of
  the real study (optimum near nu 0.46, error settling with the mesh size), for tests and
  documentation.

Work split. Parameters are of two levels (:data:`PARAMETERS`): *mesh* level (image
spacing, tetrahedra count, region of interest, ...) change the mesh; *solve* level (Poisson
ratios, Young's modulus ratio, solver tolerance, ...) only change the material. One Dask
task is made per case and mesh-level combination; it prepares the case's mesh, stiffness
structure and solver once and loops over the solve-level values, so a Poisson sweep
refactors numerically only.

Scheduling is delegated to Dask (``dask.distributed``): by default a local cluster of
single-threaded worker *processes* on this machine (gmsh has one global model, so threads
mesh one at a time behind a lock in :mod:`pvcmf.filters.meshing`, and the pipeline is
numpy/VTK work that holds the GIL in places, so processes are the default; ``scheduler="threads"`` runs an in-process cluster of
threads, ``"synchronous"`` runs in this process without Dask, for debugging);
``scheduler="tcp://host:8786"`` or a :class:`distributed.Client` runs the same sweep on a
cluster. Tasks carry ``retries``; a task whose worker dies is rescheduled by Dask on
another worker.

Caching: every (case, parameter set) result is written to ``cache_dir`` as one ``.npz``
file named by a SHA-256 of (case identity, parameters, evaluation identity, code version)
as soon as its task finishes, atomically (temporary file + rename); a rerun loads those and
sends only the missing points to Dask, so a finished sweep recomputes nothing and an
interrupted one restarts where it stopped.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import itertools
import json
import logging
import math
import numbers
import os
import tempfile
import time
import uuid
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = [
    "PARAMETERS",
    "METRICS",
    "Evaluation",
    "FunctionEvaluation",
    "PipelineEvaluation",
    "sweep",
    "validate_grid",
    "study_truth",
    "code_version",
    "source_hash",
    "error_statistics",
    "synthetic_evaluate",
    "synthetic_skin",
    "save_table",
    "load_table",
    "parse_grid",
    "add_sweep_parser",
    "run_sweep",
]

# --------------------------------------------------------------------------- parameters


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
METRICS = ("p50", "p90", "p95", "median", "mean_abs", "rms", "within_1mm", "within_2mm", "n_skin")
#: Timing columns (s): ``t_prepare`` is the task's shared cost (mesh, structure), once per
#: task and repeated on each of its rows (a prepared case loaded from
#: ``PipelineEvaluation(cache_dir=...)`` reports what preparing it cost when it was made); ``t_eval`` the cost of this row's parameter set;
#: ``cpu_*`` the same as CPU time of the worker process (what a loaded machine does not
#: inflate: wall time there includes waiting for a core).
TIMES = ("t_prepare", "t_eval", "cpu_prepare", "cpu_eval")


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
    >>> from pvcmf.sweeps import validate_grid
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


# --------------------------------------------------------------------------- statistics


def error_statistics(distance):
    """Statistics of a signed error map, as paper 001 reports them (one sweep row).

    Delegates to :func:`pvcmf.validation.summary`, renaming its point count ``n`` to
    ``n_skin``.

    Parameters
    ----------
    distance : array_like
        Signed point-to-surface distances, mm (NaN entries are ignored).

    Returns
    -------
    dict
        ``p50``, ``p90``, ``p95`` (percentiles of ``|distance|``, mm), ``median`` (signed),
        ``mean_abs``, ``rms`` (mm), ``within_1mm``, ``within_2mm`` (% of points with
        ``|d| <= 1`` and ``<= 2`` mm) and ``n_skin`` (number of points).

    Raises
    ------
    ValueError
        If there is no finite distance.

    Examples
    --------
    >>> from pvcmf.sweeps import error_statistics
    >>> s = error_statistics([0.5, -1.5, 3.0, 0.0])
    >>> s["within_1mm"], s["within_2mm"]
    (50.0, 75.0)
    """
    from pvcmf.validation import summary

    d = np.asarray(distance, dtype=float).ravel()
    if not np.isfinite(d).any():
        raise ValueError("distance must hold at least one finite value, got none")
    stats = summary(d)
    stats["n_skin"] = int(stats.pop("n"))
    return stats


# --------------------------------------------------------------------------- evaluations


class Evaluation:
    """What a sweep computes for one case: ``prepare`` once per task, ``evaluate`` per point.

    Subclass and implement both. ``prepare(case, **group_params)`` receives the case (as
    given to :func:`sweep`) and the mesh-level parameters of the task and returns any
    state (mesh, factorised solver, ...); ``evaluate(state, **params)`` receives it with
    the solve-level parameters and returns a dict with at least the :data:`METRICS` (use
    :func:`error_statistics`); values may also be numpy arrays (e.g. the per-point
    ``distance`` map Fig. 5 needs), kept in the cache and, with ``keep_arrays=True``, in
    the table. ``identity()`` returns what, besides the code version, makes results
    differ (constructor options); it enters the cache key.
    """

    #: bump to invalidate cached results of this evaluation
    version = "1"

    def prepare(self, case, **group_params):  # pragma: no cover - interface
        raise NotImplementedError

    def evaluate(self, state, **params):  # pragma: no cover - interface
        raise NotImplementedError

    def identity(self):
        """Options that change results (JSON-serialisable); part of the cache key."""
        return {"class": f"{type(self).__module__}.{type(self).__qualname__}", "version": self.version}


class FunctionEvaluation(Evaluation):
    """Wrap ``func(case, **params) -> dict`` as an :class:`Evaluation` (no shared state)."""

    def __init__(self, func):
        if not callable(func):
            raise TypeError(f"evaluate must be callable or an Evaluation, got {type(func).__name__}")
        self.func = func

    def prepare(self, case, **group_params):
        return case, group_params

    def evaluate(self, state, **params):
        case, group_params = state
        return self.func(case, **group_params, **params)

    def identity(self):
        func = self.func
        if isinstance(func, functools.partial):  # the bound arguments change results too
            return {"partial": FunctionEvaluation(func.func).identity(),
                    "args": repr(func.args), "keywords": repr(sorted(func.keywords.items()))}
        target = func if inspect.isfunction(func) or inspect.ismethod(func) else type(func)
        name = f"{getattr(target, '__module__', '?')}.{getattr(target, '__qualname__', repr(target))}"
        try:
            source = inspect.getsource(target)
        except (OSError, TypeError):
            source = name
        options = getattr(func, "identity", None)
        return {
            "function": name,
            "source": hashlib.sha256(source.encode()).hexdigest()[:16],
            "options": options() if callable(options) else None,
            "version": getattr(func, "version", "1"),
        }


def _case_seed(case, salt=0):
    label, identity = _case_identity(case)
    return zlib.crc32(f"{identity}|{salt}".encode())


def synthetic_evaluate(case, *, nu=0.46, n_tets=30_000, E_ratio=1.0, nu_fat=None, nu_muscle=None,
                       spacing=1.0, tol=1e-8, n_skin=2000, **ignored):
    """A cheap deterministic stand-in for the pipeline, pure numpy (tests, docs, demos).

    Builds a fixed signed "error map" on ``n_skin`` points of a unit half-sphere "face"
    whose dependence on the parameters has the shape of paper 001's results: each point
    has its own optimal Poisson ratio (0.1 on the lips, ~0.47 on the cheeks) around a case
    optimum near 0.46, the error settles as ``1/sqrt(n_tets)`` with the mesh size, the
    Young's modulus ratio barely matters, and coarser images add noise. Nothing is
    random at run time: the case identity seeds the map.

    Parameters
    ----------
    case : int, str or mapping
        Case spec (seeds the map).
    nu, nu_fat, nu_muscle : float
        Poisson ratio(s); with ``nu_fat``/``nu_muscle`` the effective ratio is their
        60/40 fat/muscle mix.
    n_tets : int
        Mesh size.
    E_ratio : float
        E_muscle / E_fat.
    spacing, tol : float
        Image resolution (mm) and solver tolerance; both add a small error.
    n_skin : int
        Number of "skin" points.

    Returns
    -------
    dict
        :func:`error_statistics` of the map, plus ``distance`` (the map, an array on
        the points of :func:`synthetic_skin`) and ``n_cells`` (= ``n_tets``).

    Examples
    --------
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> a = synthetic_evaluate(1, nu=0.46)["p90"]
    >>> b = synthetic_evaluate(1, nu=0.0)["p90"]
    >>> bool(a < b)
    True
    """
    rng = np.random.default_rng(_case_seed(case))
    pts, theta = _synthetic_points(n_skin)
    lips = np.exp(-((pts[:, 2] + 0.3) ** 2 + pts[:, 0] ** 2) / 0.05)
    case_opt = 0.46 + rng.uniform(-0.03, 0.02)
    nu_opt = case_opt * (1 - lips) + 0.1 * lips
    slope = rng.uniform(2.0, 6.0) * (0.3 + pts[:, 1] ** 2)
    base = rng.normal(0.0, rng.uniform(0.6, 0.9), n_skin)
    if nu_fat is not None or nu_muscle is not None:
        nu = 0.6 * (0.485 if nu_fat is None else nu_fat) + 0.4 * (0.43 if nu_muscle is None else nu_muscle)
        nu += 0.2 * (0.485 - (0.485 if nu_fat is None else nu_fat)) ** 2
    err = base + slope * (nu - nu_opt) ** 2 * np.sign(base + 1e-12)
    err += 15.0 / np.sqrt(n_tets) * np.sign(base + 1e-12) * (1 + 0.3 * np.cos(3 * theta))
    err += 0.002 * np.log(E_ratio) * np.sign(base + 1e-12)
    err += 0.05 * (spacing - 1.0) * rng.normal(0.0, 1.0, n_skin) + min(tol, 1.0) * 10.0
    out = error_statistics(err)
    out.update(distance=err, n_cells=int(n_tets))
    return out


def _synthetic_points(n_skin):
    """Fibonacci points on the unit half sphere y >= 0, and their azimuth."""
    k = np.arange(n_skin) + 0.5
    phi = np.arccos(1 - k / n_skin)
    theta = np.pi * (1 + 5**0.5) * k
    pts = np.c_[np.sin(phi) * np.cos(theta), np.cos(phi), np.sin(phi) * np.sin(theta)]
    return pts, theta


synthetic_evaluate.version = "1"


def synthetic_skin(n_skin=2000):
    """The "face" of :func:`synthetic_evaluate`: a triangulated half sphere, same point order.

    Parameters
    ----------
    n_skin : int
        Number of points (must match the ``n_skin`` given to :func:`synthetic_evaluate`).

    Returns
    -------
    pyvista.PolyData
        Unit half sphere (``y >= 0`` faces anterior), triangulated over its (x, z)
        projection.

    Examples
    --------
    >>> from pvcmf.sweeps import synthetic_skin, synthetic_evaluate
    >>> synthetic_skin(500).n_points == synthetic_evaluate(1, n_skin=500)["distance"].size
    True
    """
    import pyvista as pv
    from scipy.spatial import Delaunay

    pts, _ = _synthetic_points(int(n_skin))
    tri = Delaunay(pts[:, [0, 2]]).simplices
    faces = np.c_[np.full(len(tri), 3), tri].ravel()
    return pv.PolyData(pts, faces)


def _resolve_evaluation(evaluate):
    if evaluate is None:
        return PipelineEvaluation()
    if isinstance(evaluate, Evaluation):
        return evaluate
    if hasattr(evaluate, "prepare") and hasattr(evaluate, "evaluate"):
        return evaluate
    return FunctionEvaluation(evaluate)


# --------------------------------------------------------------------------- the pipeline


class PipelineEvaluation(Evaluation):
    """The pvcmf pipeline as a sweep evaluation (the default of :func:`sweep`).

    ``prepare(case, spacing=, n_tets=, roi=, conforming=)`` builds the virtual patient
    (``case`` is a patient number for :func:`pvcmf.datasets.phantom`, a mapping of its
    arguments, or a ``Case``) and runs :func:`pvcmf.pipeline.simulate` once *without
    solving* (``solve=False``: segmentation, muscles, labelled mesh, materials, plan ->
    boundary conditions, pre-operative skin), then keeps what does not depend on the
    material: the face skin, the post-operative truth cropped to the face and oriented
    (:class:`_TruthSurface`), and, built on first use, the skin mapping operator
    (:class:`pvcmf.filters.surface_mapping.SurfaceMapping`, per ``sigma``) and a :class:`pvcmf.mtm.Solver` (geometry,
    block pattern, elimination maps, symbolic factorisation; per ``method``/``tol``).
    ``evaluate(state, nu=..., ...)`` then only sets the materials of the parameter set
    (:meth:`materials`), refactorises numerically, solves, applies the mapping operator
    and measures the signed distance to the truth (:func:`pvcmf.filters.distance.signed_distance`).

    Parameters
    ----------
    spacing : float
        Default image resolution (mm) when the grid does not sweep ``spacing``; default
        2 mm, the study default at which :func:`pvcmf.reference.postop_skin` caches the
        truths.
    n_tets : int
        Default tetrahedra count when the grid does not sweep ``n_tets``.
    method : str
        Default MTM solver (``"direct"``; the grid may sweep ``method`` and ``tol``).
    keep_distance : bool
        Return the per-point ``distance`` map and the skin (``skin_points``,
        ``skin_faces``) with every row (for Fig. 5).
    truth : callable, optional
        ``truth(case) -> pyvista.PolyData``: the case's post-operative skin in the
        pre-operative frame. Default: the case's ``postop_skin`` attribute, else the
        virtual post-operative truth of :mod:`pvcmf.reference`. Must be picklable (a
        module-level function, e.g. :func:`study_truth`) to run on Dask workers.
    region : {'face', 'skin'}
        Where errors are measured: ``'face'`` (default) the skin points of the face
        regions of :func:`pvcmf.validation.label_face_regions` (nose, lips, chin,
        cheeks: what the surgery changes and the paper measures; the back of the head
        would dilute the percentiles with zeros), ``'skin'`` the whole skin.
    cache_dir : str or Path, optional
        Keep each prepared case (mesh with boundary conditions, skin, post-operative
        skin; VTK XML files) under a hash of (case, mesh-level parameters, options, code
        version), so later sweeps on the same meshes (Figs. 2, 4, 5, the trade
        benchmark) skip the phantom, segmentation, muscles and meshing.
    mesh_threads : int, default 1
        gmsh threads per task. A sweep runs one task per worker process and as many
        workers as cores, so more threads only oversubscribe the machine.
    """

    version = "3"

    def __init__(self, spacing=2.0, n_tets=30_000, method="direct", keep_distance=False,
                 truth=None, region="face", cache_dir=None, mesh_threads=1):
        self.cache_dir = None if cache_dir is None else str(cache_dir)
        if region not in ("face", "skin"):
            raise ValueError(f"region must be 'face' or 'skin', got {region!r}")
        self.region = region
        self.spacing = _positive("spacing", spacing)
        self.n_tets = _positive_int("n_tets", n_tets)
        self.method = _solver_method("method", method)
        self.keep_distance = bool(keep_distance)
        if truth is not None and not callable(truth):
            raise TypeError(f"truth must be callable(case) -> PolyData or None, got {type(truth).__name__}")
        self.truth = truth
        if isinstance(mesh_threads, bool) or not isinstance(mesh_threads, numbers.Integral) \
                or mesh_threads < 1:
            raise ValueError(f"mesh_threads must be an integer >= 1, got {mesh_threads!r}")
        self.mesh_threads = int(mesh_threads)

    def identity(self):
        truth = None if self.truth is None else FunctionEvaluation(self.truth).identity()
        own = "".join(inspect.getsource(o) for o in (type(self), _TruthSurface, _skin_mapping,
                                                     _face_only, _postop_skin, error_statistics))
        return {**super().identity(), "spacing": self.spacing, "n_tets": self.n_tets,
                "method": self.method, "keep_distance": self.keep_distance, "truth": truth,
                "region": self.region, "mesh_threads": self.mesh_threads,
                "code": source_hash(), "own": hashlib.sha256(own.encode()).hexdigest()[:16]}

    def prepare(self, case, *, spacing=None, n_tets=None, roi=None, conforming=True, n_points=None):
        group = {"spacing": self.spacing if spacing is None else spacing,
                 "n_tets": self.n_tets if n_tets is None else n_tets,
                 "roi": roi, "conforming": conforming, "n_points": n_points}
        if self.cache_dir is None:
            return self._finish(self._timed_prepare(case, group))
        _, ident = _case_identity(case)
        what = {k: v for k, v in self.identity().items() if k not in ("method", "keep_distance")}
        folder = Path(self.cache_dir) / _point_key(ident, group, what, code_version())
        names = {"grid": "grid.vtu", "skin": "skin.vtp", "postop": "postop.vtp"}
        if (folder / "done").exists():
            try:
                import pyvista as pv

                state = {k: pv.read(folder / f) for k, f in names.items()}
                times = folder / "times.json"
                if times.exists():  # report what the preparation cost, not the loading
                    state["prepare_times"] = json.loads(times.read_text())
                log.info("prepared case %s loaded from %s", ident, folder)
                return self._finish(state)
            except Exception as err:  # unreadable: prepare again
                log.warning("ignoring unreadable prepared case %s (%s)", folder, err)
        state = self._timed_prepare(case, group)
        Path(self.cache_dir).mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=Path(self.cache_dir).resolve(), prefix=".tmp-"))
        try:
            for k, f in names.items():
                state[k].save(tmp / f)
            (tmp / "times.json").write_text(json.dumps(state["prepare_times"]))
            (tmp / "done").touch()
            if folder.exists():
                import shutil

                shutil.rmtree(folder, ignore_errors=True)
            os.replace(tmp, folder)
        except OSError as err:  # another task won the race, or a full disk: keep computing
            log.warning("could not cache prepared case in %s (%s)", folder, err)
        finally:
            if tmp.exists():
                import shutil

                shutil.rmtree(tmp, ignore_errors=True)
        return self._finish(state)

    def _timed_prepare(self, case, group):
        _warm_up()  # once per worker process, outside the timed preparation
        t0, c0 = time.perf_counter(), time.process_time()
        state = self._prepare(case, **group)
        state["prepare_times"] = {"t_prepare": time.perf_counter() - t0,
                                  "cpu_prepare": time.process_time() - c0}
        return state

    @staticmethod
    def _finish(state):
        """Add the material-independent operators to a prepared (or loaded) state."""
        t0 = time.perf_counter()
        truth = _TruthSurface(state["postop"], np.asarray(state["skin"].points, float))
        log.info("truth cropped to the face: %d of %d points (%.2f s)", truth.surface.n_points,
                 state["postop"].n_points, time.perf_counter() - t0)
        return {"solvers": {}, **state, "truth": truth, "mappings": {}}

    def _prepare(self, case, *, spacing, n_tets, roi, conforming, n_points):
        import pvcmf
        from pvcmf.pipeline import simulate

        if isinstance(case, numbers.Integral):
            case = pvcmf.datasets.phantom(patient=int(case), spacing=spacing)
        elif isinstance(case, Mapping):
            case = pvcmf.datasets.phantom(**{"spacing": spacing, **case})
        postop = _postop_skin(case) if self.truth is None else self.truth(case)
        mesh_options = {"threads": self.mesh_threads}
        if roi is not None:  # the soft tissue within `roi` mm of the (first) moved segment
            mesh_options["roi"] = (case.plan.osteotomies[0].segment_id, roi)
        if not conforming:
            mesh_options["conforming"] = False
        # no solve, no predicted skin, no skeleton: evaluate() solves per parameter set
        result = simulate(case.ct, case.plan, bones=getattr(case, "truth", None),
                          landmarks=getattr(case, "landmarks", None), n_tets=n_tets,
                          mesh_options=mesh_options, figures=False, solve=False)
        if result.mesh is None or result.skin_pre is None:
            raise RuntimeError(f"the pipeline did not produce a mesh and skin for {case.name!r}; "
                               f"skipped steps: {result.skipped}")
        grid = result.mesh
        if not conforming and n_points:
            grid = grid.cmf.sample_muscle_fraction(result.labels, n_points=n_points)
        skin = result.skin_pre
        if self.region == "face":
            skin = _face_only(skin, getattr(case, "landmarks", None))
        return {"grid": grid, "skin": skin, "postop": postop}

    @staticmethod
    def materials(grid, *, nu=None, nu_fat=None, nu_muscle=None, E_ratio=None, E_fat=None,
                  E_muscle=None):
        """Per-cell material overrides of one parameter set (paper 001 sec. 2.1 / 2.2).

        ``nu``: homogeneous isotropic material (E = ``E_fat`` or 1; the displacement-driven
        MTM does not depend on E). Any of ``nu_fat``, ``nu_muscle``, ``E_ratio``, ``E_fat``,
        ``E_muscle``: isotropic fat and muscle (defaults nu_fat 0.485, nu_muscle 0.43,
        E_muscle = E_ratio * E_fat), mixed per cell by ``muscle_fraction`` when the grid
        has it (the baselines) or by the cell's ``tissue`` label. None of them: the grid's
        own materials (``{}``).
        """
        from pvcmf import arrays

        if nu is not None:
            e = 1.0 if E_fat is None else E_fat
            return {"E_fiber": e, "E_cross": e, "nu": nu}
        if all(v is None for v in (nu_fat, nu_muscle, E_ratio, E_fat, E_muscle)):
            return {}
        if arrays.MUSCLE_FRACTION in grid.cell_data.keys():
            f = np.clip(np.asarray(grid.cell_data[arrays.MUSCLE_FRACTION], float), 0.0, 1.0)
        else:
            tissue = arrays.require_array(grid, arrays.TISSUE, "cell", producer="tetrahedralize")
            f = (np.asarray(tissue) == arrays.MUSCLE_TISSUE).astype(float)
        e_fat = 1.0 if E_fat is None else E_fat
        e_muscle = E_muscle if E_muscle is not None else e_fat * (1.0 if E_ratio is None else E_ratio)
        e = (1 - f) * e_fat + f * e_muscle
        nu_cells = (1 - f) * (0.485 if nu_fat is None else nu_fat) + f * (0.43 if nu_muscle is None else nu_muscle)
        return {"E_fiber": e, "E_cross": e, "nu": nu_cells}

    def evaluate(self, state, *, nu=None, nu_fat=None, nu_muscle=None, E_ratio=None, E_fat=None,
                 E_muscle=None, tol=None, method=None, sigma=None):
        from pvcmf import mtm

        if "truth" not in state:  # a state built by hand: add the reusable operators
            state.update(self._finish(state))
        grid = state["grid"]
        method = self.method if method is None else method
        key = (method, tol)
        material = self.materials(grid, nu=nu, nu_fat=nu_fat, nu_muscle=nu_muscle, E_ratio=E_ratio,
                                  E_fat=E_fat, E_muscle=E_muscle)
        solver = state["solvers"].get(key)
        if solver is None:  # first parameter set of this method: structure + symbolic analysis
            options = {} if tol is None else {"tol": tol}
            solver = state["solvers"][key] = mtm.Solver(grid, method, **options, **material)
        elif material:  # no symbolic analysis; direct: the previous factor preconditions CG
            # (to the same tolerance; it refactors when that needs > 20 iterations)
            solver.update_materials(**material, refactor=False)
        u = solver.solve()
        t_solve = float(solver.info.get("time", np.nan))
        mapping = state["mappings"].get(sigma)
        if mapping is None:  # the mapping does not depend on the material: once per sigma
            mapping = state["mappings"][sigma] = _skin_mapping(grid.points, state["skin"].points,
                                                               sigma)
        pred = np.asarray(state["skin"].points, float) + mapping(u)
        d = state["truth"].distance(pred)
        out = error_statistics(d)
        out.update(n_cells=int(grid.n_cells), t_solve=t_solve,
                   residual=float(solver.info.get("residual", np.nan)))
        if self.keep_distance:
            skin = state["skin"]
            out.update(distance=d, skin_points=np.asarray(skin.points, float),
                       skin_faces=np.asarray(skin.faces))
        return out


_WARM = []


def _warm_up():
    """Import the pipeline's modules (and load the muscle atlas) once per process, so the
    first task of a worker does not report the imports as its preparation time."""
    if _WARM:
        return
    import importlib

    from pvcmf import filters

    for name in filters.__all__ if hasattr(filters, "__all__") else ():
        with contextlib.suppress(Exception):
            getattr(filters, name)
    for module in ("pvcmf.mtm", "pvcmf.pipeline", "pvcmf.validation", "pvcmf.reference",
                   "pyamg", "gmsh", "vtk"):
        with contextlib.suppress(Exception):
            importlib.import_module(module)
    with contextlib.suppress(Exception):
        from pvcmf import atlas

        atlas.default()
    _WARM.append(True)


def study_truth(case, *, spacing=None, n_tets=None):
    """The post-operative truth of the study for any image spacing of a virtual patient.

    :func:`pvcmf.reference.postop_skin` of ``phantom(case.patient, spacing=spacing)``
    (default :data:`STUDY_SPACING`, whose truths are cached; ``n_tets``: the truth's mesh
    size, default that of ``postop_skin``), whatever ``case.spacing`` is: a sweep over the
    image resolution must judge every resolution against the same truth. A module-level
    function, so it travels to Dask workers (``PipelineEvaluation(truth=study_truth)``, or
    ``functools.partial(study_truth, spacing=2.0, n_tets=16000)``).
    """
    import pvcmf
    from pvcmf import reference

    spacing = STUDY_SPACING if spacing is None else float(spacing)
    options = {} if n_tets is None else {"n_tets": int(n_tets)}
    if float(case.spacing) == spacing:
        return reference.postop_skin(case, **options)
    return reference.postop_skin(pvcmf.datasets.phantom(patient=case.patient, spacing=spacing),
                                 **options)


#: image spacing (mm) of the study's virtual patients, at which the truths are cached
STUDY_SPACING = 2.0
#: the truth is cropped to the points within this distance (mm) of the pre-operative face:
#: far more than any predicted displacement (< 20 mm) plus any error, so every predicted
#: point's closest truth point is kept (tested against the uncropped distance)
TRUTH_MARGIN = 40.0


class _TruthSurface:
    """The truth, oriented outward once and cropped to the face, for repeated distances.

    The exact point-to-triangle distance of :func:`pvcmf.filters.distance_to`, for every
    query point whose closest truth point lies within ``margin`` of ``near``, but with the
    orientation, the crop and VTK's cell locator (``vtkImplicitPolyDataDistance``, sign
    from the closest cell's normal) built once per truth instead of once per call. A
    closed truth is oriented by its signed volume before cropping; an open one (or one
    with inconsistent winding) is left to :func:`pvcmf.filters.distance_to` on each call.
    """

    def __init__(self, surface, near, margin=TRUTH_MARGIN):
        import pyvista as pv
        from scipy.spatial import cKDTree

        self.closed = surface.n_open_edges == 0 if isinstance(surface, pv.PolyData) else False
        self._full = surface
        self._implicit = None
        self.surface = surface
        if not self.closed:  # a crop of an open surface cannot be oriented reliably
            return
        surf = surface.triangulate() if not surface.is_all_triangles else surface
        tris = np.asarray(surf.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
        pts = np.asarray(surf.points, float)
        directed = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
                           @ np.array([len(pts), 1]))
        if (directed[1:] == directed[:-1]).any():  # inconsistent winding: leave it to distance_to
            self.closed = False
            return
        a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
        if np.einsum("ij,ij->", a - pts.mean(axis=0), np.cross(b - a, c - a)) < 0:
            tris = tris[:, ::-1]  # outward: positive signed volume
        dist, _ = cKDTree(np.asarray(near, float)).query(pts, distance_upper_bound=margin)
        kept = tris[np.isfinite(dist)[tris].all(axis=1)]
        used = np.unique(kept)
        new_id = np.full(len(pts), -1)
        new_id[used] = np.arange(used.size)
        self.surface = pv.PolyData(pts[used], np.c_[np.full(len(kept), 3), new_id[kept]].ravel())

    def distance(self, points):
        """Signed distances (mm) of ``(n, 3)`` points, positive outside (anterior)."""
        import pyvista as pv

        from pvcmf import arrays
        from pvcmf.filters import distance_to

        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if not self.closed:  # cannot orient a crop of an open surface reliably
            return np.asarray(distance_to(pv.PolyData(points), self._full).point_data[arrays.DISTANCE])
        import vtk
        from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

        if self._implicit is None:  # VTK's cell locator, built once per truth
            self._implicit = vtk.vtkImplicitPolyDataDistance()
            self._implicit.SetInput(self.surface)
        out = vtk.vtkDoubleArray()
        self._implicit.FunctionValue(numpy_to_vtk(points, deep=True), out)
        return vtk_to_numpy(out).astype(np.float64, copy=True)


def _skin_mapping(grid_points, skin_points, sigma):
    """:func:`pvcmf.filters.map_to_surface` as its precomputed sparse operator
    (:class:`pvcmf.filters.surface_mapping.SurfaceMapping`, built once per mesh and sigma:
    the weights do not depend on the material)."""
    import inspect

    from pvcmf.filters.surface_mapping import SurfaceMapping, map_to_surface

    if sigma is None:
        sigma = inspect.signature(map_to_surface).parameters["sigma"].default
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 mm, got {sigma}")
    return SurfaceMapping(grid_points, skin_points, sigma, 3.0 * sigma)


def _face_only(skin, landmarks):
    """The face regions of a skin (:func:`pvcmf.validation.label_face_regions`)."""
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.validation import label_face_regions

    labelled = label_face_regions(skin, landmarks=landmarks)
    face = np.asarray(labelled.point_data[arrays.REGION]) > 0
    if not face.any():
        raise ValueError("no skin point lies in a face region; use region='skin'")
    if not labelled.is_all_triangles:
        labelled = labelled.triangulate()
    tri = np.asarray(labelled.faces).reshape(-1, 4)[:, 1:]
    new_id = np.cumsum(face) - 1
    kept = new_id[tri[face[tri].all(axis=1)]]
    out = pv.PolyData(np.asarray(labelled.points)[face],
                      np.c_[np.full(len(kept), 3), kept].ravel() if len(kept) else None)
    for name in labelled.point_data.keys():
        out.point_data[name] = np.asarray(labelled.point_data[name])[face]
    return out


def _postop_skin(case):
    skin = getattr(case, "postop_skin", None)
    if skin is not None:
        return skin
    try:
        from pvcmf import reference
    except ImportError as err:
        raise ValueError(
            f"case {getattr(case, 'name', case)!r} has no post-operative skin (attribute "
            f"'postop_skin') and pvcmf.reference is not available ({err}); pass "
            "PipelineEvaluation(truth=callable) to measure errors"
        ) from err
    return reference.postop_skin(case)


# --------------------------------------------------------------------------- cases, keys


def _case_identity(case):
    """Return (label for the table, identity string for the cache key) of a case."""
    if isinstance(case, bool):
        raise TypeError(f"cases must be patient numbers, names, mappings or Case objects, got {case!r}")
    if isinstance(case, numbers.Integral):
        return f"P{int(case)}", f"phantom(patient={int(case)})"
    if isinstance(case, str):
        return case, f"name:{case}"
    if isinstance(case, Mapping):
        text = json.dumps(dict(case), sort_keys=True, default=str)
        return str(case.get("name", text)), f"spec:{text}"
    name = getattr(case, "name", None)
    ct = getattr(case, "ct", None)
    if name is not None and ct is not None:
        h = hashlib.sha256()
        for attr in ("dimensions", "spacing", "origin"):
            h.update(repr(tuple(getattr(ct, attr, ()))).encode())
        h.update(np.ascontiguousarray(ct.point_data.get("ct", np.zeros(0))).tobytes())
        return str(name), f"case:{name}:{h.hexdigest()[:24]}"
    if name is not None:
        return str(name), f"object:{name}"
    raise TypeError(
        "cases must be patient numbers, names, mappings or objects with a 'name' "
        f"(and 'ct'), got {type(case).__name__}"
    )


#: the parts of pvcmf whose code changes what the pipeline computes (relative to the
#: package): their sources enter :class:`PipelineEvaluation`'s cache identity. Figures,
#: command line, I/O and the sweep engine itself do not change a result, so editing them
#: keeps every cached sweep.
RESULT_SOURCES = ("arrays.py", "atlas", "tps.py", "plan.py", "pipeline.py", "truth",
                  "study/statistics.py", "filters", "mtm", "datasets")

_SOURCE_HASHES = {}


def code_version():
    """Version of pvcmf for cache keys of every evaluation: the package version.

    What a result depends on beyond that is in its evaluation's identity
    (:meth:`Evaluation.identity`): :class:`PipelineEvaluation` hashes the sources of
    :data:`RESULT_SOURCES` and its own code (:func:`source_hash`), a plain function
    evaluation its function's source.
    """
    import pvcmf

    return str(pvcmf.__version__)


def source_hash(parts=RESULT_SOURCES):
    """SHA-256 (16 hex digits) of the pvcmf sources named in ``parts`` (files or folders).

    Examples
    --------
    >>> from pvcmf.sweeps import source_hash
    >>> len(source_hash(("arrays.py",)))
    16
    """
    parts = tuple(parts)
    if parts not in _SOURCE_HASHES:
        import pvcmf

        root = Path(pvcmf.__file__).parent
        h = hashlib.sha256()
        for part in parts:
            target = root / part
            files = sorted(target.rglob("*.py")) if target.is_dir() else [target]
            for path in files:
                h.update(str(path.relative_to(root)).encode())
                h.update(path.read_bytes())
        _SOURCE_HASHES[parts] = h.hexdigest()[:16]
    return _SOURCE_HASHES[parts]


def _point_key(case_identity, params, evaluation_identity, version):
    payload = json.dumps(
        {"case": case_identity, "params": params, "evaluation": evaluation_identity, "code": version},
        sort_keys=True, default=repr,
    )
    return hashlib.sha256(payload.encode()).hexdigest()


# --------------------------------------------------------------------------- cache


def _cache_path(cache_dir, key):
    return Path(cache_dir) / key[:2] / f"{key}.npz"


def _cache_load(cache_dir, key):
    path = _cache_path(cache_dir, key)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["__meta__"]))
            out = dict(meta)
            for name in data.files:
                if name != "__meta__":
                    out[name] = np.array(data[name])
        return out
    except Exception as err:  # a corrupt entry is recomputed, never trusted
        log.warning("ignoring unreadable cache entry %s (%s)", path, err)
        return None


def _cache_store(cache_dir, key, result):
    path = _cache_path(cache_dir, key)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta, arrays_ = {}, {}
    for name, value in result.items():
        if isinstance(value, np.ndarray):
            arrays_[name] = value
        else:
            meta[name] = value.item() if isinstance(value, np.generic) else value
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, __meta__=np.array(json.dumps(meta, default=repr)), **arrays_)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


# --------------------------------------------------------------------------- tasks


def _run_group(evaluation, case, group_params, points):
    """One Dask task: prepare the case once, evaluate every solve-level parameter set."""
    t0, c0 = time.perf_counter(), time.process_time()
    state = evaluation.prepare(case, **group_params)
    t_prepare, cpu_prepare = time.perf_counter() - t0, time.process_time() - c0
    recorded = state.get("prepare_times") if isinstance(state, Mapping) else None
    if recorded:  # a prepared case loaded from a cache reports what preparing it cost
        t_prepare, cpu_prepare = recorded["t_prepare"], recorded["cpu_prepare"]
    results = []
    for params in points:
        t1, c1 = time.perf_counter(), time.process_time()
        result = dict(evaluation.evaluate(state, **params))
        result["t_eval"] = time.perf_counter() - t1
        result["cpu_eval"] = time.process_time() - c1
        result["t_prepare"] = t_prepare
        result["cpu_prepare"] = cpu_prepare
        missing = [m for m in ("p50", "p90", "p95") if m not in result]
        if missing:
            raise ValueError(f"evaluation returned no {missing} for parameters {params}")
        results.append(result)
    return results


def _make_client(scheduler, n_tasks, n_workers, memory_limit):
    """Return (client, exit stack) for a scheduler spec; the stack closes what we opened."""
    from distributed import Client, LocalCluster

    stack = contextlib.ExitStack()
    if isinstance(scheduler, Client):
        return scheduler, stack
    if isinstance(scheduler, str) and "://" in scheduler:
        client = stack.enter_context(Client(scheduler, timeout="30s"))
        return client, stack
    cpus = os.cpu_count() or 1
    if scheduler in (None, "processes"):
        workers = n_workers or max(1, min(cpus, n_tasks))
        cluster = stack.enter_context(LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True,
            dashboard_address=None, memory_limit=memory_limit,
        ))
    elif scheduler == "threads":
        cluster = stack.enter_context(LocalCluster(
            n_workers=1, threads_per_worker=n_workers or cpus, processes=False,
            dashboard_address=None, memory_limit=memory_limit,
        ))
    else:
        raise ValueError(
            "scheduler must be None, 'processes', 'threads', 'synchronous', an address "
            f"'tcp://host:port' or a distributed.Client, got {scheduler!r}"
        )
    client = stack.enter_context(Client(cluster))
    return client, stack


def _progress(total, enabled, desc="sweep"):
    if not enabled:
        return contextlib.nullcontext(None)
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover - tqdm is in the sweep extra
        return contextlib.nullcontext(None)
    return tqdm(total=total, desc=desc, unit="point")


# --------------------------------------------------------------------------- sweep


def sweep(cases, grid, *, evaluate=None, scheduler=None, cache_dir=None, progress_bar=False,
          retries=2, keep_arrays=False, n_workers=None, memory_limit="auto", version=None,
          on_error="raise"):
    """Run a parameter study over cases and return a tidy table.

    Parameters
    ----------
    cases : sequence
        Cases: patient numbers of the virtual patients (``1``), names, spec mappings
        (``{"patient": 1, "spacing": 2.0}``) or ``Case`` objects (anything with a
        ``name``). A single case may be given alone.
    grid : mapping
        Parameter name -> list of values; the sweep runs the full product. Names and
        allowed values: :data:`PARAMETERS`. Checked by :func:`validate_grid` before
        anything runs.
    evaluate : callable or Evaluation, optional
        What to compute for a case and parameter set (see the module docstring);
        default :class:`PipelineEvaluation`.
    scheduler : None, str or distributed.Client
        ``None``/``"processes"``: a local Dask cluster of single-threaded worker
        processes; ``"threads"``: an in-process cluster of threads; ``"synchronous"``:
        no Dask, in this process; ``"tcp://host:8786"``: that Dask scheduler; a
        ``Client``: that client (left open).
    cache_dir : str or Path, optional
        Result cache; a rerun with the same cases, parameters and code loads results
        instead of computing them. ``None`` disables caching.
    progress_bar : bool
        Show a tqdm progress bar (points done / total).
    retries : int
        Dask retries of a task that raised; a task whose worker died is rescheduled.
    keep_arrays : bool
        Keep array results (e.g. the per-point ``distance`` map) as object columns.
    n_workers : int, optional
        Worker processes (threads for ``"threads"``) of a local cluster; default one per
        CPU, at most one per task.
    memory_limit : str
        Memory limit per worker of a local cluster (Dask syntax, e.g. ``"2GiB"``).
    version : str, optional
        Code version in the cache key; default :func:`code_version` (pvcmf's version).
        The evaluation's own identity adds what else its results depend on
        (:class:`PipelineEvaluation`: the sources of :data:`RESULT_SOURCES`), so code
        that changes results recomputes and code that does not (figures, CLI) does not.
    on_error : {'raise', 'skip'}
        A task that still fails after its retries: ``'raise'`` stops the sweep with a
        :class:`RuntimeError` naming the case; ``'skip'`` finishes the other tasks and
        gives the failed points NaN metrics and the message in an ``error`` column
        (failures are not cached, so a rerun tries them again).

    Returns
    -------
    pandas.DataFrame
        One row per case and parameter set, in case order then grid order: ``case``,
        the grid's parameters, :data:`METRICS`, ``n_cells`` when the evaluation gives it,
        :data:`TIMES` (s) and ``cached`` (loaded from the cache). ``df.attrs`` holds the
        grid, the number of tasks, points computed and loaded, and the wall time.

    Raises
    ------
    ValueError
        Invalid grid or cases (before anything runs).
    RuntimeError
        A task failed after its retries (``on_error='raise'``); results of finished
        tasks stay cached.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> df = pvcmf.sweep([1, 2], {"nu": [0.3, 0.46]}, evaluate=synthetic_evaluate,
    ...                  scheduler="synchronous")
    >>> df[["case", "nu"]].values.tolist()
    [['P1', 0.3], ['P1', 0.46], ['P2', 0.3], ['P2', 0.46]]
    """
    import pandas as pd

    t_start = time.perf_counter()
    grid = validate_grid(grid)
    if isinstance(cases, (str, bytes, Mapping, numbers.Integral)) or not isinstance(cases, Sequence):
        cases = [cases]
    cases = list(cases)
    if not cases:
        raise ValueError("cases must hold at least one case, got an empty list")
    identities = [_case_identity(c) for c in cases]
    labels = [lab for lab, _ in identities]
    if len(set(labels)) != len(labels):
        raise ValueError(f"cases must have distinct names, got {labels}")
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    if not isinstance(retries, numbers.Integral) or retries < 0:
        raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
    if scheduler is not None and not isinstance(scheduler, str):
        from distributed import Client

        if not isinstance(scheduler, Client):
            raise TypeError(f"scheduler must be None, a str or a distributed.Client, got {type(scheduler).__name__}")
    evaluation = _resolve_evaluation(evaluate)
    eval_identity = evaluation.identity()
    version = code_version() if version is None else str(version)

    group_names = [n for n in grid if PARAMETERS[n][0] == "mesh"]
    inner_names = [n for n in grid if PARAMETERS[n][0] == "solve"]
    group_combos = list(itertools.product(*(grid[n] for n in group_names)))
    inner_combos = list(itertools.product(*(grid[n] for n in inner_names)))

    # every point of the sweep, in output order, with its cache key
    points = []  # (case index, group params, inner params, key)
    for ci, (case, (_, ident)) in enumerate(zip(cases, identities)):
        for gvals in group_combos:
            gparams = dict(zip(group_names, gvals))
            for ivals in inner_combos:
                iparams = dict(zip(inner_names, ivals))
                key = _point_key(ident, {**gparams, **iparams}, eval_identity, version)
                points.append((ci, gparams, iparams, key))

    results, cached = {}, set()
    if cache_dir is not None:
        for _, _, _, key in points:
            hit = _cache_load(cache_dir, key)
            if hit is not None:
                results[key] = hit
                cached.add(key)

    # tasks: one per case and mesh-level combination, holding only the missing points
    tasks = {}
    for ci, gparams, iparams, key in points:
        if key in results:
            continue
        tkey = (ci, tuple(gparams.items()))
        tasks.setdefault(tkey, (ci, gparams, [], []))
        tasks[tkey][2].append(iparams)
        tasks[tkey][3].append(key)
    n_todo = sum(len(t[3]) for t in tasks.values())
    log.info("sweep: %d cases x %d parameter sets = %d points; %d cached, %d to compute in %d tasks",
             len(cases), len(group_combos) * len(inner_combos), len(points), len(cached), n_todo,
             len(tasks))

    failed = {}

    def accept(task, task_results):
        for key, res in zip(task[3], task_results):
            results[key] = res
            if cache_dir is not None:
                _cache_store(cache_dir, key, res)

    def fail(task, err):
        ci, gparams = task[0], task[1]
        message = (f"sweep task for case {labels[ci]!r} with {gparams or 'the default mesh'} "
                   f"failed: {type(err).__name__}: {err}")
        if on_error == "raise":
            raise RuntimeError(message) from err
        log.error("%s (skipped)", message)
        for key in task[3]:
            failed[key] = f"{type(err).__name__}: {err}"

    with _progress(len(points), progress_bar) as bar:
        if bar is not None:
            bar.update(len(cached))
        if tasks and scheduler == "synchronous":
            for task in tasks.values():
                ci, gparams, iparams_list, keys = task
                try:
                    outcome = _run_group(evaluation, cases[ci], gparams, iparams_list)
                except Exception as err:
                    fail(task, err)
                else:
                    accept(task, outcome)
                if bar is not None:
                    bar.update(len(keys))
        elif tasks:
            _run_on_dask(evaluation, cases, labels, tasks, accept, fail, bar, scheduler, retries,
                         n_workers, memory_limit)

    rows = []
    for ci, gparams, iparams, key in points:
        res = results.get(key, {"error": failed.get(key)})
        row = {"case": labels[ci], **gparams, **iparams}
        for name, value in res.items():
            if isinstance(value, np.ndarray) and not keep_arrays:
                continue
            if name in row:
                continue
            row[name] = value
        row["cached"] = key in cached
        rows.append(row)
    df = pd.DataFrame(rows)
    for m in ("p50", "p90", "p95"):
        if m not in df:
            df[m] = np.nan
    front = ["case", *grid, *[m for m in METRICS if m in df], *(["n_cells"] if "n_cells" in df else [])]
    back = [c for c in (*TIMES, "cached") if c in df]
    df = df[front + [c for c in df.columns if c not in front and c not in back] + back]
    df.attrs.update(
        grid={k: list(v) for k, v in grid.items()}, n_tasks=len(tasks), n_computed=n_todo,
        n_cached=len(cached), n_failed=len(failed), wall_time=time.perf_counter() - t_start,
    )
    log.info("sweep done in %.2f s (%d computed, %d from cache)", df.attrs["wall_time"], n_todo,
             len(cached))
    return df


def _run_on_dask(evaluation, cases, labels, tasks, accept, fail, bar, scheduler, retries,
                 n_workers, memory_limit):
    from distributed import as_completed

    client, stack = _make_client(scheduler, len(tasks), n_workers, memory_limit)
    with stack:
        run_id = uuid.uuid4().hex[:8]
        # big Case objects travel once per worker that needs them, not once per task
        shipped = {}
        for ci in {t[0] for t in tasks.values()}:
            case = cases[ci]
            small = isinstance(case, (numbers.Integral, str, Mapping))
            shipped[ci] = case if small else client.scatter(case, hash=False)
        futures = {}
        for n, (tkey, task) in enumerate(tasks.items()):
            ci, gparams, iparams_list, keys = task
            fut = client.submit(
                _run_group, evaluation, shipped[ci], gparams, iparams_list,
                key=f"pvcmf-sweep-{run_id}-{n}-{labels[ci]}", pure=False, retries=retries,
            )
            futures[fut] = task
        try:
            for fut in as_completed(list(futures)):
                task = futures[fut]
                try:
                    task_results = fut.result()
                except Exception as err:
                    fail(task, err)
                else:
                    accept(task, task_results)
                if bar is not None:
                    bar.update(len(task[3]))
        finally:
            client.cancel([f for f in futures if not f.done()])


# --------------------------------------------------------------------------- saving


def save_table(df, path):
    """Write a sweep table to ``.csv`` or ``.parquet`` (chosen by suffix), atomically.

    Array columns (``keep_arrays=True``) are dropped from CSV, with a warning; Parquet
    keeps them as lists and needs ``pyarrow`` (``pip install pyarrow``).

    Parameters
    ----------
    df : pandas.DataFrame
        Table from :func:`sweep`.
    path : str or Path
        Target file, ``*.csv`` or ``*.parquet``.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import pvcmf, tempfile, pathlib
    >>> from pvcmf.sweeps import save_table, load_table, synthetic_evaluate
    >>> df = pvcmf.sweep(1, {"nu": [0.46]}, evaluate=synthetic_evaluate, scheduler="synchronous")
    >>> out = save_table(df, pathlib.Path(tempfile.mkdtemp()) / "t.csv")
    >>> float(load_table(out)["nu"].iloc[0])
    0.46
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise ValueError(f"path must end in .csv or .parquet, got {path.name!r}")
    array_cols = [c for c in df.columns if df[c].map(lambda v: isinstance(v, np.ndarray)).any()]
    out = df.copy()
    if suffix == ".csv":
        if array_cols:
            log.warning("save_table: dropping array columns %s from CSV (use .parquet)", array_cols)
            out = out.drop(columns=array_cols)
    else:
        try:
            import pyarrow  # noqa: F401
        except ImportError as err:
            raise ImportError("writing Parquet needs pyarrow: pip install pyarrow (or use .csv)") from err
        for c in array_cols:
            out[c] = out[c].map(lambda v: v.ravel().tolist() if isinstance(v, np.ndarray) else v)
    out.attrs = {}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=suffix)
    os.close(fd)
    try:
        if suffix == ".csv":
            out.to_csv(tmp, index=False)
        else:
            out.to_parquet(tmp, index=False)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def load_table(path):
    """Read a table written by :func:`save_table` (CSV or Parquet)."""
    import pandas as pd

    path = Path(path)
    if path.suffix.lower() == ".parquet":
        return pd.read_parquet(path)
    if path.suffix.lower() == ".csv":
        return pd.read_csv(path)
    raise ValueError(f"path must end in .csv or .parquet, got {path.name!r}")


# --------------------------------------------------------------------------- command line


def parse_grid(items):
    """Parse ``NAME=V1,V2,...`` or ``NAME=START:STOP:NUM`` (inclusive linspace) strings.

    Examples
    --------
    >>> from pvcmf.sweeps import parse_grid
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


def add_sweep_parser(subparsers):
    """Register ``pvcmf sweep`` on an argparse sub-parser collection."""
    p = subparsers.add_parser(
        "sweep", help="run a parameter study (Dask) and write a table",
        description="Run a parameter sweep over virtual patients on Dask; write CSV/Parquet.",
    )
    p.add_argument("--patients", type=int, nargs="+", default=[1], help="virtual patient numbers")
    p.add_argument("--grid", nargs="+", required=True, metavar="NAME=VALUES",
                   help="e.g. nu=0:0.495:20 n_tets=10000,30000 (names: %s)" % ", ".join(PARAMETERS))
    p.add_argument("--out", required=True, help="output table, .csv or .parquet")
    p.add_argument("--scheduler", default=None,
                   help="processes (default), threads, synchronous, or tcp://host:8786")
    p.add_argument("--cache-dir", default=None, help="result cache folder (rerun recomputes nothing)")
    p.add_argument("--workers", type=int, default=None, help="local worker count")
    p.add_argument("--spacing", type=float, default=STUDY_SPACING,
                   help="default image resolution, mm (2: the study default, truths cached)")
    p.add_argument("--n-tets", type=int, default=30_000, help="default tetrahedra count")
    p.add_argument("--synthetic", action="store_true",
                   help="use the cheap synthetic evaluation instead of the pipeline (demo/test)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("-v", "--verbose", action="count", default=0, help="log more (-v info, -vv debug)")
    p.set_defaults(func=run_sweep)
    return p


def run_sweep(args):
    """Run ``pvcmf sweep`` from parsed arguments; return the written path."""
    if args.scheduler != "synchronous":
        try:
            import distributed  # noqa: F401
        except ImportError as err:
            raise SystemExit('pvcmf sweep needs Dask: pip install "pvcmf[sweep]" (or run '
                             f"with --scheduler synchronous); {err}") from None
    grid = parse_grid(args.grid)
    evaluate = synthetic_evaluate if args.synthetic else PipelineEvaluation(
        spacing=args.spacing, n_tets=args.n_tets,
        cache_dir=None if args.cache_dir is None else Path(args.cache_dir) / "prepared")
    df = sweep(args.patients, grid, evaluate=evaluate, scheduler=args.scheduler,
               cache_dir=args.cache_dir, progress_bar=not args.no_progress, n_workers=args.workers)
    return save_table(df, args.out), df
