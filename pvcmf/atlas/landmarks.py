"""Landmarks of the atlas head: bony and skin points a planner can place.

Each landmark is the first crossing of a ray with the bone, tooth or skin surface of the
atlas head (vectorised ray marching refined by bisection), or a fixed point.
"""

from __future__ import annotations

import functools

import numpy as np

from .shapes import _tuple
from .skull import cranium_vault_sdf, face_bone_sdf, lower_teeth_sdf, mandible_sdf, upper_teeth_sdf
from .soft_tissue import skin_sdf


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
        raise RuntimeError(f"atlas rays {bad.tolist()} miss their surface")
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
    """Atlas landmarks: bony and skin points a planner can place.

    Returns
    -------
    dict
        name -> float ndarray (3,), mm, atlas frame; symmetric pairs end in
        ``_left`` / ``_right``.

    Examples
    --------
    >>> from pvcmf.atlas.landmarks import landmarks
    >>> lm = landmarks()
    >>> bool(lm["pronasale"][1] > lm["subnasale"][1])
    True
    """
    return {k: v.copy() for k, v in _landmarks_cached().items()}
