"""Build time and size of the virtual patients (``pvcmf.datasets.phantom``).

Not run by CI. ``python benchmarks/phantom.py [--spacings 1 2] [--patients 1 2 3 4]``.
Each build runs in a fresh process (cold: the one-off template set-up - muscle sweeps,
landmark rays, head bounds - is included) and prints whole numbers: wall and CPU
milliseconds, peak resident MB, image dimensions and voxel count; then, measured in the same
run, the ratio of the coarse-to-fine label rasterisation against evaluating every voxel
(``template.rasterize(..., factor=1)``) at 2 mm for patient 1.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

CHILD = """
import json, resource, time
t0, c0 = time.perf_counter(), time.process_time()
import pvcmf
case = pvcmf.datasets.phantom(patient={patient}, spacing={spacing})
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(dict(wall=wall, cpu=cpu, rss=rss, dims=case.ct.dimensions, n=case.ct.n_points)))
"""


def cold_build(patient, spacing):
    out = subprocess.run([sys.executable, "-c", CHILD.format(patient=patient, spacing=spacing)],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def banded_ratio():
    import importlib

    from pvcmf.datasets import template

    warp = template.patient_warp(1)
    grid = importlib.import_module("pvcmf.datasets.phantom")._grid_for(warp, 2.0)
    template.landmarks(), template.muscle_sdfs()  # set-up outside the timing
    times = {}
    for factor in (None, 1):
        t0 = time.perf_counter()
        template.rasterize(grid, warp, factor=factor)
        times[factor] = time.perf_counter() - t0
    return times


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--spacings", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 2, 3, 4])
    args = ap.parse_args()
    print("patient spacing_um wall_ms cpu_ms peak_MB nx ny nz voxels")
    for spacing in args.spacings:
        for patient in args.patients:
            r = cold_build(patient, spacing)
            print(patient, round(spacing * 1000), round(r["wall"] * 1000), round(r["cpu"] * 1000),
                  round(r["rss"]), *r["dims"], r["n"])
    t = banded_ratio()
    print("rasterise_2mm_ms banded", round(t[None] * 1000), "every_voxel", round(t[1] * 1000),
          "speedup_x100", round(100 * t[1] / t[None]))


if __name__ == "__main__":
    main()
