"""Speed against accuracy: the (time, 90 % error) curve over the knobs users turn.

For each knob — tetrahedra count, sampling points per tetrahedron (the state of the art:
homogeneous mesh + random-point muscle fractions, paper 000), iterative solver tolerance
(CG instead of the default direct solver), image resolution, region of interest — the
other knobs stay at their defaults and :func:`pvcmf.sweep` runs the real pipeline
(:class:`pvcmf.sweeps.PipelineEvaluation`: virtual patient -> segmentation -> muscles ->
mesh -> boundary conditions -> MTM -> skin -> signed distance) on each virtual patient at
nu = 0.46 against its post-operative truth (:func:`pvcmf.sweeps.study_truth`: the
:mod:`pvcmf.reference` truth of the 1.5 mm patient, the same truth for every image
spacing).

Time is the CPU time of one prediction from the CT (preparation + the solve, summed over
the worker's threads: :data:`pvcmf.sweeps.TIMES` ``cpu_prepare + cpu_eval``), because wall
time on the shared 2-core machine mostly measures the other users; for the tolerance knob
it is the solve alone (``cpu_eval``: solver set-up + solve + mapping + distance), the mesh
being the same. Error is the 90 % percentile of |distance| on the face, mm, averaged over
the patients.

Prints whole numbers (milliseconds, micrometres) and the same run's ratios to the
default, writes a CSV and one PNG panel per knob with the default (conforming mesh of
30k tetrahedra, direct solver, 1.5 mm, face region) as a red star in every panel.

Run: ``python benchmarks/trade.py [--patients 1 2] [--knobs n_tets tol] [--out DIR]``
(``--synthetic``: the same plumbing on :func:`pvcmf.sweeps.synthetic_evaluate`, whose
curves are made up, not measurements of pvcmf).
"""

import argparse
import functools
import os
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

import pvcmf
from pvcmf.sweeps import PipelineEvaluation, save_table, study_truth, synthetic_evaluate

#: the gallery's sweep cache: results and prepared meshes shared with Figs. 2-5 (a prepared
#: mesh loaded from it reports what preparing it cost, so times stay real)
GALLERY_CACHE = Path(os.environ.get("PVCMF_GALLERY_OUT",
                                    Path(__file__).resolve().parents[1] / "gallery" / "_out")) / "sweep-cache"
DEFAULTS = {"n_tets": 30_000, "n_points": None, "tol": None, "spacing": 1.5, "roi": None}
#: what the default is when it is not a point of the knob's curve
OFF_CURVE = {"n_points": "conforming mesh, no sampling", "tol": "direct solver (round-off)"}
KNOBS = {
    "n_tets": [5_000, 10_000, 20_000, 30_000, 60_000, 120_000],
    "n_points": [10, 100, 1000],  # baseline mesh (conforming=False) + random sampling
    "tol": [1e-2, 1e-3, 1e-4, 1e-6],  # method="cg" (default: direct, to round-off)
    "spacing": [3.0, 2.5, 2.0, 1.5, 1.0],
    "roi": [15.0, 25.0, 40.0, None],  # soft tissue within this distance of the moved bone (mm)
}

#: ``--quick``: fewer values per knob (what fits a shared 2-core machine in ~15 min per patient)
QUICK = {
    "n_tets": [5_000, 10_000, 20_000, 30_000, 60_000],
    "n_points": [10, 100],
    "tol": [1e-2, 1e-4, 1e-6],
    "spacing": [3.0, 2.0, 1.5, 1.0],
    "roi": [15.0, 40.0, None],
}


def knob_grid(knob, values):
    grid = {knob: values, "nu": [0.46]}
    if knob == "n_points":
        grid["conforming"] = [False]
    if knob == "tol":
        grid["method"] = ["cg"]
    return grid


def measure(knob, values, patients, evaluate, cache):
    df = pvcmf.sweep(patients, knob_grid(knob, values), evaluate=evaluate, cache_dir=cache,
                     progress_bar=True)
    if "cpu_prepare" in df:
        df["time"] = df["cpu_eval"] if knob == "tol" else df["cpu_prepare"] + df["cpu_eval"]
    else:
        df["time"] = df["t_eval"] if knob == "tol" else df["t_prepare"] + df["t_eval"]
    df["value"] = df[knob].astype(object).where(df[knob].notna(), "all")
    return df


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--knobs", nargs="+", default=list(KNOBS), choices=list(KNOBS))
    ap.add_argument("--cache", default=None,
                    help="sweep cache folder (default: the gallery's, shared with Figs. 2-5)")
    ap.add_argument("--out", default=None, help="folder for trade.csv and trade.png")
    ap.add_argument("--synthetic", action="store_true", help="synthetic evaluation (plumbing only)")
    ap.add_argument("--quick", action="store_true", help="fewer values per knob (QUICK)")
    ap.add_argument("--spacing", type=float, default=DEFAULTS["spacing"],
                    help="default image spacing, mm (also the truth's, for every spacing)")
    ap.add_argument("--truth-tets", type=int, default=None,
                    help="tetrahedra of the reference truth (default: postop_skin's 120k)")
    a = ap.parse_args()
    knobs = QUICK if a.quick else KNOBS
    DEFAULTS["spacing"] = a.spacing
    cache = Path(a.cache or (tempfile.mkdtemp(prefix="pvcmf-trade-") if a.synthetic else GALLERY_CACHE))
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; patients {a.patients}")
    rows, curves = [], {}
    for knob in a.knobs:
        if a.synthetic:
            evaluate = synthetic_evaluate
        else:  # as the gallery's figures (same cache entries); the spacing knob: one truth
            if knob == "spacing":
                truth = functools.partial(study_truth, spacing=a.spacing, n_tets=a.truth_tets)
            elif a.truth_tets is not None:
                from pvcmf import reference

                truth = functools.partial(reference.postop_skin, n_tets=a.truth_tets)
            else:
                truth = None
            evaluate = PipelineEvaluation(spacing=a.spacing, n_tets=DEFAULTS["n_tets"],
                                          truth=truth, cache_dir=cache / "prepared")
        df = measure(knob, knobs[knob], a.patients, evaluate, cache)
        curve = df.groupby("value", sort=False)[["time", "p90"]].mean()
        curves[knob] = curve
        for _, r in df.iterrows():
            rows.append({"knob": knob, "value": r["value"], "case": r["case"], "time_s": r["time"],
                         "p90_mm": r["p90"], "n_cells": r.get("n_cells", np.nan),
                         "default": r["value"] == ("all" if DEFAULTS[knob] is None else DEFAULTS[knob])
                         and knob not in OFF_CURVE})
        default = "all" if DEFAULTS[knob] is None else DEFAULTS[knob]
        ref = curve.loc[default] if default in curve.index else curve.iloc[-1]
        label = OFF_CURVE.get(knob, default)
        print(f"\n{knob} (default {label}; {'synthetic' if a.synthetic else 'pipeline'}; "
              f"load {os.getloadavg()[0]:.1f})")
        for value, row in curve.iterrows():
            mark = "  <- default" if value == default and knob not in OFF_CURVE else ""
            print(f"  {str(value):>8}: CPU {1000 * row.time:7.0f} ms ({row.time / ref.time:5.2f}x), "
                  f"p90 {1000 * row.p90:5.0f} um ({1000 * (row.p90 - ref.p90):+5.0f} um){mark}")
    table = pd.DataFrame(rows)
    out = Path(a.out) if a.out else cache.parent
    out.mkdir(parents=True, exist_ok=True)
    save_table(table, out / "trade.csv")
    star = curves["n_tets"].loc[DEFAULTS["n_tets"]] if "n_tets" in curves and \
        DEFAULTS["n_tets"] in curves["n_tets"].index else None
    draw(curves, star, out / "trade.png", a.synthetic)
    print(f"\nwrote {out / 'trade.csv'} and {out / 'trade.png'}")


def draw(curves, star, path, synthetic):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(3.3 * len(curves), 3.4), layout="constrained",
                             sharey=True)
    for ax, (knob, curve) in zip(np.atleast_1d(axes), curves.items()):
        ax.plot(curve["time"], curve["p90"], "-o", ms=4, label=knob)
        for value, row in curve.iterrows():
            text = f"{value:.0e}" if knob == "tol" else (f"{int(value) // 1000}k" if knob == "n_tets"
                                                          else str(value))
            ax.annotate(text, (row.time, row.p90), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        default = "all" if DEFAULTS[knob] is None else DEFAULTS[knob]
        if default in curve.index and knob not in OFF_CURVE:
            ax.plot(curve.loc[default, "time"], curve.loc[default, "p90"], "r*", ms=13,
                    label="default")
        elif star is not None and knob != "tol":  # the default is another configuration
            ax.plot(star["time"], star["p90"], "r*", ms=13, label="default (conforming 30k)")
        elif star is not None:
            ax.axhline(star["p90"], color="r", lw=0.8, ls="--", label="direct solver")
        ax.legend(fontsize=7)
        ax.set_xscale("log")
        ax.set_title({"n_tets": "tetrahedra", "n_points": "sampling points (state of the art)",
                      "tol": "CG tolerance (solve only)", "spacing": "image spacing (mm)",
                      "roi": "region of interest (mm)"}[knob], fontsize=9)
        ax.set_xlabel("CPU time (s)")
    np.atleast_1d(axes)[0].set_ylabel("90 % |error| on the face (mm)")
    if synthetic:
        fig.suptitle("synthetic evaluation (plumbing only, not pvcmf measurements)", fontsize=9)
    fig.savefig(path, dpi=100)


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
