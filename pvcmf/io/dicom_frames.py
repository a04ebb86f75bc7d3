"""Enhanced multi-frame DICOM (Enhanced CT Image Storage): one file holding a whole stack.

Newer scanners write a CT series as one multi-frame file whose geometry is not in the
top-level ImagePositionPatient / ImageOrientationPatient / PixelSpacing of a classic slice
but in functional groups: each frame's PlanePositionSequence (per frame), its
PlaneOrientationSequence, PixelMeasuresSequence and PixelValueTransformationSequence
(rescale), each either per frame or shared by all frames (PS3.3 C.7.6.16).
:func:`frame_headers` turns such a file into one classic-looking header per frame, so the
series reader (:mod:`pvcmf.io.dicom`) sorts, checks and stacks frames as it does slices,
and :class:`FrameCache` decodes each file's pixel data once for all its frames.

Delegates to pydicom (headers, pixel data) and, for compressed frames pydicom has no
decoder for here, to GDCM through SimpleITK.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FrameCache", "frame_headers", "frame_index", "gdcm_read"]

#: the attribute of a per-frame header that holds its frame's index in the file
_FRAME = "pvcmf_frame_index"
#: top-level attributes every frame's header carries over from the file
_COPIED = ("SOPInstanceUID", "SeriesInstanceUID", "SeriesNumber", "SeriesDescription",
           "Modality", "Rows", "Columns", "LossyImageCompression",
           "LossyImageCompressionRatio", "RescaleSlope", "RescaleIntercept")


def frame_index(header):
    """The frame a header of :func:`frame_headers` stands for; None for a classic slice."""
    return getattr(header, _FRAME, None)


def _macro(groups, name):
    """The first item of functional group ``name`` found in ``groups`` (per frame first),
    or None."""
    for group in groups:
        if group is not None and name in group and len(group[name].value):
            return group[name].value[0]
    return None


def frame_headers(ds):
    """One header per frame of multi-frame ``ds`` with the classic slice attributes
    (ImagePositionPatient, ImageOrientationPatient, PixelSpacing, Rows, Columns,
    RescaleSlope, RescaleIntercept, the series' identity), or ``[]`` where ``ds`` is not a
    multi-frame image whose frames are placed in space."""
    from pydicom.dataset import Dataset

    per_frame = ds.get("PerFrameFunctionalGroupsSequence", None)
    if not per_frame or int(ds.get("NumberOfFrames", 1) or 1) != len(per_frame):
        return []
    shared = ds.get("SharedFunctionalGroupsSequence", None)
    shared = shared[0] if shared else None
    out = []
    for i, own in enumerate(per_frame):
        groups = (own, shared)
        position = _macro(groups, "PlanePositionSequence")
        orientation = _macro(groups, "PlaneOrientationSequence")
        measures = _macro(groups, "PixelMeasuresSequence")
        if position is None or orientation is None or measures is None \
                or "PixelSpacing" not in measures:
            return []
        head = Dataset()
        for key in _COPIED:
            if key in ds:
                head[key] = ds[key]
        head.ImagePositionPatient = position.ImagePositionPatient
        head.ImageOrientationPatient = orientation.ImageOrientationPatient
        head.PixelSpacing = measures.PixelSpacing
        rescale = _macro(groups, "PixelValueTransformationSequence")
        if rescale is not None:
            head.RescaleSlope = rescale.get("RescaleSlope", 1.0)
            head.RescaleIntercept = rescale.get("RescaleIntercept", 0.0)
        object.__setattr__(head, _FRAME, i)
        out.append(head)
    return out


class FrameCache:
    """Stored values of the frames of the last multi-frame file read (decoded once)."""

    def __init__(self):
        self.file, self.stored, self.decoder = None, None, None

    def values(self, file, header, out):
        """Write the frame ``header`` stands for in HU into ``out``; return the decoder."""
        import pydicom

        if file != self.file:
            self.file, self.stored = file, None
            ds = pydicom.dcmread(file)
            try:
                stored, self.decoder = np.asarray(ds.pixel_array), "pydicom"
            except Exception as err:  # pydicom's decoders raise several types
                stored, self.decoder = _gdcm_frames(ds, file, err), "GDCM"
            self.stored = stored.reshape((-1,) + stored.shape[-2:])
        frame = self.stored[frame_index(header)]
        if frame.shape != out.shape:
            raise ValueError(f"read_ct: the frames of {str(file)!r} are {frame.shape}, "
                             f"expected {out.shape}")
        if self.decoder == "GDCM":  # rescaled by GDCM
            out[...] = frame
            return self.decoder
        np.multiply(frame, np.float32(_rescale(header)[0]), out=out, casting="unsafe")
        out += np.float32(_rescale(header)[1])
        return self.decoder


def _rescale(header):
    return (float(header.get("RescaleSlope", 1.0) or 1.0),
            float(header.get("RescaleIntercept", 0.0) or 0.0))


def _gdcm_frames(ds, file, err):
    """The frames of compressed ``ds`` pydicom cannot decode here, decoded and rescaled by
    GDCM (SimpleITK): GDCM applies one rescale to every frame, so a file whose frames each
    carry their own is refused."""
    syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", None)
    rescales = {_rescale(head) for head in frame_headers(ds)}
    if syntax is None or not syntax.is_compressed or len(rescales) > 1:
        raise _undecodable(ds, file, err, syntax) from err
    try:
        return gdcm_read(file)
    except RuntimeError as gdcm_err:
        raise _undecodable(ds, file, err, syntax, gdcm_err) from gdcm_err


def gdcm_read(file):
    """The pixel values of DICOM ``file`` as GDCM (SimpleITK) decodes and rescales them:
    ``(frames, rows, columns)``; RuntimeError where GDCM cannot."""
    import SimpleITK as sitk

    reader = sitk.ImageFileReader()
    reader.SetImageIO("GDCMImageIO")
    reader.SetFileName(str(file))
    return sitk.GetArrayFromImage(reader.Execute())


def _undecodable(ds, file, err, syntax, gdcm_err=None):
    name = getattr(syntax, "name", "unknown")
    remedy = ""
    if syntax is not None and syntax.is_compressed:
        remedy = ("; pydicom decodes it with its plugins installed (pip install pylibjpeg "
                  "pylibjpeg-libjpeg pylibjpeg-openjpeg)")
    why = "" if gdcm_err is None else f", nor GDCM ({gdcm_err})"
    return ValueError(
        f"read_ct: cannot decode the {name} pixel data of the multi-frame file "
        f"{str(file)!r} (pydicom: {type(err).__name__}: {err}{why}){remedy}")
