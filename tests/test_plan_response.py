"""Plan response operator: equals apply_plan + solve + transfer for random plans."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters import apply_plan
from pvcmf.filters.surface_mapping import transfer_operator
from pvcmf.mtm import solve
from pvcmf.mtm.response import PlanResponseWarning, plan_response
from pvcmf.plan import Osteotomy, Plan


@pytest.fixture(scope="module")
def block():
    """Soft-tissue shell around a two-segment bone block (maxilla above, mandible below,
    teeth between them) and a skin sphere partly outside the mesh."""
    img = pv.ImageData(dimensions=(15, 15, 15), origin=(-7, -7, -7))
    p = np.asarray(img.points)
    inner = (np.abs(p) <= 3).all(axis=1)
    bone = np.where(inner, np.where(p[:, 2] > 0, arrays.MAXILLA, arrays.MANDIBLE), 0)
    img[arrays.BONE] = bone.astype(np.uint8)
    tissue = np.where(inner, arrays.BONE_TISSUE, arrays.FAT)
    tissue[inner & (np.abs(p[:, 2]) <= 0) & (p[:, 1] >= 3)] = arrays.TEETH
    img[arrays.TISSUE] = tissue.astype(np.uint8)
    soft = ~(np.abs(img.cell_centers().points) < 3).all(axis=1)
    grid = img.extract_cells(np.flatnonzero(soft)).triangulate().clean()
    grid.clear_data()
    grid.cell_data[arrays.E_FIBER] = np.full(grid.n_cells, 3e-3)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.45)
    skin = pv.Sphere(radius=7.3, theta_resolution=30, phi_resolution=20)
    return grid, img, skin


def _random_plan(rng, segments=("maxilla", "mandible")):
    return Plan(tuple(Osteotomy(s, tuple(rng.uniform(-3, 3, 3)), tuple(rng.uniform(-30, 30, 3)))
                      for s in segments))


def test_predict_equals_full_solve(block):
    grid, img, skin = block
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts)
    T = transfer_operator(grid, skin)
    rng = np.random.default_rng(3)
    for segments in (("maxilla", "mandible"), ("mandible",)):
        plan = _random_plan(rng, segments)
        full = solve(apply_plan(grid, plan, img, **opts))
        u = np.asarray(full[arrays.DISPLACEMENT])
        assert np.abs(u).max() > 0.5
        pred = resp.predict(plan)
        assert np.abs(pred[arrays.DISPLACEMENT] - T @ u).max() < 1e-9
        assert np.allclose(pred.points, skin.points + pred[arrays.DISPLACEMENT])
        assert np.abs(resp.predict_nodes(plan) - u[resp.surface_ids]).max() < 1e-9
    stats = resp.statistics([_random_plan(rng) for _ in range(5)])
    assert stats.shape == (5, 3) and np.all(stats[:, 0] >= stats[:, 1])


def test_other_boundary_types_fall_back(block):
    grid, img, skin = block
    resp = plan_response(grid, img, skin=skin, dtype="float64",
                         bc_options={"fix_unmoved_bone": True},
                         plan=Plan((Osteotomy("maxilla"),)))
    plan = _random_plan(np.random.default_rng(4))  # moves the mandible too
    with pytest.warns(PlanResponseWarning):
        pred = resp.predict_displacement(plan)
    full = solve(apply_plan(grid, plan, img, fix_unmoved_bone=True))
    assert np.abs(pred - transfer_operator(grid, skin) @ full[arrays.DISPLACEMENT]).max() < 1e-9
