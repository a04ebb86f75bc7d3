"""The template head: an analytic adult head that every virtual patient is warped from.

The template is the atlas frame of pvcmf. Its anatomy is a set of approximate signed
distance functions (SDFs, negative inside, in mm) built from ellipsoids, capsules, rounded
boxes and curves swept with an elliptic or rectangular cross-section, combined with
(smooth) unions and differences. Evaluating them on a grid gives exact, fast label images;
contouring them gives the muscle surfaces of the atlas.

Frame: x = patient's left +, y = anterior +, z = superior +, mm; the origin lies between
the ear canals (porion) on the Frankfort horizontal plane (z = 0).

A virtual patient is the template through a smooth invertible map (see
:func:`patient_warp`): a global affine scaling with a mild non-linear part, a radial
stretch of the soft-tissue layer outside the bony envelope (soft-tissue thickness) and a
sagittal displacement of the Le Fort I segment or the mandibular body (jaw relation,
class II / III) that the lips and chin follow.

Delegates to numpy (SDF evaluation on grid sub-boxes), :class:`scipy.spatial.cKDTree`
(nearest points of swept curves), :mod:`scipy.ndimage` (smoothing and interpolation of the
radial soft-tissue map) and PyVista/VTK (``ImageData.contour`` for the muscle surfaces).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.spatial import cKDTree

from .. import arrays

log = logging.getLogger(__name__)

F32 = np.float32

# --------------------------------------------------------------------------- levels (mm)
Z_LEFORT = -30.0  #: Le Fort I osteotomy level: maxilla segment below, cranium above
Z_UPPER_EDGE = -62.0  #: upper incisal edge
Z_LOWER_EDGE = -65.0  #: lower incisal edge (the bite is 3 mm open)
CENTER = np.array([0.0, 20.0, -25.0])  #: centre of the radial soft-tissue map


# =========================================================================== primitives
# P is a tuple (x, y, z) of float32 arrays of one shape; every primitive returns an
# approximate signed distance (mm) of that shape.


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


# =========================================================================== anatomy
# Cranium: outer table, inner table (braincase) and the cranial floor.
CRANIUM_CENTER = (0.0, -5.0, 30.0)
CRANIUM_OUTER = (68.0, 95.0, 88.0)
CRANIUM_INNER = (62.0, 89.0, 82.0)


def _cranial_floor(y):
    """Height of the inner cranial floor: anterior, middle and posterior fossae."""
    anterior = 37.0 * _smoothstep(y, 12.0, 42.0)
    posterior = 20.0 * _smoothstep(y, -35.0, -15.0)
    return -25.0 + posterior + anterior


def braincase_sdf(P):
    """The intracranial volume (brain and CSF)."""
    return np.maximum(_ellipsoid(P, CRANIUM_CENTER, CRANIUM_INNER), _cranial_floor(P[1]) - P[2])


def cranium_vault_sdf(P):
    """Skull vault and cranial base: outer ellipsoid minus braincase, above the floor slab."""
    outer = _ellipsoid(P, CRANIUM_CENTER, CRANIUM_OUTER)
    below = (_cranial_floor(P[1]) - 10.0) - P[2]
    return np.maximum(np.maximum(outer, below), -braincase_sdf(P))


def spine_sdf(P):
    """Cervical spine (labelled with the fixed cranium)."""
    return _capsule(P, (0.0, -22.0, -130.0), (0.0, -22.0, -52.0), 9.0)


def _face_outer(P):
    """Solid outline of the mid-face skeleton (maxilla, zygoma, nasal bones)."""
    d = _ellipsoid(P, (0.0, 60.0, -25.0), (42.0, 32.0, 28.0))            # maxillary body
    d = _smin(d, _ellipsoid(P, (0.0, 55.0, 10.0), (56.0, 38.0, 40.0)), 6.0)  # orbital region
    for sx in (-1.0, 1.0):
        d = _smin(d, _ellipsoid(P, (sx * 47.0, 62.0, -5.0), (11.0, 13.0, 14.0)), 4.0)
        d = _smin(d, _capsule(P, (sx * 50.0, 55.0, -5.0), (sx * 64.0, 8.0, -6.0), 4.5), 3.0)
        d = _smin(d, _capsule(P, (sx * 47.0, 76.0, 30.0), (sx * 50.0, 68.0, -4.0), 5.0), 4.0)
    d = _smin(d, _capsule(P, (0.0, 92.0, 20.0), (0.0, 101.0, -2.0), 7.0, 4.5), 3.0)  # nasal
    d = _smin(d, _capsule(P, (0.0, 88.0, -41.0), (0.0, 97.0, -39.0), 2.5), 2.0)  # ANS
    d = _smin(d, _box(P, (0.0, 30.0, -22.0), (28.0, 10.0, 22.0), 4.0), 4.0)  # pterygoid
    d = _smin(d, _cull(UPPER_ALVEOLUS, P, *_grow((-36, 38, -56), (36, 97, -35)), 1e3), 3.0)
    return d


def face_cavities_sdf(P):
    """Air cavities of the mid-face: nasal cavity with the piriform aperture, sinuses."""
    d = _box(P, (0.0, 59.5, -19.5), (11.0, 35.5, 21.5), 5.0)  # nasal cavity
    for sx in (-1.0, 1.0):
        d = np.minimum(d, _ellipsoid(P, (sx * 26.0, 62.0, -21.0), (11.0, 18.0, 13.0)))  # sinus
    return d


def orbits_sdf(P):
    """The orbits (filled with the eyes and orbital fat)."""
    return np.minimum(*[_ellipsoid(P, (sx * 33.0, 72.0, 12.0), (16.0, 30.0, 15.0))
                        for sx in (-1.0, 1.0)])


def face_bone_sdf(P):
    """Mid-face bone: outline minus cavities (cranium above Z_LEFORT, maxilla below)."""
    return np.maximum(_face_outer(P), -np.minimum(face_cavities_sdf(P), orbits_sdf(P)))


# --- dental arches (x = ax sin t, y = y0 + ay cos t), teeth by arc length
UPPER_ARCH = dict(ax=28.0, ay=39.5, y0=50.0)
LOWER_ARCH = dict(ax=25.5, ay=39.5, y0=48.5)
#: (mesio-distal width, labio-lingual semi-axis, crown edge z, root apex z) per tooth
UPPER_TEETH = [(8.5, 3.5, -62.0, -38.0), (6.5, 3.2, -61.5, -40.0), (7.5, 4.0, -61.5, -35.0),
               (7.0, 4.5, -61.0, -41.0), (6.5, 4.5, -61.0, -41.0), (10.0, 5.5, -60.5, -42.0),
               (9.0, 5.2, -60.0, -43.0)]
LOWER_TEETH = [(5.5, 3.0, -65.0, -86.0), (6.0, 3.0, -65.0, -87.0), (7.0, 3.8, -65.5, -90.0),
               (7.0, 4.2, -66.0, -87.0), (7.5, 4.2, -66.0, -87.0), (11.0, 5.0, -66.5, -85.0),
               (10.5, 5.0, -67.0, -84.0)]


def _arch_curve(ax, ay, y0, t_max=np.radians(125), n=400):
    t = np.linspace(-t_max, t_max, n)
    return np.column_stack([ax * np.sin(t), y0 + ay * np.cos(t)])


def _teeth_layout(arch, teeth):
    """Centres, angles and sizes of the teeth placed along an arch by arc length."""
    t = np.linspace(0, np.radians(125), 4000)
    xy = np.column_stack([arch["ax"] * np.sin(t), arch["y0"] + arch["ay"] * np.cos(t)])
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    out = []
    pos = 0.0
    for width, semi_ll, edge, apex in teeth:
        mid = pos + width / 2.0
        pos += width
        k = np.searchsorted(s, mid)
        tangent = xy[min(k + 1, len(xy) - 1)] - xy[max(k - 1, 0)]
        angle = np.arctan2(tangent[1], tangent[0])
        for sx in (1.0, -1.0):
            c = (sx * xy[k, 0], xy[k, 1], 0.5 * (edge + apex))
            ang = angle if sx > 0 else np.pi - angle
            out.append((c, (width / 2.0 + 0.3, semi_ll, abs(edge - apex) / 2.0), ang))
    return out


_UPPER_LAYOUT = _teeth_layout(UPPER_ARCH, UPPER_TEETH)
_LOWER_LAYOUT = _teeth_layout(LOWER_ARCH, LOWER_TEETH)


def _teeth_sdf(P, layout):
    d = None
    for c, r, ang in layout:
        e = _rot_ellipsoid(P, c, r, ang)
        d = e if d is None else np.minimum(d, e)
    return d


def upper_teeth_sdf(P):
    """The 14 upper teeth (crowns and roots)."""
    return _teeth_sdf(P, _UPPER_LAYOUT)


def lower_teeth_sdf(P):
    """The 14 lower teeth (crowns and roots)."""
    return _teeth_sdf(P, _LOWER_LAYOUT)


UPPER_ALVEOLUS = _Arch(_arch_curve(**UPPER_ARCH, t_max=np.radians(100)), [6.0, 6.5, 6.0],
                       [-55.0], [-36.0], radius=3.0)


def _mandible_curve():
    """Centreline of the mandibular body: along the lower teeth, then back to the angles."""
    arch = _arch_curve(**LOWER_ARCH, t_max=np.radians(88), n=200)
    right_end = np.array([48.0, 8.0])
    left_end = np.array([-48.0, 8.0])
    tail_r = np.linspace(arch[-1], right_end, 30)[1:]
    tail_l = np.linspace(left_end, arch[0], 30)[:-1]
    curve = np.vstack([tail_l, arch, tail_r])
    for _ in range(60):  # soften the corners
        curve[1:-1] = 0.5 * curve[1:-1] + 0.25 * (curve[:-2] + curve[2:])
    return curve


MANDIBLE_BODY = _Arch(_mandible_curve(), [7.0, 6.5, 6.0, 6.5, 7.0],
                      [-80.0, -92.0, -104.0, -92.0, -80.0], [-68.0, -74.0, -76.0, -74.0, -68.0],
                      radius=3.5)


def mandible_sdf(P):
    """Mandible: body, chin, angles, rami, condyles and coronoid processes."""
    d = _cull(MANDIBLE_BODY, P, *_grow((-56, 0, -105), (56, 95, -67)), 1e3)
    d = _smin(d, _ellipsoid(P, (0.0, 86.0, -95.0), (14.0, 7.5, 10.0)), 4.0)  # chin
    for sx in (-1.0, 1.0):
        lo, hi = _grow((38.0, -5.0, -78.0), (62.0, 33.0, -18.0))
        if sx < 0:
            lo, hi = _grow((-62.0, -5.0, -78.0), (-38.0, 33.0, -18.0))
        d = _smin(d, _cull(functools.partial(_ramus, sx=sx), P, lo, hi, 1e3), 4.0)
    return d


def _ramus(P, sx):
    if True:
        ramus = _capsule(P, (sx * 48.5, 9.0, -72.0), (sx * 50.0, 2.0, -28.0), 4.5)
        ramus = _smin(ramus, _capsule(P, (sx * 48.5, 25.0, -68.0), (sx * 47.0, 22.0, -40.0), 4.5), 8)
        plate = _box(P, (sx * 49.0, 15.0, -50.0), (4.0, 11.0, 18.0), 2.0)
        ramus = _smin(ramus, plate, 4.0)
        ramus = _smin(ramus, _ellipsoid(P, (sx * 50.0, 2.0, -24.0), (10.0, 5.5, 5.0)), 3.0)
        ramus = _smin(ramus, _capsule(P, (sx * 47.0, 22.0, -42.0), (sx * 45.0, 28.0, -24.0), 3.5), 3)
    return ramus


# --- soft tissue: bony envelope, thickness field, nose, lips, ears, neck
_MARGIN = 32.0  #: beyond this distance a part no longer shapes the skin


def _grow(lo, hi, m=_MARGIN):
    return (np.asarray(lo, float) - m, np.asarray(hi, float) + m)


_FACE_BOX = _grow((-70, 15, -62), (70, 108, 55))
_MANDIBLE_BOX = _grow((-62, -8, -112), (62, 100, -15))
_DENT_BOX = _grow((-30, 48, -70), (30, 92, -46))


def _face_mask(P):
    """Large, smooth parts of the facial skeleton that shape the face (no small bony detail)."""
    d = _ellipsoid(P, (0.0, 60.0, -25.0), (42.0, 32.0, 28.0))  # maxillary body
    d = _smin(d, _ellipsoid(P, (0.0, 55.0, 10.0), (56.0, 38.0, 40.0)), 12.0)  # orbital region
    for sx in (-1.0, 1.0):
        d = _smin(d, _ellipsoid(P, (sx * 47.0, 62.0, -5.0), (11.0, 13.0, 14.0)), 10.0)  # zygoma
        d = _smin(d, _box(P, (sx * 49.0, 17.0, -48.0), (5.0, 14.0, 22.0), 4.0), 12.0)  # ramus
    d = _smin(d, _capsule(P, (0.0, 92.0, 20.0), (0.0, 101.0, -2.0), 7.0, 4.5), 6.0)  # nasal
    d = _smin(d, _ellipsoid(P, (0.0, 70.0, -58.0), (30.0, 22.0, 12.0)), 10.0)  # dentition
    d = _smin(d, _cull(UPPER_ALVEOLUS, P, *_grow((-36, 38, -56), (36, 97, -35)), 1e3), 8.0)
    d = _smin(d, _cull(MANDIBLE_BODY, P, *_grow((-56, 0, -105), (56, 95, -67)), 1e3), 12.0)
    return _smin(d, _ellipsoid(P, (0.0, 86.0, -95.0), (14.0, 7.5, 10.0)), 8.0)  # chin


def _bone_envelope(P):
    """Smooth outline of the skeleton (without cavities): the skin follows it."""
    d = _ellipsoid(P, CRANIUM_CENTER, CRANIUM_OUTER)
    d = np.maximum(d, (_cranial_floor(P[1]) - 30.0) - P[2])
    return _smin(d, _cull(_face_mask, P, *_FACE_MASK_BOX, 1e3), 14.0)


_FACE_MASK_BOX = _grow((-62, -5, -112), (62, 108, 55))


def _bone_cover(P):
    """Every bone grown by 2.5 mm: the skin always covers the skeleton."""
    d = np.minimum(_cull(_face_outer, P, *_grow((-70, 15, -62), (70, 108, 55), 4.0), 1e3),
                   _cull(mandible_sdf, P, *_grow((-62, -8, -112), (62, 100, -15), 4.0), 1e3))
    return d + 2.5


def thickness_field(P):
    """Soft-tissue thickness (mm) over the bony envelope, before the patient's factor."""
    t = np.full(np.shape(P[0]), 5.5, dtype=F32)
    for amp, c, sig in _THICKNESS_BUMPS:
        lo = np.asarray(c) - 3.5 * np.asarray(sig)
        hi = np.asarray(c) + 3.5 * np.asarray(sig)
        t += amp * _cull(lambda Q: _gauss(Q, c, sig), P, lo, hi, 0.0)
    return t


_THICKNESS_BUMPS = [(5.5, (0.0, 90.0, -96.0), (20.0, 14.0, 14.0))]  # chin
for _sx in (-1.0, 1.0):
    _THICKNESS_BUMPS += [
        (16.0, (_sx * 44.0, 60.0, -34.0), (15.0, 18.0, 18.0)),  # cheek
        (9.0, (_sx * 56.0, 22.0, -45.0), (14.0, 22.0, 24.0)),  # masseter region
        (6.0, (_sx * 62.0, 20.0, 28.0), (15.0, 28.0, 22.0)),  # temporalis
        (-2.5, (_sx * 33.0, 88.0, 12.0), (9.0, 9.0, 9.0)),  # eyelids
        (5.0, (_sx * 24.0, 88.0, -20.0), (10.0, 10.0, 12.0)),  # infraorbital / paranasal
    ]


EYES = [((sx * 33.0, 79.0, 12.0), 12.0) for sx in (-1.0, 1.0)]


def eyes_sdf(P):
    """Eye globes."""
    return np.minimum(*[_ellipsoid(P, c, (r, r, r)) for c, r in EYES])


def _nose(P):
    d = _capsule(P, (0.0, 96.0, 18.0), (0.0, 116.0, -20.0), 7.0, 9.5)
    d = _smin(d, _ellipsoid(P, (0.0, 117.0, -26.0), (10.0, 10.5, 9.0)), 5.0)  # tip
    for sx in (-1.0, 1.0):
        d = _smin(d, _ellipsoid(P, (sx * 13.0, 104.0, -31.0), (8.5, 11.0, 8.0)), 5.0)  # ala
    return d


def _lips(P):
    d = _ellipsoid(P, (0.0, 93.5, -51.0), (24.0, 11.0, 10.0))  # upper lip
    d = _smin(d, _ellipsoid(P, (0.0, 92.0, -70.0), (23.0, 11.0, 9.0)), 4.0)  # lower lip
    return d


def _neck(P):
    cyl = np.sqrt((P[0] / 50.0) ** 2 + ((P[1] + 10.0) / 52.0) ** 2) * 50.0 - 50.0
    return np.maximum(np.maximum(cyl, P[2] - (-10.0)), (-145.0) - P[2])


def _ears(P):
    d = None
    for sx in (-1.0, 1.0):
        e = _ellipsoid(P, (sx * 72.0, -8.0, 2.0), (5.0, 13.0, 25.0))
        d = e if d is None else np.minimum(d, e)
    return d


def skin_sdf(P, thickness=1.0):
    """Outer skin surface: bony envelope offset by the thickness field, nose, lips, ears, neck."""
    d = _bone_envelope(P) - thickness * thickness_field(P)
    d = _smin(d, _bone_cover(P), 2.0)
    d = _smin(d, _cull(eyes_sdf, P, *_grow((-47, 65, -2), (47, 93, 26)), 1e3) - 2.5, 4.0)
    d = _smin(d, _cull(_nose, P, *_grow((-22, 88, -40), (22, 129, 25)), 1e3), 5.0)
    d = _smin(d, _cull(_lips, P, *_grow((-25, 82, -80), (25, 107, -40)), 1e3), 4.0)
    d = _smin(d, _cull(_neck, P, *_grow((-55, -65, -146), (55, 50, -10), 30), 1e3), 14.0)
    d = _smin(d, _cull(_ears, P, *_grow((-78, -22, -24), (78, 6, 28), 12), 1e3), 2.0)
    return d


NOSTRILS = [((sx * 7.0, 114.0, -33.0), (sx * 7.0, 96.0, -28.0)) for sx in (-1.0, 1.0)]


def airway_sdf(P):
    """Pharynx and nasal vestibules (air inside the head that is not in the face bone)."""
    d = np.maximum(np.sqrt((P[0] / 11.0) ** 2 + ((P[1] - 20.0) / 7.0) ** 2) * 7.0 - 7.0,
                   np.maximum(P[2] - (-18.0), (-136.0) - P[2]))
    for a, b in NOSTRILS:
        d = np.minimum(d, _capsule(P, a, b, 3.5, 4.5))
    return d


def oral_air_sdf(P):
    """Air between the tongue and the palate."""
    return _box(P, (0.0, 52.0, -50.0), (15.0, 28.0, 3.5), 3.4)


def tongue_sdf(P):
    """Tongue (muscle tissue without a facial-muscle id)."""
    return _ellipsoid(P, (0.0, 55.0, -64.0), (21.0, 30.0, 11.0))


def temporalis_sdf(P):
    """Temporalis: a 7 mm layer on the temporal fossa."""
    shell = np.abs(_ellipsoid(P, CRANIUM_CENTER, CRANIUM_OUTER) - 3.5) - 3.5
    region = np.minimum(*[_ellipsoid(P, (sx * 60.0, 15.0, 25.0), (30.0, 45.0, 38.0))
                          for sx in (-1.0, 1.0)])
    return np.maximum(shell, region)


def neck_muscles_sdf(P):
    """Neck muscles (prevertebral, sternocleidomastoid, nuchal) under 9 mm of fat."""
    cyl = np.sqrt((P[0] / 41.0) ** 2 + ((P[1] + 10.0) / 43.0) ** 2) * 41.0 - 41.0
    top = -85.0 + 50.0 * (1.0 - _smoothstep(P[1], -45.0, 0.0))
    return np.maximum(np.maximum(cyl, P[2] - top), (-138.0) - P[2])


# =========================================================================== landmarks
def _pair(name, surface, start, direction, segment):
    """Left and right landmark specs (the right one mirrored in x)."""
    mirror = lambda v: None if v is None else (-v[0], v[1], v[2])  # noqa: E731
    return [(f"{name}_left", surface, start, direction, segment),
            (f"{name}_right", surface, mirror(start), mirror(direction), segment)]


#: (name, surface, ray start, ray direction (None: fixed point), bone segment or None)
_LANDMARK_SPECS = [
    ("nasion", "bone", (0, 160, 21), (0, -1, 0), "cranium"),
    ("glabella", "bone", (0, 160, 38), (0, -1, 0), "cranium"),
    ("sella", "fixed", (0, 14, -2), None, "cranium"),
    *_pair("orbitale", "bone", (33, 80, 12), (0, 0, -1), "cranium"),
    *_pair("porion", "bone", (130, 0, 0), (-1, 0, 0), "cranium"),
    *_pair("zygion", "bone", (130, 35, -6), (-1, 0, 0), "cranium"),
    *_pair("frontozygomatic", "bone", (130, 75, 14), (-1, 0, 0), "cranium"),
    ("anterior_nasal_spine", "bone", (0, 160, -39.5), (0, -1, 0), "maxilla"),
    ("A_point", "bone", (0, 160, -45), (0, -1, 0), "maxilla"),
    *_pair("infraorbital", "bone", (27, 160, -14), (0, -1, 0), "cranium"),
    ("upper_incisor", "tooth", (2, 160, -58), (0, -1, 0), "maxilla"),
    ("lower_incisor", "tooth", (2, 160, -69), (0, -1, 0), "mandible"),
    ("B_point", "bone", (0, 160, -82), (0, -1, 0), "mandible"),
    ("pogonion", "bone", (0, 160, -95), (0, -1, 0), "mandible"),
    ("menton", "bone", (0, 84, -160), (0, 0, 1), "mandible"),
    *_pair("gonion", "bone", (75, -10, -100), (-0.5, 0.3, 0.55), "mandible"),
    *_pair("supraorbital", "bone", (30, 160, 30), (0, -1, 0), "cranium"),
    *_pair("zygomaxillare", "bone", (40, 160, -22), (0, -1, 0), "cranium"),
    *_pair("piriform", "bone", (15, 160, -20), (0, -1, 0), "cranium"),
    *_pair("canine_eminence", "bone", (17, 160, -44), (0, -1, 0), "maxilla"),
    *_pair("ramus", "bone", (130, 22, -45), (-1, 0, 0), "mandible"),
    *_pair("mental", "bone", (20, 160, -92), (0, -1, 0), "mandible"),
    ("soft_tissue_glabella", "skin", (0, 160, 38), (0, -1, 0), None),
    ("soft_tissue_nasion", "skin", (0, 160, 19), (0, -1, 0), None),
    ("pronasale", "skin", (0, 160, -25), (0, -1, 0), None),
    ("subnasale", "skin", (0, 160, -40.5), (0, -1, 0), None),
    *_pair("alare", "skin", (60, 106, -31), (-1, 0, 0), None),
    ("labrale_superius", "skin", (0, 160, -52), (0, -1, 0), None),
    ("stomion", "skin", (0, 160, -61), (0, -1, 0), None),
    ("labrale_inferius", "skin", (0, 160, -70), (0, -1, 0), None),
    *_pair("soft_tissue_infraorbital", "skin", (27, 160, -14), (0, -1, 0), None),
    *_pair("nasolabial", "skin", (30, 160, -45), (0, -1, 0), None),
    *_pair("cheilion", "skin", (25, 160, -61), (0, -1, 0), None),
    ("soft_tissue_B_point", "skin", (0, 160, -82), (0, -1, 0), None),
    ("soft_tissue_pogonion", "skin", (0, 160, -95), (0, -1, 0), None),
    ("soft_tissue_menton", "skin", (0, 80, -160), (0, 0, 1), None),
    *_pair("exocanthion", "skin", (45, 160, 12), (0, -1, 0), None),
    *_pair("cheek", "skin", (48, 160, -30), (0, -1, 0), None),
    *_pair("soft_tissue_zygion", "skin", (130, 40, -6), (-1, 0, 0), None),
    *_pair("soft_tissue_gonion", "skin", (130, 8, -72), (-1, 0, 0), None),
    *_pair("supraorbital_soft", "skin", (30, 160, 30), (0, -1, 0), None),
    *_pair("malar", "skin", (40, 160, -10), (0, -1, 0), None),
    *_pair("buccal", "skin", (40, 160, -50), (0, -1, 0), None),
    *_pair("subalare", "skin", (14, 160, -37), (0, -1, 0), None),
    *_pair("mental_soft", "skin", (20, 160, -92), (0, -1, 0), None),
    *_pair("masseteric", "skin", (130, 22, -45), (-1, 0, 0), None),
    *_pair("tragion", "skin", (130, 8, 0), (-1, 0, 0), None),
]


def _bone_union(P):
    d = np.minimum(cranium_vault_sdf(P), face_bone_sdf(P))
    return np.minimum(d, mandible_sdf(P))


def _teeth_union(P):
    return np.minimum(upper_teeth_sdf(P), lower_teeth_sdf(P))


_SURFACES = {
    "bone": lambda P: np.minimum(_bone_union(P), _teeth_union(P)),
    "tooth": _teeth_union,
    "skin": skin_sdf,
}


def _ray_hit(sdf, start, direction, step=0.25, max_len=200.0):
    """First zero crossing of ``sdf`` along rays (vectorised), refined by bisection."""
    start = np.asarray(start, float)
    direction = np.asarray(direction, float)
    direction = direction / np.linalg.norm(direction, axis=1, keepdims=True)
    ts = np.arange(0.0, max_len, step)
    pts = start[:, None, :] + ts[None, :, None] * direction[:, None, :]
    vals = sdf(_tuple(pts.reshape(-1, 3))).reshape(len(start), len(ts))
    inside = vals < 0
    if not inside.any(axis=1).all():
        bad = np.flatnonzero(~inside.any(axis=1))
        raise RuntimeError(f"template rays {bad.tolist()} miss their surface")
    k = inside.argmax(axis=1)
    lo, hi = ts[k - 1], ts[k]
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        v = sdf(_tuple(start + mid[:, None] * direction))
        lo = np.where(v < 0, lo, mid)
        hi = np.where(v < 0, mid, hi)
    return start + hi[:, None] * direction


@functools.lru_cache(maxsize=1)
def _landmarks_cached():
    out = {}
    for surface in ("bone", "tooth", "skin"):
        specs = [s for s in _LANDMARK_SPECS if s[1] == surface]
        hits = _ray_hit(_SURFACES[surface], [s[2] for s in specs], [s[3] for s in specs])
        out.update({s[0]: h for s, h in zip(specs, hits)})
    for s in _LANDMARK_SPECS:
        if s[1] == "fixed":
            out[s[0]] = np.asarray(s[2], float)
    return {s[0]: out[s[0]] for s in _LANDMARK_SPECS}


def landmark_segments():
    """Bone segment name of each bony landmark (``None`` for skin landmarks)."""
    return {s[0]: s[4] for s in _LANDMARK_SPECS}


def landmarks():
    """Template landmarks: bony and skin points a planner can place.

    Returns
    -------
    dict
        name -> float ndarray (3,), mm, template frame; symmetric pairs end in
        ``_left`` / ``_right``.

    Examples
    --------
    >>> from pvcmf.datasets import template
    >>> lm = template.landmarks()
    >>> bool(lm["pronasale"][1] > lm["subnasale"][1])
    True
    """
    return {k: v.copy() for k, v in _landmarks_cached().items()}


# =========================================================================== muscles
def _skin_normal(points, h=0.5):
    points = np.asarray(points, float)
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * h
    probe = (points[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
    v = skin_sdf(_tuple(probe)).astype(float).reshape(6, len(points))
    g = (v[:3] - v[3:]).T / (2 * h)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _under_skin(points, depth, iterations=12):
    """Move points along the skin normal until they lie ``depth`` mm below the skin."""
    p = np.asarray(points, float).copy()
    depth = np.broadcast_to(np.asarray(depth, float), (len(p),))
    for _ in range(iterations):
        n = _skin_normal(p)
        d = skin_sdf(_tuple(p)).astype(float)
        p -= ((d + depth) * 0.8)[:, None] * n
    return p


def _straps(specs):
    """Muscle straps through control points kept at given depths below the skin.

    ``specs`` is a list of (control points, depth(s), half widths, half thicknesses, n,
    closed); all points are projected in one batch.
    """
    def depths(spec, m):
        d = np.atleast_1d(np.asarray(spec[1], float))
        return np.interp(np.linspace(0, 1, m), np.linspace(0, 1, len(d)), d)

    controls = [np.asarray(sp[0], float) for sp in specs]
    flat = _under_skin(np.vstack(controls), np.concatenate(
        [depths(sp, len(c)) for sp, c in zip(specs, controls)]))
    splits = np.cumsum([len(c) for c in controls])[:-1]
    curves = [_spline(c, n=sp[4], closed=sp[5]) for c, sp in zip(np.split(flat, splits), specs)]
    flat = _under_skin(np.vstack(curves), np.concatenate(
        [depths(sp, len(c)) for sp, c in zip(specs, curves)]))
    normals = _skin_normal(flat)
    splits = np.cumsum([len(c) for c in curves])[:-1]
    return [_Sweep(c, n, np.atleast_1d(sp[2]), np.atleast_1d(sp[3]), closed=sp[5])
            for c, n, sp in zip(np.split(flat, splits), np.split(normals, splits), specs)]


def _ring(center, rx, rz, tilt_y, n=16):
    """Control points of an ellipse in a near-coronal plane."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([center[0] + rx * np.cos(t), center[1] + tilt_y * np.cos(t),
                            center[2] + rz * np.sin(t)])


def _masseter(sx):
    curve = np.array([[sx * 57.0, 34.0, -15.0], [sx * 57.5, 27.0, -40.0],
                      [sx * 56.0, 19.0, -66.0]])
    curve = _spline(curve, 60)
    normals = np.tile([sx * 1.0, 0.0, 0.0], (len(curve), 1))
    return _Sweep(curve, normals, [13.0, 15.0, 13.0], [3.5, 5.0, 3.5])


@functools.lru_cache(maxsize=1)
def _muscle_models():
    specs, names = [], []
    for side, sx in (("left", 1.0), ("right", -1.0)):
        names.append(f"orbicularis_oculi_{side}")
        specs.append((_ring((sx * 33.0, 100.0, 11.0), 21.0, 18.0, -sx * 4.0), 3.0, 6.5, 1.6,
                      160, True))
        names.append(f"levator_labii_superioris_alaeque_nasi_{side}")
        specs.append(([[sx * 11.0, 95.0, 10.0], [sx * 15.0, 92.0, -10.0],
                       [sx * 20.0, 95.0, -31.0], [sx * 18.0, 94.0, -45.0]],
                      [2.6, 3.5, 4.0, 4.5], [3.0, 4.0, 5.0], [1.3, 1.6, 1.8], 120, False))
        names.append(f"levator_labii_superioris_{side}")
        specs.append(([[sx * 30.0, 87.0, -4.0], [sx * 26.0, 88.0, -20.0],
                       [sx * 20.0, 93.0, -45.0]],
                      [3.5, 4.5, 4.5], [8.0, 6.5, 4.5], [1.5, 1.8, 1.8], 120, False))
        names.append(f"zygomaticus_minor_{side}")
        specs.append(([[sx * 42.0, 78.0, -8.0], [sx * 33.0, 84.0, -28.0],
                       [sx * 22.0, 92.0, -48.0]],
                      [4.0, 5.0, 4.5], [3.5, 3.5, 3.0], [1.6, 1.8, 1.6], 120, False))
        names.append(f"zygomaticus_major_{side}")
        specs.append(([[sx * 55.0, 72.0, -12.0], [sx * 44.0, 80.0, -38.0],
                       [sx * 29.0, 88.0, -59.0]],
                      [5.5, 6.5, 4.5], [5.0, 4.5, 4.0], [2.0, 2.5, 2.2], 120, False))
    models = dict(zip(names, _straps(specs)))
    for side, sx in (("left", 1.0), ("right", -1.0)):
        models[f"masseter_{side}"] = _masseter(sx)
    return {name: models[name] for name in arrays.MUSCLES}


def muscle_sdfs():
    """The 12 facial muscles as callables ``sdf(P) -> mm`` (negative inside).

    Returns
    -------
    dict
        name (``pvcmf.arrays.MUSCLES``) -> callable taking a tuple of three coordinate
        arrays (template frame) and returning a float32 array; each callable has a
        ``bounds`` attribute ``(lo, hi)``, the template box outside which it is positive.
    """
    return dict(_muscle_models())


def muscle_sdf(name, points):
    """Evaluate one template muscle's signed distance at ``points`` (n, 3), mm.

    Examples
    --------
    >>> from pvcmf.datasets import template
    >>> import numpy as np
    >>> float(template.muscle_sdf("masseter_left", np.array([[58.0, 26.0, -40.0]]))[0]) < 0
    True
    """
    if name not in arrays.MUSCLE_IDS:
        raise ValueError(f"name must be one of {list(arrays.MUSCLES)}, got {name!r}")
    return _muscle_models()[name](_tuple(np.atleast_2d(points)))


@functools.lru_cache(maxsize=1)
def _muscle_surfaces_cached(spacing):
    out = {}
    for name, model in _muscle_models().items():
        lo, hi = model.bounds
        lo = np.floor(lo - 2.0)
        dims = np.ceil((hi + 2.0 - lo) / spacing).astype(int) + 1
        img = pv.ImageData(dimensions=dims, spacing=(spacing,) * 3, origin=lo)
        pts = img.points
        img["sdf"] = model(_tuple(pts))
        surf = img.contour([0.0], scalars="sdf", method="flying_edges")
        surf = surf.compute_normals(auto_orient_normals=True, consistent_normals=True,
                                    split_vertices=False, cell_normals=False)
        surf.point_data.clear()
        surf.field_data["muscle_id"] = np.array([arrays.MUSCLE_IDS[name]])
        out[name] = surf
    return out


def muscle_surfaces(spacing=0.5):
    """The 12 template muscles as closed, outward-oriented triangle surfaces.

    Parameters
    ----------
    spacing : float
        Sampling step (mm) of the signed distance that is contoured.

    Returns
    -------
    dict
        name (``pvcmf.arrays.MUSCLES``) -> :class:`pyvista.PolyData` in the template frame.

    Examples
    --------
    >>> from pvcmf.datasets import template
    >>> surf = template.muscle_surfaces()["zygomaticus_major_left"]
    >>> surf.n_open_edges
    0
    """
    spacing = float(spacing)
    if not 0.2 <= spacing <= 2.0:
        raise ValueError(f"spacing must be in [0.2, 2] mm, got {spacing}")
    return {k: v.copy() for k, v in _muscle_surfaces_cached(spacing).items()}


# =========================================================================== patient maps
@dataclass(frozen=True)
class PatientParameters:
    """What makes a virtual patient differ from the template.

    Attributes
    ----------
    scale : tuple of float
        Affine scaling of the head along x, y, z.
    thickness : float
        Factor on the soft-tissue layer outside the bony envelope.
    maxilla, mandible : float
        Sagittal (anterior +) displacement (mm) of the Le Fort I segment and of the
        mandibular body relative to the template's normal occlusion; the plan of Table II
        undoes it.
    wave : float
        Amplitude (mm) of the smooth non-linear part of the warp.
    seed : int
        Seed of the non-linear part and of the CT noise.
    """

    scale: tuple = (1.0, 1.0, 1.0)
    thickness: float = 1.0
    maxilla: float = 0.0
    mandible: float = 0.0
    wave: float = 0.0
    seed: int = 0


def _jaw_shift(patient):
    from ..plan import TABLE_II

    maxilla = mandible = 0.0
    for o in TABLE_II[patient].osteotomies:
        ap = -o.translation[2]
        if o.segment == "maxilla":
            maxilla = ap
        else:
            mandible = ap
    return maxilla, mandible


def patient_parameters(patient):
    """Parameters of virtual patient 1-4 (size, soft-tissue thickness, jaw relation).

    Patient 1: maxillary protrusion (class II), 2: maxillary retrusion (class III),
    3: mandibular retrusion (class II), 4: mandibular protrusion (class III). The jaw
    displacements are minus the anterior-posterior translations of
    :data:`pvcmf.plan.TABLE_II`, so each patient's plan is its correction.
    """
    _check_patient(patient)
    maxilla, mandible = _jaw_shift(patient)
    base = {
        1: dict(scale=(1.00, 1.02, 1.03), thickness=1.0, wave=1.5),
        2: dict(scale=(0.95, 0.96, 0.95), thickness=0.85, wave=2.0),
        3: dict(scale=(1.04, 1.04, 1.05), thickness=1.12, wave=2.0),
        4: dict(scale=(0.98, 1.01, 0.99), thickness=1.06, wave=1.5),
    }[patient]
    return PatientParameters(maxilla=maxilla, mandible=mandible, seed=1000 + patient, **base)


def _check_patient(patient):
    if isinstance(patient, bool) or not isinstance(patient, (int, np.integer)):
        raise TypeError(f"patient must be an int in 1..4, got {type(patient).__name__}")
    if patient not in (1, 2, 3, 4):
        raise ValueError(f"patient must be 1, 2, 3 or 4, got {patient}")


def _maxilla_weight(z):
    """1 on the Le Fort I segment, fading to 0 over the 40 mm above the cut (mid-face)."""
    return 1.0 - _smoothstep(z, Z_LEFORT, Z_LEFORT + 40.0)


def _mandible_weight(y):
    """1 on the mandibular body, 0 at the condyles (the body lengthens or shortens)."""
    return _smoothstep(y, 5.0, 45.0)


def _soft_weights(P):
    """Share of the maxillary (a) and mandibular (b) displacement the soft tissue follows."""
    lower = 1.0 - _smoothstep(P[2], -70.0, -56.0)
    a = _maxilla_weight(P[2]) * (1.0 - lower) * _smoothstep(P[1], 0.0, 60.0)
    b = lower * _mandible_weight(P[1]) * _smoothstep(P[2], -150.0, -115.0)
    return a, b


_FIELD_LO = np.array([-100.0, -130.0, -160.0])
_FIELD_STEP = 4.0


@functools.lru_cache(maxsize=1)
def _template_fields():
    """Skin and bony-envelope SDFs of the template on a 3 mm grid (bounds, radial map)."""
    ax = [_FIELD_LO[i] + _FIELD_STEP * np.arange(n) for i, n in enumerate((51, 71, 76))]
    X, Y, Z = np.meshgrid(*[a.astype(F32) for a in ax], indexing="ij")
    return skin_sdf((X, Y, Z)), _bone_envelope((X, Y, Z)), (X, Y, Z)


def _sample_field(field, pts):
    idx = [(pts[:, i] - _FIELD_LO[i]) / _FIELD_STEP for i in range(3)]
    return ndimage.map_coordinates(field, idx, order=1, mode="nearest")


#: semi-axes (mm) of the inner ellipsoid (about CENTER) beyond which the radial soft-tissue
#: map stretches: inside the skull and the facial skeleton, so the map is smooth and the
#: soft tissue (and the outer bone) scale by the patient's thickness factor
INNER_AXES = (42.0, 52.0, 62.0)


def _envelope_radius(u):
    """Radius of the inner ellipsoid along unit directions ``u`` (tuple of arrays)."""
    a = INNER_AXES
    return (1.0 / np.sqrt((u[0] / a[0]) ** 2 + (u[1] / a[1]) ** 2 + (u[2] / a[2]) ** 2)).astype(F32)


_SOFTPLUS_W = 5.0


def _psi(v, f):
    """Radial map outside the envelope, patient -> template (monotone)."""
    return v + (1.0 / f - 1.0) * _SOFTPLUS_W * np.logaddexp(0.0, v / _SOFTPLUS_W)


class PatientWarp:
    """Smooth invertible map between the template and one virtual patient.

    ``forward`` maps template points to the patient, ``inverse`` patient points to the
    template. The map is the one the soft tissue (skin, fat, muscles) follows:
    ``W(T(J(p)))`` with J the displacement of the lips and chin with the jaws, T the
    radial stretch of the soft-tissue layer and W the affine + smooth non-linear warp.
    Bone segments follow the same map with their own jaw displacement (see
    :meth:`forward_bone`).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.datasets import template
    >>> w = template.patient_warp(2)
    >>> p = np.array([[10.0, 80.0, -20.0]])
    >>> bool(np.allclose(w.inverse(w.forward(p)), p, atol=1e-3))
    True
    """

    def __init__(self, params):
        self.params = params
        self.scale = np.asarray(params.scale, float)
        rng = np.random.default_rng(params.seed)
        k = rng.normal(size=(3, 3))
        self.k = 2 * np.pi * k / np.linalg.norm(k, axis=1, keepdims=True) / rng.uniform(190, 240, 3)[:, None]
        e = rng.normal(size=(3, 3))
        self.e = params.wave * e / np.linalg.norm(e, axis=1, keepdims=True)
        self.phase = rng.uniform(0, 2 * np.pi, 3)

    # ---- W: affine + waves, defined by its inverse
    def _g(self, Y):
        out = [np.zeros_like(Y[0]) for _ in range(3)]
        for i in range(3):
            s = np.sin(self.k[i, 0] * Y[0] + self.k[i, 1] * Y[1] + self.k[i, 2] * Y[2]
                       + self.phase[i])
            for j in range(3):
                out[j] = out[j] + F32(self.e[i, j]) * s
        return out

    def _w_inverse(self, X):
        Y = tuple((X[i] / F32(self.scale[i])).astype(F32) for i in range(3))
        if self.params.wave == 0:
            return Y
        g = self._g(Y)
        return tuple(Y[i] - g[i] for i in range(3))

    def _w_forward(self, P):
        Y = tuple(np.asarray(p, float) for p in P)
        if self.params.wave:
            for _ in range(12):
                g = self._g(Y)
                Y = tuple(P[i] + g[i] for i in range(3))
        return tuple(Y[i] * self.scale[i] for i in range(3))

    # ---- T: radial stretch of the soft tissue outside the bony envelope
    def _t_inverse(self, Q):
        f = self.params.thickness
        if f == 1.0:
            return Q
        d = [Q[i] - F32(CENTER[i]) for i in range(3)]
        r = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        rs = np.maximum(r, 1e-3)
        u = tuple(d[i] / rs for i in range(3))
        rb = _envelope_radius(u)
        rt = rb + _psi(r - rb, f)
        return tuple((F32(CENTER[i]) + u[i] * rt).astype(F32) for i in range(3))

    def _t_forward(self, S):
        f = self.params.thickness
        if f == 1.0:
            return S
        d = [np.asarray(S[i], float) - CENTER[i] for i in range(3)]
        rt = np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        rs = np.maximum(rt, 1e-9)
        u = tuple(d[i] / rs for i in range(3))
        rb = _envelope_radius(u).astype(float)
        v = rt - rb  # initial guess, Newton on psi(v) = rt - rb
        for _ in range(30):
            sig = 1.0 / (1.0 + np.exp(-v / _SOFTPLUS_W))
            v = v - (_psi(v, f) - (rt - rb)) / (1.0 + (1.0 / f - 1.0) * sig)
        r = rb + v
        return tuple(CENTER[i] + u[i] * r for i in range(3))

    # ---- J and the bone segments: sagittal displacements, defined by their inverse
    def base_inverse(self, X):
        """Patient -> template before the jaw displacements (tuple of arrays)."""
        return self._t_inverse(self._w_inverse(X))

    def base_forward(self, S):
        return self._w_forward(self._t_forward(S))

    def soft(self, S):
        """Template coordinates of the soft tissue at base coordinates ``S``."""
        if not (self.params.maxilla or self.params.mandible):
            return S
        a, b = _soft_weights(S)
        return (S[0], S[1] - (F32(self.params.maxilla) * a + F32(self.params.mandible) * b), S[2])

    def face(self, S):
        """Template coordinates of the mid-face bone (Le Fort I segment displaced)."""
        if not self.params.maxilla:
            return S
        return (S[0], S[1] - F32(self.params.maxilla) * _maxilla_weight(S[2]), S[2])

    def mandible(self, S):
        """Template coordinates of the mandible (body displaced)."""
        if not self.params.mandible:
            return S
        return (S[0], S[1] - F32(self.params.mandible) * _mandible_weight(S[1]), S[2])

    def _unshift(self, P, kind):
        """Solve kind(S) = P for S (fixed point; the displacements are small and smooth)."""
        P = tuple(np.asarray(p, float) for p in P)
        S = P
        fn = {"soft": self.soft, "face": self.face, "mandible": self.mandible,
              "cranium": lambda s: s}[kind]
        for _ in range(15):
            Q = fn(S)
            S = tuple(S[i] + (P[i] - Q[i]) for i in range(3))
        return S

    def forward_kind(self, points, kind):
        points = np.atleast_2d(np.asarray(points, float))
        S = self._unshift((points[:, 0], points[:, 1], points[:, 2]), kind)
        X = self.base_forward(S)
        return np.stack(X, axis=1)

    def forward(self, points):
        """Template -> patient for soft-tissue points, (n, 3) -> (n, 3) mm."""
        return self.forward_kind(points, "soft")

    def inverse(self, points):
        """Patient -> template for soft-tissue points, (n, 3) -> (n, 3) mm."""
        points = np.atleast_2d(np.asarray(points, float))
        S = self.base_inverse(tuple(points[:, i].astype(F32) for i in range(3)))
        S = tuple(np.asarray(s, float) for s in S)
        P = self.soft(S)
        return np.stack([np.asarray(p, float) for p in P], axis=1)

    def forward_bone(self, points, segment):
        """Template -> patient for points of a bone segment ('cranium', 'maxilla', 'mandible')."""
        kind = {"cranium": "face", "maxilla": "face", "mandible": "mandible"}[segment]
        return self.forward_kind(points, kind)


def patient_warp(patient):
    """The template -> patient map of virtual patient 1-4.

    Examples
    --------
    >>> from pvcmf.datasets import template
    >>> template.patient_warp(1).forward([[0.0, 0.0, 0.0]]).shape
    (1, 3)
    """
    return PatientWarp(patient_parameters(patient))


def identity_warp():
    """The template's own (identity) map."""
    return PatientWarp(PatientParameters())


# =========================================================================== rasterising
class _Grid:
    def __init__(self, origin, spacing, dims):
        self.origin = np.asarray(origin, float)
        self.spacing = float(spacing)
        self.dims = tuple(int(d) for d in dims)  # (nx, ny, nz)

    def axes(self):
        return [(self.origin[i] + self.spacing * np.arange(self.dims[i])).astype(F32)
                for i in range(3)]

    def slices(self, lo, hi):
        """Index slices (z, y, x order) of the voxels inside the box [lo, hi]."""
        i0 = np.clip(np.floor((np.asarray(lo) - self.origin) / self.spacing), 0, self.dims)
        i1 = np.clip(np.ceil((np.asarray(hi) - self.origin) / self.spacing) + 1, 0, self.dims)
        i0, i1 = i0.astype(int), i1.astype(int)
        return (slice(i0[2], i1[2]), slice(i0[1], i1[1]), slice(i0[0], i1[0]))


def _box_lattice(lo, hi, n=5):
    t = np.linspace(0, 1, n)
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(lo) + g * (np.asarray(hi) - np.asarray(lo))


#: template bounding boxes (lo, hi) of the components, generous
_BOXES = {
    "cranium": ((-70, -102, -45), (70, 92, 120)),
    "face": ((-70, 15, -62), (70, 108, 55)),
    "upper_teeth": ((-38, 22, -66), (38, 97, -30)),
    "lower_teeth": ((-36, 28, -92), (36, 95, -60)),
    "mandible": ((-62, -8, -112), (62, 100, -15)),
    "spine": ((-12, -34, -142), (12, -10, -40)),
    "airway": ((-14, 10, -140), (14, 120, -15)),
    "oral_air": ((-17, 22, -56), (17, 82, -44)),
    "tongue": ((-23, 23, -77), (23, 87, -51)),
    "eyes": ((-47, 65, -2), (47, 93, 26)),
    "temporalis": ((-80, -35, -20), (80, 65, 70)),
    "neck": ((-45, -56, -140), (45, 36, -33)),
}


class _Rasterizer:
    """Evaluate template components on a patient grid through a :class:`PatientWarp`.

    Each component is evaluated coarse-to-fine (factors 4, 2, 1 at 1 mm): a lattice point
    is evaluated only where the value of its parent block lies within a band of the zero
    level wider than the SDF can change across the block (the SDFs change by at most
    ``LIPSCHITZ`` mm per mm), so the sign, i.e. the label, is exact everywhere while the
    costly evaluations stay near the surfaces. The patient -> template map is evaluated
    exactly at every point that is evaluated (it is analytic and cheap).
    """

    LIPSCHITZ = 1.8

    def __init__(self, grid, warp):
        self.grid = grid
        self.warp = warp
        self.shape = grid.dims[::-1]
        self.axes = grid.axes()
        self.factor = 1
        while self.factor * 2 * grid.spacing <= 4.0 + 1e-9:
            self.factor *= 2
        self._subs = {}
        self._kinds = {"soft": warp.soft, "face": warp.face, "mandible": warp.mandible,
                       "cranium": lambda s: s}

    def sub(self, lo, hi, kind):
        """Slices of the patient grid covering template box [lo, hi] for a map kind."""
        if lo is None:
            return (slice(0, self.shape[0]), slice(0, self.shape[1]), slice(0, self.shape[2]))
        key = (tuple(np.ravel(lo)), tuple(np.ravel(hi)), kind)
        if key not in self._subs:
            X = self.warp.forward_kind(_box_lattice(lo, hi), kind)
            pad = 2.0 + self.grid.spacing
            self._subs[key] = self.grid.slices(X.min(0) - pad, X.max(0) + pad)
        return self._subs[key]

    def _points(self, iz, iy, ix, kind):
        X = (self.axes[0][ix], self.axes[1][iy], self.axes[2][iz])
        return self._kinds[kind](self.warp.base_inverse(X))

    def evaluate(self, fn, box, kind, lipschitz=None):
        """``fn`` on the sub-box of template box ``box``; returns (values, slices).

        ``fn`` may return several channels (an array of shape (k, ...)); a point is then
        refined where any channel is near its zero level.
        """
        lipschitz = self.LIPSCHITZ if lipschitz is None else lipschitz
        sl = self.sub(*(box if box is not None else (None, None)), kind)
        n = [s.stop - s.start for s in sl]
        if min(n) <= 0:
            return np.zeros((0, 0, 0), F32), sl
        start = [s.start for s in sl]
        c = self.factor
        while c > 1 and min(n) < 2 * c:
            c //= 2

        def lattice(f):
            return [np.minimum(np.arange(f // 2, m + f - 1, f)[: -(-m // f)], m - 1) for m in n]

        idx = lattice(c)
        iz, iy, ix = np.meshgrid(*idx, indexing="ij")
        values = np.asarray(fn(self._points(iz + start[0], iy + start[1], ix + start[2], kind)),
                            F32)
        multi = values.ndim == 4
        if not multi:
            values = values[None]
        while c > 1:
            band = lipschitz * (np.sqrt(3.0) * c / 2.0) * self.grid.spacing + 0.5
            c //= 2
            idx = lattice(c)
            up = values
            for axis in (1, 2, 3):
                up = np.repeat(up, 2, axis=axis)
            values = np.ascontiguousarray(up[:, :len(idx[0]), :len(idx[1]), :len(idx[2])])
            near = np.nonzero((np.abs(values) < band).any(axis=0))
            if len(near[0]):
                pts = self._points(idx[0][near[0]] + start[0], idx[1][near[1]] + start[1],
                                   idx[2][near[2]] + start[2], kind)
                fine = np.asarray(fn(pts), F32)
                values[(slice(None),) + near] = fine if multi else fine[None]
        return (values if multi else values[0]), sl


def rasterize(grid, warp, factor=None, progress_bar=False):
    """Truth labels and helper fields of the template through ``warp`` on ``grid``.

    ``factor`` is the coarsest sampling step (voxels, a power of 2) of the coarse-to-fine
    evaluation; default: about 4 mm; 1 evaluates every voxel.

    Returns
    -------
    dict
        ``tissue``, ``muscle``, ``bone`` (uint8, shape (nz, ny, nx)), ``bone_depth``
        (float32 mm inside bone, for cortical/cancellous HU), ``eye`` (bool).
    """
    R = _Rasterizer(grid, warp)
    if factor is not None:
        R.factor = int(factor)
    shape = R.shape

    def masks(fn, name, kind, lipschitz=1.8):
        d, sl = R.evaluate(fn, _BOXES.get(name), kind, lipschitz)
        d = d if d.ndim == 4 else d[None]
        out = np.zeros((len(d),) + shape, bool)
        out[(slice(None),) + sl] = d < 0
        return out, d, sl

    inside = masks(skin_sdf, None, "soft", 2.6)[0][0]  # the thickness factor lives in the warp
    tissue = np.zeros(shape, np.uint8)
    bone = np.zeros(shape, np.uint8)
    muscle = np.zeros(shape, np.uint8)
    depth = np.zeros(shape, F32)
    tissue[inside] = arrays.FAT
    # generic muscle tissue: tongue, temporalis, neck
    for fn, name, lip in ((tongue_sdf, "tongue", 1.8), (temporalis_sdf, "temporalis", 1.8),
                          (neck_muscles_sdf, "neck", 2.2)):
        tissue[masks(fn, name, "soft", lip)[0][0] & inside] = arrays.MUSCLE_TISSUE

    def set_depth(d, sl):
        sub = depth[sl]
        m = d < 0
        sub[m] = np.maximum(sub[m], -d[m])

    # cranium (vault and braincase share one evaluation), spine
    m, d, sl = masks(lambda P: np.stack([cranium_vault_sdf(P), braincase_sdf(P)]), "cranium",
                     "cranium", 2.4)
    vault, brain = m
    bone[vault] = arrays.CRANIUM
    set_depth(d[0], sl)
    m, d, sl = masks(spine_sdf, "spine", "cranium")
    bone[m[0]] = arrays.CRANIUM
    set_depth(d[0], sl)
    # mid-face: bone, air cavities, oral air, upper teeth and the Le Fort I level at once
    m, d, sl = masks(lambda P: np.stack([face_bone_sdf(P), face_cavities_sdf(P),
                                         P[2] - Z_LEFORT]), "face", "face")
    face, air, low = m
    bone[face & ~low] = arrays.CRANIUM
    bone[face & low] = arrays.MAXILLA
    set_depth(d[0], sl)
    m, _, _ = masks(lambda P: np.stack([upper_teeth_sdf(P), oral_air_sdf(P)]), "upper_teeth",
                    "face")
    upper, oral = m
    air |= oral
    m, d, sl = masks(lambda P: np.stack([mandible_sdf(P), lower_teeth_sdf(P)]), "mandible",
                     "mandible")
    mand, lower = m
    bone[mand] = arrays.MANDIBLE
    set_depth(d[0], sl)
    tissue[bone > 0] = arrays.BONE_TISSUE
    teeth = upper | lower
    tissue[teeth] = arrays.TEETH
    bone[upper] = arrays.MAXILLA
    bone[lower] = arrays.MANDIBLE
    depth[teeth] = 0.0
    # air inside the head
    soft = (tissue == arrays.FAT) | (tissue == arrays.MUSCLE_TISSUE)
    air |= masks(airway_sdf, "airway", "soft")[0][0]
    eye = masks(eyes_sdf, "eyes", "soft")[0][0] & soft
    tissue[air & soft & ~eye] = arrays.AIR
    tissue[brain] = arrays.INTRACRANIAL
    bone[brain] = arrays.BONE_NONE
    depth[brain] = 0.0
    # the 12 facial muscles, only in soft tissue
    soft = ((tissue == arrays.FAT) | (tissue == arrays.MUSCLE_TISSUE)) & ~eye
    for name, model in _muscle_models().items():
        d, sl = R.evaluate(model, model.bounds, "soft", 1.8)
        if d.size == 0:
            continue
        m = (d < 0) & soft[sl]
        muscle[sl][m] = arrays.MUSCLE_IDS[name]
        tissue[sl][m] = arrays.MUSCLE_TISSUE
    return {arrays.TISSUE: tissue, arrays.MUSCLE: muscle, arrays.BONE: bone,
            "bone_depth": depth, "eye": eye}


@functools.lru_cache(maxsize=1)
def _template_bounds():
    """Points inside the template skin (3 mm sampling), for bounding boxes."""
    skin_f, _, (X, Y, Z) = _template_fields()
    inside = skin_f < 0
    return np.stack([X[inside], Y[inside], Z[inside]], 1).astype(float)


def head_points(warp, n=20000):
    """Patient-frame sample of points inside the head (for bounding boxes)."""
    pts = _template_bounds()
    step = max(1, len(pts) // n)
    return warp.forward(pts[::step])


def label_image(spacing=1.0):
    """The template head's truth labels (same arrays as ``Case.truth``).

    Parameters
    ----------
    spacing : float
        Voxel size in mm (0.5 .. 4).

    Returns
    -------
    pyvista.ImageData
        Point arrays ``tissue``, ``muscle``, ``bone`` (uint8), template frame.

    Examples
    --------
    >>> from pvcmf.datasets import template
    >>> img = template.label_image(spacing=4.0)
    >>> sorted(img.point_data.keys())
    ['bone', 'muscle', 'tissue']
    """
    from .phantom import _check_spacing, _grid_for

    spacing = _check_spacing(spacing)
    warp = identity_warp()
    grid = _grid_for(warp, spacing, table=False)
    labels = rasterize(grid, warp)
    img = pv.ImageData(dimensions=grid.dims, spacing=(spacing,) * 3, origin=grid.origin)
    for name in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE):
        img.point_data[name] = labels[name].ravel()
    return img
