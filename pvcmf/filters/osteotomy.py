"""Osteotomy: cut the bone label into the plan's segments and move them rigidly.

Paper 000 Fig. 5 shows each patient's bone segments before (white) and after (green)
the planned move. Two filters:

* :func:`cut_bones` -- label image -> label image whose ``bone`` array holds each
  planned segment (maxilla by a Le Fort I plane, mandible by bilateral sagittal split
  planes, given as half-spaces in the plan; or the label the image already has);
* :func:`move_bones` -- label image -> the post-operative skeleton. By default a
  :class:`pyvista.MultiBlock` of one closed PolyData surface per bone segment, moved
  rigidly (``output="surface"``); or a label image with the moved segments resampled
  (``output="labels"``, nearest neighbour through the inverse transform).

:func:`segment_transforms` gives the 4x4 patient-frame matrix of every moved segment
(pivot = the segment's voxel centroid unless the plan names one); boundary conditions
(:func:`pvcmf.filters.apply_plan`) use the same matrices.

Delegates to numpy (half-space tests, rigid transforms), :func:`scipy.ndimage.gaussian_filter`
and :func:`scipy.ndimage.map_coordinates` (resampling), and VTK's flying edges
(:meth:`pyvista.ImageData.contour`) for the segment surfaces.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..arrays import voxel_points
from ..plan import Plan
from .bone_segments import find_jaws, segment_volumes
from .face_axes import plan_axes
from .morphology import _box, _smoothing_margin

log = logging.getLogger(__name__)

__all__ = ["cut_bones", "move_bones", "segment_transforms", "voxel_points"]


def _check_inputs(labels, plan, func):
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan, got {type(plan).__name__}")
    return np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu",
                                           ncomp=1, producer=f"segment (needed by {func})"))


def cut_bones(labels, plan, *, keep_labelled=True, progress_bar=False):
    """Label each planned bone segment in the ``bone`` array of a label image.

    An osteotomy with cut planes (:attr:`pvcmf.plan.Osteotomy.cut`) takes every bone
    voxel on the side all its plane normals point to (the planes override the anatomy);
    one without planes keeps the segment the image already labels (the virtual patients
    label cranium, maxilla and mandible) or, where the image does not label it, finds it
    from the anatomy (:func:`pvcmf.filters.bone_segments.find_jaws`: the mandible apart at
    the joints and the occlusion, the maxilla by a Le Fort I level).

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with a point array ``bone`` (uint8, 0 = no bone).
    plan : pvcmf.Plan
        The surgical plan.
    keep_labelled : bool, default True
        With cut planes, only re-label voxels that are not already another planned
        segment's (so a Le Fort I plane does not steal an already labelled mandible).
    progress_bar : bool, default False
        Unused (the step takes milliseconds); accepted for a uniform pipeline signature.

    Returns
    -------
    pyvista.ImageData
        A copy of ``labels`` with the new ``bone`` array.

    Raises
    ------
    TypeError
        If ``labels`` is not an ImageData or ``plan`` not a Plan.
    ValueError
        If ``bone`` is missing or a segment cannot be found.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.plan import Plan, Osteotomy
    >>> from pvcmf.filters import cut_bones
    >>> img = pv.ImageData(dimensions=(10, 10, 10))
    >>> img[arrays.BONE] = np.full(1000, arrays.CRANIUM, dtype=np.uint8)
    >>> plan = Plan((Osteotomy("maxilla", cut=(((0, 0, 4.5), (0, 0, -1)),)),))
    >>> int((cut_bones(img, plan)[arrays.BONE] == arrays.MAXILLA).sum())
    500
    """
    bone = _check_inputs(labels, plan, "cut_bones")
    missing = [o.segment for o in plan.osteotomies
               if not o.cut and not np.any(bone == o.segment_id)]
    jaws = None
    if missing and arrays.TISSUE in labels.point_data:
        log.info("cut_bones: %s not labelled and no cut planes: found from the anatomy",
                 ", ".join(missing))
        try:
            jaws = find_jaws(labels, progress_bar=progress_bar)
            found = np.asarray(jaws[arrays.BONE])
        except ValueError as err:
            have = sorted(arrays.BONE_NAMES[int(b)] for b in np.unique(bone) if b > 0)
            raise ValueError(
                f"the plan moves segment {missing[0]!r} without cut planes, the labels have "
                f"only {have} and the segment could not be found from the anatomy ({err}): "
                "label it, or give the osteotomy cut planes") from None
        wanted = [o.segment_id for o in plan.osteotomies if o.segment in missing]
        bone = np.where(np.isin(found, wanted), found, bone)
    out = labels.copy()
    new = bone.astype(np.uint8, copy=True)
    planned = {o.segment_id for o in plan.osteotomies if not o.cut}
    for o in plan.osteotomies:
        if not o.cut:
            continue
        candidates = new > 0
        if keep_labelled:
            candidates &= ~np.isin(new, list(planned - {o.segment_id}))
        ids = np.flatnonzero(candidates)
        points = voxel_points(labels, ids)
        keep = np.ones(len(ids), dtype=bool)
        for p, n in o.cut:
            keep &= (points - np.asarray(p)) @ np.asarray(n) >= 0
        inside = np.zeros(len(new), dtype=bool)
        inside[ids[keep]] = True
        new[inside] = o.segment_id
        planned.add(o.segment_id)
        log.info("cut_bones: %s = %d voxels inside %d plane(s)", o.segment, int(inside.sum()),
                 len(o.cut))
    out[arrays.BONE] = new
    for name in (arrays.ARCH_PITCH, arrays.ARCH_NORMAL, arrays.ARCH_SPAN,  # the jaws' pose
                 arrays.MIRROR_NORMAL):
        if jaws is not None and name in jaws.field_data:
            out.field_data[name] = np.array(jaws.field_data[name])
    if missing or any(o.cut for o in plan.osteotomies):  # else every segment is labelled
        plan.check_segments(out)
    if log.isEnabledFor(logging.INFO):  # the volumes take a pass over the image each
        log.info("cut_bones: segments (mL) %s", ", ".join(
            f"{k} {v:.1f}" for k, v in segment_volumes(out).items()))
    return out


def segment_transforms(labels, plan):
    """Return ``{segment id: 4x4 matrix}`` for the plan's segments in ``labels``.

    The pivot of an osteotomy without one is the centroid of its voxels in the ``bone``
    array (cut the image first with :func:`cut_bones` when the plan has cut planes). The
    moves are turned into the image's axes from the plan's ``axes``
    (:func:`~pvcmf.filters.face_axes.plan_axes`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.plan import TABLE_II
    >>> from pvcmf.filters.osteotomy import segment_transforms
    >>> img = pv.ImageData(dimensions=(4, 4, 4))
    >>> img[arrays.BONE] = np.full(64, arrays.MANDIBLE, dtype=np.uint8)
    >>> sorted(segment_transforms(img, TABLE_II[4]))
    [3]
    """
    bone = _check_inputs(labels, plan, "segment_transforms")
    ids = {o.segment_id: np.flatnonzero(bone == o.segment_id) for o in plan.osteotomies}
    if any(o.cut for o in plan.osteotomies) or not all(v.size for v in ids.values()):
        plan.check_segments(labels)  # (a plan without cut planes needs its segments only)
    axes = plan_axes(labels, plan)
    out = {}
    for o in plan.osteotomies:
        centroid = None
        if o.pivot is None:
            centroid = voxel_points(labels, ids[o.segment_id]).mean(axis=0)
        out[o.segment_id] = o.matrix(centroid, axes=axes)
    return out


def _segment_surface(labels, mask, smooth):
    """Closed surface around ``mask`` (flying edges on a lightly smoothed indicator), made on
    the mask's box with a margin wider than the smoothing kernel: the same points as on the
    whole image, in a fraction of the time."""
    from scipy import ndimage

    dims = tuple(labels.dimensions)
    full = mask.reshape(dims, order="F")
    box = _box(full, _smoothing_margin(smooth)) if full.any() else tuple(
        slice(0, n) for n in dims)
    lo = [b.start for b in box]
    vol = full[box].astype(np.float32)
    if smooth > 0:
        vol = ndimage.gaussian_filter(vol, smooth, mode="constant")
    padded = np.pad(vol, 1)  # closes segments touching the image border
    img = pv.ImageData(dimensions=padded.shape, spacing=labels.spacing,
                       origin=np.asarray(labels.origin) - np.asarray(labels.spacing))
    img.extent = tuple(v for a, n in zip(lo, padded.shape) for v in (a, a + n - 1))
    img["m"] = padded.ravel(order="F")
    surf = img.contour([0.5], scalars="m", method="flying_edges")
    surf.clear_data()
    return surf


def move_bones(labels, plan, *, output="surface", smooth=0.6, progress_bar=False):
    """Return the post-operative skeleton: every planned segment moved rigidly.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``bone`` (and the planned segments, see :func:`cut_bones`;
        cut planes in the plan are applied here too).
    plan : pvcmf.Plan
        The surgical plan (pivots default to segment centroids).
    output : {'surface', 'labels'}, default 'surface'
        ``'surface'``: a :class:`pyvista.MultiBlock` with one PolyData per bone segment
        present (keys ``'cranium'``, ``'maxilla'``, ``'mandible'``), moved ones rigidly
        transformed, each with point array ``displacement`` (mm) and field data
        ``moved`` (1/0) and ``matrix`` (4x4). ``'labels'``: a copy of ``labels`` whose
        ``bone`` array is the post-operative label (moved segments resampled by nearest
        neighbour through the inverse transform, drawn over the unmoved bone).
    smooth : float, default 0.6
        Gaussian sigma in voxels applied to each segment's indicator before contouring
        (``output='surface'`` only); 0 gives the voxel staircase.
    progress_bar : bool, default False
        Unused (sub-second step); accepted for a uniform pipeline signature.

    Returns
    -------
    pyvista.MultiBlock or pyvista.ImageData

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.plan import Plan, Osteotomy
    >>> from pvcmf.filters import move_bones
    >>> img = pv.ImageData(dimensions=(12, 12, 12))
    >>> bone = np.zeros(img.n_points, dtype=np.uint8)
    >>> bone[(np.abs(img.points - 5.5) < 3).all(axis=1)] = arrays.MANDIBLE
    >>> img[arrays.BONE] = bone
    >>> post = move_bones(img, Plan((Osteotomy("mandible", (0, 0, 2.0)),)))
    >>> np.round(post["mandible"]["displacement"][0], 6).tolist()
    [0.0, 2.0, 0.0]
    """
    if output not in ("surface", "labels"):
        raise ValueError(f"output must be 'surface' or 'labels', got {output!r}")
    if not np.isfinite(smooth) or smooth < 0:
        raise ValueError(f"smooth must be a finite number >= 0 (voxels), got {smooth!r}")
    labels = cut_bones(labels, plan)
    transforms = segment_transforms(labels, plan)
    bone = np.asarray(labels[arrays.BONE])
    if output == "labels":
        return _move_labels(labels, bone, transforms)
    blocks = pv.MultiBlock()
    for value in np.unique(bone):
        if value == arrays.BONE_NONE:
            continue
        surf = _segment_surface(labels, bone == value, smooth)
        matrix = transforms.get(int(value), np.eye(4))
        pre = np.asarray(surf.points, dtype=float)
        post = pre @ matrix[:3, :3].T + matrix[:3, 3]
        surf.points = post
        surf.point_data[arrays.DISPLACEMENT] = post - pre
        surf.field_data["moved"] = np.array([int(value) in transforms], dtype=np.int8)
        surf.field_data["matrix"] = matrix.ravel()
        blocks[arrays.BONE_NAMES.get(int(value), f"bone_{int(value)}")] = surf
    log.info("move_bones: %d segment surfaces, %d moved", len(blocks), len(transforms))
    return blocks


def _move_labels(labels, bone, transforms):
    """Post-operative bone label image (nearest neighbour through inverse transforms)."""
    from scipy import ndimage

    dims = tuple(labels.dimensions)
    vol = bone.reshape(dims, order="F")
    new = np.where(np.isin(bone, list(transforms)), arrays.BONE_NONE, bone).astype(np.uint8)
    points = voxel_points(labels, np.arange(labels.n_points))
    origin, spacing = np.asarray(labels.origin), np.asarray(labels.spacing)
    for seg, matrix in transforms.items():
        inv = np.linalg.inv(matrix)
        src = points @ inv[:3, :3].T + inv[:3, 3]
        idx = ((src - origin) / spacing).T
        moved = ndimage.map_coordinates((vol == seg).astype(np.uint8), idx, order=0,
                                        mode="constant", cval=0).astype(bool)
        new[moved] = seg
    out = labels.copy()
    out[arrays.BONE] = new
    return out
