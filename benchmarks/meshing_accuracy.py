"""Benchmark: the mesh against the virtual patient's true anatomy, against the tetrahedra count.

Not run by CI. For each virtual patient, the label image itself first: the distance (mm)
of its voxel faces between a facial muscle and other soft tissue (centres and corners) to
the true surfaces, the staircase every mesh of the labels starts from. Then for each
requested count and interface mode, ``tetrahedralize`` (conforming, the anterior
``--face-fraction`` of the head, like the pipeline) of the truth labels, judged by
:mod:`pvcmf.truth.anatomy`: the distance (mm) of the facial-muscle interfaces and of the
generic muscle / fat interfaces to the true (analytic) surfaces (p50, p90), and each
facial muscle's volume error against its true volume in the same mesh (median and
largest |error| over the twelve, the masseters' error). Modes: ``staircase`` (the
default mesher: the surfaces on the local average of the voxel faces) and ``subvoxel``
(``subvoxel=True``: the muscle sheets on the half level of the smoothed label
indicators). Writes markdown tables to ``docs/benchmarks/meshing_accuracy.md`` with the
command and machine.

Run::

    python benchmarks/meshing_accuracy.py                        # patient 1, 10k 30k 60k
    python benchmarks/meshing_accuracy.py --patients 1 2 --counts 10000 30000 100000
    python benchmarks/meshing_accuracy.py --modes subvoxel --counts 60000 200000
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf.filters import tetrahedralize
from pvcmf.filters.meshing import SURFACE_SPACING
from pvcmf.pipeline import face_box
from pvcmf.truth.anatomy import (interface_distance, interface_distance_by_muscle,
                                 label_interface_distance, muscle_volume_errors)

MODES = ("staircase", "subvoxel")

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "meshing_accuracy.md"


def label_row(case):
    d = label_interface_distance(case.truth, case)
    both = np.concatenate([d["centres"], d["corners"]])
    return {"patient": case.patient, "faces": len(d["centres"]),
            "centre_p50": np.percentile(d["centres"], 50),
            "centre_p90": np.percentile(d["centres"], 90),
            "corner_p90": np.percentile(d["corners"], 90), "all_p90": np.percentile(both, 90)}


def row(case, n_tets, face_fraction, mode="staircase", by_muscle=False):
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grid = tetrahedralize(case.truth, n_tets=n_tets, conforming=True,
                              roi=face_box(case.truth, face_fraction),
                              subvoxel=mode == "subvoxel")
    seconds = time.perf_counter() - t
    d = interface_distance(grid, case)
    v = muscle_volume_errors(grid, case).set_index("muscle")["error"]
    per = ({k: (np.percentile(x, 90) if len(x) else np.nan, len(x))
            for k, x in interface_distance_by_muscle(grid, case).items()} if by_muscle else None)
    m50, m90 = np.percentile(d["muscle"], [50, 90])
    g50, g90 = np.percentile(d["generic"], [50, 90])
    return {"patient": case.patient, "requested": n_tets, "mode": mode, "tets": grid.n_cells,
            "spacing": float(grid.field_data[SURFACE_SPACING][0]), "mesh_s": seconds, "muscle_p50": m50, "muscle_p90": m90, "generic_p50": g50,
            "generic_p90": g90, "vol_median_abs": float(v.abs().median()),
            "vol_max_abs": float(v.abs().max()),
            "masseter": float(v[["masseter_left", "masseter_right"]].abs().max()),
            "per_muscle": per, "volume": v}


def per_muscle_table(rows):
    """Markdown lines: p90 (mm), number of samples and volume error per muscle, for the
    rows measured per muscle."""
    detail = [r for r in rows if r["per_muscle"] is not None]
    if not detail:
        return []
    head = [f"{r['mode']} {r['tets']}" for r in detail]
    lines = ["", "## Per muscle", "",
             "Facial-muscle interface p90 (mm), its number of samples (face centroids and",
             "vertices) and the muscle's volume error, per mesh (mode, tetrahedra).", "",
             "| muscle | " + " | ".join(head) + " |",
             "|---|" + "---|" * len(detail)]
    for name in detail[0]["per_muscle"]:
        cells = []
        for r in detail:
            p90, n = r["per_muscle"][name]
            cells.append(f"{p90:.2f} ({n}), {100 * r['volume'][name]:+.0f} %")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patients", type=int, nargs="+", default=[1])
    ap.add_argument("--counts", type=int, nargs="+", default=[10_000, 30_000, 60_000])
    ap.add_argument("--spacing", type=float, default=2.0)
    ap.add_argument("--face-fraction", type=float, default=0.5)
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    ap.add_argument("--by-muscle", type=int, nargs="*", default=[60_000],
                    help="requested counts also tabulated per muscle")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    rows, labels = [], []
    for p in args.patients:
        case = pvcmf.datasets.phantom(p, spacing=args.spacing)
        labels.append(label_row(case))
        print(labels[-1], flush=True)
        for n in args.counts:
            for mode in args.modes:
                rows.append(row(case, n, args.face_fraction, mode, n in args.by_muscle))
                print({k: v for k, v in rows[-1].items() if k not in ("per_muscle", "volume")},
                      flush=True)
    half = args.spacing / 2
    lines = [
        "# Meshing accuracy against the true anatomy", "",
        "Distance (mm) of the mesh's muscle interfaces to the virtual patient's true (analytic)",
        "surfaces, and the facial muscles' volume errors against their true volumes in the same",
        f"mesh (:mod:`pvcmf.truth.anatomy`), {args.spacing:g} mm truth labels, conforming",
        f"``tetrahedralize`` of the anterior {args.face_fraction:g} of the head. Goal: interface",
        f"p90 within half a voxel ({half:g} mm).", "",
        f"Command: `python benchmarks/meshing_accuracy.py --patients "
        f"{' '.join(map(str, args.patients))} --counts {' '.join(map(str, args.counts))} "
        f"--spacing {args.spacing:g} --modes {' '.join(args.modes)} --by-muscle "
        f"{' '.join(map(str, args.by_muscle))}`  ",
        f"Machine: {platform.machine()}, {platform.processor() or 'cpu'}, Python "
        f"{sys.version.split()[0]}, pvcmf {pvcmf.__version__}.", "",
        "## The label image", "",
        "The labels' own facial-muscle interfaces: the voxel faces between a facial muscle and",
        "other soft tissue (`label_interface_distance`), sampled at their centres and corners",
        "as the mesh's faces are at their centroids and vertices.", "",
        "| patient | voxel faces | centres p50 | centres p90 | corners p90 | centres and corners p90 |",
        "|---|---|---|---|---|---|",
    ]
    for r in labels:
        lines.append(f"| {r['patient']} | {r['faces']} | {r['centre_p50']:.2f} | "
                     f"{r['centre_p90']:.2f} | {r['corner_p90']:.2f} | {r['all_p90']:.2f} |")
    lines += [
        "", "## The meshes", "",
        "`staircase`: the default surfaces (the local average of the voxel faces);",
        "`subvoxel`: `tetrahedralize(subvoxel=True)`, the muscle sheets on the half level of",
        "the smoothed label indicators. Working spacing: the surface triangle size (mm).", "",
        "| patient | requested | mode | tetrahedra | working spacing | mesh s | muscle p50 "
        "| muscle p90 | generic p50 | generic p90 | volume median abs error "
        "| volume max abs error | masseters |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['patient']} | {r['requested']} | {r['mode']} | {r['tets']} | "
            f"{r['spacing']:.2f} | {r['mesh_s']:.1f} | "
            f"{r['muscle_p50']:.2f} | {r['muscle_p90']:.2f} | {r['generic_p50']:.2f} | "
            f"{r['generic_p90']:.2f} | {100 * r['vol_median_abs']:.0f} % | "
            f"{100 * r['vol_max_abs']:.0f} % | {100 * r['masseter']:.0f} % |")
    lines += per_muscle_table(rows)
    lines += [
        "", "## Reading the tables", "",
        "The label image is what the mesher knows of the muscles: its voxel faces' centres lie",
        "within half a voxel of the true surfaces (the surface crosses the segment between the",
        "two voxel centres), their corners beyond. The facial muscles are straps 3-5 mm thick",
        "(:mod:`pvcmf.atlas.muscles`); where the working spacing is larger, the working grid",
        "holds a strap as one layer of cells, and placing the vertices on the image",
        "interfaces (both modes) or on the smoothed indicators (`subvoxel`) moves them but",
        "cannot restore a strap's rims and bends that the coarse grid lost: the p90 falls",
        "with the working spacing, i.e. with the count. The sub-voxel interfaces lower the",
        "median distance at every count and the p90 most where the working spacing is about",
        "the muscles' thickness.", "",
        "The thin muscles' volume errors come from the same limit. On a working grid coarser",
        "than a strap, the muscle claims as many working cells as its volume fills: a layer",
        "one cell thick over about thickness / spacing of the strap's extent, which the",
        "placement then thins to the strap, so the mesh keeps about that share of the",
        "muscle. The label image itself holds each muscle's volume closely, except where two",
        "muscles overlap (the later in `arrays.MUSCLES` keeps the voxels) and under the eyes.",
    ]
    if not args.no_write:
        PAGE.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
