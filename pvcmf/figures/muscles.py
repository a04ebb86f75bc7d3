"""Paper 000 Figs. 2a, 2b and 3: embedded facial muscles, the label image, their OBBs.

- :func:`figure_2a`: the facial soft tissue (translucent) with the six muscles per side;
- :func:`figure_2b`: one slice of the tissue + muscle label image (matplotlib);
- :func:`figure_3`: the muscles with their oriented bounding boxes (one for the masseter,
  two-level for the others) and the fibre direction of each box.

All read a label image written by :func:`pvcmf.filters.embed_muscles`. Surfaces come
from PyVista's ``ImageData.contour_labels`` (SurfaceNets) and ``contour``; boxes from
:func:`pvcmf.filters.fibers.muscle_boxes`; drawing is an off-screen
:class:`pyvista.Plotter` or a matplotlib ``Figure``.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.patches import Patch
from scipy import ndimage

from .. import arrays
from ..filters.fibers import muscle_boxes, obb_polydata
from .face_views import add_patient_mesh

__all__ = ["figure_2a", "figure_2b", "figure_3", "MUSCLE_COLORS", "muscle_surfaces"]

#: one colour per muscle kind (both sides), in :data:`pvcmf.arrays.MUSCLE_KINDS` order
MUSCLE_COLORS = {
    "orbicularis_oculi": "#d62728",
    "levator_labii_superioris_alaeque_nasi": "#9467bd",
    "levator_labii_superioris": "#1f77b4",
    "masseter": "#8c1c13",
    "zygomaticus_major": "#ff7f0e",
    "zygomaticus_minor": "#2ca02c",
}
SKIN_COLOR = "#f2d16b"  # the paper's yellow soft tissue


def _kind(name):
    return name.rsplit("_", 1)[0]


def _labels(labels):
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    tissue = arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu", ncomp=1,
                                  producer="segment")
    muscle = arrays.require_array(labels, arrays.MUSCLE, "point", dtype="iu", ncomp=1,
                                  producer="embed_muscles")
    return np.asarray(tissue), np.asarray(muscle)


def muscle_surfaces(labels, smoothing_scale=0.5):
    """Surface of each embedded muscle: ``{name: PolyData}`` (SurfaceNets, smoothed)."""
    _, muscle = _labels(labels)
    img = pv.ImageData(dimensions=labels.dimensions, spacing=labels.spacing,
                       origin=labels.origin)
    img.point_data["m"] = np.asarray(muscle, dtype=np.uint8)
    present = [i for i in np.unique(muscle) if i != arrays.MUSCLE_NONE]
    out = {}
    if not present:
        return out
    surf = img.contour_labels(scalars="m", smoothing=True, smoothing_scale=smoothing_scale,
                              output_mesh_type="triangles", boundary_style="all")
    key = "boundary_labels" if "boundary_labels" in surf.cell_data else surf.cell_data.keys()[0]
    pair = np.asarray(surf.cell_data[key])
    for mid in present:
        name = arrays.MUSCLES[int(mid) - 1]
        cells = np.flatnonzero((pair == mid).any(axis=1)) if pair.ndim == 2 else np.flatnonzero(pair == mid)
        if len(cells):
            faces = np.asarray(surf.faces).reshape(-1, 4)[cells]  # triangles
            out[name] = pv.PolyData(surf.points, faces.ravel()).clean()
    return out


def _skin(labels):
    """Outer skin: boundary of the head with enclosed cavities filled, largest piece."""
    tissue, _ = _labels(labels)
    head = ndimage.binary_fill_holes((tissue != arrays.AIR).reshape(labels.dimensions,
                                                                      order="F"))
    img = pv.ImageData(dimensions=labels.dimensions, spacing=labels.spacing,
                       origin=labels.origin)
    img.point_data["head"] = head.ravel(order="F").astype(np.float32)
    surf = img.contour([0.5], scalars="head").extract_largest()
    return surf.smooth_taubin(n_iter=20, pass_band=0.1)


def _camera(plotter, labels, where="front"):
    """Look at the muscles from the patient's front-left, framing the face; the meshes are
    drawn in the display frame (:func:`pvcmf.figures.face_views.add_patient_mesh`), so the
    camera is placed there too."""
    _, muscle = _labels(labels)
    pts = np.asarray(labels.points)[muscle != arrays.MUSCLE_NONE]
    if len(pts) == 0:
        pts = np.asarray(labels.points)
    flip = np.array([-1.0, 1.0, 1.0])  # patient frame -> display frame
    lo, hi = pts.min(0), pts.max(0)
    center = 0.5 * (lo + hi) * flip
    size = float(np.linalg.norm(hi - lo))
    direction = {"front": (0.45, 1.0, 0.12), "side": (1.0, 0.35, 0.1)}[where]  # patient frame
    direction = np.asarray(direction) * flip / np.linalg.norm(direction)
    plotter.camera_position = [tuple(center + 2.0 * size * direction), tuple(center),
                               (0.0, 0.0, 1.0)]


#: short legend names
SHORT = {
    "orbicularis_oculi": "orb. oculi",
    "levator_labii_superioris_alaeque_nasi": "LLSAN",
    "levator_labii_superioris": "LLS",
    "masseter": "masseter",
    "zygomaticus_major": "zyg. major",
    "zygomaticus_minor": "zyg. minor",
}


def _legend(plotter, names):
    kinds = [k for k in MUSCLE_COLORS if any(_kind(n) == k for n in names)]
    plotter.add_legend([[SHORT[k], MUSCLE_COLORS[k]] for k in kinds],
                       bcolor="white", size=(0.36, 0.22), loc="lower right", face="rectangle")


def figure_2a(labels, window_size=(800, 800), opacity=0.25):
    """Paper 000 Fig. 2a: facial soft tissue, translucent, with the embedded muscles.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``tissue`` and ``muscle`` (from ``embed_muscles``).
    window_size : tuple of int
        Pixels.
    opacity : float
        Opacity of the skin.

    Returns
    -------
    pyvista.Plotter
        Off screen.

    Examples
    --------
    >>> import pvcmf                                                   # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)                  # doctest: +SKIP
    >>> labels = case.truth.cmf.embed_muscles(landmarks=case.landmarks)  # doctest: +SKIP
    >>> figure_2a(labels).screenshot("fig2a.png")                      # doctest: +SKIP
    """
    surfaces = muscle_surfaces(labels)
    p = pv.Plotter(off_screen=True, window_size=list(window_size))
    p.set_background("white")
    add_patient_mesh(p, _skin(labels), color=SKIN_COLOR, opacity=opacity)
    for name, surf in surfaces.items():
        add_patient_mesh(p, surf, color=MUSCLE_COLORS[_kind(name)])
    _legend(p, surfaces)
    _camera(p, labels, "front")
    return p


#: RGB colours of the label slice (Fig. 2b): background labels, then muscles
_SLICE_COLORS = {
    arrays.AIR: "#000000",
    arrays.FAT: SKIN_COLOR,
    arrays.MUSCLE_TISSUE: "#e0913a",  # generic muscle (tongue, ...) without an atlas id
    arrays.BONE_TISSUE: "#f5f5f5",
    arrays.TEETH: "#bdbdbd",
    arrays.INTRACRANIAL: "#555555",
}


def figure_2b(labels, z=None, figsize=(6.4, 5.2), style="paper"):
    """Paper 000 Fig. 2b: an axial slice of the tissue + muscle label image.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``tissue`` and ``muscle``.
    z : float, optional
        Height (mm) of the slice; default: the slice holding the most muscle voxels.
    figsize : tuple of float
        Inches.
    style : {"paper", "labels"}
        ``"paper"``: as the paper draws the meshing input, the extra-cranial soft tissue
        with one value (yellow) and the muscle segments with another (red), everything
        else (bone, teeth, intracranial volume, air) outside the image domain (black).
        ``"labels"``: every tissue label and each muscle kind in its own colour.

    Returns
    -------
    matplotlib.figure.Figure
    """
    if style not in ("paper", "labels"):
        raise ValueError(f"style must be 'paper' or 'labels', got {style!r}")
    tissue, muscle = _labels(labels)
    dims = labels.dimensions
    t3 = tissue.reshape(dims, order="F")
    m3 = muscle.reshape(dims, order="F")
    z0, dz = labels.origin[2], labels.spacing[2]
    if z is None:
        k = int(np.argmax((m3 > 0).sum(axis=(0, 1))))
    else:
        k = int(np.clip(round((z - z0) / dz), 0, dims[2] - 1))
    if style == "paper":
        cls, colors, handles = _paper_classes(t3[:, :, k], m3[:, :, k])
    else:
        cls, colors, handles = _label_classes(t3[:, :, k], m3[:, :, k])
    fig = Figure(figsize=figsize)
    ax = fig.add_subplot(1, 1, 1)
    x0, dx = labels.origin[0], labels.spacing[0]
    y0, dy = labels.origin[1], labels.spacing[1]
    extent = (x0 - dx / 2, x0 + (dims[0] - 0.5) * dx, y0 - dy / 2, y0 + (dims[1] - 0.5) * dy)
    ax.imshow(cls.T, origin="lower", cmap=ListedColormap(colors), vmin=-0.5,
              vmax=len(colors) - 0.5, interpolation="nearest", extent=extent)
    ii, jj = np.nonzero(t3[:, :, k] != arrays.AIR)
    if ii.size:  # frame the head
        ax.set_xlim(x0 + (ii.min() - 3) * dx, x0 + (ii.max() + 3) * dx)
        ax.set_ylim(y0 + (jj.min() - 3) * dy, y0 + (jj.max() + 3) * dy)
    ax.set_xlabel("x (mm, patient's left +)")
    ax.set_ylabel("y (mm, anterior +)")
    ax.set_title(f"tissue + muscle image, axial slice z = {z0 + k * dz:.0f} mm", fontsize=10)
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7,
              frameon=False)
    fig.subplots_adjust(left=0.1, right=0.66, bottom=0.1, top=0.93)
    return fig


def _paper_classes(t, m):
    """0 outside the image domain, 1 extra-cranial soft tissue, 2 muscle segments."""
    cls = np.zeros(t.shape, dtype=int)
    cls[np.isin(t, arrays.SOFT_LABELS)] = 1
    cls[m > 0] = 2
    colors = ["#000000", SKIN_COLOR, "#c0392b"]
    handles = [Patch(color=SKIN_COLOR, label="facial tissue (one value)"),
               Patch(color="#c0392b", label="muscle segments (another value)")]
    return cls, colors, handles


def _label_classes(t, m):
    """Tissue labels 0..5, then one class per muscle kind."""
    kinds = list(MUSCLE_COLORS)
    cls = t.astype(int).copy()
    cls[cls > arrays.INTRACRANIAL] = arrays.AIR
    mk = m.astype(int)
    has = mk > 0
    cls[has] = 6 + np.array([kinds.index(_kind(n)) for n in arrays.MUSCLES])[mk[has] - 1]
    colors = [_SLICE_COLORS[i] for i in range(6)] + [MUSCLE_COLORS[k_] for k_ in kinds]
    names = {v: k_ for k_, v in arrays.TISSUE_LABELS.items()}
    handles = [Patch(color=_SLICE_COLORS[i], label=names[i]) for i in range(1, 6)
               if (cls == i).any()]
    handles += [Patch(color=MUSCLE_COLORS[kinds[i]], label=SHORT[kinds[i]])
                for i in range(len(kinds)) if (cls == 6 + i).any()]
    return cls, colors, handles


def figure_3(labels, levels=None, window_size=(800, 800)):
    """Paper 000 Fig. 3: the muscles with their oriented bounding boxes.

    One box for the masseter, two-level boxes (two halves along the long axis) for the
    other muscles; a line along each box's long axis marks its fibre direction.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``muscle`` (from ``embed_muscles``).
    levels : None, int or dict
        See :func:`pvcmf.filters.fibers.muscle_boxes`.
    window_size : tuple of int
        Pixels.

    Returns
    -------
    pyvista.Plotter
        Off screen.
    """
    surfaces = muscle_surfaces(labels)
    boxes = muscle_boxes(labels, levels=levels)
    p = pv.Plotter(off_screen=True, window_size=list(window_size))
    p.set_background("white")
    add_patient_mesh(p, _skin(labels), color=SKIN_COLOR, opacity=0.08, smooth_shading=False)
    for name, surf in surfaces.items():
        add_patient_mesh(p, surf, color=MUSCLE_COLORS[_kind(name)], opacity=0.85)
    for name, parts in boxes.items():
        color = MUSCLE_COLORS[_kind(name)]
        for center, axes, half in parts:
            add_patient_mesh(p, obb_polydata(center, axes, half).extract_all_edges(),
                             color=color, line_width=2, smooth_shading=False)
            add_patient_mesh(p, pv.Line(center - half[0] * axes[0], center + half[0] * axes[0]),
                             color="black", line_width=3, smooth_shading=False)
    _legend(p, surfaces)
    _camera(p, labels, "front")
    return p
