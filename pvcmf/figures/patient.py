"""A virtual patient's skin (translucent), skull segments and the 12 facial muscles.

Surfaces are contoured from the truth label image of a :class:`pvcmf.datasets.Case`
(slightly smoothed binary masks, so the render shows anatomy rather than voxel steps).
Delegates to :func:`scipy.ndimage.gaussian_filter` (mask smoothing) and PyVista
(``ImageData.contour`` with flying edges, an off-screen :class:`pyvista.Plotter`).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays
from .face_views import add_patient_mesh

log = logging.getLogger(__name__)

__all__ = ["label_surface", "virtual_patient"]

SKIN_COLOR = "peachpuff"
BONE_COLORS = {arrays.CRANIUM: "ivory", arrays.MAXILLA: "lightskyblue",
               arrays.MANDIBLE: "palegreen"}
#: one colour per muscle kind (left and right alike)
MUSCLE_COLORS = {
    "orbicularis_oculi": "#d62728",
    "levator_labii_superioris_alaeque_nasi": "#9467bd",
    "levator_labii_superioris": "#ff7f0e",
    "masseter": "#8c564b",
    "zygomaticus_major": "#e377c2",
    "zygomaticus_minor": "#bcbd22",
}


def label_surface(image, mask, sigma=0.7):
    """Smooth surface of a boolean voxel mask of ``image`` (point order of the image).

    Parameters
    ----------
    image : pyvista.ImageData
        Geometry of the mask.
    mask : numpy.ndarray of bool
        One value per image point.
    sigma : float
        Gaussian smoothing of the mask in voxels before contouring at 0.5.

    Returns
    -------
    pyvista.PolyData
        Possibly empty.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> img = pv.ImageData(dimensions=(10, 10, 10))
    >>> m = np.linalg.norm(img.points - 4.5, axis=1) < 3
    >>> label_surface(img, m).n_points > 0
    True
    """
    dims = image.dimensions
    mask = np.asarray(mask, bool).reshape(dims[::-1])
    if not mask.any():
        return pv.PolyData()
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(0) - 3, 0)
    hi = np.minimum(idx.max(0) + 4, np.asarray(dims[::-1]))
    sub = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32)
    sub = np.pad(sub, 1)
    if sigma > 0:
        sub = ndimage.gaussian_filter(sub, sigma)
    spacing = np.asarray(image.spacing)
    origin = np.asarray(image.origin) + (lo[::-1] - 1) * spacing
    img = pv.ImageData(dimensions=sub.shape[::-1], spacing=spacing, origin=origin)
    img["m"] = sub.ravel()
    return img.contour([0.5], scalars="m", method="flying_edges")


def virtual_patient(case, *, window_size=(1200, 600), skin_opacity=0.25,
                    views=("front", "right"), off_screen=True):
    """Render a virtual patient: translucent skin, skull segments and coloured muscles.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        A virtual patient (its ``truth`` labels are drawn).
    window_size : (int, int)
        Pixels.
    skin_opacity : float
        Opacity of the skin, in [0, 1].
    views : sequence of {'front', 'right', 'left', 'oblique'}
        One subplot per view.
    off_screen : bool
        Build the plotter off screen (default).

    Returns
    -------
    pyvista.Plotter

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.figures.patient import virtual_patient
    >>> pl = virtual_patient(pvcmf.datasets.phantom(1, spacing=3.0), views=("front",))
    >>> pl.close()
    """
    if not 0.0 <= float(skin_opacity) <= 1.0:
        raise ValueError(f"skin_opacity must be in [0, 1], got {skin_opacity}")
    directions = {"front": (0.0, 1.0, 0.0), "right": (-1.0, 0.0, 0.0),
                  "left": (1.0, 0.0, 0.0), "oblique": (-0.8, 1.0, 0.25)}
    bad = [v for v in views if v not in directions]
    if bad or not views:
        raise ValueError(f"views must be a non-empty subset of {sorted(directions)}, got {views}")
    truth = case.truth
    tissue = arrays.require_array(truth, arrays.TISSUE, "point", dtype="u")
    bone = arrays.require_array(truth, arrays.BONE, "point", dtype="u")
    muscle = arrays.require_array(truth, arrays.MUSCLE, "point", dtype="u")
    # skin: everything that is not air, with internal air cavities filled
    head = ndimage.binary_fill_holes((tissue != arrays.AIR).reshape(truth.dimensions[::-1]))
    skin = label_surface(truth, head.ravel(), sigma=1.0)
    bones = {b: label_surface(truth, bone == b, sigma=0.6) for b in BONE_COLORS}
    muscles = {name: label_surface(truth, muscle == mid, sigma=0.6)
               for name, mid in arrays.MUSCLE_IDS.items()}

    pl = pv.Plotter(shape=(1, len(views)), window_size=list(window_size),
                    off_screen=off_screen, border=False)
    # drawn in the display frame (x -> -x) as a photograph: the patient's right on the
    # viewer's left from the front, the face toward the viewer's right in the right view
    flip = np.array([-1.0, 1.0, 1.0])
    center = np.asarray(skin.center) * flip
    size = float(np.linalg.norm(np.asarray(skin.bounds).reshape(3, 2)[:, 1]
                                - np.asarray(skin.bounds).reshape(3, 2)[:, 0]))
    for i, view in enumerate(views):
        pl.subplot(0, i)
        pl.set_background("white")
        for b, surf in bones.items():
            if surf.n_points:
                add_patient_mesh(pl, surf, color=BONE_COLORS[b], specular=0.2)
        for name, surf in muscles.items():
            if surf.n_points:
                kind = name.rsplit("_", 1)[0]
                add_patient_mesh(pl, surf, color=MUSCLE_COLORS[kind])
        add_patient_mesh(pl, skin, color=SKIN_COLOR, opacity=skin_opacity, specular=0.1)
        d = np.asarray(directions[view], float) * flip  # the camera side, display frame
        d /= np.linalg.norm(d)
        pl.camera_position = [tuple(center + 2.2 * size * d), tuple(center), (0.0, 0.0, 1.0)]
        pl.camera.zoom(1.25)
        pl.add_text(f"{case.name}: {view}", font_size=10, color="black")
    return pl
