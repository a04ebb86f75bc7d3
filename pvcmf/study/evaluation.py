"""What a sweep computes for a case, and the identities that key its cache.

* :class:`Evaluation` - the interface: ``prepare(case, **mesh_params)`` once per task,
  ``evaluate(state, **solve_params) -> dict`` per parameter set;
  :class:`FunctionEvaluation` wraps a plain ``f(case, **params) -> dict``;
* :func:`error_statistics` - one sweep row's metrics from a signed error map (delegates to
  :func:`pvcmf.study.statistics.summary`);
* :func:`synthetic_evaluate`, :func:`synthetic_skin` - a cheap deterministic pure-numpy
  stand-in with the shape of paper 001's results (tests, documentation);
* :func:`case_identity`, :func:`code_version`, :func:`source_hash`, :func:`point_key` -
  what enters a cache key (:func:`pvcmf.cache.make_key`, :func:`pvcmf.cache.code_hash`).
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import numbers
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy.spatial import Delaunay

from .. import __version__, arrays
from ..cache import code_hash, make_key
from .statistics import summary

__all__ = ["Evaluation", "FunctionEvaluation", "RESULT_SOURCES", "case_identity",
           "code_version", "error_statistics", "point_key", "source_hash",
           "synthetic_evaluate", "synthetic_skin"]


def error_statistics(distance):
    """Statistics of a signed error map, as paper 001 reports them (one sweep row).

    Delegates to :func:`pvcmf.study.statistics.summary`, renaming its point count ``n`` to
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
    >>> from pvcmf.study.evaluation import error_statistics
    >>> s = error_statistics([0.5, -1.5, 3.0, 0.0])
    >>> s["within_1mm"], s["within_2mm"]
    (50.0, 75.0)
    """
    d = np.asarray(distance, dtype=float).ravel()
    if not np.isfinite(d).any():
        raise ValueError("distance must hold at least one finite value, got none")
    stats = summary(d)
    stats["n_skin"] = int(stats.pop("n"))
    return stats



class Evaluation:
    """What a sweep computes for one case: ``prepare`` once per task, ``evaluate`` per point.

    Subclass and implement both. ``prepare(case, **group_params)`` receives the case (as
    given to :func:`pvcmf.study.engine.sweep`) and the mesh-level parameters of the task
    and returns any
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
            source = code_hash(target)
        except (OSError, TypeError):  # no source to read (a builtin): its name stands for it
            source = make_key(name, length=16)
        options = getattr(func, "identity", None)
        return {
            "function": name,
            "source": source,
            "options": options() if callable(options) else None,
            "version": getattr(func, "version", "1"),
        }



def _case_seed(case, salt=0):
    _, identity = case_identity(case)
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
    >>> from pvcmf.study.evaluation import synthetic_evaluate
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
    out.update({arrays.SWEEP_DISTANCE: err, arrays.SWEEP_N_CELLS: int(n_tets)})
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
    >>> from pvcmf.study.evaluation import synthetic_skin, synthetic_evaluate
    >>> synthetic_skin(500).n_points == synthetic_evaluate(1, n_skin=500)["distance"].size
    True
    """
    pts, _ = _synthetic_points(int(n_skin))
    tri = Delaunay(pts[:, [0, 2]]).simplices
    faces = np.c_[np.full(len(tri), 3), tri].ravel()
    return pv.PolyData(pts, faces)



def case_identity(case):
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
        h.update(np.ascontiguousarray(ct.point_data.get(arrays.CT, np.zeros(0))).tobytes())
        return str(name), f"case:{name}:{h.hexdigest()[:24]}"
    if name is not None:
        return str(name), f"object:{name}"
    raise TypeError(
        "cases must be patient numbers, names, mappings or objects with a 'name' "
        f"(and 'ct'), got {type(case).__name__}"
    )


#: the parts of pvcmf whose code changes what the pipeline computes (relative to the
#: package): their sources enter the cache identity of
#: :class:`pvcmf.study.pipeline_evaluation.PipelineEvaluation`. Figures,
#: command line, I/O and the sweep engine itself do not change a result, so editing them
#: keeps every cached sweep.
RESULT_SOURCES = ("arrays.py", "atlas", "tps.py", "plan.py", "pipeline.py", "truth",
                  "study/statistics.py", "filters", "mtm", "datasets")

_SOURCE_HASHES = {}
_PACKAGE_ROOT = Path(__file__).resolve().parent.parent


def code_version():
    """Version of pvcmf for cache keys of every evaluation: the package version.

    What a result depends on beyond that is in its evaluation's identity
    (:meth:`Evaluation.identity`):
    :class:`pvcmf.study.pipeline_evaluation.PipelineEvaluation` hashes the sources of
    :data:`RESULT_SOURCES` and its own code (:func:`source_hash`), a plain function
    evaluation its function's source.
    """
    return str(__version__)


def source_hash(parts=RESULT_SOURCES):
    """:func:`pvcmf.cache.code_hash` (16 hex digits) of the pvcmf sources named in ``parts``
    (files or folders, relative to the package), memoised per process.

    Examples
    --------
    >>> from pvcmf.study.evaluation import source_hash
    >>> len(source_hash(("arrays.py",)))
    16
    """
    parts = tuple(parts)
    if parts not in _SOURCE_HASHES:
        root = _PACKAGE_ROOT
        _SOURCE_HASHES[parts] = code_hash(*(root / part for part in parts), root=root)
    return _SOURCE_HASHES[parts]


def point_key(case_identity, params, evaluation_identity, version):
    """Cache key (:func:`pvcmf.cache.make_key`, 64 hex digits) of one sweep point: the
    case identity, its parameters, the evaluation's identity and the code version.

    Examples
    --------
    >>> from pvcmf.study.evaluation import point_key
    >>> len(point_key("phantom(patient=1)", {"nu": 0.3}, {"name": "f"}, "1"))
    64
    """
    return make_key({"case": case_identity, "params": params,
                     "evaluation": evaluation_identity, "code": version})
