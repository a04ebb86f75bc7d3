"""Muscle-fraction baselines against exact answers.

The analytic case: a label image whose muscle is the half-space ``x >= 0``; with the
nearest-voxel lookup the muscle is exactly ``x >= -spacing / 2``, so the exact share of a
tetrahedron is the volume of its part beyond that plane (computed independently with
VTK's ``clip``).
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters import average_voxels, sample_muscle_fraction, tetrahedralize
from pvcmf.filters.meshing import shell_labels

SPACING = 1.0


def _halfspace_labels(spacing=SPACING, second_muscle_x=None):
    img = pv.ImageData(dimensions=(41, 41, 41), spacing=(spacing,) * 3, origin=(-20.0,) * 3)
    x = img.points[:, 0]
    muscle = np.where(x >= 0, 3, 0)
    if second_muscle_x is not None:
        muscle = np.where(x >= second_muscle_x, 7, muscle)
    img.point_data[arrays.TISSUE] = np.where(muscle > 0, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    img.point_data[arrays.MUSCLE] = muscle.astype(np.uint8)
    return img


def _random_tets(n_points=300, seed=1):
    """A conforming tetrahedral mesh of random points in a box (VTK Delaunay)."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-9, 9, size=(n_points, 3))
    pts[: n_points // 3, 0] = rng.uniform(-2, 1, size=n_points // 3)  # many cut by x = -0.5
    return pv.PolyData(pts).delaunay_3d().extract_cells_by_type(pv.CellType.TETRA)


def _exact_fraction(grid, plane_x=-SPACING / 2):
    g = grid.copy()
    g.cell_data["cid"] = np.arange(g.n_cells)
    part = g.clip(normal=(1, 0, 0), origin=(plane_x, 0, 0), invert=False)
    vol = np.abs(part.compute_cell_sizes(length=False, area=False)["Volume"])
    inside = np.bincount(part.cell_data["cid"], weights=vol, minlength=g.n_cells)
    total = np.abs(grid.compute_cell_sizes(length=False, area=False)["Volume"])
    return inside / total


@pytest.fixture(scope="module")
def case():
    grid = _random_tets()
    labels = _halfspace_labels()
    exact = _exact_fraction(grid)
    return grid, labels, exact


def test_exact_fraction_helper_on_a_known_tet():
    # unit right tetrahedron, plane x = 0.5: the part beyond is (1/2)^3 of the volume
    tet = pv.UnstructuredGrid(
        {pv.CellType.TETRA: np.array([[0, 1, 2, 3]])},
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
    )
    assert _exact_fraction(tet, 0.5)[0] == pytest.approx(0.125)


def test_sampling_converges_like_one_over_sqrt_n(case):
    grid, labels, exact = case
    cut = (exact > 0.05) & (exact < 0.95)
    assert cut.sum() > 50
    rms = {}
    for n in (10, 100, 1000):
        out = sample_muscle_fraction(grid, labels, n_points=n, seed=3)
        err = out[arrays.MUSCLE_FRACTION][cut] - exact[cut]
        rms[n] = np.sqrt(np.mean(err**2))
        # binomial standard error of the share
        expected = np.sqrt(np.mean(exact[cut] * (1 - exact[cut]) / n))
        assert rms[n] == pytest.approx(expected, rel=0.3)
    assert 2.0 < rms[10] / rms[100] < 5.0
    assert 2.0 < rms[100] / rms[1000] < 5.0


def test_sampling_exact_away_from_the_boundary(case):
    grid, labels, exact = case
    out = sample_muscle_fraction(grid, labels, n_points=50)
    frac = out[arrays.MUSCLE_FRACTION]
    assert np.all(frac[exact == 1.0] == 1.0)
    assert np.all(frac[exact == 0.0] == 0.0)
    assert np.all(out[arrays.MUSCLE][frac > 0] == 3)
    assert np.all(out[arrays.MUSCLE][frac == 0] == 0)
    assert out[arrays.MUSCLE].dtype == np.uint8


def test_sampling_is_seeded_and_leaves_input_alone(case):
    grid, labels, _ = case
    before = grid.copy()
    a = sample_muscle_fraction(grid, labels, n_points=20, seed=5)
    b = sample_muscle_fraction(grid, labels, n_points=20, seed=5)
    np.testing.assert_array_equal(a[arrays.MUSCLE_FRACTION], b[arrays.MUSCLE_FRACTION])
    assert arrays.MUSCLE_FRACTION not in grid.cell_data.keys()
    assert grid == before


def test_average_voxels_against_brute_force(case):
    grid, labels, _ = case
    out = average_voxels(grid, labels)
    # independent: barycentric test of every voxel centre against every tetrahedron
    tets = np.asarray(grid.points)[grid.cells_dict[pv.CellType.TETRA]]
    pts = labels.points
    muscle = np.asarray(labels[arrays.TISSUE]) == arrays.MUSCLE_TISSUE
    check = np.linspace(0, len(tets) - 1, 80).astype(int)  # a sample of cells keeps it fast
    frac = np.full(len(check), np.nan)
    for row, i in enumerate(check):
        t = tets[i]
        near = np.all((pts >= t.min(axis=0) - 1e-6) & (pts <= t.max(axis=0) + 1e-6), axis=1)
        lam = (pts[near] - t[0]) @ np.linalg.inv((t[1:] - t[0]).T).T
        inside = np.all(lam >= -1e-9, axis=1) & (lam.sum(axis=1) <= 1 + 1e-9)
        if inside.any():
            frac[row] = muscle[near][inside].mean()
    ok = ~np.isnan(frac)
    assert ok.sum() > 40
    np.testing.assert_allclose(out[arrays.MUSCLE_FRACTION][check][ok], frac[ok], atol=0.05)


def test_average_voxels_tiny_tet_uses_centroid_voxel():
    labels = _halfspace_labels()
    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.1, 0.1], [0.1, 0.3, 0.1], [0.1, 0.1, 0.3]])
    tiny = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]])}, pts)
    assert average_voxels(tiny, labels)[arrays.MUSCLE_FRACTION][0] == 1.0
    assert average_voxels(tiny.translate((-3, 0, 0)), labels)[arrays.MUSCLE_FRACTION][0] == 0.0


def test_dominant_muscle():
    labels = _halfspace_labels(second_muscle_x=5.0)
    pts = np.array([[0.0, 0, 0], [9, 0, 0], [0, 9, 0], [0, 0, 9]])  # mostly in muscle 3
    tet = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]])}, pts)
    assert sample_muscle_fraction(tet, labels, n_points=2000)[arrays.MUSCLE][0] == 3
    assert average_voxels(tet, labels)[arrays.MUSCLE][0] == 3
    far = tet.translate((5.5, 0, 0))  # mostly beyond x = 5: muscle 7
    assert sample_muscle_fraction(far, labels, n_points=2000)[arrays.MUSCLE][0] == 7
    assert average_voxels(far, labels)[arrays.MUSCLE][0] == 7


def test_on_the_homogeneous_mesh_baselines_agree():
    labels = shell_labels(spacing=2.0)
    grid = tetrahedralize(labels, n_tets=5_000, conforming=False)
    sampled = sample_muscle_fraction(grid, labels, n_points=200)[arrays.MUSCLE_FRACTION]
    averaged = average_voxels(grid, labels)[arrays.MUSCLE_FRACTION]
    vol = grid.compute_cell_sizes(length=False, area=False)["Volume"]
    muscle_volume = np.sum(np.asarray(labels[arrays.TISSUE]) == arrays.MUSCLE_TISSUE) * 8.0
    # both recover the muscle volume of the image (to the mesh's geometric error)
    assert np.sum(vol * sampled) == pytest.approx(muscle_volume, rel=0.15)
    assert np.sum(vol * averaged) == pytest.approx(muscle_volume, rel=0.15)
    assert np.corrcoef(sampled, averaged)[0, 1] > 0.8


def test_bad_inputs(case):
    grid, labels, _ = case
    with pytest.raises(TypeError, match="UnstructuredGrid"):
        sample_muscle_fraction(pv.Sphere(), labels)
    with pytest.raises(TypeError, match="ImageData"):
        average_voxels(grid, pv.Sphere())
    with pytest.raises(ValueError, match="n_points"):
        sample_muscle_fraction(grid, labels, n_points=0)
    no_muscle = labels.copy()
    no_muscle.point_data.remove(arrays.MUSCLE)
    with pytest.raises(ValueError, match="muscle"):
        average_voxels(grid, no_muscle)
    hexes = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    with pytest.raises(ValueError, match="tetrahedra"):
        sample_muscle_fraction(hexes, labels)
