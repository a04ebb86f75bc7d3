"""narrowest_cut: the least-area cut of a voxel mask between two voxel sets, against the
analytic cross-sections of necks and a brute-force search over every split of small masks."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pvcmf.filters.narrowest_cut import narrowest_cut


def _blocks():
    """Two 6 x 6 x 6 blocks along x, 4 voxels apart."""
    m = np.zeros((16, 6, 6), dtype=bool)
    m[:6] = m[10:] = True
    s, t = np.zeros_like(m), np.zeros_like(m)
    s[0], t[-1] = True, True
    return m, s, t


def test_cut_crosses_the_thinnest_neck_of_a_chain():
    """A thick neck (3 x 3 voxels) and a thin one (1 x 2) in series: the cut is the thin
    neck's cross-section in mm^2 with anisotropic voxels, and the source's side ends there."""
    m, s, t = _blocks()
    m[6:8, 1:4, 1:4] = True       # thick neck from the source's block
    m[8:10, 2, 2:4] = True        # thin neck on to the sink's block
    spacing = (1.0, 0.5, 2.0)
    side, area = narrowest_cut(m, s, t, spacing)
    assert area == pytest.approx(2 * 0.5 * 2.0)   # two x-faces of 0.5 x 2 mm
    assert side[:8].sum() == m[:8].sum()          # the source block and the thick neck
    assert not side[10:].any()


def test_parallel_necks_add_up_and_face_areas_follow_the_axis():
    """Necks along x and a bridge along z: each face weighs its own area."""
    m, s, t = _blocks()
    m[6:10, 0, 0] = True          # one voxel neck along x: face 0.5 x 2
    m[6:10, 5, 5] = True          # another
    spacing = (1.0, 0.5, 2.0)
    _, area = narrowest_cut(m, s, t, spacing)
    assert area == pytest.approx(2 * 0.5 * 2.0)
    # the same shape with the voxels' long side along x: each neck face is 0.5 x 1 mm
    _, area = narrowest_cut(m, s, t, (2.0, 0.5, 1.0))
    assert area == pytest.approx(2 * 0.5 * 1.0)


def test_apart_source_and_sink_keep_the_source_component():
    m, s, t = _blocks()
    side, area = narrowest_cut(m, s, t)
    assert area == 0.0
    assert np.array_equal(side, m & (np.arange(16) < 8)[:, None, None])
    side, area = narrowest_cut(m, s, np.zeros_like(t))
    assert area == 0.0 and np.array_equal(side, s)


def _brute_force(m, s, t, spacing):
    """Least cut area over every split of the free voxels (an exhaustive search)."""
    idx = np.argwhere(m)
    where = {tuple(p): i for i, p in enumerate(idx)}
    areas = (spacing[1] * spacing[2], spacing[0] * spacing[2], spacing[0] * spacing[1])
    edges, weights = [], []
    for i, p in enumerate(idx):
        for axis in range(3):
            q = p.copy()
            q[axis] += 1
            if tuple(q) in where:
                edges.append((i, where[tuple(q)]))
                weights.append(areas[axis])
    edges, weights = np.array(edges), np.array(weights)
    src = np.array([s[tuple(p)] for p in idx])
    snk = np.array([t[tuple(p)] and not s[tuple(p)] for p in idx])
    free = np.flatnonzero(~src & ~snk)
    best = np.inf
    for bits in itertools.product((False, True), repeat=len(free)):
        on = src.copy()
        on[free] = bits
        best = min(best, weights[on[edges[:, 0]] != on[edges[:, 1]]].sum())
    return best


@pytest.mark.parametrize("seed", range(6))
def test_random_small_masks_match_an_exhaustive_search(seed):
    rng = np.random.default_rng(seed)
    m = rng.random((3, 3, 2)) < 0.75
    m[0, 0, 0] = m[2, 2, 1] = True
    s, t = np.zeros_like(m), np.zeros_like(m)
    s[0, 0, 0], t[2, 2, 1] = True, True
    spacing = tuple(rng.choice([0.5, 1.0, 3.0], size=3))
    side, area = narrowest_cut(m, s, t, spacing)
    assert area == pytest.approx(_brute_force(m, s, t, spacing), abs=0.03 * min(spacing) ** 2)
    assert side[0, 0, 0] and not side[2, 2, 1] and not (side & ~m).any()


def test_inputs_are_not_changed_and_bad_ones_are_named():
    m, s, t = _blocks()
    m[6:10, 2, 2] = True
    before = [a.copy() for a in (m, s, t)]
    side, _ = narrowest_cut(m, s, t)
    assert all(np.array_equal(a, b) for a, b in zip((m, s, t), before))
    assert not np.shares_memory(side, m) and not np.shares_memory(side, s)
    with pytest.raises(ValueError, match="spacing must be 3 positive"):
        narrowest_cut(m, s, t, (1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="one shape"):
        narrowest_cut(m, s[:-1], t)
