"""Paper 000 Figs. 6-8: signed error maps, box plots and cumulative error curves.

All three take plain inputs, so the same code draws the study (``gallery/
plot_fig6_8_validation.py``) and deterministic synthetic inputs (the image tests):

* :func:`fig6_error_maps` (PyVista ``Plotter``, off screen): one row per patient, left the
  proposed method, right the state of the art, skins coloured by ``arrays.DISTANCE`` with
  :func:`error_colormap` (white over [-2, 2] mm, red posterior / negative, blue anterior /
  positive) and one shared colour bar;
* :func:`fig7_boxplots` (matplotlib ``Figure``): per patient a box per method of ``|d|``
  with its median written on the box;
* :func:`fig8_cumulative` (matplotlib ``Figure``): per patient the cumulative share of
  points with ``|d| <= x``, proposed red, state of the art blue, with the % below 1 and
  2 mm marked.

Delegates to PyVista (``Plotter.add_mesh``, ``add_scalar_bar``) and matplotlib.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from .. import arrays
from .face_views import add_patient_mesh, display_bounds
from .skin_marks import MAP_CUT_COLOR, MAP_CUT_WORDS, cut_points

#: drawing order and colours of the methods (paper 000: proposed red, state of the art blue)
METHOD_COLORS = {"proposed": "tab:red", "state_of_the_art": "tab:blue"}
METHOD_LABELS = {"proposed": "proposed", "state_of_the_art": "state of the art"}


def error_colormap(limit=6.0, acceptable=2.0, n=256):
    """Diverging colour map for signed errors over ``[-limit, limit]`` mm.

    White over ``[-acceptable, acceptable]`` (errors invisible to the eye, paper 000),
    light to dark red below (prediction posterior to the truth), light to dark blue above
    (anterior).

    Parameters
    ----------
    limit : float, default 6.0
        Colour range half-width (mm); the map is meant for ``clim=(-limit, limit)``.
    acceptable : float, default 2.0
        Half-width of the white band (mm).
    n : int, default 256
        Number of colours.

    Returns
    -------
    matplotlib.colors.ListedColormap

    Examples
    --------
    >>> from pvcmf.figures.validation import error_colormap
    >>> cmap = error_colormap()
    >>> [tuple(round(float(c), 2) for c in cmap(x)[:3]) for x in (0.0, 0.5, 1.0)]
    [(0.5, 0.0, 0.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.5)]
    """
    if not 0 < acceptable < limit:
        raise ValueError(f"need 0 < acceptable < limit, got acceptable={acceptable}, limit={limit}")
    v = np.linspace(-limit, limit, n)
    t = np.clip((np.abs(v) - acceptable) / (limit - acceptable), 0, 1)  # 0 at band edge
    # red (1, g, g) darkening to (0.5, 0, 0); blue (g, g, 1) darkening to (0, 0, 0.5)
    g = (1 - t) * 0.65
    hi = 1 - 0.5 * t
    rgb = np.ones((n, 3))
    red, blue = v < -acceptable, v > acceptable
    rgb[red] = np.column_stack([hi[red], g[red], g[red]])
    rgb[blue] = np.column_stack([g[blue], g[blue], hi[blue]])
    return ListedColormap(rgb, name="pvcmf_error")


def patient_label(patient):
    """``"P1"`` for a patient number (the papers' names), the name itself otherwise.

    Examples
    --------
    >>> patient_label(3), patient_label("female head")
    ('P3', 'female head')
    """
    if isinstance(patient, (int, np.integer)) and not isinstance(patient, bool):
        return f"P{patient}"
    return str(patient)


def _check_nested(data, name):
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{name} must be a non-empty dict patient -> method -> data")
    methods = None
    for patient, per in data.items():
        if not isinstance(per, dict) or not per:
            raise ValueError(f"{name}[{patient!r}] must be a non-empty dict method -> data")
        if methods is None:
            methods = list(per)
        elif list(per) != methods:
            raise ValueError(
                f"{name}[{patient!r}] has methods {list(per)}, expected {methods} as for the "
                "first patient"
            )
    return list(data), methods


def fig6_error_maps(skins, *, limit=6.0, acceptable=2.0, window_size=None, camera=None):
    """Paper 000 Fig. 6: signed error maps, one row per patient, one column per method.

    Parameters
    ----------
    skins : dict
        ``skins[patient][method]`` -> PolyData with point array ``arrays.DISTANCE``;
        methods in column order (paper: proposed left, state of the art right).
    limit, acceptable : float
        See :func:`error_colormap`.
    window_size : (int, int), optional
        Pixels; default 380 x 440 per panel.
    camera : str or list, optional
        PyVista camera position in the display frame (x -> -x, see
        :func:`pvcmf.figures.face_views.to_display`); default: from the front (camera on
        +y, z up, the patient's right on the viewer's left as in a clinical photograph),
        parallel projection, zoomed so that the face (both methods' skins of the patient)
        fills its panel.

    Returns
    -------
    pyvista.Plotter
        Off-screen plotter (call ``show(screenshot=...)`` or ``screenshot``).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.figures.validation import fig6_error_maps
    >>> s = pv.Sphere(radius=50)
    >>> s[arrays.DISTANCE] = s.points[:, 2] / 10
    >>> pl = fig6_error_maps({1: {"proposed": s, "state_of_the_art": s}})
    >>> pl.shape
    (1, 2)
    """
    patients, methods = _check_nested(skins, "skins")
    if window_size is None:
        window_size = (380 * len(methods), 440 * len(patients))
    cmap = error_colormap(limit, acceptable)
    pl = pv.Plotter(shape=(len(patients), len(methods)), off_screen=True,
                    window_size=list(window_size), border=False)
    pl.set_background("white")
    # panel aspect (width / height)
    aspect = (window_size[0] / len(methods)) / (window_size[1] / len(patients))
    any_cut = False
    for r, patient in enumerate(patients):
        for method in methods:
            arrays.require_array(skins[patient][method], arrays.DISTANCE, "point", dtype="f",
                                 ncomp=1, producer="distance_to")
        # display frame (x -> -x): the patient's right on the viewer's left, as the face
        # figures and a clinical photograph show it (pvcmf.figures.face_views)
        lo = np.min([display_bounds(skins[patient][m])[::2] for m in methods], axis=0)
        hi = np.max([display_bounds(skins[patient][m])[1::2] for m in methods], axis=0)
        centre = (lo + hi) / 2
        half_w, half_h = max((hi[0] - lo[0]) / 2, 1e-6), max((hi[2] - lo[2]) / 2, 1e-6)
        for c, method in enumerate(methods):
            pl.subplot(r, c)
            shown, on_cut = _cut_apart(skins[patient][method])
            any_cut |= on_cut
            add_patient_mesh(pl, shown, scalars=arrays.DISTANCE, cmap=cmap,
                             clim=(-limit, limit), nan_color=MAP_CUT_COLOR, show_scalar_bar=False)
            label = f"{patient_label(patient)}  {METHOD_LABELS.get(method, method)}"
            pl.add_text(label, position="upper_left", font_size=9, color="black")
            if camera is None:  # front view, the face's box filling the panel
                scale = 1.15 * max(half_h, half_w / aspect)  # half the panel's height, mm
                focus = centre - (0.0, 0.0, 0.12 * scale)  # bottom eighth kept for the bar
                eye = focus + (0.0, 3.0 * float(np.max(hi - lo)) + 1.0, 0.0)
                pl.camera_position = [tuple(eye), tuple(focus), (0, 0, 1)]
                pl.enable_parallel_projection()
                pl.camera.parallel_scale = scale
                pl.renderer.reset_camera_clipping_range()
            else:
                pl.camera_position = camera
    pl.subplot(len(patients) - 1, len(methods) - 1)
    bar = pl.add_scalar_bar(
        title="signed error (mm)", mapper=pl.mapper, n_labels=7, color="black",
        vertical=False, position_x=0.05, position_y=0.045, width=0.9, height=0.05,
        fmt="%.0f", title_font_size=12, label_font_size=10,
    )
    bar.SetTextPositionToPrecedeScalarBar()  # tick labels under the bar
    bar.SetTitle("")  # VTK puts the title on the labels' side, over the middle label
    edge = f"; {MAP_CUT_WORDS}" if any_cut else ""
    text = pl.add_text(f"signed error (mm), white within \u00b1{acceptable:g}{edge}",
                       position=(0.5, 0.1), viewport=True, color="black")
    text.GetTextProperty().SetFontSize(12)  # pixels, as the bar's labels
    text.GetTextProperty().SetJustificationToCentered()
    return pl


def _cut_apart(skin):
    """``(skin to draw, any cut)``: the skin with the distances of its points on a cut of
    the scan (:func:`~pvcmf.figures.skin_marks.cut_points`) NaN, drawn in
    :data:`~pvcmf.figures.skin_marks.MAP_CUT_COLOR` (the scan's edge, not an error)."""
    cut = cut_points(skin)
    if not cut.any():
        return skin, False
    shown = skin.copy(deep=False)
    shown.point_data[arrays.DISTANCE] = np.where(
        cut, np.nan, np.asarray(skin.point_data[arrays.DISTANCE], dtype=float).reshape(-1))
    return shown, True


def _abs_errors(distances, patient, method):
    d = np.asarray(distances[patient][method], dtype=float)
    if d.ndim != 1 or d.size == 0:
        raise ValueError(
            f"distances[{patient!r}][{method!r}] must be a non-empty 1-D array, got "
            f"shape {d.shape}"
        )
    return np.abs(d[np.isfinite(d)])


def fig7_boxplots(distances, *, whis=(5, 95), figsize=(7.0, 3.6)):
    """Paper 000 Fig. 7: box plots of ``|d|`` per patient and method, medians on the boxes.

    Parameters
    ----------
    distances : dict
        ``distances[patient][method]`` -> 1-D signed distances (mm).
    whis : (float, float) or float, default (5, 95)
        Whisker percentiles, or (a number) matplotlib's multiple of the interquartile range;
        written under the axis (outliers are not drawn: a skin has ~1e5 points).
    figsize : (float, float)
        Inches.

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.figures.validation import fig7_boxplots
    >>> d = {1: {"proposed": np.linspace(-1, 1, 50), "state_of_the_art": np.linspace(-2, 2, 50)}}
    >>> len(fig7_boxplots(d).axes)
    1
    """
    patients, methods = _check_nested(distances, "distances")
    fig = Figure(figsize=figsize, layout="constrained")
    ax = fig.add_subplot()
    width = 0.8 / len(methods)
    for m, method in enumerate(methods):
        data = [_abs_errors(distances, p, method) for p in patients]
        pos = np.arange(len(patients)) + (m - (len(methods) - 1) / 2) * width
        color = METHOD_COLORS.get(method, f"C{m}")
        bp = ax.boxplot(data, positions=pos, widths=width * 0.85, whis=whis, showfliers=False,
                        patch_artist=True, manage_ticks=False,
                        medianprops={"color": "black"})
        for box in bp["boxes"]:
            box.set_facecolor(color)
            box.set_alpha(0.55)
        for x, d in zip(pos, data):
            med = float(np.median(d))
            ax.text(x, med, f"{med:.2f}", ha="center", va="bottom", fontsize=7,
                    color="black")
        ax.plot([], [], "s", color=color, alpha=0.55, label=METHOD_LABELS.get(method, method))
    ax.set_xticks(np.arange(len(patients)), [patient_label(p) for p in patients])
    # say on the figure what the whiskers are: the paper's box plots do not, and matplotlib's
    # default (1.5 IQR) would be read otherwise
    ax.set_xlabel(f"boxes: quartiles, line and number: median, whiskers: {_whisker_text(whis)}"
                  " (outliers not drawn)", fontsize=8)
    ax.set_ylabel("|distance| to the actual skin (mm)")
    ax.set_ylim(bottom=0)
    # above the axes: inside, it crossed the tallest whisker
    ax.legend(loc="lower center", bbox_to_anchor=(0.5, 1.0), ncols=len(methods), fontsize=8,
              frameon=False)
    ax.grid(axis="y", alpha=0.3)
    return fig


def _whisker_text(whis):
    """Words for matplotlib's ``whis``: percentiles ``(lo, hi)`` or a multiple of the IQR."""
    if np.ndim(whis) == 0:
        return f"{float(whis):g} IQR beyond the box"
    lo, hi = (float(w) for w in whis)
    return f"{lo:g}th-{hi:g}th percentiles"


def fig8_cumulative(distances, *, marks=(1.0, 2.0), xmax=None, figsize=None):
    """Paper 000 Fig. 8: cumulative error curves per patient, % below 1 and 2 mm marked.

    Parameters
    ----------
    distances : dict
        ``distances[patient][method]`` -> 1-D signed distances (mm).
    marks : sequence of float, default (1.0, 2.0)
        Error levels (mm) at which the share of points is marked and written.
    xmax : float, optional
        Right end of the error axis (mm); default the largest 99th percentile, at least
        ``max(marks) + 1``.
    figsize : (float, float), optional
        Inches; default ``(3 * n_patients, 3.2)``.

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.figures.validation import fig8_cumulative
    >>> d = {p: {"proposed": np.linspace(0, 3, 99), "state_of_the_art": np.linspace(0, 4, 99)}
    ...      for p in (1, 2)}
    >>> len(fig8_cumulative(d).axes)
    2
    """
    patients, methods = _check_nested(distances, "distances")
    if xmax is None:
        xmax = max(float(np.percentile(_abs_errors(distances, p, m), 99))
                   for p in patients for m in methods)
        xmax = max(xmax, max(marks) + 1.0)
    fig = Figure(figsize=figsize or (3.0 * len(patients), 3.2), layout="constrained")
    axes = fig.subplots(1, len(patients), sharey=True, squeeze=False)[0]
    for ax, patient in zip(axes, patients):
        for m, method in enumerate(methods):
            a = np.sort(_abs_errors(distances, patient, method))
            color = METHOD_COLORS.get(method, f"C{m}")
            x = np.r_[0.0, np.linspace(0, xmax, 400)]
            y = 100.0 * np.searchsorted(a, x, side="right") / a.size
            ax.plot(x, y, color=color, lw=1.5, label=METHOD_LABELS.get(method, method))
            for level in marks:
                share = 100.0 * np.searchsorted(a, level, side="right") / a.size
                ax.plot([level], [share], "o", color=color, ms=4)
                ax.annotate(f"{share:.0f}%", (level, share), textcoords="offset points",
                            xytext=(4, -14 - 10 * m),  # stacked below the curves: never on top of them
                            fontsize=7, color=color)
        for level in marks:
            ax.axvline(level, color="0.6", lw=0.8, ls=":")
        ax.set_title(patient_label(patient), fontsize=10)
        ax.set_xlim(0, xmax)
        ax.set_ylim(0, 102)
        ax.set_xlabel("|error| (mm)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("points with |error| <= x (%)")
    axes[-1].legend(loc="lower right", fontsize=7, frameon=False)
    return fig
