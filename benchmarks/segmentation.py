"""Seconds per step from a real head CT to labelled jaws: read, standardize, segment,
find_jaws, classify_tissue (Visible Human female, 1 mm, 512 x 512 x 234).

Not run by CI. ``python benchmarks/segmentation.py [--repeats 3] [--write]`` (needs
``PVCMF_DATA_DIR``). Prints CPU seconds (``time.process_time``: all threads of the process,
robust to other jobs on a shared machine) and wall seconds per step, medians of
``--repeats`` runs; ``--write`` also writes ``docs/benchmarks/segmentation.md`` with the
command and the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's pvcmf

import pvcmf  # noqa: E402
from pvcmf.filters.bone_segments import segment_volumes  # noqa: E402
from pvcmf.filters.segmentation import tissue_volumes  # noqa: E402
from pvcmf.io.orientation import standardize  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
STEPS = ("read", "standardize", "segment", "find_jaws", "classify")
CORE = ("read", "standardize", "segment", "find_jaws")


def one_run(folder):
    """CPU and wall seconds of every step, and the labels."""
    seconds = {}

    def step(name, func, *args):
        cpu, wall = time.process_time(), time.perf_counter()
        out = func(*args)
        seconds[name] = (time.process_time() - cpu, time.perf_counter() - wall)
        return out

    ct = step("read", pvcmf.read_ct, folder)
    ct, _ = step("standardize", standardize, ct)
    labels = step("segment", lambda c: pvcmf.filters.segment(c, check=False), ct)  # standardize checked it
    jaws = step("find_jaws", pvcmf.filters.find_jaws, labels)
    classified = step("classify", pvcmf.filters.classify_tissue, labels)
    return seconds, classified, jaws, ct


def machine():
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"{cpu}, {cores} cores available, Python {platform.python_version()}"


def data_folder(name):
    """The data folder ``name`` (``PVCMF_DATA_DIR``, default ``../shared/data``); exits
    naming it where it is missing."""
    folder = Path(os.environ.get("PVCMF_DATA_DIR", ROOT / ".." / "shared" / "data")) / name
    if not folder.is_dir():
        raise SystemExit(f"{folder} not found: set PVCMF_DATA_DIR")
    return folder


def write_page(name, title, lines, command, write):
    """Print a benchmark page (``title``, ``lines``, the command and the machine) and, where
    ``write``, write it to ``docs/benchmarks/<name>.md``."""
    text = "\n".join([f"# {title}", "", *lines, "", f"Command: `{command}`", "",
                      f"Machine: {machine()}.", ""])
    print(text)
    if write:
        out = ROOT / "docs" / "benchmarks" / f"{name}.md"
        out.write_text(text)
        print(f"wrote {out}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--write", action="store_true", help="write docs/benchmarks/segmentation.md")
    args = ap.parse_args()
    folder = data_folder("vhp_female_head")
    runs = []
    for _ in range(args.repeats):
        seconds, classified, jaws, ct = one_run(folder)
        runs.append(seconds)
    med = {s: (statistics.median(r[s][0] for r in runs), statistics.median(r[s][1] for r in runs))
           for s in STEPS}
    rows = ["| step | CPU s | wall s |", "|---|---:|---:|"]
    rows += [f"| {s} | {med[s][0]:.2f} | {med[s][1]:.2f} |" for s in STEPS]
    rows.append(f"| read + standardize + segment + find_jaws | "
                f"{sum(med[s][0] for s in CORE):.2f} | {sum(med[s][1] for s in CORE):.2f} |")
    vols = {**{k: round(v, 1) for k, v in tissue_volumes(classified).items()},
            **{k: round(v, 1) for k, v in segment_volumes(jaws).items()}}
    command = "PVCMF_DATA_DIR=/path/to/data python benchmarks/segmentation.py --write"
    write_page("segmentation", "Segmentation speed on a real head CT", [
        "Visible Human female head CT, 1 mm, dimensions "
        f"{' x '.join(str(d) for d in ct.dimensions)}: seconds per step, median of "
        f"{args.repeats} runs. CPU seconds count every thread of the process.",
        "",
        *rows,
        "",
        "Volumes (mL) found: " + ", ".join(f"{k} {v}" for k, v in vols.items()) + ".",
    ], command, args.write)


if __name__ == "__main__":
    main()
