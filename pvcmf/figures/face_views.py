"""The predicted face as a surgeon reads it: standard views, profile overlay, signed maps.

* :func:`face_comparison`: pre-operative and predicted skin side by side (columns) in the
  clinical photographic views (rows): ``"frontal"``, ``"three_quarter"`` (the patient's
  right, 45 degrees) and ``"profile"`` (the patient's right side, face to the viewer's right).
* :func:`profile_overlay` (from :mod:`pvcmf.figures.profiles`): the midsagittal cut of both
  skins as a 2-D line plot (matplotlib), the silhouettes a surgeon compares first.
* :func:`displacement_views`: a signed component of the skin displacement (anterior-posterior
  ``"ap"`` or along the outward normal ``"normal"``) on a diverging map whose symmetric range
  is the 99th percentile of ``|value|`` over the points VISIBLE in the drawn views
  (:func:`visible_points`), so points hidden inside the mouth or behind the head do not set it.

Frames: the patient frame has x toward the patient's left, y anterior, z superior. Seen from
the front with z up, a camera shows +x on the viewer's LEFT, i.e. the patient's left on the
viewer's left: a mirror image. Clinical photographs show the patient's right on the viewer's
left, so every mesh is drawn reflected (x -> -x, :func:`to_display`), which turns the patient
frame into a right-handed (right, anterior, superior) display frame in which the cameras
below are ordinary rotations.

Delegates to PyVista (off-screen :class:`pyvista.Plotter`, ``slice``), VTK's
``vtkSelectVisiblePoints`` (z-buffer visibility) and matplotlib (the 2-D overlay).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np
import pyvista as pv
from vtkmodules.vtkRenderingCore import vtkSelectVisiblePoints

from .. import arrays
from .framing import (FRAME_MARGIN, FRAME_SLAB, FRAME_TITLE, FRAME_WIDEN,  # noqa: F401
                      fit_aspect, fit_parallel, frame_bounds, frame_skins)
from .profiles import POST_LABEL, PRE_LABEL, anterior_profile, profile_overlay  # noqa: F401
from .colour_range import saturation_note, symmetric_limit
from .skin_marks import CUT_COLOR, MAP_CUT_COLOR, MAP_CUT_WORDS, cut_points, modelled_points

__all__ = ["VIEWS", "to_display", "display_bounds", "frame_bounds", "set_view", "add_patient_mesh", "shaded_display", "visible_points",
           "signed_displacement", "symmetric_limit", "visible_in_views", "displacement_limit", "modelled_points", "add_skin", "face_comparison", "anterior_profile", "profile_overlay", "chart_image",
           "prediction_summary", "carry_to_skin", "UNMODELLED_COLOR", "CUT_COLOR", "fit_parallel",
           "displacement_views", "saturation_note"]

SKIN_COLOR = "peachpuff"
#: camera direction (from the focal point toward the camera) in the DISPLAY frame
#: (x = patient's right, y anterior, z superior), view up is +z for all views
VIEWS = {
    "frontal": (0.0, 1.0, 0.0),
    "three_quarter": (np.sqrt(0.5), np.sqrt(0.5), 0.0),
    "profile": (1.0, 0.0, 0.0),
}
VIEW_TITLES = {"frontal": "frontal", "three_quarter": "three-quarter (right)",
               "profile": "profile (right)"}
COMPONENT_TITLES = {"ap": "anterior(+) / posterior(-) displacement (mm)",
                    "normal": "outward(+) / inward(-) displacement (mm)",
                    "magnitude": "displacement magnitude (mm)"}
_ID = "_face_views_point_id"


def to_display(mesh):
    """Copy of ``mesh`` reflected to the display frame (x -> -x), without normals.

    Examples
    --------
    >>> import pyvista as pv
    >>> to_display(pv.PolyData([[1.0, 2.0, 3.0]])).points.tolist()
    [[-1.0, 2.0, 3.0]]
    """
    out = mesh.copy(deep=True)
    out.points = np.asarray(mesh.points, dtype=np.float64) * np.array([-1.0, 1.0, 1.0])
    if arrays.NORMALS in out.point_data:
        del out.point_data[arrays.NORMALS]
    return out


def display_bounds(mesh):
    """Bounds of ``mesh`` (patient frame) in the display frame: ``to_display(mesh).bounds``
    without copying the mesh.

    Examples
    --------
    >>> import pyvista as pv
    >>> display_bounds(pv.PolyData([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]))
    (-4.0, -1.0, 2.0, 5.0, 3.0, 6.0)
    """
    b = [float(v) for v in mesh.bounds]
    return (-b[1], -b[0], b[2], b[3], b[4], b[5])


def _check_view(view):
    if view not in VIEWS:
        raise ValueError(f"view must be one of {sorted(VIEWS)}, got {view!r}")


def set_view(plotter, bounds, view, zoom=1.0, margin=FRAME_MARGIN, title=FRAME_TITLE,
             points=None):
    """Point the active camera at ``bounds`` (display frame) from the clinical ``view``.

    Parallel projection, so the same face has the same size in every view. The box's
    projection on the screen, or that of the display-frame ``points`` inside it, fits the
    panel (:func:`pvcmf.figures.framing.fit_parallel`): ``margin`` free on every side and
    a ``title`` band at the top, whatever the view and the panel's aspect ratio.
    """
    _check_view(view)
    direction = np.asarray(VIEWS[view])
    aspect = float(plotter.renderer.GetTiledAspectRatio()) or 1.0
    focal, scale = fit_parallel(bounds, direction, aspect, margin=margin, title=title,
                                zoom=zoom, points=points)
    b = np.asarray(bounds, dtype=float).reshape(3, 2)
    size = max(float(np.linalg.norm(b[:, 1] - b[:, 0])), 1.0)
    plotter.camera_position = [tuple(focal + 3.0 * size * direction), tuple(focal),
                               (0.0, 0.0, 1.0)]
    plotter.enable_parallel_projection()
    plotter.camera.parallel_scale = scale
    plotter.reset_camera_clipping_range()


#: display-frame surfaces with their normals, by geometry (see :func:`shaded_display`)
_SHADED = OrderedDict()
_SHADED_MAX = 4


def _geometry_key(surface):
    """The points in full and every 61st connectivity entry (a changed mesh with the same
    points and cell count but other cells is not a case the figures meet)."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(np.ascontiguousarray(surface.points).tobytes())
    digest.update(np.ascontiguousarray(surface.faces[::61]).tobytes())
    return surface.n_points, surface.n_cells, digest.hexdigest()


def _closed_outward(shown):
    """Whether a triangle surface is closed and edge-manifold (every edge in exactly two
    triangles), and which triangles wind inward: those of the connected pieces whose
    enclosed volume is negative (a nose merged onto a head may wind the other way)."""
    if not shown.n_cells or not shown.is_all_triangles:
        return False, None
    tri = shown.faces.reshape(-1, 4)[:, 1:]
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    _, count = np.unique(e[:, 0] * np.int64(shown.n_points) + e[:, 1], return_counts=True)
    if not np.all(count == 2):
        return False, None
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = shown.n_points
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    piece = piece[tri[:, 0]]
    x = np.asarray(shown.points, dtype=np.float64)
    volume = np.einsum("ij,ij->i", x[tri[:, 0]], np.cross(x[tri[:, 1]], x[tri[:, 2]]))
    return True, (np.bincount(piece, weights=volume) < 0)[piece]


def shaded_display(mesh):
    """``mesh`` (patient frame) in the display frame with point normals for smooth
    shading, computed once per geometry, and whether it is a closed manifold.

    The normals are VTK's (``compute_normals``, as PyVista's ``smooth_shading`` computes
    them), oriented outward, piece by piece, when the surface is closed; the last few geometries are kept,
    so the views of one skin share them. Point and cell arrays are those of ``mesh``.

    Returns
    -------
    (pyvista.PolyData, bool)
        A fresh shallow copy (safe to add arrays to) and ``closed``.
    """
    surface = mesh if isinstance(mesh, pv.PolyData) else mesh.extract_surface(algorithm=None)
    key = _geometry_key(surface)
    if key in _SHADED:
        _SHADED.move_to_end(key)
        base, closed = _SHADED[key]
    else:
        shown = pv.PolyData(np.asarray(surface.points, dtype=np.float64) * [-1.0, 1.0, 1.0],
                            faces=surface.faces)
        base = shown.compute_normals(cell_normals=False, split_vertices=False)
        closed, inward = _closed_outward(base)  # windings made consistent by VTK
        if closed and inward.any():  # outward, so that the culled back faces are hidden
            faces = base.faces.reshape(-1, 4).copy()
            faces[inward] = faces[inward][:, [0, 1, 3, 2]]
            normals = np.asarray(base.point_data[arrays.NORMALS]).copy()
            flipped = np.unique(faces[inward, 1:])
            normals[flipped] *= -1.0
            base = pv.PolyData(base.points, faces=faces.ravel())
            base.point_data[arrays.NORMALS] = normals
        _SHADED[key] = (base, closed)
        while len(_SHADED) > _SHADED_MAX:
            _SHADED.popitem(last=False)
    out = base.copy(deep=False)
    for name in surface.point_data.keys():
        if name != arrays.NORMALS:
            out.point_data[name] = surface.point_data[name]
    for name in surface.cell_data.keys():
        out.cell_data[name] = surface.cell_data[name]
    if surface.point_data.active_scalars_name in out.point_data:
        out.point_data.active_scalars_name = surface.point_data.active_scalars_name
    out.point_data.active_normals_name = arrays.NORMALS
    return out, closed


def add_patient_mesh(plotter, mesh, **kwargs):
    """``plotter.add_mesh`` of ``mesh`` (patient frame) reflected to the display frame.

    Smooth shading by default, with normals computed once per geometry
    (:func:`shaded_display`); an opaque closed surface has its back faces culled (they
    are hidden behind its front faces), which halves the rasterised triangles.
    """
    kwargs.setdefault("smooth_shading", True)
    if not kwargs["smooth_shading"] or not isinstance(mesh, (pv.PolyData, pv.UnstructuredGrid)):
        return plotter.add_mesh(to_display(mesh), **kwargs)
    shown, closed = shaded_display(mesh)
    actor = plotter.add_mesh(shown, **kwargs)
    if closed and kwargs.get("opacity", 1.0) == 1.0 and not kwargs.get("style"):
        actor.prop.culling = "back"
    return actor


def visible_points(surface, view, window_size=(400, 400), tolerance=1.0):
    """Boolean mask of the points of ``surface`` (patient frame) seen from ``view``.

    The surface is rendered off screen with :func:`set_view`; VTK's
    ``vtkSelectVisiblePoints`` keeps the points whose depth matches the z-buffer within
    ``tolerance`` mm, so points behind other parts of the surface (inside the mouth,
    behind the head) are hidden.

    Examples
    --------
    >>> import pyvista as pv
    >>> sphere = pv.Sphere(radius=50.0, theta_resolution=30, phi_resolution=30)
    >>> seen = visible_points(sphere, "frontal")
    >>> bool(seen[sphere.points[:, 1].argmax()]), bool(seen[sphere.points[:, 1].argmin()])
    (True, False)
    """
    _check_view(view)
    shown, closed = shaded_display(surface)  # the display frame, wound outward if closed
    shown.point_data[_ID] = np.arange(shown.n_points)
    p = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        actor = p.add_mesh(shown, color="white", lighting=False)
        if closed:  # back faces lie behind front faces: the same z-buffer, half the work
            actor.prop.culling = "back"
        set_view(p, shown.bounds, view)
        p.ren_win.Render()  # VTK's render: fills the z-buffer, no pyvista show hooks
        sel = vtkSelectVisiblePoints()
        sel.SetInputData(shown)
        sel.SetRenderer(p.renderer)
        sel.SetToleranceWorld(float(tolerance))
        sel.SelectionWindowOff()
        sel.Update()
        ids = np.asarray(pv.wrap(sel.GetOutput()).point_data[_ID], dtype=np.int64)
    finally:
        p._before_close_callback = None  # an internal render, not a figure to record
        p.close()
    mask = np.zeros(shown.n_points, dtype=bool)
    mask[ids] = True
    return mask


def signed_displacement(skin, component="ap"):
    """Signed displacement (mm) of a skin with the point array ``displacement``.

    ``"ap"``: the anterior (+y) component; ``"normal"``: along the outward surface normal;
    ``"magnitude"``: the length (not signed).
    """
    u = np.asarray(arrays.require_array(skin, arrays.DISPLACEMENT, ncomp=3), dtype=np.float64)
    if component == "ap":
        return u[:, 1].copy()
    if component == "magnitude":
        return np.linalg.norm(u, axis=1)
    if component == "normal":
        surface = pv.PolyData(np.asarray(skin.points), faces=skin.extract_surface(
            algorithm=None).faces)  # without arrays: VTK would keep stale active normals
        normals = surface.compute_normals(
            cell_normals=False, point_normals=True, auto_orient_normals=True,
            consistent_normals=True, split_vertices=False)[arrays.NORMALS]
        return np.einsum("ij,ij->i", u, np.asarray(normals, dtype=np.float64))
    raise ValueError(f"component must be one of {sorted(COMPONENT_TITLES)}, got {component!r}")


def add_skin(plotter, skin, color, unmodelled=None):
    """Add ``skin`` to ``plotter`` in ``color``; with ``unmodelled`` (a colour), its points
    outside the model (:func:`modelled_points`) in that colour; its points on a cut of the
    scan (:func:`cut_points`) in :data:`CUT_COLOR`. Returns the actor."""
    cut = cut_points(skin)
    grey = unmodelled is not None and arrays.SKIN_MODELLED in skin.point_data
    if not (grey or cut.any()):
        return add_patient_mesh(plotter, skin, color=color, specular=0.2)
    shown = skin.copy(deep=False)
    shown.clear_data()
    if not cut.any():
        shown.point_data["modelled"] = modelled_points(skin).astype(np.float64)
        return add_patient_mesh(plotter, shown, scalars="modelled", cmap=[unmodelled, color],
                                clim=(0.0, 1.0), show_scalar_bar=False, specular=0.2)
    # 0 outside the model, 1 skin, 2 on a cut: the cut borders the modelled skin
    shade = np.ones(skin.n_points)
    if grey:
        shade[~modelled_points(skin)] = 0.0
    shade[cut] = 2.0
    shown.point_data["shade"] = shade
    return add_patient_mesh(plotter, shown, scalars="shade",
                            cmap=[unmodelled or color, color, CUT_COLOR], clim=(0.0, 2.0),
                            show_scalar_bar=False, specular=0.2)


def face_comparison(pre, post, views=("frontal", "three_quarter", "profile"),
                    window_size=None, color=SKIN_COLOR, unmodelled=None, font_size=10):
    """Pre-operative and predicted skins side by side in clinical views.

    Parameters
    ----------
    pre, post : pyvista.PolyData
        Skins in the patient frame (``post`` at its predicted position).
    views : sequence of str
        Rows, from :data:`VIEWS`.
    window_size : (int, int), optional
        Default 440 x 500 pixels per panel.
    unmodelled : color, optional
        Draw the predicted skin's points the model does not reach (its
        ``arrays.SKIN_MODELLED`` array is 0: the back of the head, the neck, whose
        displacement is an extension fading to zero) in this colour, e.g. ``"0.78"``.
        Both skins' points on a cut of the scan (``arrays.SKIN_CUT``) are drawn in
        :data:`~pvcmf.figures.skin_marks.CUT_COLOR`.
    font_size : int
        Of the panel titles.

    Returns
    -------
    pyvista.Plotter
        Off screen, ``len(views)`` rows x 2 columns (pre-operative, predicted). Each view
        fits the head of both skins (:func:`frame_bounds`) with a margin on every side
        and the title's band free (:func:`set_view`).
    """
    views = tuple(views)
    for v in views:
        _check_view(v)
    window_size = window_size or (880, 500 * len(views))
    p = pv.Plotter(off_screen=True, shape=(len(views), 2), window_size=list(window_size),
                   border=False)
    bounds, points = frame_skins(pre, post)
    for row, view in enumerate(views):
        for col, (skin, label, grey) in enumerate(((pre, PRE_LABEL, None),
                                                   (post, POST_LABEL, unmodelled))):
            p.subplot(row, col)
            p.set_background("white", all_renderers=False)
            add_skin(p, skin, color, grey)
            set_view(p, bounds, view, points=points)
            p.add_text(f"{label}, {VIEW_TITLES[view]}", font_size=font_size, color="black")
    return p


def visible_in_views(surface, views=("frontal", "profile")):
    """Points of ``surface`` visible in any of ``views`` (:func:`visible_points`)."""
    seen = np.zeros(surface.n_points, dtype=bool)
    for v in views:
        seen |= visible_points(surface, v)
    return seen


def displacement_limit(skin, component="ap", views=("frontal", "profile"), percentile=99.0,
                       visible=None):
    """Colour limit (mm) of a displacement component over the VISIBLE points.

    ``percentile`` of ``|value|`` over the modelled points of ``skin``
    (:func:`modelled_points`) visible in any of ``views`` (:func:`visible_in_views`,
    :func:`symmetric_limit`), or over ``visible`` when given; never over its points on a
    cut of the scan (:func:`cut_points`).
    """
    values = signed_displacement(skin, component)
    if visible is None:
        visible = visible_in_views(skin, views) & modelled_points(skin)
    return symmetric_limit(values, np.asarray(visible, dtype=bool) & ~cut_points(skin),
                           percentile)


def displacement_views(skin, component="ap", views=("frontal", "profile"), percentile=99.0,
                       cmap=None, window_size=None, limit=None, visible=None):
    """A signed displacement component on the skin, with a range from its visible points.

    Its points on a cut of the scan (``arrays.SKIN_CUT``, :func:`cut_points`) are drawn in
    :data:`~pvcmf.figures.skin_marks.MAP_CUT_COLOR`, not in the map's colours (they are
    the scan's edge, not the patient's skin), set no range, and the caption says so.

    Parameters
    ----------
    skin : pyvista.PolyData
        Pre-operative skin with the point array ``displacement`` (mm).
    component : {"ap", "normal", "magnitude"}
        See :func:`signed_displacement`.
    views : sequence of str
        Panels, left to right.
    percentile : float
        The range is ``[-m, m]`` with ``m`` this percentile of ``|value|`` over the
        modelled points visible in any of ``views`` (:func:`displacement_limit`).
    limit : float, optional
        Use ``[-limit, limit]`` (``[0, limit]`` for the magnitude) instead.
    visible : numpy.ndarray of bool, optional
        Precomputed visibility (:func:`visible_in_views`).

    Returns
    -------
    pyvista.Plotter
        Off screen, one row of views above a strip holding the colour bar.
    """
    views = tuple(views)
    for v in views:
        _check_view(v)
    values = signed_displacement(skin, component)
    cut = cut_points(skin)  # the scan's edge: no colour of its own, no say in the range
    if visible is None and limit is None:
        visible = visible_in_views(skin, views) & modelled_points(skin)
    if visible is not None:
        visible = np.asarray(visible, dtype=bool) & ~cut
    # displacement_limit, without computing the values twice
    m = symmetric_limit(values, visible, percentile) if limit is None else float(limit)
    clim = (0.0, m) if component == "magnitude" else (-m, m)
    cmap = cmap or ("viridis" if component == "magnitude" else "RdBu_r")
    shown = skin.copy(deep=True)
    shown.clear_data()
    title = COMPONENT_TITLES[component]
    shown.point_data[title] = np.where(cut, np.nan, values)
    note = saturation_note(values, m, visible if visible is not None else ~cut,
                           signed=component != "magnitude")
    if cut.any():
        note = "; ".join(filter(None, (note, MAP_CUT_WORDS)))
    n = len(views)
    window_size = window_size or (440 * n, 600)
    p = pv.Plotter(off_screen=True, shape=(2, n), row_weights=[0.84, 0.16],
                   groups=[(1, np.s_[:])], window_size=list(window_size), border=False)
    actor = None
    bounds, points = frame_skins(skin)
    for col, view in enumerate(views):
        p.subplot(0, col)
        p.set_background("white", all_renderers=False)
        actor = add_patient_mesh(p, shown, scalars=title, cmap=cmap, clim=clim,
                                 nan_color=MAP_CUT_COLOR, show_scalar_bar=False, specular=0.1)
        set_view(p, bounds, view, points=points)
        p.add_text(VIEW_TITLES[view], font_size=10, color="black")
    p.subplot(1, 0)
    p.set_background("white", all_renderers=False)
    bar = p.add_scalar_bar(title=title, mapper=actor.mapper, color="black", vertical=False,
                     position_x=0.15, position_y=0.02, width=0.7, height=0.62,
                     title_font_size=16, label_font_size=14, n_labels=5, fmt="%.1f")
    bar.SetTextPositionToPrecedeScalarBar()  # tick labels below the bar
    bar.SetTitle("")  # the title goes above the bar, clear of the labels
    if note:  # the colours saturate: the title says where, in a size that fits the strip
        caption = p.add_text(f"{title}; {note}", position=(0.5, 0.82), viewport=True,
                             color="black")
        prop = caption.GetTextProperty()
        prop.SetFontSize(int(min(22, 0.95 * window_size[0] / (0.55 * len(caption.GetInput())))))
        prop.SetJustificationToCentered()
        prop.SetVerticalJustificationToCentered()
    else:
        p.add_text(title, position="upper_edge", font_size=11, color="black")
    return p


def chart_image(fig, dpi=100):
    """A matplotlib figure as an (h, w, 3) uint8 RGB array (Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    fig.set_dpi(dpi)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


#: colour of the predicted skin the model does not predict in :func:`prediction_summary`
UNMODELLED_COLOR = "0.78"


def _panel_width(pre, post, height, views):
    """The panel width (pixels) at which the widest of ``views`` of the heads of ``pre``
    and ``post`` fills the panel both ways (:func:`fit_aspect`)."""
    bounds, points = frame_skins(pre, post)
    aspect = max(fit_aspect(bounds, VIEWS[view], points=points) for view in views)
    return int(round(height * float(np.clip(aspect, 0.6, 1.3))))


def prediction_summary(pre, post, panel=(380, 440), unmodelled=UNMODELLED_COLOR):
    """One image for a first look: frontal and profile, pre-operative and predicted, and
    the midsagittal profile overlay, side by side.

    Parameters
    ----------
    pre, post : pyvista.PolyData
        Skins in the patient frame.
    panel : (int, int)
        Largest width and the height (pixels) of one 3-D panel: the width is narrowed to
        the head's proportions (a narrow head, narrow panels).
    unmodelled : color or None
        Colour of the predicted skin the model does not reach (``arrays.SKIN_MODELLED``
        is 0: the back of the head, the neck, spots where the mesh lies deeper than the
        transfer's band under the skin; their displacement is the transfer's extension,
        fading to zero, see :func:`face_comparison`); None draws it in the skin colour.

    Returns
    -------
    numpy.ndarray
        (h, w, 3) uint8 RGB image: a 2 x 2 block (rows frontal, profile; columns
        pre-operative, predicted) then the overlay (:func:`profile_overlay`), with a note
        under it naming the grey skin and the skin on a cut of the scan.
    """
    views = ("frontal", "profile")
    h = int(panel[1])
    w = min(int(panel[0]), _panel_width(pre, post, h, views))
    p = face_comparison(pre, post, views=views, window_size=(2 * w, 2 * h),
                        unmodelled=unmodelled, font_size=11)
    faces = p.screenshot(return_img=True)[..., :3]
    p.close()
    height = faces.shape[0]
    # at least 420 pixels wide: the title and the note fit at any height
    fig = profile_overlay(pre, post, figsize=(max(0.5 * height, 420) / 100, height / 100))
    notes = []
    if (unmodelled is not None and arrays.SKIN_MODELLED in post.point_data
            and not modelled_points(post).all()):
        notes.append("grey skin: beyond the mesh's reach;\nits move is extrapolated, fading to none")
    if cut_points(pre).any() or cut_points(post).any():
        notes.append("blue skin: where the scan cut the head;\nthe scan's edge, not the patient's")
    if notes:
        fig.subplots_adjust(bottom=0.12 + 40.0 * len(notes) / height)  # 40 pixels a note
        fig.text(0.5, 0.015, "\n".join(notes), ha="center", va="bottom", fontsize=9,
                 color="0.3")
    chart = chart_image(fig)[:height]
    pad = np.full((height - chart.shape[0], chart.shape[1], 3), 255, np.uint8)
    return np.concatenate([faces, np.concatenate([chart, pad])], axis=1)


def carry_to_skin(patch, skin, names, *, gap=8.0, k=8):
    """Carry point arrays of a face ``patch`` onto a whole ``skin``, bridging small gaps.

    Each skin point within ``gap`` mm of the patch gets the inverse-distance weighted mean
    of its ``k`` nearest patch points; points further away get NaN (drawn in the NaN
    colour). Used to show per-point results measured on the face regions (boxes with gaps
    between them) on a continuous face.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> skin = pv.Plane(i_resolution=20, j_resolution=20)
    >>> patch = skin.extract_points(skin.points[:, 0] < 0.0, adjacent_cells=False)
    >>> patch.point_data["v"] = np.ones(patch.n_points)
    >>> out = carry_to_skin(patch, skin, ["v"], gap=0.12)
    >>> bool(np.isnan(out["v"]).any()), float(np.nanmax(out["v"]))
    (True, 1.0)
    """
    from scipy.spatial import cKDTree

    k = int(min(k, patch.n_points))
    dist, idx = cKDTree(np.asarray(patch.points)).query(np.asarray(skin.points), k=k)
    dist, idx = dist.reshape(len(dist), -1), idx.reshape(len(idx), -1)
    w = 1.0 / np.maximum(dist, 1e-6) ** 2
    near = dist[:, 0] <= gap
    out = skin.copy(deep=True)
    out.clear_data()
    for name in names:
        v = np.asarray(patch.point_data[name], dtype=np.float64)
        carried = np.full(skin.n_points, np.nan)
        carried[near] = (w[near] * v[idx[near]]).sum(axis=1) / w[near].sum(axis=1)
        out.point_data[name] = carried
    return out
