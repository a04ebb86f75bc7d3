"""The predicted skin's crumple metric on the demo and on the bundled real head CTs.

Not run by CI. ``python benchmarks/crumple.py [--fit] [--write]`` (needs
``PVCMF_DATA_DIR`` for the real scans; a scan that is missing is left out) runs
:func:`pvcmf.pipeline.simulate` with its defaults on

* the demo (virtual patient 1 at the demo's voxel size with its own plan, as ``pvcmf demo``),
* headsq with ``examples/headsq_plan.toml``,
* the Visible Human female and male heads (1 mm DICOM) with the maxilla and the mandible
  each moved 3 mm forward, segments from the anatomy (no cut planes),

and reports, over the modelled skin off the scan's cuts, the number of skin edges whose
displacement jump over their length exceeds the steepest displacement gradient of the tetrahedra around
them by more than 10 % (:func:`pvcmf.filters.surface_mapping.crumple_metric`), the largest
ratio, a lower bound on the violations of *any* transfer that interpolates inside the
mesh (:func:`pvcmf.filters.crumple_bound.unavoidable_crumples`: what no extension
outside the mesh can remove), the same without the transfer's smoothing outside the
mesh (``Transfer(..., smoothing=0)``) with the transfer's nonzeros and build time, and
with ``--fit`` the same with the mesh fitted to the
dense skin (``simulate(fit_skin=True)``). ``--cases`` picks cases by the start of their
names. ``--write`` writes ``docs/benchmarks/crumple.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's pvcmf

import numpy as np  # noqa: E402

import pvcmf  # noqa: E402
from pvcmf import arrays, datasets  # noqa: E402
from pvcmf.cli import DEMO_SPACING  # noqa: E402
from pvcmf.filters.crumple_bound import unavoidable_crumples  # noqa: E402
from pvcmf.filters.surface_mapping import Transfer, crumple_metric  # noqa: E402
from pvcmf.pipeline import simulate  # noqa: E402
from pvcmf.plan import Osteotomy, Plan, read_plan  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "benchmarks" / "crumple.md"
FORWARD = Plan((Osteotomy("maxilla", translation=(0.0, 0.0, 3.0)),
                Osteotomy("mandible", translation=(0.0, 0.0, 3.0))),
               name="maxilla and mandible 3 mm forward")


def cases(data):
    """(name, kwargs of simulate) of every case whose data is present."""
    demo = datasets.phantom(patient=1, spacing=DEMO_SPACING)
    yield "demo (virtual patient 1)", dict(ct=demo.ct, plan=demo.plan, bones=demo.truth,
                                           landmarks=getattr(demo, "landmarks", None))
    yield "headsq", dict(ct=datasets.headsq(), plan=read_plan(ROOT / "examples" / "headsq_plan.toml"))
    for name in ("vhp_female_head", "vhp_male_head"):
        if (data / name).is_dir():
            yield name, dict(ct=data / name, plan=FORWARD)


def one(kwargs, fit):
    start = time.perf_counter()
    res = simulate(**kwargs, fit_skin=fit, figures=False)
    seconds = time.perf_counter() - start
    fields = res.skin_post.field_data
    pre = res.skin_pre
    u_nodes = np.asarray(res.post[arrays.DISPLACEMENT], dtype=float)
    modelled = np.asarray(pre.point_data[arrays.SKIN_MODELLED]).astype(bool)
    if arrays.SKIN_CUT in pre.point_data:  # the scan's edge: no skin to crumple (as simulate)
        modelled &= np.asarray(pre.point_data[arrays.SKIN_CUT]) == 0
    start = time.process_time()  # CPU time: less affected by other jobs than wall time
    plain = Transfer(res.post, pre, smoothing=0)
    plain_s = time.process_time() - start
    start = time.process_time()
    transfer = Transfer(res.post, pre)
    smoothed_s = time.process_time() - start
    forced = unavoidable_crumples(pre, res.post, u_nodes, transfer=transfer, modelled=modelled)
    out = np.flatnonzero(~transfer.inside & transfer.modelled)
    plain_metric = crumple_metric(pre, plain(u_nodes), res.post, u_nodes, transfer=plain,
                                  modelled=modelled)
    u_skin = np.asarray(res.skin_post.points, dtype=float) - np.asarray(pre.points, dtype=float)
    final = crumple_metric(pre, u_skin, res.post, u_nodes, transfer=transfer, modelled=modelled)
    bad = final["edges"][final["ratio"] > 1.1]
    jumps = np.linalg.norm(u_skin[bad[:, 0]] - u_skin[bad[:, 1]], axis=1)
    return {"edges": int(fields[arrays.CRUMPLE_EDGES][0]),
            "plain violations": plain_metric[arrays.CRUMPLE_VIOLATIONS],
            "plain max ratio": plain_metric[arrays.CRUMPLE_MAX_RATIO],
            "nnz": (plain.W[out].nnz / max(len(out), 1), transfer.W[out].nnz / max(len(out), 1)),
            "build": (plain_s, smoothed_s),
            "violations": int(fields[arrays.CRUMPLE_VIOLATIONS][0]),
            "max ratio": float(fields[arrays.CRUMPLE_MAX_RATIO][0]),
            "largest jump": float(jumps.max(initial=0.0)),
            "jumps over 0.05": int(np.sum(jumps > 0.05)),
            "unavoidable": forced[arrays.CRUMPLE_UNAVOIDABLE],
            "tetrahedra": res.mesh.n_cells, "seconds": seconds}


def page(rows, command):
    head = ("| case | mesh fitted to the skin | tetrahedra | skin edges | violations | max ratio "
            "| violating edges: largest jump mm, jumps over 0.05 mm "
            "| unavoidable (lower bound) | seconds | without smoothing: violations, max ratio "
            "| nonzeros per outside row | transfer build CPU s |")
    lines = ["# Crumpling of the predicted skin", "",
             f"Command: `{command}`  ",
             f"Date: {datetime.date.today().isoformat()}; machine: {platform.machine()}, "
             f"{os.cpu_count()} cores (shared with other jobs), Python "
             f"{platform.python_version()}, pvcmf {pvcmf.__version__}.", "",
             "`pvcmf.pipeline.simulate` with its defaults (`--fit`: also with "
             "`fit_skin=True`). A skin edge violates when its displacement jump over its "
             "length exceeds the steepest displacement gradient of the tetrahedra around it "
             "by more than 10 % (stretches below 1e-4 are round-off and not counted); the "
             "max ratio is the largest jump over that bound. Only the modelled skin "
             "(`skin_modelled`) off the scan's cuts (`skin_cut`: the scan's edge, not the "
             "patient's skin) is measured. The goal is zero violations. \"Unavoidable\" is a "
             "lower bound on the violations of any transfer that interpolates inside the "
             "mesh, whatever it does outside (`unavoidable_crumples`: the skin points inside "
             "the mesh fix their values, and two of them joined through outside points "
             "only may differ by no more than the allowed jumps along the path); where it "
             "is zero, no violation is proven to be forced by the mesh and its solution. "
             "Violating edges: the largest displacement jump along a violating edge and the "
             "number of violating edges that jump by more than 0.05 mm (smaller jumps are "
             "far below what a face shows; the ratio compares them with the gradient of "
             "tissue that barely moves). Seconds: the simulation. \"Without smoothing\": the same transfer with "
             "`smoothing=0` (the affine fit to the feet alone, no gradient-guided steps "
             "outside the mesh). Nonzeros per outside row: of the transfer matrix, over the "
             "modelled skin points outside the mesh, without -> with smoothing; transfer "
             "build: CPU seconds of `Transfer(mesh, skin)` without -> with smoothing, one "
             "run each.", "",
             head, "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, fit, r in rows:
        lines.append(f"| {name} | {'yes' if fit else 'no'} | {r['tetrahedra']} | {r['edges']} | "
                     f"{r['violations']} | {r['max ratio']:.2f} | "
                     f"{r['largest jump']:.3f}, {r['jumps over 0.05']} | {r['unavoidable']} | "
                     f"{r['seconds']:.0f} | {r['plain violations']}, {r['plain max ratio']:.2f} | "
                     f"{r['nnz'][0]:.0f} -> {r['nnz'][1]:.0f} | "
                     f"{r['build'][0]:.1f} -> {r['build'][1]:.1f} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fit", action="store_true", help="also run with the mesh fitted to the skin")
    ap.add_argument("--cases", nargs="*", default=None,
                    help="run only the cases whose names start with these")
    ap.add_argument("--write", action="store_true", help=f"write {PAGE.relative_to(ROOT)}")
    args = ap.parse_args()
    data = Path(os.environ.get("PVCMF_DATA_DIR", ROOT / ".." / "shared" / "data"))
    rows = []
    for name, kwargs in cases(data):
        if args.cases and not any(name.startswith(c) for c in args.cases):
            continue
        for fit in (False, True) if args.fit else (False,):
            rows.append((name, fit, one(kwargs, fit)))
            print(name, "fit" if fit else "", rows[-1][2], flush=True)
    command = ("python benchmarks/crumple.py" + (" --fit" if args.fit else "")
               + (" --cases " + " ".join(args.cases) if args.cases else "") + " --write")
    text = page(rows, command)
    print(text)
    if args.write:
        PAGE.write_text(text)


if __name__ == "__main__":
    main()
