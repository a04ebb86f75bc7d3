"""DICOM series as PACS and CD exports deliver them: compressed pixel data (JPEG Lossless,
JPEG 2000), lossy compression marked in the header, nested folders of extension-less
files beside a DICOMDIR, and Enhanced CT multi-frame files (the whole stack in one file,
its geometry in functional groups).

The exports are made from uncompressed series (:mod:`dicom_helpers`).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

import pvcmf
from pvcmf import arrays

from dicom_helpers import SYNTAXES, compress_enhanced, compress_folder, enhanced_from_slices
from test_io import DIMS, ORIGIN, SPACING, known_values, write_dicom_series

pydicom = pytest.importorskip("pydicom")


def write_series(folder, raw, **options):
    folder.mkdir(parents=True, exist_ok=True)
    write_dicom_series(folder, raw, SPACING, ORIGIN, **options)


def pydicom_decodes(path):
    try:
        pydicom.dcmread(path).pixel_array
    except Exception:  # noqa: BLE001 - any decoder failure
        return False
    return True


@pytest.mark.parametrize("compressor", sorted(SYNTAXES))
def test_compressed_series_reads_as_its_original(tmp_path, compressor, caplog):
    raw = known_values()
    write_series(tmp_path / "plain", raw, slope=2.0, intercept=-1024.0)
    compress_folder(tmp_path / "plain", tmp_path / "packed", compressor)
    with caplog.at_level("INFO", logger="pvcmf"):
        packed = pvcmf.read_ct(tmp_path / "packed")
    plain = pvcmf.read_ct(tmp_path / "plain")
    assert packed.dimensions == DIMS
    np.testing.assert_array_equal(packed[arrays.CT], plain[arrays.CT])
    np.testing.assert_array_equal(np.sort(plain[arrays.CT]),
                                  np.sort(2.0 * raw.ravel().astype(float) - 1024.0))
    first = next((tmp_path / "packed").glob("*.dcm"))
    gdcm = "decoded by GDCM" in caplog.text
    assert gdcm == (not pydicom_decodes(first)), caplog.text


def test_jpeg_lossless_is_decoded_without_a_pydicom_plugin(tmp_path, monkeypatch):
    """JPEG Lossless (process 14), the usual PACS export, read where pydicom has no decoder
    for it (as in a plain ``pip install pvcmf``): GDCM decodes it."""
    write_series(tmp_path / "plain", known_values())
    compress_folder(tmp_path / "plain", tmp_path / "packed", "JPEG")

    def no_decoder(self):
        raise RuntimeError(f"no plugin for {self.file_meta.TransferSyntaxUID.name}")

    plain = pvcmf.read_ct(tmp_path / "plain")
    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(no_decoder))
    packed = pvcmf.read_ct(tmp_path / "packed")
    np.testing.assert_array_equal(packed[arrays.CT], plain[arrays.CT])
    with pytest.raises(ValueError, match="cannot decode DICOM pixel data of .*IM"):
        pvcmf.read_ct(tmp_path / "plain")  # uncompressed data pydicom fails on: no fallback


def test_undecodable_compressed_slice_is_named(tmp_path):
    write_series(tmp_path / "plain", known_values(), extra_file=False)
    compress_folder(tmp_path / "plain", tmp_path / "packed", "JPEG")
    victim = sorted((tmp_path / "packed").glob("*.dcm"))[2]
    ds = pydicom.dcmread(victim)
    ds.PixelData = ds.PixelData[:40]  # the stream cut short
    ds["PixelData"].is_undefined_length = True
    ds.save_as(victim, enforce_file_format=True)
    with pytest.raises(ValueError, match=f"{victim.name}.*JPEG Lossless"):
        pvcmf.read_ct(tmp_path / "packed")


def test_lossy_compressed_series_is_warned(tmp_path, caplog):
    write_dicom_series(tmp_path, known_values(), SPACING, ORIGIN, extra_file=False)
    for path in sorted(tmp_path.glob("*.dcm"))[:3]:
        ds = pydicom.dcmread(path)
        ds.LossyImageCompression, ds.LossyImageCompressionRatio = "01", "8.5"
        ds.save_as(path, enforce_file_format=True)
    with caplog.at_level("WARNING"):
        pvcmf.read_ct(tmp_path)
    assert "3 of 7 slices are marked lossy compressed (ratio 8.5)" in caplog.text


def test_nested_export_folder(tmp_path, caplog):
    """A CD export: DICOMDIR at the root, series in nested folders, files without suffix."""
    raw = known_values()
    series = tmp_path / "DICOM" / "ST000000" / "SE000001"
    scout = tmp_path / "DICOM" / "ST000000" / "SE000000"
    for folder, vol, name in ((series, raw, "head 1.0 H30s"), (scout, raw[:, :, :3], "scout")):
        folder.mkdir(parents=True)
        write_dicom_series(folder, vol, SPACING, ORIGIN, description=name, extra_file=False)
        for k, path in enumerate(sorted(folder.glob("*.dcm"))):
            path.rename(folder / f"IM{k:06d}")
    (tmp_path / "DICOMDIR").write_bytes(b"\0" * 128 + b"DICM")  # a directory record, no image
    with caplog.at_level("WARNING"):
        out = pvcmf.read_ct(tmp_path)
    reference = pvcmf.read_ct(series)
    assert out.dimensions == DIMS
    np.testing.assert_array_equal(out[arrays.CT], reference[arrays.CT])
    assert "2 DICOM series" in caplog.text
    assert "'scout'" in caplog.text and "SE000000" in caplog.text
    assert pvcmf.read_ct(tmp_path, series="scout").dimensions == DIMS[:2] + (3,)


def test_folder_without_images_in_any_subfolder(tmp_path):
    (tmp_path / "a" / "b").mkdir(parents=True)
    (tmp_path / "a" / "b" / "notes.txt").write_text("no images here")
    with pytest.raises(ValueError, match="no readable DICOM image slice, nor do its subfolders"):
        pvcmf.read_ct(tmp_path)


def test_real_scan_exported_as_jpeg_lossless(data_dir, tmp_path):
    """Forty slices of the female head CT, compressed as a PACS exports them, read back to
    the same HU as the uncompressed files."""
    src = data_dir / "vhp_female_head"
    files = sorted(src.glob("*.dcm"))
    if len(files) < 200:
        pytest.skip(f"{src} not in the data folder")
    plain = tmp_path / "plain"
    plain.mkdir()
    for path in files[150:190]:  # the teeth and the jaws: bone, enamel and air
        shutil.copy(path, plain / path.name)
    compress_folder(plain, tmp_path / "packed", "JPEG")
    packed = pvcmf.read_ct(tmp_path / "packed")
    reference = pvcmf.read_ct(plain)
    assert packed.dimensions == reference.dimensions and packed.dimensions[2] == 40
    np.testing.assert_array_equal(packed[arrays.CT], reference[arrays.CT])
    assert np.ptp(reference[arrays.CT]) > 2000  # air to enamel: the data is not trivial


@pytest.mark.parametrize("per_frame_rescale", [False, True])
def test_enhanced_multiframe_ct_reads_as_its_slices(tmp_path, per_frame_rescale):
    raw = known_values()
    write_series(tmp_path / "plain", raw, slope=2.0, intercept=-1024.0, extra_file=False)
    paths = sorted((tmp_path / "plain").glob("*.dcm"))
    if per_frame_rescale:  # each frame its own rescale: the stored values differ per frame
        for k, path in enumerate(paths):
            ds = pydicom.dcmread(path)
            ds.RescaleIntercept = -1024.0 + 10 * k
            ds.save_as(path, enforce_file_format=True)
    (tmp_path / "multi").mkdir()
    order = np.random.default_rng(3).permutation(len(paths))  # frames not in slice order
    enhanced_from_slices(paths, tmp_path / "multi" / "ct.dcm", order=order,
                         per_frame_rescale=per_frame_rescale)
    multi, plain = pvcmf.read_ct(tmp_path / "multi"), pvcmf.read_ct(tmp_path / "plain")
    assert multi.dimensions == DIMS
    np.testing.assert_allclose(multi.origin, plain.origin)
    np.testing.assert_allclose(multi.spacing, SPACING)
    np.testing.assert_array_equal(multi[arrays.CT], plain[arrays.CT])
    assert len(np.unique(plain[arrays.CT])) == raw.size  # every voxel told apart


def test_enhanced_multiframe_without_geometry_is_not_an_image(tmp_path):
    write_series(tmp_path / "plain", known_values(), extra_file=False)
    (tmp_path / "multi").mkdir()
    enhanced_from_slices(sorted((tmp_path / "plain").glob("*.dcm")), tmp_path / "multi" / "a")
    ds = pydicom.dcmread(tmp_path / "multi" / "a")
    del ds.PerFrameFunctionalGroupsSequence[2].PlanePositionSequence
    ds.save_as(tmp_path / "multi" / "a", enforce_file_format=True)
    with pytest.raises(ValueError, match="no readable DICOM image slice"):
        pvcmf.read_ct(tmp_path / "multi")


def test_enhanced_multiframe_pydicom_cannot_decode_is_named(tmp_path, monkeypatch):
    write_series(tmp_path / "plain", known_values(), extra_file=False)
    (tmp_path / "multi").mkdir()
    enhanced_from_slices(sorted((tmp_path / "plain").glob("*.dcm")), tmp_path / "multi" / "a")

    def no_decoder(self):
        raise RuntimeError("no plugin")

    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(no_decoder))
    with pytest.raises(ValueError, match="multi-frame file .*/a'"):
        pvcmf.read_ct(tmp_path / "multi")


def no_pydicom_decoder(monkeypatch):
    def no_decoder(self):
        raise RuntimeError(f"no plugin for {self.file_meta.TransferSyntaxUID.name}")

    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(no_decoder))


def test_enhanced_multiframe_jpeg_lossless_decoded_by_gdcm(tmp_path, monkeypatch):
    write_series(tmp_path / "plain", known_values(), slope=2.0, intercept=-1024.0,
                 extra_file=False)
    paths = sorted((tmp_path / "plain").glob("*.dcm"))
    (tmp_path / "multi").mkdir()
    compress_enhanced(paths, tmp_path / "multi" / "ct", tmp_path,
                      order=np.random.default_rng(5).permutation(len(paths)))
    plain = pvcmf.read_ct(tmp_path / "plain")
    no_pydicom_decoder(monkeypatch)
    multi = pvcmf.read_ct(tmp_path / "multi")
    np.testing.assert_array_equal(multi[arrays.CT], plain[arrays.CT])


def test_enhanced_multiframe_gdcm_cannot_rescale_per_frame(tmp_path, monkeypatch):
    """GDCM applies one rescale to every frame: frames with their own are refused."""
    write_series(tmp_path / "plain", known_values(), extra_file=False)
    paths = sorted((tmp_path / "plain").glob("*.dcm"))
    (tmp_path / "multi").mkdir()
    compress_enhanced(paths, tmp_path / "multi" / "ct", tmp_path, per_frame_rescale=True)
    ds = pydicom.dcmread(tmp_path / "multi" / "ct")
    ds.PerFrameFunctionalGroupsSequence[1].PixelValueTransformationSequence[0] \
        .RescaleIntercept = -1000.0
    ds.save_as(tmp_path / "multi" / "ct", enforce_file_format=True)
    no_pydicom_decoder(monkeypatch)
    with pytest.raises(ValueError, match="JPEG Lossless.*multi-frame.*pip install pylibjpeg"):
        pvcmf.read_ct(tmp_path / "multi")


def test_real_scan_as_enhanced_multiframe(data_dir, tmp_path):
    """Forty slices of the female head CT as one Enhanced CT file read as the slices do."""
    files = sorted((data_dir / "vhp_female_head").glob("*.dcm"))
    if len(files) < 200:
        pytest.skip("vhp_female_head not in the data folder")
    (tmp_path / "multi").mkdir()
    enhanced_from_slices(files[150:190], tmp_path / "multi" / "IM1",
                         order=np.random.default_rng(0).permutation(40))
    plain = tmp_path / "plain"
    plain.mkdir()
    for path in files[150:190]:
        shutil.copy(path, plain / path.name)
    multi, reference = pvcmf.read_ct(tmp_path / "multi"), pvcmf.read_ct(plain)
    assert multi.dimensions == reference.dimensions
    np.testing.assert_allclose(multi.origin, reference.origin)
    np.testing.assert_array_equal(multi[arrays.CT], reference[arrays.CT])


def test_localizer_in_the_series_is_left_out(tmp_path, caplog):
    """A lateral localizer filed under the axial series' UID: read without it, warned."""
    raw = known_values()
    write_series(tmp_path, raw, extra_file=False)
    ds = pydicom.dcmread(sorted(tmp_path.glob("*.dcm"))[0])
    ds.ImageOrientationPatient = [0.0, 1.0, 0.0, 0.0, 0.0, -1.0]  # sagittal
    ds.Rows, ds.Columns = 5, 8
    ds.PixelData = np.arange(40, dtype="<i2").tobytes()
    ds.ImagePositionPatient = [0.0, -100.0, 100.0]
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = pydicom.uid.generate_uid()
    ds.save_as(tmp_path / "localizer.dcm", enforce_file_format=True)
    with caplog.at_level("WARNING"):
        out = pvcmf.read_ct(tmp_path)
    assert out.dimensions == DIMS
    np.testing.assert_array_equal(out[arrays.CT], pvcmf.read_ct(tmp_path, series="CT")[arrays.CT])
    assert "leaving out 1 of orientation [0.0, 1.0, 0.0, 0.0, 0.0, -1.0], 5x8 pixels" \
        in caplog.text
    (tmp_path / "localizer.dcm").unlink()
    np.testing.assert_array_equal(pvcmf.read_ct(tmp_path)[arrays.CT], out[arrays.CT])


def test_a_series_exported_twice_is_read_once(tmp_path, caplog):
    """The same images in two folders of an export (the same SOPInstanceUIDs): read once."""
    export = tmp_path / "export"
    write_series(export / "SE1", known_values(), extra_file=False)
    shutil.copytree(export / "SE1", export / "backup" / "SE1")
    with caplog.at_level("WARNING"):
        out = pvcmf.read_ct(export)
    assert "7 copies of images already found" in caplog.text
    np.testing.assert_array_equal(out[arrays.CT], pvcmf.read_ct(export / "SE1")[arrays.CT])
    (tmp_path / "multi").mkdir()  # a multi-frame file copied: its frames read once too
    enhanced_from_slices(sorted((export / "SE1").glob("*.dcm")), tmp_path / "multi" / "a")
    shutil.copy(tmp_path / "multi" / "a", tmp_path / "multi" / "b")
    caplog.clear()
    with caplog.at_level("WARNING"):
        multi = pvcmf.read_ct(tmp_path / "multi")
    assert "7 copies of images already found" in caplog.text
    np.testing.assert_array_equal(multi[arrays.CT], out[arrays.CT])


def test_series_on_the_command_line(tmp_path, monkeypatch):
    """``--series`` reaches read_ct from ``pvcmf simulate`` and ``pvcmf plan``."""
    import pvcmf.cli as cli
    from pvcmf.planner import app

    seen = []

    def fake_read(path, **options):
        seen.append(options.get("series"))
        raise SystemExit(0)

    monkeypatch.setattr(cli, "read_ct", fake_read)
    plan = tmp_path / "plan.toml"
    plan.write_text('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [0, 0, 3]\n')
    with pytest.raises(SystemExit):
        cli.main(["simulate", "--ct", str(tmp_path), "--plan", str(plan), "--out",
                  str(tmp_path / "out"), "--series", "bone kernel", "--no-progress"])
    monkeypatch.setattr(pvcmf.io, "read_ct", fake_read)
    args = cli.build_parser().parse_args(["plan", "--ct", str(tmp_path), "--series", "3"])
    with pytest.raises(SystemExit):
        app._load_ct(args)
    assert seen == ["bone kernel", "3"]


def test_series_of_a_file_is_refused(tmp_path):
    (tmp_path / "a.nii").write_bytes(b"")
    with pytest.raises(ValueError, match="series='2' picks a series of a DICOM folder"):
        pvcmf.read_ct(tmp_path / "a.nii", series="2")
