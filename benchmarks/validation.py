"""Validation benchmarks: rigid ICP and exact signed distance, pvcmf against VTK.

Run: ``python benchmarks/validation.py [--quick]`` (not run by CI). Prints whole numbers:
times in ms, errors in micrometres / millidegrees, and ratios measured in the same run.

1. ICP on a 50k-point face-like skin against a cropped (40k points), noisy (0.2 mm)
   copy moved by a known pose: pvcmf's point-to-plane ``register`` against VTK's
   point-to-point ``vtkIterativeClosestPointTransform`` (PyVista ``align``).
2. Signed distance of 200k points (a finer marching-cubes skin, smoothly deformed) to a
   200k-triangle marching-cubes skin: pvcmf's ``distance_to`` (which orients the truth and
   delegates to libigl's AABB tree when installed, else to VTK's
   ``vtkImplicitPolyDataDistance``; ``benchmarks/registration_distance.py`` times both
   engines and the ICP variants), that VTK filter alone, and the
   nearest vertex (scipy cKDTree); errors against closest points on the cells from VTK's
   cell locator (PyVista ``find_closest_cell``) on a 5000-point subset.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pyvista as pv
import vtk
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

import pvcmf  # noqa: F401  (registers the cmf accessor)
from pvcmf import arrays
from pvcmf.filters.distance import _outward
from pvcmf.filters.registration import registration_result


def face_like(u_res, v_res, phase=0.0):
    """Closed head-like surface (ellipsoid + nose + waves), mm."""
    s = pv.ParametricEllipsoid(70, 90, 110, u_res=u_res, v_res=v_res).triangulate().clean()
    s.clear_data()
    p = np.asarray(s.points, dtype=float)
    nose = 12 * np.exp(-((p[:, 0] / 15) ** 2 + ((p[:, 2] - 5) / 22) ** 2)) * (p[:, 1] > 0)
    p[:, 1] += nose + 2 * np.sin(p[:, 0] / 15 + 0.3 + phase) * np.cos(p[:, 2] / 20)
    p[:, 0] += 1.5 * np.sin(p[:, 2] / 17)
    s.points = p
    return s


def best_of(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def pose_error(matrix, truth, centre):
    """Max point error over a 100 mm ball (um-level) and rotation error (deg)."""
    e = matrix @ truth
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(e[:3, :3]).as_rotvec()))
    shift = np.linalg.norm(e[:3, :3] @ centre + e[:3, 3] - centre)
    return shift, angle


def bench_icp(repeat):
    target = face_like(290, 175)
    rng = np.random.default_rng(0)
    keep = target.points[:, 1] > np.percentile(target.points[:, 1], 20)
    scan = target.extract_points(keep, adjacent_cells=False).extract_surface(
        algorithm="dataset_surface")
    scan.points = scan.points + rng.normal(0, 0.2, scan.points.shape)
    truth = np.eye(4)
    truth[:3, :3] = Rotation.from_euler("xyz", [3.0, -2.0, 4.0], degrees=True).as_matrix()
    truth[:3, 3] = [4.0, -3.0, 2.0]
    source = scan.transform(truth, inplace=False)
    target = target.compute_normals(cell_normals=False, split_vertices=False)
    centre = np.asarray(target.center)
    print(f"ICP: target {target.n_points} points, source {source.n_points} points "
          "(cropped, 0.2 mm noise), pose (3, -2, 4) deg, (4, -3, 2) mm")
    rows = []
    t, out = best_of(lambda: source.cmf.register(target), repeat)
    m, rms, ok = registration_result(out)
    rows.append(("pvcmf point-to-plane", t, *pose_error(m, truth, centre), rms, ok))
    t, out = best_of(lambda: source.cmf.register(target, n_samples=None), repeat)
    m, rms, ok = registration_result(out)
    rows.append(("pvcmf point-to-plane, all pts", t, *pose_error(m, truth, centre), rms, ok))
    for iters in (50, 200):
        t, (_, m) = best_of(
            lambda: source.align(target, max_iterations=iters, max_mean_distance=1e-6,
                                 return_matrix=True), repeat)
        rows.append((f"VTK point-to-point ({iters} it)", t, *pose_error(m, truth, centre),
                     float("nan"), True))
    print(f"{'method':34s} {'ms':>7s} {'shift um':>9s} {'rot mdeg':>9s} {'RMS um':>7s}")
    for name, t, shift, ang, rms, ok in rows:
        rms_s = "-" if np.isnan(rms) else f"{rms * 1e3:7.0f}"
        print(f"{name:34s} {t * 1e3:7.0f} {shift * 1e3:9.0f} {ang * 1e3:9.0f} {rms_s:>7s}"
              + ("" if ok else "  NOT CONVERGED"))
    mine, vtk_ = rows[0], rows[3]
    print(f"ratio VTK(200 it)/pvcmf: time {vtk_[1] / mine[1]:.1f}x, "
          f"shift error {vtk_[2] / max(mine[2], 1e-9):.0f}x")


def implicit_skin(spacing, wave=0.0):
    """Marching-cubes skin (as from a CT) of the head-like implicit surface, mm."""
    n = np.ceil(np.array([170.0, 230.0, 250.0]) / spacing).astype(int)
    img = pv.ImageData(dimensions=n, spacing=(spacing,) * 3,
                       origin=(-85.0, -110.0, -125.0))
    p = img.points
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    nose = 12 * np.exp(-((x / 15) ** 2 + ((z - 5) / 22) ** 2)) * (y > 0)
    y0 = y - nose - 2 * np.sin(x / 15 + 0.3) * np.cos(z / 20) - wave * np.sin(z / 13) * np.cos(x / 17)
    img["f"] = np.sqrt((x / 70) ** 2 + (y0 / 90) ** 2 + (z / 110) ** 2) - 1
    return img.contour([0.0], scalars="f", method="flying_edges").clean()


def bench_distance(repeat, n_tri):
    # truth: ~n_tri triangles; prediction: a finer, deformed skin (errors up to ~2.5 mm)
    spacing = np.sqrt(3.06e5 / n_tri)  # flying edges gives ~3.06e5 triangles at 1 mm
    truth = implicit_skin(spacing)
    pred = implicit_skin(spacing / np.sqrt(2), wave=2.5)  # about n_tri points
    print(f"\nsigned distance: {pred.n_points} points to {truth.n_cells} triangles "
          f"(marching-cubes skins, smooth errors up to ~2.5 mm)")
    t_mine, out = best_of(lambda: pred.cmf.distance_to(truth), repeat)
    d_mine = out[arrays.DISTANCE]
    oriented = _outward(truth)

    def implicit():
        f = vtk.vtkImplicitPolyDataDistance()
        f.SetInput(oriented)
        res = vtk.vtkDoubleArray()
        f.FunctionValue(numpy_to_vtk(np.ascontiguousarray(pred.points, dtype=float)), res)
        return vtk_to_numpy(res)

    t_vtk, d_vtk = best_of(implicit, 1)

    def nearest():
        return cKDTree(truth.points).query(pred.points, workers=-1)[0]

    t_nv, d_nv = best_of(nearest, repeat)
    # reference on a subset: closest points on the cells by VTK's cell locator (PyVista)
    sub = np.random.default_rng(0).choice(pred.n_points, 5000, replace=False)
    _, cp = truth.find_closest_cell(pred.points[sub], return_closest_point=True)
    ref = np.linalg.norm(pred.points[sub] - cp, axis=1)
    print(f"{'method':36s} {'ms':>7s} {'max |err| um (5k subset)':>25s}")
    print(f"{'pvcmf distance_to (orient + libigl)':36s} {t_mine * 1e3:7.0f} "
          f"{np.abs(np.abs(d_mine[sub]) - ref).max() * 1e3:25.3f}")
    print(f"{'VTK vtkImplicitPolyDataDistance':36s} {t_vtk * 1e3:7.0f} "
          f"{np.abs(np.abs(d_vtk[sub]) - ref).max() * 1e3:25.3f}")
    print(f"{'nearest vertex (cKDTree, unsigned)':36s} {t_nv * 1e3:7.0f} "
          f"{np.abs(d_nv[sub] - ref).max() * 1e3:25.0f}")
    print(f"ratio pvcmf/VTK time {t_mine / t_vtk:.2f}x; pvcmf/nearest-vertex time "
          f"{t_mine / t_nv:.1f}x; sign agreement with VTK "
          f"{100 * np.mean(np.sign(d_mine) == np.sign(d_vtk)):.1f} %")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one repeat, 50k triangles")
    args = parser.parse_args()
    repeat = 1 if args.quick else 3
    bench_icp(repeat)
    bench_distance(repeat, 50_000 if args.quick else 200_000)


if __name__ == "__main__":
    main()
