"""A prediction as a surgeon looks at it: frontal, profile and the profile overlay
=================================================================================

Virtual patient 1 and its Table II plan (Le Fort I: the maxilla 4 mm back, 5 mm up, 6 mm
to the left, yaw 2 and roll 5 degrees), simulated with the defaults of ``pvcmf demo``.
Left: the pre-operative and the predicted face, frontal (the patient's right on the
viewer's left, as in a clinical photograph) and in right profile (face to the right).
Right: the midsagittal silhouettes of both skins overlaid. The same image is the README's
picture (``docs/_static/prediction.png``).
"""

import os
from pathlib import Path

import pyvista as pv
from PIL import Image

import pvcmf
from pvcmf.cli import DEMO_N_TETS, DEMO_SPACING
from pvcmf.figures.face_views import prediction_summary
from pvcmf.pipeline import simulate

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

case = pvcmf.datasets.phantom(patient=1, spacing=DEMO_SPACING)
result = simulate(case.ct, case.plan, bones=case.truth, n_tets=DEMO_N_TETS,
                  figures=False)
image = prediction_summary(result.skin_pre, result.skin_post)
Image.fromarray(image).save(OUT / "prediction.png")

# %%
# The same figures are written by ``pvcmf demo --out DIR`` and ``pvcmf simulate``:
# ``face_frontal.png``, ``face_three_quarter.png``, ``face_profile.png``,
# ``profile_overlay.png``, ``displacement_ap.png`` and ``displacement_normal.png``.
import matplotlib.pyplot as plt  # noqa: E402

fig, ax = plt.subplots(figsize=(12, 8.8))
ax.imshow(image)
ax.set_axis_off()
