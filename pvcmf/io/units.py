"""Units of a CT, checked from the image itself: HU from its air and soft-tissue peaks.

Otsu's threshold on a subsample of the voxels splits air from the body; the mode of each
side gives the air peak ``A`` and the soft-tissue peak ``S`` (brain, muscle). A head CT
also has bone: a tail of voxels far above ``S``. Without the two peaks and the bone tail
the image is refused (an MR volume, a uniform phantom). In HU ``A`` is near -1000 and
``S`` near +40.

* ``units='auto'``: scanner units differ from HU by a constant offset (CT conventions store
  ``HU + 1000`` or ``HU + 1024``). The offset is the convention (0, -1000, -1024, -32768)
  closest to both peaks, the soft-tissue peak counting twice (air is often clamped at the
  storage minimum whatever the convention), or, when none fits, the offset that puts ``S``
  at +40 HU. Peaks about 1040 apart (600 to 1600) are asked of a CT: an image whose peaks
  are not is refused, since an MR volume can show two such peaks too, except a DICOM
  series whose header says CT (:data:`pvcmf.arrays.MODALITY`), which is rescaled as below.
  A DICOM series of another imaging modality (MR, PET, nuclear medicine, ultrasound) is
  refused whatever ``units`` says.
* ``units='rescale'``: a cone-beam CT's grey values are often not HU: air and soft tissue
  lie closer together or farther apart than 1040 (a scale as well as an offset). The line
  through the two peaks maps them to -1000 and +40 HU (``HU = slope * value + offset``);
  only the bone tail is asked of the image.
* ``units='hu'`` or a number (the offset): given, and checked against the peaks.

A constant written outside a scanner's round field (a fill: one exact value far more common
than the values near it, :data:`FILL_SHARE`) is left out of the peaks and set to the air
peak. At the image's minimum it must also stand clear of the air: across a gap, or, where
the air's tail reaches it (a noisy field), below the air's own peak by more than
:data:`FILL_SHIFT` of the step; air clipped at the storage minimum stays air.

Delegates to numpy and :mod:`scipy.ndimage` (the peaks' smoothing).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import pyvista as pv
from scipy import ndimage as ndi

from .. import arrays

log = logging.getLogger("pvcmf.io.orientation")  # the check standardize runs, logged as such

__all__ = ["check_units", "AIR_HU", "SOFT_HU", "HU_OFFSETS", "CT_SPAN", "NOT_CT", "UNITS"]

#: offsets (HU = value + offset) of the usual CT storage conventions
HU_OFFSETS = (0.0, -1000.0, -1024.0, -32768.0)
#: nominal HU of air and of the soft-tissue peak (brain, muscle)
AIR_HU, SOFT_HU = -1000.0, 40.0
#: nominal HU of fat: a scan of the lower face and neck can hold more fat than lean tissue,
#: and its soft-tissue peak then lies at fat
FAT_HU = -100.0
#: distance between the air and soft-tissue peaks (image values) that ``units='auto'`` and
#: given units ask of a CT (HU: 1040; scanner units keep it)
CT_SPAN = (600.0, 1600.0)
#: relative difference of the peaks' distance from a CT's (1040) above which ``units='auto'``
#: says that the values may need ``units='rescale'``
SPAN_NOTE = 0.2
#: DICOM modalities that are no X-ray attenuation image (refused by :func:`check_units`)
NOT_CT = {"MR": "magnetic resonance", "PT": "positron emission tomography",
          "NM": "nuclear medicine", "US": "ultrasound"}
#: the words ``units`` takes besides a number (the offset)
UNITS = ("auto", "hu", "rescale")


def _volume(image, name="image"):
    if not isinstance(image, pv.ImageData):
        raise TypeError(f"{name} must be a pyvista.ImageData, got {type(image).__name__}")
    if arrays.CT not in image.point_data:
        raise ValueError(f"{name} needs a point array {arrays.CT!r} (pvcmf.read_ct makes it)")
    dims = tuple(int(d) for d in image.dimensions)
    if min(dims) < 2:
        raise ValueError(f"{name} must be a 3-D volume, got dimensions {dims}")
    return np.asarray(image.point_data[arrays.CT]).reshape(dims, order="F")


def _with_volume(image, vol, spacing=None):
    out = pv.ImageData(dimensions=vol.shape, spacing=image.spacing if spacing is None else spacing,
                       origin=image.origin)
    out.point_data[arrays.CT] = np.asarray(vol, dtype=np.float32).ravel(order="F")
    return out


def _otsu(x, bins=256):
    hist, edges = np.histogram(x, bins=bins)
    c = 0.5 * (edges[1:] + edges[:-1])
    w = np.cumsum(hist, dtype=float)
    m = np.cumsum(hist * c)
    w2 = w[-1] - w
    ok = (w > 0) & (w2 > 0)
    var = np.zeros_like(c)
    var[ok] = (m[-1] * w[ok] / w[-1] - m[ok]) ** 2 / (w[ok] * w2[ok])
    return float(c[np.argmax(var)])


def _mode(x, lo, hi, width):
    bins = max(8, int(math.ceil((hi - lo) / width)))
    hist, edges = np.histogram(x, bins=bins, range=(lo, hi))
    smooth = ndi.gaussian_filter1d(hist.astype(float), 1.5)
    i = int(np.argmax(smooth))
    return float(0.5 * (edges[i] + edges[i + 1]))


#: an exact value that at least this share of the voxels hold, standing above the values
#: near it, is a fill (the outside of a cone-beam scanner's round field, written as one
#: constant), not a tissue: a tissue's values spread over a peak of similar counts
FILL_SHARE = 0.02
#: "near" the fill: within this share of the image's value range (0.5th to 99.5th
#: percentile) of it; "standing above": held ``FILL_RATIO`` times more often than any value
#: near it, or, at the image's minimum, than all the values within that reach above it
FILL_REACH, FILL_RATIO = 0.01, 20.0
#: a fill at the image's minimum that the air's tail reaches is air enough where, taken for
#: the air peak, it lies below the air's own peak by at most this share of the air to
#: soft-tissue step (the scale then moves by about as much)
FILL_SHIFT = 0.1
#: least share of the body far above soft tissue (bone) that a CT shows
MIN_BONE = 0.002


def _fill(vol):
    """``(value, share, reached)`` of a constant fill of ``vol`` (see :data:`FILL_SHARE`),
    or None (``reached``: a fill at the minimum that the other values reach, no gap between):
    a fill above the image's minimum stands above the values near it, even inside a
    tissue's peak; one at the minimum stands above all the values just above it together:
    padding below air (a gap above it), or the lowest value written outside a noisy field
    (the air's far tail above it), but not air clipped at the scanner's lowest value (the
    bulk of the air above it)."""
    step = max(1, int(round((vol.size / 2e6) ** (1 / 3))))
    sub = vol[::step, ::step, ::step].ravel()
    values, counts = np.unique(sub, return_counts=True)
    i = int(np.argmax(counts))
    if counts[i] < FILL_SHARE * sub.size or counts[i] == sub.size:
        return None
    value = values[i]
    rest = sub[sub != value]
    lo, hi = np.percentile(rest, [0.5, 99.5])
    reach = FILL_REACH * float(hi - lo)
    if value < rest.min():  # at the minimum: against every value within reach above it
        if counts[i] < FILL_RATIO * np.count_nonzero(rest <= value + reach):
            return None
        if float(rest.min()) - float(value) <= reach:  # the air's tail reaches it
            return float(value), float(counts[i] / sub.size), True
    else:
        near = (np.abs(values - value) <= reach) & (values != value)
        if counts[i] < FILL_RATIO * counts[near].max(initial=0):
            return None
    return float(value), float(counts[i] / sub.size), False


def _peaks_without_fill(vol):
    """``(fill, peaks)``: :func:`_fill` and :func:`_peaks` of the other values; where
    leaving the fill out leaves no CT's peaks and bone (a noise-free image's air is one
    value too), no fill and the peaks of all values. A fill at the minimum that the air's
    tail reaches is kept only where leaving it out moves the air peak up by more than
    :data:`FILL_SHIFT` of the air to soft-tissue step (clipped air, or padding at about the
    air's level, is air enough: taken for the air peak it moves the scale by less), and
    into the lower half between the peaks of all values (else the air was clipped into
    it: what is left of the air is too little to be the air peak, and soft tissue takes
    its place)."""
    fill, every = _fill(vol), None
    if fill is not None:
        found = _peaks(vol, fill[0])
        kept = found is not None and found[3] >= MIN_BONE
        if kept and fill[2]:
            every = _peaks(vol)
            step = None if every is None else every[1] - every[0]
            kept = step is None or FILL_SHIFT * step < found[0] - every[0] < 0.5 * step
        if kept:
            return fill[:2], found
    return None, _peaks(vol) if every is None else every


def _as_air(vol, fill, air):
    """``vol`` with its fill (:func:`_fill`) set to the air peak ``air`` (a new array):
    the outside of the field reads as air, as the padding of a CT's field does."""
    value, share = fill
    log.info("check_units: %.0f %% of the image holds exactly %g, apart from the tissue "
             "values: the fill outside the scanner's field, set to the air peak %.0f",
             100 * share, value, air)
    return np.where(vol == value, vol.dtype.type(air), vol)


def _peaks(vol, fill=None):
    """Air peak, soft-tissue peak and the air/body threshold of a subsample of ``vol``
    (``fill``: a value left out, :func:`_fill`)."""
    step = max(1, int(round((vol.size / 2e6) ** (1 / 3))))
    sub = vol[::step, ::step, ::step].ravel().astype(np.float64)
    if fill is not None:
        sub = sub[sub != fill]
    lo, hi = np.percentile(sub, [0.5, 99.5])
    if not hi > lo:
        return None
    t = _otsu(np.clip(sub, lo, hi))
    air, body = sub[sub < t], sub[(sub >= t) & (sub <= hi)]
    if air.size < 0.01 * sub.size or body.size < 0.01 * sub.size:
        return None
    width = (hi - lo) / 256
    a = _mode(air, float(air.min()), t, width)
    s = _mode(body, t, hi, width)
    bone = float(np.mean(sub[sub >= t] > s + 0.6 * (s - a)))
    return a, s, t, bone


#: HU by which both the air and the soft-tissue peak may miss their values under given units
#: before the units are refused (cone-beam grey values stray by a few hundred; scanner units
#: read as HU by about a thousand)
GIVEN_UNITS_TOLERANCE = 500.0


def _check_given_units(air, soft, offset, given):
    """Refuse given units (``'hu'`` or an offset) under which both peaks miss their HU by
    more than :data:`GIVEN_UNITS_TOLERANCE`, naming the offset the peaks ask for."""
    air_hu, soft_hu = air + offset, soft + offset
    if abs(air_hu - AIR_HU) <= GIVEN_UNITS_TOLERANCE or \
            abs(soft_hu - SOFT_HU) <= GIVEN_UNITS_TOLERANCE:
        return
    cost = [2 * abs(SOFT_HU - soft - o) + abs(AIR_HU - air - o) for o in HU_OFFSETS]
    best = HU_OFFSETS[int(np.argmin(cost))]
    raise ValueError(
        f"check_units: with {given}, air lies at {air_hu:.0f} HU and soft "
        f"tissue at {soft_hu:.0f} HU (a CT has them near {AIR_HU:g} and {SOFT_HU:g}): the "
        f"values are not in HU under these units; expected units='auto' (pvcmf simulate: "
        f"--units auto and no --offset), or the offset the peaks ask for: HU = value "
        f"{best:+g} on the values read")


def check_units(image, units="auto"):
    """Bring a CT into Hounsfield units, detecting scanner units from its histogram.

    Parameters
    ----------
    image : pyvista.ImageData
        Point array ``ct``.
    units : {'auto', 'hu', 'rescale'} or float
        ``'auto'`` detects the offset of scanner units (module notes), and rescales a DICOM
        CT series whose peaks are not a CT's distance apart; ``'rescale'`` maps the air and
        soft-tissue peaks to -1000 and +40 HU by a line (a cone-beam CT's grey values);
        ``'hu'`` keeps the values; a number is the offset to add (HU = value + offset). The
        image is checked to be a CT in every case.

    Returns
    -------
    image : pyvista.ImageData
        A new image in HU.
    report : dict
        ``units`` ('hu', 'scanner' or 'rescaled'), ``slope`` and ``offset`` applied (HU =
        slope * value + offset), ``air_peak`` and ``soft_peak`` (in the input's values),
        ``how`` (a sentence), ``modality`` (where the image has one), ``fill`` (where the
        image holds one: the constant written outside a scanner's field, ``value``,
        ``share`` of the voxels, ``set_to``: the air peak, so that it reads as air).

    Raises
    ------
    ValueError
        If the image has no air peak, no soft-tissue peak or no bone (not a CT of a body
        part with bone), its peaks are not a CT's distance apart (except with
        ``'rescale'`` or a DICOM CT series), it is a DICOM series of another imaging
        modality, or ``units`` is not understood.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.filters.orientation import check_units
    >>> img = pv.ImageData(dimensions=(40, 40, 40))
    >>> r = np.linalg.norm(img.points - 19.5, axis=1)
    >>> img["ct"] = np.where(r < 15, 1040.0, 0.0) + np.where((r > 12) & (r < 14), 1200.0, 0)
    >>> hu, rep = check_units(img)
    >>> rep["units"], rep["offset"]
    ('scanner', -1000.0)
    >>> img["ct"] = 0.5 * img["ct"]  # a cone-beam CT at half the HU scale
    >>> hu, rep = check_units(img, units="rescale")
    >>> rep["units"], round(rep["slope"], 1), round(float(hu["ct"].max()), -1)
    ('rescaled', 2.0, 1240.0)
    """
    vol = _volume(image)
    if isinstance(units, str) and units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(map(repr, UNITS))} or a number "
                         f"(the offset), got {units!r}")
    if not isinstance(units, str) and not (isinstance(units, (int, float, np.number))
                                           and not isinstance(units, bool)
                                           and math.isfinite(float(units))):
        raise ValueError(f"units must be one of {', '.join(map(repr, UNITS))} or a finite "
                         f"number (the offset), got {units!r}")
    modality = _modality(image)
    fill, found = _peaks_without_fill(vol)
    if found is None:
        raise ValueError("check_units: the image has no separate air and tissue peaks in its "
                         "histogram: not a CT (a uniform or empty volume?)")
    a, s, _, bone = found
    report = {"air_peak": round(a, 1), "soft_peak": round(s, 1)}
    if fill is not None:  # (in the input's values)
        vol = _as_air(vol, fill, a)
        report["fill"] = {"value": fill[0], "share": round(fill[1], 4), "set_to": round(a, 1)}
    said = ""
    if units == "auto" and modality == "CT" and not CT_SPAN[0] <= s - a <= CT_SPAN[1]:
        units, said = "rescale", (f"a CT series (DICOM Modality CT) whose peaks are "
                                  f"{s - a:.0f} apart, not about {SOFT_HU - AIR_HU:g}: a "
                                  f"cone-beam CT's grey values; ")
    _check_ct(a, s, bone, units)
    slope = 1.0
    if units == "rescale":
        slope = (SOFT_HU - AIR_HU) / (s - a)
        offset = AIR_HU - slope * a
        how = (f"{said}air peak {a:.0f} and soft-tissue peak {s:.0f} mapped to {AIR_HU:g} "
               f"and {SOFT_HU:g} HU (units='rescale'): HU = {slope:.4g} * value "
               f"{offset:+.4g}")
    elif units == "hu":
        offset, how = 0.0, "kept as HU (units='hu')"
    elif not isinstance(units, str):
        offset, how = float(units), f"offset {float(units):g} given"
    else:
        offset, how = _auto_offset(a, s)
    if units not in ("auto", "rescale"):
        _check_given_units(a, s, offset, "units='hu'" if units == "hu" else f"units={offset:g}")
    kind = "rescaled" if units == "rescale" else "hu" if offset == 0 else "scanner"
    report.update(units=kind, slope=slope, offset=offset, how=how)
    if modality:
        report["modality"] = modality
    if kind == "hu":
        log.info("check_units: Hounsfield units (%s)", how)
        out = _with_volume(image, vol.astype(np.float32, order="F", copy=True))
    else:
        log.warning("check_units: %s; %s", "grey values rescaled" if kind == "rescaled"
                    else f"scanner units; HU = value {offset:+g}", how)
        hu = vol.astype(np.float64, order="F") * slope + offset if slope != 1.0 else \
            vol.astype(np.float32, order="F") + np.float32(offset)
        out = _with_volume(image, hu)
    return out, report


def _modality(image):
    """The image's DICOM Modality (:data:`pvcmf.arrays.MODALITY`, upper case; '' where it
    has none); refused where it names an imaging modality that is not X-ray attenuation."""
    if arrays.MODALITY not in image.field_data:
        return ""
    values = np.asarray(image.field_data[arrays.MODALITY]).ravel()
    modality = str(values[0]).strip().upper() if values.size else ""
    if modality in NOT_CT:
        raise ValueError(
            f"check_units: the image is a DICOM {modality} series ({NOT_CT[modality]}), not "
            "a CT: pvcmf segments the bone and soft tissue of a CT or cone-beam CT (a folder "
            "with several series: read_ct(..., series=...), on the command line --series)")
    return modality


def _check_ct(air, soft, bone, units):
    """Refuse an image without a bone tail, or whose peaks are not a CT's distance apart
    (``units='rescale'`` asks the bone tail only)."""
    span = soft - air
    if bone < MIN_BONE or (units != "rescale" and not CT_SPAN[0] <= span <= CT_SPAN[1]):
        hint = "" if units == "rescale" or bone < MIN_BONE else (
            "; a cone-beam CT whose grey values are not HU: units='rescale' (pvcmf simulate "
            "--units rescale) maps the two peaks to -1000 and +40 HU")
        raise ValueError(
            f"check_units: not a CT of a body part with bone: air peak {air:.0f}, soft-tissue "
            f"peak {soft:.0f} ({CT_SPAN[0]:g} to {CT_SPAN[1]:g} apart in a CT, "
            f"{span:.0f} here), {100 * bone:.2f} % of the body far above soft tissue (bone, "
            f"at least 0.2 % in a CT); an MR or a phantom without bone?{hint}")


def _auto_offset(air, soft):
    """``(offset, how)``: the storage convention the peaks match (air near ``AIR_HU``, the
    soft-tissue peak from ``FAT_HU`` to ``SOFT_HU``), else the offset that puts the
    soft-tissue peak at ``SOFT_HU``."""
    from_soft, from_air = SOFT_HU - soft, AIR_HU - air
    cost = [2 * abs(from_soft - o) + abs(from_air - o) for o in HU_OFFSETS]
    best = HU_OFFSETS[int(np.argmin(cost))]
    # the soft-tissue peak lies from fat to lean tissue (fat-rich heads and necks)
    if FAT_HU - 50 <= soft + best <= SOFT_HU + 100 and abs(from_air - best) <= 150:
        return best, (f"air peak {air:.0f} and soft-tissue peak {soft:.0f} match the "
                      f"convention HU = value {best:+g}")
    offset = float(round(from_soft))
    how = (f"air peak {air:.0f} and soft-tissue peak {soft:.0f} fit no usual convention: "
           f"offset {offset:+g} puts soft tissue at {SOFT_HU:g} HU")
    span, nominal = soft - air, SOFT_HU - AIR_HU
    if abs(span - nominal) > SPAN_NOTE * nominal:  # a scale too: say how to map it
        how += (f"; the peaks are {span:.0f} apart, not about {nominal:g}: grey values of a "
                f"cone-beam CT? units='rescale' maps both peaks")
    return offset, how
