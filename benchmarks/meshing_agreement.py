"""The centroid label-agreement test of ``benchmarks/meshing.py``: its ceiling and its failures.

``--ceiling`` (:func:`agreement_ceiling`): how often a point at a given depth inside a
smooth region has another label in its nearest voxel, what the centroid test reports for
exactly placed surfaces. ``--table`` (:func:`agreement_table`): the agreement against the
requested count with the failing cells split by class and by the thin structures that
explain them (:func:`disagreement_split`). Delegates the distance transforms and
morphology to :mod:`scipy.ndimage`.
"""

from __future__ import annotations

import json

import numpy as np

import pvcmf
from pvcmf import arrays
from pvcmf.filters import meshing

from meshing import _labels, _muscle_volume_error, _roi, _timed


def agreement_ceiling(patient, spacing, fine_spacing=None, n_samples=3_000_000, face_fraction=0.5, seed=0):
    """How often a point at a given depth inside a smooth region lands in another voxel.

    The virtual patient built at ``fine_spacing`` (default ``spacing / 2``) stands in for
    the smooth anatomy: random points in the ROI get its label and their depth inside
    that region (distance transform), and the label of the nearest ``spacing`` voxel is
    compared with it. A mesh whose surfaces lay exactly on the anatomy would have this
    disagreement rate for centroids at that depth: the ceiling of the centroid test.
    Returns the rate per depth bin (mm) in per mille.
    """
    from scipy import ndimage

    fine_spacing = fine_spacing or spacing / 2.0
    coarse = _labels(patient, spacing)
    fine = pvcmf.datasets.phantom(patient, spacing=fine_spacing).truth
    box = np.asarray(_roi(coarse, face_fraction) or coarse.bounds, float)
    rng = np.random.default_rng(seed)
    lo, hi = box[0::2], box[1::2]
    pts = lo + rng.random((n_samples, 3)) * (hi - lo)

    def nearest(img, p):
        ijk = np.rint((p - np.asarray(img.origin)) / np.asarray(img.spacing)).astype(int)
        ijk = np.clip(ijk, 0, np.asarray(img.dimensions) - 1)
        d = img.dimensions
        return np.asarray(img[arrays.TISSUE])[ijk[:, 0] + d[0] * (ijk[:, 1] + d[1] * ijk[:, 2])], ijk

    lab, ijk = nearest(fine, pts)
    soft = np.isin(lab, arrays.SOFT_LABELS)
    pts, lab, ijk = pts[soft], lab[soft], ijk[soft]
    tissue = np.asarray(fine[arrays.TISSUE]).reshape(fine.dimensions[::-1])
    depth = np.zeros(len(pts))
    for value in arrays.SOFT_LABELS:
        inside = ndimage.distance_transform_edt(tissue == value, sampling=fine_spacing)
        s = lab == value
        depth[s] = inside[ijk[s, 2], ijk[s, 1], ijk[s, 0]] - 0.5 * fine_spacing
    bad = nearest(coarse, pts)[0] != lab
    edges = [0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0, np.inf]
    out = {"spacing": spacing, "fine_spacing": fine_spacing}
    for a, b in zip(edges[:-1], edges[1:]):
        s = (depth >= a) & (depth < b)
        if s.any():
            out[f"depth_{a:g}-{b:g}_mm_permille"] = round(1000 * float(bad[s].mean()))
    return out


def _thin_near(labels, box_ijk, label, h):
    """Voxels (z, y, x, in ``box_ijk``) within one voxel of a part of ``label`` thinner than ``h``.

    A voxel of the region is thin when no ball of diameter ``h`` inside the region covers
    it (it is removed by a morphological opening with that ball; two Euclidean distance
    transforms, ``scipy.ndimage``): the local thickness there is below ``h``.
    """
    from scipy import ndimage

    tissue = np.asarray(labels[arrays.TISSUE]).reshape(labels.dimensions[::-1])[box_ijk]
    region = tissue == label
    sampling = np.asarray(labels.spacing, float)[::-1]
    r = 0.5 * h
    # depth below the region's surface (the voxel faces): a boundary voxel's centre lies
    # half a voxel deep, while the distance transform measures to the next voxel centre
    depth = ndimage.distance_transform_edt(region, sampling=sampling) - 0.5 * sampling.min()
    centres = region & (depth >= r)
    covered = ndimage.distance_transform_edt(~centres, sampling=sampling) <= r if centres.any() else np.zeros_like(region)
    thin = region & ~covered
    return ndimage.binary_dilation(thin, structure=np.ones((3, 3, 3), bool))


def disagreement_split(labels, grid):
    """Where the centroid test fails: shares of all cells, and how many thin structures explain.

    Every cell whose centroid's nearest voxel holds another tissue label is put in one
    class: a fat cell in a muscle voxel or a muscle cell in a fat voxel ("fat/muscle"),
    or by the voxel's label ("bone", "air", "teeth", "other"). A failing cell is
    "explained by a thin structure" when its centroid voxel lies within one voxel of a
    part of its own label or of the voxel's label thinner than the working spacing ``h``
    (the element size; :func:`_thin_near`), and "at the boundary" when a voxel of its own
    label is among the 26 neighbours of its centroid voxel. The thin test is repeated for
    structures thinner than half the element (``h / 2``), and both are also run on every
    cell (``all_thin_permille``, ``all_half_thin_permille``): where a test flags as large
    a share of all cells as of the failing ones, it does not single the failing ones out.
    Returns per-mille numbers.
    """
    from scipy import ndimage

    h = float(grid.field_data[meshing.SURFACE_SPACING][0])
    sp = np.asarray(labels.spacing, float)
    dims = np.asarray(labels.dimensions)
    c = grid.cell_centers().points
    ijk = np.clip(np.rint((c - np.asarray(labels.origin)) / sp).astype(int), 0, dims - 1)
    margin = int(np.ceil(h / sp.min())) + 2
    lo = np.maximum(ijk.min(axis=0) - margin, 0)
    hi = np.minimum(ijk.max(axis=0) + margin + 1, dims)
    box = tuple(slice(lo[k], hi[k]) for k in (2, 1, 0))
    rel = ijk - lo
    tissue = np.asarray(labels[arrays.TISSUE]).reshape(labels.dimensions[::-1])[box]
    image = tissue[rel[:, 2], rel[:, 1], rel[:, 0]]
    cell = np.asarray(grid.cell_data[arrays.TISSUE])
    bad = image != cell
    n = len(cell)
    classes = {
        "fat_muscle": bad & np.isin(image, arrays.SOFT_LABELS),
        "bone": bad & (image == arrays.BONE_TISSUE),
        "air": bad & (image == arrays.AIR),
        "teeth": bad & (image == arrays.TEETH),
    }
    classes["other"] = bad & ~np.any(list(classes.values()), axis=0)
    thin = np.zeros(n, bool)  # every cell, failing or not
    thin_half = np.zeros(n, bool)  # the same for structures thinner than half the element
    near_own = np.zeros(n, bool)
    for label in np.unique(np.concatenate([image, cell])):
        mine = (cell == label) | (image == label)
        thin |= mine & _thin_near(labels, box, int(label), h)[rel[:, 2], rel[:, 1], rel[:, 0]]
        thin_half |= mine & _thin_near(labels, box, int(label), h / 2)[rel[:, 2], rel[:, 1], rel[:, 0]]
        own = ndimage.binary_dilation(tissue == label, structure=np.ones((3, 3, 3), bool))
        near_own |= bad & (cell == label) & own[rel[:, 2], rel[:, 1], rel[:, 0]]
    out = {"spacing_x100": round(100 * h), "agree_permille": round(1000 * (1 - bad.mean()))}
    for name, sel in classes.items():
        out[f"{name}_permille"] = round(1000 * sel.sum() / n)
        out[f"{name}_thin_permille_of_class"] = round(1000 * (thin & sel).sum() / max(sel.sum(), 1))
    out["bad_thin_permille_of_bad"] = round(1000 * (thin & bad).sum() / max(bad.sum(), 1))
    out["all_thin_permille"] = round(1000 * thin.mean())  # the same test on every cell
    out["bad_not_thin_permille"] = round(1000 * (bad & ~thin).mean())  # of all cells
    out["bad_half_thin_permille_of_bad"] = round(1000 * (thin_half & bad).sum() / max(bad.sum(), 1))
    out["all_half_thin_permille"] = round(1000 * thin_half.mean())
    out["bad_next_to_own_permille_of_bad"] = round(1000 * near_own.sum() / max(bad.sum(), 1))
    return out


def agreement_table(cases, counts_by_spacing, face_fraction=0.5):
    """Agreement against the requested count with :func:`disagreement_split`, one row a mesh."""
    import warnings

    warnings.simplefilter("ignore")
    rows = []
    for patient, spacing in cases:
        labels = _labels(patient, spacing)
        roi = _roi(labels, face_fraction)
        for n in counts_by_spacing[spacing]:
            grid, wall, cpu = _timed(meshing.tetrahedralize, labels, n_tets=n, roi=roi)
            row = {"patient": patient, "spacing_mm": spacing, "n_tets": n, "cells": grid.n_cells,
                   "wall_ms": round(1000 * wall)}
            row.update(disagreement_split(labels, grid))
            mv = [x for x in _muscle_volume_error(labels, grid) if x is not None]
            row["muscle_volume_rms_percent"] = round(float(np.sqrt(np.mean(np.square(mv)))))
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def agreement_markdown(rows):
    """The rows of :func:`agreement_table` as a markdown table (% of all cells per class)."""
    head = ("| image | requested | cells | agree % | fat/muscle | bone | air | teeth | other "
            "| thin-explained % of failing (of all cells) | next to own label % of failing "
            "| failing, not thin: % of all cells | same as col. 10 for h/2 | muscle vol. RMS % |")
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        cls = [f"{r[f'{k}_permille'] / 10:.1f} ({r[f'{k}_thin_permille_of_class'] // 10})"
               for k in ("fat_muscle", "bone", "air", "teeth", "other")]
        lines.append(
            f"| P{r['patient']} {r['spacing_mm']:g} mm | {r['n_tets'] // 1000}k | {r['cells']} "
            f"| {r['agree_permille'] / 10:.1f} | " + " | ".join(cls)
            + f" | {r['bad_thin_permille_of_bad'] / 10:.0f} ({r['all_thin_permille'] / 10:.0f})"
            f" | {r['bad_next_to_own_permille_of_bad'] / 10:.0f} | {r['bad_not_thin_permille'] / 10:.1f}"
            f" | {r['bad_half_thin_permille_of_bad'] / 10:.0f} ({r['all_half_thin_permille'] / 10:.0f})"
            f" | {r['muscle_volume_rms_percent']} |"
        )
    return "\n".join(lines)
