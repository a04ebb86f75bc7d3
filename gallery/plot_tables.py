"""Paper 000 Tables I and II: materials and surgical plans
========================================================

Table I (Young's modulus and Poisson ratio of fat and muscle, along and across the
fibres) is printed from :data:`pvcmf.mtm.TABLES`, the table ``assign_materials`` uses;
Table II (each patient's bone move) from :data:`pvcmf.plan.TABLE_II`, the plans the four
virtual patients are operated with. Both are written as CSV and aligned text next to the
figures.
"""

import os
from pathlib import Path

from pvcmf.figures.tables import table_1, table_2

OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)

t1 = table_1()
t2 = table_2().drop(columns=["translation", "rotation"])
t1.to_csv(OUT / "table1_materials.csv")
t2.to_csv(OUT / "table2_plans.csv")
(OUT / "tables.txt").write_text(
    "TABLE I. Material properties used for simulation.\n" + t1.to_string() + "\n\n"
    "TABLE II. Surgical procedures performed on the patient cases.\n" + t2.to_string() + "\n"
)
