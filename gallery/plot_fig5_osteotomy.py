"""Paper 000 Fig. 5: osteotomy planning of the four patients
==========================================================

Each virtual patient's pre-operative face (left) next to its skeleton seen from the
right (right): every bone segment in white where it is before surgery, the moved segment
in green where Table II's plan puts it (patients 1-2: Le Fort I maxilla; 3-4: bilateral
sagittal split mandible). The segments come from the patient's bone labels
(``pvcmf.filters.cut_bones``) and are moved rigidly about their centroids
(``pvcmf.filters.move_bones``).
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.osteotomy import figure_5

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

cases = [pvcmf.datasets.phantom(patient, spacing=2.0) for patient in (1, 2, 3, 4)]
plotter = figure_5(cases)
plotter.screenshot(OUT / "fig5_osteotomy.png")
