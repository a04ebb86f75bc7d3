"""Registration and distance benchmarks: pvcmf against VTK on the same data.

Run: ``python benchmarks/registration_distance.py [--quick] [--repeat N]`` (not run by CI).
Prints whole numbers (ms, micrometres, millidegrees) as medians of ``--repeat`` runs,
ratios measured in the same run.

1. ICP on a 50k-point face-like skin against a cropped (40k points), noisy (0.2 mm) copy
   moved by a known pose: pvcmf's point-to-plane ``register`` (nearest-vertex pairs, the
   default; and closest points on the triangles at the end, libigl) against VTK's point-to-point
   ``vtkIterativeClosestPointTransform`` (PyVista ``align``).
2. Signed distance of 200k points (a finer marching-cubes skin, smoothly deformed, errors
   up to ~2.5 mm) to a 200k-triangle marching-cubes skin: ``distance_to`` through libigl
   and through VTK's ``vtkImplicitPolyDataDistance``, and the nearest vertex (scipy
   cKDTree); errors against VTK's cell locator (PyVista ``find_closest_cell``) on 5000
   points.
3. The virtual post-operative CT path on patient 1 (``--spacing``, default 2 mm): time of
   ``postop_ct`` and ``validate_from_ct`` and the pose error with a random pose.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import pvcmf  # noqa: F401  (registers the cmf accessor)
from pvcmf import arrays
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


def timed(fn, repeat):
    """(median seconds, last result) of ``repeat`` calls."""
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def pose_error(matrix, truth, centre):
    """(shift of ``centre`` in mm, rotation error in degrees) of ``matrix @ truth``."""
    e = matrix @ truth
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(e[:3, :3]).as_rotvec()))
    return float(np.linalg.norm(e[:3, :3] @ centre + e[:3, 3] - centre)), float(angle)




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
          f"(cropped, 0.2 mm noise), pose (3, -2, 4) deg, (4, -3, 2) mm")
    rows = []
    for name, kw in (("pvcmf point-to-plane (default)", {}),
                     ("pvcmf point-to-plane, surface end", {"closest": "surface"})):
        t, out = timed(lambda kw=kw: source.cmf.register(target, **kw), repeat)
        m, rms, ok = registration_result(out)
        rows.append((name, t, *pose_error(m, truth, centre), rms, ok))
    for iters in (50, 200):
        t, (_, m) = timed(lambda iters=iters: source.align(
            target, max_iterations=iters, max_mean_distance=1e-6, return_matrix=True), repeat)
        rows.append((f"VTK point-to-point ({iters} it)", t, *pose_error(m, truth, centre),
                     float("nan"), True))
    print(f"{'method':38s} {'ms':>7s} {'shift um':>9s} {'rot mdeg':>9s} {'RMS um':>7s}")
    for name, t, shift, ang, rms, ok in rows:
        rms_s = "-" if np.isnan(rms) else f"{rms * 1e3:7.0f}"
        print(f"{name:38s} {t * 1e3:7.0f} {shift * 1e3:9.0f} {ang * 1e3:9.0f} {rms_s:>7s}"
              + ("" if ok else "  NOT CONVERGED"))
    mine, vtk_ = rows[0], rows[3]
    print(f"ratio VTK(200 it)/pvcmf: time {vtk_[1] / mine[1]:.1f}x, shift error "
          f"{vtk_[2] / max(mine[2], 1e-9):.0f}x, rotation error {vtk_[3] / max(mine[3], 1e-9):.0f}x")


def bench_distance(repeat, n_tri):
    spacing = np.sqrt(3.06e5 / n_tri)  # flying edges gives ~3.06e5 triangles at 1 mm
    truth = implicit_skin(spacing)
    pred = implicit_skin(spacing / np.sqrt(2), wave=2.5)  # about n_tri points
    print(f"\nsigned distance: {pred.n_points} points to {truth.n_cells} triangles")
    t_igl, out = timed(lambda: pred.cmf.distance_to(truth, method="igl"), repeat)
    d_igl = np.asarray(out[arrays.DISTANCE])
    t_vtk, out = timed(lambda: pred.cmf.distance_to(truth, method="vtk"), repeat)
    d_vtk = np.asarray(out[arrays.DISTANCE])
    t_nv, d_nv = timed(lambda: cKDTree(truth.points).query(pred.points, workers=-1)[0], repeat)
    from pvcmf.filters.distance import SurfaceDistance, _outward

    reused = {m: SurfaceDistance(_outward(truth), method=m) for m in ("igl", "vtk")}
    t_ri, _ = timed(lambda: reused["igl"](pred.points), repeat)
    t_rv, _ = timed(lambda: reused["vtk"](pred.points), repeat)
    sub = np.random.default_rng(0).choice(pred.n_points, 5000, replace=False)
    _, cp = truth.find_closest_cell(pred.points[sub], return_closest_point=True)
    ref = np.linalg.norm(pred.points[sub] - cp, axis=1)
    print(f"{'method':40s} {'ms':>7s} {'max |err| um (5k)':>18s}")
    print(f"{'pvcmf distance_to, libigl (default)':40s} {t_igl * 1e3:7.0f} "
          f"{np.abs(np.abs(d_igl[sub]) - ref).max() * 1e3:18.6f}")
    print(f"{'pvcmf distance_to, VTK implicit':40s} {t_vtk * 1e3:7.0f} "
          f"{np.abs(np.abs(d_vtk[sub]) - ref).max() * 1e3:18.6f}")
    print(f"{'nearest vertex (cKDTree, unsigned)':40s} {t_nv * 1e3:7.0f} "
          f"{np.abs(d_nv[sub] - ref).max() * 1e3:18.0f}")
    print(f"{'SurfaceDistance built once: libigl query':40s} {t_ri * 1e3:7.0f}")
    print(f"{'SurfaceDistance built once: VTK query':40s} {t_rv * 1e3:7.0f}")
    print(f"ratio libigl/VTK time {t_igl / t_vtk:.2f}x (queries only {t_ri / t_rv:.2f}x); max |libigl - VTK| over all points "
          f"{np.abs(d_igl - d_vtk).max() * 1e3:.6f} um; sign agreement "
          f"{100 * np.mean(np.sign(d_igl) == np.sign(d_vtk)):.3f} %")


def bench_postop(repeat, spacing):
    from pvcmf.plan import Plan
    from pvcmf.postop import postop_ct, random_pose, skin_from_ct, validate_from_ct

    case = pvcmf.datasets.phantom(1, spacing=spacing)
    case.plan = Plan(())
    pre = skin_from_ct(case.ct)
    pose = random_pose(1, centre=case.ct.center)
    t_ct, (ct, _) = timed(lambda: postop_ct(case, None, pose=pose, seed=1), repeat)
    t_val, (surface, table) = timed(lambda: validate_from_ct(case, ct, pre, pre_skin=pre), repeat)
    m, _, ok = registration_result(surface)
    shift, ang = pose_error(m, pose, np.asarray(pre.center))
    face = table.set_index("region").loc["face"]
    print(f"\nvirtual post-op CT, patient 1 at {spacing:g} mm ({ct.n_points} voxels), zero plan, "
          f"random pose, 18 HU noise")
    print(f"postop_ct {t_ct * 1e3:.0f} ms; validate_from_ct {t_val * 1e3:.0f} ms; pose error "
          f"{shift * 1e3:.0f} um / {ang * 1e3:.0f} mdeg (converged {ok}); |d| p50 "
          f"{face['p50'] * 1e3:.0f} um, p90 {face['p90'] * 1e3:.0f} um")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one repeat, 50k triangles")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--spacing", type=float, default=2.0)
    args = parser.parse_args()
    repeat = 1 if args.quick else args.repeat
    bench_icp(repeat)
    bench_distance(repeat, 50_000 if args.quick else 200_000)
    bench_postop(repeat, args.spacing)


if __name__ == "__main__":
    main()
