"""Paper 000's Tables I and II regenerated from the data pvcmf simulates with.

:func:`table_1` reads the material table the MTM uses (:data:`pvcmf.mtm.TABLES`), and
:func:`table_2` the surgical plans the virtual patients are operated with
(:data:`pvcmf.plan.TABLE_II`), so the printed tables are the values the code runs, not a
copy of the paper. Both return :class:`pandas.DataFrame` laid out like the paper;
``gallery/plot_tables.py`` writes them as CSV and text.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..mtm.materials import material_table
from ..plan import TABLE_II, Plan


def table_1(table="paper000"):
    """Paper 000 Table I: Young's modulus (MPa) and Poisson ratio per tissue.

    Parameters
    ----------
    table : str or dict, default ``"paper000"``
        A material table accepted by :func:`pvcmf.mtm.material_table`.

    Returns
    -------
    pandas.DataFrame
        Index ``Fat``, ``Muscle across fiber``, ``Muscle along fiber``; columns
        ``Young's modulus (MPa)`` and ``Poisson ratio``.

    Examples
    --------
    >>> from pvcmf.figures.tables import table_1
    >>> float(table_1().loc["Muscle along fiber", "Young's modulus (MPa)"])
    0.5
    """
    props = material_table(table)
    rows = {
        "Fat": (props["fat"]["E_cross"], props["fat"]["nu"]),
        "Muscle across fiber": (props["muscle"]["E_cross"], props["muscle"]["nu"]),
        "Muscle along fiber": (props["muscle"]["E_fiber"], props["muscle"]["nu"]),
    }
    if props["fat"]["E_fiber"] != props["fat"]["E_cross"]:
        raise ValueError(
            f"table {table!r}: Table I lists an isotropic fat, got E_fiber "
            f"{props['fat']['E_fiber']} != E_cross {props['fat']['E_cross']}"
        )
    return pd.DataFrame.from_dict(rows, orient="index",
                                  columns=["Young's modulus (MPa)", "Poisson ratio"])


def _triple(values, fmt):
    return "(" + ", ".join(format(float(v), fmt) for v in values) + ")"


def table_2(plans=None):
    """Paper 000 Table II: the planned move of each patient's bone segment.

    Parameters
    ----------
    plans : dict of int -> pvcmf.plan.Plan, optional
        Default :data:`pvcmf.plan.TABLE_II` (the plans the virtual patients use).

    Returns
    -------
    pandas.DataFrame
        One row per patient and osteotomy: ``Deformed section``, ``Translation [mm]
        (horizontal, vertical, anterior-posterior)``, ``Rotation [deg]`` (``-`` for none,
        as in the paper), and the numeric ``translation`` / ``rotation`` triples.

    Examples
    --------
    >>> from pvcmf.figures.tables import table_2
    >>> table_2().loc[3, "Deformed section"]
    'Mandible'
    """
    plans = TABLE_II if plans is None else plans
    if not isinstance(plans, dict) or not plans:
        raise TypeError(f"plans must be a non-empty dict of patient -> Plan, got {plans!r}")
    rows = []
    for patient, plan in plans.items():
        if not isinstance(plan, Plan):
            raise TypeError(f"plans[{patient!r}] must be a pvcmf.plan.Plan, got "
                            f"{type(plan).__name__}")
        for o in plan.osteotomies:
            rot = np.asarray(o.rotation, float)
            rows.append({
                "Patient": patient,
                "Deformed section": o.segment.capitalize(),
                "Translation [mm] (horizontal, vertical, anterior-posterior)":
                    _triple(o.translation, "+g"),
                "Rotation [deg]": "-" if not rot.any() else _triple(rot, "g"),
                "translation": tuple(float(v) for v in o.translation),
                "rotation": tuple(float(v) for v in rot),
            })
    return pd.DataFrame(rows).set_index("Patient")
