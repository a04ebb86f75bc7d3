"""Speed of pvcmf's Mass Tensor Model: assembly, factorisation, solve, peak memory.

Not run by CI. Run ``python benchmarks/mtm.py`` (``--sizes 30000 150000 1000000``,
``--skip-skfem``, ``--skip-relaxation``). Prints whole numbers (milliseconds, MB) and ratios
measured in the same run: scikit-fem's assemble+solve relative to pvcmf's (paired runs,
alternating, ratio per pair; median of 3 below 100k tetrahedra), the paper's relaxation
solver, and a 20-value Poisson sweep with one :class:`pvcmf.mtm.Solver` (built with the first
value, 19 updates, variants interleaved, median of 3: the default numeric refactorisation
(CHOLMOD first, then the automatic switch to mixed-precision PARDISO), CHOLMOD kept, PARDISO
in double precision, and the factor reused as CG preconditioner; each line says the backend,
precision and factorisation threads of its last value). ``--threads`` adds paired 1- vs
2-thread factorisation times (PARDISO double and single, CHOLMOD); ``--only-threads`` skips
everything but those and the sweep (e.g. ``--sizes 30000 50000 150000 --threads
--only-threads``); ``--reaction`` (with one size) shows the PARDISO thread policy
reacting to a CPU-burning process started during a sweep loop. The load average is printed for each size and after the scikit-fem, thread
and sweep lines: on the shared 2-core machine compare ratios from one run, not absolute times
across runs.

The mesh is a synthetic head-like shell (a thick spherical cap, 12 mm soft tissue, jittered
structured grid split into tetrahedra) with a muscle band (paper 000 Table I materials, fibres
along the band): the inner surface is fixed at the back, joint (moved 5 mm forward) at the
chin, and sliding along its normal over the teeth; the outer (skin) surface is free.
"""

from __future__ import annotations

import argparse
import resource
import os
import statistics
import subprocess
import sys
import time

import numpy as np
import pyvista as pv

import pvcmf
from pvcmf import arrays


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
    return pvcmf.filters.assign_materials(grid, table="paper000")


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def timed(fn, repeat=1):
    """Median wall time, median CPU time (all threads) and the last result."""
    walls, cpus, out = [], [], None
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus), out


def skfem_assemble_solve(grid):
    """Independent FE: scikit-fem P1 elasticity with the same per-cell 6x6 matrices."""
    import skfem
    from skfem.helpers import sym_grad

    pts, cells = pvcmf.mtm.tetrahedra(grid)
    mesh = skfem.MeshTet(pts.T.copy(), cells.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVectorH1(skfem.ElementTetP1()), intorder=0)
    C = pvcmf.mtm.constitutive_matrix(grid[arrays.E_FIBER], grid[arrays.E_CROSS],
                                      grid[arrays.NU], grid[arrays.FIBER])
    nqp = basis.X.shape[1]
    Cw = {f"c{p}{q}": np.repeat(C[:, p, q][:, None], nqp, axis=1) for p in range(6) for q in range(6)}

    def voigt(e):
        return [e[0, 0], e[1, 1], e[2, 2], 2 * e[1, 2], 2 * e[0, 2], 2 * e[0, 1]]

    @skfem.BilinearForm
    def form(u, v, w):
        eu, ev = voigt(sym_grad(u)), voigt(sym_grad(v))
        return sum(w[f"c{p}{q}"] * eu[q] * ev[p] for p in range(6) for q in range(6))

    K = skfem.asm(form, basis, **Cw)
    return K, basis


def bench(n, args):
    t = time.perf_counter()
    grid = shell_mesh(n)
    print(f"\n== {grid.n_cells} tetrahedra, {grid.n_points} points (mesh built in "
          f"{time.perf_counter() - t:.1f} s); load average {os.getloadavg()[0]:.1f}", flush=True)
    if args.reaction:
        reaction(grid)
        return
    if args.only_threads:
        if args.threads:
            threads(grid)
        if n == args.sweep_size:
            sweep(grid)
        return
    rss_mesh = peak_rss_mb()
    rep = 5 if n < 100_000 else 3 if n < 500_000 else 1
    method = "direct" if grid.n_points <= pvcmf.mtm.AUTO_DIRECT_MAX_POINTS else "cg"
    w_total, c_total, solver = timed(lambda: _setup_and_solve(grid, method=method, tol=1e-8
                                                              if method == "cg" else 1e-10), rep)
    u = solver.solve()
    first_backend, first_analysis = solver.backend_name, solver.timings.get("analysis", np.nan)
    asm = solver.assembler
    ef, ec, nu, a = solver.materials
    w_asm, c_asm, _ = timed(lambda: asm.matrix(ef, ec, nu, a), rep)
    w_upd, c_upd, _ = timed(lambda: solver.update_materials(nu=solver.materials[2]), rep)
    w_sol, c_sol, _ = timed(solver.solve, rep)
    ms = lambda x: f"{1000 * x:7.0f} ms"  # noqa: E731
    rss_solve = peak_rss_mb()
    print(f"unknowns {solver.F.size}, method {method} ({first_backend or 'amg'}); "
          f"wall (cpu, all threads), median of {rep}")
    print(f"peak RSS {rss_solve:.0f} MB after the solves ({rss_mesh:.0f} MB after building the "
          f"mesh; the solver's share {rss_solve - rss_mesh:.0f} MB)")
    print(f"assembled + solved (from grid)   {ms(w_total)} ({ms(c_total)})   residual "
          f"{solver.info['residual']:.1e}, est. error {solver.info['error_estimate']:.1e}")
    print(f"  assembly (BSR, new materials)  {ms(w_asm)} ({ms(c_asm)})")
    if method == "direct":
        print(f"  symbolic analysis (first only) {ms(first_analysis)}")
    print(f"  re-assembly + numeric factor / AMG setup {ms(w_upd)} ({ms(c_upd)})"
          + (f" [{solver.backend_name}, {solver.info.get('precision', 'double')} precision, "
             f"{solver.info.get('threads', '-')} thread(s): a refactoring update switches a "
             f"CHOLMOD solver to PARDISO]" if method == "direct" else ""))
    if method == "direct":
        print(f"  solve (+1 refinement step)     {ms(w_sol)} ({ms(c_sol)})", flush=True)
    else:
        print(f"  cg solve ({solver.info['iterations']} iterations to "
              f"{solver.info['residual']:.0e})   {ms(w_sol)} ({ms(c_sol)})", flush=True)
    total = w_total
    if method == "direct" and "pardiso" in pvcmf.mtm.direct_backends() \
            and first_backend != "pardiso":
        # one solve from the grid: the default backend against PARDISO (mixed, double),
        # interleaved, median of 5 paired ratios
        pairs = {"mixed": [], "double": []}
        for _ in range(5):
            w_def, _, _ = timed(lambda: _setup_and_solve(grid), 1)
            for prec in pairs:
                w_p, _, sp_ = timed(lambda: _setup_and_solve(grid, backend="pardiso",
                                                            precision=prec), 1)
                pairs[prec].append((w_p, w_def, sp_.info.get("threads", "-")))
        for prec, v in pairs.items():
            print(f"  the same from the grid with PARDISO ({prec} precision, {v[-1][2]} "
                  f"thread(s)): {ms(statistics.median(x[0] for x in v))}, "
                  f"{statistics.median(x[0] / x[1] for x in v):.2f}x the {first_backend} time "
                  f"(median of 5 paired runs); load {os.getloadavg()[0]:.1f}", flush=True)
    if not args.skip_skfem and n <= args.skfem_max:
        from skfem import condense
        from skfem import solve as sksolve

        # scikit-fem has no sliding frames: compare on the variant with sliding -> joint
        g2 = grid.copy()
        bc = np.array(g2[arrays.BC])
        bc[bc == arrays.BC_SLIDING] = arrays.BC_JOINT
        g2[arrays.BC] = bc
        # like with like: the same mesh, materials and constraints, both direct to round-off,
        # scikit-fem with its own assembly and its natural solver (skfem.solve = spsolve);
        # the two sides alternate and the ratio is taken per repeat (median of 3 below 100k)
        rk = 3 if n < 100_000 else 1
        ratios, cpu_ratios, sk_times, our_times = [], [], [], []
        for _ in range(rk):
            t_skasm, c_skasm, (K, basis) = timed(lambda: skfem_assemble_solve(g2), 1)
            dofs = basis.nodal_dofs
            D = dofs[:, bc != arrays.BC_FREE].ravel()
            x = np.zeros(basis.N)
            x[dofs.T.ravel()] = np.asarray(g2[arrays.BC_DISPLACEMENT]).ravel()
            t_sksolve, c_sksolve, xs = timed(
                lambda: sksolve(*condense(K, np.zeros(basis.N), x=x, D=D)), 1)
            t_ours, c_ours, s2 = timed(lambda: _setup_and_solve(g2), 1)
            ratios.append((t_skasm + t_sksolve) / t_ours)
            cpu_ratios.append((c_skasm + c_sksolve) / c_ours)
            sk_times.append((t_skasm, t_sksolve))
            our_times.append(t_ours)
        ref = xs[dofs.T.ravel()].reshape(-1, 3)
        err = np.abs(s2.solve() - ref).max() / np.abs(ref).max()
        t_skasm, t_sksolve = (statistics.median(v) for v in zip(*sk_times))
        print(f"scikit-fem assemble {ms(t_skasm)} + solve {ms(t_sksolve)}; pvcmf "
              f"{ms(statistics.median(our_times))} -> pvcmf is {statistics.median(ratios):.1f}x "
              f"faster (median of {rk} paired runs: {', '.join(f'{r:.1f}' for r in ratios)}; CPU "
              f"time {statistics.median(cpu_ratios):.1f}x); max rel. difference {err:.1e}; load "
              f"{os.getloadavg()[0]:.1f}", flush=True)
    if not args.skip_cg and method == "direct":
        w_cg, _, cs = timed(lambda: _setup_and_solve(grid, method="cg", tol=1e-8), 1)
        uc = cs.solve()
        print(f"cg + AMG to 1e-8 {ms(w_cg)} ({cs.info['iterations']} iterations) -> "
              f"{w_cg / total:.1f}x the direct time; max rel. diff "
              f"{np.abs(uc - u).max() / np.abs(u).max():.1e}", flush=True)
    if not args.skip_relaxation:
        sweeps = args.relax_sweeps if n <= 40_000 else \
            max(args.relax_sweeps // 10, 100) if n <= 200_000 else 100
        t = time.perf_counter()
        rs = pvcmf.mtm.Solver(grid, method="relaxation", tol=1e-8, maxiter=sweeps)
        try:
            ur = rs.solve()
            msg = f"converged to 1e-8 in {rs.info['iterations']} sweeps"
        except pvcmf.mtm.ConvergenceError as err:
            msg = f"NOT converged: {err}"
            ur = None
        t_rel = time.perf_counter() - t
        bound = "" if ur is not None else "at least "  # stopped early: a lower bound
        print(f"relaxation {ms(t_rel)} ({msg}) -> {bound}{t_rel / total:.1f}x the {method} time")
        if ur is not None:
            print(f"  max |u_relax - u_direct| / max|u| = {np.abs(ur - u).max() / np.abs(u).max():.1e}")
    print(f"process peak RSS (everything above) {peak_rss_mb():.0f} MB", flush=True)
    if args.threads:
        threads(grid)
    if n == args.sweep_size:
        sweep(grid)


def _setup_and_solve(grid, **kw):
    solver = pvcmf.mtm.Solver(grid, **kw)
    solver.solve()
    return solver


def sweep(grid):
    """20 Poisson ratios, one Solver: built with the first value, updated for the other 19.

    The variants alternate (one repeat of each, three rounds) and the medians are compared:
    the default (CHOLMOD for the first value, then the automatic switch to PARDISO with a
    mixed-precision factor at the first refactoring update), CHOLMOD kept, PARDISO with a
    double factor, and the factor reused as a CG preconditioner (``refactor=False``).
    """
    nus = np.linspace(0.0, 0.495, 20)
    variants = [("default: numeric refactorisation each value (CHOLMOD first, then PARDISO "
                 "mixed precision)", {}, True),
                ("CHOLMOD kept (backend='cholmod'), numeric refactorisation each value",
                 {"backend": "cholmod"}, True),
                ("PARDISO double precision (backend='pardiso', precision='double')",
                 {"backend": "pardiso", "precision": "double"}, True),
                ("factor reused as CG preconditioner (refactor=False)", {}, False)]
    names = pvcmf.mtm.direct_backends()
    variants = [v for v in variants if v[1].get("backend", names[0]) in names]
    walls = {how: [] for how, _, _ in variants}
    cpus = {how: [] for how, _, _ in variants}
    parts = {how: {} for how, _, _ in variants}
    for _ in range(3):
        for how, kw, refactor in variants:
            part = parts[how]
            t0, c0 = time.perf_counter(), time.process_time()
            t = time.perf_counter()
            solver = pvcmf.mtm.Solver(grid, nu=nus[0], **kw)
            solver.solve()
            part.setdefault("prepare", []).append(time.perf_counter() - t)
            for nu in nus[1:]:
                t = time.perf_counter()
                solver.update_materials(nu=nu, refactor=refactor)
                part.setdefault("update", []).append(time.perf_counter() - t)
                part.setdefault("assembly", []).append(solver.timings["assembly"])
                t = time.perf_counter()
                solver.solve()
                part.setdefault("solve", []).append(time.perf_counter() - t)
                part.setdefault("iterations", []).append(solver.info["iterations"])
            walls[how].append(time.perf_counter() - t0)
            cpus[how].append(time.process_time() - c0)
            part["grouped"] = getattr(solver, "_groups", None) is not None
            part["backend"] = solver.backend_name
            part["precision"] = solver.info.get("precision", "double")
            part["threads"] = solver.info.get("threads", "-")
    first = statistics.median(walls[variants[0][0]])
    for how, _, _ in variants:
        part = parts[how]
        med = {k: 1000 * statistics.median(part[k]) for k in ("prepare", "update", "assembly", "solve")}
        w = statistics.median(walls[how])
        print(f"20-value Poisson sweep (nu 0..0.495, one Solver) at {grid.n_cells} tets, {how}: "
              f"{1000 * w:.0f} ms wall ({1000 * statistics.median(cpus[how]):.0f} ms cpu), "
              f"median of 3 interleaved ({', '.join(f'{1000 * x:.0f}' for x in walls[how])}); "
              f"{w / first:.2f}x the default; last value: backend {part['backend']}, precision "
              f"{part['precision']}, {part['threads']} factor thread(s); per value: update "
              f"{med['update']:.0f} ms (re-assembly {med['assembly']:.1f} ms, grouped materials "
              f"{part['grouped']}), solve {med['solve']:.0f} ms ({statistics.median(part['iterations']):.0f} "
              f"refinement/CG steps); first value (structure, analysis, factor, solve) "
              f"{med['prepare']:.0f} ms; load {os.getloadavg()[0]:.1f}", flush=True)


def reaction(grid, start=6.0, burn=14.0, stop=30.0):
    """The PARDISO thread policy reacting to another job: a sweep looping over its 20 values
    for ``stop`` seconds, a CPU-burning process started after ``start`` seconds for ``burn``;
    prints, per value, the time, the planned threads and the other processes' busy cores."""
    from pvcmf.mtm import solvers as S

    if "pardiso" not in pvcmf.mtm.direct_backends():
        print("reaction skipped: needs pypardiso")
        return
    s = pvcmf.mtm.Solver(grid, nu=0.0, backend="pardiso")
    s.solve()
    t0, burner, last = time.perf_counter(), None, None
    for nu in np.tile(np.linspace(0.0, 0.495, 20), 1000):
        now = time.perf_counter() - t0
        if now > stop:
            break
        if burner is None and now > start:
            burner = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\n"
                                       f"while time.time() - t < {burn}: pass"])
            print(f"  {now:5.1f} s: CPU burner started for {burn:.0f} s")
        t = time.perf_counter()
        s.update_materials(nu=nu)
        s.solve()
        row = (s._backend.threads, S._STAT["load"])
        if row[0] != last or int(10 * now) % 20 == 0:
            print(f"  {now:5.1f} s: {1000 * (time.perf_counter() - t):4.0f} ms per value, "
                  f"{row[0]} thread(s), other processes' busy cores "
                  f"{-1 if row[1] is None else row[1]:.2f}", flush=True)
        last = row[0]
    if burner is not None:
        burner.wait()


def threads(grid, repeat=7):
    """Numeric factorisation of one matrix with 1 and 2 threads, interleaved, same process:
    PARDISO double and single precision (own analysis per thread count: MKL needs the same
    count in every phase) and CHOLMOD (OpenBLAS threads through threadpoolctl)."""
    from threadpoolctl import threadpool_limits

    from pvcmf.mtm import solvers as S

    if not {"cholmod", "pardiso"} <= set(pvcmf.mtm.direct_backends()):
        print("thread comparison skipped: needs scikit-sparse (CHOLMOD) and pypardiso")
        return
    s = pvcmf.mtm.Solver(grid, nu=0.3, backend="cholmod", ordering="metis")
    s.solve()
    U = s.K_ff.upper
    policy = S._pardiso_threads
    found = {}
    try:
        handles = {}
        for prec in ("double", "single"):
            for th in (1, 2):
                S._pardiso_threads = lambda n, th=th, **kw: th
                handles[prec, th] = S._Pardiso(U, prec, natural=True)
        for _ in range(repeat):
            for (prec, th), h in handles.items():
                S._pardiso_threads = lambda n, th=th, **kw: th
                t, c = time.perf_counter(), time.process_time()
                h.factor(U)
                found.setdefault(f"PARDISO {prec} {th} thread(s)", []).append(
                    (time.perf_counter() - t, time.process_time() - c))
            for th in (1, 2):
                with threadpool_limits(th, user_api="blas"):
                    t, c = time.perf_counter(), time.process_time()
                    s._backend.factor(s.K_ff.lower)
                    found.setdefault(f"CHOLMOD {th} thread(s)", []).append(
                        (time.perf_counter() - t, time.process_time() - c))
    finally:
        S._pardiso_threads = policy
    print(f"numeric factorisation at {grid.n_cells} tets ({U.shape[0]} unknowns, METIS node "
          f"order), median of {repeat} interleaved, wall (cpu):")
    for k, v in found.items():
        w, c = (statistics.median(x) for x in zip(*v))
        print(f"  {k:28s} {1000 * w:7.1f} ms ({1000 * c:7.1f} ms)")
    for name in ("PARDISO double", "PARDISO single", "CHOLMOD"):
        one, two = found[f"{name} 1 thread(s)"], found[f"{name} 2 thread(s)"]
        ratio = statistics.median(b[0] / a[0] for a, b in zip(one, two))
        print(f"  {name}: 2 threads / 1 thread wall {ratio:.2f} (median of paired ratios)")
    others = S._others_load()
    print(f"  policy here now: {S._pardiso_threads(U.shape[0])} thread(s) (other processes' "
          f"busy cores {others if others is None else round(others, 2)}); load "
          f"{os.getloadavg()[0]:.2f} on {S._cores()} cores", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sizes", type=int, nargs="+", default=[30_000, 50_000, 150_000, 1_000_000])
    p.add_argument("--skip-skfem", action="store_true")
    p.add_argument("--skfem-max", type=int, default=160_000)
    p.add_argument("--skip-relaxation", action="store_true")
    p.add_argument("--skip-cg", action="store_true")
    p.add_argument("--relax-sweeps", type=int, default=20000)
    p.add_argument("--sweep-size", type=int, default=30_000)
    p.add_argument("--threads", action="store_true",
                   help="also time 1 vs 2 factorisation threads (PARDISO, CHOLMOD)")
    p.add_argument("--reaction", action="store_true",
                   help="only the thread policy's reaction to a CPU burner (a 30 s sweep loop)")
    p.add_argument("--only-threads", action="store_true",
                   help="only the thread comparison (with --threads) and the sweep")
    p.add_argument("--one", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.one:  # one size in this process (its peak RSS is that size's)
        bench(args.sizes[0], args)
        return 0
    print(f"pvcmf MTM benchmark; direct backends here: {pvcmf.mtm.direct_backends()}; "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)
    flags = [f"--skfem-max={args.skfem_max}", f"--relax-sweeps={args.relax_sweeps}",
             f"--sweep-size={args.sweep_size}"]
    flags += [f"--{k.replace('_', '-')}" for k in ("skip_skfem", "skip_relaxation", "skip_cg",
                                                   "threads", "only_threads", "reaction")
              if getattr(args, k)]
    for n in args.sizes:
        subprocess.run([sys.executable, __file__, "--one", "--sizes", str(n), *flags], check=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
