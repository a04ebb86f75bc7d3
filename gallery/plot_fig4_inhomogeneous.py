"""Paper 001 Fig. 4: the inhomogeneous model's parameters
========================================================

Fat and muscle get their own Poisson ratios (0 to 0.495 each) and E_muscle/E_fat runs from
1 to 64. Left: for one patient, the minimum and maximum 50 % and 90 % percentiles over all
(nu_fat, nu_muscle) per Young's modulus ratio (the paper: the ratio barely matters, the
Poisson ratios ~0.2 mm); right: the patient-averaged 90 % percentile over the
(nu_fat, nu_muscle) grid at E ratio 1 (the paper's optimum: nu_fat 0.485, nu_muscle 0.43).
One Dask task per patient meshes once; every parameter set re-assigns the materials and
refactorises numerically. ``PVCMF_SYNTHETIC=1`` draws from the synthetic evaluation.
"""

import os
from pathlib import Path

import pyvista as pv

from pvcmf.figures.parameter_studies import fig4_inhomogeneous, inhomogeneous_table, run_study

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
    nus = [0.0, 0.2, 0.4, 0.43, 0.46, 0.485, 0.495]  # 7 x 7 x 4 = 196 solves per patient
    grid = {"E_ratio": [1, 4, 16, 64], "nu_fat": nus, "nu_muscle": nus}
    df = run_study(PATIENTS, grid, "fig4_inhomogeneous", OUT, synthetic=SYNTHETIC,
                   scheduler=os.environ.get("PVCMF_SCHEDULER"), **STUDY, n_tets=30_000)
    print(inhomogeneous_table(df).round(3))
    fig = fig4_inhomogeneous(df, title=TITLE)
    fig.savefig(OUT / "fig4_inhomogeneous.png", dpi=100)


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
