"""Signed-distance primitives of the atlas head (mm, negative inside).

Every primitive takes ``P``, a tuple (x, y, z) of float32 arrays of one shape, and returns
an approximate signed distance of that shape: ellipsoids, capsules, rounded boxes, smooth
unions, and curves swept with an elliptic (:class:`_Sweep`) or rectangular
(:class:`_Arch`) cross-section. Delegates to numpy, :class:`scipy.spatial.cKDTree`
(nearest points of swept curves) and :mod:`scipy.ndimage` (interpolation of arch tables).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

F32 = np.float32


def _ellipsoid(P, c, r):
    """Approximate SDF of an axis-aligned ellipsoid (centre c, semi-axes r)."""
    x = (P[0] - c[0]) / r[0]
    y = (P[1] - c[1]) / r[1]
    z = (P[2] - c[2]) / r[2]
    k0 = np.sqrt(x * x + y * y + z * z)
    k1 = np.sqrt((x / r[0]) ** 2 + (y / r[1]) ** 2 + (z / r[2]) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, 1e-6)


def _rot_ellipsoid(P, c, r, angle):
    """Ellipsoid turned by ``angle`` (rad) about the vertical (z) axis."""
    ca, sa = np.cos(angle), np.sin(angle)
    dx, dy = P[0] - c[0], P[1] - c[1]
    u = ca * dx + sa * dy
    v = -sa * dx + ca * dy
    return _ellipsoid((u, v, P[2] - c[2]), (0.0, 0.0, 0.0), r)


def _capsule(P, a, b, ra, rb=None):
    """Segment a-b swept by a sphere whose radius goes from ra to rb."""
    rb = ra if rb is None else rb
    a = np.asarray(a, float)
    ba = np.asarray(b, float) - a
    dx, dy, dz = P[0] - a[0], P[1] - a[1], P[2] - a[2]
    h = np.clip((dx * ba[0] + dy * ba[1] + dz * ba[2]) / float(ba @ ba), 0.0, 1.0)
    ex, ey, ez = dx - ba[0] * h, dy - ba[1] * h, dz - ba[2] * h
    return np.sqrt(ex * ex + ey * ey + ez * ez) - (ra + (rb - ra) * h)


def _box(P, c, half, radius=0.0):
    """Axis-aligned box with rounded edges."""
    qx = np.abs(P[0] - c[0]) - (half[0] - radius)
    qy = np.abs(P[1] - c[1]) - (half[1] - radius)
    qz = np.abs(P[2] - c[2]) - (half[2] - radius)
    out = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
    return out + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0) - radius


def _smin(a, b, k):
    """Polynomial smooth minimum (smooth union) with blending radius k (mm)."""
    h = np.minimum(np.maximum(0.5 + (0.5 / k) * (b - a), 0.0), 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def _smoothstep(v, lo, hi):
    t = np.minimum(np.maximum((v - lo) * (1.0 / (hi - lo)), 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


def _gauss(P, c, s):
    return np.exp(-0.5 * (((P[0] - c[0]) / s[0]) ** 2 + ((P[1] - c[1]) / s[1]) ** 2
                          + ((P[2] - c[2]) / s[2]) ** 2))


def _cull(fn, P, lo, hi, fill):
    """``fn`` evaluated only inside box [lo, hi], ``fill`` elsewhere.

    In a union ``fill`` is large (the part has no influence there), in a sum it is 0.
    """
    m = ((P[0] >= lo[0]) & (P[0] <= hi[0]) & (P[1] >= lo[1]) & (P[1] <= hi[1])
         & (P[2] >= lo[2]) & (P[2] <= hi[2]))
    if m.all():
        return fn(P)
    out = np.full(np.shape(P[0]), fill, dtype=F32)
    if m.any():
        out[m] = fn(tuple(p[m] for p in P))
    return out


def _stack(P):
    return np.stack([np.ravel(P[0]), np.ravel(P[1]), np.ravel(P[2])], axis=1)


def _tuple(points):
    points = np.asarray(points, dtype=F32)
    return points[:, 0], points[:, 1], points[:, 2]


def _resample(points, step=0.5, closed=False):
    """Resample a polyline at roughly ``step`` mm."""
    pts = np.asarray(points, float)
    if closed:
        pts = np.vstack([pts, pts[:1]])
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / step)), 2)
    t = np.linspace(0.0, s[-1], n + (0 if closed else 1), endpoint=not closed)
    return np.stack([np.interp(t, s, pts[:, i]) for i in range(3)], axis=1), t / s[-1]


def _spline(control, n=200, closed=False):
    """Catmull-Rom spline through control points (dense polyline)."""
    c = np.asarray(control, float)
    if closed:
        ext = np.vstack([c[-1:], c, c[:2]])
    else:
        ext = np.vstack([2 * c[0] - c[1], c, 2 * c[-1] - c[-2]])
    nseg = len(c) if closed else len(c) - 1
    per = max(n // nseg, 4)
    t = np.linspace(0, 1, per, endpoint=False)[:, None]
    out = []
    for i in range(nseg):
        p0, p1, p2, p3 = ext[i], ext[i + 1], ext[i + 2], ext[i + 3]
        out.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t ** 2
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * t ** 3))
    if not closed:
        out.append(c[-1:])
    return np.vstack(out)


class _Sweep:
    """A curve swept by an ellipse whose axes follow a normal field.

    Parameters
    ----------
    curve : (n, 3) array
        Dense centreline.
    normals : (n, 3) array
        Thickness direction at each centreline point (made orthogonal to the tangent).
    half_width, half_thickness : (n,) arrays
        Semi-axes of the cross-section along ``tangent x normal`` and ``normal``.
    closed : bool
        Closed curve (a ring) or open (rounded ends).
    """

    def __init__(self, curve, normals, half_width, half_thickness, closed=False):
        curve, param = _resample(curve, 0.4, closed)
        idx = np.linspace(0, 1, len(normals))
        normals = np.stack([np.interp(param, idx, np.asarray(normals)[:, i]) for i in range(3)], 1)
        self.a = np.interp(param, np.linspace(0, 1, len(half_width)), half_width)
        self.b = np.interp(param, np.linspace(0, 1, len(half_thickness)), half_thickness)
        tangent = np.gradient(curve, axis=0)
        if closed:
            tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        normals = normals - (normals * tangent).sum(1, keepdims=True) * tangent
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        self.c, self.t, self.n = curve, tangent, normals
        self.w = np.cross(tangent, normals)
        self.closed = closed
        self.tree = cKDTree(curve)
        r = float(max(self.a.max(), self.b.max()))
        self.bounds = (curve.min(0) - r - 1.0, curve.max(0) + r + 1.0)

    def __call__(self, P):
        shape = np.shape(P[0])
        pts = _stack(P)
        _, i = self.tree.query(pts, workers=1)
        d = pts - self.c[i]
        dt = np.einsum("ij,ij->i", d, self.t[i])
        dw = np.einsum("ij,ij->i", d, self.w[i])
        dn = np.einsum("ij,ij->i", d, self.n[i])
        a, b = self.a[i], self.b[i]
        if not self.closed:
            last = len(self.c) - 1
            dt = np.where(((i == 0) & (dt < 0)) | ((i == last) & (dt > 0)), dt, 0.0)
        else:
            dt = 0.0
        k = np.sqrt((dw / a) ** 2 + (dn / b) ** 2 + (dt / b) ** 2)
        return ((k - 1.0) * np.minimum(a, b)).astype(F32).reshape(shape)


class _Arch:
    """A horizontal (x, y) curve swept by a rounded rectangle in (distance, z).

    Used for the mandibular body and the upper alveolar process. The distance to the
    curve and the cross-section sizes are tabulated once on a 0.5 mm (x, y) grid and
    interpolated, which is much faster than a nearest-point query per voxel.
    """

    STEP = 0.5

    def __init__(self, curve_xy, half_thickness, z_bottom, z_top, radius=2.5):
        self._args = (curve_xy, half_thickness, z_bottom, z_top)
        self.r = radius
        self.fields = None

    def _tabulate(self):
        curve_xy, half_thickness, z_bottom, z_top = self._args
        pts = np.column_stack([curve_xy, np.zeros(len(curve_xy))])
        dense, param = _resample(pts, 0.25)
        c = dense[:, :2]
        h = np.interp(param, np.linspace(0, 1, len(half_thickness)), half_thickness)
        zb = np.interp(param, np.linspace(0, 1, len(z_bottom)), z_bottom)
        zt = np.interp(param, np.linspace(0, 1, len(z_top)), z_top)
        pad = float(h.max()) + 25.0
        self.lo = c.min(0) - pad
        hi = c.max(0) + pad
        n = np.ceil((hi - self.lo) / self.STEP).astype(int) + 1
        gx = self.lo[0] + self.STEP * np.arange(n[0])
        gy = self.lo[1] + self.STEP * np.arange(n[1])
        GX, GY = np.meshgrid(gx, gy, indexing="ij")
        dist, i = cKDTree(c).query(np.column_stack([GX.ravel(), GY.ravel()]))
        self.fields = [f.reshape(n).astype(F32) for f in (dist, h[i], zb[i], zt[i])]
        self.far = pad - 1.0

    def __call__(self, P):
        if self.fields is None:
            self._tabulate()
        shape = np.shape(P[0])
        u = (np.ravel(P[0]) - self.lo[0]) / self.STEP
        v = (np.ravel(P[1]) - self.lo[1]) / self.STEP
        dist, h, zb, zt = [ndimage.map_coordinates(f, [u, v], order=1, mode="nearest")
                           for f in self.fields]
        outside = (u < 0) | (v < 0) | (u > self.fields[0].shape[0] - 1) | (v > self.fields[0].shape[1] - 1)
        dist = np.where(outside, np.maximum(dist, self.far), dist)
        z = np.ravel(P[2])
        qx = dist - (h - self.r)
        qz = np.maximum(zb - z, z - zt) + self.r
        out = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qz, 0) ** 2)
        out = out + np.minimum(np.maximum(qx, qz), 0) - self.r
        return out.astype(F32).reshape(shape)


_MARGIN = 32.0  #: beyond this distance a part no longer shapes the skin


def _grow(lo, hi, m=_MARGIN):
    return (np.asarray(lo, float) - m, np.asarray(hi, float) + m)
