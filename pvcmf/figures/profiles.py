"""Midsagittal profiles: the face's anterior silhouette in the plane x = const, and the
pre-operative and predicted silhouettes overlaid, the outline a surgeon compares first.
Where the silhouette runs over skin on a cut of the scan (``arrays.SKIN_CUT``: the
scan's edge, not the patient's skin), the overlay draws a band of
:data:`pvcmf.figures.skin_marks.CUT_COLOR` under it, as the face views colour that skin.

Delegates the cut to PyVista (``slice``) and the plot to matplotlib
(:class:`matplotlib.figure.Figure`, no pyplot state).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .. import arrays
from .framing import frame_bounds
from .skin_marks import CUT_COLOR

__all__ = ["anterior_profile", "midline_x", "profile_overlay", "PRE_LABEL", "POST_LABEL",
           "CUT_LABEL"]

PRE_LABEL = "pre-operative"
POST_LABEL = "predicted"
CUT_LABEL = "the scan's edge (cut)"


def anterior_profile(skin, x, step=0.5, on_cut=False):
    """The anterior silhouette of the cut of ``skin`` by the plane x = ``x``.

    For each ``step`` mm band of z, the most anterior (largest y) point of the cut: the
    face's outline in the midsagittal plane, without the airway and mouth cavity the cut
    also crosses.

    Returns
    -------
    numpy.ndarray
        (n, 2) array of (y, z) in mm, z increasing; with ``on_cut``, also an (n,) bool
        array: the point lies on skin marked ``arrays.SKIN_CUT`` (interpolated along the
        cut, at least one half; all False without the array).

    Examples
    --------
    >>> import pyvista as pv
    >>> line = anterior_profile(pv.Sphere(radius=10.0, theta_resolution=60), 0.0)
    >>> round(float(line[:, 0].max()), 1)
    10.0
    """
    src = skin
    if on_cut:  # a float mark to interpolate, on a shallow copy: the input keeps its arrays
        src = skin.copy(deep=False)
        src.point_data["_on_cut"] = (np.asarray(skin.point_data[arrays.SKIN_CUT], float)
                                     if arrays.SKIN_CUT in skin.point_data
                                     else np.zeros(skin.n_points))
    cut = src.slice(normal=(1.0, 0.0, 0.0), origin=(float(x), 0.0, 0.0))
    if cut.n_lines == 0:
        raise ValueError(f"the plane x = {x} does not cut the skin (x bounds "
                         f"{skin.bounds[0]:.1f}..{skin.bounds[1]:.1f} mm)")
    seg = np.asarray(cut.points)[np.asarray(cut.lines).reshape(-1, 3)[:, 1:]]  # (n, 2, 3)
    # points every step / 2 along each segment, so every z band holds the face's points
    n_sub = np.maximum(np.ceil(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) / (0.5 * step)),
                       1).astype(np.int64)
    which = np.repeat(np.arange(len(seg)), n_sub + 1)
    t = (np.arange(which.size) - np.repeat(np.cumsum(n_sub + 1) - (n_sub + 1), n_sub + 1))
    t = (t / np.repeat(n_sub, n_sub + 1))[:, None]
    pts = seg[which, 0] * (1.0 - t) + seg[which, 1] * t
    band = np.floor((pts[:, 2] - pts[:, 2].min()) / step).astype(np.int64)
    order = np.lexsort((-pts[:, 1], band))
    first = np.r_[True, band[order][1:] != band[order][:-1]]
    best = pts[order[first]]
    if not on_cut:
        return best[:, 1:].copy()
    mark = np.asarray(cut.point_data["_on_cut"])[np.asarray(cut.lines).reshape(-1, 3)[:, 1:]]
    mark = mark[which, 0] * (1.0 - t[:, 0]) + mark[which, 1] * t[:, 0]
    return best[:, 1:].copy(), mark[order[first]] >= 0.5


def midline_x(skin):
    """The x (mm) of a head's midsagittal plane: the centre of the head of ``skin`` along x
    (:func:`frame_bounds`: shoulders the scan holds do not move it)."""
    b = frame_bounds(skin)  # display frame: x -> -x
    return round(-0.5 * (b[0] + b[1]), 6) + 0.0  # + 0.0: no "-0.0" in a title


def profile_overlay(pre, post, x=None, figsize=(4.5, 6.0)):
    """Pre-operative and predicted midsagittal profiles overlaid (matplotlib).

    Parameters
    ----------
    pre, post : pyvista.PolyData
        Skins in the patient frame.
    x : float, optional
        Midsagittal plane x (mm); default the centre of the head of ``pre`` along x
        (:func:`frame_bounds`: shoulders the scan holds do not move it).

    Returns
    -------
    matplotlib.figure.Figure
        The anterior silhouettes (:func:`anterior_profile`), anterior (+y) to the right,
        superior (+z) up, equal axes in mm.
    """
    if x is None:
        x = midline_x(pre)
    fig = Figure(figsize=figsize)  # fixed layout: every draw gives the same image
    ax = fig.add_subplot()
    fig.subplots_adjust(left=0.2, right=0.96, bottom=0.17, top=0.93)
    lines, cut_label = [], CUT_LABEL
    for skin, label, style in ((pre, PRE_LABEL, dict(color="0.35", lw=2.2, ls="--")),
                               (post, POST_LABEL, dict(color="tab:red", lw=1.6))):
        line, on = anterior_profile(skin, x, on_cut=True)
        lines.append(line)
        if on.any():  # a band under the line where it runs over the scan's edge
            ax.plot(np.where(on, line[:, 0], np.nan), np.where(on, line[:, 1], np.nan),
                    color=CUT_COLOR, lw=7, solid_capstyle="butt", zorder=1, label=cut_label)
            cut_label = None
        ax.plot(line[:, 0], line[:, 1], label=label, zorder=2, **style)
    y, z = np.concatenate(lines).T
    ax.set_xlim(y.max() - 0.5 * np.ptp(z), y.max() + 0.08 * np.ptp(z))
    ax.set_ylim(z.min() - 0.04 * np.ptp(z), z.max() + 0.04 * np.ptp(z))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("anterior (y, mm)")
    ax.set_ylabel("superior (z, mm)")
    ax.set_title(f"midsagittal profile (x = {x:.1f} mm)")
    # below the axes: a legend inside would hide part of a line (the neck's end, a chin)
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=2, frameon=False,
               fontsize="small", bbox_to_anchor=(0.5, 0.0))
    ax.grid(alpha=0.3)
    return fig
