"""What the planner shows: the 3D scene and the profile silhouette, without a web framework.

* :class:`Scene` -- one offscreen :class:`pyvista.Plotter` with two linked views: the
  skeleton (bone at rest in grey, the moved segments in colour) and the predicted face
  coloured by its signed displacement (mm along the outward skin normal: + outward,
  - inward). :meth:`Scene.update` moves both for a plan, in place. Skin on a cut of the
  scan (``arrays.SKIN_CUT``) is drawn in the colour maps' cut colour
  (:data:`pvcmf.figures.skin_marks.MAP_CUT_COLOR`), not in the map's colours.
  The scene is drawn as a photograph, like every face figure: the meshes are reflected
  once into the display frame of :mod:`pvcmf.figures.face_views` (x -> -x, triangles
  rewound so that they still face outward), so the frontal view shows the patient's right
  on the viewer's left; a plan then only rewrites the moved points.
* :func:`profile_png` -- the midsagittal profile before (grey) and after (red) as a PNG
  (matplotlib's Agg canvas), and :func:`data_url` to put it in a web page.

Delegates to PyVista/VTK (slicing, rendering) and matplotlib (the profile chart).
"""

from __future__ import annotations

import base64
import io

import numpy as np
import pyvista as pv

from .. import arrays
from ..figures.face_views import VIEWS
from ..figures.profiles import CUT_LABEL, midline_x
from ..figures.skin_marks import CUT_COLOR, MAP_CUT_COLOR, cut_points

__all__ = ["Scene", "data_url", "display_copy", "profile_png", "profile_segments",
           "signed_displacement", "DISPLACEMENT_CLIM", "SCENE_VIEWS", "SIGNED"]

#: point array of the predicted face: displacement along the outward skin normal (mm)
SIGNED = "signed displacement (mm)"
#: colour range of the signed displacement map, mm
DISPLACEMENT_CLIM = (-8.0, 8.0)
_SEGMENT_COLOURS = {"maxilla": "mediumseagreen", "mandible": "dodgerblue", "cranium": "wheat"}
#: patient frame (x left, y anterior, z superior; left-handed) -> display frame (x right)
_MIRROR = np.array([-1.0, 1.0, 1.0])
#: camera directions of :meth:`Scene.set_view` in the display frame: the clinical views of
#: :data:`pvcmf.figures.face_views.VIEWS` and a front-right oblique one (the default)
SCENE_VIEWS = {"oblique": (0.8, 1.6, 0.25), **VIEWS}


def display_copy(mesh):
    """``mesh`` (patient frame) as a new PolyData in the display frame: points x -> -x,
    cells wound the other way (so their normals still point outward), no arrays.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> tri = pv.PolyData([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], faces=[3, 0, 1, 2])
    >>> shown = display_copy(tri)
    >>> shown.points[1].tolist(), float(shown.compute_normals().cell_normals[0, 2])
    ([-1.0, 0.0, 0.0], 1.0)
    """
    surface = mesh if isinstance(mesh, pv.PolyData) else mesh.extract_surface()
    shown = pv.PolyData(np.asarray(surface.points, dtype=np.float64) * _MIRROR,
                        faces=np.asarray(surface.faces).copy())
    shown.flip_faces(inplace=True)
    return shown


def signed_displacement(skin, displacement):
    """Displacement along ``skin``'s outward point normals (mm, + outward).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> sphere = pv.Sphere(radius=10.0)
    >>> disp = 0.1 * np.asarray(sphere.points)     # 1 mm outward everywhere
    >>> bool(np.allclose(signed_displacement(sphere, disp), 1.0, atol=0.05))
    True
    """
    disp = np.asarray(displacement, dtype=float)
    if disp.shape != (skin.n_points, 3):
        raise ValueError(f"displacement must have shape ({skin.n_points}, 3), got {disp.shape}")
    normals = np.asarray(skin.point_normals, dtype=float)
    return np.einsum("ij,ij->i", disp, normals)


def profile_segments(surface, x=None, on_cut=False):
    """Line segments of the surface's sagittal section at ``x`` as (m, 2, 2) (y, z) mm.

    ``x`` defaults to the middle of the surface's x bounds (the midsagittal plane).
    ``on_cut=True`` also returns, per segment, whether it lies on skin on a cut of the scan
    (both ends on the surface's ``arrays.SKIN_CUT``, interpolated; none without it).
    """
    if x is None:
        x = 0.5 * (surface.bounds[0] + surface.bounds[1])
    src = pv.PolyData(np.asarray(surface.points), faces=surface.faces)
    if on_cut and arrays.SKIN_CUT in surface.point_data:
        src.point_data["_on_cut"] = np.asarray(surface.point_data[arrays.SKIN_CUT], float)
    section = src.slice(normal="x", origin=(float(x), *surface.center[1:]))
    if section.n_points == 0:
        return (np.zeros((0, 2, 2)), np.zeros(0, bool)) if on_cut else np.zeros((0, 2, 2))
    edges = section.extract_all_edges()
    lines = np.asarray(edges.lines).reshape(-1, 3)[:, 1:]
    segs = np.asarray(edges.points)[lines][:, :, 1:]
    if not on_cut:
        return segs
    if "_on_cut" not in edges.point_data:
        return segs, np.zeros(len(segs), dtype=bool)
    return segs, (np.asarray(edges.point_data["_on_cut"])[lines] >= 0.5).all(axis=1)


def profile_png(pre, post, x=None, *, size=(4.0, 4.0), dpi=90):
    """PNG bytes of the profile before (grey) and after (red), face to the right; a band
    of the face figures' cut colour lies under a line where it runs over skin on a cut of
    the scan (as :func:`pvcmf.figures.profiles.profile_overlay` draws it).

    Parameters
    ----------
    pre, post : pyvista.PolyData
        Rest and predicted skin.
    x : float, optional
        Sagittal plane (mm); default: the head's midline (:func:`~pvcmf.figures.profiles.midline_x`
        of ``pre``, the plane of the PNG profile overlay).
    """
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    if x is None:
        x = midline_x(pre)
    fig = Figure(figsize=size, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    cut_label = CUT_LABEL
    for surface, colour, label in ((pre, "0.55", "pre-op"), (post, "tab:red", "planned")):
        segs, cut = profile_segments(surface, x, on_cut=True)
        if cut.any():  # a band under the line where it runs over the scan's edge
            ax.add_collection(LineCollection(segs[cut], colors=CUT_COLOR, linewidths=6,
                                             zorder=1, label=cut_label))
            cut_label = None
        ax.add_collection(LineCollection(segs, colors=colour, linewidths=1.2, label=label,
                                         zorder=2))
    b = pre.bounds
    ax.set_xlim(0.5 * (b[2] + b[3]), b[3] + 15)  # the face half
    ax.set_ylim(b[4] - 5, b[5] + 5)
    ax.set_aspect("equal")
    ax.set_xlabel("anterior-posterior y (mm)")
    ax.set_ylabel("vertical z (mm)")
    # below the axes, as the profile overlay's: inside, it would hide part of a line
    fig.legend(*ax.get_legend_handles_labels(), loc="lower center", ncol=3, frameon=False,
               fontsize=8, bbox_to_anchor=(0.5, 0.0))
    fig.subplots_adjust(left=0.17, right=0.97, bottom=0.19, top=0.97)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def data_url(png):
    """A ``data:image/png;base64,...`` URL of PNG bytes."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


class Scene:
    """The planner's 3D scene: skeleton (left) and predicted face (right), linked cameras.

    Parameters
    ----------
    model : pvcmf.planner.PlannerModel
        The prepared model.
    window_size : tuple of int
        Render window size in pixels.
    """

    def __init__(self, model, window_size=(1000, 500)):
        self.model = model
        self.plotter = pv.Plotter(shape=(1, 2), off_screen=True, window_size=list(window_size),
                                  border=False)
        #: the predicted skin in the patient frame (point array ``displacement``)
        self.predicted = pv.PolyData(np.asarray(model.skin.points, dtype=np.float64).copy(),
                                     faces=model.skin.faces)
        self.predicted.point_data[arrays.DISPLACEMENT] = np.zeros((model.skin.n_points, 3))
        if arrays.SKIN_CUT in model.skin.point_data:  # the profile marks the cut on both
            self.predicted.point_data[arrays.SKIN_CUT] = np.asarray(
                model.skin.point_data[arrays.SKIN_CUT]).copy()
        #: the predicted skin as drawn, in the display frame (x -> -x)
        self.face = display_copy(model.skin)
        #: the skin's points on a cut of the scan: the scan's edge, not the patient's skin
        self.on_cut = cut_points(model.skin)
        #: the profile's plane (:func:`~pvcmf.figures.profiles.midline_x`), found once
        self.midline = midline_x(model.skin)
        self.face.point_data[SIGNED] = np.where(self.on_cut, np.nan, 0.0)
        self.bones = {}
        self.plotter.subplot(0, 0)
        self.plotter.add_text("skeleton: rest (grey), planned (colour)", font_size=9)
        for name in model.bones.keys():
            rest = model.bones[name]
            if rest is None or rest.n_points == 0:
                continue
            shown = display_copy(rest)
            if name in model.segments:
                self.plotter.add_mesh(shown, color="#bbbbbb", opacity=0.35)
            moved = shown.copy()
            self.bones[name] = moved
            self.plotter.add_mesh(moved, color=_SEGMENT_COLOURS.get(name, "white"),
                                  smooth_shading=True)
        self.plotter.subplot(0, 1)
        self.plotter.add_text("predicted face", font_size=9)
        self.plotter.add_mesh(self.face, scalars=SIGNED, cmap="coolwarm",
                              clim=DISPLACEMENT_CLIM, nan_color=MAP_CUT_COLOR, smooth_shading=True,
                              scalar_bar_args={"title": "mm along normal", "n_labels": 5,
                                               "fmt": "%.0f", "vertical": False})
        self.plotter.link_views()
        self.set_view()

    def set_view(self, view="oblique"):
        """Point the linked cameras at the face from ``view`` (:data:`SCENE_VIEWS`: the
        front-right ``"oblique"``, or ``"frontal"``, ``"three_quarter"``, ``"profile"``)."""
        if view not in SCENE_VIEWS:
            raise ValueError(f"view must be one of {sorted(SCENE_VIEWS)}, got {view!r}")
        bounds = np.asarray(self.face.bounds).reshape(3, 2)
        centre = bounds.mean(axis=1)
        size = float(np.ptp(bounds, axis=1).max())
        direction = np.asarray(SCENE_VIEWS[view], dtype=float)
        direction /= np.linalg.norm(direction)
        self.plotter.camera_position = [tuple(centre + 2.2 * size * direction), tuple(centre),
                                        (0.0, 0.0, 1.0)]
        self.plotter.reset_camera()
        self.plotter.camera.zoom(1.1)

    def update(self, plan):
        """Show ``plan``: move the segments and the face; return the signed displacement
        (every skin point; :attr:`on_cut` marks the scan's edge)."""
        disp = np.asarray(self.model.displacement(plan), dtype=np.float64)
        points = np.asarray(self.model.skin.points, dtype=np.float64) + disp
        self.predicted.points = points
        self.predicted.point_data[arrays.DISPLACEMENT] = disp
        self.face.points = points * _MIRROR
        signed = signed_displacement(self.model.skin, disp)
        self.face.point_data[SIGNED] = np.where(self.on_cut, np.nan, signed)
        moved = self.model.skeleton(plan)
        for name, block in self.bones.items():
            block.points = np.asarray(moved[name].points, dtype=np.float64) * _MIRROR
        return signed  # the web view (or :meth:`screenshot`) renders

    def screenshot(self, filename=None):
        """Render and return the image (and save it when ``filename`` is given)."""
        return self.plotter.screenshot(filename)

    def close(self):
        """Release the render window."""
        self.plotter.close()
