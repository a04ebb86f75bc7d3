"""Paper 000 Fig. 4: the three boundary-condition types on a patient model
=========================================================================

Virtual patient 1 is segmented, its muscles embedded and its facial soft tissue meshed
(``pvcmf.pipeline.simulate`` up to the boundary conditions); Table II's Le Fort I plan then
becomes boundary conditions (``mesh.cmf.apply_plan(plan, labels)``):
a) the sliding-contact segment where the lips touch the teeth (blue), b) the joint sections
where soft tissue lies on the moving maxilla and moves with it (red), c) the fixed points
of the most posterior plane of the model (green). All other nodes are free. The
boundary conditions are the paper's own (``fix_unmoved_bone=False``; the pipeline's default
also fixes tissue lying on bone that does not move).
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
from pvcmf.figures.boundary_conditions import figure_4
from pvcmf.pipeline import simulate

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(1, spacing=2.0)
result = simulate(case.ct, case.plan, bones=case.truth, landmarks=case.landmarks,
                  n_tets=25_000, bc_options={"fix_unmoved_bone": False})
print(result.summary())
plotter = figure_4(result.mesh, result.labels)
plotter.screenshot(OUT / "fig4_boundary_conditions.png")
