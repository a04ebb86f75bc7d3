"""Paper 001 Fig. 5: the optimal Poisson ratio per point of the face
===================================================================

For every skin point, the Poisson ratio that minimises the local 90 % error percentile
(over its 16 nearest skin points), and the standard deviation of that percentile across
the ratios (0-0.3 mm colour scale, as in the paper), drawn on the whole skin of the patient
seen from the front (the patient's right on the viewer's left)
(the gaps between the face regions bridged from their nearest points, grey beyond them). The paper finds high ratios (~0.47) on
the cheeks and low ones (~0.1) on the lips and nose tip for its patient 2. The sweep keeps
each prediction's per-point signed distance map and the skin it lives on.
``PVCMF_SYNTHETIC=1`` draws from the synthetic evaluation and its half-sphere "face".
"""

from pathlib import Path

import numpy as np
import pyvista as pv

import pvcmf
from pvcmf.figures.parameter_studies import fig5_optimal_poisson, run_study, study_settings
from pvcmf.sweeps import synthetic_skin

pv.OFF_SCREEN = True
SETTINGS = study_settings(Path(__file__).resolve().parent)  # environment: see study_settings
OUT, SYNTHETIC, STUDY = SETTINGS["out"], SETTINGS["synthetic"], SETTINGS["study"]


def main():
    grid = {"nu": np.round(np.linspace(0.0, 0.495, 20), 4)}
    df = run_study([2], grid, "fig5_optimal_poisson", OUT, synthetic=SYNTHETIC, keep_arrays=True,
                   scheduler=SETTINGS["scheduler"], **STUDY, n_tets=30_000)
    context = None
    if SYNTHETIC:
        skin = synthetic_skin()
    else:  # the skin the maps were measured on, stored with them
        skin = pv.PolyData(np.asarray(df["skin_points"].iloc[0]), np.asarray(df["skin_faces"].iloc[0]))
        # the whole skin of patient 2: the face regions are boxes with gaps between them,
        # drawn on it as one continuous face (grey beyond the face regions)
        labels = pvcmf.datasets.phantom(2, spacing=STUDY["spacing"]).truth
        context = pvcmf.filters.extract_skin(labels)
    pl = fig5_optimal_poisson(df, skin, context=context, window_size=(1000, 500))
    pl.screenshot(OUT / "fig5_optimal_poisson.png")
    pl.close()


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
