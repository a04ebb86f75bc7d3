"""A prediction as a surgeon looks at it: frontal, profile and the profile overlay
=================================================================================

A real head CT, the Visible Human female (NLM; 1 mm DICOM series,
``$PVCMF_DATA_DIR/vhp_female_head``), and a plan that names the segment only: a Le Fort I
advancement, the maxilla 4 mm forward. :func:`pvcmf.pipeline.simulate` runs with the
defaults of ``pvcmf simulate`` (the maxilla found from the anatomy, fat and muscle from the
CT values, the muscle atlas fitted automatically, 25,000 tetrahedra over the front of the
head). Left: the pre-operative and the predicted face, frontal (the patient's right on the
viewer's left, as in a clinical photograph) and in right profile (face to the right); the
predicted skin the mesh does not reach (the back of the head, the neck) is grey. Right:
the midsagittal silhouettes of both skins overlaid. The same image is the README's picture
(``docs/_static/prediction.png``), made by::

    PVCMF_DATA_DIR=/path/to/data PVCMF_GALLERY_OUT=docs/_static python gallery/plot_prediction.py

or, from the folder of a ``pvcmf simulate`` run (its ``skin_pre.vtp`` and
``predicted_skin.vtp``), ``python gallery/plot_prediction.py RUN_FOLDER``. Without the
scan the script predicts virtual patient 1 after its Table II plan instead (the defaults
of ``pvcmf demo``) and says so.
"""

import logging
import os
import sys
from pathlib import Path

import pyvista as pv
from PIL import Image

import pvcmf
from pvcmf.cli import DEMO_N_TETS, DEMO_SPACING
from pvcmf.figures.face_views import prediction_summary
from pvcmf.pipeline import simulate
from pvcmf.plan import Osteotomy, Plan

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)
FOLDER = Path(os.environ.get("PVCMF_DATA_DIR", "")) / "vhp_female_head"
#: the plan: translation (horizontal, vertical, anterior) mm, + = left, up, forward
PLAN = Plan((Osteotomy("maxilla", translation=(0.0, 0.0, 4.0)),),
            name="Le Fort I: maxilla 4 mm forward")
RUN = Path(sys.argv[1]) if len(sys.argv) > 1 and __name__ == "__main__" else None

if RUN is not None:  # the skins of a `pvcmf simulate` run
    pre, post = pv.read(RUN / "skin_pre.vtp"), pv.read(RUN / "predicted_skin.vtp")
    source = f"the pvcmf simulate run in {RUN}"
elif FOLDER.is_dir():
    result = simulate(pvcmf.read_ct(FOLDER), PLAN, units="auto", orient="auto",
                      figures=False)
    pre, post = result.skin_pre, result.skin_post
    source = f"the Visible Human female ({FOLDER}), {PLAN.name}"
else:
    logging.getLogger("pvcmf").warning(
        "%s not found (set PVCMF_DATA_DIR): virtual patient 1 and its Table II plan "
        "are shown instead of the real scan", FOLDER)
    case = pvcmf.datasets.phantom(patient=1, spacing=DEMO_SPACING)
    result = simulate(case.ct, case.plan, bones=case.truth, n_tets=DEMO_N_TETS,
                      figures=False)
    pre, post = result.skin_pre, result.skin_post
    source = "virtual patient 1 (the scan was not found), Table II plan"
print("prediction of", source)
image = prediction_summary(pre, post)
Image.fromarray(image).save(OUT / "prediction.png", optimize=True)

# %%
# The same figures are written by ``pvcmf demo --out DIR`` and ``pvcmf simulate``:
# ``face_frontal.png``, ``face_three_quarter.png``, ``face_profile.png``,
# ``profile_overlay.png``, ``displacement_ap.png`` and ``displacement_normal.png``. The
# plan above as a file for ``pvcmf simulate --plan``::
#
#     name = "Le Fort I: maxilla 4 mm forward"
#     [[osteotomy]]
#     segment = "maxilla"
#     translation = [0.0, 0.0, 4.0]
#     rotation = [0.0, 0.0, 0.0]
import matplotlib.pyplot as plt  # noqa: E402

fig, ax = plt.subplots(figsize=(12, 8.8))
ax.imshow(image)
ax.set_axis_off()
