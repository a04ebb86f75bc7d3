"""Benchmark: facial muscle embedding (atlas + thin-plate spline) and OBB fibre directions.

Not run by CI. Prints whole numbers measured in this run: milliseconds, MiB and Dice in
per-mille (1000 = perfect overlap).

1. ``embed_muscles`` on every virtual patient at ``--spacing`` (default 1 and 2 mm) with
   three warps: ``tps`` (the paper: landmark thin-plate spline alone), ``refined`` (true
   landmarks + the atlas skin/skull registered to the patient's) and ``auto`` (no
   landmarks: similarity + non-rigid fit): time, and Dice of every muscle and of their
   union against the phantom's truth. Ratios refined/tps and auto/tps are of this run.
2. ``oriented_bounding_box`` on random points of ellipsoids of several elongations:
   long-axis error in tenths of a degree.

Run::

    python benchmarks/muscles.py                      # 1 and 2 mm, patients 1-4
    python benchmarks/muscles.py --spacing 2 --patients 1 2
"""

from __future__ import annotations

import argparse
import resource
import time
import warnings

import numpy as np


def _dice(a, b):
    n = a.sum() + b.sum()
    return 1.0 if n == 0 else 2.0 * (a & b).sum() / n


def embedding(spacings, patients):
    import pvcmf
    from pvcmf import arrays
    from pvcmf.atlas import default
    from pvcmf.filters import embed_muscles
    from pvcmf.filters.muscles import MuscleOutsideWarning

    t0 = time.perf_counter()
    atlas = default()
    print(f"atlas build: {1000 * (time.perf_counter() - t0):.0f} ms "
          f"({len(atlas.landmarks)} landmarks, {len(atlas.muscles)} muscles)")
    short = ["OO", "LLSAN", "LLS", "MAS", "ZMa", "ZMi"]
    header = " ".join(f"{s}_{side[0]}" for side in arrays.SIDES for s in short)
    for spacing in spacings:
        for p in patients:
            case = pvcmf.datasets.phantom(p, spacing=spacing)
            labels = case.truth.copy()
            t = np.array(labels[arrays.TISSUE])
            t[labels[arrays.MUSCLE] > 0] = arrays.FAT
            labels[arrays.TISSUE] = t
            del labels.point_data[arrays.MUSCLE]
            truth = np.asarray(case.truth[arrays.MUSCLE])
            print(f"\npatient {p}, {spacing:g} mm, {labels.n_points} voxels; Dice per-mille: "
                  f"union | {header}")
            times = {}
            for mode, kw in (("tps", dict(landmarks=case.landmarks, refine=False)),
                             ("refined", dict(landmarks=case.landmarks)),
                             ("auto", {})):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", MuscleOutsideWarning)
                    t0 = time.perf_counter()
                    out = embed_muscles(labels, atlas, **kw)
                    times[mode] = time.perf_counter() - t0
                m = np.asarray(out[arrays.MUSCLE])
                per = [_dice(m == i, truth == i) for i in range(1, len(arrays.MUSCLES) + 1)]
                print(f"  {mode:8s} {1000 * times[mode]:7.0f} ms  "
                      f"{1000 * _dice(m > 0, truth > 0):4.0f} | "
                      + " ".join(f"{1000 * d:4.0f}" for d in per))
            print(f"  time ratio refined/tps {times['refined'] / times['tps']:.0f}, "
                  f"auto/tps {times['auto'] / times['tps']:.0f}")
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak memory {rss:.0f} MiB")


def obb():
    from scipy.spatial.transform import Rotation

    from pvcmf.filters import oriented_bounding_box

    rng = np.random.default_rng(0)
    print("\nOBB long axis of random points in a rotated ellipsoid (tenths of a degree)")
    for semi in ((30, 10, 5), (20, 10, 5), (12, 10, 5), (30, 4, 2)):
        errs = []
        for k in range(20):
            rot = Rotation.random(random_state=k).as_matrix()
            p = rng.uniform(-1, 1, (20000, 3))
            p = p[(p**2).sum(1) <= 1] * semi
            _, axes, _ = oriented_bounding_box(p @ rot.T)
            c = min(1.0, abs(axes[0] @ rot[:, 0]))
            errs.append(np.degrees(np.arccos(c)))
        print(f"  semi-axes {semi}: mean {10 * np.mean(errs):.0f}, max {10 * np.max(errs):.0f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 2, 3, 4])
    args = ap.parse_args()
    obb()
    embedding(args.spacing, args.patients)


if __name__ == "__main__":
    main()
