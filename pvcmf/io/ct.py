"""Read CT volumes from disk into :class:`pyvista.ImageData` with a float32 ``ct`` array.

:func:`read_ct` reads

* a **DICOM series** (a folder of slice files) with pydicom: slices sorted along the slice
  normal, RescaleSlope/RescaleIntercept applied (so a CT comes out in HU), geometry from
  ImagePositionPatient / ImageOrientationPatient / PixelSpacing. (VTK's
  ``vtkDICOMImageReader`` behind ``pyvista.DICOMReader`` flips the rows and can reverse the
  slice order without saying so, so it is not used.)
* **NIfTI** (``.nii``, ``.nii.gz``) with VTK's ``vtkNIFTIImageReader``; the sform (or qform)
  matrix gives origin and orientation, ``scl_slope``/``scl_inter`` are applied.
* **MetaImage** (``.mha``, ``.mhd``) with VTK's ``vtkMetaImageReader`` (Offset,
  ElementSpacing and TransformMatrix honoured).
* **VTK ImageData** (``.vti``) with ``pyvista.read`` (origin, spacing, direction).
* **NRRD** (``.nrrd``, ``.nhdr``) with a small numpy reader of the NRRD header (raw, gzip,
  bzip2 and ascii encodings; single, ``LIST`` and ``%d``-pattern data files; ``space
  directions``/``space origin`` or ``spacings``). VTK's ``vtkNrrdReader`` is not used: in
  VTK 9.7 it reads a 3-D volume whose first axis is short (e.g. 6 voxels) as a 2-D image with
  vector components and crashes on some multi-file headers.

Geometry and orientation
------------------------
By default (``frame='patient'``) the image comes out in the pvcmf **patient frame** (x
patient's left, y anterior, z superior) with an identity direction matrix, from what the
file says: LPS for DICOM (per-slice ImageOrientationPatient / ImagePositionPatient) and
MetaImage (TransformMatrix, read in MetaIO's column order as ITK writes it), RAS for NIfTI
(sform, else qform), NRRD's ``space`` (LPS, RAS or LAS) with ``space directions``. A VTI, or
a NRRD without an anatomical ``space``, is taken as already in the patient frame (logged).
Axis-aligned scans are turned exactly (voxel axes reordered and reversed); oblique scans are
resampled trilinearly onto an axis-aligned grid holding the whole volume (logged), and a
tilted-gantry DICOM series is first resampled slice by slice onto an orthogonal stack. Units
and an anatomy-based check of the axes are :func:`pvcmf.filters.standardize`'s job.
``frame='file'`` keeps the file's voxel order, origin, spacing and direction in the file's
own world frame.

DICOM folders (and their subfolders, :mod:`pvcmf.io.dicom`): files that are not DICOM are
ignored; compressed pixel data pydicom cannot decode here is decoded by GDCM (SimpleITK);
with several series the CT series with the most slices is read and the others are listed in the log (``series=`` picks one by UID,
number or description). Missing slices and duplicate slice positions are errors that say
where; uneven slice spacing is resampled onto the finest step (with a warning). Zero, negative or non-finite spacing and 2-D images are refused in every format.

The readers are pydicom (DICOM), VTK (NIfTI pixels and matrices, MetaImage pixels), a small
numpy NRRD reader and pyvista (VTI). SimpleITK reads MetaImage, NIfTI and NRRD well too, but
it refuses NRRD headers that mix ``spacings`` and ``space`` (VTK's headsq), so it only
decodes the DICOM pixel data pydicom cannot; the tests use SimpleITK and nibabel as
independent writers.

Values
------
``ct = scale * value + offset``, where ``value`` already includes the file's own rescale
(DICOM RescaleSlope/Intercept, NIfTI scl_slope/scl_inter). Use ``offset``/``scale`` for
scanner units that are not HU (e.g. :func:`pvcmf.datasets.headsq`). :func:`flip_axes`
mirrors a read image along some of its axes (``pvcmf simulate --flip``).
"""

from __future__ import annotations

import bz2
import gzip
import logging
import math
import re
from pathlib import Path

import numpy as np
import pyvista as pv

from .. import arrays
from .dicom import check_spacing as _check_spacing
from .dicom import read_dicom_series as _read_dicom_series

log = logging.getLogger(__name__)

#: suffixes read_ct understands, and what reads them
SUPPORTED = {
    ".nii": "NIfTI (vtkNIFTIImageReader)",
    ".nii.gz": "NIfTI (vtkNIFTIImageReader)",
    ".nrrd": "NRRD (numpy reader)",
    ".nhdr": "NRRD detached header (numpy reader)",
    ".mha": "MetaImage (vtkMetaImageReader)",
    ".mhd": "MetaImage (vtkMetaImageReader)",
    ".vti": "VTK ImageData (pyvista.read)",
}
_FORMATS = "a DICOM series folder, " + ", ".join(SUPPORTED)


def read_ct(path, *, offset=0.0, scale=1.0, frame="patient", series=None):
    """Read a CT volume as ImageData with a float32 point array ``ct``.

    Parameters
    ----------
    path : str or pathlib.Path
        A folder holding DICOM series (in subfolders too: an export's root), or a
        ``.nii``, ``.nii.gz``, ``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd`` or ``.vti`` file.
    offset, scale : float
        Linear map to Hounsfield units: ``ct = scale * value + offset``. The defaults keep
        the file's values (DICOM and NIfTI rescale slopes are applied before).
    frame : {'patient', 'file'}
        ``'patient'`` (default): the pvcmf patient frame (x patient's left, y anterior, z
        superior), identity direction; oblique scans resampled (module notes). ``'file'``
        keeps the file's voxel order, origin, spacing and orientation in its own world frame.
    series : str or int, optional
        For a DICOM folder with several series: the SeriesInstanceUID, SeriesNumber or a
        part of the SeriesDescription of the one to read. Default: the CT series with the
        most slices (logged).

    Returns
    -------
    pyvista.ImageData
        One point array ``ct`` (float32); geometry as ``frame`` says; the field
        ``source_path`` (:data:`pvcmf.arrays.SOURCE_PATH`) and, from a DICOM series,
        ``modality`` (:data:`pvcmf.arrays.MODALITY`).

    Raises
    ------
    FileNotFoundError
        If ``path`` does not exist.
    ValueError
        For an unsupported format, an unknown ``frame``, a corrupt or truncated file, a
        folder without a readable DICOM series (or a ``series`` that matches none), missing
        or duplicate DICOM slices, zero/negative spacing, a 2-D image, a volume that is not
        scalar, or a bad ``offset``/``scale``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf, tempfile, os
    >>> img = pv.ImageData(dimensions=(8, 8, 4), spacing=(0.5, 0.5, 2.0))
    >>> img["values"] = np.arange(img.n_points, dtype=np.int16)
    >>> path = os.path.join(tempfile.mkdtemp(), "ct.vti")
    >>> img.save(path)
    >>> ct = pvcmf.read_ct(path, offset=-1000.0)
    >>> ct["ct"].dtype, float(ct["ct"][0]), ct.spacing
    (dtype('float32'), -1000.0, (0.5, 0.5, 2.0))
    """
    offset = _finite(offset, "offset")
    scale = _finite(scale, "scale")
    if frame not in ("file", "patient"):
        raise ValueError(f"frame must be 'file' or 'patient', got {frame!r}")
    if scale == 0.0:
        raise ValueError("scale must be non-zero, got 0.0")
    path = Path(path).expanduser()
    if not path.exists():
        raise FileNotFoundError(f"read_ct: {str(path)!r} does not exist (expected {_FORMATS})")
    if path.is_dir():
        image, values = _read_dicom_series(path, series)
        world = "LPS"
    elif series is not None:
        raise ValueError(f"read_ct: series={series!r} picks a series of a DICOM folder; "
                         f"{str(path)!r} is a file")
    else:
        name = path.name.lower()
        suffix = ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()
        if suffix not in SUPPORTED:
            raise ValueError(
                f"read_ct: unsupported file {str(path)!r} (suffix {suffix!r}); "
                f"expected {_FORMATS}"
            )
        reader = {
            ".nii": _read_nifti,
            ".nii.gz": _read_nifti,
            ".nrrd": _read_nrrd,
            ".nhdr": _read_nrrd,
            ".mha": _read_metaimage,
            ".mhd": _read_metaimage,
            ".vti": _read_vti,
        }[suffix]
        try:
            image, values = reader(path)
        except (ValueError, FileNotFoundError):
            raise
        except Exception as err:  # VTK execution errors, decoding errors, short reads...
            raise ValueError(
                f"read_ct: cannot read {str(path)!r} as {SUPPORTED[suffix]}: "
                f"corrupt or unreadable file ({type(err).__name__}: {err})"
            ) from err
        world = {".nii": "RAS", ".nii.gz": "RAS", ".mha": "LPS", ".mhd": "LPS",
                 ".vti": "patient"}.get(suffix) or _nrrd_space(path)
    _check_spacing(image.spacing, path)
    if min(image.dimensions) < 2:
        raise ValueError(
            f"read_ct: {str(path)!r} is a 2-D image (dimensions {tuple(image.dimensions)}); "
            "expected a 3-D CT volume")
    values = np.asarray(values)
    if values.ndim != 1 or values.size != image.n_points:
        raise ValueError(
            f"read_ct: {str(path)!r} holds {values.shape} values for a "
            f"{image.dimensions} grid: expected one scalar per voxel"
        )
    if values.dtype.kind not in "biuf":
        raise ValueError(f"read_ct: {str(path)!r} has non-numeric voxels ({values.dtype})")
    ct = values.astype(np.float64) * scale + offset if (scale != 1.0 or offset != 0.0) else values
    out = pv.ImageData(
        dimensions=image.dimensions, spacing=image.spacing, origin=image.origin
    )
    out.direction_matrix = np.asarray(image.direction_matrix, dtype=float)
    out.point_data[arrays.CT] = np.asarray(ct, dtype=np.float32)
    if frame == "patient":
        out = _to_patient_frame(out, world, path)
    if arrays.MODALITY in image.field_data:  # a DICOM series' modality (module arrays)
        out.field_data[arrays.MODALITY] = np.array(image.field_data[arrays.MODALITY])
    out.field_data[arrays.SOURCE_PATH] = np.array([str(path)])
    log.info(
        "read_ct %s: %s voxels, spacing %s mm, ct range [%.0f, %.0f]",
        path, out.dimensions, tuple(round(s, 4) for s in out.spacing),
        float(out[arrays.CT].min()), float(out[arrays.CT].max()),
    )
    return out


# --------------------------------------------------------------------------- frames
#: world frame -> pvcmf patient frame (x left, y anterior, z superior)
_TO_PATIENT = {
    "LPS": np.diag([1.0, -1.0, 1.0]),
    "RAS": np.diag([-1.0, 1.0, 1.0]),
    "LAS": np.eye(3),
    "patient": np.eye(3),
}


def _to_patient_frame(image, world, path):
    """The image in the patient frame with an identity direction.

    Axis-aligned scans are turned exactly (voxel axes reordered and reversed); oblique ones
    are resampled (trilinear) onto an axis-aligned grid that holds the whole volume.
    """
    if world not in _TO_PATIENT:
        log.warning("read_ct: %s gives no anatomical frame (space %r): its axes are taken as "
                    "x left, y anterior, z superior; pvcmf.filters.standardize checks this "
                    "from the anatomy", path, world)
        world = "patient"
    flip = _TO_PATIENT[world]
    direction = flip @ np.asarray(image.direction_matrix, dtype=float)
    axis = np.argmax(np.abs(direction), axis=0)  # patient axis of each voxel axis
    sign = np.sign(direction[axis, np.arange(3)])
    dims = np.asarray(image.dimensions)
    vol = image.point_data[arrays.CT].reshape(tuple(dims), order="F")
    if sorted(axis) != [0, 1, 2] or np.any(np.abs(direction[axis, np.arange(3)]) < 0.999):
        return _resample(vol, flip @ np.asarray(image.origin, dtype=float), direction,
                         np.asarray(image.spacing, dtype=float), path)
    # the voxel that becomes index (0, 0, 0): the low end of every patient axis
    corner = np.where(sign > 0, 0, dims - 1)
    origin = flip @ (np.asarray(image.origin) + np.asarray(image.direction_matrix)
                     @ (corner * np.asarray(image.spacing)))
    vol = vol[tuple(slice(None, None, -1) if s < 0 else slice(None) for s in sign)]
    order = np.argsort(axis)  # new axis a takes old voxel axis order[a]
    vol = np.transpose(vol, order)
    out = pv.ImageData(dimensions=vol.shape, spacing=np.asarray(image.spacing)[order],
                       origin=origin)
    out.point_data[arrays.CT] = np.asarray(vol).ravel(order="F")
    return out


def _resample(vol, origin, direction, spacing, path):
    """Trilinear resampling of an oblique (or sheared) volume onto an axis-aligned grid.

    ``direction`` (columns: voxel axes, in the patient frame) times ``spacing`` maps voxel
    indices to millimetres from ``origin``.
    """
    from scipy import ndimage

    axes = direction * spacing
    dims = np.asarray(vol.shape)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * (dims - 1)
    points = corners @ axes.T + origin
    # each patient axis takes the spacing of the voxel axis closest to it
    step = spacing[np.argmax(np.abs(direction), axis=1)]
    lo, hi = points.min(axis=0), points.max(axis=0)
    shape = tuple(int(n) for n in np.floor((hi - lo) / step + 1e-6).astype(int) + 1)
    inverse = np.linalg.inv(axes)
    log.warning("read_ct: %s is oblique (voxel axes %s in the patient frame): resampled "
                "(trilinear) onto an axis-aligned %s grid of %s mm", path,
                np.round(direction, 3).tolist(), shape, np.round(step, 3).tolist())
    out_vol = ndimage.affine_transform(
        np.asarray(vol, dtype=np.float32), inverse @ np.diag(step), offset=inverse @ (lo - origin),
        output_shape=shape, order=1, mode="constant", cval=float(np.min(vol)))
    out = pv.ImageData(dimensions=shape, spacing=step, origin=lo)
    out.point_data[arrays.CT] = np.asarray(out_vol, dtype=np.float32).ravel(order="F")
    return out


def _nrrd_space(path):
    """World frame of a NRRD header's ``space`` field ('LPS', 'RAS', 'LAS' or as written)."""
    head = path.read_bytes()[:4096].split(b"\n\n")[0].decode("latin-1").splitlines()
    space = next((ln.split(":", 1)[1].strip().lower() for ln in head
                  if ln.lower().startswith("space:")), "")
    names = {"left-posterior-superior": "LPS", "lps": "LPS",
             "right-anterior-superior": "RAS", "ras": "RAS",
             "left-anterior-superior": "LAS", "las": "LAS"}
    return names.get(space, space or "unknown")


# --------------------------------------------------------------------------- utilities
def _finite(value, name):
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    return value


def _run_vtk(reader, path):
    """Update a VTK reader, turning VTK error messages into a Python exception."""
    from pyvista.core.utilities.observers import VtkErrorCatcher

    reader.SetFileName(str(path))
    with pv.vtk_verbosity("off"), VtkErrorCatcher(raise_errors=True, emit_warnings=False):
        reader.Update()
    out = pv.wrap(reader.GetOutput())
    if out is None or out.n_points == 0 or out.point_data.active_scalars is None:
        raise ValueError(f"read_ct: {str(path)!r} gave an empty image (corrupt file?)")
    return out


def _orthonormal(matrix, path):
    """Return the rotation part of ``matrix`` (3x3); warn if it had shear or scaling."""
    u, s, vt = np.linalg.svd(matrix)
    rot = u @ vt
    if not np.allclose(matrix, rot, atol=1e-4):
        log.warning("%s: orientation matrix is not orthonormal; using its nearest rotation", path)
    return rot


def _read_vti(path):
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        image = pv.read(path)
    if caught and (not isinstance(image, pv.ImageData) or image.n_points == 0):
        raise ValueError(f"read_ct: cannot read {str(path)!r}: {caught[0].message}")
    if not isinstance(image, pv.ImageData) or image.n_points == 0:
        raise ValueError(f"read_ct: {str(path)!r} holds no ImageData (corrupt file?)")
    names = image.point_data.keys()
    if not names:
        raise ValueError(f"read_ct: {str(path)!r} has no point array to read as CT")
    name = arrays.CT if arrays.CT in names else (
        image.point_data.active_scalars_name or names[0]
    )
    return image, image.point_data[name]


def _metaimage_header(path):
    """Key/value pairs of a MetaImage header (up to ElementDataFile)."""
    fields = {}
    with open(path, "rb") as handle:
        for raw in handle:
            key, sep, value = raw.decode("latin-1").partition("=")
            if not sep:
                continue
            fields[key.strip().lower()] = value.strip()
            if key.strip().lower() == "elementdatafile":
                break
    return fields


def _read_metaimage(path):
    import vtk

    fields = _metaimage_header(path)
    spacing = fields.get("elementspacing") or fields.get("elementsize")
    if spacing is not None:
        _check_spacing([float(v) for v in spacing.split()], path)
    image = _run_vtk(vtk.vtkMetaImageReader(), path)
    geometry = pv.ImageData(dimensions=image.dimensions, spacing=image.spacing,
                            origin=image.origin)
    matrix = next((fields[k] for k in ("transformmatrix", "rotation", "orientation")
                   if k in fields), None)
    if matrix is not None:
        values = [float(v) for v in matrix.split()]
        if len(values) == 9:
            # MetaIO (ITK's writer) stores the direction matrix column by column: each
            # triple is the world direction of one voxel axis.
            geometry.direction_matrix = _orthonormal(np.reshape(values, (3, 3)).T, path)
    return geometry, image.point_data.active_scalars


def _read_nifti(path):
    import vtk

    reader = vtk.vtkNIFTIImageReader()
    image = _run_vtk(reader, path)
    values = np.asarray(image.point_data.active_scalars)
    slope, inter = reader.GetRescaleSlope(), reader.GetRescaleIntercept()
    # NIfTI: a slope of 0 (nibabel: or not finite) means "no scaling", the intercept too
    if np.isfinite(slope) and slope != 0.0 and (slope != 1.0 or inter != 0.0):
        values = values.astype(np.float64) * slope + (inter if np.isfinite(inter) else 0.0)
    matrix = reader.GetSFormMatrix() or reader.GetQFormMatrix()
    geometry = pv.ImageData(dimensions=image.dimensions, spacing=image.spacing)
    if matrix is not None:
        m = np.array([[matrix.GetElement(i, j) for j in range(4)] for i in range(4)])
        # VTK's data coordinates are index * spacing from origin 0; the matrix maps them to
        # NIfTI world (RAS) coordinates.
        geometry.direction_matrix = _orthonormal(m[:3, :3], path)
        geometry.origin = m[:3, 3] + m[:3, :3] @ np.asarray(image.origin)
    return geometry, values


# --------------------------------------------------------------------------- NRRD
_NRRD_TYPES = {
    "i1": ("signed char", "int8", "int8_t"),
    "u1": ("uchar", "unsigned char", "uint8", "uint8_t"),
    "i2": ("short", "short int", "signed short", "signed short int", "int16", "int16_t"),
    "u2": ("ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"),
    "i4": ("int", "signed int", "int32", "int32_t"),
    "u4": ("uint", "unsigned int", "uint32", "uint32_t"),
    "i8": ("longlong", "long long", "long long int", "signed long long",
           "signed long long int", "int64", "int64_t"),
    "u8": ("ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t"),
    "f4": ("float",),
    "f8": ("double",),
}
_NRRD_DTYPE = {name: code for code, names in _NRRD_TYPES.items() for name in names}


def _nrrd_vector(text):
    return np.array([float(v) for v in text.strip().strip("()").split(",")])


def _nrrd_header(path, raw):
    """Parse a NRRD header: its fields, sizes, dtype, encoding and where the data begins."""
    if not raw.startswith(b"NRRD000"):
        raise ValueError(f"read_ct: {str(path)!r} is not a NRRD file (no 'NRRD000x' magic)")
    header_end = raw.find(b"\n\n")
    attached = header_end >= 0
    header = raw[: header_end if attached else len(raw)].decode("latin-1").splitlines()
    fields, data_files = {}, []
    lines = iter(header[1:])
    for line in lines:
        if not line or line.startswith("#") or ":=" in line:
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise ValueError(f"read_ct: bad NRRD header line {line!r} in {str(path)!r}")
        key = key.strip().lower()
        fields[key] = value.strip()
        if key in ("data file", "datafile") and value.strip().upper().startswith("LIST"):
            data_files = [ln.strip() for ln in lines if ln.strip()]
    for key in ("type", "dimension", "sizes", "encoding"):
        if key not in fields:
            raise ValueError(f"read_ct: NRRD header of {str(path)!r} lacks the {key!r} field")
    ndim = int(fields["dimension"])
    sizes = [int(v) for v in fields["sizes"].split()]
    if ndim != 3 or len(sizes) != 3:
        raise ValueError(
            f"read_ct: {str(path)!r} is a {ndim}-D NRRD with sizes {sizes}; expected a 3-D "
            "scalar volume"
        )
    code = _NRRD_DTYPE.get(fields["type"].lower())
    if code is None:
        raise ValueError(f"read_ct: unsupported NRRD type {fields['type']!r} in {str(path)!r}")
    endian = "<" if fields.get("endian", "little").lower() == "little" else ">"
    dtype = np.dtype(endian + code)
    encoding = fields["encoding"].lower()
    if encoding not in ("raw", "gzip", "gz", "bzip2", "bz2", "ascii", "text", "txt"):
        raise ValueError(f"read_ct: unsupported NRRD encoding {encoding!r} in {str(path)!r}")
    return fields, data_files, attached, header_end, sizes, dtype, encoding


def _nrrd_chunks(path, raw, fields, data_files, attached, header_end):
    """The raw bytes of a NRRD's data: attached, one detached file or a list of them."""
    spec = fields.get("data file", fields.get("datafile"))
    if spec is None:
        if not attached:
            raise ValueError(f"read_ct: NRRD {str(path)!r} has neither data nor a 'data file'")
        chunks = [raw[header_end + 2:]]
    else:
        parts = spec.split()
        if parts[0].upper() == "LIST":
            names = data_files
        elif len(parts) >= 4 and re.search(r"%\d*d", parts[0]):
            lo, hi, step = int(parts[1]), int(parts[2]), int(parts[3])
            names = [parts[0] % i for i in range(lo, hi + (1 if step > 0 else -1), step)]
        else:
            names = [spec]
        chunks = []
        for name in names:
            file = (path.parent / name) if not Path(name).is_absolute() else Path(name)
            if not file.is_file():
                raise ValueError(f"read_ct: NRRD data file {str(file)!r} (from {str(path)!r}) is missing")
            chunks.append(file.read_bytes())
    return chunks


def _nrrd_values(path, chunks, fields, sizes, dtype, encoding):
    """Decode a NRRD's data chunks into a flat array of ``prod(sizes)`` voxel values."""
    count = int(np.prod(sizes))
    decoded = []
    for chunk in chunks:
        if encoding in ("gzip", "gz"):
            chunk = gzip.decompress(chunk)
        elif encoding in ("bzip2", "bz2"):
            chunk = bz2.decompress(chunk)
        decoded.append(chunk)
    if encoding in ("ascii", "text", "txt"):
        values = np.array(b" ".join(decoded).split(), dtype=np.float64)
    else:
        per_file = count // len(decoded) * dtype.itemsize
        skip = int(fields.get("byte skip", 0))
        parts_ = []
        for chunk in decoded:
            if skip == -1:  # data at the end of the file
                chunk = chunk[len(chunk) - per_file:] if len(chunk) >= per_file else chunk
            else:
                chunk = chunk[skip:]
            parts_.append(chunk[:per_file])
        buf = b"".join(parts_)
        if len(buf) < count * dtype.itemsize:
            raise ValueError(
                f"read_ct: NRRD data of {str(path)!r} is truncated: {len(buf)} bytes for "
                f"{count} voxels of {dtype.itemsize} bytes"
            )
        values = np.frombuffer(buf, dtype=dtype, count=count)
    if values.size != count:
        raise ValueError(f"read_ct: NRRD {str(path)!r} holds {values.size} values, expected {count}")
    return values


def _read_nrrd(path):
    raw = path.read_bytes()
    fields, data_files, attached, header_end, sizes, dtype, encoding = _nrrd_header(path, raw)
    chunks = _nrrd_chunks(path, raw, fields, data_files, attached, header_end)
    values = _nrrd_values(path, chunks, fields, sizes, dtype, encoding)

    # geometry
    origin = _nrrd_vector(fields["space origin"]) if "space origin" in fields else np.zeros(3)
    direction = np.eye(3)
    if "space directions" in fields:
        vecs = re.findall(r"\(([^)]*)\)", fields["space directions"])
        if len(vecs) != 3:
            raise ValueError(
                f"read_ct: NRRD {str(path)!r} 'space directions' must give 3 vectors, got "
                f"{fields['space directions']!r}"
            )
        axes = np.column_stack([_nrrd_vector(v) for v in vecs])
        spacing = np.linalg.norm(axes, axis=0)
        direction = _orthonormal(axes / spacing, path)
    elif "spacings" in fields:
        spacing = np.array([float(v) for v in fields["spacings"].split()])
    else:
        spacing = np.ones(3)
    if len(spacing) != 3 or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"read_ct: NRRD {str(path)!r} has bad spacing {spacing}")
    image = pv.ImageData(dimensions=sizes, spacing=spacing, origin=origin)
    image.direction_matrix = direction
    return image, values.astype(np.float32) if values.dtype == np.float64 else values


def flip_axes(image, axes):
    """Mirror an image along some of its axes, in place of a reorientation.

    Flipping two axes is a 180 degree rotation (patient left/right kept): use it to bring
    a scan whose superior is -z and anterior -y (VTK's headsq) into pvcmf's patient frame
    (x left, y anterior, z superior). Every point array is flipped; bounds are unchanged.

    Parameters
    ----------
    image : pyvista.ImageData
    axes : str or sequence of str
        Subset of ``"xyz"``, e.g. ``"yz"``.

    Returns
    -------
    pyvista.ImageData
        A new image.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.io.ct import flip_axes
    >>> img = pv.ImageData(dimensions=(2, 3, 4))
    >>> img["z"] = img.points[:, 2].copy()
    >>> flip_axes(img, "z")["z"][:3].tolist()
    [3.0, 3.0, 3.0]
    """
    axes = "".join(axes)
    if not isinstance(image, pv.ImageData):
        raise TypeError(f"image must be a pyvista.ImageData, got {type(image).__name__}")
    bad = set(axes) - set("xyz")
    if bad or len(set(axes)) != len(axes):
        raise ValueError(f"axes must be distinct letters of 'xyz', got {axes!r}")
    out = image.copy()
    dims = tuple(image.dimensions)
    for name in image.point_data.keys():
        data = np.asarray(image.point_data[name])
        vol = data.reshape(dims + data.shape[1:], order="F")
        for axis in axes:
            vol = np.flip(vol, "xyz".index(axis))
        out.point_data[name] = vol.reshape(data.shape, order="F").copy()
    return out
