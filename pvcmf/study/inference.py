"""Paired inference between two prediction methods: does one err less than the other?

The study compares methods on the *same* skin points of the *same* patients, so every
comparison is paired: the differences ``|d_a| - |d_b|`` of the absolute signed errors.

* :func:`paired_comparison` -> two-sided Wilcoxon signed-rank test
  (:func:`scipy.stats.wilcoxon`), the Hodges-Lehmann estimate of the typical difference
  (median of the Walsh averages) with a 95 % bootstrap confidence interval, the
  matched-pairs rank-biserial correlation as effect size, and a verdict
  (``"a better"``, ``"b better"`` or ``"no difference"`` at level ``alpha``);
* :func:`paired_errors` -> the paired ``|d|`` of two judged skins (same skin points,
  matched by ``arrays.SKIN_POINT_ID``);
* :func:`compare_methods` -> one comparison per patient over its skin points, and one
  over the patients (each patient's median ``|d|``), as a table.

Skin points of one face are spatially correlated: a p-value over the points of one
patient says that the two predictions differ on that face, not that the difference
generalises to other patients; only the comparison over patients (``unit="patient"``,
at least 6 patients for a two-sided p below 0.05) does. Delegates to scipy.stats and
numpy.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import stats

from .. import arrays

log = logging.getLogger("pvcmf.validation")

__all__ = ["MIN_REGION_POINTS", "PAPER_CLAIMS", "REGION_GROUPS", "claims_table",
           "compare_methods", "paired_comparison", "paired_errors"]

#: paper 000's claims as paired comparisons over patients: (claim, method a, method b,
#: per-patient statistic of |d|); each holds when the verdict is "a better". Paper 000's
#: state of the art is its own mesh without muscle surfaces, the muscles sampled onto it
#: by random points (``sample_muscle_fraction``): a muscle share per tetrahedron, not a
#: homogeneous material
PAPER_CLAIMS = (
    ("muscle-embedded mesh errs less than sampling the muscles onto the mesh (median)",
     "proposed", "state_of_the_art", "median"),
    ("muscle-embedded mesh errs less than sampling the muscles onto the mesh (p90)",
     "proposed", "state_of_the_art", "p90"),
    ("more skin within 2 mm with the muscle-embedded mesh than with sampled muscles "
     "(share outside 2 mm)", "proposed", "state_of_the_art", "outside_2mm"),
)
#: face regions of the per-region claims: groups of ``arrays.FACE_REGIONS`` names
REGION_GROUPS = {"lips": ("upper_lip", "lower_lip"), "chin": ("chin",), "nose": ("nose",),
                 "cheeks": ("cheek_left", "cheek_right")}
#: fewest judged points of a region for its statistic in one patient (else left out)
MIN_REGION_POINTS = 20
_STATISTICS = {"median": np.median, "p50": np.median, "p90": lambda a: np.percentile(a, 90),
               "outside_2mm": lambda a: float(np.mean(a > 2.0))}

#: verdicts of :func:`paired_comparison`
VERDICTS = ("a better", "b better", "no difference")


def _walsh_median(diff, max_pairs=2_000_000, rng=None):
    """Hodges-Lehmann estimate: median of the Walsh averages (sampled when too many)."""
    n = len(diff)
    if n * (n + 1) // 2 <= max_pairs:
        i, j = np.triu_indices(n)
        return float(np.median((diff[i] + diff[j]) / 2))
    rng = np.random.default_rng(rng)
    i = rng.integers(0, n, max_pairs)
    j = rng.integers(0, n, max_pairs)
    return float(np.median((diff[i] + diff[j]) / 2))


#: paired differences at most this large (mm) are ties: a remeshed model can differ from
#: itself in the last bits, and the signed-rank test would rank that round-off
RESOLUTION_MM = 1e-6


def paired_comparison(a, b, *, alpha=0.05, n_boot=1000, seed=0, resolution=RESOLUTION_MM):
    """Paired test of two sets of absolute errors on the same points (or patients).

    Parameters
    ----------
    a, b : array_like
        Errors (mm, compared as given; pass ``|d|``) of methods a and b, paired by index.
    alpha : float, default 0.05
        Significance level of the verdict.
    n_boot : int, default 1000
        Bootstrap resamples of the confidence interval of the Hodges-Lehmann difference.
    seed : int, default 0
        Seed of the bootstrap.
    resolution : float, default :data:`RESOLUTION_MM`
        Differences ``|a - b|`` at most this large (mm) count as zero (ties).

    Returns
    -------
    dict
        ``n`` (pairs), ``median_a``, ``median_b``, ``difference`` (Hodges-Lehmann estimate
        of ``a - b``, mm; negative: a errs less), ``ci_low``, ``ci_high`` (95 % bootstrap
        percentile interval of it), ``p_value`` (two-sided Wilcoxon signed-rank; 1 when
        every difference is zero), ``effect_size`` (matched-pairs rank-biserial
        correlation in [-1, 1], ``(R+ - R-) / (R+ + R-)`` of the ranks of ``|a - b|``;
        positive: a errs more), ``verdict`` (``"a better"``, ``"b better"`` or
        ``"no difference"``).

    Raises
    ------
    ValueError
        ``a`` and ``b`` of different lengths, not 1-D, not finite, or fewer than 2 pairs.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.study.inference import paired_comparison
    >>> a = np.linspace(1.0, 2.0, 30)
    >>> paired_comparison(a, a)["verdict"], paired_comparison(a, a + 1e-12)["p_value"]
    ('no difference', 1.0)
    >>> r = paired_comparison(a + 0.5, a)
    >>> r["verdict"], round(r["difference"], 2), r["p_value"] < 0.05
    ('b better', 0.5, True)
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"a and b must be 1-D of the same length, got shapes {a.shape} "
                         f"and {b.shape}")
    if len(a) < 2 or not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise ValueError(f"a and b must hold at least 2 finite pairs, got {len(a)}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha!r}")
    if not (np.isfinite(resolution) and resolution >= 0):
        raise ValueError(f"resolution must be a finite number >= 0 (mm), got {resolution!r}")
    diff = a - b
    diff[np.abs(diff) <= resolution] = 0.0  # round-off: a tie, not a difference
    out = {"n": int(len(a)), "median_a": float(np.median(a)), "median_b": float(np.median(b))}
    nonzero = diff[diff != 0]
    if len(nonzero) == 0:  # identical methods: nothing to test
        out.update(difference=0.0, ci_low=0.0, ci_high=0.0, p_value=1.0, effect_size=0.0,
                   verdict="no difference")
        return out
    ranks = stats.rankdata(np.abs(nonzero))
    r_plus, r_minus = ranks[nonzero > 0].sum(), ranks[nonzero < 0].sum()
    p = float(stats.wilcoxon(diff, zero_method="wilcox", alternative="two-sided",
                             method="auto").pvalue)
    rng = np.random.default_rng(seed)
    hl = _walsh_median(diff, rng=rng)
    boot = np.array([_walsh_median(diff[rng.integers(0, len(diff), len(diff))],
                                   max_pairs=20_000, rng=rng) for _ in range(n_boot)])
    lo, hi = np.percentile(boot, [2.5, 97.5])
    verdict = "no difference" if not p < alpha else ("a better" if hl < 0 else "b better")
    out.update(difference=hl, ci_low=float(lo), ci_high=float(hi), p_value=p,
               effect_size=float((r_plus - r_minus) / (r_plus + r_minus)), verdict=verdict)
    return out


def paired_errors(skin_a, skin_b, region=None):
    """The paired absolute errors of two judged skins on their common skin points.

    Parameters
    ----------
    skin_a, skin_b : pyvista.DataSet
        Judged skins (point arrays ``arrays.DISTANCE`` and ``arrays.SKIN_POINT_ID``, the
        index of the point in the skin both predictions were mapped to).
    region : sequence of str, optional
        Only the points that both skins' ``arrays.REGION`` puts in one of these regions
        (names of ``arrays.FACE_REGIONS``).

    Returns
    -------
    tuple of numpy.ndarray
        ``(|d_a|, |d_b|)`` on the skin points both judged, in ``SKIN_POINT_ID`` order.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.inference import paired_errors
    >>> s = pv.PolyData(np.random.default_rng(0).random((5, 3)))
    >>> s[arrays.SKIN_POINT_ID] = np.arange(5)
    >>> s[arrays.DISTANCE] = -np.arange(5.0)
    >>> t = s.extract_points([1, 3], adjacent_cells=False)
    >>> [x.tolist() for x in paired_errors(s, t)]
    [[1.0, 3.0], [1.0, 3.0]]
    """
    def read(skin, name):
        if not isinstance(skin, pv.DataSet):
            raise TypeError(f"{name} must be a pyvista dataset, got {type(skin).__name__}")
        ids = np.asarray(arrays.require_array(skin, arrays.SKIN_POINT_ID, "point", dtype="iu",
                                              ncomp=1, producer="study_predictor"))
        d = np.asarray(arrays.require_array(skin, arrays.DISTANCE, "point", dtype="f",
                                            ncomp=1, producer="distance_to"), dtype=float)
        if region is not None:
            ids_in = [arrays.FACE_REGIONS[r] for r in region]
            reg = arrays.require_array(skin, arrays.REGION, "point", dtype="iu", ncomp=1,
                                       producer="judge_skin")
            keep = np.isin(np.asarray(reg), ids_in)
            return ids.astype(np.int64)[keep], np.abs(d)[keep]
        return ids.astype(np.int64), np.abs(d)

    if region is not None:
        unknown = sorted(set(region) - set(arrays.FACE_REGIONS))
        if isinstance(region, str) or unknown:
            raise ValueError(f"region must be a sequence of names of arrays.FACE_REGIONS "
                             f"{sorted(arrays.FACE_REGIONS)}, got {region!r}")
    ia, da = read(skin_a, "skin_a")
    ib, db = read(skin_b, "skin_b")
    common, ka, kb = np.intersect1d(ia, ib, return_indices=True)
    ok = np.isfinite(da[ka]) & np.isfinite(db[kb])
    return da[ka][ok], db[kb][ok]


def compare_methods(skins, method_a, method_b, *, alpha=0.05, n_boot=1000, seed=0,
                    resolution=RESOLUTION_MM):
    """Paired comparison of two methods of a study, per patient and over the patients.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` -> judged skin (the first result of
        :func:`pvcmf.study.validation.run_study`).
    method_a, method_b : str
        Methods compared (a - b).
    alpha, n_boot, seed, resolution :
        See :func:`paired_comparison`.

    Returns
    -------
    pandas.DataFrame
        One row per patient (``unit="point"``: its skin points paired) and, with at least
        2 patients, one row ``patient="all"``, ``unit="patient"`` (each patient's median
        ``|d|`` paired), with the columns of :func:`paired_comparison` and ``method_a``,
        ``method_b``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.inference import compare_methods
    >>> def skin(err):
    ...     s = pv.PolyData(np.zeros((40, 3)))
    ...     s[arrays.SKIN_POINT_ID] = np.arange(40)
    ...     s[arrays.DISTANCE] = err + np.linspace(0, 1, 40)
    ...     return s
    >>> skins = {1: {"x": skin(0.0), "y": skin(0.3)}}
    >>> compare_methods(skins, "x", "y")["verdict"].tolist()
    ['a better']
    """
    import pandas as pd

    rows, med_a, med_b = [], [], []
    for patient, by_method in skins.items():  # a handful of patients
        for method in (method_a, method_b):
            if method not in by_method:
                raise KeyError(f"method {method!r} not in the study of patient {patient!r} "
                               f"(methods {sorted(by_method)})")
        da, db = paired_errors(by_method[method_a], by_method[method_b])
        rows.append({"patient": patient, "unit": "point",
                     **paired_comparison(da, db, alpha=alpha, n_boot=n_boot, seed=seed,
                                         resolution=resolution)})
        med_a.append(np.median(da))
        med_b.append(np.median(db))
    if len(med_a) >= 2:
        rows.append({"patient": "all", "unit": "patient",
                     **paired_comparison(med_a, med_b, alpha=alpha, n_boot=n_boot,
                                         seed=seed, resolution=resolution)})
    table = pd.DataFrame(rows)
    table["method_a"], table["method_b"] = method_a, method_b
    return table


def claims_table(skins, claims=PAPER_CLAIMS, *, alpha=0.05, n_boot=1000, seed=0,
                 resolution=RESOLUTION_MM):
    """Each claim tested over the patients: paired statistic per patient, Wilcoxon test,
    Hodges-Lehmann difference with its 95 % bootstrap interval, effect size.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` -> judged skin (:func:`pvcmf.study.validation.run_study`).
    claims : sequence, default :data:`PAPER_CLAIMS`
        ``(claim, method a, method b, statistic)`` with statistic ``'median'``, ``'p50'``,
        ``'p90'`` or ``'outside_2mm'`` of the patient's paired ``|d|``, or
        ``(claim, method a, method b, statistic, region)``: only the points of ``region``
        (a key of :data:`REGION_GROUPS` or a sequence of ``arrays.FACE_REGIONS`` names);
        a patient with fewer than :data:`MIN_REGION_POINTS` paired points there is left
        out of that claim (``n`` counts the patients tested).
    alpha, n_boot, seed, resolution :
        See :func:`paired_comparison`.

    Returns
    -------
    pandas.DataFrame
        One row per claim: ``claim``, ``statistic``, the columns of
        :func:`paired_comparison` (over the patients) and ``holds`` (verdict "a better");
        a claim with fewer than 2 patients left has NaN statistics and verdict
        ``"not tested"``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.inference import claims_table
    >>> def skin(err):
    ...     s = pv.PolyData(np.zeros((50, 3)))
    ...     s[arrays.SKIN_POINT_ID] = np.arange(50)
    ...     s[arrays.DISTANCE] = err * np.linspace(0.5, 3.0, 50)
    ...     return s
    >>> skins = {p: {"proposed": skin(1.0), "state_of_the_art": skin(1.2 + 0.1 * p)}
    ...          for p in range(8)}
    >>> claims_table(skins, n_boot=100)["holds"].tolist()
    [True, True, True]
    """
    import pandas as pd

    rows = []
    for claim, a, b, stat, *where in claims:  # a few claims
        if stat not in _STATISTICS:
            raise ValueError(f"statistic must be one of {sorted(_STATISTICS)}, got {stat!r}")
        region = where[0] if where else None
        region = REGION_GROUPS.get(region, region) if isinstance(region, str) else region
        fa, fb = [], []
        for by_method in skins.values():  # the patients
            da, db = paired_errors(by_method[a], by_method[b], region=region)
            if region is not None and len(da) < MIN_REGION_POINTS:
                continue
            fa.append(_STATISTICS[stat](da))
            fb.append(_STATISTICS[stat](db))
        if len(fa) < 2:
            res = {"n": len(fa), "median_a": np.nan, "median_b": np.nan,
                   "difference": np.nan, "ci_low": np.nan, "ci_high": np.nan,
                   "p_value": np.nan, "effect_size": np.nan, "verdict": "not tested"}
        else:
            res = paired_comparison(fa, fb, alpha=alpha, n_boot=n_boot, seed=seed,
                                    resolution=resolution)
        rows.append({"claim": claim, "statistic": stat, **res,
                     "holds": res["verdict"] == "a better"})
    return pd.DataFrame(rows)
