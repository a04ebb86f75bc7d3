"""CT -> tissue and bone labels (paper 000 section II): skin, skull, teeth, metal, brain, air.

The steps, on the voxel grid with ``scipy.ndimage`` and numpy boolean algebra (no loop over
voxels), the costly decisions on a copy downsampled to about ``coarse`` mm:

1. **thresholds** from the image's own histogram (:func:`calibrate`): the air and the
   soft-tissue peaks give the scan's HU scale, and the skin, bone, teeth and metal levels are
   placed on it (half-way from air to soft tissue; then 0.48, 1.9 and 2.85 times the
   air-to-soft-tissue step above soft tissue: about -480, 520, 2000 and 3000 HU on a
   calibrated scan, whatever offset or scale the scanner's values have).
2. **head**: ``ct >= skin`` opened with a ball of ``object_opening`` mm (on the coarse copy),
   its largest component, grown back by the same radius within the threshold mask: the
   table, a headrest, sheets and tubes go even where they touch the skin, being thinner than
   the ball or joined to the head by a thinner neck. A film (a plastic wrap, a drape) lying
   on the skin across a thin air gap goes too (:func:`pvcmf.filters.surface_objects.drop_film`),
   and so do dense objects lying on the skin (:mod:`pvcmf.filters.surface_objects`). Small
   enclosed holes (< ``min_cavity`` mm^3) become tissue; larger ones (sinuses, airway) stay
   air.
3. **hard tissue**: ``ct >= bone`` in the head; ``>= teeth`` is TEETH (except the otic
   capsule of the petrous bone, as dense: near the intracranial volume, or apart from the
   dentition, :mod:`pvcmf.filters.teeth`); ``>= metal`` is
   METAL (fillings, crowns, plates), hard tissue of its segment. Around the metal
   (:mod:`pvcmf.filters.metal`) thin bright streaks are not bone and thin dark streaks are not
   air.
4. **intracranial volume** (:func:`_intracranial`): the skull is closed with a ball of
   ``skull_closing`` mm; the distance to it is flooded from the deepest point enclosed by
   the skull and from the air outside the head (a marker-based watershed, SimpleITK's
   ``MorphologicalWatershedFromMarkers``): the two floods meet at the narrowest passages,
   the orbital fissures, foramina and the foramen magnum, so the brain neither leaks through
   an open skull ring nor stops short of the inner table; a vault cut by the scan stays
   closed since the flood from outside cannot enter it. Without SimpleITK, an axial
   slice-wise fill of the closed skull is used (with a warning).
5. **soft tissue** = head minus hard tissue minus intracranial volume minus air cavities,
   labelled ``FAT`` (see :func:`pvcmf.filters.classify_tissue` for fat/muscle).

An image that shows no head (neither a cranial cavity nor teeth: a chest, a limb) is
refused first, on the measurements of :func:`pvcmf.io.orientation.standardize`
(:func:`pvcmf.io.head_check.check_head`; ``check=False`` skips it).

A head cut flat by the field of view (nose, forehead, vertex) is reported by a warning that
names the side and the extent, and the planes are kept in the field data ``scan_cuts``
(:func:`pvcmf.filters.field_of_view.cut_planes`); a head cut by the round field of view
(the cheeks, the brow), likewise, with the circle of each slice it cuts in ``scan_fov``
(:func:`pvcmf.filters.field_of_view.fov_circles`). Index axis 2 is the axial axis; the
patient frame (x left, y anterior, z superior) is assumed for the side names.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays
from ..io.head_check import check_head
from ..io.orientation import _cues as _head_cues  # the measurements check_head judges
from .morphology import (MIN_BALL_VOXELS, _beyond, _box, _c_copy, _closing,  # noqa: F401
                         _dilate_ball, _down, _fill, _largest_component, _open_ball, _sq_edt, _up)
from ..progress import Progress
from . import metal as _metal
from .surface_objects import DENSE_STEPS, drop_film, drop_surface_objects
from .field_of_view import cut_planes, cuts_array, fov_circles, fov_cuts
from .teeth import teeth_of_the_dentition

log = logging.getLogger(__name__)

_FACES = ndimage.generate_binary_structure(3, 1)  # 6-connectivity
_FACES_2D = np.zeros((3, 3, 3), dtype=bool)
_FACES_2D[:, :, 1] = ndimage.generate_binary_structure(2, 1)  # in-slice 4-connectivity

#: reference levels (HU) of a calibrated scan; :func:`calibrate` places the thresholds of
#: each image on its own histogram instead. Skin: half-way between air and soft tissue;
#: bone: where partial volume puts the surface of cancellous bone; teeth: enamel and dentine
#: above cortical bone; metal: above any tissue.
SKIN_THRESHOLD = -500.0
BONE_THRESHOLD = 500.0
TEETH_THRESHOLD = 2000.0
METAL_THRESHOLD = 3000.0
#: thresholds as multiples of the air -> soft tissue step, above the soft-tissue peak
#: (skin: below it). On a calibrated scan (step ~1040 HU) they give the levels above.
SCALE = {"skin": -0.5, "bone": 0.48, "teeth": 1.88, "metal": 2.85}
#: smallest radius (voxels) of the skull-closing ball: 1.5 takes the in-slice diagonal


def calibrate(ct):
    """Thresholds of one image from its histogram: air and soft-tissue peaks give the scale.

    Parameters
    ----------
    ct : pyvista.ImageData or numpy.ndarray
        The image (point array ``ct``) or its values.

    Returns
    -------
    dict
        ``air``, ``soft`` (the two peaks) and ``skin``, ``bone``, ``teeth``, ``metal``
        thresholds, in the image's units.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.segmentation import calibrate
    >>> rng = np.random.default_rng(0)
    >>> v = np.concatenate([rng.normal(-1000, 20, 6000), rng.normal(40, 20, 3000),
    ...                     rng.normal(1200, 200, 500)])
    >>> t = calibrate(v)
    >>> round(t["skin"], -1), round(t["bone"], -1)
    (-480.0, 540.0)
    """
    values = np.asarray(ct[arrays.CT] if isinstance(ct, pv.DataSet) else ct, dtype=np.float32)
    values = values.ravel(order="K")  # no copy whatever the memory order
    if values.size > 2_000_000:
        values = values[:: values.size // 1_000_000]
    reference = {"air": -1000.0, "soft": 40.0, "skin": SKIN_THRESHOLD,
                 "bone": BONE_THRESHOLD, "teeth": TEETH_THRESHOLD, "metal": METAL_THRESHOLD}
    lo, hi = np.percentile(values, [0.01, 99.99]) if values.size else (0.0, 0.0)
    if not hi > lo:
        log.warning("calibrate: the ct values are constant; using the HU reference levels")
        return reference
    hist, edges = np.histogram(values, bins=512, range=(lo, hi))
    centers = 0.5 * (edges[1:] + edges[:-1])
    split = _otsu(hist, centers)
    smooth = ndimage.uniform_filter1d(hist.astype(float), 5)
    low, high = centers < split, centers >= split
    # soft tissue: the highest peak above the split, among the lower half of the values
    # above it (bone and metal are far fewer and higher)
    upper = high & (centers <= split + 0.5 * (hi - split))
    if not low.any() or not upper.any():
        log.warning("calibrate: no air and soft-tissue peaks; using the HU reference levels")
        return reference
    air = float(centers[low][np.argmax(smooth[low])])
    soft = float(centers[upper][np.argmax(smooth[upper])])
    step = soft - air
    out = {"air": air, "soft": soft}
    out.update({k: soft + f * step for k, f in SCALE.items()})
    return out


def _otsu(hist, centers):
    w = np.cumsum(hist).astype(float)
    m = np.cumsum(hist * centers)
    total, mean = w[-1], m[-1] / w[-1]
    w1 = total - w
    with np.errstate(divide="ignore", invalid="ignore"):
        between = (mean * w - m) ** 2 / (w * w1)
    between[~np.isfinite(between)] = -1
    return float(centers[int(np.argmax(between))])


def segment(
    ct,
    *,
    skin_threshold=None,
    bone_threshold=None,
    teeth_threshold=None,
    metal_threshold=None,
    fill_holes=True,
    min_cavity=30.0,
    skull_closing=3.0,
    object_opening=5.0,
    coarse=2.0,
    check=True,
    progress_bar=False,
):
    """Label a CT volume into air, soft tissue, bone, teeth, metal and intracranial volume.

    Parameters
    ----------
    ct : pyvista.ImageData
        3-D image with a float point array ``ct`` (HU, or any linear scale of it).
    skin_threshold, bone_threshold, teeth_threshold, metal_threshold : float, optional
        Thresholds in the image's units, strictly increasing; each one not given is placed
        on the image's histogram (:func:`calibrate`).
    fill_holes : bool
        Fill enclosed holes of the head smaller than ``min_cavity`` (noise, partial volume)
        as tissue. Larger enclosed holes (sinuses, a closed airway) stay ``AIR`` either way.
    min_cavity : float
        Volume (mm^3) below which an enclosed air pocket is treated as a hole to fill.
    skull_closing : float
        Radius (mm) of the closing that seals thin gaps of the skull (partial volume,
        sutures, small foramina) before the intracranial flood; at least
        ``MIN_BALL_VOXELS`` (1.5) coarse voxels.
    object_opening : float
        Radius (mm) of the opening that detaches objects thinner than ``2 * object_opening``
        (table, headrest, sheets, tubes) from the head; 0 keeps everything connected (no
        film nor dense object on the skin is removed either).
    coarse : float
        Voxel size (mm) of the downsampled copy the head and intracranial decisions use.
    check : bool
        Refuse an image that shows no head (neither a cranial cavity nor teeth: a chest, a
        limb), with :func:`pvcmf.io.head_check.check_head` on the measurements
        :func:`pvcmf.io.orientation.standardize` makes. ``False`` labels any CT (a crop of
        a head without skull vault nor teeth, a test object).
    progress_bar : bool
        Show the stages (:class:`pvcmf.progress.Progress`) and log them at INFO level.

    Returns
    -------
    pyvista.ImageData
        A deep copy of ``ct`` (``ct`` kept) with point arrays ``tissue`` (uint8: AIR, FAT,
        BONE_TISSUE, TEETH, INTRACRANIAL, METAL) and ``bone`` (uint8: CRANIUM on hard tissue),
        and field data ``thresholds`` (skin, bone, teeth, metal), ``warnings``
        (one string per warning, e.g. a face clipped by the field of view) and, where the
        scan cut the head flat, ``arrays.SCAN_CUTS`` (the planes), and where the round
        field of view cut it, ``arrays.SCAN_FOV`` (its circle per slice).

    Raises
    ------
    TypeError
        If ``ct`` is not an ImageData.
    ValueError
        If the ``ct`` array is missing, not float or has NaN/inf values, the image is not
        3-D, the thresholds are not finite and increasing, a tissue class comes out empty,
        or (``check``) the image is not a head CT (the message names the cranial cavity,
        teeth and inner air measured).

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> img = pv.ImageData(dimensions=(40, 40, 40), spacing=(2.0, 2.0, 2.0))
    >>> r = np.linalg.norm(img.points - img.center, axis=1)
    >>> img["ct"] = np.select([r < 20, r < 26, r < 34], [30.0, 1200.0, -100.0], -1000.0).astype(np.float32)
    >>> lab = img.cmf.segment(check=False)  # a ball, not a head: no check
    >>> np.unique(lab["tissue"]).tolist()  # air, fat, bone, intracranial
    [0, 1, 3, 5]
    """
    vol, spacing = _validate(ct)
    for name, value in (("min_cavity", min_cavity), ("skull_closing", skull_closing),
                        ("object_opening", object_opening)):
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    if not (isinstance(coarse, (int, float)) and math.isfinite(coarse) and coarse > 0):
        raise ValueError(f"coarse must be a finite number > 0 (mm), got {coarse!r}")
    thr = _thresholds(vol, skin_threshold, bone_threshold, teeth_threshold, metal_threshold)
    if check:
        _refuse_non_head(vol, spacing, thr)
    bar = Progress(5, "segment", enabled=progress_bar)
    say = log.info if progress_bar else log.debug
    factor = np.maximum(1, np.round(coarse / spacing)).astype(int)
    warnings = []

    say("segment: head mask (skin %.0f, objects < %.1f mm dropped)", thr["skin"], object_opening)
    box, head, sub = _head(vol, thr["skin"], spacing, factor, object_opening)
    if object_opening > 0:
        head, film = drop_film(head, sub, spacing, thr["dense"], factor, largest=False)
        head, removed = drop_surface_objects(head, sub, spacing, factor, thr["dense"],
                                             object_opening)
        if film > 0:
            say("segment: removed %.2f mL of film lying on the skin", film)
            if removed == 0:  # drop_surface_objects keeps the largest piece when it cuts
                head = _largest_component(head, _FACES)  # not None: the body is left
        if removed > 0:
            say("segment: removed %.2f mL of dense objects lying on the skin", removed)
    if fill_holes:
        head = _fill_small_holes(head, spacing, min_cavity, say)
    bar.step()

    say("segment: hard tissue (bone %.0f, teeth %.0f, metal %.0f)", thr["bone"], thr["teeth"],
        thr["metal"])
    hard = head & (sub >= thr["bone"])
    if not hard.any():
        raise ValueError(
            f"segment: no voxel inside the head is >= bone_threshold={thr['bone']:.0f} "
            f"(head ct range [{sub[head].min():.0f}, {sub[head].max():.0f}]); are the values "
            "in HU?")
    metal = hard & (sub >= thr["metal"])
    if metal.any():
        head, hard = _metal.clean_streaks(sub, head, hard, metal, spacing, thr)
        warnings += _metal.report(metal, spacing)
    teeth = hard & (sub >= thr["teeth"]) & ~metal
    bar.step()

    say("segment: intracranial volume (closing %.1f mm, watershed)", skull_closing)
    intracranial = _intracranial(hard, head, spacing, factor, skull_closing)
    if intracranial is None:
        log.warning("segment: found no volume enclosed by the skull; no INTRACRANIAL label")
        intracranial = np.zeros_like(hard)
    teeth = teeth_of_the_dentition(teeth, intracranial, spacing, factor)
    bar.step()

    soft = head & ~hard & ~intracranial
    if not soft.any():
        raise ValueError("segment: no extra-cranial soft tissue left between skin_threshold="
                         f"{thr['skin']:.0f} and bone_threshold={thr['bone']:.0f}")
    corner = np.asarray(ct.origin) + spacing * [b.start for b in box]
    cuts = cut_planes(head, spacing, corner, vol=sub)
    fov, fov_message = fov_cuts(fov_circles(vol, thr["skin"], spacing), head, spacing, corner,
                                [b.start for b in box])
    for message in [c["message"] for c in cuts] + ([fov_message] if fov_message else []):
        log.warning("segment: %s", message)
        warnings.append(message)
    bar.step()

    out = _write(ct, vol.shape, box, soft, hard, teeth, metal, intracranial)
    out.field_data[arrays.THRESHOLDS] = np.array([thr[k] for k in ("skin", "bone", "teeth", "metal")])
    out.field_data["warnings"] = np.array(warnings if warnings else [""], dtype=str)
    if cuts:
        out.field_data[arrays.SCAN_CUTS] = cuts_array(cuts)
    if len(fov):
        out.field_data[arrays.SCAN_FOV] = fov.ravel()
    if log.isEnabledFor(logging.INFO if progress_bar else logging.DEBUG):
        volumes = tissue_volumes(out)
        say("segment: volumes (mL) %s", ", ".join(f"{k} {v:.1f}" for k, v in volumes.items()))
    bar.step()
    bar.close()
    return out


def tissue_volumes(labels):
    """Volume (mL) of every tissue label present in ``labels`` (``tissue`` array).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.segmentation import tissue_volumes
    >>> img = pv.ImageData(dimensions=(10, 10, 10), spacing=(2, 2, 2))
    >>> img[arrays.TISSUE] = np.full(1000, arrays.FAT, dtype=np.uint8)
    >>> tissue_volumes(img)
    {'fat': 8.0}
    """
    tissue = np.asarray(arrays.require_array(labels, arrays.TISSUE, "point", dtype="u"))
    counts = np.zeros(256, dtype=np.int64)  # the known labels without a cast to int64
    for label in arrays.TISSUE_LABELS.values():
        counts[label] = np.count_nonzero(tissue == label)
    if counts.sum() != tissue.size:  # other values: count them all
        counts = np.bincount(tissue, minlength=256)
    voxel = float(np.prod(labels.spacing)) / 1000.0
    names = {v: k for k, v in arrays.TISSUE_LABELS.items()}
    return {names.get(i, f"label_{i}"): float(counts[i] * voxel)
            for i in np.flatnonzero(counts) if i != arrays.AIR}


# --------------------------------------------------------------------------- validation
def _validate(ct):
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"ct must be a pyvista.ImageData, got {type(ct).__name__}")
    values = arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                  producer="pvcmf.read_ct or pvcmf.datasets.phantom")
    dims = tuple(int(d) for d in ct.dimensions)
    if len(dims) != 3 or min(dims) < 2:
        raise ValueError(f"ct must be a 3-D image (every dimension >= 2), got dimensions {dims}")
    lo, hi = (float(values.min()), float(values.max())) if values.size else (0.0, 0.0)
    if not (math.isfinite(lo) and math.isfinite(hi)):  # NaN and inf reach the extremes
        bad = int(np.count_nonzero(~np.isfinite(values)))
        raise ValueError(f"ct array 'ct' must be finite, got {bad} NaN/inf value(s)")
    return values.reshape(dims, order="F"), np.asarray(ct.spacing, dtype=float)


def _thresholds(vol, skin, bone, teeth, metal):
    given = {"skin": skin, "bone": bone, "teeth": teeth, "metal": metal}
    for name, value in given.items():
        if value is not None and (not isinstance(value, (int, float, np.number))
                                  or not math.isfinite(value)):
            raise ValueError(f"{name}_threshold must be a finite number or None, got {value!r}")
    thr = dict(calibrate(vol)) if any(v is None for v in given.values()) else {}
    thr.update({k: float(v) for k, v in given.items() if v is not None})
    if "soft" in thr:  # denser than any soft tissue (objects on the skin), below bone
        thr["dense"] = min(thr["soft"] + DENSE_STEPS * (thr["soft"] - thr["air"]), thr["bone"])
    else:  # thresholds all given: from the skin level (half-way from air to soft tissue)
        thr["dense"] = thr["bone"]
    if not thr["skin"] < thr["bone"] < thr["teeth"] <= thr["metal"]:
        raise ValueError(
            "thresholds must increase: skin_threshold < bone_threshold < teeth_threshold <= "
            f"metal_threshold, got {thr['skin']:.0f}, {thr['bone']:.0f}, {thr['teeth']:.0f}, "
            f"{thr['metal']:.0f}")
    log.debug("segment: thresholds %s", {k: round(v) for k, v in thr.items()})
    return thr


def _refuse_non_head(vol, spacing, thr):
    """:func:`check_head` on the measurements of :func:`pvcmf.io.orientation.standardize`,
    with the image's own air and soft-tissue peaks."""
    peaks = thr if "air" in thr else calibrate(vol)
    cues, _ = _head_cues(vol, spacing, peaks["air"], peaks["soft"])
    try:
        check_head(cues)
    except ValueError as err:
        raise ValueError(f"segment: {err} (segment(..., check=False) labels it anyway)") \
            from None


# --------------------------------------------------------------------------- utilities
def _head(vol, skin, spacing, factor, radius):
    """The head: thresholded, objects thinner than ``2 radius`` detached (coarse opening).

    Returns the index box of the head (2 voxels wider, within the image), the head mask and
    the image values in it (C-ordered copies)."""
    above = vol >= skin
    if not above.any():
        raise ValueError(f"segment: no voxel is >= skin_threshold={skin:.0f} (ct range "
                         f"[{vol.min():.0f}, {vol.max():.0f}]); are the values in HU?")
    cspace = spacing * factor
    coarse = _down(above, factor, "mean")
    region = None
    if radius > 0 and coarse.any():
        box, region = _head_region(coarse, cspace, factor, radius, vol.shape)
    else:
        box = tuple(slice(0, n) for n in vol.shape)
    sub = _c_copy(vol[box])  # C order from here on
    above = sub >= skin
    if region is not None:
        above &= region
    head = _largest_component(above, _FACES)
    if head is None:
        head = above
    # the head's box, 2 voxels wider (within the image)
    inner = _box(head, 0) if head.any() else tuple(slice(0, n) for n in head.shape)
    tight = tuple(slice(max(b.start + i.start - 2, 0), min(b.start + i.stop + 2, n))
                  for b, i, n in zip(box, inner, vol.shape))
    inter = tuple(slice(max(t.start, b.start), min(t.stop, b.stop)) for t, b in zip(tight, box))
    src = tuple(slice(i.start - b.start, i.stop - b.start) for i, b in zip(inter, box))
    if inter == tight:
        return tight, np.ascontiguousarray(head[src]), np.ascontiguousarray(sub[src])
    out = np.zeros(tuple(t.stop - t.start for t in tight), dtype=bool)
    out[tuple(slice(i.start - t.start, i.stop - t.start) for i, t in zip(inter, tight))] = \
        head[src]
    return tight, out, _c_copy(vol[tight])


def _head_region(coarse, cspace, factor, radius, shape):
    """Index box (full resolution) and mask of the region the head may occupy: the largest
    part of the coarse mask that survives an opening by a ball of ``radius`` mm, grown by
    the ball and one coarse voxel. The opening's dilation and the growth are one dilation
    (balls add their radii) of the largest component of the erosion; only the boxes around
    the masks are transformed."""
    r = max(radius, float(np.max(cspace)))  # at least one coarse voxel
    grow = 2.0 * r + float(np.max(cspace))
    cb = _box(coarse, 0)
    eroded = _beyond(np.pad(coarse[cb], 1), cspace, r)
    core = _largest_component(eroded[1:-1, 1:-1, 1:-1], _FACES)
    if core is None:  # everything thinner than the ball: keep the plain mask, grown by it
        core, grow = coarse[cb], r + float(np.max(cspace))
    kb = _box(core, 0)
    pad = np.ceil(grow / cspace).astype(int) + 1
    grown = _dilate_ball(np.pad(core[kb], [(int(k), int(k)) for k in pad]), cspace, grow)
    lo = [c.start + k.start - int(m) for c, k, m in zip(cb, kb, pad)]  # coarse index of [0]
    trim = tuple(slice(max(-a, 0), min(n - a, g)) for a, n, g in
                 zip(lo, coarse.shape, grown.shape))
    grown = grown[trim]
    start = [(a + t.start) * int(f) for a, t, f in zip(lo, trim, factor)]
    box = tuple(slice(b, min(b + g * int(f), n)) for b, g, f, n in
                zip(start, grown.shape, factor, shape))
    return box, _up(grown, factor, tuple(b.stop - b.start for b in box))


def _fill_small_holes(head, spacing, min_cavity, say):
    """``head`` with its enclosed holes (components of the background, faces connected, that
    do not reach the array's border) smaller than ``min_cavity`` mm^3 filled: one labelling
    of the background gives both the holes and their sizes."""
    lab, n = ndimage.label(~head, structure=_FACES)
    if n == 0:
        return head
    border = np.unique(np.concatenate([f.ravel() for f in (
        lab[0], lab[-1], lab[:, 0], lab[:, -1], lab[:, :, 0], lab[:, :, -1])]))
    hole = np.ones(n + 1, dtype=bool)
    hole[border] = False
    hole[0] = False
    if not hole.any():
        return head
    size_mm3 = np.bincount(lab.ravel(), minlength=n + 1) * float(np.prod(spacing))
    small = hole & (size_mm3 < min_cavity)
    say("segment: filled %d small holes, kept %d air cavities", int(small.sum()),
        int(hole.sum() - small.sum()))
    return head | small[lab]


def _write(ct, shape, box, soft, hard, teeth, metal, intracranial):
    sub = soft.view(np.uint8) * np.uint8(arrays.FAT)  # AIR elsewhere
    for mask, label in ((hard, arrays.BONE_TISSUE), (teeth, arrays.TEETH),
                        (metal, arrays.METAL), (intracranial, arrays.INTRACRANIAL)):
        np.copyto(sub, np.uint8(label), where=mask)
    tissue = np.zeros(shape, dtype=np.uint8, order="F")  # F order: a flat view
    tissue[box] = sub
    bone = np.zeros(shape, dtype=np.uint8, order="F")
    bone[box] = hard.view(np.uint8) * np.uint8(arrays.CRANIUM)
    out = ct.copy(deep=True)
    out.point_data[arrays.TISSUE] = tissue.ravel(order="F")
    out.point_data[arrays.BONE] = bone.ravel(order="F")
    out.point_data.active_scalars_name = arrays.TISSUE
    return out


# --------------------------------------------------------------------------- intracranial
def _intracranial(hard, head, spacing, factor, radius):
    """Intracranial volume: watershed of the distance to the closed skull (coarse grid)."""
    cspace = spacing * factor
    skull = _closing(_down(hard, factor, "any"), cspace, radius)
    head_c = _down(head, factor, "any")
    enclosed = _fill(skull, _FACES_2D, z_open=True) & ~skull & head_c
    if not enclosed.any():
        return None
    dist = np.sqrt(_sq_edt(~skull, cspace), dtype=np.float64)
    seed = np.unravel_index(int(np.argmax(np.where(enclosed, dist, 0.0))), dist.shape)
    deep = enclosed & (dist >= 0.5 * dist[seed])
    lab, _ = ndimage.label(deep, structure=_FACES)
    markers = np.zeros(skull.shape, dtype=np.uint8)
    markers[lab == lab[seed]] = 1
    markers[~_fill(head_c, _FACES) & ~skull] = 2
    brain = _watershed(dist, skull, markers)
    if brain is None:
        log.warning("segment: SimpleITK is not installed; the intracranial volume is the "
                    "axial slice-wise fill of the skull (leaks where orbits open the ring)")
        brain = _largest_component(enclosed, _FACES)
        # closed-skull voxels that are not bone at full resolution: nearest label
        _, idx = ndimage.distance_transform_edt(skull, sampling=cspace, return_indices=True)
        brain = brain[tuple(idx)]
    return _up(brain, factor, hard.shape) & head & ~hard


def _watershed(dist, skull, markers):
    try:
        import SimpleITK as sitk
    except ImportError:  # optional: fall back to the slice-wise fill
        return None
    elevation = np.where(skull, np.float32(dist.max() + 1.0), -dist.astype(np.float32))
    img = sitk.GetImageFromArray(np.ascontiguousarray(elevation.transpose(2, 1, 0)))
    mark = sitk.GetImageFromArray(np.ascontiguousarray(markers.transpose(2, 1, 0)))
    ws = sitk.MorphologicalWatershedFromMarkers(img, mark, markWatershedLine=False,
                                                fullyConnected=False)
    lab = sitk.GetArrayFromImage(ws).transpose(2, 1, 0)
    # the skull, one plateau above every basin, is flooded last from both sides: its voxels
    # take the label of the nearer basin (those of bone at full resolution are removed later)
    return lab == 1
