"""Bone segments from the anatomy: mandible and Le Fort I maxilla without cut planes.

:func:`find_jaws` labels, in a segmented head (``tissue`` with hard tissue, teeth and metal):

* the **occlusal level**: the axial plane of fewest tooth voxels between the upper and the
  lower dental arch (the two largest peaks of the tooth voxels' height profile);
* the **mandible**: the hard tissue, split at the occlusal level inside the dental arch's
  footprint (where the upper and lower teeth touch), is eroded one voxel at a time until the
  part holding the lower teeth no longer holds the upper teeth or the skull's top (the
  temporomandibular joints and tooth contacts give way first); the removed voxels go back to
  the nearest part (a nearest-label fill, :func:`scipy.ndimage.distance_transform_edt`);
* the **maxilla** (Le Fort I): the remaining hard tissue from the occlusal level up to
  ``LEFORT_ABOVE_FLOOR`` mm above the nasal floor (the lowest air inside the head above the
  upper teeth: the cut runs through the lateral nasal walls and the maxillary sinuses, the
  palate and the tooth roots stay below it), in front of the pterygoid region (a margin
  behind the last upper tooth) and joined to the upper teeth; every upper tooth is in it.

Everything else is ``CRANIUM``. Delegates to :mod:`scipy.ndimage` (labelling, erosion,
distance transforms); no loop over voxels.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays

log = logging.getLogger(__name__)

__all__ = ["find_jaws", "segment_volumes"]

_FACES = ndimage.generate_binary_structure(3, 1)
_CUBE = np.ones((3, 3, 3), dtype=bool)
#: margin (mm) behind the last upper tooth where the Le Fort I cut ends (pterygoid plates)
POSTERIOR_MARGIN = 25.0
#: height (mm) of the Le Fort I cut above the nasal floor: through the lateral nasal walls
#: and the maxillary sinuses, the palate and every root below it
LEFORT_ABOVE_FLOOR = 6.0
#: dense bone (petrous temporal bone) this close (mm) to the intracranial volume is no tooth
SKULL_BASE_MM = 15.0
#: most erosion steps tried to free the mandible from the skull
MAX_EROSION = 4


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
    hard_all = np.isin(tissue, arrays.HARD_LABELS)
    if not hard_all.any():
        raise ValueError("find_jaws: the image has no hard tissue (tissue BONE/TEETH/METAL)")
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in np.nonzero(hard_all))
    hard = hard_all[box]
    teeth = np.isin(tissue[box], (arrays.TEETH, arrays.METAL))
    teeth &= _far_from(tissue[box] == arrays.INTRACRANIAL, spacing, SKULL_BASE_MM)
    if teeth.sum() < 10:
        raise ValueError("find_jaws: fewer than 10 tooth voxels: cannot find the jaws from the "
                         "anatomy; give the plan's osteotomies cut planes")
    z_occ = _occlusal_level(teeth, spacing)
    say("find_jaws: occlusal level at slice %d of the bone box", z_occ)
    upper = teeth.copy()
    upper[:, :, :z_occ + 1] = False
    lower = teeth & ~upper
    mandible = _mandible(hard, upper, lower, z_occ, spacing)
    maxilla = _maxilla(hard & ~mandible, upper, tissue[box] == arrays.AIR, z_occ, spacing)
    bone = np.zeros(dims, dtype=np.uint8)
    sub = np.where(hard, arrays.CRANIUM, arrays.BONE_NONE).astype(np.uint8)
    sub[maxilla] = arrays.MAXILLA
    sub[mandible] = arrays.MANDIBLE
    bone[box] = sub
    out = labels.copy()
    out[arrays.BONE] = bone.ravel(order="F")
    log.info("find_jaws: segments (mL) %s", ", ".join(
        f"{k} {v:.1f}" for k, v in segment_volumes(out).items()))
    return out


def _far_from(mask, spacing, distance):
    """Voxels farther than ``distance`` mm from ``mask`` (distance on a 2x coarser grid)."""
    if not mask.any():
        return np.ones(mask.shape, dtype=bool)
    coarse = mask[::2, ::2, ::2]
    far = ndimage.distance_transform_edt(~coarse, sampling=2 * spacing) > distance
    for ax in range(3):
        far = np.repeat(far, 2, axis=ax)
    return far[tuple(slice(0, n) for n in mask.shape)]


def _occlusal_level(teeth, spacing):
    """Slice index between the upper and lower teeth: fewest tooth voxels between peaks."""
    profile = teeth.sum(axis=(0, 1)).astype(float)
    smooth = ndimage.gaussian_filter1d(profile, max(1.0, 1.5 / spacing[2]))
    z = np.flatnonzero(profile)
    lo, hi = int(z[0]), int(z[-1])
    if hi - lo < 2:
        return lo
    peaks = [i for i in range(lo, hi + 1)
             if smooth[i] >= smooth[max(i - 1, 0)] and smooth[i] > smooth[min(i + 1, hi)]]
    if len(peaks) < 2:  # one arch or one block: split at the middle of the teeth
        return (lo + hi) // 2
    a, b = sorted(sorted(peaks, key=lambda i: smooth[i])[-2:])
    return int(a + np.argmin(smooth[a:b + 1]))


def _mandible(hard, upper, lower, z_occ, spacing):
    """Hard tissue connected to the lower teeth once freed from the skull (see module)."""
    # split the tooth contacts: the occlusal slab inside the arch footprint
    foot = ndimage.binary_dilation((upper | lower).any(axis=2),
                                   iterations=max(1, int(round(3.0 / spacing[0]))))
    cut = hard.copy()
    cut[:, :, z_occ][foot] = False
    top = np.zeros_like(hard)
    top[:, :, -max(1, int(round(5.0 / spacing[2]))):] = True
    anchor = (upper | top) & cut  # what must not be mandible
    work = cut
    for step in range(MAX_EROSION + 1):
        lab, _ = ndimage.label(work, _FACES)
        ids = np.bincount(lab[lower & work], minlength=lab.max() + 1)
        ids[0] = 0
        if not ids.any():
            break
        jaw = int(np.argmax(ids))
        if not np.any(lab[anchor & work] == jaw):
            seeds = np.where(lab == jaw, 1, np.where(work, 2, 0)).astype(np.uint8)
            _, idx = ndimage.distance_transform_edt(seeds == 0, sampling=spacing,
                                                    return_indices=True)
            log.debug("find_jaws: mandible free after %d erosion(s)", step)
            return (seeds[tuple(idx)] == 1) & hard
        work = ndimage.binary_erosion(work, _FACES)
    log.warning("find_jaws: the mandible stays joined to the skull after %d erosions; it is "
                "the lower teeth's part below the occlusal level", MAX_EROSION)
    below = hard.copy()
    below[:, :, z_occ + 1:] = False
    lab, _ = ndimage.label(below, _FACES)
    ids = np.bincount(lab[lower], minlength=lab.max() + 1)
    ids[0] = 0
    return lab == int(np.argmax(ids))


def _maxilla(rest, upper, air, z_occ, spacing):
    """Le Fort I segment of the non-mandible hard tissue ``rest`` (see module)."""
    if not upper.any():
        log.warning("find_jaws: no upper tooth found; no maxilla")
        return np.zeros_like(rest)
    ui = np.nonzero(upper)
    z_top = int(ui[2].max())
    foot = upper.any(axis=2)
    foot = ndimage.binary_dilation(foot, iterations=max(1, int(round(5.0 / spacing[0]))))
    # nasal floor: lowest air above the upper teeth over the dental arch
    above = air & foot[:, :, None]
    above[:, :, :z_top + 1] = False
    z_air = np.flatnonzero(above.any(axis=(0, 1)))
    z_floor = int(z_air[0]) if len(z_air) else z_top + int(round(15.0 / spacing[2]))
    z_cut = max(z_floor + int(round(LEFORT_ABOVE_FLOOR / spacing[2])), z_top + 1)
    region = rest.copy()
    region[:, :, z_cut:] = False
    region[:, :, :max(z_occ - int(round(5.0 / spacing[2])), 0)] = False
    y_back = int(ui[1].min()) - int(round(POSTERIOR_MARGIN / spacing[1]))
    region[:, :max(y_back, 0), :] = False
    lab, _ = ndimage.label(region | (upper & rest), _CUBE)
    keep = np.zeros(lab.max() + 1, dtype=bool)
    keep[np.unique(lab[upper & rest])] = True
    keep[0] = False
    log.debug("find_jaws: Le Fort I below slice %d (nasal floor %d, upper teeth top %d)",
              z_cut, z_floor, z_top)
    return keep[lab] | (upper & rest)
