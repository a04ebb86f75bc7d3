"""read_ct: every format round-trips a known volume (values, voxel order, geometry); bad
paths and corrupt files raise clear errors; headsq loads from the shared data folder."""

from __future__ import annotations

import functools
import gzip

import numpy as np
import pytest
import pyvista as pv
import vtk

import pvcmf
from pvcmf import arrays

#: the file's own geometry (read_ct's default is the patient frame)
read_file = functools.partial(pvcmf.read_ct, frame="file")

DIMS = (12, 9, 7)  # x, y, z: all different so a transposed read cannot pass
SPACING = (0.5, 0.8, 2.0)
ORIGIN = (10.0, -20.0, 30.0)
# a rotation (det +1) that is not a permutation-free identity: x->y, y->-x
ROTATION = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def known_values():
    """int16 volume whose value encodes its (i, j, k) index, x fastest (VTK point order)."""
    i, j, k = np.meshgrid(*(np.arange(n) for n in DIMS), indexing="ij")
    return (i + 20 * j + 200 * k - 700).astype(np.int16)  # (nx, ny, nz)


def flat(vol):
    return vol.ravel(order="F")


def check(image, values, *, origin=ORIGIN, spacing=SPACING, direction=np.eye(3)):
    assert isinstance(image, pv.ImageData)
    assert image.dimensions == DIMS
    np.testing.assert_allclose(image.spacing, spacing, rtol=1e-6)
    np.testing.assert_allclose(image.origin, origin, atol=1e-5)
    np.testing.assert_allclose(image.direction_matrix, direction, atol=1e-6)
    ct = arrays.require_array(image, arrays.CT, "point", dtype=np.float32)
    np.testing.assert_allclose(ct, flat(values).astype(np.float32), atol=1e-3)


# --------------------------------------------------------------------------- formats
def test_vti_roundtrip_with_direction(tmp_path):
    img = pv.ImageData(dimensions=DIMS, spacing=SPACING, origin=ORIGIN)
    img.direction_matrix = ROTATION
    img["density"] = flat(known_values())
    img.save(tmp_path / "a.vti")
    check(read_file(tmp_path / "a.vti"), known_values(), direction=ROTATION)


def test_offset_and_scale_are_applied(tmp_path):
    img = pv.ImageData(dimensions=DIMS, spacing=SPACING, origin=ORIGIN)
    img["v"] = flat(known_values())
    img.save(tmp_path / "a.vti")
    out = read_file(tmp_path / "a.vti", offset=-1024.0, scale=0.5)
    check(out, 0.5 * known_values().astype(float) - 1024.0)


def test_nifti_roundtrip_qform_and_rescale(tmp_path):
    img = pv.ImageData(dimensions=DIMS, spacing=SPACING)
    img["v"] = flat(known_values())
    qform = vtk.vtkMatrix4x4()
    for r in range(3):
        for c in range(3):
            qform.SetElement(r, c, ROTATION[r, c])
        qform.SetElement(r, 3, ORIGIN[r])
    for name in ("a.nii", "a.nii.gz"):
        writer = vtk.vtkNIFTIImageWriter()
        writer.SetInputData(img)
        writer.SetQFormMatrix(qform)
        writer.SetRescaleSlope(2.0)
        writer.SetRescaleIntercept(-1000.0)
        writer.SetFileName(str(tmp_path / name))
        writer.Write()
        out = read_file(tmp_path / name)
        check(out, 2.0 * known_values().astype(float) - 1000.0, direction=ROTATION)


def test_metaimage_mha_written_by_vtk(tmp_path):
    img = pv.ImageData(dimensions=DIMS, spacing=SPACING, origin=ORIGIN)
    img["v"] = flat(known_values())
    writer = vtk.vtkMetaImageWriter()
    writer.SetInputData(img)
    writer.SetFileName(str(tmp_path / "a.mha"))
    writer.SetCompression(False)
    writer.Write()
    check(read_file(tmp_path / "a.mha"), known_values())


def test_metaimage_mhd_by_hand_with_transform(tmp_path):
    flat(known_values()).astype("<i2").tofile(tmp_path / "a.raw")
    (tmp_path / "a.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        "CompressedData = False\n"
        # MetaIO (as ITK writes it) lists the direction column by column
        f"TransformMatrix = {' '.join(str(v) for v in ROTATION.T.ravel())}\n"
        f"Offset = {' '.join(map(str, ORIGIN))}\n"
        f"ElementSpacing = {' '.join(map(str, SPACING))}\n"
        f"DimSize = {' '.join(map(str, DIMS))}\n"
        "ElementType = MET_SHORT\nElementDataFile = a.raw\n"
    )
    check(read_file(tmp_path / "a.mhd"), known_values(), direction=ROTATION)


def _nrrd_header(extra):
    return (
        "NRRD0004\n# a comment\ntype: short\ndimension: 3\n"
        f"sizes: {' '.join(map(str, DIMS))}\nendian: little\n" + extra
    )


def test_nrrd_detached_header_with_space_directions(tmp_path):
    flat(known_values()).astype("<i2").tofile(tmp_path / "a.raw")
    axes = ROTATION * np.asarray(SPACING)  # columns: index axes in world, scaled by spacing
    dirs = " ".join("(" + ",".join(str(v) for v in axes[:, c]) + ")" for c in range(3))
    (tmp_path / "a.nhdr").write_text(
        _nrrd_header(
            "encoding: raw\nspace: left-posterior-superior\n"
            f"space directions: {dirs}\nspace origin: ({','.join(map(str, ORIGIN))})\n"
            "data file: a.raw\n"
        )
    )
    check(read_file(tmp_path / "a.nhdr"), known_values(), direction=ROTATION)


def test_nrrd_attached_gzip_big_endian(tmp_path):
    payload = gzip.compress(flat(known_values()).astype(">i2").tobytes())
    header = _nrrd_header(f"spacings: {' '.join(map(str, SPACING))}\nencoding: gzip\n")
    header = header.replace("endian: little", "endian: big")
    (tmp_path / "a.nrrd").write_bytes(header.encode() + b"\n" + payload)
    check(read_file(tmp_path / "a.nrrd"), known_values(), origin=(0.0, 0.0, 0.0))


def test_nrrd_one_file_per_slice(tmp_path):
    vol = known_values()
    for k in range(DIMS[2]):
        flat(vol[:, :, k]).astype("<i2").tofile(tmp_path / f"s.{k + 1}")
    (tmp_path / "s.nhdr").write_text(
        _nrrd_header(
            f"spacings: {' '.join(map(str, SPACING))}\nencoding: raw\n"
            f"data file: s.%d 1 {DIMS[2]} 1\n"
        )
    )
    check(read_file(tmp_path / "s.nhdr"), vol, origin=(0.0, 0.0, 0.0))


# --------------------------------------------------------------------------- DICOM
def write_dicom_series(folder, raw, spacing, origin, *, slope=1.0, intercept=-1024.0,
                       row_dir=(1, 0, 0), col_dir=(0, 1, 0), extra_file=True, drift=(0.0, 0.0),
                       description="CT"):
    """Write ``raw`` (nx, ny, nz) as one CT slice file per k, in shuffled file order."""
    pydicom = pytest.importorskip("pydicom")
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    nx, ny, nz = raw.shape
    row_dir, col_dir = np.asarray(row_dir, float), np.asarray(col_dir, float)
    normal = np.cross(row_dir, col_dir)
    series, study, frame = generate_uid(), generate_uid(), generate_uid()
    names = np.random.default_rng(1).permutation(nz)  # file names do not follow z
    for k in range(nz):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID, ds.SOPInstanceUID = CTImageStorage, meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
        ds.PatientName, ds.PatientID = "Virtual^Patient", "0"
        ds.InstanceNumber = int(names[k]) + 1
        ds.SeriesDescription, ds.SeriesNumber = description, 1 + len(description)
        # drift: in-plane shift (mm along rows, columns) per slice, as a tilted gantry makes
        ds.ImagePositionPatient = [float(v) for v in np.asarray(origin) + k * spacing[2] * normal
                                   + k * (drift[0] * row_dir + drift[1] * col_dir)]
        ds.ImageOrientationPatient = [float(v) for v in (*row_dir, *col_dir)]
        ds.PixelSpacing = [float(spacing[1]), float(spacing[0])]  # row spacing, column spacing
        ds.SliceThickness = float(spacing[2])
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleSlope, ds.RescaleIntercept = slope, intercept
        ds.PixelData = np.ascontiguousarray(raw[:, :, k].T.astype("<i2")).tobytes()
        ds.save_as(folder / f"IM{names[k]:04d}.dcm", enforce_file_format=True)
    if extra_file:
        (folder / "DICOMDIR.txt").write_text("not a DICOM file")
    return pydicom


def test_dicom_series_sorted_rescaled_oriented(tmp_path):
    raw = known_values()
    write_dicom_series(tmp_path, raw, SPACING, ORIGIN, slope=2.0, intercept=-1024.0,
                       row_dir=ROTATION[:, 0], col_dir=ROTATION[:, 1])
    out = read_file(tmp_path)
    check(out, 2.0 * raw.astype(float) - 1024.0, direction=ROTATION)
    # an independent check of the geometry: a voxel's world position is its slice position
    k = 3
    p = np.asarray(out.points[np.ravel_multi_index((0, 0, k), DIMS, order="F")])
    np.testing.assert_allclose(p, np.asarray(ORIGIN) + k * SPACING[2] * ROTATION[:, 2], atol=1e-6)


def _positions_by_value(image):
    """World position of every voxel, keyed by its (unique) value."""
    order = np.argsort(image[arrays.CT])
    return image[arrays.CT][order], np.asarray(image.points)[order]


@pytest.mark.parametrize("fmt", ["dicom", "nifti", "nrrd-ras"])
def test_patient_frame(tmp_path, fmt):
    """frame='patient': identity direction, every voxel at its file position mapped to
    (x left, y anterior, z superior): LPS flips y, RAS flips x."""
    raw = known_values()
    if fmt == "dicom":
        write_dicom_series(tmp_path, raw, SPACING, ORIGIN, intercept=0.0,
                           row_dir=ROTATION[:, 0], col_dir=ROTATION[:, 1], extra_file=False)
        path, flip = tmp_path, np.diag([1.0, -1.0, 1.0])
    elif fmt == "nifti":
        img = pv.ImageData(dimensions=DIMS, spacing=SPACING, origin=ORIGIN)
        img.direction_matrix = ROTATION
        img["v"] = flat(raw)
        path, flip = tmp_path / "a.nii.gz", np.diag([-1.0, 1.0, 1.0])
        img.save(path)
    else:
        flat(raw).astype("<i2").tofile(tmp_path / "a.raw")
        axes = ROTATION * np.asarray(SPACING)
        dirs = " ".join("(" + ",".join(str(v) for v in axes[:, c]) + ")" for c in range(3))
        (tmp_path / "a.nhdr").write_text(_nrrd_header(
            "encoding: raw\nspace: right-anterior-superior\n"
            f"space directions: {dirs}\nspace origin: ({','.join(map(str, ORIGIN))})\n"
            "data file: a.raw\n"))
        path, flip = tmp_path / "a.nhdr", np.diag([-1.0, 1.0, 1.0])
    as_file = read_file(path)
    patient = read_file(path, frame="patient")
    np.testing.assert_allclose(patient.direction_matrix, np.eye(3))
    v_file, p_file = _positions_by_value(as_file)
    v_pat, p_pat = _positions_by_value(patient)
    np.testing.assert_array_equal(v_file, v_pat)
    np.testing.assert_allclose(p_pat, p_file @ flip.T, atol=1e-4)
    assert np.all(np.asarray(patient.spacing) > 0)


def test_patient_frame_resamples_oblique_and_takes_unknown_as_patient(tmp_path, caplog):
    c, s_ = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    img = pv.ImageData(dimensions=(20, 20, 6), spacing=(1.0, 1.0, 2.0), origin=(5.0, -3.0, 7.0))
    img.direction_matrix = rot
    vol = np.zeros((20, 20, 6), np.float32)
    vol[12:15, 4:7, 2:5] = 1000.0  # a bright block around voxel (13, 5, 3)
    img["v"] = vol.ravel(order="F")
    img.save(tmp_path / "a.vti")
    with caplog.at_level("WARNING"):
        out = pvcmf.read_ct(tmp_path / "a.vti")
    assert "oblique" in caplog.text
    np.testing.assert_allclose(out.direction_matrix, np.eye(3))
    expected = np.asarray(img.origin) + rot @ (np.array([13, 5, 3]) * img.spacing)
    ct = out[arrays.CT]
    found = (out.points * ct[:, None]).sum(axis=0) / ct.sum()  # centre of the block
    np.testing.assert_allclose(found, expected, atol=0.3)
    with pytest.raises(ValueError, match="frame must be"):
        read_file(tmp_path / "a.vti", frame="RAS")
    flat(known_values()).astype("<i2").tofile(tmp_path / "b.raw")
    (tmp_path / "b.nhdr").write_text(_nrrd_header(
        "encoding: raw\nspace: 3D-left-handed\nspacings: 1 1 1\ndata file: b.raw\n"))
    with caplog.at_level("WARNING"):
        unknown = pvcmf.read_ct(tmp_path / "b.nhdr")
    assert "no anatomical frame" in caplog.text
    np.testing.assert_array_equal(unknown[arrays.CT], read_file(tmp_path / "b.nhdr")[arrays.CT])


def test_dicom_folder_without_images(tmp_path):
    pytest.importorskip("pydicom")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match="no readable DICOM image"):
        read_file(tmp_path)


def _move_slices(pydicom, folder, z_of):
    """Set each slice's z position to ``z_of[its z position]``."""
    for path in folder.glob("*.dcm"):
        ds = pydicom.dcmread(path)
        ds.ImagePositionPatient = [*ds.ImagePositionPatient[:2],
                                   z_of[round(float(ds.ImagePositionPatient[2]), 6)]]
        ds.save_as(path)


def test_dicom_uneven_slices_resampled_onto_the_finest_step(tmp_path, caplog):
    """Slices 1 mm apart, then 2 mm apart (a protocol whose step changes): resampled onto
    1 mm slices with a warning naming the steps; a CT linear along z comes back exactly."""
    z = np.array([0.0, 1.0, 2.0, 3.0, 5.0, 7.0, 9.0, 11.0])
    raw = np.zeros((4, 5, len(z)), np.int16)
    raw += (10 * z).astype(np.int16)[None, None, :] + np.arange(4, dtype=np.int16)[:, None, None]
    pydicom = write_dicom_series(tmp_path, raw, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0),
                                 intercept=0.0, extra_file=False)
    _move_slices(pydicom, tmp_path, dict(zip(np.arange(len(z), dtype=float), z)))
    with caplog.at_level("WARNING"):
        out = read_file(tmp_path)
    assert "uneven slice spacing (steps [1.0, 2.0] mm)" in caplog.text
    assert out.dimensions == (4, 5, 12) and out.spacing[2] == pytest.approx(1.0)
    vol = out[arrays.CT].reshape(out.dimensions, order="F")
    expect = 10 * np.arange(12.0)[None, None, :] + np.arange(4.0)[:, None, None]
    np.testing.assert_allclose(vol, np.broadcast_to(expect, vol.shape), atol=1e-4)


def test_dicom_missing_slice_in_a_changing_step_is_named(tmp_path):
    """A gap of twice the step inside the 2 mm part is missing slices; the change of step
    from 1 to 2 mm is not."""
    z = np.array([0.0, 1.0, 2.0, 3.0, 5.0, 7.0, 11.0, 13.0, 15.0])
    pydicom = write_dicom_series(tmp_path, np.zeros((4, 5, len(z)), np.int16), (1.0, 1.0, 1.0),
                                 (0.0, 0.0, 0.0), extra_file=False)
    _move_slices(pydicom, tmp_path, dict(zip(np.arange(len(z), dtype=float), z)))
    with pytest.raises(ValueError, match=r"misses slices \(gaps along the slice normal at "
                                         r"7.00..11.00 mm;"):
        read_file(tmp_path)


def test_dicom_displaced_slice_resampled(tmp_path, caplog):
    """The first slice 0.3 mm off its place (steps 1.7, 2, 2, ... mm): resampled onto 1.7 mm
    slices from it."""
    pydicom = write_dicom_series(tmp_path, known_values(), SPACING, ORIGIN, extra_file=False)
    z = ORIGIN[2] + SPACING[2] * np.arange(known_values().shape[2])
    _move_slices(pydicom, tmp_path, {**dict(zip(z, z)), ORIGIN[2]: ORIGIN[2] + 0.3})
    with caplog.at_level("WARNING"):
        out = read_file(tmp_path)
    assert "uneven slice spacing" in caplog.text
    assert out.spacing[2] == pytest.approx(SPACING[2] - 0.3)
    assert out.origin[2] == pytest.approx(ORIGIN[2] + 0.3)


# --------------------------------------------------------------------------- errors
def test_missing_path(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist.*DICOM series folder"):
        read_file(tmp_path / "nothing.nii")


def test_unsupported_format_names_path_and_formats(tmp_path):
    path = tmp_path / "scan.png"
    path.write_bytes(b"\x89PNG")
    with pytest.raises(ValueError, match=r"scan\.png.*\.nii\.gz.*\.nhdr.*\.mha.*\.vti"):
        read_file(path)


@pytest.mark.parametrize("name", ["a.nii", "a.nii.gz", "a.mha", "a.vti", "a.nrrd"])
def test_corrupt_file(tmp_path, name):
    path = tmp_path / name
    path.write_bytes(b"this is not an image" * 50)
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')}"):
        read_file(path)


def test_truncated_nifti_and_nrrd(tmp_path):
    img = pv.ImageData(dimensions=DIMS, spacing=SPACING)
    img["v"] = flat(known_values())
    img.save(tmp_path / "a.nii")
    data = (tmp_path / "a.nii").read_bytes()
    (tmp_path / "a.nii").write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="corrupt or unreadable"):
        read_file(tmp_path / "a.nii")
    flat(known_values())[:100].astype("<i2").tofile(tmp_path / "short.raw")
    (tmp_path / "a.nhdr").write_text(
        _nrrd_header("encoding: raw\nspacings: 1 1 1\ndata file: short.raw\n")
    )
    with pytest.raises(ValueError, match="truncated"):
        read_file(tmp_path / "a.nhdr")


@pytest.mark.parametrize("kwargs", [{"scale": 0.0}, {"offset": float("nan")}, {"scale": "x"}])
def test_bad_offset_scale(tmp_path, kwargs):
    with pytest.raises((ValueError, TypeError), match="offset|scale"):
        read_file(tmp_path, **kwargs)


# --------------------------------------------------------------------------- headsq
def test_headsq_from_data_dir(data_dir):
    if not (data_dir / "headsq" / "quarter.nhdr").is_file():
        pytest.skip("headsq not in the data folder")
    raw = read_file(data_dir / "headsq" / "quarter.nhdr")
    ct = pvcmf.datasets.headsq(offset=-1000.0, scale=1.0)
    assert ct.dimensions == (64, 64, 93)
    np.testing.assert_allclose(ct.spacing, (3.2, 3.2, 1.5))
    # the raw slices, read independently with numpy: slice 1 is file quarter.1
    first = np.fromfile(data_dir / "headsq" / "quarter.1", dtype="<i2").reshape(64, 64)
    vol = raw[arrays.CT].reshape(raw.dimensions, order="F")
    np.testing.assert_array_equal(vol[:, :, 0], first.T)
    # headsq is turned to the patient frame (y anterior, z superior) from its anatomy:
    # y and z reversed (the file stores the face toward -y and the vertex toward -z)
    hs = ct[arrays.CT].reshape(ct.dimensions, order="F")
    np.testing.assert_array_equal(hs, vol[:, ::-1, ::-1] - 1000.0)
    # without a hand-given offset the scanner units are found: a CT convention (1000 or
    # 1024) whose soft-tissue peak lands in the soft-tissue range of HU
    d = pvcmf.datasets.headsq()
    diff = np.unique(np.round(d[arrays.CT] - ct[arrays.CT], 3))
    assert diff.size == 1 and diff[0] in (0.0, -24.0)
    from pvcmf.filters.orientation import check_units

    assert -60 < check_units(d, "hu")[1]["soft_peak"] < 100


def test_headsq_download_path_without_network(data_dir, tmp_path, monkeypatch):
    """Without $PVCMF_DATA_DIR, headsq fetches its 94 files with pooch into the cache and
    checks them; here pooch.retrieve is replaced by a copy from the shared folder."""
    import shutil

    import pooch

    src = data_dir / "headsq"
    if not (src / "quarter.nhdr").is_file():
        pytest.skip("headsq not in the data folder")
    calls = []

    def fake_retrieve(url, known_hash, fname, path, progressbar):
        calls.append(url)
        target = tmp_path / "cache" / "headsq" / fname
        assert str(path) == str(target.parent)
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.exists():
            shutil.copy(src / fname, target)
        return str(target)

    monkeypatch.delenv("PVCMF_DATA_DIR")
    monkeypatch.setenv("PVCMF_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(pooch, "retrieve", fake_retrieve)
    ct = pvcmf.datasets.headsq(offset=-1000.0)
    assert len(calls) == 94 and calls[0].endswith("Data/headsq/quarter.nhdr")
    ref = read_file(src / "quarter.nhdr", offset=-1000.0)
    vol = ref[arrays.CT].reshape(ref.dimensions, order="F")[:, ::-1, ::-1]
    np.testing.assert_array_equal(ct[arrays.CT], vol.ravel(order="F"))
    # a corrupted download is refused
    (tmp_path / "cache" / "headsq" / "quarter.7").write_bytes(b"\0" * 8192)
    with pytest.raises(ValueError, match="SHA-256"):
        pvcmf.datasets.headsq()


# --------------------------------------------------------------------------- independent writers
def _patient_position(lps):
    """LPS (ITK, DICOM) -> pvcmf patient frame (x left, y anterior, z superior)."""
    return np.asarray(lps, dtype=float) * np.array([1.0, -1.0, 1.0])


def _sitk_image(direction):
    sitk = pytest.importorskip("SimpleITK")
    vol = known_values()  # (nx, ny, nz); SimpleITK arrays are (z, y, x)
    img = sitk.GetImageFromArray(np.ascontiguousarray(vol.transpose(2, 1, 0)))
    img.SetSpacing(SPACING)
    img.SetOrigin(ORIGIN)
    img.SetDirection(np.asarray(direction, dtype=float).ravel())
    return sitk, img


CORONAL = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # y index -> -z


@pytest.mark.parametrize("suffix", [".mha", ".mhd", ".nii.gz", ".nrrd"])
def test_coronal_written_by_simpleitk_lands_where_itk_says(tmp_path, suffix):
    """Every voxel of a coronal file sits where SimpleITK puts it (LPS -> patient frame)."""
    sitk, img = _sitk_image(CORONAL)
    sitk.WriteImage(img, str(tmp_path / f"a{suffix}"))
    out = pvcmf.read_ct(tmp_path / f"a{suffix}")
    np.testing.assert_allclose(out.direction_matrix, np.eye(3))
    values, positions = _positions_by_value(out)
    vol = known_values()
    for idx in [(0, 0, 0), (11, 8, 6), (3, 5, 2), (7, 1, 4)]:
        expected = _patient_position(img.TransformIndexToPhysicalPoint(idx))
        found = positions[np.searchsorted(values, vol[idx])]
        np.testing.assert_allclose(found, expected, atol=1e-4, err_msg=str(idx))


@pytest.mark.parametrize("suffix", [".mha", ".nii.gz", ".nrrd"])
def test_oblique_written_by_simpleitk_resampled_in_place(tmp_path, suffix):
    """An oblique file is resampled; a bright block keeps its physical centre."""
    sitk = pytest.importorskip("SimpleITK")
    a, b = np.radians(20.0), np.radians(-10.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    direction = rz @ rx
    vol = np.zeros((10, 16, 24), np.int16)  # (z, y, x)
    vol[4:7, 9:12, 5:8] = 1000  # block centred on index (x, y, z) = (6, 10, 5)
    img = sitk.GetImageFromArray(vol)
    img.SetSpacing((1.0, 1.25, 1.5))
    img.SetOrigin((-30.0, 12.0, 100.0))
    img.SetDirection(direction.ravel())
    sitk.WriteImage(img, str(tmp_path / f"a{suffix}"))
    out = pvcmf.read_ct(tmp_path / f"a{suffix}")
    ct = np.asarray(out[arrays.CT], dtype=float)
    centre = (np.asarray(out.points) * ct[:, None]).sum(axis=0) / ct.sum()
    expected = _patient_position(img.TransformContinuousIndexToPhysicalPoint((6.0, 10.0, 5.0)))
    np.testing.assert_allclose(centre, expected, atol=0.35)


def test_nifti_written_by_nibabel_sform_and_qform(tmp_path):
    nib = pytest.importorskip("nibabel")
    vol = known_values()
    affine = np.eye(4)
    affine[:3, :3] = np.array([[0.0, 0.0, -2.0], [-0.5, 0.0, 0.0], [0.0, 0.8, 0.0]])
    affine[:3, 3] = (40.0, 5.0, -60.0)
    for code in ("sform", "qform"):
        img = nib.Nifti1Image(vol, affine)
        if code == "qform":
            img.set_sform(None, code=0)
            img.set_qform(affine, code=1)
        nib.save(img, tmp_path / f"{code}.nii")
        out = pvcmf.read_ct(tmp_path / f"{code}.nii")
        values, positions = _positions_by_value(out)
        for idx in [(0, 0, 0), (11, 8, 6), (2, 7, 3)]:
            ras = affine[:3, :3] @ np.array(idx, float) + affine[:3, 3]
            expected = ras * np.array([-1.0, 1.0, 1.0])  # RAS -> x left
            found = positions[np.searchsorted(values, vol[idx])]
            np.testing.assert_allclose(found, expected, atol=1e-4, err_msg=f"{code} {idx}")


# --------------------------------------------------------------------------- bad geometry
@pytest.mark.parametrize("bad", ["0 1 1", "1 -1 1"])
def test_zero_or_negative_spacing_refused(tmp_path, bad):
    flat(known_values()).astype("<i2").tofile(tmp_path / "a.raw")
    (tmp_path / "a.mhd").write_text(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        f"ElementSpacing = {bad}\nDimSize = {' '.join(map(str, DIMS))}\n"
        "ElementType = MET_SHORT\nElementDataFile = a.raw\n")
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.read_ct(tmp_path / "a.mhd")
    (tmp_path / "a.nhdr").write_text(_nrrd_header(
        f"encoding: raw\nspacings: {bad}\ndata file: a.raw\n"))
    with pytest.raises(ValueError, match="spacing"):
        pvcmf.read_ct(tmp_path / "a.nhdr")


def test_two_dimensional_image_refused(tmp_path):
    nib = pytest.importorskip("nibabel")
    nib.save(nib.Nifti1Image(np.zeros((8, 9), np.int16), np.eye(4)), tmp_path / "a.nii")
    with pytest.raises(ValueError, match="2-D"):
        pvcmf.read_ct(tmp_path / "a.nii")
    raw = known_values()[:, :, :1]
    (tmp_path / "one").mkdir()
    write_dicom_series(tmp_path / "one", raw, SPACING, ORIGIN, extra_file=False)
    with pytest.raises(ValueError, match="2-D"):
        pvcmf.read_ct(tmp_path / "one")


# --------------------------------------------------------------------------- DICOM folders
def test_dicom_picks_largest_ct_series_and_lets_the_user_choose(tmp_path, caplog):
    raw = known_values()
    for name, vol in (("bone kernel", raw), ("scout", raw[:, :, :4] + 5)):
        (tmp_path / name).mkdir()
        write_dicom_series(tmp_path / name, vol, SPACING, ORIGIN, description=name)
        for path in (tmp_path / name).iterdir():
            path.rename(tmp_path / f"{name[0]}{path.name}")
    with caplog.at_level("WARNING"):
        out = pvcmf.read_ct(tmp_path)
    assert out.dimensions == DIMS and "2 DICOM series" in caplog.text and "scout" in caplog.text
    scout = pvcmf.read_ct(tmp_path, series="scout")
    assert scout.dimensions == (12, 9, 4)
    assert float(np.min(scout[arrays.CT])) == float(np.min(out[arrays.CT])) + 5
    with pytest.raises(ValueError, match="matches 0 of the series"):
        pvcmf.read_ct(tmp_path, series="nothing")


def test_dicom_missing_slice_is_named(tmp_path):
    pydicom = write_dicom_series(tmp_path, known_values(), SPACING, ORIGIN)
    for path in tmp_path.glob("*.dcm"):
        if float(pydicom.dcmread(path).ImagePositionPatient[2]) == ORIGIN[2] + 3 * SPACING[2]:
            path.unlink()
    with pytest.raises(ValueError, match="misses slices.*34.00..38.00"):
        pvcmf.read_ct(tmp_path)


def test_dicom_gantry_tilt_resampled(tmp_path, caplog):
    """Slices drifting along the columns (a tilted gantry) are moved back: a structure
    straight along z in the patient stays straight."""
    nx, ny, nz = 16, 20, 8
    spacing, drift = (1.0, 1.0, 2.0), 0.5  # mm per slice along the column direction
    raw = np.full((nx, ny, nz), -1000, np.int16)
    for k in range(nz):  # a rod at physical y = 8 mm: at row 8 - k * drift in slice k
        y = 8.0 - k * drift
        j0 = int(np.floor(y))
        raw[6:9, j0, k] += int(round(1000 * (1 - (y - j0))))
        raw[6:9, j0 + 1, k] += int(round(1000 * (y - j0)))
    write_dicom_series(tmp_path, raw, spacing, (0.0, 0.0, 0.0), intercept=0.0,
                       drift=(0.0, drift))
    with caplog.at_level("WARNING"):
        out = read_file(tmp_path)
    assert "tilted" in caplog.text
    vol = out[arrays.CT].reshape(out.dimensions, order="F")
    rows = np.arange(ny)
    weights = vol[7] + 1000.0  # (ny, nz)
    centre = (weights * rows[:, None]).sum(axis=0) / weights.sum(axis=0)
    np.testing.assert_allclose(centre, 8.0, atol=0.05)
