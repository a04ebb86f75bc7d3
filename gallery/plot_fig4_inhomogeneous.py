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

from pathlib import Path

import pyvista as pv

from pvcmf.figures.parameter_studies import fig4_inhomogeneous, inhomogeneous_table, run_study, study_settings

pv.OFF_SCREEN = True
SETTINGS = study_settings(Path(__file__).resolve().parent)  # environment: see study_settings
OUT, SYNTHETIC, STUDY = SETTINGS["out"], SETTINGS["synthetic"], SETTINGS["study"]
PATIENTS = SETTINGS["patients"]
TITLE = SETTINGS["title"]


def main():
    nus = [0.0, 0.2, 0.4, 0.43, 0.46, 0.485, 0.495]  # 7 x 7 x 4 = 196 solves per patient
    grid = {"E_ratio": [1, 4, 16, 64], "nu_fat": nus, "nu_muscle": nus}
    df = run_study(PATIENTS, grid, "fig4_inhomogeneous", OUT, synthetic=SYNTHETIC,
                   scheduler=SETTINGS["scheduler"], **STUDY, n_tets=30_000)
    print(inhomogeneous_table(df).round(3))
    fig = fig4_inhomogeneous(df, title=TITLE)
    fig.savefig(OUT / "fig4_inhomogeneous.png", dpi=100)


if __name__ == "__main__":  # Dask's worker processes re-import this file: run once
    main()
