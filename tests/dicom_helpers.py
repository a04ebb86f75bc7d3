"""DICOM exports made from uncompressed series, for the tests and benchmarks of the reader.

Compressed copies: the stored pixel values encoded by GDCM (SimpleITK's writer) and put back
into the original dataset under the new transfer syntax, so each compressed file differs
from its original in its pixel data encoding only. Enhanced CT: classic slices gathered
into one multi-frame file whose geometry and rescale live in functional groups only.
"""

from __future__ import annotations

import numpy as np
import pydicom
import SimpleITK as sitk

#: SimpleITK's compressor names and the transfer syntax GDCM writes for each
SYNTAXES = {"JPEG": "1.2.840.10008.1.2.4.70", "JPEG2000": "1.2.840.10008.1.2.4.90"}


def compress_file(src, dst, compressor):
    """``src`` with its stored pixel values encoded by GDCM (``compressor``), to ``dst``."""
    ds = pydicom.dcmread(src)
    stored = sitk.GetImageFromArray(ds.pixel_array.astype(np.int16)[None])
    tmp = dst.with_name(dst.name + ".gdcm.dcm")
    writer = sitk.ImageFileWriter()
    writer.SetImageIO("GDCMImageIO")
    writer.SetFileName(str(tmp))
    writer.SetUseCompression(True)
    writer.SetCompressor(compressor)
    writer.Execute(stored)
    encoded = pydicom.dcmread(tmp)
    tmp.unlink()
    assert encoded.file_meta.TransferSyntaxUID == SYNTAXES[compressor]
    ds.file_meta.TransferSyntaxUID = encoded.file_meta.TransferSyntaxUID
    ds.PixelData = encoded.PixelData
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
    ds.save_as(dst, enforce_file_format=True)


def compress_folder(src, dst, compressor, pattern="*"):
    dst.mkdir(parents=True, exist_ok=True)
    for path in sorted(src.glob(pattern)):
        if path.suffix == ".dcm":
            compress_file(path, dst / path.name, compressor)


def enhanced_from_slices(paths, dst, *, order=None, per_frame_rescale=False):
    """The classic slices ``paths`` as one Enhanced CT multi-frame file ``dst``: frames in
    ``order`` (default: as given), geometry and rescale in functional groups only."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import EnhancedCTImageStorage, ExplicitVRLittleEndian, generate_uid

    slices = [pydicom.dcmread(p) for p in paths]
    order = range(len(slices)) if order is None else order
    slices = [slices[i] for i in order]
    first = slices[0]

    def item(**values):
        ds = Dataset()
        for key, value in values.items():
            setattr(ds, key, value)
        return ds

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = (
        EnhancedCTImageStorage, generate_uid())
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = EnhancedCTImageStorage, meta.MediaStorageSOPInstanceUID
    for key in ("Modality", "StudyInstanceUID", "SeriesInstanceUID", "FrameOfReferenceUID",
                "PatientName", "PatientID", "SeriesDescription", "SeriesNumber", "Rows",
                "Columns", "SamplesPerPixel", "PhotometricInterpretation", "BitsAllocated",
                "BitsStored", "HighBit", "PixelRepresentation"):
        setattr(ds, key, first[key].value)
    ds.NumberOfFrames = len(slices)
    rescale = lambda s: item(RescaleSlope=s.RescaleSlope,  # noqa: E731
                             RescaleIntercept=s.RescaleIntercept, RescaleType="HU")
    shared = item(
        PixelMeasuresSequence=Sequence([item(PixelSpacing=first.PixelSpacing,
                                             SliceThickness=first.SliceThickness)]),
        PlaneOrientationSequence=Sequence([item(
            ImageOrientationPatient=first.ImageOrientationPatient)]))
    if not per_frame_rescale:
        shared.PixelValueTransformationSequence = Sequence([rescale(first)])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    frames = []
    for s in slices:
        own = item(PlanePositionSequence=Sequence([item(
            ImagePositionPatient=s.ImagePositionPatient)]))
        if per_frame_rescale:
            own.PixelValueTransformationSequence = Sequence([rescale(s)])
        frames.append(own)
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.PixelData = b"".join(s.PixelData for s in slices)
    ds.save_as(dst, enforce_file_format=True)


def compress_enhanced(paths, dst, tmp, **options):
    """:func:`enhanced_from_slices` with JPEG Lossless frames (GDCM's, one per slice)."""
    from pydicom.encaps import encapsulate, generate_frames

    packed = [tmp / f"jpeg_{p.name}" for p in paths]
    for path, out in zip(paths, packed):
        compress_file(path, out, "JPEG")
    enhanced_from_slices(paths, dst, **options)
    ds = pydicom.dcmread(dst)
    order = options.get("order", range(len(paths)))
    frames = [next(generate_frames(pydicom.dcmread(packed[i]).PixelData, number_of_frames=1))
              for i in order]
    ds.file_meta.TransferSyntaxUID = SYNTAXES["JPEG"]
    ds.PixelData = encapsulate(frames)
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
    ds.save_as(dst, enforce_file_format=True)
