"""Write ``report.html`` for a case folder (prediction or validation).

:func:`write_report` gathers what a case folder holds (``summary.json``, the PNGs, the
skins ``skin_pre.vtp``, ``predicted_skin.vtp``, ``validated_skin.vtp``,
``postop_skin.vtp``), or takes them from a :class:`pvcmf.pipeline.Result`, and writes the
page of :func:`pvcmf.report.html.report_html` atomically. Delegates the page to
:mod:`pvcmf.report.html` and the 3D scene to :mod:`pvcmf.report.scene`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pyvista as pv
from matplotlib.colors import to_rgb

from .. import arrays
from .._atomic import write_text
from ..figures.skin_marks import MAP_CUT_COLOR, MAP_CUT_WORDS, cut_points, judged_points
from ..figures.validation import error_colormap
from .html import _ENABLED, REPORT_NAME, SKIN_FILES, _colourbar, region_rows, report_html
from .scene import DEFAULT_MAX_POINTS, colormap_stops, pack_skin, scene_json

log = logging.getLogger("pvcmf.report")

__all__ = ["write_report"]

#: half-width (mm) of the error colour map in the 3D view (paper 000 Fig. 6)
ERROR_LIMIT = 6.0


def _read(folder, name):
    path = folder / name
    return pv.read(path) if path.exists() else None


def _skins(folder, result):
    """Viewer name -> (PolyData, label, colour, opacity, shown)."""
    found = {}
    for name, (key, label, color, opacity, shown) in SKIN_FILES.items():
        skin = None
        if result is not None and name == "skin_pre.vtp":
            skin = result.skin_pre
        elif result is not None and name == "predicted_skin.vtp":
            skin = result.skin_post
        if skin is None:
            skin = _read(folder, name)
        if skin is not None and skin.n_points:
            found[key] = (skin.extract_surface(algorithm="dataset_surface")
                          if not isinstance(skin, pv.PolyData) else skin,
                          label, color, opacity, shown)
    return found


def _scene(skins, max_points):
    """Packed skins, colourings and colour bars for the viewer."""
    packed, colourings, bars, ui = {}, {}, [], []
    pred = skins.get("predicted", (None,))[0]
    scalars = {}
    # the scan's edge: in its own colour (NaN), out of the ranges, named under the bars
    cut = None if pred is None else cut_points(pred)
    edge = f"; {MAP_CUT_WORDS}" if cut is not None and cut.any() else ""
    if pred is not None and arrays.DISPLACEMENT in pred.point_data:
        u = np.linalg.norm(np.asarray(pred[arrays.DISPLACEMENT], dtype=float), axis=1)
        scalars["displacement"] = np.where(cut, np.nan, u)
        stops = colormap_stops("viridis")
        hi = max(float(u[~cut].max(initial=0.0)), 1e-3)
        colourings["displacement"] = {"skin": "predicted", "scalar": "displacement",
                                      "stops": stops, "range": [0.0, hi],
                                      "nan": list(to_rgb(MAP_CUT_COLOR))}
        bars.append(_colourbar("displacement", "|displacement| (mm)" + edge, stops, 0.0, hi))
        ui.append(("displacement", "displacement |u| (mm)"))
    if pred is not None and arrays.DISTANCE in pred.point_data:
        scalars["error"] = np.where(cut, np.nan, np.asarray(pred[arrays.DISTANCE], dtype=float))
        stops = colormap_stops(error_colormap(ERROR_LIMIT), 25)
        colourings["error"] = {"skin": "predicted", "scalar": "error", "stops": stops,
                               "range": [-ERROR_LIMIT, ERROR_LIMIT],
                               "nan": list(to_rgb(MAP_CUT_COLOR))}
        bars.append(_colourbar("error", "signed error (mm), + anterior" + edge, stops,
                               -ERROR_LIMIT, ERROR_LIMIT))
        ui.insert(0, ("error", "error: predicted - post-operative (mm)"))
    for key, (skin, label, color, opacity, shown) in skins.items():
        packed[key] = pack_skin(skin, scalars if key == "predicted" else None,
                                max_points=max_points)
        packed[key].update(color=list(color), opacity=opacity, visible=shown)
    skins_ui = [(k, v[1], v[4]) for k, v in skins.items()]
    return scene_json(packed, colourings), bars, skins_ui, ui


def _regions(summary, skins):
    """(rows, caption) of the per-region table."""
    if summary.get("regions"):
        return summary["regions"], ("Signed distance d of the predicted skin to the registered "
                                    "post-operative skin: percentiles of |d| and share of "
                                    "points with |d| within 1 and 2 mm.")
    pred = skins.get("predicted", (None,))[0]
    if pred is None or arrays.DISPLACEMENT not in pred.point_data:
        return None, ""
    pre = skins.get("pre", (None,))[0]
    where = pre if pre is not None and pre.n_points == pred.n_points else pred
    u = np.linalg.norm(np.asarray(pred[arrays.DISPLACEMENT], dtype=float), axis=1)
    mask = None  # the unmoved back of the head is not counted, nor the scan's edge
    if arrays.SKIN_MODELLED in pred.point_data or cut_points(pred).any():
        mask = judged_points(pred)
    return region_rows(where, u, mask=mask), ("Predicted displacement |u| of the skin (no post-operative "
                                   "scan given): percentiles and share of points that move "
                                   "at most 1 and 2 mm. Regions are labelled on the "
                                   "pre-operative skin.")


def write_report(folder, *, result=None, path=None, title=None,
                 max_points=DEFAULT_MAX_POINTS):
    """Write the case's self-contained offline ``report.html``.

    Parameters
    ----------
    folder : str or pathlib.Path
        Case folder of ``pvcmf simulate`` / ``demo`` / ``validate``.
    result : pvcmf.pipeline.Result, optional
        Take the skins, plan and timings from here instead of the folder's files.
    path : str or pathlib.Path, optional
        Output file (default ``folder / 'report.html'``).
    title : str, optional
        Page title (default from the plan's name or the folder's name).
    max_points : int, default DEFAULT_MAX_POINTS
        Skins with more points are decimated for the 3D view.

    Returns
    -------
    pathlib.Path or None
        The written page; ``None`` inside :func:`pvcmf.report.disabled`.

    Examples
    --------
    >>> import tempfile, pyvista as pv
    >>> from pvcmf.report import write_report
    >>> folder = tempfile.mkdtemp()
    >>> pv.ParametricEllipsoid(70, 95, 110).save(f"{folder}/predicted_skin.vtp")
    >>> write_report(folder).name
    'report.html'
    """
    if not _ENABLED.get():
        return None
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"folder must be an existing case folder, got {str(folder)!r}")
    sfile = folder / "summary.json"
    summary = json.loads(sfile.read_text(encoding="utf-8")) if sfile.exists() else {}
    skins = _skins(folder, result)
    scene = bars = skins_ui = colourings_ui = None
    if skins:
        scene, bars, skins_ui, colourings_ui = _scene(skins, max_points)
    regions, caption = _regions(summary, skins)
    plan = result.plan.to_dict() if result is not None else summary.get("plan")
    timings = dict(result.timings) if result is not None else summary.get("seconds")
    notes = list(result.warnings) if result is not None else summary.get("warnings", [])
    images = {p.name: p.read_bytes() for p in sorted(folder.glob("*.png"))}
    extra = {}
    if summary.get("registration"):
        extra["Registration (ICP)"] = {k: v for k, v in summary["registration"].items()
                                       if k != "matrix"}
    if summary.get("inputs"):
        extra["Inputs"] = summary["inputs"]
    if title is None:
        kind = "Validation" if summary.get("regions") else "Prediction"
        name = (plan or {}).get("name") or folder.resolve().name
        title = f"{kind}: {name}"
    page = report_html(title=title, scene=scene, colourbars=bars or (), skins_ui=skins_ui or (),
                       colourings_ui=colourings_ui or (), regions=regions,
                       regions_caption=caption, plan=plan, timings=timings, images=images,
                       extra=extra, warnings=notes)
    out = write_text(path or folder / REPORT_NAME, page)
    log.info("report: %s (%.1f MB)", out, out.stat().st_size / 1e6)
    return out
