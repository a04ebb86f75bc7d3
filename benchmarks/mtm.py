"""Speed of pvcmf's Mass Tensor Model: assembly, factorisation, solve, peak memory.

Not run by CI. Run ``python benchmarks/mtm.py`` (``--sizes 30000 150000 1000000``,
``--skip-skfem``, ``--skip-relaxation``). Prints whole numbers (milliseconds, MB) and ratios
measured in the same run: scikit-fem's assemble+solve and the paper's relaxation solver
relative to pvcmf's direct solve, and a 20-value Poisson sweep with :class:`pvcmf.mtm.Solver`.

The mesh is a synthetic head-like shell (a thick spherical cap, 12 mm soft tissue, jittered
structured grid split into tetrahedra) with a muscle band (paper 000 Table I materials, fibres
along the band): the inner surface is fixed at the back, joint (moved 5 mm forward) at the
chin, and sliding along its normal over the teeth; the outer (skin) surface is free.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
import tracemalloc

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
    ts, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts), out


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
    grid = shell_mesh(n)
    print(f"\n== {grid.n_cells} tetrahedra, {grid.n_points} points", flush=True)
    tracemalloc.start()
    t_setup, solver = timed(lambda: pvcmf.mtm.Solver(grid))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    t_solve, u = timed(solver.solve, 3)
    asm = solver.assembler
    ef, ec, nu, a = solver.materials
    t_asm, _ = timed(lambda: asm.matrix(ef, ec, nu, a), 3)
    t_upd, _ = timed(lambda: solver.update_materials(nu=solver.materials[2]), 3)
    print(f"unknowns {solver.F.size}, backend {solver.backend_name}")
    print(f"assembly (BSR, materials only)   {1000 * t_asm:8.0f} ms")
    print(f"first Solver (geometry+pattern+symbolic+numeric) {1000 * t_setup:8.0f} ms")
    print(f"  of which numeric factor        {1000 * solver.timings['factor']:8.0f} ms")
    print(f"re-assembly + numeric refactor   {1000 * t_upd:8.0f} ms")
    print(f"solve (2 triangular solves + refinement) {1000 * t_solve:8.0f} ms")
    total = t_setup + t_solve
    print(f"assembled + solved               {1000 * total:8.0f} ms   residual "
          f"{solver.info['residual']:.1e}, est. error {solver.info['error_estimate']:.1e}")
    print(f"python heap peak during setup    {peak / 2**20:8.0f} MB; process peak RSS "
          f"{peak_rss_mb():.0f} MB")
    if not args.skip_skfem and n <= args.skfem_max:
        import scipy.sparse.linalg as spla
        from skfem import condense

        t = time.perf_counter()
        K, basis = skfem_assemble_solve(grid)
        t_skasm = time.perf_counter() - t
        cons = solver.constraints
        # scikit-fem cannot express sliding frames: compare on the joint/fixed-only variant
        g2 = grid.copy()
        bc = np.array(g2[arrays.BC])
        bc[bc == arrays.BC_SLIDING] = arrays.BC_JOINT
        d2 = np.array(g2[arrays.BC_DISPLACEMENT])
        g2[arrays.BC] = bc
        dofs = basis.nodal_dofs  # (3, n)
        D = dofs[:, bc != arrays.BC_FREE].T.ravel()
        x = np.zeros(basis.N)
        x[dofs.T.ravel()] = d2.ravel() * (bc != arrays.BC_FIXED)[:, None].repeat(3, 1).ravel()
        t = time.perf_counter()
        usk = condense(K, np.zeros(basis.N), x=x, D=D)
        from skfem import solve as sksolve

        xs = sksolve(*usk)
        t_sksolve = time.perf_counter() - t
        t = time.perf_counter()
        s2 = pvcmf.mtm.Solver(g2)
        u2 = s2.solve()
        t_ours = time.perf_counter() - t
        ref = xs[dofs.T.ravel()].reshape(-1, 3)
        err = np.abs(u2 - ref).max() / np.abs(ref).max()
        print(f"scikit-fem assemble {1000 * t_skasm:.0f} ms + solve {1000 * t_sksolve:.0f} ms; "
              f"pvcmf {1000 * t_ours:.0f} ms -> ratio {(t_skasm + t_sksolve) / t_ours:.1f}x; "
              f"max rel. difference {err:.1e}")
    if not args.skip_relaxation:
        t = time.perf_counter()
        rs = pvcmf.mtm.Solver(grid, method="relaxation", tol=1e-8, maxiter=args.relax_sweeps)
        try:
            ur = rs.solve()
            msg = f"converged to 1e-8 in {rs.info['iterations']} sweeps"
        except pvcmf.mtm.ConvergenceError as err:
            msg = f"NOT converged: {err}"
            ur = None
        t_rel = time.perf_counter() - t
        print(f"relaxation {1000 * t_rel:.0f} ms ({msg}) -> ratio {t_rel / total:.0f}x direct")
        if ur is not None:
            print(f"  max |u_relax - u_direct| / max|u| = "
                  f"{np.abs(ur - u).max() / np.abs(u).max():.1e}")
    if not args.skip_cg:
        t = time.perf_counter()
        cs = pvcmf.mtm.Solver(grid, method="cg", tol=1e-8)
        uc = cs.solve()
        t_cg = time.perf_counter() - t
        print(f"cg+amg {1000 * t_cg:.0f} ms ({cs.info['iterations']} iterations) -> "
              f"{t_cg / total:.1f}x direct; max diff {np.abs(uc - u).max() / np.abs(u).max():.1e}")
    return grid, solver


def sweep(grid):
    nus = np.linspace(0.0, 0.495, 20)
    t = time.perf_counter()
    solver = pvcmf.mtm.Solver(grid)
    us = []
    for nu in nus:
        solver.update_materials(nu=nu)
        us.append(solver.solve())
    dt = time.perf_counter() - t
    print(f"\n20-value Poisson sweep (nu 0..0.495) incl. first setup: {1000 * dt:.0f} ms "
          f"({grid.n_cells} tets)")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sizes", type=int, nargs="+", default=[30_000, 150_000, 1_000_000])
    p.add_argument("--skip-skfem", action="store_true")
    p.add_argument("--skfem-max", type=int, default=200_000)
    p.add_argument("--skip-relaxation", action="store_true")
    p.add_argument("--skip-cg", action="store_true")
    p.add_argument("--relax-sweeps", type=int, default=20000)
    p.add_argument("--sweep", action="store_true", help="only the Poisson sweep at 30k")
    args = p.parse_args(argv)
    print(f"pvcmf MTM benchmark; direct backends here: {pvcmf.mtm.direct_backends()}")
    if args.sweep:
        sweep(shell_mesh(30_000))
        return
    for n in args.sizes:
        grid, _ = bench(n, args)
        if n == 30_000:
            sweep(grid)


if __name__ == "__main__":
    sys.exit(main())
