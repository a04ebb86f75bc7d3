"""Several plans' predicted faces side by side, as the planner's slider shows them.

:func:`plan_sequence` draws each predicted skin in the same clinical view (the photographic
convention of :mod:`pvcmf.figures.face_views`: reflected to the display frame, so the
patient's right is on the viewer's left in a frontal view and a right three-quarter view
has the face toward the viewer's right), coloured by its signed displacement along the
outward skin normal on one shared symmetric range, with one colour bar in a strip under
the panels, clear of the faces.

Delegates to PyVista (off-screen :class:`pyvista.Plotter`) and
:mod:`pvcmf.figures.face_views`.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .face_views import (VIEW_TITLES, add_patient_mesh, frame_skins, saturation_note, set_view,
                         signed_displacement)

__all__ = ["plan_sequence", "SEQUENCE_TITLE"]

#: the colour bar's title
SEQUENCE_TITLE = "outward(+) / inward(-) displacement along the skin normal (mm)"


def plan_sequence(faces, titles, view="three_quarter", limit=None, window_size=None):
    """Predicted faces of several plans in one row, coloured by the normal displacement.

    Parameters
    ----------
    faces : sequence of pyvista.PolyData
        Predicted skins (patient frame) at their predicted positions, each with the point
        array ``displacement`` (mm).
    titles : sequence of str
        One panel title per face (e.g. the plan's name).
    view : str
        A view of :data:`pvcmf.figures.face_views.VIEWS`.
    limit : float, optional
        Colour range ``[-limit, limit]`` mm; default the largest ``|value|`` of all faces
        (at least 0.1 mm).
    window_size : (int, int), optional
        Default 400 x 480 pixels per panel.

    Returns
    -------
    pyvista.Plotter
        Off screen: a row of panels above a strip holding the colour bar.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.figures.plan_sequence import plan_sequence
    >>> s = pv.Sphere(radius=50.0)
    >>> s["displacement"] = np.zeros((s.n_points, 3))
    >>> plan_sequence([s, s], ["+0 mm", "+3 mm"]).shape
    (2, 2)
    """
    faces, titles = list(faces), list(titles)
    if not faces or len(faces) != len(titles):
        raise ValueError(f"need one title per face and at least one face, got {len(faces)} "
                         f"faces and {len(titles)} titles")
    if view not in VIEW_TITLES:
        raise ValueError(f"view must be one of {sorted(VIEW_TITLES)}, got {view!r}")
    values = [signed_displacement(face, "normal") for face in faces]
    largest = max(float(np.max(np.abs(v))) if v.size else 0.0 for v in values)
    m = max(largest, 0.1) if limit is None else float(limit)
    n = len(faces)
    window_size = window_size or (400 * n, 480)
    p = pv.Plotter(off_screen=True, shape=(2, n), row_weights=[0.85, 0.15],
                   groups=[(1, np.s_[:])], window_size=list(window_size), border=False)
    bounds, points = frame_skins(*faces)
    actor = None
    for col, (face, value, title) in enumerate(zip(faces, values, titles)):
        p.subplot(0, col)
        p.set_background("white", all_renderers=False)
        shown = face.copy(deep=False)
        shown.clear_data()
        shown.point_data[SEQUENCE_TITLE] = value
        actor = add_patient_mesh(p, shown, scalars=SEQUENCE_TITLE, cmap="coolwarm",
                                 clim=(-m, m), show_scalar_bar=False)
        set_view(p, bounds, view, points=points)
        p.add_text(title, font_size=10, color="black")
    p.subplot(1, 0)
    p.set_background("white", all_renderers=False)
    bar = p.add_scalar_bar(title="", mapper=actor.mapper, color="black", vertical=False,
                           position_x=0.2, position_y=0.05, width=0.6, height=0.5,
                           label_font_size=14, n_labels=5, fmt="%.1f")
    bar.SetTextPositionToPrecedeScalarBar()  # tick labels under the bar, the title above
    note = saturation_note(np.concatenate(values), m)
    p.add_text(f"{SEQUENCE_TITLE}; {note}" if note else SEQUENCE_TITLE, position="upper_edge",
               font_size=10, color="black")
    return p
