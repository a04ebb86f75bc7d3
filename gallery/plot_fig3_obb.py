"""Paper 000 Fig. 3: muscle fibre directions from oriented bounding boxes
========================================================================

Each embedded muscle is boxed by an oriented bounding box (principal axes of its voxels):
one box for the masseter, two-level boxes (the muscle halved along its long axis, one box
per half) for the others. The long axis of each box (black line) is the fibre direction
of the voxels in it (``labels.cmf.fiber_directions()`` writes it as the point array
``fiber``; on a tetrahedral mesh it becomes the cell array used by the transversely
isotropic material).
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.muscles import figure_3

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(1, spacing=1.0)
labels = case.truth.cmf.embed_muscles(landmarks=case.landmarks)
figure_3(labels).screenshot(OUT / "fig3_obb.png")
