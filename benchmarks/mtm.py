"""Speed of pvcmf's MTM solver: 30k assemble + solve and a 20-value Poisson sweep.

Not run by CI. ``python benchmarks/mtm.py --against REF`` measures this tree's solver and the
one of git revision ``REF`` (checked out with ``git worktree add`` under the temporary
folder) in the same run: every measurement runs in a fresh subprocess that imports one of the
two ``pvcmf`` packages (``PYTHONPATH``), the two alternate, and the ratio is taken per round
(median of ``--rounds``). Without ``--against`` it compares this tree's backends and options.
``--write docs/benchmarks/mtm.md`` writes the tables as a MyST page with the command and the
machine.

Measured per subprocess: ``assemble+solve``, a :class:`pvcmf.mtm.Solver` built from the grid
and solved (median of ``--repeat``, after one warm-up), and ``sweep``, one Solver built with
the first of 20 Poisson ratios (0 to 0.495) and updated for the other 19 (refactor and solve
each). The mesh is a synthetic head-like shell (a thick spherical cap, 12 mm soft tissue,
jittered structured grid split into tetrahedra) with a muscle band (paper 000 Table I
materials, fibres along the band): the inner surface is fixed at the back, joint (moved 5 mm
forward) at the chin, and sliding along its normal over the teeth; the outer surface is free.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
import pyvista as pv

from pvcmf import arrays

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: what the page says of the ``--against`` revision
REF_NOTE = ("REF: a revision whose solver chose its backend, precision and threads by itself "
            "from the machine's load and past timings (the `before` rows); this tree's solver "
            "does what the caller asks, with documented defaults (`Solver(backend='auto', "
            "precision='auto', threads=1)`: PARDISO, mixed precision, one thread here).")
#: variants of this tree's solver: label -> Solver keyword arguments
VARIANTS = {
    "default": {},
    "pardiso mixed": {"backend": "pardiso", "precision": "mixed"},
    "pardiso double, 1 thread": {"backend": "pardiso", "precision": "double", "threads": 1},
    "pardiso mixed, 2 threads": {"backend": "pardiso", "precision": "mixed", "threads": 2},
    "pardiso double, 2 threads": {"backend": "pardiso", "precision": "double", "threads": 2},
    "pardiso mixed, MKL threads": {"backend": "pardiso", "precision": "mixed", "threads": None},
    "superlu": {"backend": "superlu"},
}


def shell_mesh(n_tets, seed=0):
    """Thick spherical-cap shell with about ``n_tets`` tetrahedra, bc and materials set."""
    # hexes = nr * nt * np, 5 tets per hex (vtkDataSetTriangleFilter on a structured grid)
    nh = n_tets / 5.0
    nr = max(3, int(round((nh / 12.0) ** (1 / 3))))
    nt = max(4, int(round(np.sqrt(nh / nr / 1.5))))
    npp = max(4, int(round(nh / nr / nt)))
    r = np.linspace(80.0, 92.0, nr + 1)
    th = np.linspace(0.35 * np.pi, 0.75 * np.pi, nt + 1)  # polar angle
    ph = np.linspace(-0.1 * np.pi, 1.1 * np.pi, npp + 1)  # azimuth, face at pi/2 (y+)
    R, T, P = np.meshgrid(r, th, ph, indexing="ij")
    rng = np.random.default_rng(seed)
    dr, dt, dp = r[1] - r[0], th[1] - th[0], ph[1] - ph[0]
    inner = (R > r[0]) & (R < r[-1]) & (T > th[0]) & (T < th[-1]) & (P > ph[0]) & (P < ph[-1])
    R = R + inner * rng.uniform(-0.2, 0.2, R.shape) * dr
    T = T + inner * rng.uniform(-0.2, 0.2, T.shape) * dt
    P = P + inner * rng.uniform(-0.2, 0.2, P.shape) * dp
    x, y, z = R * np.sin(T) * np.cos(P), R * np.sin(T) * np.sin(P), R * np.cos(T)
    grid = pv.StructuredGrid(x, y, z).triangulate()
    grid = grid.clean() if grid.n_points != x.size else grid
    pts = grid.points
    rad = np.linalg.norm(pts, axis=1)
    azim = np.arctan2(pts[:, 1], pts[:, 0])
    polar = np.arccos(pts[:, 2] / rad)
    bc = np.zeros(grid.n_points, np.int8)
    disp = np.zeros((grid.n_points, 3))
    normal = np.zeros((grid.n_points, 3))
    on_inner = rad < r[0] + 1e-6
    back = (azim < 0.05 * np.pi) | (azim > 0.95 * np.pi) | (azim < -0.5 * np.pi)
    bc[on_inner | back] = arrays.BC_FIXED
    chin = on_inner & (polar > 0.62 * np.pi) & (np.abs(azim - 0.5 * np.pi) < 0.25 * np.pi)
    bc[chin] = arrays.BC_JOINT
    disp[chin] = (0.0, 5.0, 1.0)
    teeth = on_inner & (polar > 0.5 * np.pi) & (polar <= 0.62 * np.pi) \
        & (np.abs(azim - 0.5 * np.pi) < 0.2 * np.pi)
    bc[teeth] = arrays.BC_SLIDING
    normal[teeth] = pts[teeth] / rad[teeth, None]
    disp[teeth] = 0.5 * normal[teeth]
    grid.point_data[arrays.BC] = bc
    grid.point_data[arrays.BC_DISPLACEMENT] = disp
    grid.point_data[arrays.BC_NORMAL] = normal
    cc = grid.cell_centers().points
    crad = np.linalg.norm(cc, axis=1)
    band = (crad > 84) & (crad < 88) & (np.abs(np.arccos(cc[:, 2] / crad) - 0.55 * np.pi) < 0.06 * np.pi)
    grid.cell_data[arrays.TISSUE] = np.where(band, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    tang = np.cross([0.0, 0.0, 1.0], cc)
    grid.cell_data[arrays.FIBER] = tang / np.linalg.norm(tang, axis=1)[:, None]
    import pvcmf

    return pvcmf.filters.assign_materials(grid, table="paper000")


def measure(size, repeat, kw):
    # the sweep's update_materials(refactor=...): see --sweep
    REFACTOR = os.environ.get("PVCMF_BENCH_SWEEP", "refactor") == "refactor"
    """Timings of one solver configuration in this process (printed as one JSON line)."""
    import pvcmf

    grid = shell_mesh(size)
    pvcmf.mtm.Solver(grid, **kw).solve()  # warm-up: imports, MKL start
    walls = []
    for _ in range(repeat):
        t = time.perf_counter()
        solver = pvcmf.mtm.Solver(grid, **kw)
        solver.solve()
        walls.append(time.perf_counter() - t)
    nus = np.linspace(0.0, 0.495, 20)
    t = time.perf_counter()
    solver = pvcmf.mtm.Solver(grid, nu=nus[0], **kw)
    solver.solve()
    for nu in nus[1:]:
        solver.update_materials(nu=nu, refactor=REFACTOR)
        solver.solve()
    sweep = time.perf_counter() - t
    info = solver.info
    return {"cells": int(grid.n_cells), "unknowns": int(solver.F.size),
            "assemble_solve": statistics.median(walls), "sweep": sweep,
            "backend": str(info.get("backend")), "precision": str(info.get("precision", "")),
            "threads": str(info.get("threads", ""))}


def run_child(tree, size, repeat, kw):
    env = dict(os.environ, PYTHONPATH=tree)
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--sizes", str(size),
           "--repeat", str(repeat), "--kw", json.dumps(kw)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True, cwd=tree)
    return json.loads(out.stdout.strip().splitlines()[-1])


def old_tree(ref):
    """A checkout of ``ref`` (git worktree, reused when present) under the temporary folder."""
    sha = subprocess.run(["git", "rev-parse", ref], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    path = os.path.join(tempfile.gettempdir(), f"pvcmf-mtm-{sha[:12]}")
    if not os.path.isdir(path):
        subprocess.run(["git", "worktree", "add", "--detach", path, sha], cwd=ROOT, check=True,
                       capture_output=True)
    return path, sha


def compare(runs, rounds, size, repeat):
    """Alternate the (label, tree, kw) runs for ``rounds`` rounds; medians and per-round ratios
    to the first run."""
    got = {label: [] for label, _, _ in runs}
    for _ in range(rounds):
        for label, tree, kw in runs:
            got[label].append(run_child(tree, size, repeat, kw))
    base = runs[0][0]
    rows = []
    for label, _, kw in runs:
        r = got[label]
        row = {"label": label, "kw": kw, "last": r[-1]}
        for key in ("assemble_solve", "sweep"):
            row[key] = statistics.median(x[key] for x in r)
            row[key + "_ratio"] = statistics.median(
                x[key] / y[key] for x, y in zip(r, got[base]))
        rows.append(row)
    return rows


def table(rows, base):
    lines = [f"| solver | backend, precision, threads | assemble+solve (ms) | ratio to "
             f"{base} | 20-value sweep (ms) | ratio to {base} |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        last = r["last"]
        lines.append(
            f"| {r['label']} | {last['backend']}, {last['precision'] or 'double'}, "
            f"{last['threads'] or '-'} | {1000 * r['assemble_solve']:.0f} | "
            f"{r['assemble_solve_ratio']:.2f} | {1000 * r['sweep']:.0f} | {r['sweep_ratio']:.2f} |")
    return "\n".join(lines)


def machine():
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, {platform.system()}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[30_000])
    p.add_argument("--against", metavar="REF", help="also run the solver of git revision REF "
                   "(labelled 'before' in the tables)")
    p.add_argument("--variants", nargs="*", default=None, choices=sorted(VARIANTS),
                   help="variants of this tree to run (default: all; with --against: default)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--write", metavar="PAGE", help="write the tables to this Markdown page")
    p.add_argument("--sweep", choices=("refactor", "reuse"), default="refactor",
                   help="the sweep's update_materials: a numeric refactorisation at every value "
                        "(refactor=True) or the factor kept where it still converges "
                        "(refactor=False, what pvcmf.sweep does)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--kw", default="{}", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    os.environ["PVCMF_BENCH_SWEEP"] = args.sweep  # the children read it
    if args.child:
        print(json.dumps(measure(args.sizes[0], args.repeat, json.loads(args.kw))))
        return 0
    names = args.variants if args.variants is not None else (
        ["default"] if args.against else list(VARIANTS))
    runs = []
    if args.against:
        tree, sha = old_tree(args.against)
        runs.append(("before default", tree, {}))
    runs += [(f"this tree {name}" if args.against else name, ROOT, VARIANTS[name])
             for name in names]
    words = list(argv if argv is not None else sys.argv[1:])
    if args.against:  # the page names the reference REF, not by its revision
        words = ["REF" if w == args.against else w.replace(args.against, "REF") for w in words]
    command = "python benchmarks/mtm.py " + shlex.join(words)
    out = []
    for size in args.sizes:
        rows = compare(runs, args.rounds, size, args.repeat)
        cells = rows[0]["last"]["cells"]
        text = (f"{cells} tetrahedra, {rows[0]['last']['unknowns']} unknowns; wall times, "
                f"median of {args.rounds} alternating rounds (assemble+solve: median of "
                f"{args.repeat} per round); ratios per round, then the median. Wall times "
                f"depend on what else runs on the machine; the ratios compare runs that "
                f"alternate in one run of the script.\n\n"
                + table(rows, runs[0][0]))
        print(text, flush=True)
        out.append(text)
    if args.write:
        ref = f"{REF_NOTE}\n\n" if args.against else ""
        page = ("# MTM solver speed\n\nGenerated by `benchmarks/mtm.py`.\n\n"
                f"Command: `{command}`\n\n{ref}Machine: {machine()}\n\n" + "\n\n".join(out)
                + "\n")
        os.makedirs(os.path.dirname(os.path.abspath(args.write)), exist_ok=True)
        with open(args.write, "w") as f:
            f.write(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
