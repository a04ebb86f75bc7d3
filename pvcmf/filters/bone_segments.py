"""Bone segments from the anatomy: mandible and Le Fort I maxilla without cut planes.

:func:`find_jaws` labels, in a segmented head (``tissue`` with hard tissue, teeth and metal),
on the bone's box turned level with the dental arches where they tilt
(:mod:`pvcmf.filters.jaw_pose`; the labels found there are turned back):

* the **occlusal level** (:func:`pvcmf.filters.dental_arches.dental_arches`): the axial
  plane of fewest tooth voxels between the upper and the lower dental arch. Teeth in
  occlusion are split by the **occlusal surface** instead, and the hard tissue along it,
  over the arch and in front of it, is cut;
* the **mandible**: the hard tissue, split at the occlusal level inside the dental arch's
  footprint (where the upper and lower teeth touch), connected to the lower teeth. Where
  that part still holds the upper teeth, the skull's top or bone ``SKULL_ABOVE_MM`` above
  the occlusal level (the condyles touch their fossae: a joint space lost to thick slices
  or partial volume; teeth in contact beyond the arch), it is split along its narrowest
  cut
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
from scipy.spatial import cKDTree

from .. import arrays
from .morphology import _beyond, _c_copy
from .dental_arches import ALVEOLAR_MM, dental_arches
from .jaw_pose import MIN_ARCH_SPAN_MM, Level, arch_pose, arch_span, pitch
from .narrowest_cut import narrowest_cut

log = logging.getLogger(__name__)

__all__ = ["find_jaws", "segment_volumes", "transfer_segments"]

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
#: smallest area (mm^2) of nasal floor seen on the palate in one slice
PALATE_MM2 = 50.0
#: least area (mm^2) of nasal floor seen on the palate in one slice of a narrow nasal cavity
PALATE_MIN_MM2 = 10.0
#: height (mm) above the occlusal level that no mandible reaches: the condyles and the
#: coronoid processes rise 25-35 mm above the occlusal plane, which crosses the ramus about
#: half-way up (at the mandibular foramen), the ramus being 55-65 mm high
SKULL_ABOVE_MM = 50.0
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
    say = log.info if progress_bar else log.debug
    dims, spacing, box, hard, tissue, teeth = _jaw_box(labels, "find_jaws")
    turn, tilt, arches, normal = arch_pose(teeth, hard, spacing)
    if turn is None:
        sub = _segments(tissue, hard, teeth, spacing, say, arches)
    else:
        log.info("find_jaws: the dental arches tilt %.1f degrees from the axial plane; the "
                 "segments are found on the image turned level with them", tilt)
        level = Level(hard.shape, spacing, turn)
        # one resampling: the dense bone by the skull base that is not teeth goes as bone
        dense = np.isin(tissue, (arrays.TEETH, arrays.METAL))
        turned = level.forward(np.where(dense & ~teeth, arrays.BONE_TISSUE, tissue),
                               cval=arrays.AIR)
        cut = _bounds(np.isin(turned, arrays.HARD_LABELS), 0)
        turned = _c_copy(turned[cut])
        found = np.zeros(level.level_shape, dtype=np.uint8)
        found[cut] = _segments(turned, np.isin(turned, arrays.HARD_LABELS),
                               np.isin(turned, (arrays.TEETH, arrays.METAL)), spacing, say)
        sub = level.back(found, hard)
        sub[hard & (sub == arrays.BONE_NONE)] = arrays.CRANIUM
        # the nearest-voxel round trip can cut a one-voxel link: the mandible is one bone
        pieces, n = ndimage.label(sub == arrays.MANDIBLE, _CUBE)
        if n > 1:
            largest = 1 + int(np.argmax(np.bincount(pieces.ravel())[1:]))
            sub[(pieces > 0) & (pieces != largest)] = arrays.CRANIUM
    bone = np.zeros(dims, dtype=np.uint8, order="F")
    bone[box] = sub
    out = labels.copy()
    out[arrays.BONE] = bone.ravel(order="F")
    if normal is not None:
        out.field_data[arrays.ARCH_PITCH] = np.array([pitch(normal)])
        out.field_data[arrays.ARCH_NORMAL] = np.asarray(normal, dtype=float)
        out.field_data[arrays.ARCH_SPAN] = np.array([arch_span(teeth, spacing, normal)])
    voxel = float(np.prod(spacing)) / 1000.0
    log.info("find_jaws: segments (mL) %s", ", ".join(
        f"{arrays.BONE_NAMES[i]} {np.count_nonzero(sub == i) * voxel:.1f}"
        for i in (arrays.CRANIUM, arrays.MAXILLA, arrays.MANDIBLE)))
    return out


def _segments(tissue, hard, teeth, spacing, say, arches=None):
    """Bone labels (BONE_NONE, CRANIUM, MAXILLA, MANDIBLE) of the hard voxels of a box whose
    axial slices are level with the dental arches (``arches``: their
    :func:`~pvcmf.filters.dental_arches.dental_arches`, if known)."""
    if arches is None:
        arches = dental_arches(teeth, hard, spacing)
    z_occ, upper, lower, contact = arches
    say("find_jaws: occlusal level at slice %d of the bone box (%d upper, %d lower tooth "
        "voxels)", z_occ, int(upper.sum()), int(lower.sum()))
    mandible = _mandible(hard, upper, lower, z_occ, spacing, contact)
    maxilla = _maxilla(hard & ~mandible, upper, lower, tissue == arrays.AIR, z_occ, spacing)
    sub = np.where(hard, arrays.CRANIUM, arrays.BONE_NONE).astype(np.uint8)
    sub[maxilla] = arrays.MAXILLA
    sub[mandible] = arrays.MANDIBLE
    return sub


def _jaw_box(labels, caller):
    """The box of the hard tissue of ``labels`` and, in it (C order), the hard tissue, the
    tissue labels and the teeth away from the skull base: ``(dims, spacing, box, hard,
    tissue, teeth)``."""
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    tissue = np.asarray(arrays.require_array(labels, arrays.TISSUE, "point", dtype="u",
                                             producer="segment"))
    dims = tuple(int(d) for d in labels.dimensions)
    spacing = np.asarray(labels.spacing, float)
    tissue = tissue.reshape(dims, order="F")
    hard_all = np.zeros(dims, dtype=bool, order="F")
    for label in arrays.HARD_LABELS:  # comparisons in memory order, no flattening copy
        hard_all |= tissue == label
    if not hard_all.any():
        raise ValueError(f"{caller}: the image has no hard tissue (tissue BONE/TEETH/METAL)")
    box = _bounds(hard_all, 0)
    # C-ordered copies of the bone's box: labelling and elementwise operations on the
    # Fortran-ordered image (or mixed orders) run several times slower
    hard = _c_copy(hard_all[box])
    tissue = _c_copy(tissue[box])
    teeth = (tissue == arrays.TEETH) | (tissue == arrays.METAL)
    teeth &= _far_from(tissue == arrays.INTRACRANIAL, spacing, SKULL_BASE_MM)
    if teeth.sum() < 10:
        raise ValueError(f"{caller}: fewer than 10 tooth voxels: cannot find the jaws from the "
                         "anatomy; give the plan's osteotomies cut planes")
    return dims, spacing, box, hard, tissue, teeth


def occlusal_plane(labels):
    """Unit normal (superior) of the upper dental arch's plane in ``labels`` and the teeth's
    spread across their row in it (mm): the values :func:`find_jaws` keeps as
    ``arrays.ARCH_NORMAL`` and ``ARCH_SPAN``, else measured as it measures them
    (:func:`~pvcmf.filters.jaw_pose.arch_pose`, :func:`~pvcmf.filters.jaw_pose.arch_span`).

    Raises
    ------
    ValueError
        Fewer than 10 tooth voxels, or teeth that form no flat arch.
    """
    fd = labels.field_data
    if arrays.ARCH_NORMAL in fd and arrays.ARCH_SPAN in fd:
        normal = np.asarray(fd[arrays.ARCH_NORMAL], dtype=float).ravel()
        return normal / np.linalg.norm(normal), float(np.asarray(fd[arrays.ARCH_SPAN]).ravel()[0])
    _, spacing, _, hard, _, teeth = _jaw_box(labels, "occlusal_normal")
    normal = arch_pose(teeth, hard, spacing)[3]
    if normal is None:
        raise ValueError("occlusal_normal: the teeth of labels form no flat dental arch "
                         "(a few front teeth alone, or none): no occlusal plane to plan in")
    return np.asarray(normal, dtype=float), arch_span(teeth, spacing, normal)


def occlusal_normal(labels):
    """The normal of :func:`occlusal_plane`, refused where the teeth span a row rather than
    an arch (less than :data:`~pvcmf.filters.jaw_pose.MIN_ARCH_SPAN_MM` across it: the
    plane of a row may turn about it, so it gives no plane to plan in).

    Raises
    ------
    ValueError
        As :func:`occlusal_plane`, or a row of teeth.
    """
    normal, span = occlusal_plane(labels)
    if span < MIN_ARCH_SPAN_MM:
        raise ValueError(
            f"occlusal_normal: the teeth found spread {span:.1f} mm across their row (an arch "
            f"spreads 12-15 mm; at least {MIN_ARCH_SPAN_MM:g}): a row of front teeth (the "
            "others missing, or below the image's teeth level) gives no occlusal plane to "
            "plan in; use axes = 'frankfort' with landmarks, or 'image'")
    return normal


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
    top = np.zeros_like(hard)  # the skull's top, and what is too high for any mandible
    top[:, :, min(z_occ + int(round(SKULL_ABOVE_MM / spacing[2])), hard.shape[2] - 1):] = True
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


def transfer_segments(labels, bones):
    """A copy of ``labels`` whose hard tissue takes, voxel by voxel, the segment id
    (``bone``) of the nearest ``bones`` voxel of a segment (a distance transform where
    both images share a grid, else a :class:`scipy.spatial.cKDTree` query): the segments
    of another label image (e.g. a virtual patient's ``truth``), on any grid."""
    ref = np.asarray(arrays.require_array(bones, arrays.BONE, "point", dtype="iu"))
    ours = np.asarray(labels[arrays.BONE]) if arrays.BONE in labels.point_data else None
    tissue = np.asarray(labels[arrays.TISSUE])
    hard = np.isin(tissue, arrays.HARD_LABELS) | ((ours > 0) if ours is not None else False)
    same = (tuple(bones.dimensions) == tuple(labels.dimensions)
            and np.allclose(bones.origin, labels.origin)
            and np.allclose(bones.spacing, labels.spacing))
    new = np.zeros(labels.n_points, dtype=np.uint8)
    if same:
        vol = ref.reshape(tuple(bones.dimensions), order="F")
        _, idx = ndimage.distance_transform_edt(vol == 0, sampling=bones.spacing,
                                                return_indices=True)
        nearest = vol[tuple(idx)].ravel(order="F")
        new[hard] = nearest[hard]
    else:
        ref_pts = np.asarray(bones.points)[ref > 0]
        _, near = cKDTree(ref_pts).query(np.asarray(labels.points)[hard])
        new[hard] = ref[ref > 0][near]
    out = labels.copy()
    out[arrays.BONE] = new
    return out
