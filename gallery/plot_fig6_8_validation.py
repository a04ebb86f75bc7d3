"""
Paper 000 Figs. 6-8: validation of the proposed and the state-of-the-art model
==============================================================================

For the four virtual patients and Table II's plans, predict the post-operative face
with the proposed model (muscle-embedded conforming mesh) and the state of the art
(homogeneous mesh + random-point sampling of the muscle fraction), map each prediction
to the same dense skin (paper 001's Gaussian mapping), register the virtual
post-operative skin to the pre-operative one with point-to-plane ICP on the forehead
and nose bridge (the truth is scanned in another pose), and measure signed distances.

Fig. 6 colours the errors on the face, Fig. 7 draws their box plots, Fig. 8 their
cumulative curves; the statistics table is written next to them (CSV).

The truth comes from :mod:`pvcmf.reference` (the richer model, optional extra
``pip install pvcmf[reference]``); without it this script says so and stops.
Set ``PVCMF_STUDY_SPACING`` (mm), ``PVCMF_STUDY_TETS``, ``PVCMF_STUDY_TRUTH_TETS`` and
``PVCMF_STUDY_PATIENTS`` (e.g. ``1,2``) for a quicker, coarser run.
"""

import logging
import os
from pathlib import Path

import numpy as np
import pyvista as pv
from scipy.spatial.transform import Rotation

import pvcmf
from pvcmf import arrays, filters, mtm
from pvcmf.datasets import phantom
from pvcmf.figures.validation import fig6_error_maps, fig7_boxplots, fig8_cumulative
from pvcmf.pipeline import DEFAULT_FACE_FRACTION, face_box, simulate
from pvcmf.validation import run_study

pv.OFF_SCREEN = True
logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
log = logging.getLogger("plot_fig6_8_validation")
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT", Path(__file__).parent / "_out"))
OUT.mkdir(parents=True, exist_ok=True)
SPACING = float(os.environ.get("PVCMF_STUDY_SPACING", 1.5))
N_TETS = int(os.environ.get("PVCMF_STUDY_TETS", 30_000))
TRUTH_TETS = int(os.environ.get("PVCMF_STUDY_TRUTH_TETS", 4 * N_TETS))  # finer truth mesh
PATIENTS = tuple(int(p) for p in os.environ.get("PVCMF_STUDY_PATIENTS", "1,2,3,4").split(","))
SIGMA = 2.0  # mm, smallest Gaussian width of the tetrahedra -> dense skin mapping

try:
    from pvcmf import reference
except ImportError as err:  # the truth model is an optional extra
    raise SystemExit(f"pvcmf.reference is needed for the post-operative truth: {err}")

_cases = {}


def case(patient):
    if patient not in _cases:
        _cases[patient] = phantom(patient=patient, spacing=SPACING)
    return _cases[patient]


def truth_in_scanner(patient):
    """The virtual post-operative skin, as a scan in another pose, registered back."""
    c = case(patient)
    post = reference.postop_skin(c, n_tets=TRUTH_TETS)
    rng = np.random.default_rng(patient)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-4, 4, 3), degrees=True).as_matrix()
    pose[:3, 3] = rng.uniform(-5, 5, 3)
    scan = post.transform(pose, inplace=False)
    scan.points = scan.points + rng.normal(0, 0.1, scan.points.shape)  # scanner noise
    pre = filters.extract_skin(c.truth)
    tip = c.landmarks.get("pronasale", pre.points[np.argmax(pre.points[:, 1])])
    # unchanged by jaw surgery: the face above the nose tip (forehead, orbits, nose bridge)
    region = lambda p: (p[:, 2] > tip[2] + 15) & (p[:, 1] > tip[1] - 60)  # noqa: E731
    return scan.cmf.register(pre, region=region)


def predict(patient, method):
    c = case(patient)
    conforming = method == "proposed"
    res = simulate(c.ct, c.plan, bones=c.truth, landmarks=c.landmarks, n_tets=N_TETS,
                   mesh_options={"conforming": conforming}, figures=False)
    post = res.post
    if not conforming:  # state of the art: muscle share by random points, then re-solve
        grid = filters.sample_muscle_fraction(res.mesh, res.labels)
        grid = filters.fiber_directions(grid)
        post = mtm.solve(filters.assign_materials(grid))
    skin = filters.extract_skin(res.labels)
    # the Gaussian must span the element size, or coarse meshes leave holes in the skin
    edges = post.extract_all_edges().compute_cell_sizes(length=True, area=False, volume=False)
    sigma = max(SIGMA, 0.5 * float(np.median(edges["Length"])))
    pred = post.cmf.map_to_surface(skin, sigma=sigma)
    pred = pvcmf.validation.label_face_regions(pred, landmarks=c.landmarks)
    truth = truth_in_scanner(patient)
    out = pred.cmf.distance_to(truth, max_distance=10.0)
    # only the face the model simulates (the meshed, anterior part) is judged
    y0 = face_box(res.labels, DEFAULT_FACE_FRACTION)[2]
    face = (out["mapping_support"] > 0) & (out.points[:, 1] >= y0)
    return out.extract_points(face, adjacent_cells=False).extract_surface(
        algorithm="dataset_surface")


skins, distances, table = run_study(predict, patients=PATIENTS)
table.to_csv(OUT / "fig6_8_validation_table.csv", index=False)
log.info("whole-face statistics:\n%s", table[table["region"] == "face"].to_string(index=False))

pl = fig6_error_maps(skins)
pl.screenshot(OUT / "fig6_error_maps.png")
fig7_boxplots(distances).savefig(OUT / "fig7_boxplots.png", dpi=120)
fig8_cumulative(distances).savefig(OUT / "fig8_cumulative.png", dpi=120)
