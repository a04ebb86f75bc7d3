"""The cohort page's section on paper 001's mesh-size claim (``benchmarks/study.py``):
its verdict follows the claims' rows, its numbers come from the per-patient table, and it
says which comparison depends on the truth. Synthetic skins, no pipeline run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pyvista as pv

from pvcmf import arrays
from pvcmf.study.claims import mesh_size_claims, mesh_size_table
from pvcmf.study.paper001 import FINE_METHOD


def _benchmark():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "study.py"
    spec = importlib.util.spec_from_file_location("_study_benchmark_page", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _skin(err, shift, n=60):
    s = pv.PolyData(np.column_stack([np.zeros(n), np.full(n, shift), np.arange(n, 0.0, -1.0)]))
    s[arrays.SKIN_POINT_ID] = np.arange(n)
    s[arrays.DISTANCE] = err * np.linspace(0.5, 1.5, n)
    return s


def _section(shift, n_patients=10, truth_tets=2000, edit=None, truth_face_mm=None):
    """The mesh-size section for synthetic skins ``shift`` mm (plus 0.01 mm per patient)
    apart; ``edit(table)`` changes the per-patient table before the section is written."""
    skins = {101 + p: {"homogeneous": _skin(1.0 + 0.002 * p, shift + 0.01 * p),
                       FINE_METHOD: _skin(1.0, 0.0)} for p in range(n_patients)}
    table = mesh_size_table(skins)
    if edit is not None:
        edit(table)
    rows = pd.DataFrame(mesh_size_claims(skins, sizes=(30000, 60000), n_boot=200))
    other = pd.DataFrame([{"claim": "the inhomogeneous model is not better", "holds": True}])
    text = "\n".join(_benchmark().mesh_note(table, pd.concat([other, rows]), 30000, 60000,
                                             truth_tets, truth_face_mm))
    return text, table


def test_mesh_section_reports_an_equivalence_it_shows():
    text, table = _section(0.1)
    assert "Verdict: 30000 tetrahedra are enough at the clinical tolerance" in text
    assert "shown below the 0.5 mm clinical tolerance" in text
    assert f"median {table['skin_p90'].median():.3f} mm" in text
    assert "independent of the truth" in text and "does not depend on the truth" in text
    assert "2000 tetrahedra, coarser than either model mesh" in text
    assert "| 110 |" in text  # the per-patient table
    assert "0 of 10 patients above 0.5 mm" in text
    graded = _section(0.1, truth_tets=30000, truth_face_mm=4.0)[0]
    assert "graded: 4 mm in the face, the conforming spacing of 30000 tetrahedra" in graded
    assert "as fine as the coarser model mesh" not in graded


def test_mesh_section_names_the_patients_above_the_tolerance():
    """An equivalence shown for the cohort may leave a patient above the tolerance: the
    section counts and names them."""
    def edit(table):
        table.loc[table["patient"] == 104, "skin_p90"] = 0.61

    text, _ = _section(0.1, edit=edit)
    assert "1 of 10 patients above 0.5 mm: patient 104 (0.610 mm)" in text


def test_mesh_section_does_not_claim_what_the_skins_contradict():
    text, _ = _section(0.8)
    assert "Verdict: 30000 tetrahedra are not shown to be enough" in text
    assert "not shown below the 0.5 mm clinical tolerance" in text
    assert "does not hold" in text and "10 of 10 patients above 0.5 mm" in text
    text, _ = _section(0.1, truth_tets=90000)
    assert "coarser than either" not in text and "finer than the coarser model mesh" in text
