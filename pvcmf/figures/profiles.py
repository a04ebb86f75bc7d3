"""Midsagittal profiles: the face's anterior silhouette in the plane x = const, and the
pre-operative and predicted silhouettes overlaid, the outline a surgeon compares first.

Delegates the cut to PyVista (``slice``) and the plot to matplotlib
(:class:`matplotlib.figure.Figure`, no pyplot state).
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from .framing import frame_bounds

__all__ = ["anterior_profile", "profile_overlay", "PRE_LABEL", "POST_LABEL"]

PRE_LABEL = "pre-operative"
POST_LABEL = "predicted"


def anterior_profile(skin, x, step=0.5):
    """The anterior silhouette of the cut of ``skin`` by the plane x = ``x``.

    For each ``step`` mm band of z, the most anterior (largest y) point of the cut: the
    face's outline in the midsagittal plane, without the airway and mouth cavity the cut
    also crosses.

    Returns
    -------
    numpy.ndarray
        (n, 2) array of (y, z) in mm, z increasing.

    Examples
    --------
    >>> import pyvista as pv
    >>> line = anterior_profile(pv.Sphere(radius=10.0, theta_resolution=60), 0.0)
    >>> round(float(line[:, 0].max()), 1)
    10.0
    """
    cut = skin.slice(normal=(1.0, 0.0, 0.0), origin=(float(x), 0.0, 0.0))
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
    return best[:, 1:].copy()


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
        b = frame_bounds(pre)  # display frame: x -> -x
        x = round(-0.5 * (b[0] + b[1]), 6) + 0.0  # + 0.0: no "-0.0" in the title
    fig = Figure(figsize=figsize)  # fixed layout: every draw gives the same image
    ax = fig.add_subplot()
    fig.subplots_adjust(left=0.2, right=0.96, bottom=0.12, top=0.93)
    lines = []
    for skin, label, style in ((pre, PRE_LABEL, dict(color="0.35", lw=2.2, ls="--")),
                               (post, POST_LABEL, dict(color="tab:red", lw=1.6))):
        line = anterior_profile(skin, x)
        lines.append(line)
        ax.plot(line[:, 0], line[:, 1], label=label, **style)
    y, z = np.concatenate(lines).T
    ax.set_xlim(y.max() - 0.5 * np.ptp(z), y.max() + 0.08 * np.ptp(z))
    ax.set_ylim(z.min() - 0.04 * np.ptp(z), z.max() + 0.04 * np.ptp(z))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("anterior (y, mm)")
    ax.set_ylabel("superior (z, mm)")
    ax.set_title(f"midsagittal profile (x = {x:.1f} mm)")
    ax.legend(loc="lower left")
    ax.grid(alpha=0.3)
    return fig
