"""CT -> tissue and bone labels (paper 000 section II): skin, skull, soft tissue, cavities.

The steps, all on the voxel grid with ``scipy.ndimage`` (``label``, ``binary_closing``,
``binary_erosion``)
and numpy boolean algebra, vectorised over the whole volume:

1. **head**: ``ct >= skin_threshold``, largest face-connected component (drops the table,
   head holder and noise, which do not touch the head); with ``fill_holes`` its small
   enclosed holes (noise, < ``min_cavity`` mm^3) become tissue, larger ones stay air.
2. **hard tissue**: ``ct >= bone_threshold`` inside the head; ``ct >= teeth_threshold`` is
   TEETH (enamel and dentine are denser than bone), the rest BONE. The ``bone`` segment array
   is ``CRANIUM`` on every hard voxel: splitting maxilla and mandible is
   :func:`pvcmf.filters.cut_bones`.
3. **intracranial volume**: the skull is closed with a ball of radius ``skull_closing`` mm
   (``scipy.ndimage.binary_closing``; 2.8x faster than a distance-transform closing at 3 mm,
   ``benchmarks/segment.py``), each axial
   slice of the closed skull has its holes filled (a slice-wise fill, so the foramen magnum
   and a skull vault cut off by the scan do not open the cavity), and the largest 3-D
   connected non-bone, non-air region enclosed this way is ``INTRACRANIAL``.
4. **extra-cranial soft tissue** = head minus hard tissue minus intracranial volume minus air
   cavities (the boolean difference of the paper), labelled ``FAT`` (generic soft tissue, see
   :func:`pvcmf.filters.classify_tissue` for fat/muscle). Air inside the head (sinuses,
   airway, mouth, nasal cavity) stays ``AIR``.

Index axis 2 of the image is taken as the axial (slice) axis.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays

log = logging.getLogger(__name__)

_FACES = ndimage.generate_binary_structure(3, 1)  # 6-connectivity
_FACES_2D = np.zeros((3, 3, 3), dtype=bool)
_FACES_2D[:, :, 1] = ndimage.generate_binary_structure(2, 1)  # in-slice 4-connectivity

#: default HU thresholds. Skin: half-way between air (-1000) and soft tissue (~0). Bone:
#: half-way between soft tissue (~40) and cancellous bone (~700-1000), where partial volume
#: puts the bone surface (on the virtual patients 300-400 HU grows the bone by a voxel layer,
#: hard-tissue Dice 0.90-0.94; 500 HU gives 0.97); lower it for thin bone (orbit floor,
#: sinus walls) in real scans. Teeth: enamel/dentine (~2500) above cortical bone (~1700).
SKIN_THRESHOLD = -500.0
BONE_THRESHOLD = 500.0
TEETH_THRESHOLD = 2000.0
#: smallest radius (voxels) of the skull-closing ball: 1.5 takes the in-slice diagonal
#: neighbours, which bridge a one-voxel gap in a one-voxel-thin skull ring
MIN_BALL_VOXELS = 1.5


def segment(
    ct,
    *,
    skin_threshold=SKIN_THRESHOLD,
    bone_threshold=BONE_THRESHOLD,
    teeth_threshold=TEETH_THRESHOLD,
    fill_holes=True,
    min_cavity=30.0,
    skull_closing=3.0,
    progress_bar=False,
):
    """Label a CT volume into air, soft tissue, bone, teeth and intracranial volume.

    Parameters
    ----------
    ct : pyvista.ImageData
        3-D image with a float point array ``ct`` in Hounsfield units.
    skin_threshold, bone_threshold, teeth_threshold : float
        HU thresholds, strictly increasing: air/skin, soft tissue/bone, bone/teeth.
    fill_holes : bool
        Fill enclosed holes of the head smaller than ``min_cavity`` (noise, partial volume)
        as tissue. Larger enclosed holes (sinuses, a closed airway) stay ``AIR`` either way.
    min_cavity : float
        Volume (mm^3) below which an enclosed air pocket is treated as a hole to fill.
    skull_closing : float
        Radius (mm) of the morphological closing that seals gaps in the skull (thin bone lost
        to partial volume, sutures, small foramina) before the intracranial fill; at least
        ``MIN_BALL_VOXELS`` (1.5) voxels along each axis.
    progress_bar : bool
        Log each stage at INFO level (otherwise DEBUG).

    Returns
    -------
    pyvista.ImageData
        A deep copy of ``ct`` (``ct`` kept) with point arrays ``tissue`` (uint8: AIR, FAT,
        BONE_TISSUE, TEETH, INTRACRANIAL) and ``bone`` (uint8: CRANIUM on hard tissue).

    Raises
    ------
    TypeError
        If ``ct`` is not an ImageData.
    ValueError
        If the ``ct`` array is missing, not float or has NaN/inf values, the image is not
        3-D, the thresholds are not finite and increasing, or a tissue class comes out empty
        (no head above ``skin_threshold``, no bone, no soft tissue): usually the values are
        not in HU (rescale them with :func:`pvcmf.read_ct`'s ``offset``/``scale``).

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> img = pv.ImageData(dimensions=(40, 40, 40), spacing=(2.0, 2.0, 2.0))
    >>> r = np.linalg.norm(img.points - img.center, axis=1)
    >>> img["ct"] = np.select([r < 20, r < 26, r < 34], [30.0, 1200.0, -100.0], -1000.0).astype(np.float32)
    >>> lab = img.cmf.segment()
    >>> from pvcmf import arrays
    >>> np.unique(lab["tissue"]).tolist()  # air, fat, bone, intracranial
    [0, 1, 3, 5]
    """
    say = log.info if progress_bar else log.debug
    vol, spacing = _validate(ct, skin_threshold, bone_threshold, teeth_threshold)
    for name, value in (("min_cavity", min_cavity), ("skull_closing", skull_closing)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")

    # 1. head: largest connected component above the skin threshold
    say("segment: head mask (threshold %.0f HU, largest component)", skin_threshold)
    above = vol >= skin_threshold
    head = _largest_component(above, _FACES)
    if head is None:
        raise ValueError(
            f"segment: no voxel is >= skin_threshold={skin_threshold} HU "
            f"(ct range [{vol.min():.0f}, {vol.max():.0f}]); are the values in HU?"
        )
    inside = _fill(head, _FACES)
    holes = inside & ~head
    if fill_holes and holes.any():
        lab, n = ndimage.label(holes, structure=_FACES)
        size_mm3 = np.bincount(lab.ravel())[1:] * float(np.prod(spacing))
        small = np.concatenate([[False], size_mm3 < min_cavity])
        head = head | small[lab]
        say("segment: filled %d small holes, kept %d air cavities", int(small.sum()),
            int(n - small.sum()))

    # 2. hard tissue
    hard = head & (vol >= bone_threshold)
    if not hard.any():
        raise ValueError(
            f"segment: no voxel inside the head is >= bone_threshold={bone_threshold} HU "
            f"(head ct range [{vol[head].min():.0f}, {vol[head].max():.0f}]); are the values in "
            "HU?"
        )
    teeth = hard & (vol >= teeth_threshold)

    # 3. intracranial volume
    say("segment: intracranial volume (closing %.1f mm, slice-wise fill)", skull_closing)
    intracranial = _intracranial(hard, head, spacing, skull_closing)
    if intracranial is None:
        log.warning("segment: found no volume enclosed by the skull; no INTRACRANIAL label")
        intracranial = np.zeros_like(hard)

    # 4. labels
    soft = head & ~hard & ~intracranial
    if not soft.any():
        raise ValueError(
            "segment: no extra-cranial soft tissue left between skin_threshold="
            f"{skin_threshold} and bone_threshold={bone_threshold} HU"
        )
    tissue = np.zeros(vol.shape, dtype=np.uint8)  # AIR
    tissue[soft] = arrays.FAT
    tissue[hard] = arrays.BONE_TISSUE
    tissue[teeth] = arrays.TEETH
    tissue[intracranial] = arrays.INTRACRANIAL
    bone = np.where(hard, arrays.CRANIUM, arrays.BONE_NONE).astype(np.uint8)

    out = ct.copy(deep=True)
    out.point_data[arrays.TISSUE] = tissue.ravel(order="F")
    out.point_data[arrays.BONE] = bone.ravel(order="F")
    out.point_data.active_scalars_name = arrays.TISSUE
    say(
        "segment: %d soft, %d bone, %d teeth, %d intracranial voxels",
        int(soft.sum()), int((hard & ~teeth).sum()), int(teeth.sum()), int(intracranial.sum()),
    )
    return out


# --------------------------------------------------------------------------- validation
def _validate(ct, skin_threshold, bone_threshold, teeth_threshold):
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"ct must be a pyvista.ImageData, got {type(ct).__name__}")
    values = arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                  producer="pvcmf.read_ct or pvcmf.datasets.phantom")
    dims = tuple(int(d) for d in ct.dimensions)
    if len(dims) != 3 or min(dims) < 2:
        raise ValueError(f"ct must be a 3-D image (every dimension >= 2), got dimensions {dims}")
    if not np.all(np.isfinite(values)):
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise ValueError(f"ct array 'ct' must be finite, got {bad} NaN/inf value(s)")
    names = ("skin_threshold", "bone_threshold", "teeth_threshold")
    thresholds = (skin_threshold, bone_threshold, teeth_threshold)
    for name, value in zip(names, thresholds):
        if not isinstance(value, (int, float, np.number)) or not math.isfinite(value):
            raise ValueError(f"{name} must be a finite number (HU), got {value!r}")
    if not skin_threshold < bone_threshold < teeth_threshold:
        raise ValueError(
            "thresholds must increase: skin_threshold < bone_threshold < teeth_threshold, got "
            f"{skin_threshold}, {bone_threshold}, {teeth_threshold}"
        )
    return values.reshape(dims, order="F"), np.asarray(ct.spacing, dtype=float)


# --------------------------------------------------------------------------- helpers
def _largest_component(mask, structure):
    lab, n = ndimage.label(mask, structure=structure)
    if n == 0:
        return None
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return lab == int(np.argmax(sizes))


def _fill(mask, structure, z_open=False):
    """Fill holes: background not connected to the array border (through ``structure``).

    With ``z_open`` the first and last slices do not count as border (for a slice-wise fill
    with an in-slice structure, every slice is then filled on its own).
    """
    lab, _ = ndimage.label(~mask, structure=structure)
    faces = [lab[0], lab[-1], lab[:, 0], lab[:, -1]]
    if not z_open:
        faces += [lab[:, :, 0], lab[:, :, -1]]
    outside = np.unique(np.concatenate([f.ravel() for f in faces]))
    keep = np.ones(lab.max() + 1, dtype=bool)
    keep[outside] = False
    keep[0] = False
    return mask | keep[lab]


def _ball(spacing, radius):
    """Ellipsoidal structuring element: the ball of ``radius`` mm (>= MIN_BALL_VOXELS voxels
    per axis)."""
    r_vox = np.maximum(radius / np.maximum(np.asarray(spacing, float), 1e-12), MIN_BALL_VOXELS)
    half = np.floor(r_vox).astype(int)
    grid = np.meshgrid(*(np.arange(-h, h + 1) for h in half), indexing="ij")
    return sum((g / r) ** 2 for g, r in zip(grid, r_vox)) <= 1.0 + 1e-9


def _closing(mask, spacing, radius):
    """Binary closing with a ball of ``radius`` mm, padded so the border does not erode."""
    ball = _ball(spacing, radius)
    pad = [(h + 1, h + 1) for h in np.array(ball.shape) // 2]
    closed = ndimage.binary_closing(np.pad(mask, pad), structure=ball)
    return closed[tuple(slice(a, -b) for a, b in pad)]


def _intracranial(hard, head, spacing, radius):
    # work in the bounding box of the hard tissue
    idx = np.nonzero(hard)
    box = tuple(slice(int(i.min()), int(i.max()) + 1) for i in idx)
    skull = _closing(hard[box], spacing, radius)
    enclosed = _fill(skull, _FACES_2D, z_open=True) & ~skull
    candidate = enclosed & head[box] & ~hard[box]
    brain = _largest_component(candidate, _FACES)
    if brain is None:
        return None
    out = np.zeros_like(hard)
    out[box] = brain
    return out
