"""The real head CTs read as DICOM exports deliver them, against their plain slice files.

Not run by CI. ``python benchmarks/reading.py [--write]`` (needs ``PVCMF_DATA_DIR``; about a
minute). Each Visible Human head is written three ways from its plain files
(``tests/dicom_helpers.py``): a CD/PACS export (nested folders, files without suffix, a
DICOMDIR, every slice JPEG Lossless, as GDCM encodes it), the same with JPEG 2000, and
one Enhanced CT multi-frame file (frames shuffled); :func:`pvcmf.read_ct` reads each, and
the table gives its CPU seconds (median of ``--repeat``), the files' size and whether the
volume equals the plain read voxel for voxel, with the same origin and spacing. ``--write``
writes ``docs/benchmarks/reading.md`` with the command and the machine.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's pvcmf
sys.path.insert(0, str(ROOT / "tests"))  # the export writers the tests use

import pvcmf  # noqa: E402
from dicom_helpers import compress_folder, enhanced_from_slices  # noqa: E402
from pvcmf import arrays  # noqa: E402
from segmentation import data_folder, write_page  # noqa: E402  (benchmarks/segmentation.py)

SCANS = {"female": "vhp_female_head", "male": "vhp_male_head"}


def cd_export(src, root, compressor):
    """``src``'s slices as an export: DICOMDIR, DICOM/ST000000/SE000001/IM000001, ..."""
    series = root / "DICOM" / "ST000000" / "SE000001"
    compress_folder(src, series, compressor, "*.dcm")
    for k, path in enumerate(sorted(series.iterdir())):
        path.rename(series / f"IM{k + 1:06d}")
    (root / "DICOMDIR").write_bytes(b"\0" * 128 + b"DICM")
    return root


def multiframe(src, root):
    files = sorted(src.glob("*.dcm"))
    root.mkdir(parents=True)
    enhanced_from_slices(files, root / "IM000001",
                         order=np.random.default_rng(0).permutation(len(files)))
    return root


def cpu_read(path, repeat):
    times, image = [], None
    for _ in range(repeat):
        t = time.process_time()
        image = pvcmf.read_ct(path)
        times.append(time.process_time() - t)
    return float(np.median(times)), image


def size_mb(path):
    return sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file()) / 1e6


def rows_for(name, src, tmp, repeat):
    plain_s, plain = cpu_read(src, repeat)
    cases = [("plain slice files", src)]
    cases.append(("CD export, JPEG Lossless", cd_export(src, tmp / f"{name}_jpeg", "JPEG")))
    cases.append(("CD export, JPEG 2000", cd_export(src, tmp / f"{name}_j2k", "JPEG2000")))
    cases.append(("Enhanced CT, one multi-frame file", multiframe(src, tmp / f"{name}_mf")))
    rows = []
    for case, path in cases:
        s, image = (plain_s, plain) if path == src else cpu_read(path, repeat)
        same = (image.dimensions == plain.dimensions
                and np.allclose(image.origin, plain.origin)
                and np.allclose(image.spacing, plain.spacing)
                and np.array_equal(image[arrays.CT], plain[arrays.CT]))
        rows.append(f"| {name} | {case} | {'x'.join(map(str, image.dimensions))} | "
                    f"{size_mb(path):.0f} | {s:.2f} | {s / plain_s:.2f} | "
                    f"{'yes' if same else 'NO'} |")
        print(rows[-1], flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--write", action="store_true", help="write docs/benchmarks/reading.md")
    args = ap.parse_args()
    data = data_folder(SCANS["female"]).parent
    rows = ["| head | as | voxels | MB | read, CPU s | / plain | same volume |",
            "|---|---|---|---:|---:|---:|---|"]
    tmp = Path(tempfile.mkdtemp(prefix="pvcmf-reading-"))
    try:
        for name, folder in SCANS.items():
            rows += rows_for(name, data / folder, tmp, args.repeat)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    command = ("PVCMF_DATA_DIR=/path/to/data python benchmarks/reading.py "
               f"--repeat {args.repeat} --write")
    write_page("reading", "Reading DICOM exports", [
        "The Visible Human heads' plain DICOM slices written as exports deliver them and read "
        "by `pvcmf.read_ct`: a CD or PACS export (a DICOMDIR beside nested folders of files "
        "without a suffix) with every slice JPEG Lossless (GDCM's encoding: the usual lossless "
        "compression of PACS exports, which pydicom decodes only with a plugin, so GDCM decodes "
        "it here) or JPEG 2000, and one Enhanced CT multi-frame file with its frames shuffled. "
        "CPU seconds of the read (median of the repeats), the files' size, and whether the "
        "volume equals the plain read voxel for voxel with the same origin and spacing.",
        "",
        *rows,
    ], command, args.write)


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    main()
