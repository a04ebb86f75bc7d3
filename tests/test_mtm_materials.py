"""MTM materials: tables, the transverse-isotropy convention, positive definiteness, assign_materials."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from mtm_helpers import jittered_box, reference_C

import pvcmf
from pvcmf import arrays
from pvcmf.mtm import (TABLES, check_positive_definite, constitutive_matrix, material_table,
                       positive_definite_mask)


def test_tables_hold_the_papers_values():
    t = TABLES["paper000"]
    assert t["fat"] == {"E_fiber": 0.003, "E_cross": 0.003, "nu": 0.46}
    assert t["muscle"] == {"E_fiber": 0.5, "E_cross": 0.79, "nu": 0.43}
    assert TABLES["paper001_homogeneous"]["fat"]["nu"] == TABLES["paper001_homogeneous"]["muscle"]["nu"] == 0.46
    inh = material_table("paper001_inhomogeneous", e_ratio=64)
    assert inh["fat"]["nu"] == 0.485 and inh["muscle"]["nu"] == 0.43
    assert inh["muscle"]["E_fiber"] == inh["muscle"]["E_cross"] == 64 * inh["fat"]["E_fiber"]
    over = material_table("paper000", fat={"nu": 0.49}, muscle={"E": 0.1})
    assert over["fat"]["nu"] == 0.49 and over["muscle"]["E_cross"] == 0.1
    with pytest.raises(ValueError, match="table must be one of"):
        material_table("paper002")
    with pytest.raises(ValueError, match="overrides must use keys"):
        material_table("paper000", fat={"poisson": 0.3})


@pytest.mark.parametrize("ef,ec,nu", [(0.5, 0.79, 0.43), (1.0, 1.0, 0.3), (3.0, 0.7, 0.1),
                                      (0.003, 0.003, 0.4999)])
def test_constitutive_matrix_is_the_inverse_of_the_documented_compliance(ef, ec, nu):
    rng = np.random.default_rng(3)
    for fiber in ([0, 0, 1], rng.normal(size=3), rng.normal(size=3)):
        fiber = np.asarray(fiber, float) / np.linalg.norm(fiber)
        C = constitutive_matrix([ef], [ec], [nu], [fiber])[0]
        ref = reference_C(ef, ec, nu, fiber)
        assert np.abs(C - ref).max() <= 1e-10 * np.abs(ref).max()


def test_isotropic_case_is_lame():
    E, nu = 2.0, 0.3
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    C = constitutive_matrix([E], [E], [nu])[0]
    ref = np.zeros((6, 6))
    ref[:3, :3] = lam
    ref[[0, 1, 2], [0, 1, 2]] += 2 * mu
    ref[[3, 4, 5], [3, 4, 5]] = mu
    np.testing.assert_allclose(C, ref, rtol=1e-13, atol=1e-13)


def test_positive_definite_mask_agrees_with_eigenvalues():
    rng = np.random.default_rng(0)
    ef = 10 ** rng.uniform(-3, 1, 400)
    ec = 10 ** rng.uniform(-3, 1, 400)
    nu = rng.uniform(-0.2, 0.99, 400)
    mask = positive_definite_mask(ef, ec, nu)
    assert 50 < mask.sum() < 350
    for i in range(400):
        C_eig = np.linalg.eigvalsh(np.linalg.inv(reference_C(ef[i], ec[i], nu[i])))
        assert bool(C_eig.min() > 0) == bool(mask[i]), (ef[i], ec[i], nu[i])


def test_nu_over_E_fiber_convention_is_indefinite_and_named():
    # Table I muscle read with -nu/E_fiber in the fibre column: in pvcmf's convention the same
    # S13 needs nu' = nu * E_cross / E_fiber (here 0.679), which is indefinite
    nu_other = 0.43 * 0.79 / 0.5
    with pytest.raises(ValueError, match=r"not positive definite in 1 cell\(s\): cell 2: "
                                         r"E_fiber=0.5, E_cross=0.79, nu=0.6794"):
        check_positive_definite([0.5, 0.5, 0.5], [0.79, 0.79, 0.79], [0.43, 0.43, nu_other])
    with pytest.raises(ValueError, match="nu over E_cross"):
        check_positive_definite([1.0], [1.0], [0.5])


def _labelled(seed=0):
    grid = jittered_box(shape=(5, 4, 4), seed=seed)
    rng = np.random.default_rng(seed)
    tissue = np.where(rng.random(grid.n_cells) < 0.4, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    grid.cell_data[arrays.TISSUE] = tissue
    fib = rng.normal(size=(grid.n_cells, 3))
    grid.cell_data[arrays.FIBER] = fib
    return grid


def test_assign_materials_by_label_and_does_not_mutate():
    grid = _labelled()
    before = {k: np.array(grid.cell_data[k]) for k in grid.cell_data.keys()}
    out = grid.cmf.assign_materials(table="paper000")
    assert set(grid.cell_data.keys()) == set(before)
    for k, v in before.items():
        np.testing.assert_array_equal(grid.cell_data[k], v)
    musc = grid[arrays.TISSUE] == arrays.MUSCLE_TISSUE
    np.testing.assert_array_equal(out[arrays.E_FIBER], np.where(musc, 0.5, 0.003))
    np.testing.assert_array_equal(out[arrays.E_CROSS], np.where(musc, 0.79, 0.003))
    np.testing.assert_array_equal(out[arrays.NU], np.where(musc, 0.43, 0.46))
    fib = out[arrays.FIBER]
    assert np.all(fib[~musc] == 0)
    np.testing.assert_allclose(np.linalg.norm(fib[musc], axis=1), 1.0)
    unit = before[arrays.FIBER][musc] / np.linalg.norm(before[arrays.FIBER][musc], axis=1)[:, None]
    np.testing.assert_allclose(fib[musc], unit)
    same = pvcmf.filters.assign_materials(grid, table="paper000")
    np.testing.assert_array_equal(same[arrays.E_FIBER], out[arrays.E_FIBER])


def test_muscle_without_fibre_direction_is_isotropic_mean():
    """Muscle outside the atlas muscles (zero fibre) gets E = (0.5 + 0.79) / 2, no fibre."""
    grid = _labelled(seed=3)
    fib = np.array(grid.cell_data[arrays.FIBER])
    musc = grid[arrays.TISSUE] == arrays.MUSCLE_TISSUE
    unknown = musc & (np.arange(grid.n_cells) % 2 == 0)
    fib[unknown] = 0.0
    grid.cell_data[arrays.FIBER] = fib
    out = grid.cmf.assign_materials(table="paper000")
    np.testing.assert_allclose(out[arrays.E_FIBER][unknown], 0.645)
    np.testing.assert_allclose(out[arrays.E_CROSS][unknown], 0.645)
    np.testing.assert_allclose(out[arrays.NU][unknown], 0.43)
    assert np.all(out[arrays.FIBER][unknown] == 0)
    known = musc & ~unknown
    np.testing.assert_allclose(out[arrays.E_FIBER][known], 0.5)
    np.testing.assert_allclose(np.linalg.norm(out[arrays.FIBER][known], axis=1), 1.0)


def test_assign_materials_paper001_and_isotropic_muscle_needs_no_fiber():
    grid = _labelled()
    del grid.cell_data[arrays.FIBER]
    out = grid.cmf.assign_materials(table="paper001_inhomogeneous", e_ratio=8)
    musc = grid[arrays.TISSUE] == arrays.MUSCLE_TISSUE
    np.testing.assert_array_equal(out[arrays.E_FIBER], np.where(musc, 8.0, 1.0))
    np.testing.assert_array_equal(out[arrays.NU], np.where(musc, 0.43, 0.485))
    assert np.all(out[arrays.FIBER] == 0)
    with pytest.raises(ValueError, match="no cell array 'fiber'.*fiber_directions"):
        grid.cmf.assign_materials(table="paper000")
    out = grid.cmf.assign_materials(table="paper000", default_fiber=(0, 0, 2))
    np.testing.assert_array_equal(out[arrays.FIBER][musc], np.tile([0.0, 0.0, 1.0], (musc.sum(), 1)))


def test_assign_materials_weights_by_muscle_fraction():
    grid = _labelled()
    f = np.linspace(0, 1, grid.n_cells)
    grid.cell_data[arrays.MUSCLE_FRACTION] = f
    out = grid.cmf.assign_materials(table="paper000")
    np.testing.assert_allclose(out[arrays.E_FIBER], (1 - f) * 0.003 + f * 0.5)
    np.testing.assert_allclose(out[arrays.E_CROSS], (1 - f) * 0.003 + f * 0.79)
    np.testing.assert_allclose(out[arrays.NU], (1 - f) * 0.46 + f * 0.43)
    assert np.all(out[arrays.FIBER][f == 0] == 0) and np.all(np.linalg.norm(out[arrays.FIBER][f > 0], axis=1) > 0.99)
    grid.cell_data[arrays.MUSCLE_FRACTION] = f * 2
    with pytest.raises(ValueError, match="muscle_fraction.*\\[0, 1\\]"):
        grid.cmf.assign_materials()


def test_assign_materials_rejects_bad_input():
    grid = _labelled()
    grid.cell_data[arrays.TISSUE][0] = arrays.BONE_TISSUE
    with pytest.raises(ValueError, match="only FAT.*got labels \\[3\\]"):
        grid.cmf.assign_materials()
    with pytest.raises(ValueError, match="no cell array 'tissue'.*tetrahedralize"):
        pv.ImageData(dimensions=(2, 2, 2)).triangulate().cmf.assign_materials()
    with pytest.raises(TypeError, match="UnstructuredGrid"):
        pvcmf.filters.assign_materials(pv.ImageData(dimensions=(2, 2, 2)))
    grid = _labelled()
    with pytest.raises(ValueError, match="not positive definite.*cell"):
        grid.cmf.assign_materials(muscle={"E_fiber": 10.0})
