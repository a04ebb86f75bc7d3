"""Patient warps: the smooth invertible maps that make virtual patients from the atlas head.

A virtual patient is the atlas head (:mod:`pvcmf.atlas`) through a :class:`PatientWarp`: a
global affine scaling with a mild non-linear part, the face shaping of
:mod:`pvcmf.datasets.template.face` (real face proportions), a radial stretch of the soft-tissue
layer outside the bony envelope (soft-tissue thickness) and a sagittal displacement of the
Le Fort I segment or the mandibular body (jaw relation, class II / III) that the lips and
chin follow. Each patient's jaw displacement is undone by its plan
(:data:`pvcmf.plan.TABLE_II`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...atlas.shapes import F32, _smoothstep
from ...atlas.skull import Z_LEFORT
from ...plan import TABLE_II
from .face import FaceShape

#: centre of the radial soft-tissue map
CENTER = np.array([0.0, 20.0, -25.0])


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
    face : float
        Strength of the face shaping (:class:`pvcmf.datasets.template.face.FaceShape`):
        1 gives the proportions of a real face, 0 the atlas head's.
    nose : float or None
        Factor on the nose and lip kernels of the face shaping; None: drawn from ``seed``
        (0.85-1.15), so a seeded cohort varies in face shape too.
    """

    scale: tuple = (1.0, 1.0, 1.0)
    thickness: float = 1.0
    maxilla: float = 0.0
    mandible: float = 0.0
    wave: float = 0.0
    seed: int = 0
    face: float = 1.0
    nose: float = None


def _jaw_shift(patient):
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
        1: dict(scale=(1.00, 1.02, 1.03), thickness=1.0, wave=1.5, nose=1.0),
        2: dict(scale=(0.95, 0.96, 0.95), thickness=0.85, wave=2.0, nose=0.9),
        3: dict(scale=(1.04, 1.04, 1.05), thickness=1.12, wave=2.0, nose=1.1),
        4: dict(scale=(0.98, 1.01, 0.99), thickness=1.06, wave=1.5, nose=1.15),
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
    ``W(F(T(J(p))))`` with J the displacement of the lips and chin with the jaws, T the
    radial stretch of the soft-tissue layer, F the face shaping
    (:class:`pvcmf.datasets.template.face.FaceShape`) and W the affine + smooth non-linear
    warp.
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
        nose = params.nose
        if nose is None:
            nose = float(np.random.default_rng(params.seed + 7).uniform(0.85, 1.15))
        self.shape = FaceShape(params.face, nose)

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
        return self._t_inverse(self.shape.inverse_tuple(self._w_inverse(X)))

    def base_forward(self, S):
        return self._w_forward(self.shape.forward_tuple(self._t_forward(S)))

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
    return PatientWarp(PatientParameters(face=0.0))
