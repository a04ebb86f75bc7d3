"""Seconds per step of ``pvcmf simulate`` on the real head CTs, and its peak memory.

Not run by CI. ``python benchmarks/real_scan_steps.py [--repeat 3] [--write]`` (needs
``PVCMF_DATA_DIR``; about five minutes with three rounds). Each round runs ``pvcmf
simulate`` with its defaults (figures and report included) on the Visible Human female's
and male's 1 mm DICOM series and a bimaxillary plan, each run in a process of its own:
its wall time from the start of the process (the imports and the reading included), its
peak resident memory (``VmHWM``) and the seconds of every step from ``summary.json``.
The table gives the medians over the rounds; the rounds alternate the two scans.
``--write`` writes ``docs/benchmarks/real_scan_steps.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pvcmf

from scan_size import PLAN, peak_memory  # noqa: E402  (benchmarks/scan_size.py)
from segmentation import data_folder, write_page  # noqa: E402  (benchmarks/segmentation.py)

SCANS = {"female": "vhp_female_head", "male": "vhp_male_head"}


def child(folder, plan, out):
    """One ``pvcmf simulate`` in this process; prints its wall time and peak memory."""
    from pvcmf.cli import main as cli

    start = float(sys.argv[sys.argv.index("--started") + 1])
    code = cli(["simulate", "--ct", str(folder), "--plan", str(plan), "--out", str(out),
                "--no-progress"])
    print(json.dumps({"code": code, "seconds": time.time() - start,
                      "peak_gb": peak_memory()}))


def one_run(folder, plan, out):
    """``(wall seconds, peak GB, {step: seconds})`` of one run in a new process."""
    proc = subprocess.run(
        [sys.executable, __file__, "--child", str(folder), str(plan), str(out),
         "--started", repr(time.time())], cwd=ROOT, capture_output=True, text=True,
        check=False)
    if proc.returncode != 0:
        raise SystemExit(f"simulate failed on {folder}:\n{proc.stderr[-3000:]}")
    record = json.loads(proc.stdout.strip().splitlines()[-1])
    steps = json.loads((out / "summary.json").read_text())["seconds"]
    return record["seconds"], record["peak_gb"], steps


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=3, help="rounds (default 3)")
    ap.add_argument("--write", action="store_true",
                    help="write docs/benchmarks/real_scan_steps.md")
    args = ap.parse_args(argv)
    runs = {name: [] for name in SCANS}
    with tempfile.TemporaryDirectory() as work:
        plan = Path(work) / "plan.toml"
        plan.write_text(PLAN)
        for r in range(args.repeat):
            for name, data in SCANS.items():
                out = Path(work) / f"{name}_{r}"
                runs[name].append(one_run(data_folder(data), plan, out))
                print(f"{name} round {r + 1}: {runs[name][-1][0]:.1f} s", flush=True)
    steps = list(runs["female"][0][2])
    rows = ["| step | " + " | ".join(SCANS) + " |", "|---|" + "---:|" * len(SCANS)]
    for step in steps:
        rows.append(f"| {step} | " + " | ".join(
            f"{statistics.median(r[2].get(step, 0.0) for r in runs[n]):.2f}" for n in SCANS)
            + " |")
    rows.append("| whole run, from the process's start (s) | " + " | ".join(
        f"{statistics.median(r[0] for r in runs[n]):.1f}" for n in SCANS) + " |")
    rows.append("| peak memory (GB) | " + " | ".join(
        f"{statistics.median(r[1] for r in runs[n]):.2f}" for n in SCANS) + " |")
    lines = [
        "`pvcmf simulate` with its defaults (figures and report included) on the Visible "
        "Human heads' 1 mm DICOM series (female: 512 x 512 x 234 voxels, the whole face; "
        "male: amalgam fillings, the face cut by the field of view) and a bimaxillary plan "
        "(the maxilla 3 mm forward and 1 mm up, the mandible 5 mm forward), each run in a "
        "process of its own. Seconds per step from `summary.json`; the whole run from the "
        "process's start (imports and reading included); peak resident memory (`VmHWM`). "
        f"Medians of {args.repeat} rounds that alternate the scans.", "", *rows]
    write_page("real_scan_steps", "Seconds per step on the real scans", lines,
               "python benchmarks/real_scan_steps.py --repeat "
               f"{args.repeat} --write", args.write)


if __name__ == "__main__":
    if "--child" in sys.argv:
        i = sys.argv.index("--child")
        child(Path(sys.argv[i + 1]), Path(sys.argv[i + 2]), Path(sys.argv[i + 3]))
    else:
        main()
