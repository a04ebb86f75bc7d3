"""Why the virtual post-operative truth failed on finer meshes: the prescribed data alone.

Run: ``python benchmarks/reference_release.py [--patient 1] [--spacing 4.0] [--tets 3000]
[--order 1] [--steps 1] [--no-solve]`` (not run by CI; the solve needs the ``reference``
extra). Builds the truth's planned grid of one virtual patient (``reference._truth_grid``)
and prints, as whole numbers where it can: the fixed/joint nodes, the elements whose four
nodes are all prescribed (the Dirichlet faces of model 1 and every fixed/joint node of
model 2), those that the prescribed displacements alone invert or crush (volume ratio of
``x + s * bc_displacement`` below 0 / below 0.2 at load ``s``), the load where each
inverts, its nodes' bc codes, distances and prescribed displacements, and the nodes
``solve_reference`` releases. Then solves it with the release off (``release_below=None``:
every fixed/joint vertex prescribed, nothing released) and on (the default),
printing the load reached or the Newton iterations, wall and CPU seconds.

"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import pyvista as pv

from pvcmf import arrays, reference
from pvcmf.datasets import phantom


def volumes(x, tets):
    q = x[tets]
    return np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), q[:, 3] - q[:, 0])


def diagnose(grid):
    points = np.asarray(grid.points, dtype=np.float64)
    tets = np.asarray(grid.cells_dict[pv.CellType.TETRA], dtype=np.int64)
    bc = np.asarray(grid[arrays.BC])
    g = np.asarray(grid[arrays.BC_DISPLACEMENT], dtype=np.float64)
    constrained = np.isin(bc, (arrays.BC_FIXED, arrays.BC_JOINT))
    faces = reference._boundary_faces(grid)
    on_face = np.zeros(len(points), bool)
    on_face[faces[constrained[faces].all(axis=1)].ravel()] = True
    print(f"fixed {np.sum(bc == arrays.BC_FIXED)}, joint {np.sum(bc == arrays.BC_JOINT)}, "
          f"sliding {np.sum(bc == arrays.BC_SLIDING)} nodes; fixed/joint nodes on no "
          f"Dirichlet face (free in model 1): {np.sum(constrained & ~on_face)}")
    v0 = volumes(points, tets)
    loads = np.linspace(0, 1, 1001)[1:]
    for name, mask in (("on Dirichlet faces (model 1)", on_face),
                       ("fixed/joint (model 2)", constrained)):
        full = np.flatnonzero(mask[tets].all(axis=1))
        ratio = np.stack([volumes(points + s * g, tets[full]) / v0[full] for s in loads])
        inverted = (ratio <= 0).any(axis=0)
        first = loads[np.argmax(ratio <= 0, axis=0)]
        print(f"elements with 4 prescribed nodes, {name}: {len(full)}; inverted by the data "
              f"alone: {inverted.sum()}; crushed below 0.2: {(ratio[-1] < 0.2).sum()}")
        for k in np.argsort(np.where(inverted, first, 2.0))[: inverted.sum()]:
            nodes = tets[full[k]]
            edge = max(np.linalg.norm(points[a] - points[b]) for a in nodes for b in nodes)
            print(f"   element {full[k]}: inverts at load {first[k]:.3f}, volume ratio at full "
                  f"load {ratio[-1, k]:.2f}, bc {bc[nodes].tolist()}, |bc_displacement| "
                  f"{np.round(np.linalg.norm(g[nodes], axis=1), 1).tolist()} mm, longest edge "
                  f"{edge:.1f} mm, centre {np.round(points[nodes].mean(axis=0)).tolist()} mm")
    released = reference._released_nodes(points, tets, constrained, g, 0.2)
    print(f"released at release_below=0.2: {released.sum()} nodes, bc {bc[released].tolist()}, "
          f"at {np.round(points[released]).tolist()} mm")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patient", type=int, default=1)
    ap.add_argument("--spacing", type=float, default=4.0)
    ap.add_argument("--tets", type=int, default=3000)
    ap.add_argument("--order", type=int, default=1)
    ap.add_argument("--steps", type=int, default=1)
    ap.add_argument("--no-solve", action="store_true")
    args = ap.parse_args()

    case = phantom(patient=args.patient, spacing=args.spacing)
    _, grid = reference._truth_grid(case, args.tets, 0.5, False)
    print(f"patient {args.patient}, spacing {args.spacing} mm, {grid.n_cells} tetrahedra, "
          f"{grid.n_points} nodes, {os.cpu_count()} cores")
    diagnose(grid)
    if args.no_solve:
        return
    for release in (None, 0.2):
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            out = reference.solve_reference(grid, order=args.order, steps=args.steps,
                                            release_below=release, threads=False)
            dofs, its, facts, _ = out.field_data["reference_solver"]
            result = (f"converged: {int(dofs)} dofs, {int(its)} Newton iterations, "
                      f"{int(facts)} factorisations")
        except RuntimeError as err:
            result = f"failed: {err}"
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        print(f"order {args.order}, release_below={release}: {result}; wall {wall:.1f} s, "
              f"CPU {cpu:.1f} s")


if __name__ == "__main__":
    main()
