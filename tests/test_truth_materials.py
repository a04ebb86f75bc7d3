"""The truth's materials as fields of the position (``materials`` of
:func:`pvcmf.truth.solver.solve_reference`, :func:`pvcmf.truth.independent.material_field`).

* a uniform field gives the solution of the same uniform cell materials;
* the field's energy is linearised consistently (the small-strain law, a quadratic
  energy, converges in one Newton iteration with a varying field);
* the material the solve integrates is the field's on two different meshes of one domain
  (a step in the stiffness that the element faces do not follow), to the projection's
  clipped overshoot;
* the sampled muscle indicator is laid out as ``VoxelCoefficient`` reads it (x fastest)
  and mixes Table I fat and muscle as ``assign_materials`` does;
* two meshes of different bounds get the same field: the same lattice points (whole
  multiples of the step), so the same trilinear interpolant where both reach.
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays

pytest.importorskip("ngsolve")


def _cube(n=3, size=2.0):
    g = pv.ImageData(dimensions=(n, n, n), spacing=(size / (n - 1),) * 3)
    g = g.cast_to_unstructured_grid().triangulate()
    g[arrays.BC] = np.where(np.isin(g.points, [0.0, size]).any(1), arrays.BC_JOINT,
                            arrays.BC_FREE).astype(np.int8)
    g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, 0.003)
    g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    return g


def _field(e, nu, lo=-1.0, hi=3.0):
    return {"origin": (lo,) * 3, "end": (hi,) * 3, "e_cross": e, "nu": nu}


def test_a_uniform_field_is_the_uniform_cell_material():
    from pvcmf.truth import solve_reference

    g = _cube()
    rng = np.random.default_rng(0)
    g[arrays.BC_DISPLACEMENT] = 0.05 * g.points + 0.02 * rng.standard_normal((g.n_points, 3))
    cells = solve_reference(g, steps=1, threads=False)[arrays.DISPLACEMENT]
    field = solve_reference(g, steps=1, threads=False, materials=_field(
        np.full((5, 5, 5), 0.003), np.full((5, 5, 5), 0.46)))[arrays.DISPLACEMENT]
    np.testing.assert_allclose(field, cells, atol=1e-9)


def test_a_varying_field_is_linearised_consistently():
    from pvcmf.truth import solve_reference

    g = _cube()
    g[arrays.BC_DISPLACEMENT] = np.column_stack([0.1 * g.points[:, 0] ** 2,
                                                 np.zeros(g.n_points), np.zeros(g.n_points)])
    x = np.linspace(-1.0, 3.0, 9)
    e = np.broadcast_to(0.003 * (1 + 10 * (x[None, None, :] > 1.0)), (9, 9, 9)).copy()
    out = solve_reference(g, law="linear", steps=1, threads=False,
                          materials=_field(e, np.full((9, 9, 9), 0.46)))
    assert out.field_data[arrays.REFERENCE_SOLVER][1] == 1  # one Newton iteration
    uniform = solve_reference(g, law="linear", steps=1, threads=False)
    free = g[arrays.BC] == arrays.BC_FREE
    assert np.abs(out[arrays.DISPLACEMENT][free] - uniform[arrays.DISPLACEMENT][free]).max() > 1e-4


def test_the_field_is_the_same_material_on_two_meshes():
    from pvcmf.truth.solver import _inputs, _material_fields, _model, _ngsolve

    ngm, ngs = _ngsolve()
    step = 0.02
    x = np.arange(-1.0, 3.0 + step / 2, step)
    # stiffness 1 up to the sample at x = 0.68, 3 from the one at 0.70 (trilinear: the
    # step at 0.69 in the mean): a plane across the elements of both meshes
    e = np.broadcast_to(np.where(x[None, None, :] < 0.69, 1.0, 3.0), (len(x),) * 3).copy()
    field = _field(e, np.full_like(e, 0.3), hi=float(x[-1]))
    exact = 4.0 * (0.69 * 1.0 + 1.31 * 3.0)  # the 2 mm cube's integral of E
    for n in (3, 4):
        g = _cube(n)
        g[arrays.BC_DISPLACEMENT] = np.zeros((g.n_points, 3))
        mesh = _model(ngm, ngs, _inputs(g, None, "tangent"), 1, 1e3, "linear")["mesh"]
        e_f, _ = _material_fields(ngs, mesh, field)
        # (the projection's overshoot at the step is clipped to the samples' range)
        assert ngs.Integrate(e_f, mesh) == pytest.approx(exact, rel=0.01)


def test_material_field_samples_the_muscles_x_fastest():
    import pvcmf
    from pvcmf import filters
    from pvcmf.truth.anatomy import _warp
    from pvcmf.truth.independent import _muscle_indicator, material_field

    case = pvcmf.datasets.phantom(1, spacing=3.0)
    warp = _warp(case)
    # a box of 24 mm around a muscle point of the face
    c = _muscle_point(case, warp)
    box = pv.Box(bounds=np.column_stack([c - 12.0, c + 12.0]).ravel())
    box = box.cast_to_unstructured_grid()
    m = material_field(case, box, step=2.0, sigma=0.0)
    f = m["fraction"]
    assert f.ndim == 3 and 0.05 < f.mean() < 0.95, f.mean()
    nz, ny, nx = f.shape
    rng = np.random.default_rng(0)
    k, j, i = (rng.integers(0, s, 200) for s in (nz, ny, nx))
    p = np.asarray(m["origin"]) + 2.0 * np.column_stack([i, j, k])
    np.testing.assert_array_equal(f[k, j, i], _muscle_indicator(warp, p))
    two = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]] * 2)},
                              np.vstack([np.zeros(3), np.eye(3)]))
    two.cell_data[arrays.TISSUE] = np.array([arrays.FAT, arrays.MUSCLE_TISSUE], np.uint8)
    two.cell_data[arrays.MUSCLE_FRACTION] = np.array([0.0, 1.0])
    two = filters.assign_materials(two, default_fiber=(0.0, 0.0, 1.0))
    e = np.asarray(two.cell_data[arrays.E_CROSS])
    np.testing.assert_allclose(m["e_cross"][f == 1], e[1])
    np.testing.assert_allclose(m["e_cross"][f == 0], e[0])


def _muscle_point(case, warp):
    """A point inside a muscle of the patient (the first of a 30^3 lattice of its box)."""
    from pvcmf.truth.independent import _muscle_indicator

    b = np.asarray(case.truth.bounds).reshape(3, 2)
    grid = np.stack(np.meshgrid(*(np.linspace(lo, hi, 30) for lo, hi in b), indexing="ij"),
                    axis=-1).reshape(-1, 3)
    return grid[np.flatnonzero(_muscle_indicator(warp, grid))[0]]


def _trilinear(m, step, p):
    from scipy.interpolate import RegularGridInterpolator

    f = m["e_cross"]
    axes = [m["origin"][i] + step * np.arange(f.shape[2 - i]) for i in range(3)]
    return RegularGridInterpolator(axes[::-1], f)(p[:, ::-1])


def test_material_field_is_the_same_for_meshes_of_different_bounds():
    import pvcmf
    from pvcmf.truth.anatomy import _warp
    from pvcmf.truth.independent import material_field

    case = pvcmf.datasets.phantom(1, spacing=3.0)
    c = _muscle_point(case, _warp(case))
    boxes = [pv.Box(bounds=np.column_stack([c - 12.0 + s, c + 12.0 + s]).ravel())
             .cast_to_unstructured_grid() for s in (0.0, 0.7)]  # bounds 0.7 mm apart
    m = [material_field(case, box, step=1.5, sigma=1.0) for box in boxes]
    p = np.random.default_rng(1).uniform(c - 11.0, c + 11.0, (5000, 3))
    a, e = _trilinear(m[0], 1.5, p), _trilinear(m[1], 1.5, p)
    assert np.ptp(a) > 0.1  # a muscle's edge in the box
    np.testing.assert_allclose(a, e, rtol=1e-6)
