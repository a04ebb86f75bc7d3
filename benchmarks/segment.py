"""Speed and accuracy of CT segmentation and fat/muscle classification on the virtual patients.

Not run by CI. ``python benchmarks/segment.py [--spacings 1 2 3] [--patients 1 2 3 4]``.
Prints whole numbers: CPU milliseconds (``time.process_time``), peak MB of numpy allocations (tracemalloc), Dice in
per mille against the phantom truth, fitted fat/muscle means minus the phantom's HU; and two
ratios measured in the same run that justify implementation choices: the EDT-based skull
closing against ``scipy.ndimage.binary_closing`` with the same ball, and the per-slice
majority (median) filter against ``scipy.ndimage.median_filter``.
"""

from __future__ import annotations

import argparse
import time
import tracemalloc

import numpy as np
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.datasets.phantom import HU
from pvcmf.filters import classify as C
from pvcmf.filters import segmentation as S


def dice(a, b):
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)


def timed(func, *args, **kwargs):
    """Result, CPU milliseconds (process time: robust to other jobs on a shared machine),
    peak MB of traced allocations."""
    tracemalloc.start()
    t = time.process_time()
    out = func(*args, **kwargs)
    ms = 1000.0 * (time.process_time() - t)
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return out, ms, peak


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--spacings", type=float, nargs="+", default=[1.0, 2.0, 3.0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1, 2, 3, 4])
    args = ap.parse_args()
    print("spacing patient voxels build_ms segment_ms segment_MB classify_ms "
          "dice_soft dice_hard dice_intra dice_teeth fat_err muscle_err pooled_fat_err "
          "pooled_muscle_err fat_recall muscle_recall")
    for spacing in args.spacings:
        for p in args.patients:
            case, build_ms, _ = timed(pvcmf.datasets.phantom, patient=p, spacing=spacing)
            seg, seg_ms, seg_mb = timed(pvcmf.filters.segment, case.ct)
            (lab, mix), cls_ms, _ = timed(pvcmf.filters.classify_tissue, seg,
                                          return_mixtures=True)
            t, s, c = case.truth[arrays.TISSUE], seg[arrays.TISSUE], lab[arrays.TISSUE]
            own = (mix.n_voxels > 0) & ~mix.fallback
            fat = np.average(mix.fat_mean[own], weights=mix.n_voxels[own])
            muscle = np.average(mix.muscle_mean[own], weights=mix.n_voxels[own])
            soft = np.isin(t, arrays.SOFT_LABELS) & np.isin(c, arrays.SOFT_LABELS)
            row = [
                spacing, p, case.ct.n_points, build_ms, seg_ms, seg_mb, cls_ms,
                1000 * dice(np.isin(s, arrays.SOFT_LABELS), np.isin(t, arrays.SOFT_LABELS)),
                1000 * dice(np.isin(s, arrays.HARD_LABELS), np.isin(t, arrays.HARD_LABELS)),
                1000 * dice(s == arrays.INTRACRANIAL, t == arrays.INTRACRANIAL),
                1000 * dice(s == arrays.TEETH, t == arrays.TEETH),
                fat - HU["fat"], muscle - HU["muscle"],
                mix.pooled_means[0] - HU["fat"], mix.pooled_means[1] - HU["muscle"],
                1000 * np.mean(c[soft & (t == arrays.FAT)] == arrays.FAT),
                1000 * np.mean(c[soft & (t == arrays.MUSCLE_TISSUE)] == arrays.MUSCLE_TISSUE),
            ]
            print(f"{row[0]:g} " + " ".join(str(int(round(v))) for v in row[1:]), flush=True)

    # implementation choices, same run, finest spacing, patient 1
    case = pvcmf.datasets.phantom(patient=args.patients[0], spacing=min(args.spacings))
    seg = pvcmf.filters.segment(case.ct)
    dims = case.ct.dimensions
    hard = np.isin(seg[arrays.TISSUE], arrays.HARD_LABELS).reshape(dims, order="F")
    idx = np.nonzero(hard)
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in idx)
    r = 3.0  # segment default skull_closing (mm)
    t = time.process_time()
    ours = S._closing(hard[box], case.ct.spacing, r)
    edt_ms = 1000 * (time.process_time() - t)
    ball = S._ball(case.ct.spacing, r)
    sampling = 1.0 / np.maximum(r / np.asarray(case.ct.spacing), 1.0)  # ball = unit ball
    pad = [(k + 1, k + 1) for k in np.array(ball.shape) // 2]
    t = time.process_time()
    padded = np.pad(hard[box], pad)
    dilated = ndimage.distance_transform_edt(~padded, sampling=sampling) <= 1.0
    ref = ndimage.distance_transform_edt(dilated, sampling=sampling) > 1.0
    ref = ref[tuple(slice(a, -b) for a, b in pad)]
    ref_ms = 1000 * (time.process_time() - t)
    same = int(round(1000 * np.mean(ours == ref)))
    print(f"closing {r:g} mm: binary_closing_ms {int(edt_ms)} two_edt_ms {int(ref_ms)} "
          f"ratio {ref_ms / edt_ms:.1f} agreement_per_mille {same}")
    lab = pvcmf.filters.classify_tissue(seg, median_size=1)[arrays.TISSUE].reshape(dims, order="F")
    soft = np.isin(lab, arrays.SOFT_LABELS)
    muscle = lab == arrays.MUSCLE_TISSUE
    t = time.process_time()
    C._majority(muscle, soft, 5)
    maj_ms = 1000 * (time.process_time() - t)
    t = time.process_time()
    ndimage.median_filter(np.where(soft, muscle.astype(np.uint8) + 1, 0), size=(5, 5, 1))
    med_ms = 1000 * (time.process_time() - t)
    print(f"5x5 median: majority_ms {int(maj_ms)} median_filter_ms {int(med_ms)} "
          f"ratio {med_ms / maj_ms:.1f}")


if __name__ == "__main__":
    main()
