"""A real head CT from DICOM to a predicted face: the Visible Human female
==========================================================================

The whole chain on a real scan, the Visible Human female head (NLM; 1 mm DICOM series,
512 x 512 x 234, Hounsfield units, ``$PVCMF_DATA_DIR/vhp_female_head``):

1. :func:`pvcmf.read_ct` reads the series in the patient frame and
   :func:`pvcmf.filters.standardize` checks the units and the axes (face +y, vertex +z);
2. :func:`pvcmf.filters.segment` labels air, soft tissue, bone, teeth and the intracranial
   volume: three orthogonal slices with the labels over the CT;
3. :func:`pvcmf.filters.find_jaws` finds the mandible and the Le Fort I maxilla from the
   anatomy alone (no cut planes): both in 3D with the skull;
4. :func:`pvcmf.filters.classify_tissue` splits the soft tissue into fat and muscle (paper
   001: per-slice Gaussian mixtures, EM, 5x5 median);
5. :func:`pvcmf.pipeline.simulate` predicts the face after a plan that names the segment
   only: the maxilla 3 mm forward. The prediction runs on a 2 mm copy of the scan (the
   resolution of ``pvcmf demo``): pre-operative and predicted face, frontal and profile,
   and the midsagittal profiles overlaid.

The script takes a few minutes on two cores, so the documentation shows its code without
running it. Without the data it does nothing.
"""

import os
from pathlib import Path

import numpy as np
import pyvista as pv
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from PIL import Image

import pvcmf
from pvcmf import arrays
from pvcmf.figures.face_views import (VIEW_TITLES, add_patient_mesh, prediction_summary,
                                     set_view, to_display)
from pvcmf.io.orientation import standardize
from pvcmf.pipeline import DEFAULT_FACE_FRACTION, face_box, simulate
from pvcmf.plan import Osteotomy, Plan

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)
FOLDER = Path(os.environ.get("PVCMF_DATA_DIR", "")) / "vhp_female_head"

#: label colours (tissue ids of pvcmf.arrays) and names
COLORS = {arrays.AIR: (0, 0, 0, 0), arrays.FAT: (1.0, 0.8, 0.3, 0.45),
          arrays.MUSCLE_TISSUE: (0.85, 0.15, 0.15, 0.55), arrays.BONE_TISSUE: (0.3, 0.55, 1.0, 0.6),
          arrays.TEETH: (1.0, 1.0, 1.0, 0.9), arrays.INTRACRANIAL: (0.6, 0.3, 0.8, 0.35),
          arrays.METAL: (0.2, 1.0, 0.2, 0.9)}
NAMES = {arrays.FAT: "fat", arrays.MUSCLE_TISSUE: "muscle",
         arrays.BONE_TISSUE: "bone", arrays.TEETH: "teeth", arrays.INTRACRANIAL: "intracranial",
         arrays.METAL: "metal"}


def volume(image, name):
    """A point array of an image as an (x, y, z) volume."""
    return np.asarray(image[name]).reshape(image.dimensions, order="F")


def downsample(image, step=2):
    """Every ``step``-th voxel of every point array (a coarser copy of the image)."""
    out = pv.ImageData(dimensions=tuple(len(range(0, d, step)) for d in image.dimensions),
                       spacing=tuple(step * np.asarray(image.spacing)), origin=image.origin)
    for name in image.point_data.keys():
        vol = volume(image, name)[::step, ::step, ::step]
        out[name] = np.ascontiguousarray(vol).ravel(order="F")
    return out


def label_slices(labels, ct, cut, classes, title, names=None):
    """Axial, coronal and sagittal slices through voxel ``cut``: CT in grey, labels over it."""
    cmap = ListedColormap([COLORS[k] for k in range(max(COLORS) + 1)])
    hu, tissue = volume(ct, arrays.CT), volume(labels, arrays.TISSUE)
    # the head's box (10 voxels wider): the scan's air around it is left out
    box = tuple(slice(max(int(a.min()) - 10, 0), int(a.max()) + 11)
                for a in np.nonzero(tissue != arrays.AIR))
    hu, tissue = hu[box], tissue[box]
    sx, sy, sz = ct.spacing
    i, j, k = (int(c) - b.start for c, b in zip(cut, box))
    views = (("axial", hu[:, :, k].T, tissue[:, :, k].T, sy / sx, "x (left +)", "y (anterior +)"),
             ("coronal", hu[:, j, :].T, tissue[:, j, :].T, sz / sx, "x (left +)", "z (superior +)"),
             ("sagittal", hu[i, :, :].T, tissue[i, :, :].T, sz / sy, "y (anterior +)",
              "z (superior +)"))
    fig = Figure(figsize=(14, 6.0))
    axes = fig.subplots(1, 3)
    for ax, (name, grey, lab, aspect, xl, yl) in zip(axes, views):
        ax.imshow(np.clip(grey, -400, 1500), cmap="gray", origin="lower", aspect=aspect,
                  interpolation="nearest")
        ax.imshow(lab, cmap=cmap, vmin=-0.5, vmax=max(COLORS) + 0.5, origin="lower",
                  aspect=aspect, interpolation="nearest")
        ax.set_title(name)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_xticks([])
        ax.set_yticks([])
    names = {**NAMES, **(names or {})}
    fig.legend(handles=[Patch(facecolor=COLORS[c][:3], edgecolor="k", label=names[c])
                        for c in classes],
               loc="lower center", ncol=len(classes), frameon=False)
    fig.suptitle(title)
    fig.subplots_adjust(left=0.03, right=0.99, top=0.9, bottom=0.12, wspace=0.12)
    return fig


if FOLDER.is_dir():
    ct = pvcmf.read_ct(FOLDER)
    ct, report = standardize(ct)
    labels = pvcmf.filters.segment(ct)
    tissue = volume(labels, arrays.TISSUE)
    print("CT", ct.dimensions, "spacing", ct.spacing, "standardize:", report)
    print("tissue volumes (mL):", pvcmf.filters.segmentation.tissue_volumes(labels))

# %%
# Segmentation: three orthogonal slices through the upper teeth
# -------------------------------------------------------------
# The axial slice is the one with the most teeth voxels; the coronal one passes through
# the anterior maxilla, the sagittal one through the midline.
if FOLDER.is_dir():
    hard = np.isin(tissue, arrays.HARD_LABELS)
    teeth = tissue == arrays.TEETH
    k = int(np.argmax(teeth.sum(axis=(0, 1)))) if teeth.any() else tissue.shape[2] // 3
    i = tissue.shape[0] // 2
    rows = np.flatnonzero(hard[:, :, k].any(axis=0))
    j = int(rows.max() - 12 / ct.spacing[1]) if rows.size else tissue.shape[1] // 2
    fig = label_slices(labels, ct, (i, j, k), (arrays.FAT, arrays.BONE_TISSUE, arrays.TEETH,
                                               arrays.INTRACRANIAL),
                       "pvcmf.filters.segment on the Visible Human female (1 mm)",
                       names={arrays.FAT: "soft tissue"})
    fig.savefig(OUT / "female_segmentation.png", dpi=90)

# %%
# Bone segments found from the anatomy: cranium, maxilla, mandible
# ----------------------------------------------------------------
if FOLDER.is_dir():
    jaws = pvcmf.filters.find_jaws(labels)
    print("bone segment volumes (mL):", pvcmf.filters.bone_segments.segment_volumes(jaws))
    coarse = downsample(jaws, 2)
    bone = volume(coarse, arrays.BONE)
    colours = {arrays.CRANIUM: ("wheat", 0.3), arrays.MAXILLA: ("tomato", 1.0),
               arrays.MANDIBLE: ("royalblue", 1.0)}
    surfaces = {}
    for seg in colours:
        mask = pv.ImageData(dimensions=coarse.dimensions, spacing=coarse.spacing,
                            origin=coarse.origin)
        mask["m"] = (bone == seg).astype(np.float32).ravel(order="F")
        if np.any(mask["m"]):
            surfaces[seg] = mask.contour([0.5], scalars="m").smooth(n_iter=20)
    # framed on the skull (its largest piece: stray bone voxels far from the head would
    # move the frame)
    skull = surfaces.get(arrays.CRANIUM, surfaces.get(arrays.MANDIBLE))
    bounds = to_display(skull.connectivity("largest")).bounds
    shots = []
    for view in ("frontal", "profile"):
        pl = pv.Plotter(window_size=(600, 640))
        for seg, surf in surfaces.items():
            colour, opacity = colours[seg]
            add_patient_mesh(pl, surf, color=colour, opacity=opacity, label=arrays.BONE_NAMES[seg])
        set_view(pl, bounds, view)
        pl.add_text(VIEW_TITLES[view], font_size=11, color="black")
        if view == "frontal":
            pl.add_legend(bcolor=(0.35, 0.35, 0.35), face="rectangle", size=(0.28, 0.14),
                          loc="lower left")
        shots.append(pl.screenshot(return_img=True))
        pl.close()
    Image.fromarray(np.hstack(shots)).save(OUT / "female_jaws.png")

# %%
# Fat and muscle (paper 001's classification)
# -------------------------------------------
if FOLDER.is_dir():
    classified = pvcmf.filters.classify_tissue(labels)
    fig = label_slices(classified, ct, (i, j, k), (arrays.FAT, arrays.MUSCLE_TISSUE,
                                                   arrays.BONE_TISSUE, arrays.TEETH),
                       "pvcmf.filters.classify_tissue: fat and muscle")
    fig.savefig(OUT / "female_classification.png", dpi=90)

# %%
# A prediction: the maxilla 3 mm forward
# ---------------------------------------
# The plan names the segment only; :func:`pvcmf.filters.find_jaws` cuts it out of the bone.
# The pipeline's defaults: fat/muscle classification, the muscle atlas fitted automatically,
# 25,000 tetrahedra over the anterior half of the head.
if FOLDER.is_dir():
    plan = Plan((Osteotomy("maxilla", translation=(0.0, 0.0, 3.0)),), name="maxilla 3 mm forward")
    result = simulate(downsample(ct, 2), plan, units="hu", orient="none", figures=False)
    print(result.summary())
    # the face: the skin in front of the modelled region's posterior plane (the whole head's
    # skin would frame the back of the head in profile) and within 15 mm of the skull's
    # width (the shoulder the field of view cuts would move the midsagittal plane)
    y0 = face_box(result.labels, DEFAULT_FACE_FRACTION)[2]
    x0, x1 = skull.connectivity("largest").bounds[:2]
    points = np.asarray(result.skin_pre.points)
    behind = (points[:, 1] < y0) | (points[:, 0] < x0 - 15.0) | (points[:, 0] > x1 + 15.0)
    pre, post = (skin.extract_points(~behind, adjacent_cells=False).extract_surface(
        algorithm="dataset_surface") for skin in (result.skin_pre, result.skin_post))
    image = prediction_summary(pre, post)
    Image.fromarray(image).save(OUT / "female_prediction.png")
