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
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays, filters
from pvcmf.study.inference import compare_methods
from pvcmf.study.validation import run_study, study_predictor
from pvcmf.truth.independent import independent_truth_grid
from pvcmf.truth.refinement import exact_skin_samples, refinement_change

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "truth_refinement.md"


def refinement(patients, counts, spacing, cache=True):
    rows = []
    for p in patients:
        case = pvcmf.datasets.phantom(p, spacing=spacing)
        points = exact_skin_samples(case)
        prev = None
        for n in counts:
            grid = independent_truth_grid(case, n_tets=n, cache=cache)
            dofs, newton, factors, seconds = grid.field_data[arrays.REFERENCE_SOLVER]
            edges = grid.extract_all_edges().compute_cell_sizes(
                length=True, area=False, volume=False)["Length"]
            row = {"patient": p, "tets": grid.n_cells, "h": float(np.median(edges)),
                   "dofs": int(dofs), "newton": int(newton), "factorisations": int(factors),
                   "seconds": float(seconds), "share": np.nan, "p50": np.nan,
                   "p90": np.nan, "max": np.nan, "released":
                   len(grid.field_data[arrays.REFERENCE_RELEASED])}
            if prev is not None:
                row.update({k: v for k, v in refinement_change(prev, grid, points).items()
                            if k in ("p50", "p90", "max")})
                row["share"] = refinement_change(prev, grid, points)["compared"]
            prev = grid
            rows.append(row)
            print(row, flush=True)
    head = ("| patient | tetrahedra | edge mm | dofs | Newton | factorisations | solve s "
            "| released | skin compared | change p50 mm | p90 mm | max mm |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|")
    body = [f"| {r['patient']} | {r['tets']} | {r['h']:.1f} | {r['dofs']} | {r['newton']} | "
            f"{r['factorisations']} | {r['seconds']:.0f} | {r['released']} | "
            f"{100 * r['share']:.0f} % | {r['p50']:.3f} | {r['p90']:.3f} | {r['max']:.3f} |"
            for r in rows]
    text = ("Skin points: the exact skin of the meshed face "
            "(``pvcmf.truth.refinement.exact_skin_samples``: the voxel skin projected onto "
            "the zero set of the patient's level sets, kept where that boundary is the "
            "skin); each truth's displacement there is that of its closest boundary point "
            "(``skin_displacement``); the change is taken from the next coarser truth over "
            "the points both meshes reach within a quarter of the coarser median edge "
            "(``refinement_change``). Converged: p90 <= 0.1 mm between the two finest. "
            "Solve s: the NGSolve solve (load steps, Newton, factorisations) on this "
            "machine, read from the truth's ``reference_solver`` record (cached truths keep "
            "the cost of the run that made them).\n\n")
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
    ap.add_argument("--no-cache", action="store_true",
                    help="solve every truth again (default: reuse the on-disk cache)")
    ap.add_argument("--n-tets", type=int, default=30_000)
    ap.add_argument("--truth-tets", type=int, default=30_000)
    args = ap.parse_args(argv)
    parts = ["# Validation study: the truth's convergence and the paired inference", "",
             f"Command: `python benchmarks/study.py {' '.join(sys.argv[1:] if argv is None else argv)}`  ",
             f"Machine: {platform.machine()}, Python {sys.version.split()[0]}, "
             f"pvcmf {pvcmf.__version__}.", ""]
    if args.refinement:
        parts.append(refinement(args.patients, args.counts, args.spacing,
                                cache=not args.no_cache))
    if args.compare:
        parts.append(compare(args.patients, args.truth, args.spacing, args.n_tets,
                             args.truth_tets))
    PAGE.write_text("\n".join(parts) + "\n")
    print("\n".join(parts))


if __name__ == "__main__":
    main()
