"""Thin-plate-spline (TPS) warps between landmark sets, in 3-D.

The 3-D thin-plate spline is the interpolant of minimal bending energy through the
landmarks: an affine part plus a sum of radial terms ``w_i * |x - p_i|`` (the biharmonic
Green's function in 3-D, VTK's ``vtkThinPlateSplineTransform.SetBasisToR``). It maps every
source landmark exactly onto its target and is the identity when both sets coincide.

Delegates to :class:`scipy.interpolate.RBFInterpolator` (kernel ``'linear'``, i.e.
``-r``, with a degree-1 polynomial), which solves the same linear system as VTK's
transform; ``tests/test_atlas.py`` checks the two agree. ``smoothing > 0`` gives the
regularised (approximating) spline used by the automatic atlas fitting.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

#: landmarks closer than this (mm) count as coincident
COINCIDENT_TOL = 1e-6


def landmark_arrays(source, target, *, name="landmarks", min_points=4, check_target=True):
    """Validate two landmark sets and return them as matching ``(n, 3)`` arrays.

    Parameters
    ----------
    source, target : dict[str, array_like] or array_like
        Landmarks as ``{name: (x, y, z)}`` dictionaries (matched by name, in ``source``'s
        order; every source name must be in ``target``) or as ``(n, 3)`` arrays of the same
        shape (matched by row).
    name : str
        Parameter name quoted in error messages.
    min_points : int
        Least number of landmarks (4 non-coplanar points fix a 3-D affine map).
    check_target : bool
        Also reject coincident or coplanar target points (a spline is still defined for
        them, but as patient landmarks they are a mistake).

    Returns
    -------
    names : list of str
        Landmark names (``'0'``, ``'1'``, ... for arrays).
    src, dst : numpy.ndarray
        ``(n, 3)`` float arrays.

    Raises
    ------
    ValueError
        On missing names, NaN/inf coordinates, too few points, coincident points or a
        degenerate (coplanar) configuration; the message names the offending landmarks.

    Examples
    --------
    >>> from pvcmf import tps
    >>> a = {"a": (0, 0, 0), "b": (1, 0, 0), "c": (0, 1, 0), "d": (0, 0, 1)}
    >>> names, src, dst = tps.landmark_arrays(a, a)
    >>> names
    ['a', 'b', 'c', 'd']
    """
    if isinstance(source, dict) or isinstance(target, dict):
        if not (isinstance(source, dict) and isinstance(target, dict)):
            raise TypeError(
                f"{name}: source and target must both be dicts or both arrays, got "
                f"{type(source).__name__} and {type(target).__name__}"
            )
        missing = [k for k in source if k not in target]
        if missing:
            raise ValueError(
                f"{name} is missing {len(missing)} landmark(s) the atlas needs: {missing}; "
                f"given {sorted(target)}"
            )
        names = list(source)
        src = np.array([np.asarray(source[k], dtype=float).reshape(3) for k in names])
        dst = np.array([np.asarray(target[k], dtype=float).reshape(3) for k in names])
    else:
        src = np.asarray(source, dtype=float)
        dst = np.asarray(target, dtype=float)
        if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
            raise ValueError(
                f"{name}: source and target must be (n, 3) arrays of one shape, got "
                f"{src.shape} and {dst.shape}"
            )
        names = [str(i) for i in range(len(src))]
    for label, pts in (("source", src), ("target", dst)):
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            raise ValueError(
                f"{name}: {label} landmark(s) {[names[i] for i in np.flatnonzero(bad)]} "
                f"have NaN or infinite coordinates"
            )
    if len(src) < min_points:
        raise ValueError(f"{name}: need at least {min_points} landmarks, got {len(src)}")
    checks = (("source", src), ("target", dst)) if check_target else (("source", src),)
    for label, pts in checks:
        close = sorted(cKDTree(pts).query_pairs(COINCIDENT_TOL))
        if close:
            pairs = [(names[a], names[b]) for a, b in close]
            raise ValueError(
                f"{name}: {label} landmarks coincide (closer than {COINCIDENT_TOL} mm): {pairs}"
            )
        centred = pts - pts.mean(axis=0)
        sv = np.linalg.svd(centred, compute_uv=False)
        if sv[2] <= 1e-9 * max(sv[0], 1.0):
            raise ValueError(
                f"{name}: {label} landmarks are coplanar or collinear (singular values "
                f"{np.round(sv, 6).tolist()}); a 3-D thin-plate spline needs them spread in 3-D"
            )
    return names, src, dst


class ThinPlateSpline:
    """A 3-D thin-plate-spline map ``R^3 -> R^3`` fitted through landmark pairs.

    Parameters
    ----------
    source, target : dict[str, array_like] or (n, 3) array_like
        Landmarks in the source (e.g. atlas) and target (e.g. patient) frames; see
        :func:`landmark_arrays`.
    smoothing : float or array_like of shape (n,)
        0 (default) interpolates exactly; larger values (mm) trade exactness for
        smoothness (scipy's ``smoothing``); an array gives each landmark its own value
        (0 keeps that landmark exact).
    check_target : bool
        See :func:`landmark_arrays` (internal fits with many points turn it off).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.tps import ThinPlateSpline
    >>> src = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [5, 5, 5.]])
    >>> dst = src + [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0.]]
    >>> tps = ThinPlateSpline(src, dst)
    >>> bool(np.allclose(tps(src), dst))
    True
    """

    def __init__(self, source, target, *, smoothing=0.0, check_target=True):
        self.names, self.source, self.target = landmark_arrays(
            source, target, check_target=check_target
        )
        sm = np.asarray(smoothing, dtype=float)
        if sm.ndim > 1 or (sm.ndim == 1 and sm.shape != (len(self.source),)):
            raise ValueError(
                f"smoothing must be a number or {len(self.source)} numbers, got shape {sm.shape}"
            )
        if not np.isfinite(sm).all() or (sm < 0).any():
            raise ValueError(f"smoothing must be finite and >= 0, got {smoothing!r}")
        self.smoothing = float(sm) if sm.ndim == 0 else sm
        # the spline of the displacement keeps the numbers small and the identity exact
        self._rbf = RBFInterpolator(
            self.source,
            self.target - self.source,
            kernel="linear",
            degree=1,
            smoothing=self.smoothing,
        )

    def __call__(self, points):
        """Map ``(n, 3)`` points (or one point) from the source to the target frame."""
        pts = np.asarray(points, dtype=float)
        single = pts.ndim == 1
        pts = np.atleast_2d(pts)
        if pts.shape[1] != 3:
            raise ValueError(f"points must have shape (n, 3), got {np.shape(points)}")
        if len(pts) == 0:
            return pts.copy()
        out = pts + self._rbf(pts)
        return out[0] if single else out

    def warp(self, dataset):
        """Return a copy of a PyVista dataset with its points mapped by the spline."""
        out = dataset.copy()
        out.points = self(np.asarray(dataset.points))
        return out

    def __repr__(self):
        sm = self.smoothing if np.ndim(self.smoothing) == 0 else "per point"
        return f"ThinPlateSpline({len(self.source)} landmarks, smoothing={sm})"


def vtk_transform(source, target):
    """The same warp as a VTK ``vtkThinPlateSplineTransform`` (basis ``R``).

    Useful to hand the warp to VTK pipelines (``vtkTransformPolyDataFilter``) and as an
    independent implementation in tests.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.tps import vtk_transform
    >>> src = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10.]])
    >>> t = vtk_transform(src, src * 2)
    >>> bool(np.allclose(t.TransformPoint(10, 0, 0), (20, 0, 0)))
    True
    """
    from vtkmodules.vtkCommonTransforms import vtkThinPlateSplineTransform

    _, src, dst = landmark_arrays(source, target)
    t = vtkThinPlateSplineTransform()
    t.SetSourceLandmarks(pv.vtk_points(src))
    t.SetTargetLandmarks(pv.vtk_points(dst))
    t.SetBasisToR()
    t.Update()
    return t
