"""Sweep engine: scheduler overhead, cache, and the full Poisson sweep on the pipeline.

Prints whole numbers (milliseconds) measured in this run:

1. the same 4 cases x 20 Poisson ratios x 2 mesh sizes (160 points) with the cheap
   synthetic evaluation on ``synchronous`` (no Dask), ``threads`` (in-process Dask cluster)
   and ``processes`` (local Dask cluster of worker processes, the default), each with its
   start-up, and a cached rerun: the engine's own cost;
2. with ``--pipeline``: the full Poisson sweep of the issue (20 ratios x 4 virtual
   patients at 30k tetrahedra) on the default scheduler, split into the one-off
   preparation per patient (phantom, segmentation, muscles, mesh, boundary conditions) and
   the sweep proper (numeric refactorisation + solve + distance per ratio).

Run: ``python benchmarks/sweeps.py [--pipeline] [--spacing 1.5] [--cache DIR]
[--stand-in-truth]`` (the last measures times before :mod:`pvcmf.reference` exists, with the
pre-operative skin as the "truth"). Run it twice with ``--cache DIR``: the second run loads
the prepared cases (meshes) and measures the sweep proper alone.
"""

import argparse
import os
import tempfile
import time

import numpy as np

import pvcmf
from pvcmf.sweeps import PipelineEvaluation, synthetic_evaluate


def engine():
    grid = {"n_tets": [10_000, 30_000], "nu": list(np.round(np.linspace(0, 0.495, 20), 4))}
    cases = [1, 2, 3, 4]
    ref = None
    for scheduler in ("synchronous", "threads", "processes"):
        t = time.perf_counter()
        df = pvcmf.sweep(cases, grid, evaluate=synthetic_evaluate, scheduler=scheduler)
        ms = 1000 * (time.perf_counter() - t)
        work = 1000 * df["t_eval"].sum()
        same = ref is None or np.array_equal(ref, df["p90"].to_numpy())
        ref = df["p90"].to_numpy() if ref is None else ref
        print(f"{scheduler:12s} {len(df)} points: wall {ms:6.0f} ms (evaluation {work:4.0f} ms), "
              f"same table: {same}")
    with tempfile.TemporaryDirectory() as cache:
        pvcmf.sweep(cases, grid, evaluate=synthetic_evaluate, scheduler="synchronous", cache_dir=cache)
        t = time.perf_counter()
        df = pvcmf.sweep(cases, grid, evaluate=synthetic_evaluate, scheduler="processes", cache_dir=cache)
        print(f"cached rerun {len(df)} points: wall {1000 * (time.perf_counter() - t):6.0f} ms, "
              f"computed {df.attrs['n_computed']}")


def preop_truth(case):
    """Timing stand-in for the post-operative truth: the pre-operative skin (the "errors"
    are then the predicted motion, not an accuracy)."""
    from pvcmf.filters import extract_skin

    return extract_skin(case.truth)


def pipeline(spacing, stand_in, cache):
    ev = PipelineEvaluation(spacing=spacing, n_tets=30_000, truth=preop_truth if stand_in else None,
                            cache_dir=cache)
    nus = list(np.round(np.linspace(0, 0.495, 20), 4))
    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    t = time.perf_counter()
    df = pvcmf.sweep([1, 2, 3, 4], {"nu": nus}, evaluate=ev, progress_bar=True)
    wall = time.perf_counter() - t
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    prep = df.groupby("case")["t_prepare"].first()
    cpu_prep = df.groupby("case")["cpu_prepare"].first()
    per_case_sweep = df.groupby("case")["t_eval"].sum()
    cpu = cpu_prep.sum() + df["cpu_eval"].sum()
    print(f"Poisson sweep 20 x 4 at ~{int(df['n_cells'].mean())} tetrahedra: wall {wall:.0f} s; "
          f"preparation per patient {prep.mean():.0f} s wall / {cpu_prep.mean():.0f} s CPU (once), "
          f"sweep proper per patient {per_case_sweep.mean():.1f} s "
          f"({1000 * df['t_eval'].mean():.0f} ms wall / {1000 * df['cpu_eval'].mean():.0f} ms CPU "
          f"per ratio, median {1000 * df['cpu_eval'].median():.0f} ms CPU; "
          f"solve {1000 * df['t_solve'].mean():.0f} ms)")
    print(f"CPU in the tasks: {cpu:.0f} s (preparation {cpu_prep.sum():.0f} s, ratios "
          f"{df['cpu_eval'].sum():.0f} s); on 2 idle cores that is >= {cpu / 2:.0f} s of wall "
          f"time plus the cluster start")
    print(df.groupby("case")[["p50", "p90", "p95"]].min().round(3).to_string())


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--pipeline", action="store_true")
    ap.add_argument("--spacing", type=float, default=1.5)
    ap.add_argument("--stand-in-truth", action="store_true",
                    help="measure times with the pre-operative skin as 'truth' (no pvcmf.reference)")
    ap.add_argument("--cache", default=None,
                    help="folder keeping prepared cases (results are never cached here)")
    ap.add_argument("--no-engine", action="store_true")
    a = ap.parse_args()
    if not a.no_engine:
        engine()
    if a.pipeline:
        pipeline(a.spacing, a.stand_in_truth, a.cache)
