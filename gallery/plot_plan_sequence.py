"""A sequence of plans and their predicted faces
=============================================

What the interactive planner (``pvcmf plan``) shows while a slider moves: virtual
patient 1's mandible advanced 0, 3, 6 and 9 mm (anterior-posterior translation of a
bilateral sagittal split), each plan's predicted face in the right three-quarter view
(as a clinical photograph: the face toward the viewer's right) coloured by its signed
displacement (mm along the outward skin normal,
:func:`pvcmf.figures.plan_sequence.plan_sequence`). The model is prepared once
(:func:`pvcmf.planner.prepare_model`); each plan is then one call of
:meth:`pvcmf.planner.PlannerModel.predict` (the plan-response operator when installed,
else one MTM solve on the coarse mesh).
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.plan_sequence import plan_sequence
from pvcmf.plan import Osteotomy, Plan
from pvcmf.planner import prepare_model

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT", Path(__file__).resolve().parent / "_out"))
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
model = prepare_model(case.ct, bones=case.truth, landmarks=case.landmarks, n_tets=5000,
                      muscles=False)
advances = (0.0, 3.0, 6.0, 9.0)
plans = [Plan((Osteotomy("mandible", translation=(0.0, 0.0, advance)),),
              name=f"mandible +{advance:g} mm") for advance in advances]
faces = [model.predict(plan) for plan in plans]  # the predicted skins, with "displacement"
plotter = plan_sequence(faces, [plan.name for plan in plans], view="three_quarter")
plotter.screenshot(OUT / "plan_sequence.png")
