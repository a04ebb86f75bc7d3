"""The dental arches in occlusion: the occlusal surface fitted to the crowns' contact gaps
(:mod:`pvcmf.filters.dental_arches`) stays an occlusal surface where its samples are few
or scattered, and cuts only where the crowns meet."""

from __future__ import annotations

import numpy as np
import pytest

from pvcmf.filters.dental_arches import (OCCLUSAL_MIN_RADIUS, _fit_quadric, _quadric,
                                         dental_arches)


def _patch(n=400, seed=0):
    rng = np.random.default_rng(seed)
    return np.column_stack([rng.uniform(0, 50, n), rng.uniform(0, 40, n)])


def test_an_occlusal_curve_is_fitted_as_it_is():
    """A surface bent like the curve of Spee (radius 150 mm) is fitted exactly."""
    pts = _patch()
    z = 80.0 + 0.2 * pts[:, 0] + (pts[:, 1] - 20.0) ** 2 / (2 * 150.0)
    fit = _fit_quadric(pts, z)
    np.testing.assert_allclose(_quadric(pts, fit), z, atol=1e-9)


def test_a_fold_sharper_than_any_occlusal_surface_is_fitted_as_a_plane():
    """Samples on a fold of radius 17 mm (no dentition bends so; scattered samples of part
    of the arch can): the least-squares plane, not the fold."""
    pts = _patch()
    z = 80.0 + 0.03 * (pts[:, 1] - 20.0) ** 2
    assert 1.0 / 0.06 < OCCLUSAL_MIN_RADIUS
    fit = _fit_quadric(pts, z)
    A = np.column_stack([np.ones(len(z)), pts - fit[0]])
    plane = np.linalg.lstsq(A, z, rcond=None)[0]
    np.testing.assert_allclose(_quadric(pts, fit), A @ plane, atol=1e-9)


@pytest.fixture(scope="module")
def tilted_bite():
    """Two arches in occlusion on a 1 mm grid whose contact gap falls 0.4 mm per mm toward
    the front (+y), with alveolar bone above and below and a chin in front of and below the
    lower incisors, in a box that reaches 30 mm in front of them (the arch's footprint runs
    to the box's front)."""
    shape = (60, 90, 70)
    x, y = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    # a U open toward -y: the arch's crest 20 mm from its centre, crowns 6 mm wide
    r = np.hypot(x - 30.0, np.maximum(y - 30.0, 0.0) * 1.0)
    arch = (np.abs(r - 20.0) <= 3.0) & (y >= 10) & (y <= 55)
    gap = np.rint(40.0 - 0.4 * (y - 30.0)).astype(int)
    z = np.arange(shape[2])[None, None, :]
    g = gap[:, :, None]
    teeth = arch[:, :, None] & (((z >= g - 5) & (z <= g - 1)) | ((z >= g + 1) & (z <= g + 5)))
    hard = teeth | (arch[:, :, None] & (((z >= g - 15) & (z <= g - 6))
                                        | ((z >= g + 6) & (z <= g + 15))))
    chin = (np.abs(x - 30) <= 10) & (y > 55) & (y <= 80)  # below the incisors, in front
    hard |= chin[:, :, None] & (z >= 5) & (z <= 24)
    return teeth, hard, (1.0, 1.0, 1.0), g


def test_the_occlusal_level_lies_within_the_teeth(tilted_bite):
    teeth, hard, spacing, _ = tilted_bite
    z = np.flatnonzero(teeth.any(axis=(0, 1)))
    z_occ, upper, lower, contact = dental_arches(teeth, hard, spacing)
    assert contact is not None, "the arches touch"
    assert z[0] <= z_occ <= z[-1], (z_occ, z[0], z[-1])


def test_the_contact_cut_lies_where_the_crowns_meet(tilted_bite):
    """The surface runs on in front of the incisors, below the lowest crown: the hard voxels
    it crosses there are no contact and stay uncut."""
    teeth, hard, spacing, gap = tilted_bite
    z = np.flatnonzero(teeth.any(axis=(0, 1)))
    _, upper, lower, contact = dental_arches(teeth, hard, spacing)
    assert np.array_equal(upper, teeth & (np.arange(teeth.shape[2]) > gap))
    cut = np.nonzero(contact)[2]
    assert cut.size and cut.min() >= z[0] and cut.max() <= z[-1]


def test_stray_tooth_dense_voxels_make_no_second_arch():
    """One lower arch over its alveolar bone, and a few tooth-dense voxels (noise on the
    dense cortex) 20 mm below it: their peak of the height profile is no second arch, so
    the arch stays lower, not upper over a lower arch of stray voxels."""
    shape = (60, 60, 70)
    x, y = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    arch = (np.abs(np.hypot(x - 30.0, np.maximum(y - 25.0, 0.0)) - 20.0) <= 3.0) & (y >= 10)
    z = np.arange(shape[2])[None, None, :]
    teeth = arch[:, :, None] & (z >= 40) & (z <= 46)
    hard = teeth | (arch[:, :, None] & (z >= 25) & (z <= 39))
    stray = np.zeros_like(teeth)
    stray[28:31, 14:16, 19:22] = True  # 18 voxels, under 15 % of the teeth
    teeth |= stray
    hard |= stray
    z_occ, upper, lower, contact = dental_arches(teeth, hard, (1.0, 1.0, 1.0))
    assert not upper.any() and np.array_equal(lower, teeth) and contact is None
