"""The virtual post-operative truth model (NGSolve neo-Hookean, P2): exactness, convergence,
sliding contact, bad input. Skipped without the optional extra ``pvcmf[reference]``."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays

pytest.importorskip("ngsolve")
from pvcmf.reference import solve_reference  # noqa: E402


def cube(n, size=10.0):
    """Tetrahedral cube [0, size]^3 with n cells per side, Table I fat."""
    g = pv.ImageData(dimensions=(n + 1,) * 3, spacing=(size / n,) * 3)
    g = g.cast_to_unstructured_grid().triangulate()
    g[arrays.BC] = np.zeros(g.n_points, np.int8)
    g[arrays.BC_DISPLACEMENT] = np.zeros((g.n_points, 3))
    g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, 0.003)
    g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    return g


def test_homogeneous_large_deformation_is_exact():
    """Any homogeneous hyperelastic body under affine boundary data deforms affinely."""
    g = cube(4)
    a = np.array([[0.3, 0.1, 0.0], [0.0, -0.2, 0.05], [0.03, 0.0, 0.25]])  # 30 % strains
    g[arrays.BC] = np.where(np.isin(g.points, [0.0, 10.0]).any(axis=1), arrays.BC_JOINT,
                            arrays.BC_FREE).astype(np.int8)
    g[arrays.BC_DISPLACEMENT] = g.points @ a.T
    # fibre-reinforced (E_fiber > E_cross) and still homogeneous
    g.cell_data[arrays.E_FIBER] = np.full(g.n_cells, 0.01)
    g.cell_data[arrays.FIBER] = np.tile([1.0, 0.0, 0.0], (g.n_cells, 1))
    before = g[arrays.BC_DISPLACEMENT].copy()
    out = solve_reference(g)
    np.testing.assert_allclose(out[arrays.DISPLACEMENT], g.points @ a.T, atol=1e-9)
    np.testing.assert_array_equal(g[arrays.BC_DISPLACEMENT], before)
    assert arrays.DISPLACEMENT not in g.point_data


def shear(n):
    g = cube(n)
    z = g.points[:, 2]
    g[arrays.BC] = np.where((z == 0) | (z == 10), arrays.BC_FIXED, arrays.BC_FREE).astype(np.int8)
    g[arrays.BC_DISPLACEMENT] = np.where((z == 10)[:, None], [3.0, 0.0, 0.0], 0.0)
    out = solve_reference(g)
    centre = np.argmin(np.linalg.norm(g.points - 5.0, axis=1))
    return out[arrays.DISPLACEMENT][centre]


def test_converges_under_refinement():
    u2, u4, u6 = shear(2), shear(4), shear(6)
    assert u6[0] == pytest.approx(1.5, abs=0.3)  # about half the top's shear at mid height
    assert np.linalg.norm(u4 - u6) < 0.5 * np.linalg.norm(u2 - u6)
    assert np.linalg.norm(u4 - u6) < 0.02 * np.linalg.norm(u6)


def test_sliding_contact_holds_the_normal_and_frees_the_tangent():
    g = cube(4)
    z = g.points[:, 2]
    bc = np.full(g.n_points, arrays.BC_FREE, np.int8)
    bc[z == 0] = arrays.BC_SLIDING
    bc[z == 10] = arrays.BC_FIXED
    g[arrays.BC] = bc
    g[arrays.BC_DISPLACEMENT] = np.where((z == 10)[:, None], [0.0, 0.0, -2.0], 0.0)
    g[arrays.BC_NORMAL] = np.tile([0.0, 0.0, 1.0], (g.n_points, 1))
    u = solve_reference(g)[arrays.DISPLACEMENT]
    bottom = z == 0
    assert np.abs(u[bottom, 2]).max() < 1e-3  # stays on the plane
    corner = bottom & (g.points[:, 0] == 10) & (g.points[:, 1] == 10)
    assert u[corner, 0] > 0.1 and u[corner, 1] > 0.1  # slides outward (bulges)


def test_bad_input():
    g = cube(2)
    with pytest.raises(TypeError, match="UnstructuredGrid"):
        solve_reference(pv.Sphere())
    bad = g.copy()
    del bad.cell_data[arrays.NU]
    with pytest.raises(ValueError, match="no cell array 'nu'.*assign_materials"):
        solve_reference(bad)
    bad = g.copy()
    bad.cell_data[arrays.NU] = np.full(g.n_cells, 0.5)
    with pytest.raises(ValueError, match="nu in"):
        solve_reference(bad)
    hexes = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    with pytest.raises(ValueError, match="tetrahedra"):
        solve_reference(hexes)
