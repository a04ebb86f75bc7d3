"""MTM tensors: the BSR stiffness against scikit-fem, symmetry, rigid motions, validation."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from mtm_helpers import delaunay_box, jittered_box, set_materials, skfem_stiffness

import pvcmf
from pvcmf import arrays
from pvcmf.mtm import Assembler, stiffness, tetrahedra


def mixed_grid(seed=0, shape=(7, 5, 5)):
    """Irregular mesh, fat and transversely isotropic muscle cells (paper 000), random fibres."""
    grid = jittered_box(shape=shape, seed=seed)
    rng = np.random.default_rng(seed)
    m = grid.n_cells
    musc = rng.random(m) < 0.4
    fib = rng.normal(size=(m, 3))
    fib /= np.linalg.norm(fib, axis=1)[:, None]
    set_materials(grid, np.where(musc, 0.5, 0.003), np.where(musc, 0.79, 0.003),
                  np.where(musc, 0.43, 0.46), np.where(musc[:, None], fib, 0.0))
    return grid


@pytest.fixture(scope="module")
def grid():
    return mixed_grid()


def test_stiffness_equals_scikit_fem(grid):
    K = stiffness(grid)
    assert isinstance(K, pvcmf.mtm.Assembler.bsr.__globals__["sp"].bsr_matrix)
    assert K.blocksize == (3, 3) and K.shape == (3 * grid.n_points, 3 * grid.n_points)
    Ksk, dofs = skfem_stiffness(grid)
    perm = dofs.T.ravel()  # node-major order of pvcmf
    Kref = Ksk[perm][:, perm].toarray()
    assert np.abs(K.toarray() - Kref).max() <= 1e-12 * np.abs(Kref).max()


def test_symmetric_rigid_null_space_and_rank(grid):
    K = stiffness(grid).toarray()
    scale = np.abs(K).max()
    assert np.abs(K - K.T).max() <= 1e-14 * scale
    x = grid.points - grid.points.mean(axis=0)
    modes = [np.tile(e, grid.n_points) for e in np.eye(3)] + [np.cross(w, x).ravel() for w in np.eye(3)]
    for r in modes:
        assert np.abs(K @ r).max() <= 1e-12 * scale * np.abs(r).max()
    ev = np.linalg.eigvalsh(K)
    assert np.sum(np.abs(ev) <= 1e-10 * ev[-1]) == 6 and ev[6] > 1e-8 * ev[-1]


def test_blocks_are_the_mtm_tensors(grid):
    """Diagonal blocks K_jj, off-diagonal K_jk only along mesh edges."""
    K = stiffness(grid)
    cells = tetrahedra(grid)[1]
    edges = {(min(a, b), max(a, b)) for c in cells[:50] for a in c for b in c if a != b}
    rows = np.repeat(np.arange(grid.n_points), np.diff(K.indptr))
    stored = {(min(r, c), max(r, c)) for r, c in zip(rows, K.indices) if r != c}
    assert edges <= stored
    assert len(stored) == len(grid.extract_all_edges().lines.reshape(-1, 3))
    dense = K.toarray()
    j = 5
    np.testing.assert_array_equal(dense[3 * j:3 * j + 3, 3 * j:3 * j + 3],
                                  K.data[np.flatnonzero((rows == j) & (K.indices == j))[0]])


def test_reassembly_reuses_geometry_and_overrides():
    grid = mixed_grid(seed=2, shape=(5, 4, 4))
    asm = Assembler(*tetrahedra(grid))
    K1 = asm.matrix(grid[arrays.E_FIBER], grid[arrays.E_CROSS], np.full(grid.n_cells, 0.3), grid[arrays.FIBER])
    K2 = stiffness(grid, nu=0.3)
    np.testing.assert_allclose(K1.toarray(), K2.toarray(), rtol=0, atol=1e-15 * abs(K2).max())
    # homogeneous scaling: K is proportional to E (paper 001 eq. 3)
    Ka = stiffness(grid, E_fiber=1.0, E_cross=1.0, nu=0.46).toarray()
    Kb = stiffness(grid, E_fiber=7.0, E_cross=7.0, nu=0.46).toarray()
    np.testing.assert_allclose(Kb, 7 * Ka, rtol=1e-13, atol=1e-15 * np.abs(Kb).max())


def test_stiffness_validation_messages():
    with pytest.raises(TypeError, match="UnstructuredGrid of linear tetrahedra"):
        stiffness(pv.ImageData(dimensions=(3, 3, 3)))
    hexes = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    with pytest.raises(ValueError, match="only linear tetrahedra"):
        stiffness(hexes)
    grid = jittered_box(shape=(3, 3, 3))
    with pytest.raises(ValueError, match="no cell array 'E_fiber'.*assign_materials"):
        stiffness(grid)
    set_materials(grid, 1.0, 2.0, 0.3)
    with pytest.raises(ValueError, match="fiber must be a nonzero vector.*cell 0"):
        stiffness(grid)
    flat = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]])},
                               np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.0]]))
    set_materials(flat, 1.0, 1.0, 0.3)
    with pytest.raises(ValueError, match="degenerate.*cell 0"):
        stiffness(flat)


def test_delaunay_slivers_assemble_finite():
    grid = delaunay_box()
    set_materials(grid, 1.0, 1.0, 0.49)
    K = stiffness(grid)
    assert np.all(np.isfinite(K.data))
    u = np.tile([0.3, -0.2, 0.1], grid.n_points)
    assert np.abs(K @ u).max() <= 1e-11 * abs(K).max()


def test_linear_reassembly_equals_scikit_fem_after_material_and_fibre_changes(grid):
    """The cached coefficient -> blocks map used by sweeps (new nu, new moduli, new fibres)."""
    pts, cells = tetrahedra(grid)
    asm = Assembler(pts, cells)
    rng = np.random.default_rng(3)
    ef, ec = np.array(grid[arrays.E_FIBER]), np.array(grid[arrays.E_CROSS])
    fib = np.array(grid[arrays.FIBER])
    for nu, scale, turn in ((0.3, 1.0, False), (0.49, 2.0, False), (0.1, 1.0, True)):
        if turn:  # rotate every fibre: the map must be rebuilt, not reused
            fib = np.where(np.linalg.norm(fib, axis=1)[:, None] > 0, rng.normal(size=fib.shape), 0.0)
            fib /= np.maximum(np.linalg.norm(fib, axis=1), 1e-300)[:, None]
        g = grid.copy()
        set_materials(g, scale * ef, scale * ec, nu, fib)
        Ksk, dofs = skfem_stiffness(g)
        perm = dofs.T.ravel()
        Kref = Ksk[perm][:, perm].toarray()
        K = asm.bsr(asm.full_blocks(asm.linear_upper_blocks(scale * ef, scale * ec, nu, fib)))
        assert np.abs(K.toarray() - Kref).max() <= 1e-12 * np.abs(Kref).max(), (nu, scale, turn)


def test_merge_pairs_matches_numpy_unique():
    from pvcmf.mtm.assembly import _merge_pairs, _merge_pairs_numpy

    rng = np.random.default_rng(0)
    n = 50
    rows, cols = rng.integers(0, n, 2000), rng.integers(0, n, 2000)
    rows[rows == 7] = 8  # an empty row inside
    rows[rows == 0] = 1  # and one at the start
    indptr, indices, inverse = _merge_pairs(rows, cols, n)
    keys, inv = np.unique(rows * n + cols, return_inverse=True)
    np.testing.assert_array_equal(indices, keys % n)
    np.testing.assert_array_equal(inverse, inv.ravel())
    np.testing.assert_array_equal(np.diff(indptr), np.bincount(keys // n, minlength=n))
    for a, b in zip(_merge_pairs_numpy(rows, cols, n), (indptr, indices, inverse)):
        np.testing.assert_array_equal(a, b)  # the fallback without scipy's private kernels
