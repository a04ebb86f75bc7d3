"""Every public filter leaves its input untouched (filters are pure).

One small pipeline on a coarse virtual patient runs every filter of
``pvcmf.filters`` (and ``pvcmf.mtm.solve``); each call gets a dataset whose deep copy is
compared with it afterwards: points, cells and every point, cell and field array.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays


def _snapshot(ds):
    return ds.copy(deep=True)


def _assert_same(before, after, name):
    assert type(before) is type(after), name
    assert before.n_points == after.n_points, f"{name} changed the number of points"
    assert before.n_cells == after.n_cells, f"{name} changed the number of cells"
    if before.n_points:
        np.testing.assert_array_equal(before.points, after.points, err_msg=f"{name} moved points")
    if isinstance(before, pv.UnstructuredGrid):
        np.testing.assert_array_equal(before.cell_connectivity, after.cell_connectivity)
    for assoc in ("point_data", "cell_data", "field_data"):
        b, a = getattr(before, assoc), getattr(after, assoc)
        assert sorted(b.keys()) == sorted(a.keys()), f"{name} changed the {assoc} keys"
        for key in b.keys():
            np.testing.assert_array_equal(np.asarray(b[key]), np.asarray(a[key]),
                                          err_msg=f"{name} modified {assoc}[{key!r}]")


CALLED = set()


def _pure(name, func, dataset, *args, **kwargs):
    """Call ``func(dataset, *args)``; assert no dataset argument changed; return the result."""
    inputs = [dataset, *[a for a in args if isinstance(a, pv.DataSet)]]
    snaps = [_snapshot(d) for d in inputs]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        out = func(dataset, *args, **kwargs)
    for snap, d in zip(snaps, inputs):
        _assert_same(snap, d, name)
    CALLED.add(name)
    return out


@pytest.fixture(scope="module")
def chain():
    """Run the whole pipeline once on patient 3 at 3 mm, checking purity at every step."""
    f = pvcmf.filters
    case = pvcmf.datasets.phantom(patient=3, spacing=3.0)
    out = {}
    _pure("standardize", f.standardize, case.ct)
    out["working"] = _pure("working_grid", f.working_grid, case.ct, 6.0)
    out["flat"] = _pure("flatten_shading", f.flatten_shading, out["working"])
    labels = _pure("segment", f.segment, case.ct)
    labels = _pure("classify_tissue", f.classify_tissue, labels)
    labels = _pure("embed_muscles", f.embed_muscles, labels, landmarks=case.landmarks,
                   refine=False)
    bones = _pure("cut_bones", f.cut_bones, case.truth, case.plan)
    out["moved"] = _pure("move_bones", f.move_bones, bones, case.plan)
    jaw = case.truth.points[case.truth[arrays.BONE] == arrays.MANDIBLE]
    lo, hi = jaw.min(axis=0) - 20.0, jaw.max(axis=0) + 20.0
    roi = (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    grid = _pure("tetrahedralize", f.tetrahedralize, labels, n_tets=6000, roi=roi)
    out["fitted"] = _pure("fit_to_skin", f.fit_to_skin, grid, f.extract_skin(labels),
                          labels=labels, box=roi)
    homog = _pure("tetrahedralize", f.tetrahedralize, case.truth, n_tets=4000, roi=roi,
                  conforming=False)
    out["sampled"] = _pure("sample_muscle_fraction", f.sample_muscle_fraction, homog,
                           case.truth, n_points=10)
    out["averaged"] = _pure("average_voxels", f.average_voxels, homog, case.truth)
    grid = _pure("fiber_directions", f.fiber_directions, grid)
    grid = _pure("assign_materials", f.assign_materials, grid)
    grid = _pure("apply_plan", f.apply_plan, grid, case.plan, bones)
    post = _pure("solve", pvcmf.mtm.solve, grid)
    skin = _pure("extract_skin", f.extract_skin, case.truth)
    out["mapped"] = _pure("map_to_surface", f.map_to_surface, post, skin)
    _pure("transfer_operator", f.transfer_operator, post, np.asarray(skin.points[:200]))
    _pure("crumple_metric", f.crumple_metric, skin, out["mapped"][arrays.DISPLACEMENT], post,
          post[arrays.DISPLACEMENT])
    jaws = _pure("find_jaws", f.find_jaws, case.truth)
    for axes, image in (("occlusal", jaws), ("frankfort", labels)):
        plan = dataclasses.replace(case.plan, axes=axes)
        _pure("plan_axes", f.plan_axes, image, plan)
    _pure("mirror_plane", f.mirror_plane, jaws, jaws.field_data[arrays.ARCH_NORMAL])
    moved = skin.translate((0.5, -0.3, 0.2), inplace=False)
    out["registered"] = _pure("register", f.register, moved, skin)
    out["distance"] = _pure("distance_to", f.distance_to, moved, skin)
    pts = np.asarray(skin.points[:500]).copy()
    snap = pts.copy()
    f.oriented_bounding_box(pts)
    np.testing.assert_array_equal(pts, snap)
    CALLED.add("oriented_bounding_box")
    out["post"] = post
    return out


def test_every_filter_is_pure(chain):
    assert arrays.DISPLACEMENT in chain["post"].point_data
    assert arrays.DISTANCE in chain["distance"].point_data
    missing = set(pvcmf.filters.__all__) - CALLED
    assert not missing, f"filters not exercised by the purity test: {sorted(missing)}"
