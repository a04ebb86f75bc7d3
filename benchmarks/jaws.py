"""The jaws found from the anatomy on scans reconstructed in thick slices, on heads scanned
tilted and on noisy or blurred scans, against the same scan's jaws at 1 mm, upright and as
scanned (Visible Human female and male), and against the virtual patient's true segments.

Not run by CI. ``python benchmarks/jaws.py [--write]`` (needs ``PVCMF_DATA_DIR``; about 15
minutes on two cores). Thick slices: every ``step``-th slice of the 1 mm scan kept, from
each slice position (``phase``); the Dice of the mandible and the Le Fort I maxilla against
the 1 mm scan's on the slices kept. Tilted: the 1 mm scan turned through its centre about
the left-right axis (trilinear; chin down for a negative angle), the vertical one (yaw) or
the anterior one (roll), against the upright scan's jaws turned the same way (nearest
voxel). Degraded: correlated Gaussian noise added (``NOISE_HU``), or the scan blurred by a
Gaussian of ``BLUR_VOXELS`` voxels. Virtual patient 1 (2 mm): its labels and its true
segments turned the same way (nearest voxel). ``--write`` also writes
``docs/benchmarks/jaws.md`` with the command and the machine.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's pvcmf

import pvcmf  # noqa: E402
from pvcmf import arrays  # noqa: E402
from pvcmf.filters.bone_segments import segment_volumes  # noqa: E402
from segmentation import data_folder, write_page  # noqa: E402  (benchmarks/segmentation.py)

ROOT = Path(__file__).resolve().parents[1]
SCANS = {"female": "vhp_female_head", "male": "vhp_male_head"}
STEPS = ((2, (0, 1)), (3, (0, 1, 2)), (4, (0, 2)), (5, (0, 3)))
PITCH = (-15.0, -8.0, 15.0)
#: other turns (degrees) of the head: about the vertical axis (yaw) and the anterior one (roll)
TURNS = (("z", 10.0), ("y", 6.0), ("y", -10.0))
#: standard deviations (HU) of the added noise (Gaussian, correlated over about a voxel, as a
#: low-dose reconstruction's)
NOISE_HU = (30.0, 60.0)
#: standard deviation (voxels) of the Gaussian blur standing for a smoother reconstruction
#: kernel than the scan's own
BLUR_VOXELS = 1.0
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


def turned(values, spacing, degrees, order, cval, axis="x"):
    a = np.radians(degrees)
    c_, s_ = np.cos(a), np.sin(a)
    turn = {"x": np.array([[1, 0, 0], [0, c_, -s_], [0, s_, c_]]),
            "y": np.array([[c_, 0, s_], [0, 1, 0], [-s_, 0, c_]]),
            "z": np.array([[c_, -s_, 0], [s_, c_, 0], [0, 0, 1]])}[axis]
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
    for axis, degrees in TURNS:
        img = image(turned(v, ct.spacing, degrees, 1, float(v.min()), axis), ct.spacing,
                    ct.origin)
        found, warned = jaws(img)
        what = {"z": "vertical axis (yaw)", "y": "anterior axis (roll)"}[axis]
        rows.append(row(name, f"turned {degrees:+g} degrees about the {what}", found,
                        turned(ref, ct.spacing, degrees, 0, 0, axis), warned))
        print(rows[-1], flush=True)
    return rows + degraded_rows(name, ct, v, ref)


def degraded_rows(name, ct, v, ref):
    """The scan with noise added and blurred, against its own jaws."""
    rows = []
    rng = np.random.default_rng(0)
    for sd in NOISE_HU:
        noise = ndimage.gaussian_filter(rng.normal(0.0, 1.0, v.shape).astype(np.float32), 0.8)
        found, warned = jaws(image(v + noise * np.float32(sd / noise.std()), ct.spacing,
                                   ct.origin))
        rows.append(row(name, f"noise {sd:g} HU", found, ref, warned))
        print(rows[-1], flush=True)
    sigma = np.round(BLUR_VOXELS * np.asarray(ct.spacing), 2).tolist()
    found, warned = jaws(image(ndimage.gaussian_filter(v, BLUR_VOXELS), ct.spacing, ct.origin))
    rows.append(row(name, f"blurred (Gaussian, sigma {sigma} mm)", found, ref, warned))
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
    root = data_folder(SCANS["female"]).parent
    rows = ["| head | scan | Dice hard tissue | mandible (mL) | maxilla (mL) | Dice mandible | "
            "Dice maxilla | warned |", "|---|---|---:|---:|---:|---:|---:|---|"]
    for name, folder in SCANS.items():
        rows += real_rows(name, root / folder)
    rows += phantom_rows()
    command = "PVCMF_DATA_DIR=/path/to/data python benchmarks/jaws.py --write"
    write_page("jaws", "Jaws from the anatomy: thick slices, tilted heads, noise and blur", [
        "`pvcmf.filters.find_jaws` on the Visible Human heads reconstructed in thick slices "
        "(every 2nd to 5th slice of the 1 mm scan kept, from each slice position), turned "
        "about the left-right axis (negative: chin down), the vertical axis and the anterior "
        "one, with noise added (Gaussian, correlated over about a voxel) and blurred (a "
        "Gaussian of one voxel, standing for a smoother reconstruction kernel), against the "
        "same scan's jaws at 1 mm, upright and as scanned (on the slices kept; turned the "
        "same way, nearest voxel); and the "
        "virtual patient's labels turned likewise against its true segments. Dice of the "
        "hard tissue as a whole (what the resampling and the segmentation of the thick or "
        "turned image leave: the segments cannot agree better), of the mandible and of the "
        "Le Fort I maxilla; `warned`: find_jaws logged a warning (an occlusion it cannot "
        "split, no nasal floor).",
        "",
        *rows,
    ], command, args.write)


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    logging.getLogger().handlers[0].setLevel(logging.ERROR)  # counted, not printed
    logging.getLogger("pvcmf").setLevel(logging.WARNING)
    main()
