"""The jaws found from the anatomy on scans reconstructed in thick slices and on heads scanned
tilted, against the same scan's jaws at 1 mm and upright (Visible Human female and male),
and against the virtual patient's true segments.

Not run by CI. ``python benchmarks/jaws.py [--write]`` (needs ``PVCMF_DATA_DIR``; about 10
minutes on two cores). Thick slices: every ``step``-th slice of the 1 mm scan kept, from
each slice position (``phase``); the Dice of the mandible and the Le Fort I maxilla against
the 1 mm scan's on the slices kept. Tilted: the 1 mm scan turned about the left-right axis
through its centre (trilinear; chin down for a negative angle), against the upright scan's
jaws turned the same way (nearest voxel). Virtual patient 1 (2 mm): its labels and its true
segments turned the same way (nearest voxel). ``--write`` also writes
``docs/benchmarks/jaws.md`` with the command and the machine.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's pvcmf

import pvcmf  # noqa: E402
from pvcmf import arrays  # noqa: E402
from pvcmf.filters.bone_segments import segment_volumes  # noqa: E402
from segmentation import machine  # noqa: E402  (benchmarks/segmentation.py)

ROOT = Path(__file__).resolve().parents[1]
SCANS = {"female": "vhp_female_head", "male": "vhp_male_head"}
STEPS = ((2, (0, 1)), (3, (0, 1, 2)), (4, (0, 2)), (5, (0, 3)))
PITCH = (-15.0, -8.0, 15.0)
PHANTOM_PITCH = (-30.0, -20.0, -10.0, 0.0, 10.0, 20.0, 30.0)


def dice(a, b):
    return 2.0 * np.count_nonzero(a & b) / max(np.count_nonzero(a) + np.count_nonzero(b), 1)


def image(values, spacing, origin):
    img = pv.ImageData(dimensions=values.shape, spacing=spacing, origin=origin)
    img[arrays.CT] = np.ascontiguousarray(values, dtype=np.float32).ravel(order="F")
    return img


def jaws(img):
    """Bone labels of a CT, and the warnings find_jaws logged."""
    said = []
    handler = logging.Handler(logging.WARNING)
    handler.emit = lambda record: said.append(record.getMessage())
    logger = logging.getLogger("pvcmf.filters")
    logger.addHandler(handler)
    try:
        found = pvcmf.filters.find_jaws(pvcmf.filters.segment(img))
    finally:
        logger.removeHandler(handler)
    return found, [w for w in said if w.startswith("find_jaws")]


def turned(values, spacing, degrees, order, cval):
    a = np.radians(degrees)
    turn = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    s = np.asarray(spacing, float)
    c = (np.asarray(values.shape) - 1) / 2
    matrix = (turn.T * s[None, :]) / s[:, None]
    return ndimage.affine_transform(values, matrix, offset=c - matrix @ c, order=order,
                                    cval=cval)


def row(name, case, found, ref, warned):
    """One table row: volumes, the Dice of each segment and of the hard tissue as a whole
    (the bound that the resampling and the segmentation put on the segments' Dice)."""
    bone = volume_of(found, arrays.BONE)
    vols = segment_volumes(found)
    return (f"| {name} | {case} | {dice(bone > 0, ref > 0):.3f} | "
            f"{vols.get('mandible', 0.0):.1f} | "
            f"{vols.get('maxilla', 0.0):.1f} | "
            f"{dice(bone == arrays.MANDIBLE, ref == arrays.MANDIBLE):.3f} | "
            f"{dice(bone == arrays.MAXILLA, ref == arrays.MAXILLA):.3f} | "
            f"{'yes' if warned else ''} |")


def real_rows(name, folder):
    ct = pvcmf.read_ct(folder, frame="patient")
    v = volume_of(ct, arrays.CT).astype(np.float32)
    upright, _ = jaws(ct)
    ref = volume_of(upright, arrays.BONE)
    rows = [row(name, "1 mm, upright", upright, ref, [])]
    for step, phases in STEPS:
        for phase in phases:
            img = image(v[:, :, phase::step], (*ct.spacing[:2], ct.spacing[2] * step),
                        np.asarray(ct.origin) + [0, 0, phase * ct.spacing[2]])
            found, warned = jaws(img)
            rows.append(row(name, f"{step * ct.spacing[2]:g} mm slices from slice {phase}",
                            found, ref[:, :, phase::step], warned))
            print(rows[-1], flush=True)
    for degrees in PITCH:
        img = image(turned(v, ct.spacing, degrees, 1, float(v.min())), ct.spacing, ct.origin)
        found, warned = jaws(img)
        rows.append(row(name, f"turned {degrees:+g} degrees", found,
                        turned(ref, ct.spacing, degrees, 0, 0), warned))
        print(rows[-1], flush=True)
    return rows


def phantom_rows():
    case = pvcmf.datasets.phantom(patient=1, spacing=2.0)
    lab = pvcmf.filters.segment(case.ct)
    tissue, truth = volume_of(lab, arrays.TISSUE), volume_of(case.truth, arrays.BONE)
    rows = []
    for degrees in PHANTOM_PITCH:
        img = pv.ImageData(dimensions=lab.dimensions, spacing=lab.spacing, origin=lab.origin)
        t_turned = turned(tissue, lab.spacing, degrees, 0, arrays.AIR)
        img[arrays.TISSUE] = t_turned.ravel(order="F")
        found = pvcmf.filters.find_jaws(img)
        ref = turned(truth, lab.spacing, degrees, 0, 0)
        ref = np.where(np.isin(t_turned, arrays.HARD_LABELS), ref, 0)
        rows.append(row("virtual patient 1", f"turned {degrees:+g} degrees", found, ref, []))
        print(rows[-1], flush=True)
    return rows


def volume_of(img, name):
    return np.asarray(img[name]).reshape(img.dimensions, order="F")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--write", action="store_true", help="write docs/benchmarks/jaws.md")
    args = ap.parse_args()
    root = Path(os.environ.get("PVCMF_DATA_DIR", ROOT / ".." / "shared" / "data"))
    if not (root / SCANS["female"]).is_dir():
        raise SystemExit(f"{root / SCANS['female']} not found: set PVCMF_DATA_DIR")
    rows = ["| head | scan | Dice hard tissue | mandible (mL) | maxilla (mL) | Dice mandible | "
            "Dice maxilla | warned |", "|---|---|---:|---:|---:|---:|---:|---|"]
    for name, folder in SCANS.items():
        rows += real_rows(name, root / folder)
    rows += phantom_rows()
    command = "PVCMF_DATA_DIR=/path/to/data python benchmarks/jaws.py --write"
    text = "\n".join([
        "# Jaws from the anatomy: thick slices and tilted heads",
        "",
        "`pvcmf.filters.find_jaws` on the Visible Human heads reconstructed in thick slices "
        "(every 2nd to 5th slice of the 1 mm scan kept, from each slice position) and turned "
        "about the left-right axis (negative: chin down), against the same scan's jaws at "
        "1 mm and upright (on the slices kept; turned the same way, nearest voxel); and the "
        "virtual patient's labels turned likewise against its true segments. Dice of the "
        "hard tissue as a whole (what the resampling and the segmentation of the thick or "
        "turned image leave: the segments cannot agree better), of the mandible and of the "
        "Le Fort I maxilla; `warned`: find_jaws logged a warning (an occlusion it cannot "
        "split, no nasal floor).",
        "",
        *rows,
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine()}.\n",
    ])
    print(text)
    if args.write:
        (ROOT / "docs" / "benchmarks" / "jaws.md").write_text(text)


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger().handlers[0].setLevel(logging.ERROR)  # counted, not printed
    logging.getLogger("pvcmf").setLevel(logging.WARNING)
    main()
