"""Bones and teeth of the atlas head: cranium, mid-face, dental arches, mandible, spine.

Frame: x = patient's left +, y = anterior +, z = superior +, mm; the origin lies between
the ear canals (porion) on the Frankfort horizontal plane (z = 0). Each part is a signed
distance function built from :mod:`pvcmf.atlas.shapes`.
"""

from __future__ import annotations

import functools

import numpy as np

from .shapes import (_Arch, _box, _capsule, _cull, _ellipsoid, _grow, _rot_ellipsoid, _smin,
                     _smoothstep)

# --------------------------------------------------------------------------- levels (mm)
Z_LEFORT = -30.0  #: Le Fort I osteotomy level: maxilla segment below, cranium above
Z_UPPER_EDGE = -62.0  #: upper incisal edge
Z_LOWER_EDGE = -65.0  #: lower incisal edge (the bite is 3 mm open)


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
