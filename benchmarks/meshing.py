"""Benchmark: labelled tetrahedral meshing against the homogeneous mesh + muscle-fraction baselines.

Not run by CI. Prints whole numbers (ms, MiB, degrees x10, per-mille) measured in this
run. Every case runs in a fresh subprocess so that its peak memory is its own (``VmHWM``,
reset after loading the image so that it is the meshing's peak).

1. ``tetrahedralize`` (conforming, the proposed method) on the 1 mm virtual patient at
   10k/30k/100k/300k requested tetrahedra, meshing the anterior half of the head like
   the pipeline (``--face-fraction``): median wall and CPU time of ``--repeats`` runs
   peak memory, count hit, min / 1st-percentile dihedral angle,
   label agreement at the centroids, volume error of every named muscle.
2. the baseline: the homogeneous mesh (``conforming=False``) + ``sample_muscle_fraction``
   at 10/100/1000 points per tetrahedron and ``average_voxels``: time, and the fraction
   error against the exact fraction on an analytic half-space muscle (exact = volume of
   the clipped tetrahedra, VTK ``clip``) and on the patient against 4000 points.

3. ``--against REV``: the current mesher against the one of git revision ``REV``,
   alternating in one warm process (median CPU and wall time, agreement, ratio); ``REV``
   must be a revision where the mesher is the single module ``pvcmf/filters/meshing.py``.
4. ``--ceiling``: the share of points at a given depth inside a region of the smooth
   anatomy (the virtual patient at half the spacing) whose nearest voxel has another
   label, i.e. what the centroid test would report for exactly placed surfaces.
5. ``--table``: agreement against the requested count (2 mm patients 1-4 and the 1 mm
   patient 1 up to 500k) with the failing cells split into fat/muscle confusion, bone,
   air, teeth, and the share of them within one voxel of a structure thinner than the
   element (``disagreement_split``); prints JSON rows and a markdown table. 4. and 5.
   live in ``benchmarks/meshing_agreement.py``.
6. ``--grading G``: the graded meshes (``tetrahedralize(grading=G)``) against the uniform
   ones at ``--counts``: the same rows as 1. for both (fresh subprocess each, with the
   RMS of the muscle-volume errors), then uniform, graded and uniform at the graded
   mesh's count alternating in one warm process (median wall and CPU time, ratios, label
   agreement per cell and weighted by volume); with ``--shell MM`` only the latter, on
   the analytic head shell with MM of soft tissue.

Run::

    python benchmarks/meshing.py                 # all cases, 1 mm patient 1
    python benchmarks/meshing.py --spacing 2 --counts 10000 30000
    python benchmarks/meshing.py --compare-only   # proposed vs baseline, one warm process
    python benchmarks/meshing.py --no-baseline --counts 10000 30000 100000 300000
    python benchmarks/meshing.py --against REV --counts 30000 160000  # old vs new mesher
    python benchmarks/meshing.py --spacing 2 --ceiling  # centroid-test ceiling per depth
    python benchmarks/meshing.py --table          # agreement vs count, failing cells by class
    python benchmarks/meshing.py --grading 2 --counts 30000 160000  # graded vs uniform
    python benchmarks/meshing.py --grading 3 --shell 30 --counts 30000 100000  # thick tissue
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays
from pvcmf.filters import average_voxels, meshing, sample_muscle_fraction, tetrahedralize
from pvcmf.filters.meshing import shell_labels
from pvcmf.pipeline import face_box

CACHE = Path(os.environ.get("PVCMF_CACHE_DIR", tempfile.gettempdir())) / "pvcmf_benchmark_meshing"


def _labels(patient, spacing):
    import pyvista as pv


    import hashlib
    import importlib

    phantom_module = importlib.import_module("pvcmf.datasets.phantom")
    template = importlib.import_module("pvcmf.datasets.template")

    # the cache is keyed on the phantom's source, so a changed virtual patient is rebuilt
    digest = hashlib.sha1(
        Path(template.__file__).read_bytes() + Path(phantom_module.__file__).read_bytes()
    ).hexdigest()[:10]
    CACHE.mkdir(parents=True, exist_ok=True)
    path = CACHE / f"truth_p{patient}_{spacing:g}mm_{digest}.vti"
    if path.exists():
        return pv.read(path)
    truth = pvcmf.datasets.phantom(patient, spacing=spacing).truth
    truth.save(path)
    return truth


def _centroid_labels(labels, grid):
    """Tissue label of the image voxel nearest to every cell centroid."""
    c = grid.cell_centers().points
    ijk = np.rint((c - np.asarray(labels.origin)) / np.asarray(labels.spacing)).astype(int)
    ijk = np.clip(ijk, 0, np.asarray(labels.dimensions) - 1)
    d = labels.dimensions
    return np.asarray(labels[arrays.TISSUE])[ijk[:, 0] + d[0] * (ijk[:, 1] + d[1] * ijk[:, 2])]


def _agreement(labels, grid):
    lab = _centroid_labels(labels, grid)
    soft = np.isin(lab, arrays.SOFT_LABELS)
    agree = lab == grid.cell_data[arrays.TISSUE]
    return float(soft.mean()), float(agree[soft].mean()), float(agree.mean())


def _agreement_by_volume(labels, grid):
    """Share of the mesh volume in cells whose centroid voxel has the cell's tissue."""
    lab = _centroid_labels(labels, grid)
    vol = grid.compute_cell_sizes(length=False, area=False)["Volume"]
    return float(vol[lab == grid.cell_data[arrays.TISSUE]].sum() / vol.sum())


def _timed(func, *args, **kwargs):
    w, c = time.perf_counter(), time.process_time()
    out = func(*args, **kwargs)
    return out, time.perf_counter() - w, time.process_time() - c


def _peak_mib():
    """Peak resident memory of this process in MiB.

    ``VmHWM`` from /proc (reset by ``exec``); ``ru_maxrss`` elsewhere, which Linux keeps
    across ``exec`` and would report the parent's peak.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)


def _roi(labels, face_fraction):
    if face_fraction is None:
        return None

    return face_box(labels, face_fraction)


def _warm(labels, face_fraction):
    """(labels, face-box roi or None) after one small meshing: imports and caches warm,
    warnings silenced for the timed runs that follow."""
    import warnings


    roi = None if face_fraction is None else _roi(labels, face_fraction)
    warnings.simplefilter("ignore")
    meshing.tetrahedralize(labels, n_tets=5_000, roi=roi)
    return labels, roi


def _muscle_volume_error(labels, grid):
    """Per muscle id 1..12: mesh volume / image volume - 1, in per cent (None if absent)."""
    n = len(arrays.MUSCLES) + 1
    image = np.bincount(np.asarray(labels[arrays.MUSCLE]), minlength=n) * float(np.prod(labels.spacing))
    vol = grid.compute_cell_sizes(length=False, area=False)["Volume"]
    mesh = np.bincount(grid.cell_data[arrays.MUSCLE], weights=vol, minlength=n)
    return [round(100 * (mesh[m] / image[m] - 1)) if image[m] > 0 else None for m in range(1, n)]


def _rms(errors):
    errors = [e for e in errors if e is not None]
    return round(float(np.sqrt(np.mean(np.square(errors))))) if errors else None


def case_mesh(patient, spacing, n_tets, conforming, face_fraction=0.5, repeats=3, grading=None):
    import os
    import warnings


    labels = _labels(patient, spacing)
    roi = _roi(labels, face_fraction)
    rss0 = _peak_mib()  # image, imports and the face box (labels.points: 24 bytes a voxel)
    try:  # reset the peak so that peak_mib is the meshing's own (Linux >= 4.0)
        import gc

        gc.collect()
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass
    walls, cpus = [], []
    for _ in range(repeats):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            grid, wall, cpu = _timed(
                tetrahedralize, labels, n_tets=n_tets, conforming=conforming, roi=roi, grading=grading
            )
        walls.append(wall)
        cpus.append(cpu)
    inside, agree_soft, agree_all = _agreement(labels, grid)
    fd = grid.field_data
    errors = _muscle_volume_error(labels, grid) if conforming else None
    return {
        "n_tets": n_tets,
        "conforming": conforming,
        "grading": grading,
        "face_fraction": face_fraction,
        "cells": grid.n_cells,
        "wall_ms_median": round(float(np.median(walls)) * 1000),
        "cpu_ms_median": round(float(np.median(cpus)) * 1000),
        "repeats": repeats,
        "surface_ms": round(fd[meshing.TIME_SURFACE][0] * 1000),
        "volume_ms": round(fd[meshing.TIME_VOLUME][0] * 1000),
        "spacing_x100": round(fd[meshing.SURFACE_SPACING][0] * 100),
        "peak_mib": _peak_mib(),
        "image_mib": rss0,
        "min_dihedral_x10": round(fd[meshing.MIN_DIHEDRAL][0] * 10),
        "p1_dihedral_x10": round(fd[meshing.P1_DIHEDRAL][0] * 10),
        "min_radius_ratio_x1000": round(fd[meshing.MIN_RADIUS_RATIO][0] * 1000),
        "centroids_in_soft_permille": round(inside * 1000),
        "label_agree_in_soft_permille": round(agree_soft * 1000),
        "label_agree_all_permille": round(agree_all * 1000),
        "muscle_volume_error_percent": errors,
        "muscle_volume_rms_percent": _rms(errors) if conforming else None,
        "warnings": [str(w.message)[:120] for w in caught],
    }


def _halfspace(n_tets):
    """Homogeneous shell mesh and a half-space muscle x >= 0 with its exact fractions."""
    import pyvista as pv


    labels = shell_labels(spacing=1.0)
    grid = tetrahedralize(labels, n_tets=n_tets, conforming=False)
    x = labels.points[:, 0]
    # nearest-voxel lookup: muscle exactly where x >= -spacing / 2
    labels.point_data[arrays.TISSUE] = np.where(x >= 0, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    labels.point_data[arrays.MUSCLE] = np.where(x >= 0, 1, 0).astype(np.uint8)
    g = grid.copy()
    g.cell_data["cid"] = np.arange(g.n_cells)
    part = g.clip(normal=(-1, 0, 0), origin=(-0.5, 0, 0), invert=True)
    vol = part.compute_cell_sizes(length=False, area=False)["Volume"]
    exact = np.bincount(part.cell_data["cid"], weights=vol, minlength=g.n_cells)
    exact /= grid.compute_cell_sizes(length=False, area=False)["Volume"]
    return grid, labels, np.clip(exact, 0, 1), pv


def case_fractions(patient, spacing, n_tets):
    out = {"n_tets": n_tets}
    grid, labels, exact, _ = _halfspace(n_tets)
    cut = (exact > 0) & (exact < 1)
    for n in (10, 100, 1000):
        res, wall, _ = _timed(sample_muscle_fraction, grid, labels, n_points=n)
        err = res[arrays.MUSCLE_FRACTION] - exact
        out[f"halfspace_rms_err_permille_n{n}"] = round(float(np.sqrt(np.mean(err[cut] ** 2))) * 1000)
    res, wall, _ = _timed(average_voxels, grid, labels)
    err = res[arrays.MUSCLE_FRACTION] - exact
    out["halfspace_rms_err_permille_voxels"] = round(float(np.sqrt(np.mean(err[cut] ** 2))) * 1000)
    out["halfspace_cut_cells"] = int(cut.sum())

    labels = _labels(patient, spacing)
    grid, wall, _ = _timed(tetrahedralize, labels, n_tets=n_tets, conforming=False)
    out["homogeneous_mesh_ms"] = round(wall * 1000)
    out["homogeneous_cells"] = grid.n_cells
    ref = sample_muscle_fraction(grid, labels, n_points=4000, seed=99)[arrays.MUSCLE_FRACTION]
    has = ref > 0
    for n in (10, 100, 1000):
        res, wall, _ = _timed(sample_muscle_fraction, grid, labels, n_points=n)
        out[f"sample_ms_n{n}"] = round(wall * 1000)
        err = res[arrays.MUSCLE_FRACTION] - ref
        out[f"patient_rms_err_permille_n{n}"] = round(float(np.sqrt(np.mean(err[has] ** 2))) * 1000)
    res, wall, _ = _timed(average_voxels, labels=labels, grid=grid)
    out["average_voxels_ms"] = round(wall * 1000)
    err = res[arrays.MUSCLE_FRACTION] - ref
    out["patient_rms_err_permille_voxels"] = round(float(np.sqrt(np.mean(err[has] ** 2))) * 1000)
    out["cells_with_muscle"] = int(has.sum())
    return out


def compare_same_process(patient, spacing, n_tets=30_000, repeats=2):
    """Proposed vs baseline in one warm process, alternating, best of ``repeats``."""
    import warnings


    labels = _labels(patient, spacing)
    warnings.simplefilter("ignore")
    tetrahedralize(labels, n_tets=5_000)  # imports and caches warm
    best = {}
    for _ in range(repeats):
        _, w, c = _timed(tetrahedralize, labels, n_tets=n_tets)
        best["conforming"] = min(best.get("conforming", (1e9, 1e9)), (w, c))
        grid, w1, c1 = _timed(tetrahedralize, labels, n_tets=n_tets, conforming=False)
        _, w2, c2 = _timed(sample_muscle_fraction, grid, labels, n_points=100)
        best["homogeneous+sampling100"] = min(
            best.get("homogeneous+sampling100", (1e9, 1e9)), (w1 + w2, c1 + c2)
        )
        best["sampling100"] = min(best.get("sampling100", (1e9, 1e9)), (w2, c2))
    return {k: {"wall_ms": round(v[0] * 1000), "cpu_ms": round(v[1] * 1000)} for k, v in best.items()}


def compare_revision(patient, spacing, revision, counts, face_fraction=0.5, repeats=3):
    """Current mesher vs the one of git ``revision``, alternating in one warm process.

    The previous ``pvcmf/filters/meshing.py`` is read with ``git show`` and imported as
    a module of ``pvcmf.filters``; both mesh the same image and ROI ``repeats`` times per
    count. Returns medians (ms) and the ratio new / old of the CPU times.
    """
    import importlib.util
    import statistics


    root = Path(__file__).resolve().parents[1]
    source = subprocess.run(
        ["git", "show", f"{revision}:pvcmf/filters/meshing.py"], cwd=root, capture_output=True,
        text=True, check=True,
    ).stdout
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "meshing_previous.py"
        path.write_text(source)
        spec = importlib.util.spec_from_file_location("pvcmf.filters._meshing_previous", path)
        old = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(old)
    labels, roi = _warm(_labels(patient, spacing), face_fraction)
    rows = []
    for n in counts:
        times = {"old": [], "new": []}
        grids = {}
        for _ in range(repeats):
            for name, mod in (("old", old), ("new", meshing)):
                grid, w, c = _timed(mod.tetrahedralize, labels, n_tets=n, roi=roi)
                times[name].append((w, c, grid.n_cells, _agreement(labels, grid)[2]))
                grids[name] = grid
        row = {"n_tets": n, "revision": revision}
        for name, t in times.items():
            row[name] = {
                "wall_ms_median": round(1000 * statistics.median(x[0] for x in t)),
                "cpu_ms_median": round(1000 * statistics.median(x[1] for x in t)),
                "cells": t[0][2],
                "label_agree_all_permille": round(1000 * t[0][3]),
            }
        row["cpu_new_over_old_x100"] = round(100 * row["new"]["cpu_ms_median"] / row["old"]["cpu_ms_median"])
        a, b = grids["old"], grids["new"]  # same cells and labels, points to round-off
        row["same_mesh"] = bool(
            a.n_points == b.n_points and np.array_equal(a.cells, b.cells)
            and np.abs(np.asarray(a.points) - np.asarray(b.points)).max() < 1e-9
            and np.array_equal(a.cell_data["muscle"], b.cell_data["muscle"])
        )
        rows.append(row)
    return rows


def compare_grading(patient, spacing, grading, counts, face_fraction=0.5, repeats=3, shell_soft=None):
    """Uniform and graded meshes alternating in one warm process: medians and ratios.

    Also the uniform mesh at the graded mesh's count ("uniform_equal_count", requested
    ``n * graded cells / uniform cells`` after the first pair): the uniform calibration
    lands 11-16 % below the request on the patients, the graded one on it.
    ``shell_soft``: the analytic head shell (``shell_labels``) with that soft-tissue
    thickness in mm instead of the patient (whole shell, no roi).
    """
    import statistics


    if shell_soft:
        labels, roi = _warm(meshing.shell_labels(spacing=spacing, soft=shell_soft), None)
    else:
        labels, roi = _warm(_labels(patient, spacing), face_fraction)
    rows = []
    for n in counts:
        times = {"uniform": [], "graded": [], "uniform_equal_count": []}
        grids = {}
        n_equal = None
        for _ in range(repeats):
            for name, g in (("uniform", None), ("graded", grading), ("uniform_equal_count", None)):
                if name == "uniform_equal_count":
                    if n_equal is None:
                        n_equal = round(n * grids["graded"].n_cells / grids["uniform"].n_cells)
                    request = n_equal
                else:
                    request = n
                grid, w, c = _timed(meshing.tetrahedralize, labels, n_tets=request, roi=roi, grading=g)
                times[name].append((w, c))
                grids[name] = grid
        row = {"n_tets": n, "grading": grading, "repeats": repeats, "shell_soft_mm": shell_soft}
        for name, t in times.items():
            grid = grids[name]
            fd = grid.field_data
            row[name] = {
                "wall_ms_median": round(1000 * statistics.median(x[0] for x in t)),
                "cpu_ms_median": round(1000 * statistics.median(x[1] for x in t)),
                "cells": grid.n_cells,
                "spacing_x100": round(fd[meshing.SURFACE_SPACING][0] * 100),
                "min_dihedral_x10": round(fd[meshing.MIN_DIHEDRAL][0] * 10),
                "p1_dihedral_x10": round(fd[meshing.P1_DIHEDRAL][0] * 10),
                "label_agree_all_permille": round(1000 * _agreement(labels, grid)[2]),
                # the same test weighted by cell volume: grading moves cells from the deep
                # inside (which agree) to the surfaces (which fail more), so the per-cell
                # share is biased against graded meshes
                "label_agree_volume_permille": round(1000 * _agreement_by_volume(labels, grid)),
                "muscle_volume_rms_percent": _rms(_muscle_volume_error(labels, grid)),
            }
        row["wall_graded_over_uniform_x100"] = round(
            100 * row["graded"]["wall_ms_median"] / row["uniform"]["wall_ms_median"]
        )
        row["cpu_graded_over_uniform_x100"] = round(
            100 * row["graded"]["cpu_ms_median"] / row["uniform"]["cpu_ms_median"]
        )
        row["uniform_equal_count"]["n_tets_requested"] = n_equal
        row["cpu_graded_over_uniform_equal_count_x100"] = round(
            100 * row["graded"]["cpu_ms_median"] / row["uniform_equal_count"]["cpu_ms_median"]
        )
        rows.append(row)
    return rows


def _run_child(args):
    cmd = [sys.executable, __file__, "--child", json.dumps(args)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        return {"case": args, "error": res.stderr.strip().splitlines()[-1:]}
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--patient", type=int, default=1)
    p.add_argument("--spacing", type=float, default=1.0)
    p.add_argument("--counts", type=int, nargs="+", default=[10_000, 30_000, 100_000, 300_000])
    p.add_argument("--compare-only", action="store_true", help="only the same-process comparison")
    p.add_argument("--face-fraction", type=float, default=0.5,
                   help="mesh the anterior fraction of the head like the pipeline (0: whole head)")
    p.add_argument("--repeats", type=int, default=3, help="timing repeats per case (median)")
    p.add_argument("--no-baseline", action="store_true",
                   help="skip the homogeneous meshes and the sampling baseline")
    p.add_argument("--against", default=None, metavar="REV",
                   help="only: current mesher vs the one of git revision REV, one process")
    p.add_argument("--ceiling", action="store_true",
                   help="only: wrong-voxel rate of exact surfaces per centroid depth")
    p.add_argument("--table", action="store_true",
                   help="only: agreement against count with the failing cells split by class "
                        "(2 mm patients --patients at --counts, 1 mm patient 1 at --counts + 500k)")
    p.add_argument("--patients", type=int, nargs="+", default=[1, 2, 3, 4],
                   help="patients of --table (2 mm)")
    p.add_argument("--grading", type=float, default=None, metavar="G",
                   help="only: graded (grading=G) against uniform meshes at --counts")
    p.add_argument("--shell", type=float, default=None, metavar="MM",
                   help="with --grading: only the same-process comparison, on the analytic "
                        "shell with MM of soft tissue (e.g. 30: thicker than a face)")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        spec = json.loads(a.child)
        kind = spec.pop("kind")
        result = case_mesh(**spec) if kind == "mesh" else case_fractions(**spec)
        print(json.dumps(result))
        return
    if a.grading and a.shell:
        print(f"# analytic shell, {a.shell:g} mm of soft tissue, at {a.spacing:g} mm")
        for row in compare_grading(None, a.spacing, a.grading, a.counts, None, a.repeats, a.shell):
            print(json.dumps(row), flush=True)
        return
    _labels(a.patient, a.spacing)  # build the phantom once, cached on disk
    print(f"# patient {a.patient} at {a.spacing:g} mm; wall and CPU in ms")
    if a.compare_only:
        print(json.dumps(compare_same_process(a.patient, a.spacing)), flush=True)
        return
    ff = a.face_fraction if a.face_fraction > 0 else None
    if a.against:
        for row in compare_revision(a.patient, a.spacing, a.against, a.counts, ff, a.repeats):
            print(json.dumps(row), flush=True)
        return
    if a.grading:
        for n in a.counts:
            for g in (None, a.grading):
                row = _run_child(
                    {"kind": "mesh", "patient": a.patient, "spacing": a.spacing, "n_tets": n,
                     "conforming": True, "face_fraction": ff, "repeats": a.repeats, "grading": g}
                )
                print(json.dumps(row), flush=True)
        print("# same warm process, alternating uniform / graded:")
        for row in compare_grading(a.patient, a.spacing, a.grading, a.counts, ff, a.repeats):
            print(json.dumps(row), flush=True)
        return
    if a.table or a.ceiling:  # benchmarks/meshing_agreement.py
        from meshing_agreement import agreement_ceiling, agreement_markdown, agreement_table
    if a.table:
        cases = [(q, 2.0) for q in a.patients] + [(1, 1.0)]
        for q, spacing in cases:
            _labels(q, spacing)
        counts = {2.0: a.counts, 1.0: sorted(set(a.counts) | {500_000})}
        rows = agreement_table(cases, counts, ff)
        print("# per-mille in the JSON; the table: % of all cells per class (in brackets: % of the")
        print("# class explained by a structure thinner than the element)")
        print(agreement_markdown(rows))
        return
    if a.ceiling:
        print(json.dumps(agreement_ceiling(a.patient, a.spacing, face_fraction=ff)), flush=True)
        return
    rows = []
    for n in a.counts:
        for conforming in (True,) if a.no_baseline else (True, False):
            row = _run_child(
                {"kind": "mesh", "patient": a.patient, "spacing": a.spacing, "n_tets": n,
                 "conforming": conforming, "face_fraction": ff, "repeats": a.repeats}
            )
            rows.append(row)
            print(json.dumps(row), flush=True)
    if a.no_baseline:
        return
    frac = _run_child({"kind": "fractions", "patient": a.patient, "spacing": a.spacing, "n_tets": 30_000})
    print(json.dumps(frac), flush=True)
    same = compare_same_process(a.patient, a.spacing)
    print("# same warm process, best of 2:", json.dumps(same))
    ratio = same["conforming"]["cpu_ms"] / same["homogeneous+sampling100"]["cpu_ms"]
    print(f"# 30k: conforming / (homogeneous + 100-point sampling), CPU, x100 = {round(100 * ratio)}")


if __name__ == "__main__":
    main()
