"""Face shaping: a smooth invertible deformation giving the atlas head real face proportions.

The analytic atlas head (:mod:`pvcmf.atlas`) has the right tissues in the right order but the
outline of an egg on a short cylinder. :class:`FaceShape` deforms the whole head (skin, fat,
muscles, bones and teeth alike, so every label keeps its neighbours and the soft tissue keeps a
positive thickness) toward the proportions of a real face, :data:`REAL_FACE`, measured on the
ArtiSynth face finite-element mesh and the Visible Human female head (``PVCMF_DATA_DIR``):

* a forehead that rises steeply above the brow and a cranium as broad at the parietal
  eminences as a real skull (not pointed like an egg);
* brow ridges, shallow eye sockets (the globes sit behind the brow and the cheek);
* lips that project ahead of the subnasale, a philtrum groove between two ridges;
* a neck that continues below the jaw, with a jaw line and mandibular angle above it.

The deformation is defined by its inverse (face -> atlas), ``x - D(x)``, where ``D`` is a sum
of landmark-anchored Gaussian displacement kernels (each kernel's centre is an atlas landmark
or a point between landmarks, its amplitude the offset that brings the landmark's proportion
to the real one) plus a softplus stretch of the neck below the mandible. Each kernel's
displacement gradient stays below 0.8 and the neck stretch is monotone, so the map is a
diffeomorphism (``tests/test_phantom.py`` checks its Jacobian). The forward map (atlas ->
face) is a fixed-point iteration. Delegates to numpy only.
"""

from __future__ import annotations

import numpy as np

from ...atlas.shapes import F32

#: proportions of a real face: (lo, hi) ranges, mm or ratios, around the values measured on
#: the ArtiSynth face mesh (outer surface; midline profile at x = 0.7 mm) and the Visible
#: Human female skin (-500 HU), widened by the spread of adult norms. ``nose``: pronasale
#: ahead of subnasale (ArtiSynth 30 mm); ``upper_lip``: labrale superius ahead of subnasale
#: (12 mm); ``lower_lip``: labrale inferius ahead of the soft pogonion (6 mm); ``forehead``:
#: soft glabella ahead of the skin 20 mm above it (4 mm: a steep forehead); ``neck``: head
#: below the soft menton within a head CT (one that reaches the third cervical vertebra;
#: the Visible Human female's continues to the shoulders); ``height_width``: soft
#: nasion-menton height over the soft bizygomatic width
#: (0.92); ``lower_face``: subnasale-menton over nasion-subnasale height (1.18);
#: ``vault_width``: head breadth 60 mm above the tragion over the soft bizygomatic width
#: (Visible Human female 1.1: the vault is as broad as the face, not pointed).
REAL_FACE = {
    "nose": (18.0, 32.0),
    "upper_lip": (4.0, 14.0),
    "lower_lip": (1.0, 10.0),
    "forehead": (0.0, 8.0),
    "neck": (35.0, 100.0),
    "height_width": (0.85, 1.10),
    "lower_face": (1.0, 1.4),
    "vault_width": (1.0, 1.2),
}

# (centre (x, y, z), sigma (x, y, z), displacement (x, y, z)), atlas frame, mm;
# mirrored kernels are listed for the patient's left side (x > 0) and copied to the right.
_MIDLINE = [
    ((0.0, 92.0, 72.0), (55.0, 30.0, 24.0), (0.0, 8.0, 0.0)),     # forehead: steep, less sloped
    ((0.0, 104.0, -52.0), (13.0, 6.0, 6.0), (0.0, 6.0, 0.0)),     # upper lip projects
    ((0.0, 105.0, -46.0), (2.6, 4.0, 4.5), (0.0, -1.5, 0.0)),     # philtrum groove
    ((0.0, 103.0, -70.0), (13.0, 8.0, 5.5), (0.0, 6.0, -1.0)),    # lower lip
    ((0.0, 100.0, -83.0), (14.0, 7.0, 5.0), (0.0, -2.0, 0.0)),    # mentolabial sulcus
    ((0.0, 60.0, -122.0), (30.0, 22.0, 12.0), (0.0, -6.0, -3.0)),  # submental
    ((0.0, 45.0, -125.0), (40.0, 18.0, 20.0), (0.0, 0.0, -12.0)),  # cervicomental slope
]
_LATERAL = [
    ((33.0, 92.0, 12.0), (9.0, 8.0, 8.0), (0.0, -4.5, 0.0)),      # eye socket
    ((28.0, 92.0, 31.0), (13.0, 6.0, 5.0), (0.0, 2.5, 0.5)),      # brow ridge
    ((14.0, 109.0, -31.0), (5.0, 6.0, 5.0), (1.5, -1.0, 0.0)),    # alar flare
    ((62.0, 10.0, 70.0), (30.0, 60.0, 35.0), (9.0, 0.0, 0.0)),    # parietal breadth
]


def _kernels():
    out = list(_MIDLINE)
    for c, s, a in _LATERAL:
        out.append((c, s, a))
        out.append(((-c[0], c[1], c[2]), s, (-a[0], a[1], a[2])))
    return out


#: the neck stretch: below ``NECK_TOP`` (mm, atlas z) the neck is longer by 1 / NECK_SLOPE
NECK_TOP = -118.0
NECK_SLOPE = 0.6
_NECK_W = 5.0


class FaceShape:
    """The face-shaping deformation, scaled by ``strength`` (0: the atlas head unchanged).

    Parameters
    ----------
    strength : float
        Factor on every kernel's displacement and on the neck stretch (1: the real
        proportions of :data:`REAL_FACE`; patients vary it a little).
    nose : float
        Extra factor on the nasal kernels (alar flare) and the lip projection, for face
        variation between patients.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.datasets.template.face import FaceShape
    >>> f = FaceShape(1.0)
    >>> p = np.array([[0.0, 104.6, -52.0], [0.0, 0.0, -140.0]])
    >>> bool(np.allclose(f.inverse(f.forward(p)), p, atol=1e-4))
    True
    >>> bool(f.forward(p)[0, 1] > 108.0), bool(f.forward(p)[1, 2] < -150.0)
    (True, True)
    """

    def __init__(self, strength=1.0, nose=1.0):
        self.strength = float(strength)
        self.nose = float(nose)
        ks = []
        for c, s, a in _kernels():
            f = self.nose if (abs(c[0]) < 20 and c[2] < -25 and c[2] > -90) else 1.0
            ks.append((np.asarray(c, float), np.asarray(s, float),
                       np.asarray(a, float) * self.strength * f))
        self.kernels = ks

    def displacement(self, X):
        """``D(x)`` at deformed-frame points (tuple of arrays) -> tuple of 3 arrays."""
        out = [np.zeros(np.shape(X[0]), dtype=X[0].dtype) for _ in range(3)]
        if self.strength == 0:
            return out
        dt = out[0].dtype
        for c, s, a in self.kernels:
            q = sum(((X[i] - dt.type(c[i])) / dt.type(s[i])) ** 2 for i in range(3))
            g = np.exp(-0.5 * np.minimum(q, 60.0))
            for i in range(3):
                if a[i]:
                    out[i] = out[i] + dt.type(a[i]) * g
        return out

    def _neck(self, z):
        """Atlas z of deformed z: slope NECK_SLOPE below NECK_TOP, 1 above (monotone)."""
        k = (1.0 - NECK_SLOPE) * self.strength
        if not k:
            return z
        return z + k * _NECK_W * np.logaddexp(0.0, (NECK_TOP - z) / _NECK_W).astype(z.dtype)

    def _neck_forward(self, zt):
        k = (1.0 - NECK_SLOPE) * self.strength
        if not k:
            return zt
        z = np.asarray(zt, float).copy()
        for _ in range(40):  # Newton on _neck(z) = zt; derivative in [1 - k, 1]
            sig = 1.0 / (1.0 + np.exp(-(NECK_TOP - z) / _NECK_W))
            z = z - (self._neck(z) - zt) / (1.0 - k * sig)
        return z

    def inverse_tuple(self, X):
        """Deformed -> atlas frame for a tuple of coordinate arrays (the hot path)."""
        if self.strength == 0:
            return X
        d = self.displacement(X)
        Y = tuple(X[i] - d[i] for i in range(3))
        return (Y[0], Y[1], self._neck(Y[2]))

    def forward_tuple(self, S):
        """Atlas -> deformed frame (fixed-point iteration on ``x = y + D(x)``)."""
        if self.strength == 0:
            return S
        S = tuple(np.asarray(s, float) for s in S)
        Y = (S[0], S[1], self._neck_forward(S[2]))
        X = Y
        for _ in range(60):
            d = self.displacement(X)
            Xn = tuple(Y[i] + d[i] for i in range(3))
            step = max(float(np.max(np.abs(Xn[i] - X[i]))) if np.size(X[i]) else 0.0
                       for i in range(3))
            X = Xn
            if step < 1e-7:
                break
        return X

    def forward(self, points):
        """Atlas -> deformed frame, (n, 3) -> (n, 3) mm."""
        p = np.atleast_2d(np.asarray(points, float))
        return np.stack(self.forward_tuple(tuple(p[:, i] for i in range(3))), axis=1)

    def inverse(self, points):
        """Deformed -> atlas frame, (n, 3) -> (n, 3) mm."""
        p = np.atleast_2d(np.asarray(points, float))
        return np.stack(self.inverse_tuple(tuple(p[:, i] for i in range(3))), axis=1)

    def jacobian_determinant(self, points, h=0.25):
        """Determinant of the inverse map's Jacobian (central differences), (n,) array.

        Positive everywhere for an invertible, orientation-preserving map.
        """
        p = np.atleast_2d(np.asarray(points, float))
        J = np.empty((len(p), 3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            J[:, :, j] = (self.inverse(p + e) - self.inverse(p - e)) / (2 * h)
        return np.linalg.det(J)


IDENTITY = FaceShape(0.0)
__all__ = ["FaceShape", "IDENTITY", "NECK_SLOPE", "NECK_TOP", "REAL_FACE", "F32"]
