"""Paper 000 Fig. 5: osteotomy planning, pre-operative bone in white, planned in green.

For each patient the pre-operative face is shown next to its skeleton seen from the
side: every bone segment in white where it is before surgery, the moved segments in
green where the plan puts them (:func:`pvcmf.filters.move_bones`). Delegates to PyVista
(off-screen :class:`pyvista.Plotter`).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.osteotomy import move_bones
from ..filters.skin import extract_skin

__all__ = ["osteotomy_panel", "draw_osteotomy", "figure_5"]

PRE_COLOR = "white"
POST_COLOR = "limegreen"
SKIN_COLOR = "peachpuff"


def _camera(plotter, bounds, side, zoom=1.7):
    b = np.asarray(bounds).reshape(3, 2)
    center = b.mean(axis=1)
    size = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    direction = {"front": (0.0, 1.0, 0.0), "right": (-1.0, 0.35, 0.0)}[side]
    direction = np.asarray(direction) / np.linalg.norm(direction)
    plotter.camera_position = [tuple(center + 2.6 * size * direction), tuple(center),
                               (0.0, 0.0, 1.0)]
    plotter.camera.zoom(zoom)


def draw_osteotomy(plotter, labels, plan, skeleton=None):
    """Draw pre-operative segments (white) and moved segments (green) into ``plotter``.

    Parameters
    ----------
    plotter : pyvista.Plotter
        Target (its active subplot).
    labels : pyvista.ImageData
        Label image with ``bone`` (see :func:`pvcmf.filters.cut_bones`).
    plan : pvcmf.Plan
    skeleton : pyvista.MultiBlock, optional
        Output of :func:`pvcmf.filters.move_bones` (computed when omitted).
    """
    if skeleton is None:
        skeleton = move_bones(labels, plan)
    bounds = []
    for name in skeleton.keys():
        post = skeleton[name]
        pre = post.copy()
        pre.points = np.asarray(post.points) - np.asarray(post[arrays.DISPLACEMENT])
        moved = bool(post.field_data["moved"][0])
        plotter.add_mesh(pre, color=PRE_COLOR, smooth_shading=True,
                         opacity=0.55 if moved else 1.0, specular=0.3)
        if moved:
            plotter.add_mesh(post, color=POST_COLOR, smooth_shading=True, specular=0.3)
        bounds.append(np.asarray(pre.bounds))
    return skeleton


def osteotomy_panel(labels, plan, skin=None, skeleton=None, window_size=(900, 450)):
    """One patient of Fig. 5: the face (left) next to the planned osteotomy (right).

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``tissue`` and ``bone``.
    plan : pvcmf.Plan
    skin : pyvista.PolyData, optional
        Pre-operative skin (from the labels when omitted).
    skeleton : pyvista.MultiBlock, optional
        Output of :func:`pvcmf.filters.move_bones`.

    Returns
    -------
    pyvista.Plotter
        Off screen, 1 x 2 subplots.

    Examples
    --------
    >>> import pvcmf                                                # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(3, spacing=2.0)               # doctest: +SKIP
    >>> osteotomy_panel(case.truth, case.plan).screenshot("p3.png")  # doctest: +SKIP
    """
    p = pv.Plotter(off_screen=True, shape=(1, 2), window_size=list(window_size),
                   border=False)
    _draw_patient(p, (0, 0), labels, plan, skin, skeleton, title=plan.name)
    return p


def _draw_patient(p, first, labels, plan, skin, skeleton, title=""):
    row, col = first
    if skin is None:
        skin = extract_skin(labels)
    p.subplot(row, col)
    p.set_background("white", all_renderers=False)
    p.add_mesh(skin, color=SKIN_COLOR, smooth_shading=True, specular=0.2)
    _camera(p, skin.bounds, "front")
    if title:
        p.add_text(title, font_size=10, color="black")
    p.subplot(row, col + 1)
    p.set_background("dimgray", all_renderers=False)
    skeleton = draw_osteotomy(p, labels, plan, skeleton)
    _camera(p, skin.bounds, "right")
    text = "\n".join(f"{o.segment}: T{tuple(round(v, 2) for v in o.translation)} mm"
                      f" R{tuple(round(v, 2) for v in o.rotation)} deg"
                      for o in plan.osteotomies)
    p.add_text(text, font_size=7, color="white", position="lower_left")


def figure_5(cases, window_size=(1600, 800)):
    """Paper 000 Fig. 5 for several patients: faces next to their plans, 2 per row.

    Parameters
    ----------
    cases : sequence of (labels, plan) or objects with ``truth`` and ``plan``
        E.g. ``[pvcmf.datasets.phantom(i, spacing=2.0) for i in (1, 2, 3, 4)]``.

    Returns
    -------
    pyvista.Plotter
        Off screen, ``ceil(n/2)`` rows x 4 columns (face, bones, face, bones).
    """
    pairs = []
    for case in cases:
        if hasattr(case, "truth"):
            pairs.append((case.truth, case.plan))
        else:
            labels, plan = case
            pairs.append((labels, plan))
    if not pairs:
        raise ValueError("cases must hold at least one (labels, plan), got none")
    rows = (len(pairs) + 1) // 2
    p = pv.Plotter(off_screen=True, shape=(rows, 4), window_size=list(window_size),
                   border=False)
    for i, (labels, plan) in enumerate(pairs):
        _draw_patient(p, (i // 2, 2 * (i % 2)), labels, plan, None, None,
                      title=plan.name or f"case {i + 1}")
    return p
