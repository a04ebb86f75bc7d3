"""The real head CTs of the data folder: read, stored in scanner units with turned axes, come
back to the same image.

Each scan is read once per module (fixture) and cut to a 2 mm copy (every second voxel) so
that the checks stay within CI's time. Skipped cleanly when the data folder lacks the scan.
"""

from __future__ import annotations

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays
from pvcmf.filters.orientation import standardize

from ct_helpers import image_of, stored_as, volume

TURNS = ["LPI", "SLA", "IRA"]  # proper rotations: left/right cannot be told from anatomy


def _scan(data_dir, name, step):
    path = data_dir / name
    if not path.exists():
        pytest.skip(f"{path} not in the data folder")
    ct = pvcmf.read_ct(path)
    vol = volume(ct)[::step, ::step, ::step]
    return image_of(vol, np.asarray(ct.spacing) * step)


@pytest.fixture(scope="module", params=["vhp_female_head", "vhp_male_head"])
def vhp(request, data_dir):
    return _scan(data_dir, request.param, 2)


@pytest.fixture(scope="module")
def headsq_raw(data_dir):
    return _scan(data_dir, "headsq/quarter.nhdr", 1)


def test_vhp_read_in_hu_and_patient_frame(vhp):
    """The DICOM series is in HU with face +y and vertex +z: standardize changes nothing."""
    out, report = standardize(vhp)
    assert report["units"]["units"] == "hu"
    assert report["orientation"]["code"] == "LAS"
    np.testing.assert_array_equal(out[arrays.CT], vhp[arrays.CT])


@pytest.mark.parametrize("code", TURNS)
def test_vhp_scanner_units_and_turned_axes_come_back(vhp, code):
    out, report = standardize(stored_as(vhp, code, 1000.0))
    assert report["orientation"]["code"] == code and report["units"]["offset"] == -1000.0
    assert out.dimensions == vhp.dimensions
    np.testing.assert_array_equal(out[arrays.CT], vhp[arrays.CT])


def test_headsq_needs_no_hand_offset_or_flip(headsq_raw):
    """headsq is stored in scanner units with the face toward -y and the vertex toward -z."""
    ref, report = standardize(headsq_raw)
    assert report["units"]["units"] == "scanner" and report["orientation"]["code"] == "LPI"
    np.testing.assert_array_equal(
        volume(ref), volume(headsq_raw)[:, ::-1, ::-1] + report["units"]["offset"])
    for code in TURNS:
        out, rep = standardize(stored_as(ref, code, 1024.0))
        assert rep["orientation"]["code"] == code, code
        np.testing.assert_array_equal(out[arrays.CT], ref[arrays.CT])


def test_vhp_written_as_coronal_nifti_in_scanner_units(vhp, tmp_path):
    """A file written by nibabel (coronal slices, RAS affine, scanner units) is read into the
    patient frame by the header and into HU by the histogram."""
    nib = pytest.importorskip("nibabel")
    vol = volume(vhp)[:, :, ::2]  # a lighter copy
    s = np.asarray(vhp.spacing) * [1, 1, 2]
    # file axes: i -> patient right (-x), j -> superior, k -> posterior (-y)
    data = np.transpose(vol, (0, 2, 1))[::-1, :, ::-1] + 1024
    affine = np.zeros((4, 4))
    affine[3, 3] = 1.0
    affine[0, 0], affine[2, 1], affine[1, 2] = s[0], s[2], -s[1]  # RAS: x right, y anterior
    nib.save(nib.Nifti1Image(data.astype(np.int16), affine), tmp_path / "coronal.nii.gz")
    read = pvcmf.read_ct(tmp_path / "coronal.nii.gz")
    out, report = standardize(read)
    assert report["orientation"]["code"] == "LAS" and report["units"]["offset"] == -1024.0
    np.testing.assert_array_equal(volume(out), vol)


def test_cli_simulate_finds_units_and_axes(data_dir, tmp_path, capsys):
    """`pvcmf simulate` on the raw headsq file, no --offset and no --flip: units and axes
    are found and written to summary.json; a bad --orient is a usage error."""
    import json
    from pathlib import Path

    from pvcmf.cli import main

    nhdr = data_dir / "headsq" / "quarter.nhdr"
    if not nhdr.is_file():
        pytest.skip(f"{nhdr} not in the data folder")
    plan = Path(__file__).resolve().parents[1] / "examples" / "headsq_plan.toml"
    code = main(["simulate", "--ct", str(nhdr), "--plan", str(plan), "--out", str(tmp_path),
                 "--no-progress", "--no-predict", "--no-figures"])
    assert code == 0, capsys.readouterr()
    ct = json.loads((tmp_path / "summary.json").read_text())["ct"]
    assert ct["units"]["units"] == "scanner" and ct["orientation"]["code"] == "LPI"
    assert "left/right taken from the file" in ct["orientation"]["left_right"]
    with pytest.raises(SystemExit) as info:  # refused by the argument parser
        main(["simulate", "--ct", str(nhdr), "--plan", str(plan), "--out",
              str(tmp_path / "bad"), "--no-progress", "--no-predict", "--orient", "XYZ"])
    assert info.value.code == 2 and "3-letter code" in capsys.readouterr().err
