"""Paper 001 Figs. 2-5: the parameter studies, drawn from a sweep table.

Every function takes the tidy table of :func:`pvcmf.sweep` (columns ``case``, the swept
parameters, ``p50``/``p90``/``p95`` in mm, ``n_cells``, ``t_eval``/``t_solve`` in s), so it
can be drawn from the real virtual-patient study or from a synthetic table in tests.

* :func:`fig2_poisson`: 90 % error against the Poisson ratio per case, minima marked, and
  the case-averaged 50/90/95 % curves;
* :func:`fig3_mesh_size`, :func:`mesh_size_table`: 90 % error and time against the mesh size,
  and the table (N_tetra near 30k, T_sim, D_90 to the finest mesh);
* :func:`fig4_inhomogeneous`, :func:`inhomogeneous_table`: min/max 50/90 % over (nu_fat,
  nu_muscle) per E_muscle/E_fat, and the averaged 90 % error over that grid at E ratio 1;
* :func:`optimal_poisson`, :func:`fig5_optimal_poisson`: per skin point, the Poisson ratio
  minimising the local 90 % error and that error's spread across ratios (PyVista).

Delegates to matplotlib, pandas (grouping), scipy's cKDTree and PyVista (3-D renders).
"""

from __future__ import annotations

import functools
import logging
import os
from pathlib import Path

import numpy as np

from ..study.engine import sweep
from ..study.evaluation import synthetic_evaluate
from ..study.pipeline_evaluation import STUDY_SPACING, PipelineEvaluation
from ..study.tables import save_table
from ..truth.grid import postop_skin
from .face_views import add_patient_mesh, carry_to_skin, set_view, to_display

log = logging.getLogger(__name__)

__all__ = [
    "fig2_poisson",
    "poisson_optimum",
    "fig3_mesh_size",
    "mesh_size_table",
    "fig4_inhomogeneous",
    "inhomogeneous_table",
    "optimal_poisson",
    "fig5_optimal_poisson",
    "run_study",
]


def study_settings(gallery_dir=None):
    """The gallery's study settings, read from the environment (one place for Figs. 2-5).

    ``PVCMF_GALLERY_OUT`` (output folder, default ``gallery_dir / "_out"``),
    ``PVCMF_SYNTHETIC=1`` (cheap synthetic evaluation), ``PVCMF_SCHEDULER``,
    ``PVCMF_STUDY_PATIENTS`` (e.g. ``"1 2"``, default all four), ``PVCMF_STUDY_SPACING``
    (mm, default :data:`pvcmf.sweeps.STUDY_SPACING`, shared with Figs. 6-8 so the truths are
    shared) and ``PVCMF_STUDY_TRUTH_TETS`` (P2 truth elements, default 16000: ~75k dofs,
    richer than the 30k P1 MTM; 120k needs over an hour of CPU per patient on 2 cores).

    Returns
    -------
    dict
        ``out`` (Path), ``synthetic``, ``scheduler``, ``patients`` (list of int),
        ``study`` (``spacing`` and ``truth_tets`` for :func:`run_study`), ``title``.
    """
    env = os.environ.get
    base = Path(gallery_dir) if gallery_dir is not None else Path.cwd()
    synthetic = env("PVCMF_SYNTHETIC") == "1"
    patients = [int(p) for p in env("PVCMF_STUDY_PATIENTS", "1 2 3 4").replace(",", " ").split()]
    return {
        "out": Path(env("PVCMF_GALLERY_OUT", base / "_out")),
        "synthetic": synthetic,
        "scheduler": env("PVCMF_SCHEDULER"),
        "patients": patients,
        "study": {"spacing": float(env("PVCMF_STUDY_SPACING", STUDY_SPACING)),
                  "truth_tets": int(env("PVCMF_STUDY_TRUTH_TETS", 16_000))},
        "title": ("synthetic evaluation" if synthetic
                  else f"virtual patients {', '.join(map(str, patients))}"),
    }


def run_study(cases, grid, name, out, *, synthetic=False, scheduler=None, keep_arrays=False,
              progress_bar=True, **options):
    """Run a figure's sweep as the gallery does: cached in ``out``, table saved as CSV.

    Parameters
    ----------
    cases : sequence
        Virtual patient numbers.
    grid : mapping
        Parameter grid (:func:`pvcmf.sweep`).
    name : str
        File stem of the saved table ``out / f"{name}.csv"``.
    out : pathlib.Path
        Output folder; results are cached in ``out / "sweep-cache"``, prepared cases
        (meshes) in ``out / "sweep-cache" / "prepared"``, shared by all figures.
    synthetic : bool
        Use :func:`pvcmf.sweeps.synthetic_evaluate` instead of the pipeline.
    scheduler : optional
        As :func:`pvcmf.sweep`.
    keep_arrays : bool
        Keep per-point maps (Fig. 5); the pipeline then returns them too.
    progress_bar : bool
        Show the sweep's progress bar.
    **options
        :class:`pvcmf.sweeps.PipelineEvaluation` options (``spacing``, ``n_tets``, ...), and
        ``truth_tets``: judge against ``pvcmf.reference.postop_skin(case, n_tets=truth_tets)``
        instead of the default (16k P2) truth.

    Returns
    -------
    pandas.DataFrame
        The sweep table.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    truth_tets = options.pop("truth_tets", None)
    if truth_tets is not None and "truth" not in options:  # a coarser (cached) reference truth
        options["truth"] = functools.partial(postop_skin, n_tets=int(truth_tets))
    evaluate = synthetic_evaluate if synthetic else PipelineEvaluation(
        keep_distance=keep_arrays, cache_dir=out / "sweep-cache" / "prepared", **options)
    df = sweep(cases, grid, evaluate=evaluate, scheduler=scheduler, cache_dir=out / "sweep-cache",
               progress_bar=progress_bar, keep_arrays=keep_arrays)
    save_table(df, out / f"{name}.csv")
    return df


def _require(df, columns, who):
    import pandas as pd

    if not isinstance(df, pd.DataFrame):
        raise TypeError(f"{who}: df must be a pandas DataFrame from pvcmf.sweep, got {type(df).__name__}")
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(f"{who}: df has no column(s) {missing} (it has {list(df.columns)}); "
                         "sweep the parameter in the grid")
    if df.empty:
        raise ValueError(f"{who}: df is empty")


def _figure(figsize):
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, layout="constrained")


# --------------------------------------------------------------------------- Fig. 2

def poisson_optimum(df, metric="p90"):
    """Per-case and average optimum of ``metric`` over the Poisson ratio ``nu``.

    Returns
    -------
    pandas.DataFrame
        One row per case (and a final ``"average"`` row over the case-averaged curve):
        ``nu_opt``, ``best`` (the minimal ``metric``), ``at_046`` (``metric`` at the nu
        closest to 0.46) and ``d_046`` = ``at_046 - best`` (mm, paper 001 sec. 3.1).

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> from pvcmf.figures.parameter_studies import poisson_optimum
    >>> df = pvcmf.sweep([1], {"nu": [0.0, 0.3, 0.46]}, evaluate=synthetic_evaluate,
    ...                  scheduler="synchronous")
    >>> float(poisson_optimum(df).loc["P1", "nu_opt"])
    0.46
    """
    import pandas as pd

    _require(df, ["case", "nu", metric], "poisson_optimum")
    curves = df.pivot_table(index="nu", columns="case", values=metric, aggfunc="mean", sort=True)
    curves = curves[list(dict.fromkeys(df["case"]))]
    curves["average"] = curves.mean(axis=1)
    nus = curves.index.to_numpy()
    ref = nus[np.argmin(np.abs(nus - 0.46))]
    rows = {}
    for name in curves.columns:
        c = curves[name]
        rows[name] = {"nu_opt": float(c.idxmin()), "best": float(c.min()), "at_046": float(c[ref]),
                      "d_046": float(c[ref] - c.min())}
    return pd.DataFrame.from_dict(rows, orient="index")


def fig2_poisson(df, *, metric="p90", title=None):
    """Paper 001 Fig. 2: error against the Poisson ratio.

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep table with columns ``case``, ``nu``, ``p50``, ``p90``, ``p95`` (mm).
    metric : str
        Statistic of the left panel (the paper: ``"p90"``).
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        (a) ``metric`` against nu per case, a cross at each case's minimum; (b) the
        case-averaged 50/90/95 % curves with their minima marked.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> from pvcmf.figures.parameter_studies import fig2_poisson
    >>> df = pvcmf.sweep([1, 2], {"nu": [0.0, 0.25, 0.46, 0.495]},
    ...                  evaluate=synthetic_evaluate, scheduler="synchronous")
    >>> fig = fig2_poisson(df)
    """
    _require(df, ["case", "nu", "p50", "p90", "p95"], "fig2_poisson")
    fig = _figure((10, 4.2))
    ax_a, ax_b = fig.subplots(1, 2)
    cases = list(dict.fromkeys(df["case"]))
    colors = _case_colors(len(cases))
    for color, case in zip(colors, cases):
        sub = df[df["case"] == case].groupby("nu")[metric].mean().sort_index()
        ax_a.plot(sub.index, sub.values, "-", color=color, lw=1.4, label=str(case))
        ax_a.plot(sub.idxmin(), sub.min(), "x", color=color, ms=9, mew=2.2)
    ax_a.set_xlabel("Poisson ratio $\\nu$")
    ax_a.set_ylabel(f"{metric[1:]} % percentile error (mm)")
    ax_a.set_title(f"(a) {metric[1:]} % percentile per case (x = minimum)")
    ax_a.legend(fontsize=8, ncol=2, frameon=False)
    ax_a.grid(alpha=0.3)

    styles = {"p50": ("tab:green", "50 %"), "p90": ("tab:blue", "90 %"), "p95": ("tab:red", "95 %")}
    mean = df.groupby("nu")[["p50", "p90", "p95"]].mean().sort_index()
    for col, (color, label) in styles.items():
        ax_b.plot(mean.index, mean[col], "-", color=color, lw=1.8, label=label)
        ax_b.plot(mean[col].idxmin(), mean[col].min(), "x", color=color, ms=9, mew=2.2)
        ax_b.annotate(f"{mean[col].idxmin():.3g}", (mean[col].idxmin(), mean[col].min()),
                      textcoords="offset points", xytext=(-6, 7), fontsize=8, color=color)
    ax_b.axvspan(0.45, 0.46, color="0.85", zorder=0, label="paper: 0.45-0.46")
    ax_b.set_xlabel("Poisson ratio $\\nu$")
    ax_b.set_ylabel("average percentile error (mm)")
    ax_b.set_title(f"(b) average over {len(cases)} case(s)")
    ax_b.legend(fontsize=8, frameon=False)
    ax_b.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig


def _case_colors(n):
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


# --------------------------------------------------------------------------- Fig. 3

def _size_column(df):
    return "n_cells" if "n_cells" in df.columns else "n_tets"


def _time_column(df):
    for c in ("t_solve", "t_eval"):
        if c in df.columns:
            return c
    raise ValueError("df has no time column ('t_solve' or 't_eval')")


def mesh_size_table(df, *, target=30_000, metric="p90"):
    """Paper 001 Fig. 3's table: per case the mesh nearest ``target`` tetrahedra.

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep table over ``n_tets`` (actual counts from ``n_cells`` when present).
    target : int
        Tetrahedra count of the table's mesh (the paper: 30,000).
    metric : str
        Error statistic (the paper: ``"p90"``).

    Returns
    -------
    pandas.DataFrame
        Index: cases and ``"Average"``; columns ``N_tetra``, ``T_sim`` (s), ``D90`` =
        ``metric`` at ~``target`` minus ``metric`` on the finest mesh (mm; negative where
        the coarser mesh was better; the Average row averages ``|D90|``) and
        ``N_finest``.
    """
    import pandas as pd

    size = _size_column(df)
    _require(df, ["case", "n_tets", metric], "mesh_size_table")
    tcol = _time_column(df)
    rows = {}
    for case in dict.fromkeys(df["case"]):
        sub = df[df["case"] == case].groupby("n_tets")[[size, metric, tcol]].mean()
        sub = sub.sort_values(size)
        near = sub.iloc[int(np.argmin(np.abs(sub[size].to_numpy() - target)))]
        finest = sub.iloc[-1]
        rows[case] = {"N_tetra": int(round(near[size])), "T_sim": float(near[tcol]),
                      "D90": float(near[metric] - finest[metric]), "N_finest": int(round(finest[size]))}
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.loc["Average"] = {"N_tetra": int(round(table["N_tetra"].mean())), "T_sim": table["T_sim"].mean(),
                            "D90": table["D90"].abs().mean(), "N_finest": int(round(table["N_finest"].mean()))}
    table["N_tetra"] = table["N_tetra"].astype(int)
    table["N_finest"] = table["N_finest"].astype(int)
    return table


def fig3_mesh_size(df, *, target=30_000, metric="p90", title=None):
    """Paper 001 Fig. 3: error and simulation time against the mesh size, and its table.

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep table over ``n_tets`` with ``p90`` and a time column (``t_solve`` or
        ``t_eval``, s).
    target : int
        Tetrahedra count marked by the vertical line and used by the table.
    metric : str
        Error statistic.
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Left: ``metric`` (full lines) and time (dotted, right axis) per case against the
        number of tetrahedra; right: :func:`mesh_size_table`.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> from pvcmf.figures.parameter_studies import fig3_mesh_size
    >>> df = pvcmf.sweep([1], {"n_tets": [5000, 30000, 200000]},
    ...                  evaluate=synthetic_evaluate, scheduler="synchronous")
    >>> fig = fig3_mesh_size(df)
    """
    _require(df, ["case", "n_tets", metric], "fig3_mesh_size")
    size, tcol = _size_column(df), _time_column(df)
    table = mesh_size_table(df, target=target, metric=metric)
    fig = _figure((11, 4.2))
    ax, ax_t = fig.subplots(1, 2, width_ratios=[1.6, 1])
    ax_time = ax.twinx()
    cases = list(dict.fromkeys(df["case"]))
    for color, case in zip(_case_colors(len(cases)), cases):
        sub = df[df["case"] == case].groupby("n_tets")[[size, metric, tcol]].mean().sort_values(size)
        ax.plot(sub[size], sub[metric], "-o", color=color, ms=3, lw=1.4, label=str(case))
        ax_time.plot(sub[size], sub[tcol], ":", color=color, lw=1.4)
    ax.axvline(target, color="k", lw=1.2)
    ax.set_xlabel("number of tetrahedra")
    ax.set_ylabel(f"{metric[1:]} % percentile error (mm), full lines")
    ax_time.set_ylabel(f"simulation time (s), dotted ({tcol})")
    ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, frameon=False, loc="upper center")
    ax.set_title(f"{metric[1:]} % percentile and time against mesh size")
    ax_t.axis("off")
    cells = [[str(i), f"{int(r.N_tetra):d}", f"{r.T_sim:.2f}", f"{r.D90:+.3f}" if i != "Average" else f"{r.D90:.3f}"]
             for i, r in table.iterrows()]
    tab = ax_t.table(cellText=cells, colLabels=["case", "N_tetra", "T_sim (s)", "D90 (mm)"],
                     loc="center", cellLoc="center")
    tab.auto_set_font_size(False)
    tab.set_fontsize(9)
    tab.scale(1, 1.4)
    ax_t.set_title(f"near {target:,} tetrahedra; D90 vs finest mesh (~{int(table['N_finest'].iloc[-1]):,})",
                   fontsize=9)
    if title:
        fig.suptitle(title)
    return fig


# --------------------------------------------------------------------------- Fig. 4

def inhomogeneous_table(df, *, case=None):
    """Paper 001 Fig. 4 (a): min/max 50 % and 90 % percentiles over (nu_fat, nu_muscle).

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep table over ``E_ratio``, ``nu_fat`` and ``nu_muscle``.
    case : str, optional
        Case of the table (default: the first case).

    Returns
    -------
    pandas.DataFrame
        Index ``E_ratio``; columns ``p50_min``, ``p50_max``, ``p90_min``, ``p90_max`` (mm)
        and ``nu_fat_opt``, ``nu_muscle_opt`` (the arg-min of ``p90``).
    """
    import pandas as pd

    _require(df, ["case", "E_ratio", "nu_fat", "nu_muscle", "p50", "p90"], "inhomogeneous_table")
    case = df["case"].iloc[0] if case is None else case
    sub = df[df["case"] == case]
    if sub.empty:
        raise ValueError(f"inhomogeneous_table: case {case!r} not in df (cases: {sorted(set(df['case']))})")
    rows = {}
    for ratio, g in sub.groupby("E_ratio", sort=True):
        best = g.loc[g["p90"].idxmin()]
        rows[ratio] = {"p50_min": g["p50"].min(), "p50_max": g["p50"].max(), "p90_min": g["p90"].min(),
                       "p90_max": g["p90"].max(), "nu_fat_opt": best["nu_fat"],
                       "nu_muscle_opt": best["nu_muscle"]}
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index.name = "E_ratio"
    return table


def fig4_inhomogeneous(df, *, case=None, ratio=1.0, title=None):
    """Paper 001 Fig. 4: Young's modulus ratio table and the (nu_fat, nu_muscle) map.

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep table over ``E_ratio``, ``nu_fat``, ``nu_muscle``.
    case : str, optional
        Case of the table (default: the first).
    ratio : float
        E_muscle/E_fat of the map (the paper: 1; the nearest swept ratio is used).
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Left: :func:`inhomogeneous_table`; right: case-averaged ``p90`` over the
        (nu_fat, nu_muscle) grid at ``ratio``, minimum marked.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate
    >>> from pvcmf.figures.parameter_studies import fig4_inhomogeneous
    >>> df = pvcmf.sweep([1], {"E_ratio": [1, 8], "nu_fat": [0.3, 0.485],
    ...                  "nu_muscle": [0.3, 0.43]}, evaluate=synthetic_evaluate,
    ...                  scheduler="synchronous")
    >>> fig = fig4_inhomogeneous(df)
    """
    table = inhomogeneous_table(df, case=case)
    case = df["case"].iloc[0] if case is None else case
    ratios = np.array(sorted(set(df["E_ratio"])))
    use = ratios[np.argmin(np.abs(ratios - ratio))]
    avg = (df[df["E_ratio"] == use].groupby(["nu_muscle", "nu_fat"])["p90"].mean()
           .unstack("nu_fat").sort_index().sort_index(axis=1))
    fig = _figure((11, 4.4))
    ax_t, ax = fig.subplots(1, 2, width_ratios=[1, 1.1])
    ax_t.axis("off")
    cells = [[f"{r:g}", f"{t.p50_min:.3f}", f"{t.p50_max:.3f}", f"{t.p90_min:.3f}", f"{t.p90_max:.3f}"]
             for r, t in table.iterrows()]
    tab = ax_t.table(cellText=cells, loc="center", cellLoc="center",
                     colLabels=["E_m/E_f", "P50 min", "P50 max", "P90 min", "P90 max"])
    tab.auto_set_font_size(False)
    tab.set_fontsize(9)
    tab.scale(1, 1.4)
    ax_t.set_title(f"(a) {case}: min/max over ($\\nu_{{fat}}$, $\\nu_{{muscle}}$), mm", fontsize=10)
    nf, nm = avg.columns.to_numpy(float), avg.index.to_numpy(float)
    values = avg.to_numpy()
    # one cell per sampled pair, on index axes labelled with the sampled ratios: value-scaled
    # cells would stretch the coarse grid's end cells into ratios that were never run (< 0)
    im = ax.imshow(values, origin="lower", aspect="auto", cmap="viridis", interpolation="nearest")
    ax.set_xticks(np.arange(nf.size), [f"{v:.3g}" for v in nf])
    ax.set_yticks(np.arange(nm.size), [f"{v:.3g}" for v in nm])
    j, i = np.unravel_index(np.nanargmin(values), values.shape)
    if values.size <= 100:  # the number in each sampled cell
        lo, hi = np.nanmin(values), np.nanmax(values)
        for (r, c), v in np.ndenumerate(values):
            if np.isfinite(v):
                dark = (v - lo) < 0.6 * (hi - lo) if hi > lo else True
                ax.text(c, r, f"{v:.2f}", ha="center", va="center", fontsize=7,
                        color="w" if dark else "k")
    ax.plot(i, j, "s", mfc="none", mec="r", ms=16, mew=2)
    ax.annotate(f"min {values[j, i]:.3f} mm ($\\nu_f$={nf[i]:.3g}, $\\nu_m$={nm[j]:.3g})",
                (0.0, 1.0), xycoords="axes fraction", xytext=(2, 4), textcoords="offset points",
                fontsize=8, va="bottom")
    ax.set_xlabel("$\\nu_{fat}$")
    ax.set_ylabel("$\\nu_{muscle}$")
    ncase = df["case"].nunique()
    ax.set_title(f"(b) mean 90 % percentile over {ncase} case(s), $E_m/E_f$ = {use:g}",
                 fontsize=10, pad=16)
    fig.colorbar(im, ax=ax, label="90 % percentile error (mm)")
    if title:
        fig.suptitle(title)
    return fig


# --------------------------------------------------------------------------- Fig. 5

def optimal_poisson(df, skin, *, case=None, neighbours=16, percentile=90.0):
    """Per skin point: the Poisson ratio minimising the local error percentile, and its spread.

    For each point the local statistic is the ``percentile`` of ``|distance|`` over its
    ``neighbours`` nearest skin points (``neighbours=1``: the point's own ``|distance|``),
    evaluated for every swept nu (paper 001 Fig. 5, "the value that minimises the 90 %
    error percentile").

    Parameters
    ----------
    df : pandas.DataFrame
        Sweep over ``nu`` made with ``keep_arrays=True``: a ``distance`` column holding
        each row's per-point signed distance map on ``skin``.
    skin : pyvista.PolyData
        The skin surface the maps live on (same number of points).
    case : str, optional
        Case to use (default: the first).
    neighbours : int
        Neighbourhood size for the local percentile.
    percentile : float
        Local percentile (the paper: 90).

    Returns
    -------
    pyvista.PolyData
        Copy of ``skin`` with point arrays ``nu_opt`` (optimal ratio), ``p90_spread``
        (std of the local percentile across nu, mm) and ``p90_best`` (mm).
    """
    from scipy.spatial import cKDTree

    _require(df, ["case", "nu", "distance"], "optimal_poisson")
    case = df["case"].iloc[0] if case is None else case
    sub = df[df["case"] == case].sort_values("nu")
    if sub.empty:
        raise ValueError(f"optimal_poisson: case {case!r} not in df")
    maps = np.stack([np.asarray(d, float).ravel() for d in sub["distance"]])  # (n_nu, n_pts)
    if maps.shape[1] != skin.n_points:
        raise ValueError(f"optimal_poisson: distance maps have {maps.shape[1]} points, "
                         f"skin has {skin.n_points}; pass the skin the maps were measured on")
    k = int(min(max(1, neighbours), skin.n_points))
    if k > 1:
        _, nbr = cKDTree(np.asarray(skin.points)).query(np.asarray(skin.points), k=k)
        local = np.percentile(np.abs(maps[:, nbr]), percentile, axis=2)  # (n_nu, n_pts)
    else:
        local = np.abs(maps)
    nus = sub["nu"].to_numpy(float)
    out = skin.copy()
    out.point_data["nu_opt"] = nus[np.argmin(local, axis=0)]
    out.point_data["p90_spread"] = local.std(axis=0)
    out.point_data["p90_best"] = local.min(axis=0)
    return out


def fig5_optimal_poisson(df, skin, *, case=None, neighbours=16, spread_max=0.3,
                         window_size=(1000, 500), context=None):
    """Paper 001 Fig. 5: per-point optimal Poisson ratio and error spread on the face.

    Parameters
    ----------
    df, skin, case, neighbours
        As :func:`optimal_poisson`.
    spread_max : float
        Upper end of the spread colour scale, mm (the paper: 0.3).
    window_size : tuple of int
        Render size in pixels.
    context : pyvista.PolyData, optional
        The whole pre-operative skin: the maps are drawn on it, bridging the gaps between
        the face regions (:func:`pvcmf.figures.face_views.carry_to_skin`), grey elsewhere.

    Returns
    -------
    pyvista.Plotter
        Off-screen plotter, two views of the face seen from the front in the photographic
        convention (the patient's right on the viewer's left, as
        :func:`pvcmf.figures.face_views.set_view`): (a) ``nu_opt``, (b) ``p90_spread``.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.sweeps import synthetic_evaluate, synthetic_skin
    >>> from pvcmf.figures.parameter_studies import fig5_optimal_poisson
    >>> df = pvcmf.sweep([1], {"nu": [0.1, 0.3, 0.46]}, evaluate=synthetic_evaluate,
    ...                  scheduler="synchronous", keep_arrays=True)
    >>> pl = fig5_optimal_poisson(df, synthetic_skin())
    >>> pl.close()
    """
    import pyvista as pv

    face = patch = optimal_poisson(df, skin, case=case, neighbours=neighbours)
    if context is not None:
        face = carry_to_skin(patch, context, ["nu_opt", "p90_spread"])
    nus = np.sort(df["nu"].unique())
    pl = pv.Plotter(off_screen=True, shape=(1, 2), window_size=list(window_size), border=False)
    for col, (name, clim, cmap, label, unit) in enumerate([
        ("nu_opt", (float(nus.min()), float(nus.max())), "viridis", "(a) optimal Poisson ratio", " "),
        ("p90_spread", (0.0, spread_max), "magma", "(b) std of the 90 % percentile over nu (mm)", "  "),
    ]):
        pl.subplot(0, col)
        pl.add_text(label, position="upper_edge", font_size=9, color="black")
        add_patient_mesh(pl, face, scalars=name, clim=clim, cmap=cmap, nan_color="lightgray",
                    scalar_bar_args={"title": unit, "vertical": False, "position_x": 0.15,
                                     "position_y": 0.04, "width": 0.7, "height": 0.08,
                                     "title_font_size": 14, "label_font_size": 12, "fmt": "%.2f",
                                     "color": "black"})
        set_view(pl, to_display(patch).bounds, "frontal", zoom=0.75)  # room for title, bar
    pl.set_background("white")
    return pl
