"""The dental arches: which tooth voxels are upper and which lower, and the occlusal level.

:func:`dental_arches` (a step of :func:`pvcmf.filters.find_jaws`, on a box whose axial
slices are about level with the arches) finds:

* two arches apart: the axial slice of fewest tooth voxels between the two largest peaks
  of the tooth voxels' height profile, each side holding ``MIN_ARCH_SHARE`` of the teeth
  (a smaller peak is stray tooth-dense voxels, noise on dense bone);
* two arches in occlusion (one run of teeth with the alveolar bone of both jaws beside
  it): the **occlusal surface**, a quadratic surface fitted to the contact gaps of the
  columns that hold both crowns, and the hard voxels along it over the arch to cut;
* one arch (an edentulous jaw, an open mouth whose arches share no slice of teeth): upper
  or lower by the bone beside its roots.

Delegates to numpy (least squares), :mod:`scipy.ndimage` (smoothing, dilation) and
:class:`scipy.spatial.Delaunay` (the arch's footprint); no loop over voxels.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError

log = logging.getLogger(__name__)

__all__ = ["dental_arches"]

#: height (mm) of the alveolar process beside the roots that tells a lone arch's side: the
#: roots are 13-17 mm long (Wheeler's Dental Anatomy: maxillary canine root 17 mm,
#: mandibular incisor root 12.5 mm)
ALVEOLAR_MM = 15.0
#: bone next to a lone run of teeth on its other side, as a share of the bone on its
#: busier side, that tells two arches in occlusion (a lone arch has soft tissue or air
#: beyond its crowns)
OCCLUSION_BONE = 0.25
#: least share of the teeth on each side of a split into two arches (else one arch)
MIN_ARCH_SHARE = 0.15
#: samples (mm) farther than this from the fitted occlusal surface are left out of the fit
OCCLUSAL_TRIM = 2.0
#: fewest columns with a contact gap that fit an occlusal surface
MIN_SAMPLES = 20
#: smallest radius of curvature (mm) of a fitted occlusal surface: the curves of Spee and
#: Wilson lie on a sphere of about 100 mm radius (Monson's 4 inches); a sharper fit is
#: taken as a plane
OCCLUSAL_MIN_RADIUS = 50.0


def _silent(*args, **kwargs):
    """A logger call that says nothing (a trial split)."""


def dental_arches(teeth, hard, spacing, *, quiet=False):
    """Occlusal slice, the upper and lower tooth voxels and the hard voxels of their contact
    (None where the arches are apart: the occlusal slice separates them).

    Two arches: the slice of fewest tooth voxels between the two largest peaks of the teeth's
    height profile, where each side holds ``MIN_ARCH_SHARE`` of the teeth. One arch (an
    edentulous jaw, or an open mouth whose arches share no slice of teeth, or stray
    tooth-dense voxels beside one arch): the arch is the lower one when its footprint holds
    more bone in the ``ALVEOLAR_MM`` below the teeth than above them (the alveolar process
    and the body hold the roots below the lower crowns, the alveolar process and palate
    above the upper ones), and the occlusal level is at its crowns' free end. ``quiet``:
    log nothing (a trial split).
    """
    tell = _silent if quiet else log.log
    profile = teeth.sum(axis=(0, 1)).astype(float)
    smooth = ndimage.gaussian_filter1d(profile, max(1.0, 1.5 / spacing[2]))
    z = np.flatnonzero(profile)
    lo, hi = int(z[0]), int(z[-1])
    inner = np.arange(lo + 1, hi)
    peaks = inner[(smooth[inner] >= smooth[inner - 1]) & (smooth[inner] > smooth[inner + 1])]
    gap = int(round(ALVEOLAR_MM / spacing[2]))
    if len(peaks) >= 2:
        a, b = sorted(peaks[np.argsort(smooth[peaks])[-2:]])
        # two peaks of one arch (enamel of the crowns and its partial volume) are closer
        # than a crown's height apart and have teeth in every slice between them
        if b - a > gap // 2 or np.any(profile[a:b + 1] == 0):
            z_occ = int(a + np.argmin(smooth[a:b + 1]))
            n_up = int(profile[z_occ + 1:].sum())
            # two arches hold their share of the teeth each (else stray tooth-dense voxels,
            # noise on dense bone, made the second peak: one arch)
            if min(n_up, int(profile.sum()) - n_up) >= MIN_ARCH_SHARE * profile.sum():
                upper = teeth.copy()
                upper[:, :, :z_occ + 1] = False
                return z_occ, upper, teeth & ~upper, None
    foot = ndimage.binary_dilation(teeth.any(axis=2),
                                   iterations=max(1, int(round(3.0 / spacing[0]))))
    bone = (hard & ~teeth)[foot].sum(axis=0)
    below, above = bone[max(lo - gap, 0):lo].sum(), bone[hi + 1:hi + 1 + gap].sum()
    none = np.zeros_like(teeth)
    touch = min(below, above) >= OCCLUSION_BONE * max(below, above)
    if touch:
        # bone of both jaws' alveolar processes next to one run of teeth: the arches touch
        split = _occlusion(teeth, hard, spacing, lo, hi, tell)
        if split is not None:
            return split
        tell(logging.WARNING, "find_jaws: the teeth have the bone of both jaws beside them "
             "(arches in occlusion?), but no occlusal surface shows between them (slices "
             "%.1f mm apart); taken as one arch: the segments may be wrong, give the plan "
             "cut planes", spacing[2])
    if below >= above:
        tell(logging.INFO, "find_jaws: one dental arch, the lower one (bone below it %d, "
             "above %d voxels); no upper tooth", below, above)
        return hi, none, teeth.copy(), None
    tell(logging.INFO, "find_jaws: one dental arch, the upper one (bone below it %d, above "
         "%d voxels); no lower tooth", below, above)
    return lo - 1, teeth.copy(), none, None


def _occlusion(teeth, hard, spacing, lo, hi, tell):
    """Upper and lower teeth of two arches in occlusion, split by the occlusal surface.

    Where the crowns of both arches stand in one column (x, y), the column's tooth voxels
    have a gap at the contact (the enamel of the cusps meets over less than a voxel, its
    partial volume falls below the teeth's threshold): the centre of each column's largest
    inner gap is a sample of the occlusal surface. A quadratic surface z(x, y) (the curves of
    Spee and Wilson: the occlusal surface lies close to a sphere, Monson) is fitted to the
    samples by least squares, twice trimmed of samples more than ``OCCLUSAL_TRIM`` mm off
    it. Tooth voxels above it are upper, below it lower. Returns (z of the surface's lowest
    point, upper, lower, the hard voxels on the surface inside the arch's footprint), or
    None where the samples are too few or fewer than ``MIN_ARCH_SHARE`` of the teeth fall
    on one side (one arch after all).
    """
    sub = teeth[:, :, lo:hi + 1]
    k = np.arange(lo, hi + 1, dtype=float)
    # per column: the largest run of non-tooth slices between two tooth voxels
    above = np.maximum.accumulate(np.where(sub, k, -np.inf), axis=2)  # last tooth at or below
    below = np.minimum.accumulate(np.where(sub, k, np.inf)[:, :, ::-1], axis=2)[:, :, ::-1]
    gap = np.where(~sub & np.isfinite(above) & np.isfinite(below), below - above, 0.0)
    size = gap.max(axis=2)
    cols = size >= 2  # at least one empty slice between two tooth voxels
    if cols.sum() < MIN_SAMPLES:
        return None
    arg = np.argmax(gap, axis=2)
    xi, yi = np.nonzero(cols)
    lower_top = above[xi, yi, arg[xi, yi]]
    zs = lower_top + 0.5 * size[xi, yi]
    pts = np.column_stack([xi * spacing[0], yi * spacing[1]])
    keep = np.ones(len(zs), dtype=bool)
    for _ in range(3):
        coef = _fit_quadric(pts[keep], zs[keep] * spacing[2])
        off = np.abs(_quadric(pts, coef) - zs * spacing[2])
        keep = off <= OCCLUSAL_TRIM
        if keep.sum() < MIN_SAMPLES:
            return None
    nx, ny, nz = teeth.shape
    gx, gy = np.meshgrid(np.arange(nx) * spacing[0], np.arange(ny) * spacing[1], indexing="ij")
    surf = _quadric(np.column_stack([gx.ravel(), gy.ravel()]), coef).reshape(nx, ny)
    surf = surf / spacing[2]  # slice index of the surface per column
    zz = np.arange(nz)[None, None, :]
    upper = teeth & (zz > surf[:, :, None])
    lower = teeth & ~upper
    n_up, n_low = int(upper.sum()), int(lower.sum())
    tell(logging.DEBUG, "find_jaws: occlusal surface from %d of %d columns, %d upper, %d "
         "lower tooth voxels", int(keep.sum()), len(zs), n_up, n_low)
    if min(n_up, n_low) < MIN_ARCH_SHARE * (n_up + n_low):
        return None
    foot = _arch_area(teeth.any(axis=2), spacing)
    # the crowns meet within the teeth's slices: where the surface leaves them (bent by
    # noisy samples at the footprint's edge) it crosses bone, not a contact
    contact = (hard & (np.abs(zz - surf[:, :, None]) < 1.0) & foot[:, :, None]
               & (zz >= lo) & (zz <= hi))
    tell(logging.INFO, "find_jaws: the dental arches touch (occlusion): %d upper and %d lower "
         "tooth voxels either side of the occlusal surface", n_up, n_low)
    # the surface's lowest point over the arch, within the teeth's slices: a surface fitted
    # to noisy gaps can bend far below the crowns at the footprint's edge
    z_low = int(np.floor(surf[foot].min())) if foot.any() else lo
    return int(np.clip(z_low, lo, hi)), upper, lower, contact


def _arch_area(foot, spacing):
    """Where the arches meet, seen from above: the convex hull of the teeth's footprint
    (:class:`scipy.spatial.Delaunay`), 3 mm wider, and everything in front of it (incisors
    and canines below the tooth threshold stand in front of the hull's chord)."""
    ij = np.argwhere(foot)
    inside = np.zeros_like(foot)
    try:
        hull = Delaunay(ij)
    except (QhullError, ValueError):  # collinear footprint
        inside = foot.copy()
    else:
        lo, hi = ij.min(axis=0), ij.max(axis=0) + 1
        grid = np.indices(hi - lo).reshape(2, -1).T + lo
        inside[lo[0]:hi[0], lo[1]:hi[1]] = (hull.find_simplex(grid) >= 0).reshape(hi - lo)
    inside = ndimage.binary_dilation(inside, iterations=max(1, int(round(3.0 / spacing[0]))))
    return np.maximum.accumulate(inside, axis=1)  # and in front of it (+y)


def _quadric_terms(pts):
    x, y = pts[:, 0], pts[:, 1]
    return np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])


def _fit_quadric(pts, z):
    """Least-squares quadratic surface z(x, y) (coordinates centred for conditioning); a
    plane where the quadric bends more sharply than any occlusal surface
    (:data:`OCCLUSAL_MIN_RADIUS`): samples from part of the arch, scattered by noise, can
    fit a fold that the surface then carries through the bone beyond them."""
    c = pts.mean(axis=0)
    terms = _quadric_terms(pts - c)
    coef, *_ = np.linalg.lstsq(terms, z, rcond=None)
    hessian = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    if np.abs(np.linalg.eigvalsh(hessian)).max() > 1.0 / OCCLUSAL_MIN_RADIUS:
        plane, *_ = np.linalg.lstsq(terms[:, :3], z, rcond=None)
        coef = np.concatenate([plane, np.zeros(3)])
    return c, coef


def _quadric(pts, fit):
    c, coef = fit
    return _quadric_terms(pts - c) @ coef
