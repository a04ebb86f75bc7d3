"""A sequence of plans and their predicted faces
=============================================

What the interactive planner (``pvcmf plan``) shows while a slider moves: virtual
patient 1's mandible advanced 0, 3, 6 and 9 mm (anterior-posterior translation of a
bilateral sagittal split), each plan's predicted face coloured by its signed
displacement (mm along the outward skin normal). The model is prepared once
(:func:`pvcmf.planner.prepare_model`); each plan is then one call of
:meth:`pvcmf.planner.PlannerModel.predict` (the plan-response operator when installed,
else one MTM solve on the coarse mesh).
"""

import os
from pathlib import Path

import numpy as np
import pyvista as pv

import pvcmf
from pvcmf.plan import Osteotomy, Plan
from pvcmf.planner import prepare_model, signed_displacement

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT", Path(__file__).resolve().parent / "_out"))
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
model = prepare_model(case.ct, bones=case.truth, landmarks=case.landmarks, n_tets=5000,
                      muscles=False)
advances = (0.0, 3.0, 6.0, 9.0)
plotter = pv.Plotter(shape=(1, len(advances)), window_size=(1600, 480), border=False)
for col, advance in enumerate(advances):
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, advance)),),
                name=f"mandible +{advance:g} mm")
    face = model.predict(plan)
    face["signed displacement (mm)"] = signed_displacement(model.skin, face["displacement"])
    plotter.subplot(0, col)
    plotter.add_text(plan.name, font_size=10)
    plotter.add_mesh(face, scalars="signed displacement (mm)", cmap="coolwarm",
                     clim=(-8, 8), smooth_shading=True, show_scalar_bar=col == 0,
                     scalar_bar_args={"title": "mm along normal", "vertical": False})
    centre = np.asarray(face.center)
    plotter.camera_position = [tuple(centre + np.array([-350.0, 450.0, 80.0])),
                               tuple(centre), (0.0, 0.0, 1.0)]
plotter.link_views()
plotter.screenshot(OUT / "plan_sequence.png")
