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

import os
from pathlib import Path

import numpy as np
import pyvista as pv

from pvcmf.figures.parameter_studies import fig2_poisson, poisson_optimum, run_study

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT", Path(__file__).resolve().parent / "_out"))
SYNTHETIC = os.environ.get("PVCMF_SYNTHETIC") == "1"
SPACING = float(os.environ.get("PVCMF_STUDY_SPACING", 2.0))  # as Figs. 6-8: shares their truth
# 16k P2 truth elements (~75k dofs, richer than the 30k P1 MTM): the 120k default of
# pvcmf.reference needs over an hour of CPU per patient on a 2-core machine
TRUTH_TETS = os.environ.get("PVCMF_STUDY_TRUTH_TETS", "16000")
STUDY = {"spacing": SPACING} if TRUTH_TETS is None else {"spacing": SPACING,
                                                        "truth_tets": int(TRUTH_TETS)}
PATIENTS = [int(p) for p in os.environ.get("PVCMF_STUDY_PATIENTS", "1 2 3 4").split()]
TITLE = "synthetic evaluation" if SYNTHETIC else f"virtual patients {', '.join(map(str, PATIENTS))}"


def main():
    grid = {"nu": np.round(np.linspace(0.0, 0.495, 20), 4)}
    df = run_study(PATIENTS, grid, "fig2_poisson_sweep", OUT, synthetic=SYNTHETIC,
                   scheduler=os.environ.get("PVCMF_SCHEDULER"), **STUDY, n_tets=30_000)
    print(poisson_optimum(df).round(3))
    fig = fig2_poisson(df, title=TITLE)
    fig.savefig(OUT / "fig2_poisson_sweep.png", dpi=100)


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
