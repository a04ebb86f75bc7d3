"""Refinement of the independent truth (:mod:`pvcmf.truth.refinement`).

* the skin sampler: points on the exact skin (the patient's level set is zero there);
* the displacement at a boundary point: exact for an affine field (linear interpolation
  on the closest boundary triangle), and the distance to the boundary is the analytic one;
* convergence: the truth's mesher and boundary model on virtual patient 1 at three lattice
  sizes, solved with the small-strain control law on linear elements (seconds, where the
  P2 neo-Hookean truth takes minutes; the mesher and the boundary model are the same):
  the skin's change between successive refinements shrinks at a positive rate, in the
  median and in the 90th percentile. A model that moves with the lattice (tied nodes
  switched free node by node along a cut, muscle by the centroid of each element, a
  tongue hanging on bridges of tissue between the teeth, boundary nodes left off the
  surface) keeps the 90th percentile from shrinking. The target of the benchmark, a 90th
  percentile change of at most 0.1 mm, is a strict xfail: these lattices are far too coarse
  for it (``docs/benchmarks/truth_refinement.md`` measures the P2 truth).
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays

pytest.importorskip("ngsolve")


def test_skin_displacement_is_exact_for_an_affine_field():
    from pvcmf.truth.refinement import skin_displacement

    g = pv.ImageData(dimensions=(5, 5, 5), spacing=(2.5, 2.5, 2.5)).cast_to_unstructured_grid()
    g = g.triangulate()
    a = np.array([[0.1, 0.2, 0.0], [0.0, -0.3, 0.1], [0.05, 0.0, 0.2]])
    g[arrays.DISPLACEMENT] = g.points @ a.T + [1.0, 2.0, 3.0]
    rng = np.random.default_rng(0)
    # points above the top face z = 10 and beside the face x = 0
    top = np.column_stack([rng.uniform(0.5, 9.5, (50, 2)), rng.uniform(10.0, 12.0, 50)])
    side = np.column_stack([rng.uniform(-2.0, 0.0, 50), rng.uniform(0.5, 9.5, (50, 2))])
    pts = np.vstack([top, side])
    u, d = skin_displacement(g, pts)
    foot = pts.copy()
    foot[:50, 2] = 10.0
    foot[50:, 0] = 0.0
    np.testing.assert_allclose(d, np.linalg.norm(pts - foot, axis=1), atol=1e-9)
    np.testing.assert_allclose(u, foot @ a.T + [1.0, 2.0, 3.0], atol=1e-9)


@pytest.fixture(scope="module")
def case():
    import pvcmf

    return pvcmf.datasets.phantom(1, spacing=3.0)


def test_exact_skin_samples_lie_on_the_exact_skin(case):
    from pvcmf.filters.model_region import face_box
    from pvcmf.truth.anatomy import true_level_set
    from pvcmf.truth.refinement import exact_skin_samples

    p = exact_skin_samples(case)
    assert len(p) > 2000
    assert np.abs(true_level_set(case, "skin", p)).max() < 0.05
    assert p[:, 1].min() > face_box(case.truth, 0.5)[2]


def _refinement_changes(case):
    """Skin change between the 2k/4k and 4k/8k linear truths, and the mesh sizes."""
    from pvcmf import filters
    from pvcmf.truth.independent import _boundary_conditions, soft_tissue_mesh
    from pvcmf.truth.refinement import exact_skin_samples, refinement_change
    from pvcmf.truth.solver import solve_reference

    points = exact_skin_samples(case)
    solved, h = [], []
    for n in (2000, 4000, 8000):
        g = _boundary_conditions(case, soft_tissue_mesh(case, n_tets=n))
        g = filters.assign_materials(g, default_fiber=(0.0, 0.0, 1.0))
        solved.append(solve_reference(g, order=1, law="linear", steps=1, threads=False))
        h.append(n ** (-1 / 3))
    return refinement_change(solved[0], solved[1], points), \
        refinement_change(solved[1], solved[2], points), h


@pytest.fixture(scope="module")
def changes(case):
    return _refinement_changes(case)


@pytest.mark.slow
def test_truth_skin_median_converges_under_refinement(changes):
    first, second, h = changes
    rate = np.log(first["p50"] / second["p50"]) / np.log(h[1] / h[2])
    assert rate > 0.5, (first["p50"], second["p50"], rate)
    assert second["compared"] > first["compared"] > 0.3


@pytest.mark.slow
def test_truth_skin_p90_converges_under_refinement(changes):
    first, second, h = changes
    rate = np.log(first["p90"] / second["p90"]) / np.log(h[1] / h[2])
    assert rate > 1.0, (first["p90"], second["p90"], rate)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="the skin's 90th percentile change between the two "
                   "finest truths is still above 0.1 mm (docs/benchmarks/truth_refinement.md)")
def test_truth_skin_p90_change_is_within_a_tenth_of_a_millimetre(changes):
    _, second, _ = changes
    assert second["p90"] <= 0.1, second["p90"]
