"""Paper 000 Fig. 5: osteotomy planning, pre-operative bone in white, planned in green.

For each patient the pre-operative face (frontal, photographic convention: the patient's
right on the viewer's left) is shown next to its skeleton seen from the patient's right
side (face to the viewer's right): every bone segment in white where it is before
surgery, the moved segments in green where the plan puts them
(:func:`pvcmf.filters.move_bones`), with a legend and the plan's numbers written out
(:func:`plan_lines`). Views and the display frame come from :mod:`pvcmf.figures.face_views`.
Delegates to PyVista (off-screen :class:`pyvista.Plotter`).
"""

from __future__ import annotations

import textwrap

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.osteotomy import move_bones
from ..filters.skin import extract_skin
from .face_views import add_patient_mesh, add_skin, display_bounds, set_view

__all__ = ["osteotomy_panel", "draw_osteotomy", "figure_5", "plan_lines"]

PRE_COLOR = "white"
POST_COLOR = "limegreen"
SKIN_COLOR = "peachpuff"


def plan_lines(plan):
    """The plan's numbers as text, one line per osteotomy, signs spelled out.

    Examples
    --------
    >>> from pvcmf.plan import Osteotomy, Plan
    >>> plan_lines(Plan([Osteotomy("maxilla", translation=(0.0, 2.0, -4.0))]))
    ['maxilla: 4.0 mm back, 2.0 mm up']
    >>> plan_lines(Plan([Osteotomy("mandible", translation=(0.0, 0.0, 5.0))], axes="occlusal"))
    ['mandible: 5.0 mm forward (occlusal axes)']
    """
    names = (("left", "right"), ("up", "down"), ("forward", "back"))
    rot_names = ("pitch", "yaw", "roll")
    out = []
    for o in plan.osteotomies:
        moves = [f"{abs(v):.1f} mm {names[i][0] if v > 0 else names[i][1]}"
                 for i, v in ((2, o.translation[2]), (1, o.translation[1]),
                              (0, o.translation[0])) if abs(v) >= 0.05]
        turns = [f"{rot_names[i]} {v:+.1f} deg" for i, v in enumerate(o.rotation)
                 if abs(v) >= 0.05]
        axes = f" ({plan.axes} axes)" if plan.axes != "image" and (moves or turns) else ""
        out.append(f"{o.segment}: " + (", ".join(moves + turns) or "not moved") + axes)
    return out


def _wrapped(lines, width=44):
    return "\n".join(textwrap.fill(line, width, subsequent_indent="    ") for line in lines)


def draw_osteotomy(plotter, labels, plan, skeleton=None):
    """Draw pre-operative segments (white) and moved segments (green) into ``plotter``.

    Meshes are drawn in the display frame of :mod:`pvcmf.figures.face_views` (x mirrored).

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
        add_patient_mesh(plotter, pre, color=PRE_COLOR, opacity=0.55 if moved else 1.0,
                         specular=0.3)
        if moved:
            add_patient_mesh(plotter, post, color=POST_COLOR, specular=0.3)
        bounds.append(np.asarray(pre.bounds))
    return skeleton


def osteotomy_panel(labels, plan, skin=None, skeleton=None, window_size=(1000, 520)):
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
    bounds = display_bounds(skin)
    p.subplot(row, col)
    p.set_background("white", all_renderers=False)
    add_skin(p, skin, SKIN_COLOR)  # the scan's cuts apart, as the face figures draw them
    set_view(p, bounds, "frontal")
    if title:
        p.add_text(title, font_size=12, color="black")
    p.subplot(row, col + 1)
    p.set_background("dimgray", all_renderers=False)
    skeleton = draw_osteotomy(p, labels, plan, skeleton)
    set_view(p, bounds, "profile")
    p.add_legend([["pre-operative bone", PRE_COLOR], ["planned position", POST_COLOR]],
                 bcolor="dimgray", border=False, loc="upper left", size=(0.5, 0.12),
                 face="rectangle")
    p.add_text(_wrapped(plan_lines(plan)), font_size=10, color="white",
               position="lower_left")


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
