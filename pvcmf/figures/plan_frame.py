"""Figures in a plan's axes: a head the scan holds tilted or turned, shown upright.

A plan whose moves are given in the face's axes (``axes = "occlusal"`` or ``"frankfort"``,
:func:`pvcmf.filters.plan_axes`) says where the face points. The face figures then show
the surfaces turned into those axes, about the pre-operative skin's centre: the frontal
view looks the face in the eye, the profile cut is the face's midsagittal plane rather than
an oblique cut through a turned head, and a displacement's anterior-posterior component is
the face's forward, not the scanner's. A plan in the image's axes leaves every surface as
the scan holds it.

Delegates to :func:`pvcmf.filters.plan_axes` and pyvista's ``copy``.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays

log = logging.getLogger(__name__)

__all__ = ["figure_frame", "turned_into"]

#: point arrays turned with the points (vectors); every other array is carried as it is
VECTORS = (arrays.DISPLACEMENT, arrays.NORMALS)


def figure_frame(labels, plan):
    """The rotation whose columns are ``plan``'s axes in the image, where the figures show
    the surfaces turned into them: None for a plan in the image's axes, without labels, or
    where the labels do not give the axes (logged; the figures then keep the image's)."""
    if plan is None or labels is None or plan.axes == "image":
        return None
    from ..filters.face_axes import plan_axes

    try:
        return plan_axes(labels, plan)
    except ValueError as exc:
        log.info("figures in the image's axes: the plan's %r axes are not measurable (%s)",
                 plan.axes, exc)
        return None


def turned_into(mesh, frame, centre):
    """A copy of ``mesh`` (a DataSet or a MultiBlock of them) in the axes ``frame`` (3x3,
    columns the axes in the image) about ``centre``: points ``c + F^T (p - c)``, and the
    point vectors of :data:`VECTORS` turned alike. ``frame`` None: a copy as it is.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> a = np.radians(90.0)  # axes turned 90 degrees about z
    >>> F = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    >>> np.round(turned_into(pv.PolyData([[0.0, 1.0, 0.0]]), F, (0, 0, 0)).points, 6).tolist()
    [[1.0, 0.0, 0.0]]
    """
    if isinstance(mesh, pv.MultiBlock):
        out = pv.MultiBlock()
        for name in mesh.keys():
            out[name] = turned_into(mesh[name], frame, centre)
        for name in mesh.field_data.keys():
            out.field_data[name] = np.array(mesh.field_data[name])
        return out
    out = mesh.copy(deep=True)
    if frame is None:
        return out
    F = np.asarray(frame, dtype=float)
    if F.shape != (3, 3) or not np.allclose(F.T @ F, np.eye(3), atol=1e-9):
        raise ValueError(f"frame must be a 3x3 rotation, got {np.round(F, 3).tolist()}")
    c = np.asarray(centre, dtype=float)
    out.points = (np.asarray(mesh.points, dtype=float) - c) @ F + c
    for name in VECTORS:
        if name in mesh.point_data:
            out.point_data[name] = np.asarray(mesh.point_data[name], dtype=float) @ F
    return out
