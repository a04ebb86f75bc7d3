"""Benchmark of the virtual post-operative truth (``pvcmf.reference``; NGSolve, P2).

Run: ``python benchmarks/reference.py [--patient 1] [--spacing 3.0] [--tets 4000]
[--repeat 3] [--predictors tangent,proportional]`` (not run by CI; needs the ``reference``
extra). Builds the truth's planned grid for one virtual patient (true labels, conforming
mesh, materials, plan boundary conditions), then solves it with each load-step predictor
and prints whole numbers: dofs, Newton iterations, factorisations, wall and CPU
milliseconds (medians of ``--repeat``), the largest displacement difference between the
predictors in micrometres and the CPU ratio measured in the
same run. Also times one assembly and one factorisation of the P2 Hessian per NGSolve
direct solver (``--solvers``).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from pvcmf import arrays, reference
from pvcmf.datasets import phantom


def solve(grid, predictor):
    wall, cpu = time.perf_counter(), time.process_time()
    out = reference.solve_reference(grid, predictor=predictor, threads=False)
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    dofs, its, facts, _ = out.field_data["reference_solver"]
    return out[arrays.DISPLACEMENT], int(dofs), int(its), int(facts), wall, cpu


def factor_times(grid, solvers):
    """CPU seconds of one Hessian assembly and one factorisation per direct solver, at
    the linear-elastic state (the first Newton system)."""
    found = {}

    class Probe(reference._Linear):
        def linearize(self, x):
            c = time.process_time()
            super().linearize(x)
            found["assemble"] = time.process_time() - c
            for name in solvers:
                c = time.process_time()
                self.form.mat.Inverse(self.freedofs, inverse=name)
                found[name] = time.process_time() - c
            raise StopIteration

    keep, reference._Linear = reference._Linear, Probe
    try:
        reference.solve_reference(grid, threads=False)
    except StopIteration:
        pass
    finally:
        reference._Linear = keep
    return found


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patient", type=int, default=1)
    ap.add_argument("--spacing", type=float, default=3.0)
    ap.add_argument("--tets", type=int, default=4000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--predictors", default="tangent,proportional")
    ap.add_argument("--solvers", default="sparsecholesky,pardiso,umfpack")
    args = ap.parse_args()

    case = phantom(patient=args.patient, spacing=args.spacing)
    _, grid = reference._truth_grid(case, args.tets, 0.5, False)
    print(f"patient {args.patient}, spacing {args.spacing} mm, {grid.n_cells} tetrahedra, "
          f"{os.cpu_count()} cores")
    if args.solvers:
        t = factor_times(grid, args.solvers.split(","))
        print("one P2 Hessian, CPU ms: " + ", ".join(f"{k} {1000 * v:.0f}" for k, v in t.items()))
    rows, disp = {}, {}
    for name in args.predictors.split(","):
        runs = []
        for _ in range(args.repeat):
            try:
                u, dofs, its, facts, wall, cpu = solve(grid, name)
            except RuntimeError as err:  # a predictor that never converges is a result
                print(f"{name:>12}: failed: {err}")
                break
            runs.append((wall, cpu))
            disp[name] = u
        if runs:
            wall, cpu = np.median(np.array(runs), axis=0)
            rows[name] = cpu
            print(f"{name:>12}: {dofs} dofs, {its} Newton iterations, {facts} factorisations, "
                  f"wall {1000 * wall:.0f} ms, CPU {1000 * cpu:.0f} ms (median of {len(runs)})")
    if len(rows) == 2:
        (a, ca), (b, cb) = rows.items()
        diff = np.abs(disp[a] - disp[b]).max()
        print(f"CPU {b} / {a}: {cb / ca:.1f}x; largest displacement difference "
              f"{1000 * diff:.0f} um")


if __name__ == "__main__":
    main()
