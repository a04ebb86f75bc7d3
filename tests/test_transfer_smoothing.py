"""Gradient-guided smoothing of the transfer outside the mesh: no crumple in a crack, the
inside untouched, affine fields exact, a sparse operator."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
import scipy.sparse as sp

from pvcmf import arrays
from pvcmf.filters.crumple_bound import unavoidable_crumples
from pvcmf.filters.surface_mapping import Transfer, crumple_metric, transfer_operator
from pvcmf.filters.transfer_smoothing import smooth_outside, strength


@pytest.fixture(scope="module")
def crack():
    """A block (12 x 8 x 8 mm) with a slot 2 mm wide and 6 mm deep cut from its top (the
    unmeshed layer between two lips), a skin plane across it at mid depth, and a field
    that opens the slot (the lips turn apart) and bends it: the feet of the skin points in
    the slot jump between its walls."""
    src = pv.ImageData(dimensions=(13, 9, 9), origin=(-6.0, -4.0, 0.0)).triangulate()
    cc = src.cell_centers().points
    slot = (np.abs(cc[:, 0]) < 1.0) & (cc[:, 2] > 2.0)
    grid = src.extract_cells(np.flatnonzero(~slot)).clean()
    grid.clear_data()
    skin = pv.Plane(center=(0.0, 0.13, 5.3), direction=(0, 0, 1), i_size=10, j_size=6,
                    i_resolution=41, j_resolution=23).triangulate()
    x = np.asarray(grid.points)
    u = np.column_stack([0.2 * np.tanh(2 * x[:, 0]) * x[:, 2] / 8, np.zeros(len(x)),
                         0.05 * x[:, 0] ** 2])
    return grid, skin, u


def test_crack_old_extension_crumples_smoothed_does_not(crack):
    grid, skin, u = crack
    assert unavoidable_crumples(skin, grid, u)[arrays.CRUMPLE_UNAVOIDABLE] == 0
    plain = Transfer(grid, skin, smoothing=0)
    smooth = Transfer(grid, skin)
    assert (~smooth.inside & smooth.modelled).sum() > 100  # points in the slot
    before = crumple_metric(skin, plain(u), grid, u, transfer=plain)
    after = crumple_metric(skin, smooth(u), grid, u, transfer=smooth)
    assert before[arrays.CRUMPLE_VIOLATIONS] > 10 and before[arrays.CRUMPLE_MAX_RATIO] > 1.2
    assert after[arrays.CRUMPLE_VIOLATIONS] == 0 and after[arrays.CRUMPLE_MAX_RATIO] <= 1.0


def test_inside_rows_unchanged_and_affine_exact(crack):
    grid, skin, _ = crack
    plain = Transfer(grid, skin, smoothing=0)
    smooth = Transfer(grid, skin)
    assert sp.issparse(smooth.W) and smooth.W.shape == (skin.n_points, grid.n_points)
    ins = smooth.inside
    assert abs(smooth.W[ins] - plain.W[ins]).max() == 0.0
    out = ~ins & smooth.modelled
    assert abs(smooth.W[out] - plain.W[out]).max() > 1e-3  # the slot's rows did move
    rng = np.random.default_rng(7)
    for _ in range(3):
        B, c = rng.normal(size=(3, 3)), rng.normal(size=3) * 10
        got = smooth(grid.points @ B.T + c)
        assert np.abs(got - (skin.points @ B.T + c)).max() < 1e-9
    assert np.allclose(np.asarray(smooth.W.sum(axis=1)).ravel(), 1.0)
    # modest widening: each moved row takes its neighbours' supports a few times
    assert smooth.W[out].nnz < 8 * plain.W[out].nnz


def test_points_only_equal_surface(crack):
    """The smoothing's neighbours come from the points: a transfer built from the skin's
    points equals the one built from the skin (as the plan response builds it)."""
    grid, skin, u = crack
    a = transfer_operator(grid, skin)
    b = transfer_operator(grid, np.asarray(skin.points))
    assert abs(a - b).max() < 1e-12


def test_affine_exact_everywhere_with_infinite_band(crack):
    grid, skin, _ = crack
    pts = np.asarray(skin.points) + [0.0, 0.0, 4.0]  # partly above the block
    rng = np.random.default_rng(8)
    B, c = rng.normal(size=(3, 3)), rng.normal(size=3)
    T = transfer_operator(grid, pts, band=np.inf)
    assert np.abs(T @ (grid.points @ B.T + c) - (pts @ B.T + c)).max() < 1e-9


def test_strength_profile():
    d = np.array([0.0, 1e-3, 0.5, 2.0, 3.0, 3.9, 4.0, 5.0])
    a = strength(d, 4.0, 7.0, 0.5)
    assert a[0] == 0.0 and a[1] < 1e-3 and a[-1] == 0.0 and a[-2] == 0.0
    assert a[3] == 0.5 and np.all(a <= 0.5) and 0 < a[5] < a[4]
    assert np.all(strength(d, np.inf, 7.0, 0.5)[3:] == 0.5)


def test_smooth_outside_validates_and_keeps_fixed_rows():
    x = np.column_stack([np.linspace(0, 3, 7), np.zeros(7), np.zeros(7)])
    T = sp.csr_matrix(np.column_stack([x[:, 0] ** 2, np.ones(7)]))
    dist = np.array([0, 0, 1, 1, 1, 0, 0.0])

    def guide(rows, o):
        return sp.csr_matrix((o[:, 0] * 2 * x[rows, 0], (rows, 0 * rows)), shape=(7, 2))

    S = smooth_outside(T, x, dist, 4.0, 1.0, guide, iterations=3)
    fixed = [0, 1, 5, 6]
    assert np.array_equal(S[fixed].toarray(), T[fixed].toarray())
    assert not np.allclose(S[2:5].toarray(), T[2:5].toarray())
    assert smooth_outside(T, x, dist, 4.0, 1.0, guide, iterations=0) is not None
    with pytest.raises(ValueError, match="smoothing"):
        Transfer(pv.ImageData(dimensions=(3, 3, 3)).triangulate(), x, smoothing=-1)


def test_steps_on_dense_columns_equal_the_smoothed_transfer(crack):
    """Smoothing ``W0 X`` (a few dense columns) equals the smoothed sparse transfer times
    ``X``, and the plan response's skin operator built from ``W0`` and the steps equals the
    one built from the smoothed transfer."""
    from pvcmf.mtm.response_operator import SkinOperator

    grid, skin, _ = crack
    tr = Transfer(grid, skin)
    steps = tr.steps
    assert steps is not None and len(steps.rows) > 100
    assert (steps.apply(tr.W0) != tr.W).nnz == 0
    rng = np.random.default_rng(3)
    X = rng.normal(size=(grid.n_points, 7))
    full = tr.W @ X
    moved = steps.moved_rows(tr.W0, X)
    assert np.abs(moved - full[steps.rows]).max() < 1e-12 * np.abs(full).max()
    rest = np.setdiff1d(np.arange(skin.n_points), steps.rows)
    assert np.array_equal(tr.W[rest].toarray(), tr.W0[rest].toarray())
    nodal = rng.normal(size=(grid.n_points, 3, 12))
    folded = SkinOperator(tr.W0, nodal, steps=steps)
    plain = SkinOperator(tr.W, nodal)
    assert np.array_equal(folded.reached, plain.reached)
    ids = np.arange(skin.n_points)
    assert np.abs(folded.rows(ids) - plain.rows(ids)).max() < 1e-12 * np.abs(nodal).max()
    a = rng.normal(size=12)
    got, want = folded.apply(a, np.empty(3 * skin.n_points)), plain.apply(a, np.empty(3 * skin.n_points))
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()
    with pytest.raises(ValueError, match="steps must act on"):
        SkinOperator(tr.W0[:-1], nodal, steps=steps)


def test_rows_product_into_a_buffer_with_a_term_added(monkeypatch):
    """Rows split among threads and written by scipy's kernel into a kept buffer, with a
    term added per row range, equal ``A @ X + add`` bit for bit (empty rows, any split);
    where the kernel does not fit (float32 values, a vector, a Fortran-ordered buffer)
    the same numbers come from scipy's product."""
    from pvcmf.filters import transfer_smoothing as ts

    rng = np.random.default_rng(11)
    A = sp.random(500, 40, density=0.15, format="csr", random_state=rng)
    A = sp.csr_matrix(A.multiply(rng.random((500, 1)) > 0.2))  # some rows empty
    X, add = rng.normal(size=(40, 6)), rng.normal(size=(500, 6))
    want = A @ X + add
    monkeypatch.setattr(ts, "ROWS_PER_THREAD", 7)
    buf = np.full((500, 6), np.nan)
    for threads in (1, 2, 3):
        got = ts.rows_product(A, X, threads, out=buf, add=add)
        assert got is buf and np.array_equal(got, want)
        assert np.array_equal(ts.rows_product(A, X, threads), A @ X)
    assert np.array_equal(ts.rows_product(A.astype(np.float32), X, 2), A.astype(np.float32) @ X)
    assert np.array_equal(ts.rows_product(A, X[:, 0], 2), A @ X[:, 0])
    fortran = np.asfortranarray(np.zeros((500, 6)))
    assert np.array_equal(ts.rows_product(A, X, 2, out=fortran, add=add), want)


def test_moved_rows_from_the_full_product_equal_their_own(crack):
    """The steps' rows made from ``T @ X`` over every row (the first step reading the
    block's rows in place) equal those made from the block's own product, bit for bit,
    on one thread and on several."""
    from pvcmf.filters import transfer_smoothing as ts

    grid, skin, _ = crack
    tr = Transfer(grid, skin)
    X = np.random.default_rng(5).normal(size=(grid.n_points, 9))
    own = tr.steps.moved_rows(tr.W0, X)
    full = tr.W0 @ X
    before = full.copy()
    for threads in (1, 3):
        got = tr.steps.moved_rows(tr.W0, X, threads, product=full)
        assert np.array_equal(got, own)
    assert np.array_equal(full, before)  # the caller's product is read, not written
    assert ts.ROWS_PER_THREAD > 0
