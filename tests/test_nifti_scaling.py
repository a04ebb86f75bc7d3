"""NIfTI's scl_slope / scl_inter as the standard reads them: a slope of 0 means no scaling
at all (the intercept is ignored too), whatever the intercept says."""

from __future__ import annotations

import struct

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays

nib = pytest.importorskip("nibabel")

#: byte offsets of scl_slope and scl_inter in a NIfTI-1 header (float32 each)
SCL = slice(112, 120)


@pytest.mark.parametrize("slope, inter, scaled", [
    (0.0, 0.0, False), (0.0, 1024.0, False), (float("nan"), 5.0, False),
    (1.0, -1024.0, True), (2.0, -1000.0, True)])
def test_slope_and_intercept(tmp_path, slope, inter, scaled):
    stored = (np.arange(6 * 7 * 8).reshape(6, 7, 8) * 3 - 500).astype(np.int16)
    nib.save(nib.Nifti1Image(stored, np.diag([0.5, 0.6, 0.7, 1.0])), tmp_path / "a.nii")
    data = bytearray((tmp_path / "a.nii").read_bytes())
    data[SCL] = struct.pack("<ff", slope, inter)
    (tmp_path / "a.nii").write_bytes(bytes(data))
    values = np.sort(pvcmf.read_ct(tmp_path / "a.nii", frame="file")[arrays.CT])
    expected = stored.ravel().astype(float) * (slope if scaled else 1.0) + (inter if scaled else 0)
    np.testing.assert_array_equal(values, np.sort(expected))
