"""Grey values that are not Hounsfield units: a scale as well as an offset (pvcmf.io.units).

A cone-beam CT's grey values are often not HU: its air and soft-tissue peaks lie closer
together or farther apart than a CT's 1040. ``units='rescale'`` maps the two peaks to -1000
and +40 HU by a line; ``'auto'`` refuses peaks that are not a CT's distance apart (an MR
volume shows two peaks too) and names ``'rescale'``. The virtual patient (HU) stored with a
scale and an offset must come back; so must the segmentation of a real scan.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays
from pvcmf.cli import build_parser
from pvcmf.filters.orientation import check_units, standardize
from pvcmf.io.units import AIR_HU, FILL_SHARE, SOFT_HU
from pvcmf.plan import Osteotomy, Plan

from ct_helpers import image_of


@pytest.fixture(scope="module")
def head():
    ct = pvcmf.datasets.phantom(patient=1, spacing=3.0).ct.copy()
    ct[arrays.CT] = np.round(ct[arrays.CT])
    return ct


def _scaled(image, slope, offset):
    """``image`` stored as ``slope * HU + offset`` (the grey values of another device)."""
    out = image.copy()
    out[arrays.CT] = (slope * np.asarray(image[arrays.CT], dtype=np.float64)
                      + offset).astype(np.float32)
    return out


@pytest.mark.parametrize("slope, offset", [(0.5, -500.0), (1.8, 0.0), (0.7, 1000.0)])
def test_rescale_gives_the_hu_back(head, slope, offset):
    """The line through the peaks undoes the device's line: every voxel within a few HU of
    the original (the peaks are found on a histogram of bins a few grey values wide)."""
    out, report = check_units(_scaled(head, slope, offset), units="rescale")
    assert report["units"] == "rescaled"
    assert report["slope"] == pytest.approx(1.0 / slope, rel=0.01)
    hu = np.asarray(head[arrays.CT], dtype=float)
    back = np.asarray(out[arrays.CT], dtype=float)
    for level in (AIR_HU, SOFT_HU):  # the two peaks land on their HU
        at = np.abs(hu - level) < 1
        assert np.abs(back[at] - level).max() < 12
    soft = np.abs(hu) < 300  # within the peaks' span: the line's error is a few HU
    assert np.abs(back[soft] - hu[soft]).max() < 12
    assert np.abs(back - hu).max() < 0.01 * np.ptp(hu) + 12


@pytest.mark.parametrize("slope", [0.5, 1.8])
def test_auto_refuses_peaks_not_a_ct_apart_and_names_rescale(head, slope):
    with pytest.raises(ValueError, match=r"not a CT.*apart in a CT.*units='rescale'"):
        check_units(_scaled(head, slope, -200.0))
    with pytest.raises(ValueError, match=r"units='rescale'"):
        check_units(_scaled(head, slope, -200.0), units="hu")


def test_auto_within_a_ct_span_says_rescale_where_the_scale_is_off(head, caplog):
    """Peaks 700 apart still pass 'auto' (an offset only: the segmentation places its
    levels on the image's own peaks), and the report says how to map the scale too."""
    with caplog.at_level(logging.WARNING, logger="pvcmf.io.orientation"):
        _, report = check_units(_scaled(head, 0.67, 300.0))
    assert report["units"] == "scanner" and report["slope"] == 1.0
    assert "units='rescale'" in report["how"] and "units='rescale'" in caplog.text
    _, plain = check_units(_scaled(head, 1.0, 1000.0))
    assert "rescale" not in plain["how"]


def test_rescale_still_asks_for_bone_and_a_head():
    """'rescale' asks the bone tail only (the user says the image is a CT): a volume without
    one is refused; an MR-like volume, whose peaks 'auto' refuses, is refused as no head."""
    flat = np.where(np.sqrt(((np.indices((40, 40, 40)) - 19.5) ** 2).sum(axis=0)) < 16,
                    300.0, 0.0)
    with pytest.raises(ValueError, match="not a CT of a body part with bone"):
        check_units(image_of(flat + np.random.default_rng(0).normal(0, 5, flat.shape)),
                    units="rescale")
    g = np.indices((40, 40, 40)).astype(float) - 19.5
    r = np.sqrt((g ** 2).sum(axis=0))
    mr = np.where(r < 16, 400.0 + 15.0 * g[2], 0.0) + np.random.default_rng(0).normal(0, 5, r.shape)
    with pytest.raises(ValueError, match="not a CT"):
        check_units(image_of(mr))
    with pytest.raises(ValueError, match="not a head CT"):
        standardize(image_of(mr), units="rescale")


@pytest.mark.parametrize("bad", ["kelvin", float("nan"), True, None, [1.0]])
def test_bad_units_named(head, bad):
    with pytest.raises(ValueError, match="units must be"):
        check_units(head, bad)


def test_cli_takes_rescale():
    args = build_parser().parse_args(["simulate", "--ct", "scan", "--plan", "p.toml",
                                      "--out", "out", "--units", "Rescale"])
    assert args.units == "rescale"


def _female_folder():
    root = Path(os.environ.get("PVCMF_DATA_DIR", Path(__file__).parents[1] / ".." / "shared"
                               / "data"))
    folder = root / "vhp_female_head"
    if not folder.is_dir():
        pytest.skip(f"{folder} not found (set PVCMF_DATA_DIR to the real-data folder)")
    return folder


def _female_2mm():
    return pvcmf.filters.working_grid(pvcmf.read_ct(_female_folder(), frame="patient"), 2.0)


def test_a_real_scan_with_cone_beam_grey_values_segments_as_in_hu():
    """The Visible Human female (2 mm blocks) stored at half the HU scale:
    'auto' rescales it (its DICOM header says CT; without one, 'rescale' does), to the
    same values as the scan in HU rescaled (the line through its own peaks: its air lies
    at -1024), and the same head, tissues and jaws as the scan in HU."""
    ct = _female_2mm()
    device = _scaled(ct, 0.5, -480.0)
    ref, ref_report = standardize(ct)
    assert ref_report["units"]["units"] == "hu"
    out, report = standardize(device)
    assert report["units"]["units"] == "rescaled"
    assert report["orientation"]["code"] == ref_report["orientation"]["code"]
    own = np.asarray(check_units(ct, units="rescale")[0][arrays.CT])
    assert np.median(np.abs(np.asarray(out[arrays.CT]) - own)) < 10
    jaws = [pvcmf.filters.find_jaws(pvcmf.filters.segment(img, check=False))
            for img in (ref, out)]
    for name, label in ((arrays.TISSUE, arrays.INTRACRANIAL), (arrays.TISSUE, arrays.TEETH),
                        (arrays.BONE, arrays.MANDIBLE), (arrays.BONE, arrays.MAXILLA)):
        a, b = (np.asarray(j[name]) == label for j in jaws)
        assert a.sum() > 0
        dice = 2 * (a & b).sum() / (a.sum() + b.sum())
        assert dice > 0.97, (name, label, dice)


def _series_copy(folder, dst, count, **header):
    """``count`` slices of the DICOM series ``folder`` from its middle, with ``header``'s
    values set (the stored pixels unchanged)."""
    import pydicom

    files = sorted(folder.glob("*.dcm"))
    mid = len(files) // 2
    dst.mkdir()
    for path in files[mid - count // 2: mid - count // 2 + count]:
        ds = pydicom.dcmread(path)
        for key, value in header.items():
            setattr(ds, key, value(ds) if callable(value) else value)
        ds.save_as(dst / path.name)
    return dst


def test_a_dicom_ct_series_with_cone_beam_grey_values_is_rescaled_by_auto(tmp_path):
    """A DICOM series whose header says CT is a CT: 'auto' maps its grey values whatever
    their scale (the female's slices with a rescale slope and intercept that store
    0.5 * HU - 480); one whose header says MR is refused whatever ``units`` says."""
    folder = _female_folder()
    hu = pvcmf.read_ct(_series_copy(folder, tmp_path / "hu", 40), frame="patient")
    assert hu.field_data[arrays.MODALITY].tolist() == ["CT"]
    device = pvcmf.read_ct(_series_copy(
        folder, tmp_path / "cbct", 40,
        RescaleSlope=lambda ds: 0.5 * float(ds.RescaleSlope),
        RescaleIntercept=lambda ds: 0.5 * float(ds.RescaleIntercept) - 480.0), frame="patient")
    out, report = check_units(device)
    assert report["units"] == "rescaled" and report["modality"] == "CT"
    assert "DICOM Modality CT" in report["how"]
    own = np.asarray(check_units(hu, units="rescale")[0][arrays.CT])
    assert np.median(np.abs(np.asarray(out[arrays.CT]) - own)) < 10
    without = device.copy()
    without.field_data.clear()
    with pytest.raises(ValueError, match="units='rescale'"):
        check_units(without)  # no header to say it is a CT: refused, 'rescale' named
    mr = pvcmf.read_ct(_series_copy(folder, tmp_path / "mr", 40, Modality="MR"))
    for units in ("auto", "hu", "rescale", -1000.0):
        with pytest.raises(ValueError, match="DICOM MR series.*not a CT"):
            check_units(mr, units)


def test_simulate_checks_a_ct_as_read_ct_returned_it(head, tmp_path, monkeypatch):
    """A CT given in memory as read_ct returned it (field ``source_path``) has its units and
    axes checked as one read from a path; a CT standardize returned, or a virtual
    patient, is not checked again; given units win."""
    from pvcmf import pipeline, scan_steps

    path = tmp_path / "scan.vti"
    head.save(path)
    ct = pvcmf.read_ct(path)
    assert ct.field_data[arrays.SOURCE_PATH].tolist() == [str(path)]
    calls = []

    def fake_standardize(image, **options):
        calls.append(options)
        raise SystemExit(0)

    monkeypatch.setattr(scan_steps, "standardize", fake_standardize)
    plan = Plan((Osteotomy("maxilla", translation=(0, 2, 0)),))
    for kwargs, expected in (({}, {"units": "auto", "orient": "auto"}),
                             ({"units": "rescale"}, {"units": "rescale", "orient": "auto"})):
        with pytest.raises(SystemExit):
            pipeline.simulate(ct, plan, working_spacing=None, **kwargs)
        assert calls[-1] == expected
    checked, _ = standardize(ct)
    assert arrays.SOURCE_PATH not in checked.field_data
    monkeypatch.setattr(pipeline, "_label_steps", lambda *a, **k: (_ for _ in ()).throw(
        SystemExit(1)))
    for image in (checked, head):
        with pytest.raises(SystemExit):
            pipeline.simulate(image, plan, working_spacing=None)
    assert len(calls) == 2


# --------------------------------------------------------------------------- fills
def _with_fill(ct, value, radius=110.0):
    """``ct`` with everything outside a vertical cylinder of ``radius`` mm about its centre
    set to the constant ``value``: the outside of a cone-beam scanner's round field."""
    x, y, _ = (np.asarray(ct.points) - np.asarray(ct.center)).T
    out = ct.copy()
    out[arrays.CT] = np.where(x**2 + y**2 > radius**2, value,
                              np.asarray(ct[arrays.CT])).astype(np.float32)
    return out


@pytest.mark.parametrize("value", [0.0, -600.0, 1000.0, -3000.0])
def test_a_constant_fill_outside_the_field_reads_as_air(head, value):
    """Whatever constant a scanner writes outside its field (between air and soft tissue,
    above soft tissue, far below air), the peaks, the units and the head come out as with
    that outside at air."""
    ref_img, ref = standardize(_with_fill(head, -1000.0))
    out, report = standardize(_with_fill(head, value))
    units = report["units"]
    assert units["fill"]["value"] == value and units["fill"]["share"] > FILL_SHARE
    assert abs(units["air_peak"] - ref["units"]["air_peak"]) < 15.0
    assert abs(units["soft_peak"] - ref["units"]["soft_peak"]) < 15.0
    assert units["offset"] == ref["units"]["offset"] and report["orientation"]["code"] == "LAS"
    labels, ref_labels = out.cmf.segment(), ref_img.cmf.segment()
    same = np.mean(np.asarray(labels[arrays.TISSUE]) == np.asarray(ref_labels[arrays.TISSUE]))
    assert same > 0.99


@pytest.mark.parametrize("noise", [60.0, 100.0])
def test_the_lowest_value_outside_a_noisy_field_is_a_fill(head, noise):
    """A noisy field whose outside is written as its lowest value: the air's far tail
    reaches down to it (no gap), yet it is a fill. Taken for the air peak, it would set the
    scale 4-5 noise widths below air and lose the teeth."""
    rng = np.random.default_rng(3)
    noisy = head.copy()
    noisy[arrays.CT] = np.round(np.asarray(head[arrays.CT])
                                + rng.normal(0.0, noise, head.n_points)).astype(np.float32)
    inside = np.asarray(_with_fill(noisy, np.nan)[arrays.CT])
    low = float(np.nanmin(inside))
    _, ref = check_units(_with_fill(noisy, -1000.0))
    _, report = check_units(_with_fill(noisy, low))
    assert report["fill"]["value"] == low
    tolerance = 0.25 * noise  # the peaks of a noisy histogram move by a share of the noise
    assert abs(report["air_peak"] - ref["air_peak"]) < tolerance
    assert abs(report["soft_peak"] - ref["soft_peak"]) < tolerance


def test_the_lowest_value_reached_by_noisy_air_is_a_fill(head):
    """The image clipped at its lowest value, which the outside of the field holds too,
    three noise widths below a noisy air: the air's tail reaches it, yet it is a fill
    (taken for air it lies 15 % of the air to soft-tissue step below the air's peak)."""
    rng = np.random.default_rng(4)
    img = head.copy()
    img[arrays.CT] = np.maximum(np.round(np.asarray(head[arrays.CT])
                                         + rng.normal(0.0, 60.0, head.n_points)), -1180.0)
    _, report = check_units(_with_fill(img, -1180.0))
    assert report["fill"]["value"] == -1180.0
    assert abs(report["air_peak"] + 1000.0) < 15.0


def test_padding_just_below_a_quiet_air_is_air_enough(head):
    """A scanner's padding 50 HU below a quiet air, a few voxels between them (partial
    volume at the field's edge): taken for air it lies 5 % of the step below the air's
    peak, within FILL_SHIFT, so it stays (as the Visible Human female's -1024 HU padding
    below her air at -948)."""
    rng = np.random.default_rng(5)
    v = np.round(np.asarray(head[arrays.CT], dtype=float))
    air = v < -900
    v[air] = np.round(-1000.0 + 0.2 * (v[air] + 1000.0))  # a quiet air
    edge = rng.random(v.size) < 5e-4
    v[edge] = np.round(rng.uniform(-1049.0, -1000.0, edge.sum()))
    img = head.copy()
    img[arrays.CT] = v.astype(np.float32)
    _, report = check_units(_with_fill(img, -1050.0))
    assert "fill" not in report, report
    assert report["air_peak"] < -1040.0


def test_clipped_air_is_not_a_fill(head):
    """Air clipped at the scanner's lowest value, next to the air's other values, stays."""
    clipped = head.copy()
    clipped[arrays.CT] = np.maximum(np.asarray(head[arrays.CT]), -1000.0).astype(np.float32)
    _, report = check_units(clipped)
    assert "fill" not in report
