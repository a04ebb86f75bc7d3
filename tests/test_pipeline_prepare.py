"""Pipeline pieces a sweep relies on: dropping parts the boundary conditions do not hold,
and ``simulate(solve=False)`` (prepare a mesh without solving)."""

import numpy as np
import pyvista as pv

from pvcmf import arrays


def test_drop_floating_parts_drops_a_part_held_on_one_line():
    """A part whose constrained nodes are collinear keeps a rotation: it goes (the slivers a
    mesher cuts off on the fixed posterior plane); a part held by a plane of nodes stays."""
    from pvcmf.pipeline import drop_floating_parts

    held = pv.ImageData(dimensions=(4, 4, 4)).triangulate()
    sliver = held.translate((10.0, 0.0, 0.0), inplace=False)
    grid = held.merge(sliver, merge_points=False)
    x, y, z = grid.points.T
    bc = np.zeros(grid.n_points, dtype=np.int8)
    bc[(x < 0.5)] = arrays.BC_FIXED  # a plane of nodes: held
    bc[(x > 9.5) & (y < 0.5) & (z < 0.5)] = arrays.BC_FIXED  # four nodes on one line
    grid.point_data[arrays.BC] = bc
    out = drop_floating_parts(grid)
    assert out.n_cells == held.n_cells and out.points[:, 0].max() <= 3.0


def test_simulate_without_solve_prepares_the_mesh_only():
    """solve=False (what a sweep prepares once per mesh): mesh with materials and boundary
    conditions and the pre-operative skin; no solve, no predicted skin, no skeleton."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    res = simulate(case.ct, case.plan, bones=case.truth, n_tets=3000, muscles=False,
                   solve=False, out=None)
    assert res.post is None and res.skin_post is None and res.skeleton is None
    assert {"solve", "skeleton"} <= set(res.skipped) and "solve" not in res.timings
    for name in (arrays.BC, arrays.BC_DISPLACEMENT):
        assert name in res.mesh.point_data
    assert arrays.NU in res.mesh.cell_data and res.skin_pre.n_points > 0
    u = pvcmf.mtm.Solver(res.mesh).solve()  # every kept part is held: it solves
    moved = np.asarray(res.mesh[arrays.BC]) != arrays.BC_FREE
    np.testing.assert_allclose(u[moved & (np.asarray(res.mesh[arrays.BC]) == arrays.BC_FIXED)],
                               np.asarray(res.mesh[arrays.BC_DISPLACEMENT])[
                                   moved & (np.asarray(res.mesh[arrays.BC]) == arrays.BC_FIXED)],
                               atol=1e-9)


def test_simulate_classifies_fat_and_muscle_by_default(tmp_path):
    """The default run labels the soft tissue fat or muscle from the CT (paper 001), in
    agreement with the virtual patient's true tissue, and says so in summary.json;
    ``classify=False`` leaves every soft-tissue voxel the atlas does not cover fat."""
    import json

    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    truth = np.asarray(case.truth[arrays.TISSUE])
    runs = {}
    for name, options in (("default", {}), ("off", {"classify": False})):
        runs[name] = simulate(case.ct, case.plan, tmp_path / name, bones=case.truth,
                              predict=False, figures=False, **options)
    on, off = runs["default"], runs["off"]
    assert "classify" in on.timings and "classify" not in on.skipped
    assert "classify" in off.skipped and "classify" not in off.timings
    assert json.loads((tmp_path / "default" / "summary.json").read_text())["classified"] is True
    assert json.loads((tmp_path / "off" / "summary.json").read_text())["classified"] is False
    t_on, t_off = np.asarray(on.labels[arrays.TISSUE]), np.asarray(off.labels[arrays.TISSUE])
    assert not np.any(t_off == arrays.MUSCLE_TISSUE)
    soft = np.isin(t_on, (arrays.FAT, arrays.MUSCLE_TISSUE)) & np.isin(
        truth, (arrays.FAT, arrays.MUSCLE_TISSUE))
    muscle = t_on[soft] == arrays.MUSCLE_TISSUE
    assert 0.1 < muscle.mean() < 0.6
    assert np.mean(muscle == (truth[soft] == arrays.MUSCLE_TISSUE)) > 0.9
