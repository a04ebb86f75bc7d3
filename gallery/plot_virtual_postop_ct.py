"""Virtual post-operative CT
==========================

No public pair of pre/post-operative scans exists, so pvcmf makes the post-operative CT
of its virtual patients: the pre-operative CT warped backwards through the displaced
soft-tissue grid, the plan's bone segments moved rigidly, fresh noise (18 HU), and
(in the validation) a random pose in the scanner. Validation then runs the path of a
real scan on it: segment -> skin -> ICP on the upper face -> signed distances.

Left: the pre-operative CT of virtual patient 1 (2 mm), midline sagittal slice. Middle:
its virtual post-operative CT after Table II's plan (Le Fort I, maxilla 4 mm back,
5 mm up and 6 mm to the side with a small rotation), shown without the pose so that the
slices line up. Right: post minus pre (red: denser now, blue: less dense), where bone,
teeth and lip moved. The soft-tissue displacement here is the MTM's
(``pvcmf.pipeline.simulate``, 25k tetrahedra, a minute); set ``PVCMF_GALLERY_REFERENCE=1``
to use the reference model's instead (``pvcmf.postop.reference_grid``, NGSolve, 20k
tetrahedra, P2: tens of minutes on two cores).
"""

import os
from pathlib import Path

import pyvista as pv

import pvcmf
import pvcmf.pipeline
from pvcmf.figures.postop_ct import postop_ct_slices
from pvcmf.postop import postop_ct, reference_grid

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(1, spacing=2.0)
if os.environ.get("PVCMF_GALLERY_REFERENCE") == "1":
    grid = reference_grid(case, n_tets=20_000)
else:
    grid = pvcmf.pipeline.simulate(case.ct, case.plan, bones=case.truth,
                                   landmarks=case.landmarks, figures=False).post
post, pose = postop_ct(case, grid, seed=0)
fig = postop_ct_slices(case.ct, post, axis="x", position=0.0, zoom=(0, 150, -130, 30))
fig.savefig(OUT / "virtual_postop_ct.png", dpi=90)
