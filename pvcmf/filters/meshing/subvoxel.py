"""Sub-voxel muscle interfaces: the surface vertices projected onto smoothed label indicators.

A label image says on which side of a muscle surface every voxel centre lies, not where
between two centres the surface passes: its interface is a staircase half a voxel off
the anatomy at worst, and more at the staircase's corners. The indicator of a named
muscle (1 in its voxels, 0 elsewhere), smoothed by a Gaussian of half a voxel
(``scipy.ndimage.gaussian_filter``) and interpolated trilinearly
(``scipy.ndimage.map_coordinates``), crosses one half on a smooth surface between the
centres: at the staircase's middle where the surface is flat, inside its corners where
it is curved. A surface vertex on the sheet between a named muscle and other soft
tissue is moved along the indicator's gradient
onto that level (a few clipped Newton steps); a vertex where the level is out of reach
(the indicator flat, or the muscle thinner than the smoothing keeps at one half) stays
where it was; a vertex on the junction with the skin, the bone or the region's cut
moves within the plane of that surface. The label image is the only input: this works on any label image (an atlas
fit, a segmentation), not on a known anatomy.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, spatial

from .grid import _FAT, _MUSCLE0

#: Gaussian of the indicator, in voxels (0.5: the half level stays inside a muscle one
#: voxel thick, and follows the staircase's middle)
SIGMA_VOXELS = 0.5
#: the level of the interface
LEVEL = 0.5
#: voxels around a muscle's box where its indicator is evaluated
_PAD = 3
#: Newton steps, each clipped to this many voxels; the total move to ``_MAX_MOVE`` voxels
_STEPS = 4
_STEP_VOXELS = 0.5
_MAX_MOVE = 1.5
#: a projection is kept where the level is met to this tolerance, where the indicator
#: grows along the sheet's normal (towards the muscle; cosine above this) and where the
#: move is at most this share of the distance to the nearest vertex of another sheet
_TOLERANCE = 0.05
_MIN_COS = 0.3
_CLEARANCE = 0.5
#: the lowest code projected: the named muscles (``_MUSCLE0 + 1``). ``_MUSCLE0`` would also
#: move the muscle tissue without id (tongue, temporalis, neck) against the fat; the
#: temporalis, a thin sheet under thin fat on the skull, then makes sheets intersect
_LOWEST = _MUSCLE0 + 1
#: vertices searched for the nearest vertex of another sheet
_NEIGHBOURS = 24


class MuscleIndicators:
    """Smoothed indicators of the named muscles of a code volume, built on demand.

    ``fine``: ``(code (z, y, x), origin (x, y, z), spacing (x, y, z), ...)`` as
    :func:`pvcmf.filters.meshing.grid._crop_fine` returns.
    """

    def __init__(self, fine):
        self.code, self.origin, self.spacing = fine[0], np.asarray(fine[1], float), np.asarray(fine[2], float)
        # box of code c at index c - _MUSCLE0 (muscle tissue without id, then the named)
        self._boxes = ndimage.find_objects(
            np.where(self.code >= _MUSCLE0, self.code.astype(np.int64) - _MUSCLE0 + 1, 0))
        self._cache = {}

    def _field(self, c):
        """(value, gradient (3 arrays, per voxel), box start (z, y, x)) of code ``c``."""
        if c not in self._cache:
            i = c - _MUSCLE0
            box = self._boxes[i] if 0 <= i < len(self._boxes) else None
            if box is None:
                self._cache[c] = None
                return None
            pad = _PAD
            sl = tuple(slice(max(b.start - pad, 0), min(b.stop + pad, n))
                       for b, n in zip(box, self.code.shape))
            f = ndimage.gaussian_filter((self.code[sl] == c).astype(np.float32), SIGMA_VOXELS,
                                        mode="constant", truncate=3.0)
            grad = np.gradient(f)  # per voxel, array axes z, y, x
            self._cache[c] = (f, grad, np.array([s.start for s in sl], float))
        return self._cache[c]

    def evaluate(self, c, points):
        """Indicator and its gradient (per mm, x y z) of code ``c`` at ``points``; None if
        the code is absent."""
        field = self._field(c)
        if field is None:
            return None
        f, grad, start = field
        ijk = ((points - self.origin) / self.spacing)[:, ::-1] - start  # voxel z, y, x
        coords = ijk.T
        value = ndimage.map_coordinates(f, coords, order=1, mode="constant", cval=0.0)
        g = np.stack([ndimage.map_coordinates(gk, coords, order=1, mode="constant", cval=0.0)
                      for gk in grad[::-1]], axis=1)  # x, y, z per voxel
        return value, g / self.spacing


def _projected_vertices(points, tri, side_codes):
    """Muscle code per vertex to project (0: none) and the normal of the plane it must
    stay in (zero: free).

    A vertex is projected when its sheets border one named muscle only (no sheet between
    two named muscles). A vertex on the sheets between that muscle and other soft tissue
    (fat or muscle tissue without id) only moves freely; a vertex also on the skin, the
    bone or the region-of-interest cut (a sheet with air or not-meshed tissue on one
    side) moves within the plane of those sheets, so they keep their place and the
    junction line slides onto the muscle's interface.
    """
    n_pts = len(points)
    named = side_codes > _MUSCLE0
    top = side_codes.max(axis=1)
    muscle_code = np.where(top >= _LOWEST, top, 0)
    v = tri.ravel()
    code = np.repeat(muscle_code, 3)
    big = np.iinfo(np.int64).max
    lo = np.full(n_pts, big)
    hi = np.zeros(n_pts, np.int64)
    sel = code > 0
    np.minimum.at(lo, v[sel], code[sel])
    np.maximum.at(hi, v[sel], code[sel])
    out = np.where((hi > 0) & (lo == hi), hi, 0)
    out[np.unique(tri[named.all(axis=1)])] = 0
    hard = (side_codes < _FAT).any(axis=1)  # skin, bone, roi cut
    n = np.cross(points[tri[:, 1]] - points[tri[:, 0]], points[tri[:, 2]] - points[tri[:, 0]])
    n *= np.where(side_codes[:, 1] > side_codes[:, 0], 1.0, -1.0)[:, None]
    t = tri[hard]
    plane = np.stack([np.bincount(t.ravel(), weights=np.repeat(n[hard, k], 3), minlength=n_pts)
                      for k in range(3)], axis=1)
    norm = np.linalg.norm(plane, axis=1)
    on_hard = np.zeros(n_pts, bool)
    on_hard[t.ravel()] = True
    out[on_hard & (norm < 1e-12)] = 0  # sheets that cancel: no plane
    plane = np.where(on_hard[:, None], plane / np.maximum(norm, 1e-30)[:, None], 0.0)
    return out, plane


def _muscle_normals(points, tri, side_codes):
    """Unit vertex normals of the named muscles' sheets, pointing into the muscle (the
    higher code; VTK's SurfaceNets orients a triangle towards its second side)."""
    named = (side_codes >= _LOWEST).any(axis=1)
    t = tri[named]
    n = np.cross(points[t[:, 1]] - points[t[:, 0]], points[t[:, 2]] - points[t[:, 0]])
    n *= np.where(side_codes[named, 1] > side_codes[named, 0], 1.0, -1.0)[:, None]
    vn = np.stack([np.bincount(t.ravel(), weights=np.repeat(n[:, k], 3), minlength=len(points))
                   for k in range(3)], axis=1)
    return vn / np.maximum(np.linalg.norm(vn, axis=1), 1e-30)[:, None]


def _clearance(tree, x, code, c, k=_NEIGHBOURS):
    """Distance from ``x`` to the nearest surface vertex not projected with muscle code
    ``c`` (among the ``k`` nearest vertices; beyond them, the distance of the last)."""
    k = min(k, tree.n)
    d, j = tree.query(x, k=k)
    d, j = d.reshape(len(x), k), j.reshape(len(x), k)
    other = code[j] != c
    first = np.argmax(other, axis=1)
    return np.where(other.any(axis=1), d[np.arange(len(x)), first], d[:, -1])


def project_onto_indicators(points, tri, side_codes, indicators):
    """Move the vertices of the named muscles' sheets onto the half level of their
    smoothed indicator.

    Parameters
    ----------
    points : numpy.ndarray, shape (n, 3)
    tri : numpy.ndarray, shape (m, 3)
    side_codes : numpy.ndarray, shape (m, 2)
        Working-grid code of each side of each triangle.
    indicators : MuscleIndicators

    Returns
    -------
    numpy.ndarray
        The moved points (a copy) and the number of vertices moved.
    """
    points = np.array(points, dtype=float)
    code, plane = _projected_vertices(points, tri, side_codes)
    voxel = float(np.min(indicators.spacing))
    normal = _muscle_normals(points, tri, side_codes)
    tree = spatial.cKDTree(points)
    moved = 0
    for c in np.unique(code[code > 0]):  # one pass per named muscle (a dozen)
        idx = np.flatnonzero(code == c)
        clearance = _clearance(tree, points[idx], code, c)
        x0 = points[idx]
        x = x0.copy()
        for _ in range(_STEPS):
            out = indicators.evaluate(int(c), x)
            if out is None:
                break
            f, g = out
            g = g - np.einsum("ij,ij->i", g, plane[idx])[:, None] * plane[idx]
            gg = np.maximum(np.einsum("ij,ij->i", g, g), 1e-12)
            step = ((LEVEL - f) / gg)[:, None] * g
            norm = np.linalg.norm(step, axis=1)
            step *= np.minimum(1.0, _STEP_VOXELS * voxel / np.maximum(norm, 1e-12))[:, None]
            x = x + step
        out = indicators.evaluate(int(c), x)
        if out is None:
            continue
        dist = np.linalg.norm(x - x0, axis=1)
        g = out[1] - np.einsum("ij,ij->i", out[1], plane[idx])[:, None] * plane[idx]
        cos = np.einsum("ij,ij->i", g, normal[idx]) / np.maximum(np.linalg.norm(g, axis=1), 1e-12)
        ok = ((np.abs(out[0] - LEVEL) < _TOLERANCE) & (dist <= _MAX_MOVE * voxel)
              & (dist <= _CLEARANCE * clearance) & (cos > _MIN_COS))
        points[idx[ok]] = x[ok]
        moved += int(ok.sum())
    return points, moved
