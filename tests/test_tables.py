"""Paper 000 Tables I and II, regenerated from the data the simulation runs with.

Expected values are transcribed from the paper's text (Tables I and II), independently of
pvcmf's own constants."""

import numpy as np
import pytest

from pvcmf.figures.tables import table_1, table_2
from pvcmf.plan import Osteotomy, Plan

PAPER_TABLE_I = {  # tissue: (Young's modulus MPa, Poisson ratio)
    "Fat": (0.003, 0.46),
    "Muscle across fiber": (0.79, 0.43),
    "Muscle along fiber": (0.5, 0.43),
}
PAPER_TABLE_II = {  # patient: (section, translation (h, v, ap) mm, rotation deg or None)
    1: ("Maxilla", (6, 5, -4), (0, 2, 5)),
    2: ("Maxilla", (-0.27, 0.13, 4.98), (0, 0, 1.31)),
    3: ("Mandible", (1.07, -0.74, 5.47), (0, 2.71, 0)),
    4: ("Mandible", (0.67, 0.61, -3.24), None),
}


def test_table_1_is_the_paper():
    t = table_1()
    assert list(t.index) == list(PAPER_TABLE_I)
    for tissue, (e, nu) in PAPER_TABLE_I.items():
        assert t.loc[tissue, "Young's modulus (MPa)"] == pytest.approx(e)
        assert t.loc[tissue, "Poisson ratio"] == pytest.approx(nu)


def test_table_2_is_the_paper():
    t = table_2()
    assert list(t.index) == [1, 2, 3, 4]
    for patient, (section, trans, rot) in PAPER_TABLE_II.items():
        row = t.loc[patient]
        assert row["Deformed section"] == section
        np.testing.assert_allclose(row["translation"], trans)
        np.testing.assert_allclose(row["rotation"], (0, 0, 0) if rot is None else rot)
        assert (row["Rotation [deg]"] == "-") == (rot is None)
    assert t.loc[1, "Translation [mm] (horizontal, vertical, anterior-posterior)"] == "(+6, +5, -4)"


def test_tables_follow_the_data_and_reject_bad_input():
    mine = {"fat": {"E_fiber": 0.01, "E_cross": 0.01, "nu": 0.3},
            "muscle": {"E_fiber": 0.2, "E_cross": 0.1, "nu": 0.4}}
    assert table_1(mine).loc["Muscle across fiber", "Young's modulus (MPa)"] == 0.1
    plan = Plan((Osteotomy("mandible", (0.0, 0.0, 5.0)),), name="x")
    assert table_2({7: plan}).loc[7, "Rotation [deg]"] == "-"
    with pytest.raises(TypeError, match="plans"):
        table_2({1: "maxilla"})
    with pytest.raises(TypeError, match="plans"):
        table_2({})
    with pytest.raises(ValueError, match="table"):
        table_1("paper999")
