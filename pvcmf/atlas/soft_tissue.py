"""Soft tissue of the atlas head: skin over a thickness field, eyes, airway, tongue, muscles.

The skin is the bony envelope grown by a soft-tissue thickness field; nose, lips, ears and
neck are added with smooth unions. Signed distances in mm (negative inside), built from
:mod:`pvcmf.atlas.shapes` and the bones of :mod:`pvcmf.atlas.skull`.
"""

from __future__ import annotations

import numpy as np

from .shapes import F32, _box, _capsule, _cull, _ellipsoid, _gauss, _grow, _smin, _smoothstep
from .skull import (CRANIUM_CENTER, CRANIUM_OUTER, MANDIBLE_BODY, UPPER_ALVEOLUS,
                    _cranial_floor, _face_outer, mandible_sdf)


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
