"""The skin of a prediction: the whole head, moved where the face model reaches.

:func:`predict_skin` takes the head's skin (:func:`pvcmf.filters.skin.head_skin`: the
whole head as the scan has it, open where its field of view ends), keeps a quarter of the
triangles beyond :func:`transfer_reach` of the model's box (they do not move:
:func:`pvcmf.filters.skin.coarsen_outside`), and carries the solved mesh's displacement
onto the rest with :class:`pvcmf.filters.surface_mapping.Transfer` (zero farther out, as
the transfer itself is beyond ``2 band``; the band is the mesh's,
:func:`pvcmf.filters.surface_mapping.mesh_band`: a coarse mesh models the skin farther
from its surface). Skin on bare teeth or bone is not modelled
(:func:`pvcmf.filters.meshing.skin_fit.on_hard_tissue`); the crumple metric
(:func:`pvcmf.filters.surface_mapping.crumple_metric`) is taken over the modelled skin
that is not on a cut of the scan. Where the scan cut the head (flat: the labels'
``arrays.SCAN_CUTS``; by its round field of view: ``arrays.SCAN_FOV``), the skin points
on the cut get ``arrays.SKIN_CUT`` = 1 (:func:`pvcmf.filters.field_of_view.on_scan_cuts`):
the scan's edge, not the patient's skin, which the figures draw apart and the crumple
metric leaves out (its sharp rim is no crumple of the face).
"""

from __future__ import annotations

import logging

import numpy as np

from .. import arrays
from .field_of_view import on_scan_cuts
from .meshing.skin_fit import DEFAULT_REACH, on_hard_tissue
from .skin import coarsen_outside, head_skin, sub_surface
from .surface_mapping import DEFAULT_BAND, Transfer, crumple_metric, mesh_band

log = logging.getLogger(__name__)

__all__ = ["TRANSFER_REACH", "FAR_REDUCTION", "SKIN_SUMMARY", "near_box", "predict_skin",
           "transfer_reach"]

#: the crumple metric's fields that go to the predicted skin's field data
SKIN_SUMMARY = (arrays.SKIN_MODELLED_POINTS, arrays.CRUMPLE_EDGES, arrays.CRUMPLE_VIOLATIONS,
                arrays.CRUMPLE_MAX_RATIO)

#: :func:`transfer_reach` of the smallest band (the skin drawn without a solved mesh)
TRANSFER_REACH = 2 * DEFAULT_BAND + DEFAULT_REACH + 1.0
#: share of the skin's triangles beyond TRANSFER_REACH removed (it does not move; drawn)
FAR_REDUCTION = 0.75


def near_box(points, box, grow):
    """Points within ``box`` grown by ``grow`` mm (all points without a box).

    Examples
    --------
    >>> near_box([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]], (-1, 1, -1, 1, -1, 1), 2.0).tolist()
    [True, False]
    """
    p = np.asarray(points)
    if box is None:
        return np.ones(len(p), dtype=bool)
    b = np.asarray(box, dtype=float) + float(grow) * np.tile([-1.0, 1.0], 3)
    return ((p >= b[0::2]) & (p <= b[1::2])).all(axis=1)


def transfer_reach(band):
    """mm beyond the model's box within which the skin takes a transfer of band ``band``:
    beyond it the mesh (within the skin fit's ``DEFAULT_REACH`` of the box) is farther
    than ``2 band``, where the transfer is zero.

    >>> transfer_reach(4.0)
    13.0
    """
    return 2.0 * float(band) + DEFAULT_REACH + 1.0


def predict_skin(labels, post, pre=None, box=None):
    """Pre-operative skin (``pre`` or :func:`head_skin`) and, with a solved mesh, the
    predicted skin: :class:`~pvcmf.filters.surface_mapping.Transfer` of the mesh
    displacement onto the skin within :func:`transfer_reach` of the box (farther, zero
    displacement: the transfer is zero there anyway, and the skin there keeps a quarter of
    its triangles, :data:`FAR_REDUCTION`). Skin beyond the transfer's band or on
    bare teeth or bone is not modelled (``arrays.SKIN_MODELLED``); the crumple metric over
    the modelled skin goes to the predicted skin's field data (``SKIN_SUMMARY``).

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image (point array ``tissue``).
    post : pyvista.UnstructuredGrid or None
        Solved mesh with point array ``displacement``; None gives the skin only.
    pre : pyvista.PolyData, optional
        The skin to use instead of :func:`head_skin` of ``labels`` and ``box``.
    box : tuple of 6 floats, optional
        The model's box (:func:`pvcmf.filters.model_region.face_box`).

    Returns
    -------
    (pyvista.PolyData, pyvista.PolyData or None)
        The pre-operative skin (with ``displacement`` and ``skin_modelled`` given ``post``;
        ``skin_cut`` where the labels have ``scan_cuts``) and the predicted skin (None
        without ``post``).
    """
    pre = head_skin(labels, box) if pre is None else pre
    band = DEFAULT_BAND if post is None else mesh_band(post)
    near = near_box(pre.points, box, transfer_reach(band))
    pre = coarsen_outside(pre, near, FAR_REDUCTION)
    if arrays.SCAN_CUTS in labels.field_data or arrays.SCAN_FOV in labels.field_data:
        pre.point_data[arrays.SKIN_CUT] = on_scan_cuts(pre.points, labels).astype(np.uint8)
    if post is None:
        return pre, None
    near = near_box(pre.points, box, transfer_reach(band))
    tri = pre.faces.reshape(-1, 4)[:, 1:]
    part, ids = sub_surface(pre, tri[near[tri].all(axis=1)])
    u_nodes = np.asarray(post[arrays.DISPLACEMENT], dtype=np.float64)
    transfer = Transfer(post, part, band=band)
    disp_part = transfer(u_nodes)
    modelled_part = transfer.modelled & ~on_hard_tissue(part.points, labels)
    checked = modelled_part  # the scan's edge is not the patient's skin: no crumple
    if arrays.SKIN_CUT in pre.point_data:
        checked = checked & (np.asarray(pre[arrays.SKIN_CUT])[ids] == 0)
    metric = crumple_metric(part, disp_part, post, u_nodes, transfer=transfer,
                            modelled=checked)
    metric[arrays.SKIN_MODELLED_POINTS] = int(modelled_part.sum())
    log.info("skin: %d points (%d within reach of the model, %d modelled), %d edges stretched "
             "beyond the mesh's gradients (max ratio %.3g)", pre.n_points, len(ids),
             metric[arrays.SKIN_MODELLED_POINTS], metric[arrays.CRUMPLE_VIOLATIONS],
             metric[arrays.CRUMPLE_MAX_RATIO])
    disp = np.zeros((pre.n_points, 3))
    disp[ids] = disp_part
    modelled = np.zeros(pre.n_points, dtype=np.uint8)
    modelled[ids] = modelled_part
    pre.point_data[arrays.DISPLACEMENT] = disp
    pre.point_data[arrays.SKIN_MODELLED] = modelled
    moved = pre.copy()
    moved.points = np.asarray(pre.points) + disp
    for name in SKIN_SUMMARY:
        moved.field_data[name] = np.array([metric[name]])
    if arrays.SKIN_CUT in pre.point_data:
        moved.field_data[arrays.SKIN_CUT_POINTS] = np.array([int(pre[arrays.SKIN_CUT].sum())])
    return pre, moved
