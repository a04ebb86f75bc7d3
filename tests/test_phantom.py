"""Virtual patients (pvcmf.datasets.phantom) and the template head (datasets.template)."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.datasets import phantom as phantom_module
from pvcmf.datasets import template

SPACING = 3.0


@pytest.fixture(scope="module")
def cases():
    return {p: pvcmf.datasets.phantom(patient=p, spacing=SPACING) for p in (1, 2, 3, 4)}


def _labels(case, name):
    return np.asarray(case.truth[name]).reshape(case.truth.dimensions[::-1])


def test_case_fields_and_dtypes(cases):
    case = cases[1]
    assert isinstance(case, pvcmf.datasets.Case)
    assert case.name == "patient 1" and case.patient == 1 and case.spacing == SPACING
    assert isinstance(case.ct, pv.ImageData) and isinstance(case.truth, pv.ImageData)
    assert case.ct[arrays.CT].dtype == np.float32
    for name in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE):
        assert case.truth[name].dtype == np.uint8
    assert case.ct.dimensions == case.truth.dimensions
    assert np.allclose(case.ct.origin, case.truth.origin)
    assert case.plan is pvcmf.plan.TABLE_II[1]
    assert len(case.landmarks) >= 20


def test_bad_input_raises():
    with pytest.raises(ValueError, match="patient"):
        pvcmf.datasets.phantom(patient=5)
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.datasets.phantom(patient=1, spacing=0.1)
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.datasets.phantom(patient=1, spacing=float("nan"))
    with pytest.raises(TypeError, match="patient"):
        pvcmf.datasets.phantom(patient="1")


def test_deterministic_and_cache_returns_copies(cases):
    again = pvcmf.datasets.phantom(patient=1, spacing=SPACING)
    assert again.ct is not cases[1].ct
    np.testing.assert_array_equal(again.ct[arrays.CT], cases[1].ct[arrays.CT])
    again.ct[arrays.CT][:] = 0.0
    third = pvcmf.datasets.phantom(patient=1, spacing=SPACING)
    np.testing.assert_array_equal(third.ct[arrays.CT], cases[1].ct[arrays.CT])
