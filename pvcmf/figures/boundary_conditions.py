"""Paper 000 Fig. 4: the three boundary-condition types on a patient model.

a) sliding-contact segment (nodes on the teeth), b) joint sections (soft tissue moving
with the bone, red), c) fixed points (the most posterior plane). Each panel shows the
soft-tissue mesh's surface, translucent, with that type's nodes as spheres and, where a
label image is given, the bone segments. Reads the ``bc`` arrays written by
:func:`pvcmf.filters.apply_plan`; delegates to PyVista (off-screen
:class:`pyvista.Plotter`).
"""

from __future__ import annotations

import inspect

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.osteotomy import _segment_surface
from .face_views import add_patient_mesh

__all__ = ["figure_4", "BC_COLORS"]

#: colour of each boundary-condition type in the figure
BC_COLORS = {"sliding": "royalblue", "joint": "red", "fixed": "forestgreen"}
_PANELS = (("sliding", "a) sliding-contact segment", "front"),
           ("joint", "b) joint sections", "side"),
           ("fixed", "c) fixed points", "back"))


def _view(plotter, bounds, where):
    """Camera on the patient-frame ``bounds`` from ``where``, placed in the display frame
    (x -> -x) in which :func:`pvcmf.figures.face_views.add_patient_mesh` draws."""
    flip = np.array([-1.0, 1.0, 1.0])
    b = np.asarray(bounds).reshape(3, 2)
    center = b.mean(axis=1) * flip
    size = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    direction = {"front": (0.25, 1.0, 0.15), "side": (-1.0, 0.6, 0.2),
                 "back": (-0.6, -1.0, 0.3)}[where]  # patient frame: "side" is the right
    direction = np.asarray(direction) * flip / np.linalg.norm(direction)
    plotter.camera_position = [tuple(center + 2.2 * size * direction), tuple(center),
                               (0.0, 0.0, 1.0)]
    plotter.camera.zoom(1.5)


def figure_4(grid, labels=None, window_size=(1500, 520), point_size=9.0):
    """Draw the sliding, joint and fixed nodes of a mesh in three panels (Fig. 4).

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Mesh with the point array ``bc`` (from :func:`pvcmf.filters.apply_plan`).
    labels : pyvista.ImageData, optional
        Label image with ``bone``: its segments are drawn in white for context.
    window_size : tuple of int
        Pixels (width, height).
    point_size : float
        Size of the node spheres in pixels.

    Returns
    -------
    pyvista.Plotter
        Off screen, 1 x 3 subplots.

    Raises
    ------
    ValueError
        If ``grid`` has no ``bc`` array.

    Examples
    --------
    >>> import pvcmf                                       # doctest: +SKIP
    >>> figure_4(mesh_with_bc, labels).screenshot("fig4.png")  # doctest: +SKIP
    """
    bc = np.asarray(arrays.require_array(grid, arrays.BC, "point", dtype="i", ncomp=1,
                                         producer="apply_plan"))
    with_ids = grid.copy()
    with_ids.point_data["_ids"] = np.arange(grid.n_points)
    surface = with_ids.extract_surface(algorithm=None) if _has_algorithm() \
        else with_ids.extract_surface()
    bone = None
    if labels is not None:
        values = np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu"))
        bone = _segment_surface(labels, values > 0, 0.6)
    points = np.asarray(grid.points)
    p = pv.Plotter(off_screen=True, shape=(1, 3), window_size=list(window_size), border=False)
    for col, (kind, title, where) in enumerate(_PANELS):
        p.subplot(0, col)
        p.set_background("white", all_renderers=False)
        if bone is not None:
            add_patient_mesh(p, bone, color="lightgray", opacity=0.35)
        add_patient_mesh(p, surface, color="peachpuff", opacity=0.3)
        sel = bc == arrays.BC_CODES[kind]
        if sel.any():
            add_patient_mesh(p, pv.PolyData(points[sel]), color=BC_COLORS[kind],
                             render_points_as_spheres=True, point_size=point_size,
                             smooth_shading=False)
        p.add_text(f"{title} ({int(sel.sum())} nodes)", font_size=10, color="black")
        _view(p, grid.bounds, where)
    return p


def _has_algorithm():
    return "algorithm" in inspect.signature(pv.UnstructuredGrid.extract_surface).parameters
