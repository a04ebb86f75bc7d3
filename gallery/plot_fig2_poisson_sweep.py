"""Paper 001 Fig. 2: prediction error against the Poisson ratio
==============================================================

The homogeneous MTM is solved for 20 Poisson ratios between 0 and 0.495 on each virtual
patient (Table II's plans); each prediction is compared with the patient's post-operative
skin. Left: the 90 % percentile error per patient, a cross at each minimum; right: the
average 50/90/95 % percentiles (the paper finds the minimum at 0.45-0.46).

The sweep runs on Dask (a local cluster of worker processes by default; set
``PVCMF_SCHEDULER=tcp://host:8786`` for a cluster) with one task per patient that meshes once
and re-solves per ratio, and caches every result, so a second run only draws.
``PVCMF_SYNTHETIC=1`` draws from the cheap synthetic evaluation instead (engine demo).
"""

from pathlib import Path

import numpy as np
import pyvista as pv

from pvcmf.figures.parameter_studies import fig2_poisson, poisson_optimum, run_study, study_settings

pv.OFF_SCREEN = True
SETTINGS = study_settings(Path(__file__).resolve().parent)  # environment: see study_settings
OUT, SYNTHETIC, STUDY = SETTINGS["out"], SETTINGS["synthetic"], SETTINGS["study"]
PATIENTS = SETTINGS["patients"]
TITLE = SETTINGS["title"]


def main():
    grid = {"nu": np.round(np.linspace(0.0, 0.495, 20), 4)}
    df = run_study(PATIENTS, grid, "fig2_poisson_sweep", OUT, synthetic=SYNTHETIC,
                   scheduler=SETTINGS["scheduler"], **STUDY, n_tets=30_000)
    print(poisson_optimum(df).round(3))
    fig = fig2_poisson(df, title=TITLE)
    fig.savefig(OUT / "fig2_poisson_sweep.png", dpi=100)


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
