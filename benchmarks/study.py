"""Benchmark: the independent truth's convergence and cost, and the study's paired inference.

Not run by CI. Heavy (NGSolve P2 solves of minutes each): run on a quiet machine.

1. ``--refinement``: per virtual patient, :func:`pvcmf.truth.independent.independent_truth_grid`
   at the requested ``--counts`` (P2), each solve timed (dofs, Newton iterations,
   factorisations, seconds); the skin of the truth labels moved by each truth, and the
   p50 / p90 / max of the skin's difference between successive counts. Converged when the
   p90 between the two finest is <= 0.1 mm.
2. ``--compare``: the study (``study_predictor(truth=...)``) of "proposed",
   "state_of_the_art" and the controls, and :func:`pvcmf.study.inference.compare_methods`
   per patient and over the patients.

Writes markdown tables to ``docs/benchmarks/truth_refinement.md`` with the command and machine.

Run::

    python benchmarks/study.py --refinement --patients 1 --counts 8000 16000 32000
    python benchmarks/study.py --compare --truth independent --patients 1 2 3 4
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays, filters
from pvcmf.study.inference import compare_methods
from pvcmf.study.validation import run_study, study_predictor
from pvcmf.truth.independent import independent_truth_grid

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "truth_refinement.md"


def refinement(patients, counts, spacing):
    rows = []
    for p in patients:
        case = pvcmf.datasets.phantom(p, spacing=spacing)
        skin = filters.extract_skin(case.truth)
        skins = []
        for n in counts:
            t = time.perf_counter()
            grid = independent_truth_grid(case, n_tets=n, cache=False)
            seconds = time.perf_counter() - t
            dofs, newton, factors, _ = grid.field_data[arrays.REFERENCE_SOLVER]
            probe = skin.sample(grid, progress_bar=False)
            skins.append((np.asarray(probe[arrays.DISPLACEMENT], dtype=float),
                          np.asarray(probe[arrays.VALID_POINT_MASK], dtype=bool)))
            if len(skins) > 1:  # the skin points inside both truths' meshes
                both = skins[-1][1] & skins[-2][1]
                diff = np.linalg.norm(skins[-1][0][both] - skins[-2][0][both], axis=1)
                share = float(both.mean())
            else:
                diff, share = np.full(1, np.nan), np.nan
            rows.append({"patient": p, "tets": grid.n_cells, "dofs": int(dofs),
                         "newton": int(newton), "factorisations": int(factors),
                         "seconds": seconds, "p50": np.percentile(diff, 50),
                         "p90": np.percentile(diff, 90), "max": diff.max(),
                         "share": share})
            print(rows[-1], flush=True)
    head = ("| patient | tetrahedra | dofs | Newton | factorisations | s | skin compared "
            "| change p50 mm | p90 mm | max mm |\n|---|---|---|---|---|---|---|---|---|---|")
    body = [f"| {r['patient']} | {r['tets']} | {r['dofs']} | {r['newton']} | "
            f"{r['factorisations']} | {r['seconds']:.0f} | {100 * r['share']:.0f} % | "
            f"{r['p50']:.3f} | {r['p90']:.3f} | {r['max']:.3f} |" for r in rows]
    text = ("The skin of the truth labels (``extract_skin``) moved by each truth (linear "
            "interpolation of its vertex displacements); the change from the next coarser "
            "truth over the skin points inside both meshes. Converged: p90 <= 0.1 mm between "
            "the two finest.\n\n")
    return "## Refinement of the independent truth\n\n" + text + head + "\n" + "\n".join(body)


def compare(patients, truth, spacing, n_tets, truth_tets):
    predict = study_predictor(spacing=spacing, n_tets=n_tets, truth_tets=truth_tets,
                              truth=None if truth == "reference" else truth)
    methods = ("proposed", "state_of_the_art", "no_muscles", "wrong_nu")
    skins, _, _ = run_study(predict, patients=patients, methods=methods)
    out = ["## Paired inference", ""]
    for other in methods[1:]:
        table = compare_methods(skins, "proposed", other)
        out.append(f"proposed vs {other}:\n")
        out.append(table.round(3).to_markdown(index=False))
        out.append("")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refinement", action="store_true")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--truth", default="independent", choices=["independent", "reference"])
    ap.add_argument("--patients", type=int, nargs="+", default=[1])
    ap.add_argument("--counts", type=int, nargs="+", default=[8000, 16000, 32000])
    ap.add_argument("--spacing", type=float, default=2.0)
    ap.add_argument("--n-tets", type=int, default=30_000)
    ap.add_argument("--truth-tets", type=int, default=30_000)
    args = ap.parse_args(argv)
    parts = ["# Validation study: the truth's convergence and the paired inference", "",
             f"Command: `python benchmarks/study.py {' '.join(sys.argv[1:] if argv is None else argv)}`  ",
             f"Machine: {platform.machine()}, Python {sys.version.split()[0]}, "
             f"pvcmf {pvcmf.__version__}.", ""]
    if args.refinement:
        parts.append(refinement(args.patients, args.counts, args.spacing))
    if args.compare:
        parts.append(compare(args.patients, args.truth, args.spacing, args.n_tets,
                             args.truth_tets))
    PAGE.write_text("\n".join(parts) + "\n")
    print("\n".join(parts))


if __name__ == "__main__":
    main()
