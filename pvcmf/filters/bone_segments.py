"""Bone segments from the anatomy: mandible and Le Fort I maxilla without cut planes.

:func:`find_jaws` labels, in a segmented head (``tissue`` with hard tissue, teeth and metal):

* the **occlusal level**: the axial plane of fewest tooth voxels between the upper and the
  lower dental arch (the two largest peaks of the tooth voxels' height profile). Teeth in
  occlusion (one run of teeth with the alveolar bone of both jaws beside it) are split by
  the **occlusal surface** instead: a quadratic surface fitted to the contact gaps of the
  columns that hold both crowns; the hard tissue along it, over the arch and in front of
  it, is cut;
* the **mandible**: the hard tissue, split at the occlusal level inside the dental arch's
  footprint (where the upper and lower teeth touch), connected to the lower teeth. Where
  that part still holds the upper teeth or the skull's top (the condyles touch their
  fossae: a joint space lost to thick slices or partial volume; teeth in contact beyond
  the arch), it is split along its narrowest cut
  (:func:`pvcmf.filters.narrowest_cut.narrowest_cut`, a minimum cut in mm^2 of voxel faces)
  between the bone under the lower teeth and those parts; the voxels the occlusal split
  removed go back to the nearest side (a nearest-label fill,
  :func:`scipy.ndimage.distance_transform_edt`);
* the **maxilla** (Le Fort I): the remaining hard tissue from the occlusal level up to
  ``LEFORT_ABOVE_FLOOR`` mm above the nasal floor (the lowest air inside the head above the
  upper teeth: the cut runs through the lateral nasal walls and the maxillary sinuses, the
  palate and the tooth roots stay below it), in front of the pterygoid region (a margin
  behind the last upper tooth, or the back end of the hard palate, the posterior nasal
  spine, where it lies farther back: the segment holds the whole palate) and joined to the
  upper teeth; every upper tooth is in it.
  An edentulous maxilla (one dental arch, the lower one) is seeded by its alveolar ridge
  (the lowest non-mandible bone over the maxilla's area, found from the lower arch's midline
  and front), cut ``LEFORT_ABOVE_FLOOR`` mm above the nasal floor found over the palate,
  and ends behind at the posterior nasal spine.

Everything else is ``CRANIUM``. Delegates to :mod:`scipy.ndimage` (labelling, distance
transforms) and :mod:`scipy.sparse.csgraph` (the cut's maximum flow); no loop over voxels.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.spatial import Delaunay, QhullError

from .. import arrays
from .morphology import _beyond, _c_copy
from .narrowest_cut import narrowest_cut

log = logging.getLogger(__name__)

__all__ = ["find_jaws", "segment_volumes"]

_FACES = ndimage.generate_binary_structure(3, 1)
_CUBE = np.ones((3, 3, 3), dtype=bool)
#: margin (mm) behind the last upper tooth where the Le Fort I cut ends at the
#: pterygomaxillary junction: the mesiodistal widths of the second and third molars that may
#: be missing behind a first molar (9 and 8.5 mm, Wheeler's Dental Anatomy) plus the
#: maxillary tuberosity behind the third molar (about 7 mm)
POSTERIOR_MARGIN = 25.0
#: height (mm) of the Le Fort I cut above the nasal floor: the osteotomy enters the
#: piriform aperture 5-6 mm above the nasal floor and runs above the apices of the teeth
#: (Bell, J Oral Surg 1975; Hall & McKenna), the palate and every root below it
LEFORT_ABOVE_FLOOR = 6.0
#: dense bone (petrous temporal bone) this close (mm) to the intracranial volume is no tooth
SKULL_BASE_MM = 15.0
#: height (mm) of the alveolar process beside the roots that tells a lone arch's side: the
#: roots are 13-17 mm long (Wheeler's Dental Anatomy: maxillary canine root 17 mm,
#: mandibular incisor root 12.5 mm)
ALVEOLAR_MM = 15.0
#: smallest area (mm^2) of nasal floor seen on the palate in one slice
PALATE_MM2 = 50.0
#: least area (mm^2) of nasal floor seen on the palate in one slice of a narrow nasal cavity
PALATE_MIN_MM2 = 10.0
#: height (mm) above the teeth or ridge searched for the nasal floor (the palate lies
#: 10-20 mm above the alveolar crest)
NASAL_SEARCH_MM = 25.0
#: thickness (mm) of the nasal mucosa between the palate's bone and the nasal air
MUCOSA_MM = 4.0
#: half width (mm) of the nasal floor about the midline, medial to the maxillary sinuses (the
#: nasal cavity is 25-35 mm wide at its floor)
NASAL_HALF_WIDTH = 8.0
#: height (mm) of an edentulous alveolar ridge taken as the maxilla's seed
RIDGE_MM = 5.0
#: bone next to a lone run of teeth on its other side, as a share of the bone on its
#: busier side, that tells two arches in occlusion (a lone arch has soft tissue or air
#: beyond its crowns)
OCCLUSION_BONE = 0.25
#: least share of the teeth on each side of an occlusion split (else one arch)
MIN_ARCH_SHARE = 0.15
#: samples (mm) farther than this from the fitted occlusal surface are left out of the fit
OCCLUSAL_TRIM = 2.0
#: fewest columns with a contact gap that fit an occlusal surface
MIN_SAMPLES = 20
#: half width (mm) of an edentulous maxilla about the lower arch's midline (the maxillary
#: arch is 55-65 mm wide over its tuberosities)
MAXILLA_HALF_WIDTH = 30.0
#: reach (mm) of an edentulous maxilla in front of the lower teeth's front (an open mouth
#: swings them back under the upper alveolar ridge)
MAXILLA_AHEAD = 20.0
#: depth (mm) of an edentulous maxilla behind the lower teeth's front (the hard palate is
#: 45-50 mm long, from the incisive papilla to the posterior nasal spine)
MAXILLA_DEPTH = 60.0


def segment_volumes(labels):
    """Volume (mL) of each bone segment of ``labels``'s ``bone`` array.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.bone_segments import segment_volumes
    >>> img = pv.ImageData(dimensions=(10, 10, 10))
    >>> img[arrays.BONE] = np.full(1000, arrays.MANDIBLE, dtype=np.uint8)
    >>> segment_volumes(img)
    {'mandible': 1.0}
    """
    bone = np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu"))
    counts = np.array([np.count_nonzero(bone == i) for i in range(len(arrays.BONE_NAMES))])
    if counts.sum() != bone.size:  # other ids: count them all
        counts = np.bincount(bone.astype(np.int64), minlength=len(arrays.BONE_NAMES))
    voxel = float(np.prod(labels.spacing)) / 1000.0
    return {arrays.BONE_NAMES.get(i, f"bone_{i}"): float(counts[i] * voxel)
            for i in np.flatnonzero(counts) if i != arrays.BONE_NONE}


def find_jaws(labels, *, progress_bar=False):
    """Label cranium, Le Fort I maxilla and mandible from the anatomy of a segmented head.

    Parameters
    ----------
    labels : pyvista.ImageData
        Output of :func:`pvcmf.filters.segment` (point array ``tissue``), patient frame
        (z superior, y anterior).
    progress_bar : bool
        Log the stages at INFO level.

    Returns
    -------
    pyvista.ImageData
        A copy of ``labels`` whose ``bone`` array is CRANIUM, MAXILLA or MANDIBLE on every
        hard-tissue voxel (BONE_TISSUE, TEETH, METAL) and BONE_NONE elsewhere.

    Raises
    ------
    TypeError
        If ``labels`` is not an ImageData.
    ValueError
        If there is no tissue array, no hard tissue or no teeth (give the plan cut planes).
    """
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    say = log.info if progress_bar else log.debug
    tissue = np.asarray(arrays.require_array(labels, arrays.TISSUE, "point", dtype="u",
                                             producer="segment"))
    dims = tuple(int(d) for d in labels.dimensions)
    spacing = np.asarray(labels.spacing, float)
    tissue = tissue.reshape(dims, order="F")
    hard_all = np.zeros(dims, dtype=bool, order="F")
    for label in arrays.HARD_LABELS:  # comparisons in memory order, no flattening copy
        hard_all |= tissue == label
    if not hard_all.any():
        raise ValueError("find_jaws: the image has no hard tissue (tissue BONE/TEETH/METAL)")
    box = _bounds(hard_all, 0)
    # C-ordered copies of the bone's box: labelling and elementwise operations on the
    # Fortran-ordered image (or mixed orders) run several times slower
    hard = _c_copy(hard_all[box])
    tissue = _c_copy(tissue[box])
    teeth = (tissue == arrays.TEETH) | (tissue == arrays.METAL)
    teeth &= _far_from(tissue == arrays.INTRACRANIAL, spacing, SKULL_BASE_MM)
    if teeth.sum() < 10:
        raise ValueError("find_jaws: fewer than 10 tooth voxels: cannot find the jaws from the "
                         "anatomy; give the plan's osteotomies cut planes")
    z_occ, upper, lower, contact = _arches(teeth, hard, spacing)
    say("find_jaws: occlusal level at slice %d of the bone box (%d upper, %d lower tooth "
        "voxels)", z_occ, int(upper.sum()), int(lower.sum()))
    mandible = _mandible(hard, upper, lower, z_occ, spacing, contact)
    maxilla = _maxilla(hard & ~mandible, upper, lower, tissue == arrays.AIR, z_occ, spacing)
    bone = np.zeros(dims, dtype=np.uint8, order="F")
    sub = np.where(hard, arrays.CRANIUM, arrays.BONE_NONE).astype(np.uint8)
    sub[maxilla] = arrays.MAXILLA
    sub[mandible] = arrays.MANDIBLE
    bone[box] = sub
    out = labels.copy()
    out[arrays.BONE] = bone.ravel(order="F")
    voxel = float(np.prod(spacing)) / 1000.0
    log.info("find_jaws: segments (mL) %s", ", ".join(
        f"{arrays.BONE_NAMES[i]} {np.count_nonzero(sub == i) * voxel:.1f}"
        for i in (arrays.CRANIUM, arrays.MAXILLA, arrays.MANDIBLE)))
    return out


def _bounds(mask, margin):
    """Index box of a non-empty mask, ``margin`` voxels wider (projections, no index
    arrays of every voxel)."""
    box = []
    for axis in range(3):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        box.append(slice(max(int(hit[0]) - margin, 0),
                         min(int(hit[-1]) + margin + 1, mask.shape[axis])))
    return tuple(box)


def _far_from(mask, spacing, distance):
    """Voxels farther than ``distance`` mm from ``mask`` (distance on a 2x coarser grid)."""
    if not mask.any():
        return np.ones(mask.shape, dtype=bool)
    coarse = np.ascontiguousarray(mask[::2, ::2, ::2])
    far = _beyond(~coarse, 2 * spacing, distance)
    for ax in range(3):
        far = np.repeat(far, 2, axis=ax)
    return far[tuple(slice(0, n) for n in mask.shape)]


def _arches(teeth, hard, spacing):
    """Occlusal slice, the upper and lower tooth voxels and the hard voxels of their contact
    (None where the arches are apart: the occlusal slice separates them).

    Two arches: the slice of fewest tooth voxels between the two largest peaks of the teeth's
    height profile. One arch (an edentulous jaw, or an open mouth whose arches share no
    slice of teeth): the arch is the lower one when its footprint holds more bone in the
    ``ALVEOLAR_MM`` below the teeth than above them (the alveolar process and the body
    hold the roots below the lower crowns, the alveolar process and palate above the upper
    ones), and the occlusal level is at its crowns' free end.
    """
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
        split = _occlusion(teeth, hard, spacing, lo, hi)
        if split is not None:
            return split
        log.warning("find_jaws: the teeth have the bone of both jaws beside them (arches in "
                    "occlusion?), but no occlusal surface shows between them (slices %.1f mm "
                    "apart); taken as one arch: the segments may be wrong, give the plan cut "
                    "planes", spacing[2])
    if below >= above:
        log.info("find_jaws: one dental arch, the lower one (bone below it %d, above %d "
                 "voxels); no upper tooth", below, above)
        return hi, none, teeth.copy(), None
    log.info("find_jaws: one dental arch, the upper one (bone below it %d, above %d voxels); "
             "no lower tooth", below, above)
    return lo - 1, teeth.copy(), none, None


def _occlusion(teeth, hard, spacing, lo, hi):
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
    log.debug("find_jaws: occlusal surface from %d of %d columns, %d upper, %d lower tooth "
              "voxels", int(keep.sum()), len(zs), n_up, n_low)
    if min(n_up, n_low) < MIN_ARCH_SHARE * (n_up + n_low):
        return None
    foot = _arch_area(teeth.any(axis=2), spacing)
    contact = hard & (np.abs(zz - surf[:, :, None]) < 1.0) & foot[:, :, None]
    log.info("find_jaws: the dental arches touch (occlusion): %d upper and %d lower tooth "
             "voxels either side of the occlusal surface", n_up, n_low)
    z_low = int(np.floor(surf[foot].min())) if foot.any() else lo
    return max(z_low, 0), upper, lower, contact


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
    """Least-squares quadratic surface z(x, y) (coordinates centred for conditioning)."""
    c = pts.mean(axis=0)
    coef, *_ = np.linalg.lstsq(_quadric_terms(pts - c), z, rcond=None)
    return c, coef


def _quadric(pts, fit):
    c, coef = fit
    return _quadric_terms(pts - c) @ coef


def _mandible(hard, upper, lower, z_occ, spacing, contact=None):
    """Hard tissue connected to the lower teeth, split from the skull along the narrowest cut
    where they touch (see module); none without lower teeth (a scan cut above them).
    ``contact``: the upper side of the arches' contact surface, for arches in occlusion (cut
    instead of the occlusal slice)."""
    if not lower.any():
        log.warning("find_jaws: no lower tooth: no mandible found")
        return np.zeros_like(hard)
    # split the tooth contacts: the occlusal slab inside the arch footprint
    foot = ndimage.binary_dilation((upper | lower).any(axis=2),
                                   iterations=max(1, int(round(3.0 / spacing[0]))))
    cut = hard.copy()
    if contact is not None:
        cut &= ~contact
    elif upper.any():
        cut[:, :, z_occ][foot] = False
    lab, _ = ndimage.label(cut, _FACES)
    ids = np.bincount(lab[lower & cut], minlength=lab.max() + 1)
    ids[0] = 0
    if not ids.any():
        log.warning("find_jaws: the occlusal split leaves no lower tooth: no mandible found")
        return np.zeros_like(hard)
    jaw = lab == int(np.argmax(ids))
    top = np.zeros_like(hard)
    top[:, :, -max(1, int(round(5.0 / spacing[2]))):] = True
    anchor = (upper | top) & jaw  # what must not be mandible
    if anchor.any():
        jaw, area = narrowest_cut(jaw, _under_teeth(lower, spacing) & ~anchor, anchor, spacing)
        log.info("find_jaws: the lower teeth's bone is joined to the skull (the joints or "
                 "the teeth touch); split along the narrowest cut, %.0f mm^2", area)
    else:
        log.debug("find_jaws: the mandible is free of the skull")
    return _regrow(jaw, cut, hard, spacing) & ~upper


def _under_teeth(lower, spacing):
    """The lower teeth and the ``ALVEOLAR_MM`` below their lowest voxel inside their
    footprint (3 mm wider): the alveolar process and the body that hold their roots,
    mandible for sure."""
    foot = ndimage.binary_dilation(lower.any(axis=2),
                                   iterations=max(1, int(round(3.0 / spacing[0]))))
    z_low = int(np.nonzero(lower.any(axis=(0, 1)))[0][0])
    out = lower.copy()
    out[:, :, max(z_low - int(round(ALVEOLAR_MM / spacing[2])), 0):z_low + 1] |= foot[:, :, None]
    return out


def _regrow(jaw, work, hard, spacing):
    """The hard voxels nearer to ``jaw`` than to the rest of ``work``: the voxels the
    occlusal cut removed from ``hard`` go back to the nearer side. Only the jaw's box, 2
    voxels wider, can change."""
    box = _bounds(jaw, 2)
    seeds = np.where(jaw[box], 1, np.where(work[box], 2, 0)).astype(np.uint8)
    _, idx = ndimage.distance_transform_edt(seeds == 0, sampling=spacing,
                                            return_indices=True)
    out = np.zeros_like(hard)
    out[box] = (seeds[tuple(idx)] == 1) & hard[box]
    return out


def _maxilla(rest, upper, lower, air, z_occ, spacing):
    """Le Fort I segment of the non-mandible hard tissue ``rest`` (see module)."""
    teeth = upper if upper.any() else lower
    if not teeth.any():
        return np.zeros_like(rest)
    if upper.any():
        foot = ndimage.binary_dilation(teeth.any(axis=2),
                                       iterations=max(1, int(round(5.0 / spacing[0]))))
        z_top = int(np.nonzero(upper)[2].max())
        z_floor = _nasal_floor(rest, air, foot, z_top, spacing)
    else:  # edentulous: the alveolar ridge, the lowest RIDGE_MM of bone over the maxilla's area
        foot = _edentulous_area(lower, spacing)
        z_bone = np.flatnonzero((rest & foot[:, :, None])[:, :, z_occ + 1:].any(axis=(0, 1)))
        if not len(z_bone):
            log.warning("find_jaws: no upper tooth and no bone over the lower arch; no maxilla")
            return np.zeros_like(rest)
        z_ridge = z_occ + 1 + int(z_bone[0])
        z_top = z_ridge + int(round(RIDGE_MM / spacing[2]))
        z_floor = _nasal_floor(rest, air, foot & _midline_band(foot, spacing), z_ridge, spacing)
    z_cut = max(z_floor + int(round(LEFORT_ABOVE_FLOOR / spacing[2])), z_top + 1)
    if upper.any():
        y_back = min(int(np.nonzero(upper)[1].min()) - int(round(POSTERIOR_MARGIN / spacing[1])),
                     _palate_end(rest, air, foot, z_occ, z_floor, spacing))
    else:
        y_back = _posterior_nasal_spine(rest, foot, z_floor + int(round(MUCOSA_MM / spacing[2])),
                                        spacing)
    region = rest.copy()
    region[:, :, z_cut:] = False
    region[:, :, :max(z_occ - int(round(5.0 / spacing[2])), 0)] = False
    region[:, :max(y_back, 0), :] = False
    # seeds: the upper teeth, or (edentulous) the alveolar ridge over the lower arch
    seeds = upper & rest if upper.any() else region & foot[:, :, None]
    seeds[:, :, z_top + 1:] = False
    if not seeds.any():
        log.warning("find_jaws: no upper tooth and no alveolar ridge over the lower arch; "
                    "no maxilla")
        return np.zeros_like(rest)
    lab, _ = ndimage.label(region | seeds, _CUBE)
    keep = np.zeros(lab.max() + 1, dtype=bool)
    keep[np.unique(lab[seeds])] = True
    keep[0] = False
    log.debug("find_jaws: Le Fort I below slice %d (nasal floor %d, upper teeth top %d), "
              "in front of y index %d (posterior nasal spine)", z_cut, z_floor, z_top, y_back)
    return keep[lab] | (upper & rest)


def _nasal_floor(rest, air, foot, z_top, spacing, fallback=None):
    """Slice of the nasal floor: the lowest slice within ``NASAL_SEARCH_MM`` above ``z_top``
    where the palate (non-mandible bone over the arch's footprint) has air at most
    ``MUCOSA_MM`` above it over at least ``PALATE_MM2`` (higher up, the floors of the orbits
    and the roofs of the sinuses can have as much); else the lowest slice there with half
    the largest such area (at least ``PALATE_MIN_MM2``); else ``fallback``, or (None given)
    15 mm above the teeth, with a warning."""
    reach = max(1, int(round(MUCOSA_MM / spacing[2])))
    air_above = np.zeros_like(air)
    for k in range(1, reach + 1):  # a few shifts along z
        air_above[:, :, :-k] |= air[:, :, k:]
    on_bone = rest & air_above & foot[:, :, None]
    area = on_bone.sum(axis=(0, 1)) * spacing[0] * spacing[1]
    area[:z_top + 1] = 0
    near = area[:z_top + 1 + int(round(NASAL_SEARCH_MM / spacing[2]))]
    z = np.flatnonzero(near >= PALATE_MM2)
    if len(z):
        return int(z[0])
    # a narrow nasal cavity (swollen mucosa, turbinates) or thick slices (partial volume
    # hides the thin mucosa's air): the lowest slice with half the largest such area
    if near.max() >= PALATE_MIN_MM2:
        z = int(np.flatnonzero(near >= 0.5 * near.max())[0])
        log.info("find_jaws: nasal floor at slice %d, where the palate has %.0f mm^2 of nasal "
                 "air within %.0f mm above it", z, area[z], MUCOSA_MM)
        return z
    if fallback is not None:
        return fallback
    log.warning("find_jaws: no nasal floor found above the teeth; the Le Fort I level is "
                "15 mm above them")
    return z_top + int(round(15.0 / spacing[2]))


def _edentulous_area(lower, spacing):
    """Where an edentulous maxilla lies, seen from above: ``MAXILLA_HALF_WIDTH`` mm either
    side of the lower arch's midline, from ``MAXILLA_AHEAD`` mm in front of the lower
    teeth's front (an open mouth swings them down and back) to ``MAXILLA_DEPTH`` mm behind
    it (the hard palate to the posterior nasal spine)."""
    ij = np.argwhere(lower.any(axis=2))
    xc = 0.5 * (ij[:, 0].min() + ij[:, 0].max())
    front = int(ij[:, 1].max())
    half = MAXILLA_HALF_WIDTH / spacing[0]
    area = np.zeros(lower.shape[:2], dtype=bool)
    area[max(int(np.ceil(xc - half)), 0):int(xc + half) + 1,
         max(front - int(round(MAXILLA_DEPTH / spacing[1])), 0):
         front + int(round(MAXILLA_AHEAD / spacing[1])) + 1] = True
    return area


def _midline_band(foot, spacing):
    """The columns within ``NASAL_HALF_WIDTH`` mm of the footprint's midline (the nasal
    floor, medial to the maxillary sinuses that may reach lower)."""
    band = np.zeros_like(foot)
    xs = np.flatnonzero(foot.any(axis=1))
    xc, half = 0.5 * (xs[0] + xs[-1]), NASAL_HALF_WIDTH / spacing[0]
    band[int(np.ceil(xc - half)):int(xc + half) + 1] = True
    return band


def _palate_end(rest, air, foot, z_occ, z_floor, spacing):
    """y index of the back end of the hard palate under the nasal cavity (the posterior nasal
    spine) of a dentate maxilla: the nasal floor is sought above the occlusal level in the
    midline +-``NASAL_HALF_WIDTH`` mm (the maxillary sinuses beside it may reach lower than
    the nasal floor, the roots higher; ``z_floor``, the floor over the whole arch, where
    the midline shows none), and the palate followed back in its top ``MUCOSA_MM``, just
    under the nasal air."""
    z_floor = _nasal_floor(rest, air, foot & _midline_band(foot, spacing), z_occ, spacing,
                           fallback=z_floor)
    return _posterior_nasal_spine(rest, foot, z_floor + int(round(MUCOSA_MM / spacing[2])),
                                  spacing)


def _posterior_nasal_spine(rest, foot, z_floor, spacing):
    """y index of the posterior nasal spine: the back end of the hard palate in the midline
    (the 4 mm below the nasal floor, the midline +-3 mm of the arch), followed from the
    arch's front to the first gap of 3 mm; the pterygomaxillary junction, where Le Fort I
    separates the maxilla from the pterygoid plates, lies in about its coronal plane."""
    xs = np.flatnonzero(foot.any(axis=1))
    xc = int(round(0.5 * (xs[0] + xs[-1])))
    half = max(1, int(round(3.0 / spacing[0])))
    z0 = max(z_floor - int(round(4.0 / spacing[2])), 0)
    palate = rest[max(xc - half, 0):xc + half + 1, :, z0:z_floor + 1].any(axis=(0, 2))
    front = int(np.flatnonzero(foot.any(axis=0)).max())
    bone_y = np.flatnonzero(palate[:front + 1])[::-1]  # from the front backwards
    if not len(bone_y):
        return int(np.flatnonzero(foot.any(axis=0)).min())
    gap = max(1, int(round(3.0 / spacing[1])))
    big = np.flatnonzero(-np.diff(bone_y) > gap)
    return int(bone_y[big[0]]) if len(big) else int(bone_y[-1])
