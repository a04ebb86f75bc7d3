"""Image tests of paper 000 Fig. 1 (sampling) and Fig. 2c (labelled mesh, cut open)."""

from __future__ import annotations

import numpy as np
import pytest

from pvcmf.figures.mesh import mesh_figure
from pvcmf.figures.sampling import TET, exact_share, sampling_figure
from pvcmf.filters import tetrahedralize
from pvcmf.filters.meshing import shell_labels


def test_exact_share_converges_and_matches_monte_carlo():
    a, b = exact_share(20), exact_share(40)
    assert abs(a - b) < 5e-3
    rng = np.random.default_rng(0)
    lam = rng.exponential(size=(200_000, 4))
    lam /= lam.sum(axis=1, keepdims=True)
    from pvcmf.figures.sampling import _muscle_distance

    mc = np.mean(_muscle_distance(lam @ TET) <= 0)
    assert b == pytest.approx(mc, abs=4e-3)


def test_fig1_sampling(verify_image_cache):
    pl = sampling_figure(n_points=150, seed=0)
    pl.show()


def test_fig2c_mesh(verify_image_cache):
    grid = tetrahedralize(shell_labels(spacing=2.0), spacing=6.0)
    tube = grid.extract_cells(np.asarray(grid.cell_data["muscle"]) == 1)
    pl = mesh_figure(grid, normal=(0.0, 0.0, 1.0), origin=tube.center, window_size=(600, 460))
    pl.show()
