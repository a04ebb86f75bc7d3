"""DICOM series for :func:`pvcmf.read_ct`, read with pydicom.

A folder may hold several series and files that are not DICOM, in subfolders too (a PACS
or CD export: a DICOMDIR beside folders of extension-less image files): the files that are
not DICOM images are ignored, an image found twice (the same SOPInstanceUID) is read
once, and of the series found in the folder and its subfolders the
CT with the most slices is read (the others are logged with their folders) unless
``series`` names one (UID, number or part of the description). An enhanced multi-frame
file (one file per series, :mod:`pvcmf.io.dicom_frames`) gives one slice per frame. Slices
are sorted along the slice normal; RescaleSlope/RescaleIntercept are applied (a CT comes
out in HU); missing slices (a step well above the steps either side of it) and duplicate
slice positions are errors that say where. Images of another orientation or size filed
under the series' UID (a localizer, a reformat) are left out, with a warning. Uneven slice
spacing (a protocol whose slice step changes along the stack, a displaced slice) is
resampled (linear along the normal) onto the finest step, with a warning that names the
steps. A tilted-gantry series (slice origins drifting in-plane along the stack) is
resampled slice by slice (linear) onto an orthogonal stack.

Compressed pixel data that pydicom has no decoder for in this environment (JPEG Lossless,
the usual lossless compression of PACS exports, JPEG-LS, 12-bit JPEG) is decoded by GDCM
through SimpleITK (a dependency), which applies the rescale itself; a series marked lossy
compressed (LossyImageCompression "01") is read with a warning: its HU carry the
compression's error. VTK's ``vtkDICOMImageReader`` flips rows and can reverse the slice
order without saying so, so it is not used.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import pyvista as pv

from .. import arrays
from .dicom_frames import FrameCache, frame_headers, frame_index, gdcm_read

log = logging.getLogger(__name__)


def check_spacing(spacing, path):
    """Refuse zero, negative or non-finite voxel sizes, naming the file."""
    spacing = np.asarray(spacing, dtype=float)
    if spacing.size < 3 or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(
            f"read_ct: {str(path)!r} has voxel spacing {spacing.tolist()}: expected three "
            "positive, finite sizes in mm (the file's header is wrong)")



def _pick_series(folder, headers, wanted):
    """The slices of one series: ``wanted`` (UID, number or description) or the largest CT."""
    series = {}
    for file, ds in headers:
        series.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((file, ds))

    def describe(uid):
        file, ds = series[uid][0]
        where = file.parent.relative_to(folder)
        return (f"series {ds.get('SeriesNumber', '?')} {str(ds.get('SeriesDescription', ''))!r} "
                f"({ds.get('Modality', '?')}, {len(series[uid])} slices, UID {uid}"
                + ("" if where == Path(".") else f", in {str(where)!r}") + ")")

    if wanted is not None:
        text = str(wanted)
        hits = [uid for uid in series
                if text == uid or text == str(series[uid][0][1].get("SeriesNumber", ""))
                or text.lower() in str(series[uid][0][1].get("SeriesDescription", "")).lower()]
        if len(hits) != 1:
            raise ValueError(
                f"read_ct: series={wanted!r} matches {len(hits)} of the series in "
                f"{str(folder)!r}: " + "; ".join(describe(uid) for uid in series))
        chosen = hits[0]
    else:
        chosen = max(series, key=lambda uid: (
            str(series[uid][0][1].get("Modality", "CT")).upper() == "CT", len(series[uid])))
    if len(series) > 1:
        log.warning("read_ct: %s holds %d DICOM series; reading %s (choose another with "
                    "series=..., on the command line --series): %s", folder, len(series),
                    describe(chosen),
                    "; ".join(describe(uid) for uid in series if uid != chosen))
    return series[chosen]


def _one_stack(folder, slices):
    """The slices of the series' stack: those sharing the most common orientation, size and
    pixel spacing (a localizer or a reformat filed under the series' UID is left out, with
    a warning)."""
    def key(ds):
        return (tuple(np.round(np.asarray(ds.ImageOrientationPatient, dtype=float), 3).tolist()),
                int(ds.Rows), int(ds.Columns),
                tuple(np.round(np.asarray(ds.PixelSpacing, dtype=float), 4).tolist()))

    slices = _once(folder, slices)
    keys = [key(ds) for _, ds in slices]
    counts = {k: keys.count(k) for k in set(keys)}
    if len(counts) == 1:
        return slices
    main = max(counts, key=lambda k: (counts[k], k[1] * k[2]))
    others = "; ".join(f"{n} of orientation {list(k[0])}, {k[1]}x{k[2]} pixels of "
                       f"{list(k[3])} mm" for k, n in counts.items() if k != main)
    log.warning("read_ct: %s: the series holds images of %d orientations or sizes; reading "
                "its %d slices of orientation %s, %dx%d pixels, and leaving out %s (a "
                "localizer or a reformat)", folder, len(counts), counts[main], list(main[0]),
                main[1], main[2], others)
    return [sl for sl, k in zip(slices, keys) if k == main]


def _once(folder, slices):
    """Each image once: copies of a file (the same SOPInstanceUID and frame, an export
    holding a series twice) are read from the first path only, with a warning."""
    seen, kept = set(), []
    for file, ds in slices:
        uid = str(ds.get("SOPInstanceUID", "")) or str(file)
        key = (uid, frame_index(ds))
        if key not in seen:
            seen.add(key)
            kept.append((file, ds))
    if len(kept) < len(slices):
        log.warning("read_ct: %s holds %d copies of images already found (the same "
                    "SOPInstanceUID); each image is read once", folder, len(slices) - len(kept))
    return kept


def _slice_geometry(folder, slices):
    """Sort the slices; return them, the slice step, and the in-plane shift per slice (tilt)."""
    first = slices[0][1]
    iop = np.array([float(v) for v in first.ImageOrientationPatient], dtype=float)
    row_dir, col_dir = iop[:3], iop[3:]
    normal = np.cross(row_dir, col_dir)
    pos = np.array([[float(v) for v in ds.ImagePositionPatient] for _, ds in slices])
    order = np.argsort(pos @ normal, kind="stable")
    slices, pos = [slices[i] for i in order], pos[order]
    if len(slices) < 2:
        raise ValueError(f"read_ct: the DICOM series in {str(folder)!r} has one slice: a 2-D "
                         "image, expected a 3-D CT volume")
    along = pos @ normal
    steps = np.diff(along)
    dz = float(np.median(steps))
    if dz <= 0 or np.any(steps <= 1e-3 * max(dz, 1e-3)):
        raise ValueError(f"read_ct: the DICOM series in {str(folder)!r} has two slices at the "
                         "same position (duplicates or two series with one UID)")
    gap = np.nonzero(steps > 1.5 * _neighbour_steps(steps))[0]
    if gap.size:
        where = ", ".join(f"{along[i]:.2f}..{along[i + 1]:.2f} mm" for i in gap[:5])
        raise ValueError(f"read_ct: the DICOM series in {str(folder)!r} misses slices "
                         f"(gaps along the slice normal at {where}; slice step {dz:.3g} mm)")
    if np.ptp(steps) > 0.01 * dz + 1e-3:
        dz = float(steps.min())  # resampled onto the finest step (read_dicom_series)
    # gantry tilt: slice origins drift in-plane along the stack
    drift = pos - pos[0] - np.outer((pos - pos[0]) @ normal, normal)
    shift = np.column_stack([drift @ row_dir, drift @ col_dir])  # mm along row, column
    return slices, pos[0], (row_dir, col_dir, normal), dz, shift, along - along[0]


def _neighbour_steps(steps):
    """The larger of the steps either side of each step (the step itself at the ends): a
    step well above both is a gap of missing slices, a change of step that lasts is not."""
    padded = np.concatenate([steps[:1], steps, steps[-1:]])
    return np.maximum(padded[:-2], padded[2:]) if len(steps) > 1 else steps


def read_dicom_series(folder, wanted=None):
    try:
        import pydicom
    except ImportError as err:  # pragma: no cover - pydicom is a dependency
        raise ImportError("reading a DICOM series needs pydicom: pip install pydicom") from err
    from pydicom.errors import InvalidDicomError

    headers = []
    for file in _files(folder):
        try:
            ds = pydicom.dcmread(file, stop_before_pixels=True)
        except (InvalidDicomError, OSError, EOFError, ValueError):
            continue  # not DICOM: ignored
        if "ImagePositionPatient" in ds and "PixelSpacing" in ds and "Rows" in ds:
            headers.append((file, ds))
        elif int(ds.get("NumberOfFrames", 1) or 1) > 1:  # enhanced multi-frame: per frame
            headers.extend((file, head) for head in frame_headers(ds))
    if not headers:
        raise ValueError(
            f"read_ct: folder {str(folder)!r} holds no readable DICOM image slice, nor do its "
            "subfolders "
            "(expected a DICOM series folder, or a .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd or "
            ".vti file)"
        )
    slices = _one_stack(folder, _pick_series(folder, headers, wanted))
    slices, origin, (row_dir, col_dir, normal), dz, shift, along = _slice_geometry(
        folder, slices)
    first = slices[0][1]
    rows, cols = int(first.Rows), int(first.Columns)
    dy, dx = (float(v) for v in first.PixelSpacing)  # row spacing, column spacing
    check_spacing([dx, dy, dz], folder)
    _check_lossy(folder, slices)
    volume = np.empty((len(slices), rows, cols), dtype=np.float32)
    decoded_by, frames = set(), FrameCache()
    for k, (file, head) in enumerate(slices):  # one file per slice: I/O, not a voxel loop
        decoded_by.add(_slice_values(pydicom.dcmread(file), file, volume[k])
                       if frame_index(head) is None else frames.values(file, head, volume[k]))
    if "GDCM" in decoded_by:
        log.info("read_ct: %s: compressed pixel data pydicom has no decoder for here, "
                 "decoded by GDCM (SimpleITK)", folder)
    if np.abs(shift).max() > 0.01 * min(dx, dy):
        volume = _untilt(volume, shift, dx, dy, folder)
    if np.ptp(np.diff(along)) > 0.01 * dz + 1e-3:
        volume = _regular(volume, along, dz, folder)
    image = pv.ImageData(dimensions=(cols, rows, volume.shape[0]), spacing=(dx, dy, dz))
    image.direction_matrix = np.column_stack([row_dir, col_dir, normal])
    image.origin = origin
    modality = str(first.get("Modality", "") or "").strip().upper()
    if modality:
        image.field_data[arrays.MODALITY] = np.array([modality])
    return image, volume.ravel()


def _files(folder):
    """Every file in ``folder`` and its subfolders (symbolic links to folders not followed),
    sorted by path."""
    found = []
    for root, dirs, names in os.walk(folder):
        dirs.sort()
        found.extend(Path(root) / name for name in sorted(names))
    return [f for f in found if f.is_file()]


def _check_lossy(folder, slices):
    """Warn where the series' pixel data went through lossy compression."""
    lossy = [ds for _, ds in slices if str(ds.get("LossyImageCompression", "")) == "01"]
    if lossy:
        ratio = lossy[0].get("LossyImageCompressionRatio", None)
        log.warning("read_ct: %s: %d of %d slices are marked lossy compressed%s: their HU "
                    "carry the compression's error (ask for the original or a lossless "
                    "export)", folder, len(lossy), len(slices),
                    "" if ratio is None else f" (ratio {ratio})")


def _slice_values(ds, file, out):
    """Write slice ``ds``'s values in HU into ``out`` (rows, columns); return the decoder
    ("pydicom", or "GDCM" for compressed data pydicom cannot decode here)."""
    try:
        pixels = ds.pixel_array
    except Exception as err:  # pydicom's decoders raise several types
        syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
        if syntax is None or not syntax.is_compressed:
            raise ValueError(f"read_ct: cannot decode DICOM pixel data of {str(file)!r} "
                             f"({type(err).__name__}: {err})") from err
        values = _gdcm_values(file, syntax, err)
        _check_shape(values, out, file)
        out[...] = values
        return "GDCM"
    _check_shape(pixels, out, file)
    slope = float(ds.get("RescaleSlope", 1.0) or 1.0)
    inter = float(ds.get("RescaleIntercept", 0.0) or 0.0)
    np.multiply(pixels, np.float32(slope), out=out, casting="unsafe")
    out += np.float32(inter)
    return "pydicom"


def _gdcm_values(file, syntax, pydicom_error):
    """One compressed slice decoded by GDCM (SimpleITK), rescaled to HU by it."""
    try:
        values = gdcm_read(file)
    except RuntimeError as err:
        raise ValueError(
            f"read_ct: cannot decode the {syntax.name} pixel data of {str(file)!r}: pydicom "
            f"({type(pydicom_error).__name__}: {pydicom_error}) nor GDCM ({err})") from err
    return values[0] if values.ndim == 3 and values.shape[0] == 1 else values


def _check_shape(pixels, out, file):
    if pixels.shape != out.shape:
        raise ValueError(
            f"read_ct: DICOM slice {str(file)!r} is {pixels.shape}, expected {out.shape}")


def _untilt(volume, shift, dx, dy, folder):
    """Undo a gantry tilt: move each slice in-plane so the stack is orthogonal (linear)."""
    from scipy import ndimage

    log.warning("read_ct: %s is a tilted-gantry series (slices drift %.2f mm in-plane over "
                "the stack): each slice resampled (linear) onto an orthogonal stack", folder,
                float(np.linalg.norm(shift[-1])))
    fill = float(volume.min())
    out = np.empty_like(volume)
    for k in range(volume.shape[0]):  # one 2-D shift per slice, vectorised within the slice
        out[k] = ndimage.shift(volume[k], (shift[k, 1] / dy, shift[k, 0] / dx), order=1,
                               mode="constant", cval=fill)
    return out


def _regular(volume, along, dz, folder):
    """Slices at uneven positions ``along`` (mm from the first, along the normal) resampled
    (linear between the two slices around each new one) onto slices ``dz`` mm apart from
    the first slice: the finest step, so no part of the stack loses detail."""
    steps = np.unique(np.round(np.diff(along), 3))
    n = int(np.floor(along[-1] / dz + 1e-6)) + 1
    z = np.arange(n) * dz
    hi = np.clip(np.searchsorted(along, z, side="right"), 1, len(along) - 1)
    w = ((z - along[hi - 1]) / (along[hi] - along[hi - 1])).astype(np.float32)
    log.warning("read_ct: %s has uneven slice spacing (steps %s mm): resampled (linear) onto "
                "%d slices %.3g mm apart", folder, steps.tolist(), n, dz)
    out = np.empty((n,) + volume.shape[1:], dtype=volume.dtype)
    for k in range(n):  # one weighted sum of two slices per new slice
        np.multiply(volume[hi[k] - 1], 1 - w[k], out=out[k])
        out[k] += w[k] * volume[hi[k]]
    return out
