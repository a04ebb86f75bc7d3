"""The per-case HTML report: one self-contained, offline page per prediction or validation.

:func:`pvcmf.report.write_report` (:mod:`pvcmf.report.case`) reads a case folder written by ``pvcmf simulate`` / ``pvcmf demo``
(:func:`pvcmf.outputs.write_outputs`) or ``pvcmf validate`` (:mod:`pvcmf.study.validate`)
and writes ``report.html`` into it with :func:`report_html`: an interactive 3D view of the pre-operative,
predicted and (validation) post-operative skins with the displacement or error map and
its colour bar (:mod:`pvcmf.report.scene`, vtk.js inlined), the PNG figures of the run
(base64), the plan, the per-region table (lips, chin, nose, cheeks:
:func:`pvcmf.study.statistics.label_face_regions` and
:func:`pvcmf.study.statistics.summary`), the software versions and the seconds per step.
Nothing is fetched when the page is viewed. Delegates to :mod:`html` (escaping),
:mod:`importlib.metadata` (versions) and Pillow-free base64 embedding of the PNG bytes.
"""

from __future__ import annotations

import base64
import contextlib
import contextvars
import datetime
import html
import logging
import platform
from importlib import metadata

import numpy as np

from .. import arrays
from ..study.statistics import label_face_regions, summary
from .scene import VIEWER_JS, VTKJS_VERSION, vtkjs_source

log = logging.getLogger("pvcmf.report")

__all__ = ["REPORT_NAME", "disabled", "region_rows", "report_html"]

#: file name of the report in a case folder
REPORT_NAME = "report.html"
#: the table's statistics: (key of summary(), column header)
TABLE_COLUMNS = (("n", "points"), ("p50", "p50 (mm)"), ("p90", "p90 (mm)"),
                 ("p95", "p95 (mm)"), ("within_1mm", "≤ 1 mm (%)"),
                 ("within_2mm", "≤ 2 mm (%)"))
#: skins of a case folder: file -> (viewer name, label, colour, opacity, shown at start)
SKIN_FILES = {
    "skin_pre.vtp": ("pre", "pre-operative", (0.80, 0.80, 0.80), 1.0, False),
    "predicted_skin.vtp": ("predicted", "predicted", (1.0, 0.85, 0.73), 1.0, True),
    "validated_skin.vtp": ("predicted", "predicted", (1.0, 0.85, 0.73), 1.0, True),
    "postop_skin.vtp": ("post", "post-operative (registered)", (0.55, 0.70, 0.95), 0.6, False),
}
_ENABLED = contextvars.ContextVar("pvcmf_report_enabled", default=True)


@contextlib.contextmanager
def disabled():
    """Within this block :func:`write_report` writes nothing (``--no-report``)."""
    token = _ENABLED.set(False)
    try:
        yield
    finally:
        _ENABLED.reset(token)


def _fmt(value, key):
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "–"
    return f"{int(value)}" if key == "n" else f"{float(value):.2f}"


def region_rows(skin, values, *, landmarks=None, mask=None):
    """Statistics of ``|values|`` for the whole face and per face region.

    Parameters
    ----------
    skin : pyvista.PolyData
        Skin in the patient frame (its ``arrays.REGION`` array, or
        :func:`pvcmf.study.statistics.label_face_regions`).
    values : array_like
        One value per point (signed distances or displacement magnitudes, mm).
    landmarks : dict, optional
        Passed to ``label_face_regions``.
    mask : array_like of bool, optional
        Points to count (e.g. the skin the model predicts, ``arrays.SKIN_MODELLED``); the
        first row is then ``'modelled skin'``.

    Returns
    -------
    list of dict
        ``region`` (``'all skin'``, then the regions) and the columns of
        :func:`pvcmf.study.statistics.summary`.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.report.html import region_rows
    >>> head = pv.ParametricEllipsoid(70, 95, 110)
    >>> rows = region_rows(head, np.full(head.n_points, 1.5))
    >>> rows[0]["region"], rows[0]["p90"], rows[0]["within_1mm"]
    ('all skin', 1.5, 0.0)
    """
    values = np.asarray(values, dtype=float)
    if arrays.REGION in skin.point_data:
        reg = np.asarray(skin.point_data[arrays.REGION])
    else:
        reg = np.asarray(label_face_regions(skin, landmarks=landmarks)[arrays.REGION])
    keep = np.ones(values.shape[0], dtype=bool)
    if mask is not None:
        keep = np.asarray(mask, dtype=bool).reshape(-1)
        if keep.shape != values.shape[:1]:
            raise ValueError(f"mask must have one entry per point ({values.shape[0]}), "
                             f"got shape {keep.shape}")
    first = "all skin" if mask is None else "modelled skin"
    rows = [{"region": first, **summary(values[keep])}]
    for name, rid in arrays.FACE_REGIONS.items():
        if rid:
            rows.append({"region": name, **summary(values[(reg == rid) & keep])})
    return rows


def _table(headers, rows, table_id):
    head = "".join(f"<th>{html.escape(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>"
                   for row in rows)
    return f'<table id="{table_id}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _pvcmf_version():
    try:
        return metadata.version("pvcmf")
    except metadata.PackageNotFoundError:  # a source tree that was not installed
        return "unknown"


def _versions():
    out = {"pvcmf": _pvcmf_version(), "python": platform.python_version()}
    for dist in ("numpy", "scipy", "pyvista", "vtk", "meshio", "pandas"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            out[dist] = metadata.version(dist)
    out["vtk.js (viewer)"] = VTKJS_VERSION
    out["platform"] = platform.platform()
    return out


def _plan_rows(plan):
    rows = []
    for o in (plan or {}).get("osteotomy", []):
        rows.append([o.get("segment", ""),
                     ", ".join(f"{v:g}" for v in o.get("translation", [])) or "matrix",
                     ", ".join(f"{v:g}" for v in o.get("rotation", [])) or "–"])
    return rows


def _colourbar(key, label, stops, lo, hi):
    grad = ", ".join(f"rgb({int(255 * r)},{int(255 * g)},{int(255 * b)}) {100 * t:.1f}%"
                     for t, r, g, b in stops)
    ticks = "".join(f"<span>{v:.1f}</span>" for v in np.linspace(lo, hi, 5))
    return (f'<div class="colourbar" data-colouring="{key}"><div class="cb-title">'
            f'{html.escape(label)}</div><div class="cb-grad" style="background: '
            f'linear-gradient(to right, {grad})"></div><div class="cb-ticks">{ticks}</div></div>')


#: first script of the page: records console errors, uncaught exceptions and rejected
#: promises in ``<pre id="pvcmf-errors">`` (hidden), one per line, for headless checks
ERROR_HOOK_JS = r"""
(function () {
  const errs = [];
  function note(text) {
    errs.push(String(text).split('\n')[0]);
    let pre = document.getElementById('pvcmf-errors');
    if (!pre && document.body) {
      pre = document.createElement('pre'); pre.id = 'pvcmf-errors'; pre.hidden = true;
      document.body.appendChild(pre);
    }
    if (pre) pre.textContent = errs.join('\n');
  }
  const original = console.error;
  console.error = function () { note(Array.from(arguments).join(' ')); original.apply(console, arguments); };
  window.addEventListener('error', function (e) { note('Uncaught ' + e.message); });
  window.addEventListener('unhandledrejection', function (e) { note('Unhandled rejection ' + e.reason); });
  window.addEventListener('DOMContentLoaded', function () { if (errs.length) note(errs.pop()); });
})();
"""

_CSS = """
body{font-family:system-ui,sans-serif;margin:0 auto;max-width:1200px;padding:1em;color:rgb(34,34,34)}
h1{font-size:1.5em}h2{font-size:1.15em;border-bottom:1px solid #ddd;margin-top:1.5em}
#viewer-box{display:flex;gap:1em;flex-wrap:wrap}
#viewer{position:relative;width:760px;height:560px;border:1px solid #ccc}
#controls{min-width:260px}#controls label{display:block;margin:.2em 0}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.2em .6em;
text-align:right}td:first-child,th:first-child{text-align:left}
.cb-grad{height:16px;width:240px;border:1px solid gray}
.cb-ticks{display:flex;justify-content:space-between;width:244px;font-size:.8em}
.figures{display:flex;flex-wrap:wrap;gap:.5em}.figures figure{margin:0}
.figures img{max-width:560px;max-height:460px;border:1px solid #eee}.note{color:dimgray;font-size:.9em}
.warnings{background:rgb(255,243,205);border:1px solid rgb(224,190,90);padding:.5em 1em .5em 2em}
"""


def report_html(*, title, scene=None, colourbars=(), skins_ui=(), colourings_ui=(),
                regions=None, regions_caption="", plan=None, timings=None, images=None,
                extra=None, warnings=()):
    """The report page as a string (see :func:`write_report` for what goes in).

    ``scene`` is :func:`pvcmf.report.scene.scene_json`'s text; ``skins_ui`` (name, label,
    shown) and ``colourings_ui`` (key, label) make the viewer's controls; ``regions`` the
    rows of :func:`region_rows`; ``timings`` step -> seconds; ``images`` name -> PNG bytes;
    ``extra`` (heading, key -> value) rows shown after the plan; ``warnings`` what the
    run warned about (shown first).
    """
    parts = [f"<!doctype html><html lang='en'><head><meta charset='utf-8'>"
             f"<title>{html.escape(title)}</title><script>{ERROR_HOOK_JS}</script>"
             f"<style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(title)}</h1><p class='note'>pvcmf {_pvcmf_version()}, written "
             f"{datetime.datetime.now().isoformat(timespec='seconds')}. This page works "
             f"offline: data and viewer are inside it.</p>"]
    if warnings:
        items = "".join(f"<li>{html.escape(str(w))}</li>" for w in warnings)
        parts.append(f"<h2>Warnings</h2><ul id='warnings' class='warnings'>{items}</ul>")
    if scene is not None:
        boxes = "".join(f"<label><input type='checkbox' data-skin='{n}'"
                        f"{' checked' if shown else ''}> {html.escape(lab)}</label>"
                        for n, lab, shown in skins_ui)
        options = "".join(f"<option value='{k}'>{html.escape(lab)}</option>"
                          for k, lab in colourings_ui)
        parts.append(
            "<h2>3D view</h2><div id='viewer-box'><div id='viewer'></div><div id='controls'>"
            f"<b>skins</b>{boxes}<p><b>colour</b> <select id='colouring'>{options}"
            "<option value=''>none</option></select></p>" + "".join(colourbars) +
            "<p><button id='reset-view'>front view</button></p><p class='note'>drag: rotate, "
            "wheel: zoom, shift-drag: pan</p></div></div>")
    if regions:
        headers = ["region", *[h for _, h in TABLE_COLUMNS]]
        rows = [[r["region"], *[_fmt(r.get(k), k) for k, _ in TABLE_COLUMNS]] for r in regions]
        parts.append(f"<h2>Per-region statistics</h2><p class='note'>"
                     f"{html.escape(regions_caption)}</p>{_table(headers, rows, 'regions')}")
    if plan is not None:
        parts.append("<h2>Plan</h2>" + (f"<p>{html.escape(plan.get('name', ''))}</p>"
                                        if plan.get("name") else "")
                     + _table(["segment", "translation (mm)", "rotation (deg)"],
                              _plan_rows(plan), "plan"))
    for heading, values in (extra or {}).items():
        parts.append(f"<h2>{html.escape(heading)}</h2>"
                     + _table(["", ""], [[k, f"{v:.4g}" if isinstance(v, float) else v]
                                         for k, v in values.items()],
                              heading.split()[0].lower()))
    if images:
        figs = "".join(f"<figure><img alt='{html.escape(name)}' src='data:image/png;base64,"
                       f"{base64.b64encode(data).decode('ascii')}'><figcaption>"
                       f"{html.escape(name)}</figcaption></figure>"
                       for name, data in images.items())
        parts.append(f"<h2>Figures</h2><div class='figures'>{figs}</div>")
    if timings:
        rows = [[k, f"{v:.2f}"] for k, v in timings.items()]
        rows.append(["total", f"{sum(timings.values()):.2f}"])
        parts.append("<h2>Seconds per step</h2>" + _table(["step", "seconds"], rows, "timings"))
    parts.append("<h2>Software</h2>" + _table(["package", "version"],
                                              list(_versions().items()), "versions"))
    if scene is not None:
        parts.append(f"<script type='application/json' id='pvcmf-scene'>{scene}</script>"
                     f"<script>{vtkjs_source()}</script><script>{VIEWER_JS}</script>")
    parts.append("</body></html>")
    return "\n".join(parts)
