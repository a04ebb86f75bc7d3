"""Paper 001's claims and the per-region results, tested over the patients of a study.

* :func:`below_tolerance` -> a per-patient quantity tested against a tolerance (Wilcoxon
  signed-rank of ``x - tolerance``, Hodges-Lehmann estimate with its bootstrap interval):
  the claim "at most ``tolerance``" holds when the verdict says the quantity lies below it;
* :func:`nu_optimum` -> the Poisson ratio of the homogeneous model that minimises each
  patient's error statistic over a sweep, its spread over the patients (median,
  quartiles, bootstrap interval of the median), whether paper 001's optimum lies in that
  interval, and the error the paper's value costs each patient against its own optimum;
* :func:`mesh_size_claims` -> a mesh size against a finer one: the paired difference of
  the error (the claim that the two err alike holds only when the change of the error is
  shown below :data:`CLINICAL_TOLERANCE_MM`: an equivalence test, not the absence of a
  difference), the change of the error against paper 001's 0.05 mm, and the skin
  difference between the two meshes' predictions against :data:`CLINICAL_TOLERANCE_MM`
  (the one comparison that does not depend on the truth);
* :func:`mesh_size_table` -> per patient, both meshes' error statistic and the distance
  between their predicted skins (p50, p90, max);
* :func:`paper001_claims` -> all of paper 001's claims: the inhomogeneous model against
  the homogeneous one, the Poisson ratio, the mesh size;
* :func:`region_table` -> per patient, method and face region (lips, chin, nose,
  cheeks) the median and p90 of ``|d|``.

Rows share the columns of :func:`pvcmf.study.inference.claims_table`. Delegates to
numpy, pandas and :mod:`pvcmf.study.inference`.
"""

from __future__ import annotations

import numpy as np

from .. import arrays
from .inference import (
    _STATISTICS, MIN_REGION_POINTS, REGION_GROUPS, paired_comparison, paired_errors,
)
from .paper001 import FINE_METHOD, PAPER_NU, method_nu

__all__ = ["CLINICAL_TOLERANCE_MM", "MESH_TOLERANCE_MM", "NU_LOSS_TOLERANCE_MM",
           "below_tolerance", "mesh_size_claims", "mesh_size_table", "nu_optimum",
           "paper001_claims", "region_table"]

#: the skin change a finer mesh may make and still leave the prediction clinically the
#: same (mm): a quarter of the 2 mm within which paper 000 counts a prediction accurate
CLINICAL_TOLERANCE_MM = 0.5
#: paper 001 sec. 3.2: with about 30 000 tetrahedra the p90 error differs from that of a
#: very dense mesh by less than this on average (mm)
MESH_TOLERANCE_MM = 0.05
#: paper 001 sec. 4: the p90 error at nu 0.46 exceeds each patient's own minimum by less
#: than this (mm)
NU_LOSS_TOLERANCE_MM = 0.1


def below_tolerance(values, tolerance, claim, statistic, *, alpha=0.05, n_boot=1000,
                    seed=0):
    """Test that a per-patient quantity lies below a tolerance.

    The Wilcoxon signed-rank test of ``values - tolerance`` (:func:`paired_comparison`
    of the values against the constant tolerance): the claim holds when the verdict is
    "a better", i.e. the values lie below the tolerance with p < ``alpha``.

    Parameters
    ----------
    values : array_like
        One value per patient (mm).
    tolerance : float
        The bound the claim states (mm).
    claim, statistic : str
        Labels of the row.
    alpha, n_boot, seed :
        See :func:`pvcmf.study.inference.paired_comparison`.

    Returns
    -------
    dict
        A row of :func:`pvcmf.study.inference.claims_table` (``median_b`` is the
        tolerance; ``difference``: Hodges-Lehmann estimate of ``values - tolerance``).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.study.claims import below_tolerance
    >>> small = below_tolerance(np.linspace(0.01, 0.1, 8), 0.5, "c", "x", n_boot=100)
    >>> small["holds"], small["p_value"] < 0.05
    (True, True)
    >>> below_tolerance(np.linspace(0.4, 0.6, 8), 0.5, "c", "x", n_boot=100)["holds"]
    False
    """
    x = np.asarray(values, float)
    if not (np.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be a finite number >= 0 (mm), got {tolerance!r}")
    res = paired_comparison(x, np.full(x.shape, float(tolerance)), alpha=alpha,
                            n_boot=n_boot, seed=seed)
    return {"claim": claim, "statistic": statistic, **res,
            "holds": res["verdict"] == "a better"}


def _statistic(skin, stat, region=None, other=None):
    da, _ = paired_errors(skin, skin if other is None else other, region=region)
    if region is not None and len(da) < MIN_REGION_POINTS:
        return np.nan
    return float(_STATISTICS[stat](da)) if len(da) else np.nan


def nu_optimum(skins, statistic="p90", *, paper_nu=PAPER_NU, alpha=0.05, n_boot=2000,
               seed=0):
    """Each patient's optimal Poisson ratio of the homogeneous model, and its spread.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` with homogeneous methods of several Poisson ratios
        (:func:`pvcmf.study.paper001.nu_method` names, ``"homogeneous"`` at 0.46).
    statistic : str, default 'p90'
        Per-patient statistic of ``|d|`` minimised (paper 001 uses the p90).
    paper_nu : float, default 0.46
        Paper 001's optimum.
    alpha, n_boot, seed :
        See :func:`pvcmf.study.inference.paired_comparison`; ``n_boot`` also for the
        interval of the median optimum.

    Returns
    -------
    per_patient : pandas.DataFrame
        ``patient``, ``nu`` and the statistic, one row per patient and ratio, and
        ``optimum`` (True on each patient's minimum; the lowest ratio on a tie).
    spread : dict
        ``n``, ``median``, ``q25``, ``q75`` of the optimal ratios, ``ci_low``,
        ``ci_high`` (95 % percentile bootstrap interval of their median),
        ``paper_in_ci``, ``at_grid_end`` (patients whose optimum is the smallest or the
        largest ratio swept: the sweep bounds their optimum), ``grid``.
    claims : list of dict
        Rows of :func:`pvcmf.study.inference.claims_table`: the optimum against the
        paper's (Wilcoxon signed-rank of ``optimum - paper_nu``; holds when it finds no
        difference and the paper's value lies in the interval of the median optimum),
        and the error the paper's value costs each patient against its own optimum,
        below :data:`NU_LOSS_TOLERANCE_MM` (:func:`below_tolerance`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.claims import nu_optimum
    >>> from pvcmf.study.paper001 import nu_method
    >>> def skin(err):
    ...     s = pv.PolyData(np.zeros((30, 3)))
    ...     s[arrays.SKIN_POINT_ID] = np.arange(30)
    ...     s[arrays.DISTANCE] = err * np.linspace(0.5, 1.5, 30)
    ...     return s
    >>> skins = {p: {nu_method(nu): skin(1 + abs(nu - 0.45 - 0.01 * (p % 3)))
    ...              for nu in (0.40, 0.45, 0.46, 0.47, 0.49)} for p in range(8)}
    >>> table, spread, claims = nu_optimum(skins, n_boot=200)
    >>> spread["median"], spread["paper_in_ci"]
    (0.46, True)
    """
    import pandas as pd

    rows = []
    for patient, by_method in skins.items():  # the patients
        for method, skin in by_method.items():
            nu = method_nu(method)
            if nu is None or method == FINE_METHOD:
                continue
            rows.append({"patient": patient, "nu": nu, statistic: _statistic(skin, statistic)})
    if not rows:
        raise ValueError("skins hold no homogeneous method at any Poisson ratio (nu_method)")
    table = pd.DataFrame(rows).sort_values(["patient", "nu"], ignore_index=True)
    best = table.loc[table.groupby("patient")[statistic].idxmin()]
    table["optimum"] = table.index.isin(best.index)
    opt = best["nu"].to_numpy(float)
    grid = np.unique(table["nu"])
    rng = np.random.default_rng(seed)
    boot = np.median(opt[rng.integers(0, len(opt), (n_boot, len(opt)))], axis=1)
    lo, hi = np.percentile(boot, [2.5, 97.5])
    spread = {"n": len(opt), "median": float(np.median(opt)),
              "q25": float(np.percentile(opt, 25)), "q75": float(np.percentile(opt, 75)),
              "ci_low": float(lo), "ci_high": float(hi),
              "paper_in_ci": bool(lo <= paper_nu <= hi),
              "at_grid_end": int(np.sum((opt == grid[0]) | (opt == grid[-1]))),
              "grid": tuple(float(g) for g in grid)}
    claims = []
    if len(opt) >= 2:
        res = paired_comparison(opt, np.full(opt.shape, paper_nu), alpha=alpha,
                                n_boot=n_boot, seed=seed)
        claims.append({"claim": f"the optimal Poisson ratio of the homogeneous model is "
                                f"{paper_nu:g} (paper 001; optimum - {paper_nu:g})",
                       "statistic": f"argmin {statistic}", **res,
                       "holds": res["verdict"] == "no difference" and spread["paper_in_ci"]})
        at_paper = table[np.isclose(table["nu"], paper_nu)].set_index("patient")[statistic]
        loss = at_paper.loc[best["patient"]].to_numpy(float) - best[statistic].to_numpy(float)
        claims.append(below_tolerance(
            loss, NU_LOSS_TOLERANCE_MM,
            f"nu {paper_nu:g} costs each patient less than {NU_LOSS_TOLERANCE_MM:g} mm of "
            f"{statistic} against its own optimum (paper 001; {statistic} at {paper_nu:g} "
            f"- at the optimum)",
            statistic, alpha=alpha, n_boot=n_boot, seed=seed))
    return table, spread, claims


def _skin_change(skin_a, skin_b):
    """The distance between two predictions of the same skin points (matched by
    ``arrays.SKIN_POINT_ID``); empty when they share no point."""
    ia = np.asarray(skin_a.point_data[arrays.SKIN_POINT_ID], np.int64)
    ib = np.asarray(skin_b.point_data[arrays.SKIN_POINT_ID], np.int64)
    _, ka, kb = np.intersect1d(ia, ib, return_indices=True)
    return np.linalg.norm(np.asarray(skin_a.points)[ka] - np.asarray(skin_b.points)[kb], axis=1)


def mesh_size_table(skins, coarse="homogeneous", fine=FINE_METHOD, *, statistic="p90"):
    """Per patient, a mesh against a finer one: their errors and their skins' difference.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` with the two methods (judged skins: the predicted
        skin points with ``arrays.DISTANCE`` to the truth and ``arrays.SKIN_POINT_ID``).
    coarse, fine : str
        The methods of the two mesh sizes (the same model).
    statistic : str, default 'p90'
        Per-patient statistic of ``|d|``.

    Returns
    -------
    pandas.DataFrame
        One row per patient: ``coarse`` and ``fine`` (the statistic of ``|d|`` on the
        points both meshes judge: it depends on the truth), ``change`` (coarse - fine),
        and the distance between the two predicted skins on their common points, which
        does not depend on the truth: ``skin_p50``, ``skin_p90``, ``skin_max`` (mm) and
        ``points`` (NaN and 0 when they share no point).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.claims import mesh_size_table
    >>> s = pv.PolyData(np.zeros((10, 3)))
    >>> s[arrays.SKIN_POINT_ID] = np.arange(10)
    >>> s[arrays.DISTANCE] = np.linspace(0.0, 0.9, 10)
    >>> t = s.copy()
    >>> t.points = t.points + [0.0, 0.3, 0.4]
    >>> mesh_size_table({1: {"homogeneous": s, "homogeneous_fine": t}})[
    ...     ["change", "skin_p90", "points"]].values.tolist()
    [[0.0, 0.5, 10.0]]
    """
    import pandas as pd

    if statistic not in _STATISTICS:
        raise ValueError(f"statistic must be one of {sorted(_STATISTICS)}, got {statistic!r}")
    rows = []
    for patient, by_method in skins.items():  # the patients
        for name in (coarse, fine):
            if name not in by_method:
                raise KeyError(f"patient {patient} has no method {name!r}")
        da, db = paired_errors(by_method[coarse], by_method[fine])
        a = float(_STATISTICS[statistic](da)) if len(da) else np.nan
        b = float(_STATISTICS[statistic](db)) if len(db) else np.nan
        d = _skin_change(by_method[coarse], by_method[fine])
        q = np.percentile(d, [50, 90, 100]) if len(d) else np.full(3, np.nan)
        rows.append({"patient": patient, "coarse": a, "fine": b, "change": a - b,
                     "skin_p50": float(q[0]), "skin_p90": float(q[1]),
                     "skin_max": float(q[2]), "points": len(d)})
    return pd.DataFrame(rows)


def mesh_size_claims(skins, coarse="homogeneous", fine=FINE_METHOD, *, sizes=None,
                     statistic="p90", alpha=0.05, n_boot=1000, seed=0):
    """Paper 001's "N tetrahedra are enough": a mesh against a finer one, paired.

    Two questions, one that does not depend on the truth and one that does:

    * do the two meshes predict the same skin? The per-patient p90 of the distance
      between their predicted skins (:func:`mesh_size_table`), shown below
      :data:`CLINICAL_TOLERANCE_MM` by :func:`below_tolerance` (an equivalence test:
      the claim holds only when the test puts it below with p < ``alpha``);
    * do they err alike against the truth? The paired difference of the error
      statistic, which holds only when its per-patient change is shown below
      :data:`CLINICAL_TOLERANCE_MM` (finding no difference does not show that there is
      none), and that change against paper 001's :data:`MESH_TOLERANCE_MM`.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` with the two methods.
    coarse, fine : str
        The methods of the two mesh sizes (the same model).
    sizes : (int, int), optional
        Their requested tetrahedra, for the claims' wording.
    statistic : str, default 'p90'
        Per-patient statistic of ``|d|``.
    alpha, n_boot, seed :
        See :func:`pvcmf.study.inference.paired_comparison`.

    Returns
    -------
    list of dict
        Rows of :func:`pvcmf.study.inference.claims_table`, in this order: the paired
        difference of the statistic (coarse - fine; holds exactly when the next row
        does); its absolute change per patient below :data:`CLINICAL_TOLERANCE_MM`; its
        absolute change below :data:`MESH_TOLERANCE_MM`; the p90 of the skin difference
        between the two meshes' predictions below :data:`CLINICAL_TOLERANCE_MM`. The
        first three are measured against the truth, the last is not.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.claims import mesh_size_claims
    >>> def skin(err):
    ...     s = pv.PolyData(np.zeros((30, 3)))
    ...     s[arrays.SKIN_POINT_ID] = np.arange(30)
    ...     s[arrays.DISTANCE] = err * np.linspace(0.5, 1.5, 30)
    ...     return s
    >>> skins = {p: {"homogeneous": skin(1.0), "homogeneous_fine": skin(1.0)} for p in range(8)}
    >>> [r["holds"] for r in mesh_size_claims(skins, n_boot=100)]
    [True, True, True, True]
    """
    table = mesh_size_table(skins, coarse, fine, statistic=statistic)
    fa, fb = table["coarse"].to_numpy(float), table["fine"].to_numpy(float)
    change = np.abs(table["change"].to_numpy(float))
    n_c, n_f = sizes if sizes is not None else (coarse, fine)
    res = paired_comparison(fa, fb, alpha=alpha, n_boot=n_boot, seed=seed)
    # "no difference" is absence of evidence: the claim holds only when the per-patient
    # change of the statistic is shown to lie below the clinical tolerance (next row)
    same = below_tolerance(
        change, CLINICAL_TOLERANCE_MM,
        f"{n_c} tetrahedra change the {statistic} error by less than "
        f"{CLINICAL_TOLERANCE_MM:g} mm from {n_f} (clinical tolerance; against the truth)",
        f"|{statistic} change|", alpha=alpha, n_boot=n_boot, seed=seed)
    rows = [{"claim": f"{n_c} tetrahedra err as {n_f} do ({statistic}, {n_c} - {n_f}; "
                      f"against the truth; holds when the change is shown below "
                      f"{CLINICAL_TOLERANCE_MM:g} mm, next row)",
             "statistic": statistic, **res, "holds": same["holds"]}, same]
    rows.append(below_tolerance(
        change, MESH_TOLERANCE_MM,
        f"{n_c} tetrahedra change the {statistic} error by less than "
        f"{MESH_TOLERANCE_MM:g} mm from {n_f} (paper 001; against the truth)",
        f"|{statistic} change|", alpha=alpha, n_boot=n_boot, seed=seed))
    rows.append(below_tolerance(
        table["skin_p90"].to_numpy(float), CLINICAL_TOLERANCE_MM,
        f"{n_c} and {n_f} tetrahedra predict skins within {CLINICAL_TOLERANCE_MM:g} mm "
        f"of each other (p90 of the skin difference; clinical tolerance; independent of "
        f"the truth)", "p90 skin difference", alpha=alpha, n_boot=n_boot, seed=seed))
    return rows


def region_table(skins, methods, groups=None):
    """Median and p90 of ``|d|`` per patient, method and face region.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` -> judged skin (point array ``arrays.REGION``).
    methods : sequence of str
        Methods tabulated.
    groups : dict, optional
        Region name -> names of ``arrays.FACE_REGIONS`` (default
        :data:`pvcmf.study.inference.REGION_GROUPS`: lips, chin, nose, cheeks).

    Returns
    -------
    pandas.DataFrame
        ``patient``, ``method``, ``region``, ``n`` (judged points), ``p50``, ``p90``
        (NaN with fewer than :data:`~pvcmf.study.inference.MIN_REGION_POINTS` points).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.claims import region_table
    >>> s = pv.PolyData(np.zeros((40, 3)))
    >>> s[arrays.SKIN_POINT_ID] = np.arange(40)
    >>> s[arrays.DISTANCE] = np.r_[np.full(20, 1.0), np.full(20, 3.0)]
    >>> s[arrays.REGION] = np.r_[np.full(20, 3), np.full(20, 4)].astype(np.uint8)
    >>> region_table({1: {"m": s}}, ["m"])[["region", "n", "p90"]].values.tolist()
    [['lips', 0, nan], ['chin', 20, 1.0], ['nose', 20, 3.0], ['cheeks', 0, nan]]
    """
    import pandas as pd

    groups = REGION_GROUPS if groups is None else groups
    rows = []
    for patient, by_method in skins.items():  # patients x methods x 4 regions
        for method in methods:
            for name, region in groups.items():
                d, _ = paired_errors(by_method[method], by_method[method], region=region)
                ok = len(d) >= MIN_REGION_POINTS
                rows.append({"patient": patient, "method": method, "region": name,
                             "n": len(d), "p50": float(np.median(d)) if ok else np.nan,
                             "p90": float(np.percentile(d, 90)) if ok else np.nan})
    return pd.DataFrame(rows)


def paper001_claims(skins, *, sizes=None, alpha=0.05, n_boot=1000, seed=0):
    """Paper 001's claims over the patients of a study, as they come out.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` with ``"homogeneous"``, ``"inhomogeneous"``,
        ``"homogeneous_fine"`` and the homogeneous model at several Poisson ratios; where
        every patient also has ``"homogeneous_auto"`` and ``"inhomogeneous_auto"`` (from
        the CT alone), the inhomogeneous-homogeneous rows are repeated for them
        ("[CT-only]").
    sizes : (int, int), optional
        Requested tetrahedra of ``"homogeneous"`` and ``"homogeneous_fine"``.
    alpha, n_boot, seed :
        See :func:`pvcmf.study.inference.paired_comparison`.

    Returns
    -------
    claims : pandas.DataFrame
        Rows of :func:`pvcmf.study.inference.claims_table`: the inhomogeneous model
        against the homogeneous one (median and p90; paper 001 finds it not significantly
        better: holds unless the verdict is "a better"), :func:`nu_optimum`'s and
        :func:`mesh_size_claims`' rows.
    nu_table, spread :
        :func:`nu_optimum`'s per-patient table and spread.
    """
    import pandas as pd

    from .inference import claims_table

    pairs = [(f"the inhomogeneous model is not significantly better than the homogeneous one "
              f"(paper 001; {s})", "inhomogeneous", "homogeneous", s) for s in ("median", "p90")]
    if all({"homogeneous_auto", "inhomogeneous_auto"} <= set(m) for m in skins.values()):
        pairs += [(f"{c} [CT-only]", f"{a}_auto", f"{b}_auto", s) for c, a, b, s in pairs]
    rows = claims_table(skins, pairs, alpha=alpha, n_boot=n_boot, seed=seed)
    rows["holds"] = rows["verdict"] != "a better"
    nu_table, spread, nu_rows = nu_optimum(skins, alpha=alpha, n_boot=max(n_boot, 2000),
                                           seed=seed)
    mesh_rows = mesh_size_claims(skins, sizes=sizes, alpha=alpha, n_boot=n_boot, seed=seed)
    table = pd.concat([rows, pd.DataFrame(nu_rows + mesh_rows)], ignore_index=True)
    return table, nu_table, spread
