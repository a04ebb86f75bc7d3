"""Benchmark: CalculiX (ccx) on the exported virtual-patient model against pvcmf's MTM.

Not run by CI. Builds virtual patient 1 (``--spacing`` mm voxels) through
:func:`pvcmf.pipeline.simulate` once per requested tetrahedra count, solves the predicted
model with pvcmf's MTM (:func:`pvcmf.mtm.solve`, median of ``--repeats``) and with
``ccx`` on the ``.inp`` export (:func:`pvcmf.io.run_calculix`, median of ``--repeats``),
and reports sizes, materials, times and the relative difference
``||u_ccx - u_mtm|| / ||u_mtm||`` (ccx prints 7 significant digits). Also the time of the
``.inp`` and ``.feb`` exports. Writes ``docs/benchmarks/interop.md`` with ``--write``.

Run::

    python benchmarks/interop.py --counts 3000 10000 --write
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays, datasets
from pvcmf.io import run_calculix, write_feb, write_inp
from pvcmf.pipeline import simulate


def _median_time(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), out


def case(ct, plan, truth, landmarks, n_tets, repeats):
    result = simulate(ct, plan, None, bones=truth, landmarks=landmarks, n_tets=n_tets,
                      figures=False)
    post = result.post
    t_mtm, solved = _median_time(lambda: pvcmf.mtm.solve(post), repeats)
    u = np.asarray(solved[arrays.DISPLACEMENT])
    with tempfile.TemporaryDirectory() as tmp:
        t_inp, _ = _median_time(lambda: write_inp(post, Path(tmp) / "m.inp"), repeats)
        t_feb, _ = _median_time(lambda: write_feb(post, Path(tmp) / "m.feb"), repeats)
        runs = [run_calculix(post, Path(tmp) / "ccx") for _ in range(repeats)]
    t_ccx = statistics.median(s for _, s in runs)
    u_ccx = runs[0][0]
    materials = np.unique(np.column_stack([post.cell_data[arrays.E_FIBER],
                                           post.cell_data.get(arrays.E_CROSS,
                                                              post.cell_data[arrays.E_FIBER]),
                                           post.cell_data[arrays.NU]]), axis=0)
    aniso = int(np.sum(np.asarray(post.cell_data.get(arrays.E_CROSS, post.cell_data[
        arrays.E_FIBER])) != np.asarray(post.cell_data[arrays.E_FIBER])))
    bc = np.asarray(post[arrays.BC])
    return {"requested": n_tets, "tets": post.n_cells, "nodes": post.n_points,
            "materials": len(materials), "aniso": aniso,
            "sliding": int(np.sum(bc == arrays.BC_SLIDING)),
            "mtm_ms": 1000 * t_mtm, "ccx_ms": 1000 * t_ccx, "inp_ms": 1000 * t_inp,
            "feb_ms": 1000 * t_feb,
            "rel": float(np.linalg.norm(u_ccx - u) / np.linalg.norm(u))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[3000, 10000])
    parser.add_argument("--spacing", type=float, default=2.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--write", action="store_true", help="write docs/benchmarks/interop.md")
    args = parser.parse_args(argv)
    c = datasets.phantom(patient=1, spacing=args.spacing)
    rows = [case(c.ct, c.plan, c.truth, getattr(c, "landmarks", None), n, args.repeats)
            for n in args.counts]
    head = ("| requested | tetrahedra | nodes | materials | anisotropic cells | sliding nodes "
            "| MTM solve (ms) | ccx (ms) | .inp export (ms) | .feb export (ms) "
            "| relative difference |")
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    for r in rows:
        lines.append(f"| {r['requested']} | {r['tets']} | {r['nodes']} | {r['materials']} | "
                     f"{r['aniso']} | {r['sliding']} | {r['mtm_ms']:.0f} | {r['ccx_ms']:.0f} | "
                     f"{r['inp_ms']:.0f} | {r['feb_ms']:.0f} | {r['rel']:.1e} |")
    table = "\n".join(lines)
    print(table)
    if args.write:
        command = "python benchmarks/interop.py " + " ".join(sys.argv[1:] if argv is None else argv)
        machine = (f"{platform.machine()}, {os.cpu_count()} cores, {platform.system()} "
                   f"{platform.release()}, Python {platform.python_version()}, "
                   f"pvcmf {pvcmf.__version__}")
        text = ("# Exports: CalculiX against the MTM\n\n"
                "Virtual patient 1 at "
                f"{args.spacing:g} mm through the pipeline; the predicted model solved by "
                "pvcmf's MTM (direct solver) and by CalculiX `ccx` on its `.inp` export "
                "(C3D4, engineering constants, fibre orientation distribution, sliding "
                f"`*EQUATION`s). Medians of {args.repeats} runs; ccx time is the `ccx` "
                "process alone (it prints 7 significant digits, which bounds the relative "
                "difference near 1e-7).\n\n"
                f"Command: `{command}`\n\nMachine: {machine}\n\n{table}\n")
        out = Path(__file__).resolve().parent.parent / "docs" / "benchmarks" / "interop.md"
        out.write_text(text, encoding="utf-8")
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
