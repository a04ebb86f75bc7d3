"""A cone-beam scan's slow shading divided out (pvcmf.filters.flatten_shading) and the
pipeline's "shading" step (pvcmf.scan_steps)."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.filters import flatten_shading
from pvcmf.pipeline import Result
from pvcmf.scan_steps import check_shading, shading_step


@pytest.fixture(scope="module")
def head():
    """Virtual patient 2 at 3 mm, in HU."""
    return pvcmf.datasets.phantom(patient=2, spacing=3.0).ct


def _cupped(ct, share):
    """``ct`` with its attenuation darkened by ``share`` on the head's vertical axis."""
    x, y, _ = (np.asarray(ct.points) - np.asarray(ct.center)).T
    r2 = np.minimum((x**2 + y**2) / 100.0**2, 1.0)
    out = ct.copy()
    out[arrays.CT] = ((np.asarray(ct[arrays.CT]) + 1000.0) * (1 - share * (1 - r2))
                      - 1000.0).astype(np.float32)
    return out


def _hard(ct):
    return np.isin(np.asarray(ct.cmf.segment()[arrays.TISSUE]), arrays.HARD_LABELS)


def test_a_cupped_head_segments_as_the_unshaded_one(head):
    ref = _hard(head)
    cupped = _cupped(head, 0.25)
    flat = flatten_shading(cupped)

    def dice(mask):
        return 2 * np.count_nonzero(mask & ref) / (np.count_nonzero(mask) + np.count_nonzero(ref))

    raw, fixed = dice(_hard(cupped)), dice(_hard(flat))
    assert 1 - fixed < 0.5 * (1 - raw) and fixed > 0.95, (raw, fixed)  # the misses halved
    low, high = flat.field_data[arrays.SHADING]
    assert low < 0.95 < 1.05 < high  # the field spans the cupping


def test_the_output_is_new_and_keeps_the_grid_and_fields(head):
    img = head.copy()
    img.field_data["note"] = np.array([7.0])
    out = flatten_shading(img)
    assert out is not img and out.dimensions == img.dimensions
    np.testing.assert_allclose(out.spacing, img.spacing)
    assert not np.shares_memory(np.asarray(out[arrays.CT]), np.asarray(img[arrays.CT]))
    assert out.field_data["note"].tolist() == [7.0] and arrays.SHADING in out.field_data
    assert out[arrays.CT].dtype == np.float32


def test_bad_input_is_refused(head):
    with pytest.raises(TypeError, match="ct must be a pyvista.ImageData"):
        flatten_shading(head.cast_to_unstructured_grid())
    with pytest.raises(ValueError, match="shrink_mm must be a positive number"):
        flatten_shading(head, shrink_mm=0)
    with pytest.raises(ValueError, match="shrink_mm must be a positive number"):
        flatten_shading(head, shrink_mm=True)
    bad = head.copy()
    values = np.asarray(bad[arrays.CT]).copy()
    values[3] = np.nan
    bad[arrays.CT] = values
    with pytest.raises(ValueError, match="must be finite, got 1 NaN"):
        flatten_shading(bad)
    air = pv.ImageData(dimensions=(8, 8, 8))
    air[arrays.CT] = np.full(air.n_points, -1000.0, dtype=np.float32)
    with pytest.raises(ValueError, match="holds no tissue"):
        flatten_shading(air)
    with pytest.raises(ValueError, match="'ct'"):
        flatten_shading(pv.ImageData(dimensions=(8, 8, 8)))


class _Run:
    """The pipeline's step runner, as shading_step uses it."""

    def __init__(self, units):
        self.result = Result(plan=None)
        self.result.ct_report = {"units": {"units": units}}
        self.done = []

    def run(self, step, func, *args):
        self.done.append(step)
        return func(*args)

    def skip(self, step, why):
        self.result.skipped[step] = why


def test_the_step_flattens_rescaled_grey_values_only(head):
    run = _Run("hu")
    assert shading_step(run, head, "auto") is head
    assert "HU" in run.result.skipped["shading"] and "shading" not in run.result.ct_report
    run = _Run("rescaled")
    out = shading_step(run, head, "auto")
    assert run.done == ["shading"] and arrays.SHADING in out.field_data
    report = run.result.ct_report["shading"]
    assert report["method"] == "N4" and report["field_p5"] <= 1.0 <= report["field_p95"]
    run = _Run("rescaled")
    assert shading_step(run, head, "none") is head and run.result.skipped["shading"]
    run = _Run("hu")
    assert arrays.SHADING in shading_step(run, head, "N4").field_data


def test_shading_values_are_checked():
    assert check_shading("Auto") == "auto"
    with pytest.raises(ValueError, match=r"shading must be one of \('auto', 'n4', 'none'\)"):
        check_shading("yes")
    with pytest.raises(ValueError, match="shading must be one of"):
        pvcmf.pipeline.simulate(None, pvcmf.Plan(()), shading=1)
