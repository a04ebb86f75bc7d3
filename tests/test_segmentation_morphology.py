"""The morphology functions of segment against scipy.ndimage's own operators (independent
implementations): distance transform, closing by a ball, dilation/opening, block copies."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pvcmf.filters.morphology import (_ball, _c_copy, _closing, _dilate_ball, _open_ball,
                                      _pack, _packed_step, _sq_edt, _unpack)

SPACINGS = [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (0.9, 0.7, 2.5), (0.5, 0.5, 1.25)]


def _blobs(seed, shape=(40, 37, 30)):
    rng = np.random.default_rng(seed)
    return ndimage.binary_dilation(rng.random(shape) > 0.97)


@pytest.mark.parametrize("spacing", SPACINGS)
def test_distance_transform_matches_scipy(spacing):
    mask = _blobs(0)
    ref = ndimage.distance_transform_edt(mask, sampling=spacing)
    np.testing.assert_allclose(np.sqrt(_sq_edt(mask, spacing)), ref, rtol=1e-5, atol=1e-5)
    inner = ~mask  # the complement: one large piece with the blobs as holes
    ref = ndimage.distance_transform_edt(inner, sampling=spacing)
    np.testing.assert_allclose(np.sqrt(_sq_edt(inner, spacing)), ref, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("spacing, radius", [((2.0, 2.0, 2.0), 3.0), ((1.0, 1.0, 1.0), 3.0),
                                             ((1.0, 1.0, 1.0), 1.8), ((0.5, 0.5, 1.25), 1.0),
                                             ((0.9, 0.7, 2.5), 2.2)])
def test_closing_matches_binary_closing(spacing, radius):
    """Both the shifted-copies path (a ball within 3x3x3 voxels) and the distance path."""
    mask = _blobs(1)
    ball = _ball(spacing, radius)
    pad = [(h + 1, h + 1) for h in np.array(ball.shape) // 2]
    ref = ndimage.binary_closing(np.pad(mask, pad), structure=ball)
    ref = ref[tuple(slice(a, -b) for a, b in pad)]
    out = _closing(mask, spacing, radius)
    assert out.shape == mask.shape
    assert np.array_equal(out, ref)
    assert not np.array_equal(out, mask)  # the closing does something here


@pytest.mark.parametrize("spacing", SPACINGS[:3])
def test_dilation_and_opening_match_binary_operators(spacing):
    mask = _blobs(2)
    radius = 2.0
    ball = _ball(spacing, radius, minimum=0.0)
    assert np.array_equal(_dilate_ball(mask, spacing, radius),
                          ndimage.binary_dilation(mask, structure=ball))
    pad = np.pad(mask, ball.shape[0])
    ref = ndimage.binary_opening(pad, structure=ball)[tuple(
        slice(ball.shape[0], -ball.shape[0]) for _ in range(3))]
    assert np.array_equal(_open_ball(mask, spacing, radius), ref)


def test_c_copy_of_a_fortran_view():
    a = np.asfortranarray(np.arange(7 * 9 * 40, dtype=np.float32).reshape(7, 9, 40))
    view = a[1:6, 2:8, 3:37]
    out = _c_copy(view)
    assert out.flags.c_contiguous and not np.shares_memory(out, a)
    assert np.array_equal(out, view)


@pytest.mark.parametrize("connectivity", [1, 2, 3])
def test_packed_steps_match_scipy(connectivity):
    """A dilation or erosion by a 3x3x3 element on masks packed eight voxels a byte equals
    scipy's on the boolean mask (away from the outermost layer, which the callers pad)."""
    element = ndimage.generate_binary_structure(3, connectivity)
    rng = np.random.default_rng(connectivity)
    mask = np.pad(rng.random((21, 18, 37)) < 0.5, 1)
    inner = (slice(1, -1),) * 3
    grown = _unpack(_packed_step(_pack(mask), element, np.bitwise_or), mask.shape[2])
    np.testing.assert_array_equal(grown[inner],
                                  ndimage.binary_dilation(mask, element)[inner])
    shrunk = _unpack(_packed_step(_pack(mask), element, np.bitwise_and), mask.shape[2])
    np.testing.assert_array_equal(shrunk[inner],
                                  ndimage.binary_erosion(mask, element, border_value=0)[inner])
