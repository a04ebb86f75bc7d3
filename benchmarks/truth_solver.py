"""Benchmark: the truth's linear solvers on one large truth (``solve_reference(inverse=...)``).

Run: ``python benchmarks/truth_solver.py [--patient 101] [--spacing 3] [--tets 30000]
[--face-mm 3.2] [--face-margin-mm 30] [--inverse mkl sparsecholesky] [--write PAGE]``
(not run by CI; needs the ``reference`` extra). Builds the graded independent truth of one
refinement patient (:func:`pvcmf.truth.independent.truth_problem`: the cohort's patients
from 101 on, the phantoms 1-4), solves it once per linear solver, as the cohort does
(factor reused as the preconditioner of conjugate gradients, materials a field, NGSolve's
threads where the cores are free), and tabulates where the time goes: factorisations, the
solves, the assemblies, in wall seconds of the same run, with each solution's largest
difference from the first solver's. ``--write`` writes the table as a page.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from pvcmf import arrays
from pvcmf.truth import solver
from pvcmf.truth.graded import face_size_text
from pvcmf.truth.independent import truth_problem
from truth_refinement import refinement_case

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "truth_solver.md"
COLUMNS = ("inverse", "dofs", "newton", "solves", "factorisations", "factor_s", "cg_iterations",
           "solves_s", "assembly_s", "energy_s", "total_s", "cores", "max_diff_mm")


def solve(grid, field, inverse):
    """One truth solve with ``inverse``: its displacement and a table row."""
    seen = []

    class Recorded(solver._Linear):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            seen.append(self)

    keep, solver._Linear = solver._Linear, Recorded
    try:
        start = time.perf_counter()
        out = solver.solve_reference(grid, order=2, steps=4, reuse_factor=True,
                                     materials=field, inverse=inverse)
        total = time.perf_counter() - start
    finally:
        solver._Linear = keep
    lin = seen[0]
    dofs, newton, factors, _ = out.field_data[arrays.REFERENCE_SOLVER]
    row = {"inverse": inverse, "dofs": int(dofs), "newton": int(newton), "solves": lin.solves,
           "factorisations": int(factors), "factor_s": lin.times["factor"],
           "cg_iterations": lin.cg_iterations, "solves_s": lin.times["solve"],
           "assembly_s": lin.times["assemble"], "energy_s": lin.times["energy"],
           "total_s": total, "cores": lin.threads}
    return np.asarray(out[arrays.DISPLACEMENT]), row


def page(args, grid, rows):
    """The markdown page of a run."""
    cmd = "python benchmarks/truth_solver.py " + shlex.join(sys.argv[1:])
    head = [
        "# The truth's linear solvers",
        "",
        f"Command: `{cmd.strip()}`  ",
        f"Date: {datetime.date.today().isoformat()}; machine: {platform.machine()}, "
        f"{os.cpu_count()} cores, Python {platform.python_version()}.",
        "",
        f"One truth solved once per linear solver in the same run: patient {args.patient} "
        f"({'the cohort' if args.patient >= 101 else 'the phantoms'}), "
        f"{grid.n_cells} tetrahedra (graded mesh, face {face_size_text(args.face_mm)} "
        f"within {args.face_margin_mm:g} mm of the moved bones), P2 neo-Hookean, 4 load "
        "steps, each factorisation reused as the preconditioner of conjugate gradients "
        "until those need more than 25 iterations (``reuse_factor=True``, as the cohort "
        "solves). Wall seconds: factor_s the factorisations, solves_s the direct and "
        "preconditioned CG solves, assembly_s the Hessians (NGSolve), energy_s the line "
        "search, total_s the whole solve with the model's set-up; cores: 2 where NGSolve's "
        "threads (and MKL's) were on, because other processes kept less than half a core "
        "busy, else 1; max_diff_mm: the largest "
        "vertex displacement difference from the first row's solution.",
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    body = []
    for r in rows:
        cells = [f"{r[c]:.1f}" if c.endswith("_s") else
                 f"{r[c]:.2e}" if c == "max_diff_mm" else str(r[c]) for c in COLUMNS]
        body.append("| " + " | ".join(cells) + " |")
    return "\n".join(head + body) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patient", type=int, default=101)
    ap.add_argument("--spacing", type=float, default=3.0)
    ap.add_argument("--tets", type=int, default=30000)
    ap.add_argument("--face-mm", type=float, default=3.2)
    ap.add_argument("--face-margin-mm", type=float, default=30.0)
    ap.add_argument("--inverse", nargs="+", default=["mkl", "sparsecholesky"])
    ap.add_argument("--write", type=Path, default=None, help="write the page here")
    args = ap.parse_args(argv)
    case = refinement_case(args.patient, args.spacing)
    grid, field, _ = truth_problem(case, n_tets=args.tets, mesher="graded", materials="field",
                                   face_mm=args.face_mm, face_margin_mm=args.face_margin_mm)
    rows, first = [], None
    for inverse in args.inverse:
        u, row = solve(grid, field, inverse)
        first = u if first is None else first
        row["max_diff_mm"] = float(np.abs(u - first).max())
        rows.append(row)
        print(row, flush=True)
    text = page(args, grid, rows)
    print(text)
    if args.write:
        args.write.write_text(text)


if __name__ == "__main__":
    main()
