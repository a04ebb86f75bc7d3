"""Virtual patient: skin, skull and the facial muscles
=====================================================

The embedded default data set of pvcmf is a virtual patient built from an analytic template
head (:mod:`pvcmf.datasets.template`): a cranium with orbits and nasal aperture, the Le Fort I
maxilla with the upper teeth, the mandible with the lower teeth, soft tissue of realistic
thickness shaped to a real face's proportions (forehead, brow ridges, eye sockets, nose,
lips with a philtrum, chin, a neck that continues; :mod:`pvcmf.datasets.template.face`), and the six muscles of paper 000 Fig. 2a on both sides
(orbicularis oculi red, levator labii superioris alaeque nasi purple, levator labii
superioris orange, zygomaticus major pink and minor olive, masseter brown). Bone segments:
cranium ivory, maxilla blue, mandible green; the skin is translucent. Patients 1-4 differ
in size, soft-tissue thickness and jaw relation (class II / III), which Table II corrects.
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.patient import virtual_patient

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(patient=1, spacing=1.0)
plotter = virtual_patient(case, views=("front", "oblique", "right"), window_size=(1800, 700))
plotter.screenshot(OUT / "virtual_patient.png")
