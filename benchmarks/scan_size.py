"""Time, memory and prediction of a very fine scan on its working grid, against the 1 mm scan.

Not run by CI. ``python benchmarks/scan_size.py [--write]`` (needs ``PVCMF_DATA_DIR``; about
15 minutes and 8 GB of memory). The Visible Human female's 1 mm head CT stands for a scan
as most users bring it; the same head interpolated (trilinear) to 0.5 mm voxels, eight
times the voxels (491 million, as a 0.3 mm cone-beam CT of a whole face), stands for a very
fine one. Each case runs :func:`pvcmf.pipeline.simulate` (the bimaxillary plan below, no
figures) in a process of its own, which reports its wall time and its peak resident memory
(``VmHWM``, the image held in memory included):

* ``1 mm``: the scan as read (its own grid);
* ``0.5 mm, working_spacing='auto'``: the default, blocks chosen to fit
  :data:`pvcmf.filters.resolution.MAX_VOXELS`;
* ``0.5 mm, working_spacing=1.0``: blocks of 2 x 2 x 2 voxels.

Each fine case's predicted skin is compared with the 1 mm one's: at every skin point the
1 mm run models (not on a cut of the scan), the displacement of the nearest pre-operative
skin point of the fine run (median, 90th percentile and largest difference, mm), and the
distance between the two pre-operative skins there. The 0.5 mm scan on its own grid would
need about 50 bytes per voxel (25 GB): not run. ``--write`` writes
``docs/benchmarks/scan_size.md``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pvcmf

from segmentation import data_folder, write_page  # noqa: E402  (benchmarks/segmentation.py)

PLAN = """name = "bimaxillary"

[[osteotomy]]
segment = "maxilla"
translation = [0.0, 1.0, 3.0]

[[osteotomy]]
segment = "mandible"
translation = [0.0, 0.0, 5.0]
"""
CASES = {"1 mm": ("native", "auto"), "0.5 mm, working_spacing='auto'": ("fine", "auto"),
         "0.5 mm, working_spacing=1.0": ("fine", 1.0)}


def make_fine(folder, work):
    """The 1 mm head interpolated to 0.5 mm voxels (trilinear, voxel centres kept in
    place; a fine voxel whose nearest 1 mm voxel is at the image's minimum, the padding
    outside the round field of view or clipped air, keeps that value, as a scanner masks
    its field of view on the grid it reconstructs), saved as ``fine.npy`` and
    ``fine_geometry.npy`` in ``work``."""
    from scipy import ndimage

    from pvcmf import arrays, read_ct

    ct = read_ct(folder)
    vol = np.asarray(ct[arrays.CT]).reshape(ct.dimensions, order="F")
    fine = ndimage.zoom(vol, 2, order=1, grid_mode=True, mode="nearest", output=np.float32)
    low = vol == vol.min()
    for axis in range(3):  # the nearest 1 mm voxel of fine voxel j is j // 2
        low = np.repeat(low, 2, axis=axis)
    fine[low] = vol.min()
    del low
    np.save(work / "fine.npy", np.asfortranarray(fine))
    step = np.asarray(ct.spacing, dtype=float)
    np.save(work / "fine_geometry.npy",
            np.vstack([step / 2, np.asarray(ct.origin) - step / 4, ct.direction_matrix]))


def run_case(kind, spacing, work, folder):
    """One ``simulate`` in this process; writes its skins and ``case.json`` into ``work``."""
    import pyvista as pv

    from pvcmf import arrays, read_ct
    from pvcmf.pipeline import simulate

    if kind == "fine":
        vol, geometry = np.load(work / "fine.npy"), np.load(work / "fine_geometry.npy")
        ct = pv.ImageData(dimensions=vol.shape, spacing=geometry[0], origin=geometry[1],
                          direction_matrix=geometry[2:5])
        ct[arrays.CT] = vol.ravel(order="F")
        del vol
    else:
        ct = read_ct(folder)
    voxels = ct.n_points
    t = time.perf_counter()
    res = simulate(ct, work / "plan.toml", units="auto", orient="auto", figures=False,
                   working_spacing=spacing)
    seconds = time.perf_counter() - t
    for name in (arrays.TISSUE, arrays.BONE):  # the labels, for their agreement
        np.save(work / f"{name}.npy", np.asarray(res.labels[name]).reshape(
            res.labels.dimensions, order="F"))
    np.save(work / "labels_geometry.npy", np.vstack([res.labels.spacing, res.labels.origin]))
    res.skin_pre.save(work / "skin_pre.vtp")
    res.skin_post.save(work / "skin_post.vtp")
    record = {"seconds": seconds, "peak_gb": peak_memory(), "voxels": voxels,
              "working": res.working_grid, "labels_voxels": int(res.labels.n_points),
              "warnings": res.warnings}
    (work / "case.json").write_text(json.dumps(record))


def peak_memory():
    """Peak resident memory (GB) of this process since it started: ``VmHWM`` of
    ``/proc/self/status`` (reset when the process starts its program, unlike
    ``getrusage``'s ``ru_maxrss``, which keeps the parent's at the fork), or ``ru_maxrss``
    where there is no ``/proc``."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def compare(ref, other):
    """Displacement differences (mm) at the skin points ``ref`` models, against the nearest
    pre-operative skin point of ``other``, and the distance between the skins there."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    from pvcmf import arrays

    pre, post = pv.read(ref / "skin_pre.vtp"), pv.read(ref / "skin_post.vtp")
    keep = np.asarray(post[arrays.SKIN_MODELLED]) > 0
    if arrays.SKIN_CUT in post.point_data:
        keep &= np.asarray(post[arrays.SKIN_CUT]) == 0
    o_pre, o_post = pv.read(other / "skin_pre.vtp"), pv.read(other / "skin_post.vtp")
    gap, near = cKDTree(np.asarray(o_pre.points)).query(np.asarray(pre.points)[keep])
    du = np.linalg.norm(np.asarray(post[arrays.DISPLACEMENT])[keep]
                        - np.asarray(o_post[arrays.DISPLACEMENT])[near], axis=1)
    u = np.linalg.norm(np.asarray(o_post[arrays.DISPLACEMENT])[near], axis=1)
    return {"points": int(keep.sum()), "u_max": float(u.max()),
            "du_median": float(np.median(du)), "du_p90": float(np.percentile(du, 90)),
            "du_max": float(du.max()), "gap_median": float(np.median(gap)),
            "gap_p90": float(np.percentile(gap, 90))}


def dice(ref, other):
    """Dice of fat, muscle, the mandible and the maxilla of ``other``'s labels against
    ``ref``'s, on ``ref``'s grid (``other``'s label at the nearest of its voxels to each
    of ``ref``'s voxel centres; both grids axis-aligned)."""
    from pvcmf import arrays

    g_ref, g_other = np.load(ref / "labels_geometry.npy"), np.load(other / "labels_geometry.npy")
    out = {}
    for name, label, key in ((arrays.TISSUE, arrays.FAT, "fat"),
                             (arrays.TISSUE, arrays.MUSCLE_TISSUE, "muscle"),
                             (arrays.BONE, arrays.MANDIBLE, "mandible"),
                             (arrays.BONE, arrays.MAXILLA, "maxilla")):
        a, b = np.load(ref / f"{name}.npy") == label, np.load(other / f"{name}.npy") == label
        index = [np.clip(np.round((g_ref[1, ax] + g_ref[0, ax] * np.arange(a.shape[ax])
                                   - g_other[1, ax]) / g_other[0, ax]).astype(int),
                         0, b.shape[ax] - 1) for ax in range(3)]
        b = b[np.ix_(*index)]
        out[key] = 2.0 * np.count_nonzero(a & b) / max(1, a.sum() + b.sum())
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true", help="write docs/benchmarks/scan_size.md")
    ap.add_argument("--case", help=argparse.SUPPRESS)  # (a child process: one case)
    ap.add_argument("--work", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--spacing", help=argparse.SUPPRESS)
    args = ap.parse_args()
    folder = data_folder("vhp_female_head")
    if args.case:
        spacing = args.spacing if args.spacing == "auto" else float(args.spacing)
        return run_case(args.case, spacing, args.work, folder)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        make_fine(folder, tmp)
        records = {}
        for name, (kind, spacing) in CASES.items():
            work = tmp / f"case{len(records)}"
            work.mkdir()
            (work / "plan.toml").write_text(PLAN)
            for f in ("fine.npy", "fine_geometry.npy"):
                (work / f).symlink_to(tmp / f)
            subprocess.run([sys.executable, __file__, "--case", kind, "--work", str(work),
                            "--spacing", str(spacing)], check=True)
            records[name] = json.loads((work / "case.json").read_text())
            records[name]["dir"] = work
            print(name, records[name], flush=True)
        ref = records["1 mm"]["dir"]
        rows = ["| scan | voxels (million) | working grid | voxels segmented (million) | "
                "simulate (s) | peak memory (GB) | skin points compared | largest "
                "displacement (mm) | displacement difference: median / p90 / max (mm) | "
                "pre-operative skins apart: median / p90 (mm) | Dice: fat, muscle, mandible, "
                "maxilla |", "|---|" + "---:|" * 10]
        for name, r in records.items():
            c = compare(ref, r["dir"])
            same = r["dir"] == ref  # the reference row: its own skin
            grid = ("blocks " + "x".join(map(str, r["working"]["factors"])) + ", "
                    + "x".join(f"{v:g}" for v in r["working"]["spacing_mm"]) + " mm"
                    if r["working"] else "the scan's own")
            rows.append(f"| {name} | {r['voxels'] / 1e6:.0f} | {grid} | "
                        f"{r['labels_voxels'] / 1e6:.0f} | {r['seconds']:.0f} | "
                        f"{r['peak_gb']:.1f} | {c['points']} | {c['u_max']:.2f} | "
                        + ("reference | reference | reference |" if same else
                           f"{c['du_median']:.3f} / {c['du_p90']:.3f} / {c['du_max']:.2f} | "
                           f"{c['gap_median']:.3f} / {c['gap_p90']:.3f} | "
                           + ", ".join(f"{v:.3f}" for v in dice(ref, r["dir"]).values())
                           + " |"))
    lines = [
        "A scan as most users bring it, the Visible Human female's 1 mm head CT (61 million "
        "voxels), against a very fine one: the same head interpolated (trilinear) to 0.5 mm "
        "voxels, 491 million of them, as a 0.3 mm cone-beam CT of a whole face holds; a fine "
        "voxel whose nearest 1 mm voxel is at the image's minimum (the padding outside the "
        "round field of view, clipped air) keeps that value, as a scanner masks its field of "
        "view on the grid it reconstructs. `pvcmf.pipeline.simulate` runs each case (no "
        "figures) in a process of its own, which gives its wall time and its peak resident "
        "memory, the image held in memory included. The working grid "
        "(`pvcmf.filters.working_grid`) averages the fine scan over blocks of whole voxels: "
        "`working_spacing='auto'`, the default, grows the blocks until the image fits "
        "`MAX_VOXELS` (2^27, about 134 million); `working_spacing=1.0` asks for 1 mm voxels. "
        "The fine scan on its own grid (`working_spacing=None`) would need about 25 GB: not "
        "run.", "",
        "Each fine case's predicted skin against the 1 mm scan's, at every skin point the "
        "1 mm run models and that is not on a cut of the scan: the displacement of the "
        "nearest pre-operative skin point of the fine run, the difference of the two, and "
        "the distance between the two pre-operative skins there; and the Dice overlap of "
        "the labels (fat, muscle, the two jaws) on the 1 mm grid. The interpolated head is "
        "smoother than the 1 mm scan it comes from (the 1 mm voxels' edges are blended), "
        "and blocks of 2 x 2 x 2 of it are smoother still than a 1 mm scan: a real 0.5 mm "
        "scan averaged to 1 mm keeps its finer detail up to the blocks.", "",
        "Plan: the maxilla 3 mm forward and 1 mm up, the mandible 5 mm forward (translations "
        "(0, 1, 3) and (0, 0, 5) mm).", "", *rows]
    write_page("scan_size", "A very fine scan on its working grid", lines,
               "python benchmarks/scan_size.py --write", args.write)


if __name__ == "__main__":
    main()
