"""Paper 000 Fig. 2b: a slice of the tissue + muscle label image
================================================================

The label image that the muscle-embedded meshing starts from: soft tissue (yellow), bone
and teeth, and each embedded facial muscle with its own value (colour), written by
``embed_muscles`` only where the image held soft tissue. The axial slice shown is the one
holding the most muscle voxels (masseters, zygomatici, levators).
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
