"""Paper 000 Fig. 2b: a slice of the tissue + muscle label image
================================================================

The image the muscle-embedded meshing starts from, drawn as the paper does: the
extra-cranial soft tissue with one value (yellow) and the facial muscle segments with
another (red), written by ``embed_muscles`` only where the image held soft tissue; bone,
teeth and the intracranial volume lie outside the image domain (black). The axial slice
shown is the one holding the most muscle voxels (masseters, zygomatici, levators). A
second figure gives every tissue label and muscle kind its own colour.
"""

import os
from pathlib import Path

import pvcmf
from pvcmf.figures.muscles import figure_2b

OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(1, spacing=1.0)
labels = case.truth.cmf.embed_muscles(landmarks=case.landmarks)
figure_2b(labels).savefig(OUT / "fig2b_label_slice.png", dpi=120)
figure_2b(labels, style="labels").savefig(OUT / "fig2b_label_slice_labels.png", dpi=120)
