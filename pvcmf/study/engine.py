"""The sweep engine: the grid of points, the result cache, tasks on Dask, the table.

:func:`sweep` runs a parameter study over cases and returns a tidy
:class:`pandas.DataFrame` (one row per case and parameter set). One task is made per case
and mesh-level combination (:data:`pvcmf.study.parameters.PARAMETERS`); it prepares the
case once and loops over the solve-level values, so a Poisson sweep refactors
numerically only.

Scheduling is delegated to Dask (``dask.distributed``): by default a local cluster of
single-threaded processes on this machine (gmsh has one global model, and the pipeline is
numpy/VTK work that holds the GIL in places); ``scheduler="threads"`` runs an in-process
cluster of threads, ``"synchronous"`` runs in this process without Dask;
``scheduler="tcp://host:8786"`` or a :class:`distributed.Client` runs the same sweep on a
cluster. Tasks carry ``retries``; a task whose process dies is rescheduled by Dask.

Caching (:mod:`pvcmf.cache`): every (case, parameter set) result is one ``.npz`` entry
under ``cache_dir`` named by :func:`pvcmf.study.evaluation.point_key` (case identity,
parameters, evaluation identity, code version), written as soon as its task finishes
(:func:`pvcmf.cache.store_entry`: under the entry's lock, atomically); a rerun loads those
and sends only the missing points to Dask, so a finished sweep recomputes nothing and an
interrupted one restarts where it stopped.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import multiprocessing
import numbers
import os
import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from .. import arrays
from ..cache import load_entry, store_entry
from ..plan import TABLE_II
from ..progress import Progress
from .evaluation import Evaluation, FunctionEvaluation, case_identity, code_version, point_key
from .parameters import METRICS, PARAMETERS, TIMES, validate_grid
from .pipeline_evaluation import PipelineEvaluation

log = logging.getLogger(__name__)

__all__ = ["LocalClusterStartError", "NonFiniteResultError", "resolve_evaluation", "sweep"]

#: metrics without which a row is not a result
REQUIRED_METRICS = ("p50", "p90", "p95")
#: patient numbers of the virtual patients (:func:`pvcmf.datasets.phantom`, Table II)
PATIENTS = tuple(sorted(TABLE_II))

#: what a sweep says when its local Dask cluster cannot start processes
GUARD_HINT = ('the local Dask cluster starts its processes with "spawn", which re-imports '
              "the main module: a script that calls pvcmf.sweep must do so under "
              '`if __name__ == "__main__":`, or run with scheduler="synchronous" or '
              'scheduler="threads"')


class NonFiniteResultError(ValueError):
    """A sweep point gave a NaN or infinite metric (a failed point, never cached)."""


class LocalClusterStartError(RuntimeError):
    """The local Dask cluster of a sweep could not start its processes."""


def resolve_evaluation(evaluate):
    """The :class:`~pvcmf.study.evaluation.Evaluation` for ``sweep(evaluate=...)``: None
    gives :class:`~pvcmf.study.pipeline_evaluation.PipelineEvaluation`, an object with
    ``prepare`` and ``evaluate`` is used as is, a callable is wrapped in
    :class:`~pvcmf.study.evaluation.FunctionEvaluation`."""
    if evaluate is None:
        return PipelineEvaluation()
    if isinstance(evaluate, Evaluation):
        return evaluate
    if hasattr(evaluate, "prepare") and hasattr(evaluate, "evaluate"):
        return evaluate
    return FunctionEvaluation(evaluate)


# --------------------------------------------------------------------------- cache entries


def _entry_path(cache_dir, key):
    return Path(cache_dir) / key[:2] / f"{key}.npz"


def _read_result(path):
    """One cached result: scalars from the JSON ``__meta__`` entry, arrays as they are."""
    with np.load(path, allow_pickle=False) as data:
        out = dict(json.loads(str(data["__meta__"])))
        for name in data.files:
            if name != "__meta__":
                out[name] = np.array(data[name])
    return out


def _write_result(result, path):
    meta, named = {}, {}
    for name, value in result.items():
        if isinstance(value, np.ndarray):
            named[name] = value
        else:
            meta[name] = value.item() if isinstance(value, np.generic) else value
    with open(path, "wb") as fh:
        np.savez(fh, __meta__=np.array(json.dumps(meta, default=repr)), **named)


class _Results:
    """Results of a sweep as they arrive: loaded, computed (and cached) or failed."""

    def __init__(self, labels, cache_dir, on_error):
        self.labels, self.cache_dir, self.on_error = labels, cache_dir, on_error
        self.results, self.cached, self.failed = {}, set(), {}

    def load(self, keys):
        """Read the cached entries of ``keys`` (none without a ``cache_dir``); an entry
        with a non-finite metric (written by an older version) is computed again."""
        if self.cache_dir is None:
            return
        for key in keys:
            hit = load_entry(_entry_path(self.cache_dir, key), _read_result)
            if hit is not None and _non_finite(hit) is None:
                self.results[key] = hit
                self.cached.add(key)

    def accept(self, task, task_results):
        """Keep (and cache) a task's results; a point with a NaN/inf metric is a failed
        point: not cached, recorded (``on_error='skip'``) or raised after the task's
        finite points are cached (``'raise'``)."""
        bad = []
        for key, params, result in zip(task[3], task[2], task_results):
            reason = _non_finite(result)
            if reason is not None:
                bad.append((key, params, reason))
                continue
            self.results[key] = result
            if self.cache_dir is not None:
                store_entry(_entry_path(self.cache_dir, key), result, _write_result)
        for key, params, reason in bad:
            message = (f"sweep point for case {self.labels[task[0]]!r} with "
                       f"{ {**task[1], **params} } gave {reason}")
            if self.on_error == "raise":
                raise NonFiniteResultError(message)
            log.error("%s (skipped)", message)
            self.failed[key] = f"NonFiniteResultError: {reason}"

    def fail(self, task, err):
        ci, gparams = task[0], task[1]
        message = (f"sweep task for case {self.labels[ci]!r} with "
                   f"{gparams or 'the default mesh'} failed: {type(err).__name__}: {err}")
        if self.on_error == "raise":
            raise RuntimeError(message) from err
        log.error("%s (skipped)", message)
        for key in task[3]:
            self.failed[key] = f"{type(err).__name__}: {err}"


def _non_finite(result):
    """Why ``result`` is not a result (a NaN/inf scalar metric), or None."""
    bad = []
    for name in METRICS:
        value = result.get(name)
        if isinstance(value, (numbers.Real, np.generic)) and not isinstance(value, bool) \
                and not math.isfinite(float(value)):
            bad.append(f"{name}={float(value)}")
    return f"non-finite metrics {', '.join(bad)}" if bad else None


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
        missing = [m for m in REQUIRED_METRICS if m not in result]
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
        try:
            cluster = stack.enter_context(LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True,
                dashboard_address=None, memory_limit=memory_limit,
            ))
        except Exception as err:
            stack.close()
            raise LocalClusterStartError(
                f"sweep could not start its local Dask cluster ({type(err).__name__}: {err}). "
                f"Most often {GUARD_HINT}."
            ) from err
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
        allowed values: :data:`~pvcmf.study.parameters.PARAMETERS`. Checked by
        :func:`~pvcmf.study.parameters.validate_grid` before
        anything runs.
    evaluate : callable or Evaluation, optional
        What to compute for a case and parameter set: an
        :class:`~pvcmf.study.evaluation.Evaluation` (``prepare`` once per task,
        ``evaluate`` per point), or any ``f(case, **params) -> dict``
        (:class:`~pvcmf.study.evaluation.FunctionEvaluation`); default
        :class:`~pvcmf.study.pipeline_evaluation.PipelineEvaluation`.
    scheduler : None, str or distributed.Client
        ``None``/``"processes"``: a local Dask cluster of single-threaded
        processes; ``"threads"``: an in-process cluster of threads; ``"synchronous"``:
        no Dask, in this process; ``"tcp://host:8786"``: that Dask scheduler; a
        ``Client``: that client (left open).
    cache_dir : str or Path, optional
        Result cache; a rerun with the same cases, parameters and code loads results
        instead of computing them. ``None`` disables caching.
    progress_bar : bool
        Show a tqdm progress bar (points done / total).
    retries : int
        Dask retries of a task that raised; a task whose process died is rescheduled.
    keep_arrays : bool
        Keep array results (e.g. the per-point ``distance`` map) as object columns.
    n_workers : int, optional
        Dask processes (threads for ``"threads"``) of a local cluster, a positive integer;
        default (``None``) one per CPU, at most one per task.
    memory_limit : str
        Memory limit per Dask process of a local cluster (Dask syntax, e.g. ``"2GiB"``).
    version : str, optional
        Code version in the cache key; default
        :func:`~pvcmf.study.evaluation.code_version` (pvcmf's version).
        The evaluation's own identity adds what else its results depend on
        (:class:`~pvcmf.study.pipeline_evaluation.PipelineEvaluation`: the sources of
        :data:`~pvcmf.study.evaluation.RESULT_SOURCES`), so code
        that changes results recomputes and code that does not (figures, CLI) does not.
    on_error : {'raise', 'skip'}
        A task that still fails after its retries, or a point whose metrics are NaN or
        infinite: ``'raise'`` stops the sweep with a :class:`RuntimeError` naming the
        case (:class:`NonFiniteResultError`, a ``ValueError``, naming the case and the
        parameters for a non-finite metric); ``'skip'`` finishes the other tasks and
        gives the failed points NaN metrics and the reason in an ``error`` column
        (failures are not cached, so a rerun tries them again).

    Returns
    -------
    pandas.DataFrame
        One row per case and parameter set, in case order then grid order: ``case``,
        the grid's parameters, :data:`~pvcmf.study.parameters.METRICS`, ``n_cells`` when
        the evaluation gives it, :data:`~pvcmf.study.parameters.TIMES` (s) and ``cached``
        (loaded from the cache). ``df.attrs`` holds the grid, the number of tasks, points
        computed and loaded, and the wall time.

    Raises
    ------
    ValueError
        Invalid grid, cases (a patient number that is no virtual patient) or options
        (``n_workers``, ``retries``, ``on_error``), before anything runs; a non-finite
        metric (:class:`NonFiniteResultError`, ``on_error='raise'``).
    RuntimeError
        A task failed after its retries (``on_error='raise'``); results of finished
        tasks stay cached. :class:`LocalClusterStartError` when the local Dask cluster
        cannot start (a script without an ``if __name__ == "__main__":`` guard).

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.study.evaluation import synthetic_evaluate
    >>> df = pvcmf.sweep([1, 2], {"nu": [0.3, 0.46]}, evaluate=synthetic_evaluate,
    ...                  scheduler="synchronous")
    >>> df[["case", "nu"]].values.tolist()
    [['P1', 0.3], ['P1', 0.46], ['P2', 0.3], ['P2', 0.46]]
    """
    _refuse_bootstrapping(scheduler)
    t_start = time.perf_counter()
    grid = validate_grid(grid)
    cases, identities = _check_cases(cases)
    labels = [label for label, _ in identities]
    _check_options(scheduler, retries, on_error, n_workers)
    evaluation = resolve_evaluation(evaluate)
    version = code_version() if version is None else str(version)
    points = _points(grid, identities, evaluation.identity(), version)
    run = _Results(labels, cache_dir, on_error)
    run.load([key for *_, key in points])
    tasks = _tasks(points, run.results)
    n_todo = sum(len(t[3]) for t in tasks.values())
    log.info("sweep: %d cases x %d parameter sets = %d points; %d cached, %d to compute in %d "
             "tasks", len(cases), len(points) // len(cases), len(points), len(run.cached),
             n_todo, len(tasks))
    with Progress(len(points), "sweep", enabled=progress_bar, unit="point") as bar:
        if run.cached:
            bar.step(f"{len(run.cached)} points from the cache", n=len(run.cached))
        if tasks and scheduler == "synchronous":
            _run_here(evaluation, cases, labels, tasks, run, bar)
        elif tasks:
            _run_on_dask(evaluation, cases, labels, tasks, run, bar, scheduler, retries,
                         n_workers, memory_limit)
    df = _table(points, grid, labels, run, keep_arrays)
    df.attrs.update(
        grid={k: list(v) for k, v in grid.items()}, n_tasks=len(tasks), n_computed=n_todo,
        n_cached=len(run.cached), n_failed=len(run.failed),
        wall_time=time.perf_counter() - t_start,
    )
    log.info("sweep done in %.2f s (%d computed, %d from cache)", df.attrs["wall_time"], n_todo,
             len(run.cached))
    return df


def _refuse_bootstrapping(scheduler):
    """Refuse a sweep started while a spawned process re-imports an unguarded main module
    (it would start a cluster of its own, and so on); one short message, no traceback."""
    if scheduler in ("synchronous", "threads"):
        return
    if getattr(multiprocessing.current_process(), "_inheriting", False):
        raise SystemExit(f"pvcmf.sweep called while a new process imports the main module: "
                         f"{GUARD_HINT}")


def _check_patient(case, where):
    patient = case
    if isinstance(case, Mapping):
        if "patient" not in case:
            return
        patient = case["patient"]
    if isinstance(patient, bool) or not isinstance(patient, numbers.Integral) \
            or int(patient) not in PATIENTS:
        raise ValueError(f"{where} must be a virtual patient number {list(PATIENTS)} "
                         f"(pvcmf.datasets.phantom, Table II), got {patient!r}")


def _check_cases(cases):
    """The cases as a list and their (label, identity) pairs; distinct labels; patient
    numbers (alone or as a spec's ``patient``) must be virtual patients."""
    if isinstance(cases, (str, bytes, Mapping, numbers.Integral)) or not isinstance(cases, Sequence):
        cases = [cases]
    cases = list(cases)
    if not cases:
        raise ValueError("cases must hold at least one case, got an empty list")
    for i, case in enumerate(cases):
        if isinstance(case, (numbers.Integral, Mapping)):
            _check_patient(case, f"cases[{i}]")
    identities = [case_identity(c) for c in cases]
    labels = [label for label, _ in identities]
    if len(set(labels)) != len(labels):
        raise ValueError(f"cases must have distinct names, got {labels}")
    return cases, identities


def _check_options(scheduler, retries, on_error, n_workers=None):
    if n_workers is not None and (isinstance(n_workers, bool)
                                  or not isinstance(n_workers, numbers.Integral)
                                  or n_workers < 1):
        raise ValueError(f"n_workers must be a positive integer or None (one per CPU), "
                         f"got {n_workers!r}")
    if on_error not in ("raise", "skip"):
        raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
    if not isinstance(retries, numbers.Integral) or retries < 0:
        raise ValueError(f"retries must be an integer >= 0, got {retries!r}")
    if scheduler is not None and not isinstance(scheduler, str):
        from distributed import Client

        if not isinstance(scheduler, Client):
            raise TypeError("scheduler must be None, a str or a distributed.Client, got "
                            f"{type(scheduler).__name__}")


def _points(grid, identities, eval_identity, version):
    """Every point of the sweep in output order: (case index, mesh-level parameters,
    solve-level parameters, cache key)."""
    group_names = [n for n in grid if PARAMETERS[n][0] == "mesh"]
    inner_names = [n for n in grid if PARAMETERS[n][0] in ("solve", "plan")]
    group_combos = list(itertools.product(*(grid[n] for n in group_names)))
    inner_combos = list(itertools.product(*(grid[n] for n in inner_names)))
    points = []
    for ci, (_, ident) in enumerate(identities):
        for gvals in group_combos:
            gparams = dict(zip(group_names, gvals))
            for ivals in inner_combos:
                iparams = dict(zip(inner_names, ivals))
                key = point_key(ident, {**gparams, **iparams}, eval_identity, version)
                points.append((ci, gparams, iparams, key))
    return points


def _tasks(points, done):
    """One task per case and mesh-level combination, holding only the points not in
    ``done``: task key -> (case index, mesh-level parameters, [solve-level parameters],
    [cache keys])."""
    tasks = {}
    for ci, gparams, iparams, key in points:
        if key in done:
            continue
        task = tasks.setdefault((ci, tuple(gparams.items())), (ci, gparams, [], []))
        task[2].append(iparams)
        task[3].append(key)
    return tasks


def _run_here(evaluation, cases, labels, tasks, run, bar):
    """Run the tasks one after the other in this process (``scheduler='synchronous'``)."""
    for task in tasks.values():
        ci, gparams, iparams_list, keys = task
        try:
            outcome = _run_group(evaluation, cases[ci], gparams, iparams_list)
        except Exception as err:
            run.fail(task, err)
        else:
            run.accept(task, outcome)
        bar.step(f"{labels[ci]} {gparams or ''}".strip(), n=len(keys))


def _run_on_dask(evaluation, cases, labels, tasks, run, bar, scheduler, retries,
                 n_workers, memory_limit):
    """Submit the tasks to Dask and collect them as they finish."""
    from distributed import as_completed

    client, stack = _make_client(scheduler, len(tasks), n_workers, memory_limit)
    with stack:
        run_id = uuid.uuid4().hex[:8]
        # big Case objects travel once per Dask process that needs them, not once per task
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
                    run.fail(task, err)
                else:
                    run.accept(task, task_results)
                bar.step(labels[task[0]], n=len(task[3]))
        finally:
            client.cancel([f for f in futures if not f.done()])



def _table(points, grid, labels, run, keep_arrays):
    """The tidy table of a sweep: one row per point, columns in a fixed order."""
    rows = []
    for ci, gparams, iparams, key in points:
        result = run.results.get(key, {arrays.SWEEP_ERROR: run.failed.get(key)})
        row = {arrays.SWEEP_CASE: labels[ci], **gparams, **iparams}
        for name, value in result.items():
            if (isinstance(value, np.ndarray) and not keep_arrays) or name in row:
                continue
            row[name] = value
        row[arrays.SWEEP_CACHED] = key in run.cached
        rows.append(row)
    df = pd.DataFrame(rows)
    for m in REQUIRED_METRICS:
        if m not in df:
            df[m] = np.nan
    front = [arrays.SWEEP_CASE, *grid, *[m for m in METRICS if m in df],
             *([arrays.SWEEP_N_CELLS] if arrays.SWEEP_N_CELLS in df else [])]
    back = [c for c in (*TIMES, arrays.SWEEP_CACHED) if c in df]
    return df[front + [c for c in df.columns if c not in front and c not in back] + back]
