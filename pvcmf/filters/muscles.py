"""Embed the facial muscles of an atlas into a label image (paper 000, sec. II, Fig. 2b).

The atlas muscles (closed surfaces, :mod:`pvcmf.atlas`) are carried to the patient by a
3-D thin-plate spline through landmarks (:mod:`pvcmf.tps`, scipy ``RBFInterpolator``) —
either the patient's landmarks or landmarks found automatically by registering the
atlas's skin and skull to the patient's (:meth:`pvcmf.atlas.Atlas.fit`) — refined by
default so that the atlas skin and skull also land on the patient's
(:meth:`pvcmf.atlas.Atlas.register`). The warped
surfaces are rasterised with VTK's ``vtkPolyDataToImageStencil`` (PyVista's
``voxelize_binary_mask``) on the part of the image each muscle covers, and written as
``muscle`` ids and ``tissue = MUSCLE_TISSUE``, but only where the image holds soft tissue:
a muscle never replaces air, bone, teeth or intracranial voxels.
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import pyvista as pv

from .. import arrays
from .. import atlas as atlas_mod
from ..progress import Progress

log = logging.getLogger(__name__)


class MuscleOutsideWarning(UserWarning):
    """A warped muscle falls mostly outside the soft tissue (or the image)."""


#: least share of a muscle's rasterised voxels that must be soft tissue before a warning
MIN_SOFT_FRACTION = 0.5


def _index_frame(image):
    """(origin, R, spacing, offset) such that ijk = R^T (p - origin) / spacing - offset."""
    origin = np.asarray(image.origin, dtype=float)
    spacing = np.asarray(image.spacing, dtype=float)
    direction = np.asarray(image.direction_matrix, dtype=float)
    offset = np.asarray(image.offset, dtype=float)
    return origin, direction, spacing, offset


def to_index(image, points):
    """Continuous (i, j, k) index coordinates of world points in an ImageData."""
    origin, direction, spacing, offset = _index_frame(image)
    return (np.asarray(points, dtype=float) - origin) @ direction / spacing - offset


def rasterize_surface(image, surface):
    """Boolean mask (``image.n_points``) of the image points inside a closed surface.

    Only the sub-block of the image around the surface is voxelised (VTK's
    ``vtkPolyDataToImageStencil`` through ``PolyData.voxelize_binary_mask``), so the cost
    scales with the muscle, not with the image.

    Parameters
    ----------
    image : pyvista.ImageData
        Reference grid (any origin, spacing, offset and direction matrix).
    surface : pyvista.PolyData
        Closed triangulated surface in world coordinates.

    Returns
    -------
    numpy.ndarray of bool

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.filters.muscles import rasterize_surface
    >>> img = pv.ImageData(dimensions=(21, 21, 21), origin=(-10, -10, -10))
    >>> mask = rasterize_surface(img, pv.Sphere(radius=5.5, theta_resolution=60, phi_resolution=60))
    >>> int(mask.sum())  # the 739 lattice points with |p| < 5.5
    739
    """
    mask = np.zeros(int(np.prod(image.dimensions)), dtype=bool)
    mask[_inside_ids(image, surface)] = True
    return mask


def _inside_ids(image, surface):
    """Point ids (VTK order, increasing) of the image points inside a closed surface: the
    voxelised sub-block around it, so that the cost scales with the surface's box."""
    dims = np.asarray(image.dimensions)
    surf = surface.triangulate() if not surface.is_all_triangles else surface
    if surf.n_points == 0:
        return np.zeros(0, dtype=np.int64)
    ijk = to_index(image, surf.points)
    lo = np.maximum(np.floor(ijk.min(axis=0)).astype(int) - 1, 0)
    hi = np.minimum(np.ceil(ijk.max(axis=0)).astype(int) + 1, dims - 1)
    if (hi < lo).any():
        return np.zeros(0, dtype=np.int64)
    sub_dims = hi - lo + 1
    ref = pv.ImageData(dimensions=sub_dims, origin=lo.astype(float), spacing=(1.0, 1.0, 1.0))
    local = pv.PolyData(ijk, surf.faces)
    sub = local.voxelize_binary_mask(reference_volume=ref)
    # "mask": the name PyVista's voxelize_binary_mask gives its output (x fastest)
    inside = np.flatnonzero(np.asarray(sub.point_data["mask"]))
    i, j, k = np.unravel_index(inside, sub_dims, order="F")
    return np.ravel_multi_index((i + lo[0], j + lo[1], k + lo[2]), dims, order="F")


def _soft_mask(tissue):
    return np.isin(tissue, arrays.SOFT_LABELS)


def embed_muscles(
    labels,
    atlas=None,
    landmarks=None,
    *,
    refine=True,
    replace=True,
    strict=False,
    min_soft_fraction=MIN_SOFT_FRACTION,
    progress_bar=False,
):
    """Embed atlas muscles, warped to the patient, into a tissue label image.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with point array ``tissue`` (uint8, :data:`pvcmf.arrays.TISSUE_LABELS`),
        e.g. from ``segment`` (all soft tissue ``FAT``) or a phantom's truth.
    atlas : pvcmf.atlas.Atlas, optional
        Muscle atlas; :func:`pvcmf.atlas.default` when omitted.
    landmarks : dict[str, array_like], optional
        Patient landmarks ``{name: (x, y, z)}`` in mm with (at least) every name of
        ``atlas.landmarks``; extra names are ignored. When omitted, landmarks are found
        automatically by :meth:`pvcmf.atlas.Atlas.fit` (similarity + non-rigid registration
        of the atlas skin and skull to the patient's), so a CT needs no hand work.
    refine : bool
        ``True`` (default): the spline keeps the landmarks exact and also brings the
        atlas skin and skull onto the patient's (:meth:`pvcmf.atlas.Atlas.register`), so
        the soft-tissue thickness between landmarks follows the patient. ``False``: the
        landmark spline alone (paper 000), also used for an atlas without skin and skull
        surfaces; always refined without ``landmarks``.
    replace : bool
        Voxels that already carry a ``muscle`` id go back to ``FAT`` before embedding, so
        the result holds the atlas muscles only (voxels labelled ``MUSCLE_TISSUE`` without
        a muscle id, e.g. from ``classify_tissue``, are kept). ``False`` keeps old ids where
        no atlas muscle lands.
    strict : bool
        Raise instead of warn when a muscle falls mostly outside the soft tissue.
    min_soft_fraction : float
        Least share (0-1) of a muscle's voxels that must lie in soft tissue (and of its
        surface inside the image) before a :class:`MuscleOutsideWarning` names it.
    progress_bar : bool
        Show the steps, one per muscle (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.ImageData
        A copy with point arrays ``muscle`` (uint8, id ``arrays.MUSCLE_IDS[name]``) and
        ``tissue`` (``MUSCLE_TISSUE`` where a muscle covers soft tissue). Where two warped
        muscles overlap, the later in :data:`pvcmf.arrays.MUSCLES` order wins (as in the
        virtual patients' truth). The warped
        landmarks used are stored as field data ``landmark_names`` / ``landmark_points``.

    Raises
    ------
    ValueError
        On a missing/ill-typed ``tissue`` array, missing landmark names (listed), NaN or
        coincident landmarks, or (``strict=True``) a muscle outside the soft tissue.
    TypeError
        If ``labels`` is not an ImageData.

    Warns
    -----
    MuscleOutsideWarning
        Naming every muscle that falls mostly outside the soft tissue or the image.

    Examples
    --------
    >>> import pvcmf
    >>> case = pvcmf.datasets.phantom(patient=1, spacing=3.0)  # doctest: +SKIP
    >>> out = case.truth.cmf.embed_muscles(landmarks=case.landmarks)  # doctest: +SKIP
    >>> sorted(set(out["muscle"])) == list(range(13))  # doctest: +SKIP
    True
    """
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    tissue = arrays.require_array(
        labels, arrays.TISSUE, "point", dtype="iu", ncomp=1, producer="segment"
    )
    if not 0 <= min_soft_fraction <= 1:
        raise ValueError(f"min_soft_fraction must be in [0, 1], got {min_soft_fraction!r}")
    if atlas is None:
        atlas = atlas_mod.default()
    if not isinstance(atlas, atlas_mod.Atlas):
        raise TypeError(f"atlas must be a pvcmf.atlas.Atlas, got {type(atlas).__name__}")
    if landmarks is not None and not isinstance(landmarks, dict):
        raise TypeError(
            f"landmarks must be a dict name -> (x, y, z) or None, got {type(landmarks).__name__}"
        )
    t0 = time.perf_counter()
    with Progress(total=len(arrays.MUSCLES) + 1, desc="embed_muscles", enabled=progress_bar,
                  logger=log) as bar:
        warped = _warp_atlas(labels, atlas, landmarks, refine, progress_bar)
        bar.step("atlas warped to the patient")
        new_tissue, muscle = _start_labels(labels, tissue, replace)
        assigned, problems = _paint_muscles(labels, warped, new_tissue, muscle,
                                            min_soft_fraction, bar)
    if problems:
        msg = (
            "muscle(s) falling mostly outside the soft tissue (check landmarks or "
            "segmentation): " + "; ".join(problems)
        )
        if strict:
            raise ValueError(msg)
        warnings.warn(msg, MuscleOutsideWarning, stacklevel=2)
        log.warning(msg)

    out = labels.copy()
    out.point_data[arrays.TISSUE] = new_tissue
    out.point_data[arrays.MUSCLE] = muscle
    names = list(warped.landmarks)
    out.field_data[arrays.LANDMARK_NAMES] = np.array(names)
    out.field_data[arrays.LANDMARK_POINTS] = np.array([warped.landmarks[n] for n in names])
    log.info(
        "embed_muscles: %d muscle voxels in %.2f s", int(assigned.sum()), time.perf_counter() - t0
    )
    return out


def _warp_atlas(labels, atlas, landmarks, refine, progress_bar):
    """The atlas warped to the patient: by the landmark spline, refined on the surfaces."""
    can_refine = atlas.skin is not None and atlas.skull is not None
    if landmarks is not None and not (refine and can_refine):
        return atlas.warp(landmarks)  # validates names, NaN, coincident points
    if landmarks is not None:  # fail fast on bad landmarks, before any contouring
        atlas.transform_to(landmarks)
    transform, landmarks, info = atlas.register(labels, landmarks, progress_bar=progress_bar)
    warped = atlas.apply(transform, surfaces=False)
    log.info(
        "embed_muscles: registration in %.2f s (surface rms %.2f mm)",
        info.seconds,
        info.rms_refined,
    )
    return warped


def _start_labels(labels, tissue, replace):
    """Copies of the tissue and muscle labels to paint into (old muscles cleared on ``replace``)."""
    old = labels.point_data.get(arrays.MUSCLE)
    new_tissue = np.array(tissue, dtype=np.uint8, copy=True)
    if old is None:
        return new_tissue, np.zeros(tissue.shape, dtype=np.uint8)
    old = np.asarray(old)
    if old.shape != tissue.shape:
        raise ValueError(
            f"point array {arrays.MUSCLE!r} must have shape {tissue.shape}, got {old.shape}"
        )
    muscle = np.array(old, dtype=np.uint8, copy=True)
    if replace:
        had = muscle != arrays.MUSCLE_NONE
        new_tissue[had & (new_tissue == arrays.MUSCLE_TISSUE)] = arrays.FAT
        muscle[:] = arrays.MUSCLE_NONE
    return new_tissue, muscle


def _paint_muscles(labels, warped, new_tissue, muscle, min_soft_fraction, bar):
    """Rasterise every warped muscle into ``new_tissue`` and ``muscle`` (in place).

    Returns the voxels painted and the problems (muscles mostly outside the soft tissue
    or the image).
    """
    soft = _soft_mask(new_tissue)
    assigned = np.zeros(new_tissue.shape, dtype=bool)
    dims = np.asarray(labels.dimensions)
    problems = []
    for name in arrays.MUSCLES:  # on each muscle's voxels, not the whole image
        surf = warped.muscles.get(name)
        if surf is None:
            continue
        inside = _inside_ids(labels, surf)
        n_in = len(inside)
        in_soft = inside[soft[inside]]
        n_soft = len(in_soft)
        share_soft = n_soft / n_in if n_in else 0.0
        ijk = to_index(labels, surf.points)
        share_image = float(np.mean(((ijk >= -0.5) & (ijk <= dims - 0.5)).all(axis=1)))
        if n_in == 0 or share_soft < min_soft_fraction or share_image < min_soft_fraction:
            problems.append(
                f"{name}: {100 * share_soft:.0f}% of its {n_in} voxels in soft tissue, "
                f"{100 * share_image:.0f}% of its surface inside the image"
            )
        overlap = int(np.count_nonzero(assigned[in_soft]))
        if overlap:
            log.debug("%s overlaps earlier muscles in %d voxels", name, overlap)
        muscle[in_soft] = arrays.MUSCLE_IDS[name]
        new_tissue[in_soft] = arrays.MUSCLE_TISSUE
        assigned[in_soft] = True
        bar.step(f"{name}: {n_in} voxels ({n_soft} in soft tissue)")
    return assigned, problems
