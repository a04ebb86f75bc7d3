"""Framing of the face figures: the bounds a camera fits, the head's and not the shoulders'.

A scan that ends at the shoulders holds skin three times as wide as the head; framed on all
of it, the face fills a third of a frontal panel. :func:`frame_bounds` measures the head's
width in axial slabs (numpy only) and frames the head, its full height kept.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FRAME_SLAB", "FRAME_WIDEN", "frame_bounds"]


def _display_bounds(points):
    """Bounds of patient-frame ``points`` in the display frame (x -> -x)."""
    if len(points) == 0:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (-float(hi[0]), -float(lo[0]), float(lo[1]), float(hi[1]), float(lo[2]), float(hi[2]))


#: height (mm) of the axial slabs in which :func:`frame_bounds` measures the head's width
FRAME_SLAB = 5.0
#: a slab this many times wider than the head (the upper half's widest slab) is shoulders
FRAME_WIDEN = 1.1


def frame_bounds(mesh):
    """Display-frame bounds that frame the head of ``mesh`` (patient frame).

    :func:`pvcmf.figures.face_views.display_bounds`, with the width and depth of the head above the shoulders: the
    skin is cut into :data:`FRAME_SLAB` mm axial slabs, the head's width (x) is the widest
    slab of the upper half, and the slabs below the highest one wider than
    :data:`FRAME_WIDEN` times that (a scan that ends at the shoulders) set neither the
    width nor the depth; the height is the whole skin's (a bent head's chin may reach
    below the shoulders' top). A head with no shoulders is framed whole. The panels then
    show the head as a portrait, the shoulders running out of it.

    Examples
    --------
    >>> import pyvista as pv
    >>> head = pv.Sphere(radius=80.0, center=(0.0, 0.0, 100.0))
    >>> shoulders = pv.Cylinder(center=(0.0, 0.0, 0.0), direction=(0, 0, 1), radius=200.0,
    ...                         height=20.0)
    >>> b = frame_bounds(head.merge(shoulders))
    >>> round(b[1] - b[0]), round(b[4])
    (160, -10)
    """
    p = np.asarray(mesh.points, dtype=np.float64)
    if len(p) == 0:
        return _display_bounds(p)
    z = p[:, 2]
    n = max(int(np.ceil((z.max() - z.min()) / FRAME_SLAB)), 2)
    slab = np.minimum(((z - z.min()) / FRAME_SLAB).astype(np.int64), n - 1)
    lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(lo, slab, p[:, 0])
    np.maximum.at(hi, slab, p[:, 0])
    width = np.where(hi >= lo, hi - lo, 0.0)
    head = width[n // 2:].max()
    wide = np.flatnonzero(width[:n // 2] > FRAME_WIDEN * head)
    if head <= 0 or not len(wide):
        return _display_bounds(p)
    keep = p[slab > wide.max()]  # the head: its width and depth; the height is all of it
    return (-float(keep[:, 0].max()), -float(keep[:, 0].min()), float(keep[:, 1].min()),
            float(keep[:, 1].max()), float(z.min()), float(z.max()))
