"""End-to-end timings of the prediction: seconds per step of ``pvcmf demo``,
and the boundary-condition step alone against the solve it feeds.

Run: ``python benchmarks/pipeline.py [--patient 1] [--spacing 2] [--n-tets 25000]``.
Prints whole milliseconds per step (and ratios measured in the same run). Not run by CI.
"""

import argparse
import time

import numpy as np

import pvcmf
from pvcmf.filters import apply_plan
from pvcmf.pipeline import simulate


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--patient", type=int, default=1)
    parser.add_argument("--spacing", type=float, default=2.0)
    parser.add_argument("--n-tets", type=int, default=25_000)
    parser.add_argument("--no-muscles", action="store_true")
    args = parser.parse_args()

    start = time.perf_counter()
    case = pvcmf.datasets.phantom(args.patient, spacing=args.spacing)
    phantom_ms = 1000 * (time.perf_counter() - start)
    res = simulate(case.ct, case.plan, bones=case.truth, landmarks=case.landmarks,
                   n_tets=args.n_tets, muscles=not args.no_muscles)
    print(f"phantom {args.patient} at {args.spacing} mm: {phantom_ms:.0f} ms")
    for step, seconds in res.timings.items():
        print(f"{step:<20} {1000 * seconds:8.0f} ms")
    print(f"{'total':<20} {1000 * sum(res.timings.values()) + phantom_ms:8.0f} ms")
    if res.mesh is None:
        print("no mesh: prediction steps not available")
        return
    grid = res.mesh
    times = []
    for _ in range(3):
        t = time.perf_counter()
        out = apply_plan(grid, case.plan, res.labels)
        times.append(time.perf_counter() - t)
    bc = out["bc"]
    counts = {k: int(np.sum(bc == v)) for k, v in pvcmf.arrays.BC_CODES.items()}
    best = min(times)
    print(f"apply_plan on {grid.n_cells} tets / {grid.n_points} points: {1000 * best:.0f} ms "
          f"(best of 3), counts {counts}")
    solve = res.timings.get("solve")
    if solve:
        print(f"apply_plan / solve time ratio: {best / solve:.2f}")


if __name__ == "__main__":
    main()
