"""A CT as a cone-beam scanner holds a face (pvcmf.datasets.cone_beam_field)."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.datasets import cone_beam_field


@pytest.fixture
def water():
    ct = pv.ImageData(dimensions=(60, 60, 40), spacing=(2.0, 2.0, 2.0), origin=(-59, -59, -39))
    ct[arrays.CT] = np.zeros(ct.n_points, dtype=np.float32)
    return ct


def test_grey_values_cupping_and_the_outside(water):
    field = cone_beam_field(water, (0, 0, 0), radius=40, below=20, above=30, behind=0,
                            cupping=0.2, outside=-5000.0)
    grey = np.asarray(field[arrays.CT])
    x, y, z = np.asarray(field.points).T
    r2 = x**2 + y**2
    np.testing.assert_allclose(field.bounds[4:], (-21.0, 31.0))
    assert np.all(grey[r2 > 41**2] == -5000.0)
    # water: attenuation 1000, darkened 20 % on the axis -> 0.6 * (800 - 1000) + 200
    axis = r2 < 2**2  # the four voxel centres next to the axis, 1.4 mm from it
    shade = 1 - 0.2 * (1 - r2[axis] / 40**2)
    np.testing.assert_allclose(grey[axis], 0.6 * (1000 * shade - 1000) + 200, rtol=1e-5)
    edge = (r2 > 38**2) & (r2 < 40**2)
    assert np.all(grey[edge] > grey[axis].max() + 20)
    assert np.asarray(water[arrays.CT]).max() == 0.0  # the input is kept


def test_noise_is_seeded_and_the_default_outside_is_the_lowest_inside(water):
    a = cone_beam_field(water, (0, 0, 0), radius=30, noise=10.0, seed=3)
    b = cone_beam_field(water, (0, 0, 0), radius=30, noise=10.0, seed=3)
    np.testing.assert_array_equal(a[arrays.CT], b[arrays.CT])
    grey = np.asarray(a[arrays.CT])
    assert grey.min() == np.float32(np.min(grey))
    assert np.count_nonzero(grey == grey.min()) > 0.1 * grey.size


def test_bad_input_is_refused(water):
    with pytest.raises(TypeError, match="ct must be a pyvista.ImageData"):
        cone_beam_field(water.cast_to_unstructured_grid(), (0, 0, 0))
    with pytest.raises(ValueError, match="radius must be > 0 mm"):
        cone_beam_field(water, (0, 0, 0), radius=0)
    with pytest.raises(ValueError, match=r"cupping must be in \[0, 1\)"):
        cone_beam_field(water, (0, 0, 0), cupping=1.0)
    with pytest.raises(ValueError, match="misses the image"):
        cone_beam_field(water, (500, 0, 0), radius=20)
