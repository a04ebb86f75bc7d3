"""Checks of :func:`~pvcmf.filters.meshing.tetrahedralize`'s inputs and its region of interest.

The region of interest is a box, a distance to a bone segment (``scipy.ndimage``
Euclidean distance transform), a boolean mask or a callable on the image points; a box
also crops the image before the whole-image passes.
"""

from __future__ import annotations

import numbers

import numpy as np
import pyvista as pv
from scipy import ndimage

from ... import arrays
from .._checks import check_image_geometry

#: range of ``n_tets`` accepted (the count is calibrated within +-20 % from 5k to 500k)
N_TETS_RANGE = (1_000, 2_000_000)


def _check_image(labels, conforming):
    if not isinstance(labels, pv.ImageData):
        raise TypeError(
            f"labels must be a pyvista.ImageData label image, got {type(labels).__name__}"
        )
    check_image_geometry(labels, "labels")
    if not np.allclose(labels.direction_matrix, np.eye(3)):
        raise ValueError("labels must be axis aligned (identity direction_matrix)")
    tissue = arrays.require_array(labels, arrays.TISSUE, "point", producer="segment")
    if tissue.dtype.kind not in "iu":
        raise ValueError(
            f"labels: point array {arrays.TISSUE!r} must hold integer labels, "
            f"got dtype {tissue.dtype}"
        )
    muscle = None
    if arrays.MUSCLE in labels.point_data.keys():
        muscle = np.asarray(labels.point_data[arrays.MUSCLE])
        if muscle.dtype.kind not in "iu":
            raise ValueError(
                f"labels: point array {arrays.MUSCLE!r} must hold integer labels, "
                f"got dtype {muscle.dtype}"
            )
    elif conforming and np.any(tissue == arrays.MUSCLE_TISSUE):
        arrays.require_array(labels, arrays.MUSCLE, "point", producer="embed_muscles")
    return tissue, muscle


def _check_n_tets(n_tets):
    if isinstance(n_tets, bool) or not isinstance(n_tets, numbers.Integral):
        raise TypeError(f"n_tets must be an integer, got {type(n_tets).__name__} {n_tets!r}")
    lo, hi = N_TETS_RANGE
    if not lo <= n_tets <= hi:
        raise ValueError(f"n_tets must lie in [{lo}, {hi}], got {n_tets}")


def _roi_crop(labels, roi):
    """(z, y, x) slices of the image points within one voxel of a box ``roi`` (else None)."""
    if roi is None or callable(roi):
        return None
    arr = np.asarray(roi)
    if arr.shape != (6,) or arr.dtype == bool or arr.dtype.kind not in "iuf":
        return None
    box = arr.astype(float)
    if np.any(box[1::2] <= box[0::2]):
        return None  # _roi_mask raises
    crop = []
    for k in range(3):
        a = labels.origin[k] + labels.spacing[k] * np.arange(labels.dimensions[k])
        idx = np.flatnonzero((a >= box[2 * k]) & (a <= box[2 * k + 1]))
        if not len(idx):
            return None
        crop.append(slice(max(int(idx[0]) - 1, 0), min(int(idx[-1]) + 2, labels.dimensions[k])))
    return tuple(crop[::-1])


def _roi_mask(labels, roi, shape_zyx, crop=None):
    """Boolean (z, y, x) mask of the image points kept by ``roi`` (None: all).

    With ``crop`` (the slices of :func:`_roi_crop`, box rois only) the mask of the
    cropped image.
    """
    if roi is None:
        return None
    pts_axes = [
        labels.origin[k] + labels.spacing[k] * np.arange(labels.dimensions[k]) for k in range(3)
    ]
    if crop is not None:
        pts_axes = [a[crop[2 - k]] for k, a in enumerate(pts_axes)]
    if callable(roi):
        mask = np.asarray(roi(labels.points), dtype=bool)
        if mask.shape != (labels.n_points,):
            raise ValueError(
                f"roi callable must return a boolean array of shape ({labels.n_points},), "
                f"got shape {mask.shape}"
            )
        return mask.reshape(shape_zyx)
    arr = np.asarray(roi)
    if arr.dtype == bool:
        if arr.shape != (labels.n_points,):
            raise ValueError(
                f"roi mask must have shape ({labels.n_points},) (one per image point), "
                f"got {arr.shape}"
            )
        return arr.reshape(shape_zyx)
    if arr.shape == (6,):
        box = arr.astype(float)
        if np.any(box[1::2] <= box[0::2]):
            raise ValueError(f"roi box must be (xmin, xmax, ymin, ymax, zmin, zmax), got {roi}")
        inside = [(a >= box[2 * k]) & (a <= box[2 * k + 1]) for k, a in enumerate(pts_axes)]
        return inside[2][:, None, None] & inside[1][None, :, None] & inside[0][None, None, :]
    if arr.shape == (2,):
        bone_id, distance = int(arr[0]), float(arr[1])
        if distance <= 0:
            raise ValueError(f"roi distance must be > 0 mm, got {distance}")
        bone = arrays.require_array(labels, arrays.BONE, "point", dtype="iu", producer="segment")
        seg = bone.reshape(shape_zyx) == bone_id
        if not seg.any():
            raise ValueError(
                f"roi bone id {bone_id} not found in point array {arrays.BONE!r}; "
                f"ids present: {sorted(np.unique(bone).tolist())}"
            )
        sampling = np.asarray(labels.spacing)[::-1]
        dist = ndimage.distance_transform_edt(~seg, sampling=sampling)
        return dist <= distance
    raise ValueError(
        "roi must be None, a box (xmin, xmax, ymin, ymax, zmin, zmax), a (bone_id, distance) "
        f"pair, a boolean mask of length n_points or a callable; got {roi!r}"
    )

