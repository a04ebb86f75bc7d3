"""Paper 000 Fig. 2a: facial soft tissue with the embedded muscles
==================================================================

Virtual patient 1's label image gets the six facial muscles of paper 000 on both sides
(orbicularis oculi, levator labii superioris alaeque nasi (LLSAN), levator labii
superioris (LLS), masseter, zygomaticus major and minor): the atlas
(``pvcmf.atlas.default()``) is carried to the patient by a thin-plate spline through its
landmarks, refined so the atlas skin and skull land on the patient's, and rasterised into
the soft tissue (``labels.cmf.embed_muscles(landmarks=...)``). The skin is drawn
translucent in the paper's yellow.
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.muscles import figure_2a

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(1, spacing=1.0)
labels = case.truth.cmf.embed_muscles(landmarks=case.landmarks)
figure_2a(labels).screenshot(OUT / "fig2a_muscles.png")
