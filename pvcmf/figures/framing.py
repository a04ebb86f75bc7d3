"""Framing of the face figures: the bounds a camera fits, the head's and not the shoulders'.

A scan that ends at the shoulders holds skin three times as wide as the head; framed on all
of it, the face fills a third of a frontal panel. :func:`frame_bounds` measures the head's
width in axial slabs (numpy only) and frames the head, its full height kept.

:func:`fit_parallel` places a parallel-projection camera so that a box's projection on the
screen (its extent along the view's right and up vectors, whatever the view direction)
fills a panel of a given aspect ratio with a margin on every side and a band at the top
left free for the panel's title: the nose, the chin and the back of the head stay inside
the panel for any head, because the fit is measured on the box, not set by constants.
"""

from __future__ import annotations

import numpy as np

__all__ = ["FRAME_SLAB", "FRAME_WIDEN", "FRAME_MARGIN", "FRAME_TITLE", "frame_bounds",
           "frame_skins", "fit_aspect", "fit_parallel"]


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


def frame_skins(*skins):
    """The display-frame box that frames the heads of all ``skins`` (patient frame,
    :func:`frame_bounds`) and their points in the display frame (x -> -x), for the
    ``points`` of :func:`fit_parallel`.

    Examples
    --------
    >>> import pyvista as pv
    >>> bounds, points = frame_skins(pv.Sphere(center=(10.0, 0.0, 0.0)), pv.Sphere())
    >>> [round(v, 1) for v in bounds[:2]], points.shape[1]
    ([-10.5, 0.5], 3)
    """
    boxes = np.array([np.asarray(frame_bounds(s)).reshape(3, 2) for s in skins])
    bounds = np.c_[boxes[:, :, 0].min(axis=0), boxes[:, :, 1].max(axis=0)].ravel()
    points = np.concatenate([np.asarray(s.points, dtype=np.float64) for s in skins])
    return tuple(float(v) for v in bounds), points * [-1.0, 1.0, 1.0]


#: free margin on every side of a panel, a fraction of the panel's height (width)
FRAME_MARGIN = 0.05
#: band at the top of a panel kept free for its title, a fraction of the panel's height
FRAME_TITLE = 0.06


def _screen_extent(bounds, direction, up=(0.0, 0.0, 1.0), points=None):
    """Extents ``(lo, hi)`` across and along the screen of the box ``bounds`` (or of the
    ``points`` inside it) seen along ``direction``, and the screen's (right, up) vectors."""
    b = np.asarray(bounds, dtype=np.float64).reshape(3, 2)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    up = np.asarray(up, dtype=np.float64)
    up = up - (up @ d) * d  # orthogonal to the view direction
    if not np.linalg.norm(up) > 1e-9:
        raise ValueError(f"up must not be parallel to direction {tuple(d)}, got {tuple(up)}")
    up = up / np.linalg.norm(up)
    right = np.cross(-d, up)  # screen right: the camera looks along -d
    corners = np.array(np.meshgrid(*b, indexing="ij")).reshape(3, -1).T
    if points is not None:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        tol = 1e-6 * max(float(np.ptp(corners)), 1.0)
        p = p[np.all((p >= b[:, 0] - tol) & (p <= b[:, 1] + tol), axis=1)]
        corners = p if len(p) else corners
    across, along = corners @ right, corners @ up
    return ((float(across.min()), float(across.max())), (float(along.min()), float(along.max())),
            (right, up))


def fit_aspect(bounds, direction, up=(0.0, 0.0, 1.0), margin=FRAME_MARGIN, title=FRAME_TITLE,
               points=None):
    """The panel aspect ratio (width / height) that :func:`fit_parallel` fills both ways.

    Examples
    --------
    >>> round(fit_aspect((0, 100, 0, 100, 0, 100), (0, 1, 0), title=0.0), 3)
    1.0
    """
    (a0, a1), (u0, u1), _ = _screen_extent(bounds, direction, up, points)
    return ((a1 - a0) / (1.0 - 2.0 * margin)) / max((u1 - u0) / (1.0 - 2.0 * margin - title),
                                                    1e-6)


def fit_parallel(bounds, direction, aspect=1.0, up=(0.0, 0.0, 1.0), margin=FRAME_MARGIN,
                 title=FRAME_TITLE, zoom=1.0, points=None):
    """A parallel-projection camera that shows the box ``bounds`` whole, seen along ``direction``.

    The eight corners of the box (or the ``points`` inside it) are projected on the
    screen's right and up vectors; the visible height is the larger of what the projected
    height (plus the ``title`` band and two margins) and the projected width (plus two
    margins, at the panel's ``aspect`` = width / height) need, divided by ``zoom``. The box's projection is
    centred across and sits ``margin`` above the panel's bottom edge, so that the title
    band stays free.

    Parameters
    ----------
    bounds : sequence of 6 float
        ``(xmin, xmax, ymin, ymax, zmin, zmax)`` of what must be seen (mm).
    direction : sequence of 3 float
        From the focal point toward the camera.
    aspect : float
        Panel width / height (pixels).
    up : sequence of 3 float
        View up (not parallel to ``direction``).
    margin, title : float
        Fractions of the panel (see :data:`FRAME_MARGIN`, :data:`FRAME_TITLE`).
    zoom : float
        Above 1 magnifies (the box may then leave the panel).
    points : (n, 3) array_like, optional
        The surface's points: the fit is then that of those inside ``bounds``, tighter
        than the box's corners in an oblique view (a three-quarter view of a head).

    Returns
    -------
    focal_point : numpy.ndarray
        (3,) the camera's focal point.
    parallel_scale : float
        Half the visible height (VTK's ``parallel_scale``).

    Examples
    --------
    A 100 mm cube seen from the front in a square panel: 100 mm of content, a 5 % margin
    at the bottom and 5 % plus a 6 % title band at the top.

    >>> focal, scale = fit_parallel((0, 100, 0, 100, 0, 100), (0, 1, 0))
    >>> round(2 * scale, 1), [round(float(v), 1) for v in focal]
    (119.0, [50.0, 50.0, 53.6])
    """
    if not (aspect > 0 and 0 <= margin and 0 <= title and 2 * margin + title < 1 and zoom > 0):
        raise ValueError("need aspect > 0, zoom > 0, margin >= 0, title >= 0 and "
                         f"2 * margin + title < 1; got aspect={aspect}, zoom={zoom}, "
                         f"margin={margin}, title={title}")
    (a0, a1), (u0, u1), (right, up) = _screen_extent(bounds, direction, up, points)
    height = max((u1 - u0) / (1.0 - 2.0 * margin - title),
                 (a1 - a0) / (aspect * (1.0 - 2.0 * margin)))
    height = max(height, 1e-6) / zoom
    centre = np.asarray(bounds, dtype=np.float64).reshape(3, 2).mean(axis=1)
    centre = (centre - (centre @ right) * right - (centre @ up) * up
              + 0.5 * (a0 + a1) * right + (0.5 * (u0 + u1) + 0.5 * title * height) * up)
    return centre, 0.5 * height
