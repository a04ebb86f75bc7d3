"""Input checks shared by the filters: finite points and a usable image geometry.

Every check raises ``ValueError`` naming the parameter, what is expected and what was
found, before a library downstream turns the bad value into an internal error or a
silently wrong number (a NaN point poisons a mean; a zero spacing asks for terabytes).
Pure numpy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["check_finite_points", "check_image_geometry", "MAX_COORDINATE"]

#: largest |coordinate| (mm) accepted for a point: beyond it squared distances overflow
#: or lose every digit, and no head is that large
MAX_COORDINATE = 1e6


def check_finite_points(dataset, name):
    """Raise ``ValueError`` naming ``name`` when some points of ``dataset`` are NaN or inf.

    A single non-finite point poisons every mean, bounding box and closest-point search;
    filters refuse such data instead of returning silently wrong numbers. Drop the points
    first if they are known to be garbage, e.g. ``dataset.extract_points(np.isfinite(
    dataset.points).all(axis=1))``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters._checks import check_finite_points
    >>> s = pv.Sphere(); s.points[0] = np.nan
    >>> check_finite_points(s, "actual")
    Traceback (most recent call last):
    ...
    ValueError: actual must have finite point coordinates, got 1 of 842 points with NaN/inf (e.g. point 0)
    """
    pts = np.asarray(dataset.points)
    if not pts.size:
        return
    bad = ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{name} must have finite point coordinates, got {int(bad.sum())} of {len(pts)} "
            f"points with NaN/inf (e.g. point {int(np.flatnonzero(bad)[0])})"
        )
    far = (np.abs(pts) > MAX_COORDINATE).any(axis=1)
    if far.any():
        raise ValueError(
            f"{name} must have point coordinates within +-{MAX_COORDINATE:g} mm, got "
            f"{int(far.sum())} of {len(pts)} points beyond (e.g. point "
            f"{int(np.flatnonzero(far)[0])} at {pts[far][0].tolist()})"
        )


def check_image_geometry(image, name):
    """Raise ``ValueError`` unless ``image`` has a finite origin and finite spacing > 0.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.filters._checks import check_image_geometry
    >>> check_image_geometry(pv.ImageData(dimensions=(2, 2, 2), spacing=(1, 0, 1)), "labels")
    Traceback (most recent call last):
    ...
    ValueError: labels must have a finite voxel spacing > 0 mm on every axis, got (1.0, 0.0, 1.0)
    """
    spacing = tuple(float(s) for s in image.spacing)
    if not all(np.isfinite(s) and s > 0 for s in spacing):
        raise ValueError(
            f"{name} must have a finite voxel spacing > 0 mm on every axis, got {spacing}"
        )
    origin = tuple(float(o) for o in image.origin)
    if not all(np.isfinite(origin)):
        raise ValueError(f"{name} must have a finite origin (mm), got {origin}")
    if image.n_points == 0:
        raise ValueError(f"{name} must have voxels, got dimensions {tuple(image.dimensions)}")
