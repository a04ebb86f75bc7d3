"""Speed against accuracy: the (time, 90 % error) curve over the knobs users turn.

For each knob — tetrahedra count, sampling points per tetrahedron (the baseline's
homogeneous mesh + random-point muscle fractions), iterative solver tolerance, image
resolution, region of interest — the other knobs stay at their defaults and the sweep
(:func:`pvcmf.sweep`, cached in ``--cache``) records, per virtual patient, the time
(preparation + one solve for mesh-level knobs, the solve for the tolerance) and the 90 %
percentile error against the patient's post-operative skin. It prints whole numbers
(milliseconds, micrometres) and the same run's ratios to the default, and draws one panel
per knob with the default marked (``--png``).

The defaults should sit at the knee: little error gained by paying more, much lost by
paying less. ``--synthetic`` runs the same plumbing on the cheap synthetic evaluation (no
pipeline needed; its curves are made up, not measurements of pvcmf).

Run: ``python benchmarks/trade.py [--patients 1 2] [--spacing 1.0] [--png trade.png]``.
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf.sweeps import PipelineEvaluation, synthetic_evaluate

DEFAULTS = {"n_tets": 30_000, "n_points": None, "tol": None, "spacing": 1.0, "roi": None}
#: what the default is when it is not a point of the knob's curve (ratios are then to the last)
OFF_CURVE = {"n_points": "conforming mesh, no sampling", "tol": "direct solver (round-off)"}
KNOBS = {
    "n_tets": [5_000, 10_000, 20_000, 30_000, 60_000, 120_000],
    "n_points": [10, 100, 1000],  # baseline mesh (conforming=False) + random sampling
    "tol": [1e-2, 1e-3, 1e-4, 1e-6, 1e-8],  # method="cg" (default: direct, to round-off)
    "spacing": [3.0, 2.0, 1.5, 1.0],
    "roi": [15.0, 25.0, 40.0, None],  # soft tissue within this distance of the moved bone (mm)
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
    time_col = "t_solve" if knob == "tol" and "t_solve" in df else None
    df["time"] = df[time_col] if time_col else df["t_prepare"] + df["t_eval"]
    key = df[knob].astype(object).where(df[knob].notna(), "all")
    return df.assign(value=key).groupby("value", sort=False)[["time", "p90"]].mean()


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--spacing", type=float, default=DEFAULTS["spacing"])
    ap.add_argument("--knobs", nargs="+", default=list(KNOBS), choices=list(KNOBS))
    ap.add_argument("--cache", default=None, help="sweep cache folder (default: temporary)")
    ap.add_argument("--png", default=None, help="write the curves to this PNG")
    ap.add_argument("--synthetic", action="store_true", help="synthetic evaluation (plumbing only)")
    a = ap.parse_args()
    evaluate = synthetic_evaluate if a.synthetic else PipelineEvaluation(spacing=a.spacing,
                                                                         n_tets=DEFAULTS["n_tets"])
    cache = a.cache or tempfile.mkdtemp(prefix="pvcmf-trade-")
    curves = {}
    for knob in a.knobs:
        curve = measure(knob, KNOBS[knob], a.patients, evaluate, cache)
        curves[knob] = curve
        default = "all" if DEFAULTS[knob] is None else DEFAULTS[knob]
        ref = curve.loc[default] if default in curve.index else curve.iloc[-1]
        label = OFF_CURVE.get(knob, default)
        print(f"\n{knob} (default {label}; {'synthetic' if a.synthetic else 'pipeline'})")
        for value, row in curve.iterrows():
            mark = "  <- default" if value == default and knob not in OFF_CURVE else ""
            print(f"  {str(value):>8}: time {1000 * row.time:7.0f} ms ({row.time / ref.time:5.2f}x), "
                  f"p90 {1000 * row.p90:5.0f} um ({1000 * (row.p90 - ref.p90):+5.0f} um){mark}")
    if a.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(curves), figsize=(3.2 * len(curves), 3.2), layout="constrained")
        for ax, (knob, curve) in zip(np.atleast_1d(axes), curves.items()):
            ax.plot(curve["time"], curve["p90"], "-o", ms=4)
            for value, row in curve.iterrows():
                ax.annotate(str(value), (row.time, row.p90), fontsize=7, xytext=(3, 3),
                            textcoords="offset points")
            default = "all" if DEFAULTS[knob] is None else DEFAULTS[knob]
            if default in curve.index and knob not in OFF_CURVE:
                ax.plot(curve.loc[default, "time"], curve.loc[default, "p90"], "r*", ms=12,
                        label="default")
                ax.legend(fontsize=7)
            ax.set_xscale("log")
            ax.set_title(knob)
            ax.set_xlabel("time (s)")
            ax.set_ylabel("90 % error (mm)")
        fig.savefig(Path(a.png), dpi=100)


if __name__ == "__main__":
    main()
