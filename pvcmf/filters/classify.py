"""Fat / muscle classification of the soft tissue (paper 001, Fig. 1).

Per axial slice (index axis 2), a 1-D Gaussian mixture is fitted by expectation-maximisation
(EM) to the histogram of the CT values of the soft-tissue voxels; the fat/muscle threshold is
where the posterior probabilities of the fat and muscle components are equal; a 5x5 median
filter per slice then removes isolated misclassified voxels.

Implementation: numpy only. The EM runs on the per-slice histograms (``bin_width`` HU bins in
``hu_range``), all slices at once as ``(slice, bin, component)`` arrays, so the cost does not
depend on the number of voxels and no Python loop runs over slices or voxels. The threshold
solves ``w_f N(t; m_f, s_f) = w_m N(t; m_m, s_m)`` (a quadratic) between the two means (with
more components, the crossing of the fat group's and muscle group's posteriors). The
median filter of a two-class map is a majority vote; it is computed with separable running
sums (``scipy.ndimage.uniform_filter1d``) over the soft-tissue voxels of each 5x5 window only
(air, bone and intracranial voxels do not vote). The work is done in the in-slice box of the
soft tissue; the soft tissue within the metal streak zone (:mod:`pvcmf.filters.metal`) is
classified but left out of the fit. Initialisation is deterministic: the
``n_components`` most prominent peaks of each smoothed histogram. A uniform background
component over ``hu_range`` absorbs partial-volume voxels.

Borders: a soft-tissue voxel touching air, bone, teeth or metal is a partial-volume mixture
whose value says little about its tissue (``border``); it takes the majority class of the
soft tissue around it in its slice.

Robustness: a slice whose histogram is not clearly bimodal (too few voxels, the two-Gaussian
fit not better than one Gaussian by BIC, Ashman's D < 2, or a component weight below
``min_weight``) uses the threshold fitted on all slices pooled; ``SliceMixtures.fallback``
records which slices did.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays
from . import metal as _metal
from .mixture import _crossing, _em, _fat_muscle, _pair, _pv_density
from .mixture import _prominences  # noqa: F401  (tests use it here)

log = logging.getLogger(__name__)



@dataclasses.dataclass
class SliceMixtures:
    """Fitted Gaussian mixtures of the soft-tissue HU, one row per axial slice.

    Arrays have one row per slice index ``k`` of the image (``n_slices = dimensions[2]``);
    slices without soft tissue hold NaN and ``n_voxels == 0``. Component columns are sorted by
    mean. The last fit, on all slices pooled, is kept in the ``pooled_*`` fields.

    Attributes
    ----------
    edges : ndarray (n_bins + 1,)
        Histogram bin edges (HU).
    hist : ndarray (n_slices, n_bins)
        Per-slice histogram counts of the soft-tissue voxels inside ``edges``.
    n_voxels : ndarray (n_slices,)
        Number of fitted soft-tissue voxels per slice (including those outside ``edges``).
    init_weights, init_means, init_stds : ndarray (n_slices, n_components)
        Initial mixtures of each slice: the pooled fit (which itself starts at the most
        prominent peaks of the pooled histogram, ``pooled_init_*``).
    weights, means, stds : ndarray (n_slices, n_components)
        Mixtures after EM.
    fat, muscle : ndarray (n_slices,) of int
        Column of the fat and of the muscle component (highest peak of each group).
    fat_group : ndarray (n_slices, n_components) of bool
        Components counted as fat (the rest are muscle).
    threshold : ndarray (n_slices,)
        Threshold (HU) used in each slice: below is fat, at or above is muscle.
    fallback : ndarray (n_slices,) of bool
        True where the slice used the pooled threshold (not clearly bimodal).
    iterations : ndarray (n_slices,) of int
        EM iterations until the slice converged.
    pooled_weights, pooled_means, pooled_stds : ndarray (n_components,)
        Mixture fitted to all slices' histograms together.
    pooled_init_weights, pooled_init_means, pooled_init_stds : ndarray (n_components,)
        Its start: the most prominent peaks of the pooled histogram.
    pooled_threshold : float
        Threshold of the pooled mixture.
    background : ndarray (n_slices,)
        Weight of the uniform background component (0 without one).
    pooled_background : float
        Its weight in the pooled mixture.
    partial_volume, pooled_partial_volume : ndarray (n_slices,), float
        Weight of the fat/muscle partial-volume component (0 without one).
    init_background, init_partial_volume : ndarray (n_slices,)
        Their initial weights.
    span : float
        Width (HU) of the window the background is uniform over.
    """

    edges: np.ndarray
    hist: np.ndarray
    n_voxels: np.ndarray
    init_weights: np.ndarray
    init_means: np.ndarray
    init_stds: np.ndarray
    weights: np.ndarray
    means: np.ndarray
    stds: np.ndarray
    fat: np.ndarray
    muscle: np.ndarray
    fat_group: np.ndarray
    threshold: np.ndarray
    fallback: np.ndarray
    iterations: np.ndarray
    pooled_weights: np.ndarray
    pooled_means: np.ndarray
    pooled_stds: np.ndarray
    pooled_init_weights: np.ndarray
    pooled_init_means: np.ndarray
    pooled_init_stds: np.ndarray
    pooled_threshold: float
    background: np.ndarray
    pooled_background: float
    partial_volume: np.ndarray
    pooled_partial_volume: float
    init_background: np.ndarray
    init_partial_volume: np.ndarray
    span: float

    @property
    def centers(self):
        """Histogram bin centres (HU)."""
        return 0.5 * (self.edges[1:] + self.edges[:-1])

    @property
    def fat_mean(self):
        """Fitted fat mean (HU) per slice: weighted mean of the fat group's components."""
        return _group_mean(self.weights, self.means, self.fat_group)

    @property
    def muscle_mean(self):
        """Fitted muscle mean (HU) per slice: weighted mean of the muscle group's components."""
        return _group_mean(self.weights, self.means, ~self.fat_group)

    def densities(self, k, x, initial=False):
        """Component curves of slice ``k`` at ``x``, scaled to histogram counts per bin.

        Returns an ``(len(x), n_components)`` array; its row sum plus :meth:`floor` and
        :meth:`partial_volume_density` is the mixture curve.
        """
        w, m, s = (
            (self.init_weights[k], self.init_means[k], self.init_stds[k])
            if initial
            else (self.weights[k], self.means[k], self.stds[k])
        )
        width = float(self.edges[1] - self.edges[0])
        total = float(self.hist[k].sum())
        x = np.asarray(x, dtype=float)[:, None]
        return total * width * w * np.exp(-0.5 * ((x - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))


    def floor(self, k, initial=False):
        """Level of the uniform background of slice ``k`` in counts per bin."""
        bg = self.init_background[k] if initial else self.background[k]
        width = float(self.edges[1] - self.edges[0])
        return float(self.hist[k].sum()) * width * float(bg) / self.span

    def partial_volume_density(self, k, x, initial=False):
        """Curve of the fat/muscle partial-volume component of slice ``k`` at ``x``
        (counts per bin)."""
        w, m, s = (
            (self.init_partial_volume, self.init_means, self.init_stds)
            if initial
            else (self.partial_volume, self.means, self.stds)
        )
        width = float(self.edges[1] - self.edges[0])
        total = float(self.hist[k].sum())
        fat, muscle = _pair(
            (self.init_weights if initial else self.weights)[k:k + 1], m[k:k + 1], s[k:k + 1])
        dens = _pv_density(np.asarray(x, float), m[k:k + 1], s[k:k + 1], fat, muscle)[0]
        return total * width * float(w[k]) * dens


def _group_mean(weights, means, group):
    with np.errstate(divide="ignore", invalid="ignore"):
        return (weights * means * group).sum(axis=1) / (weights * group).sum(axis=1)


def classify_tissue(
    image,
    *,
    median_size=5,
    n_components=2,
    hu_range=(-400.0, 300.0),
    bin_width=4.0,
    background=True,
    partial_volume=True,
    interior=True,
    border=1,
    min_voxels=200,
    min_weight=0.02,
    max_iter=200,
    tol=1e-5,
    return_mixtures=False,
    progress_bar=False,
):
    """Label the soft tissue FAT or MUSCLE by per-slice Gaussian mixtures + EM (paper 001).

    Parameters
    ----------
    image : pyvista.ImageData
        Output of :func:`pvcmf.filters.segment`: point arrays ``ct`` (HU) and ``tissue``.
        Voxels labelled FAT or MUSCLE are (re)classified; other labels are left as they are.
    median_size : int
        Odd in-slice window of the median (majority) filter, in voxels; 1 switches it off.
    n_components : int
        Gaussians per slice (>= 2). With more than two (the paper initialises five), the
        components are split into a fat group and a muscle group at the widest gap between
        their means that has a clear peak on each side, and the threshold is where the two
        groups' posteriors are equal; ``SliceMixtures.fat``/``muscle`` are then the highest
        peak of each group.
    hu_range : (float, float)
        HU window of the histograms the mixtures are fitted to. Voxels outside it are still
        classified by the threshold.
    bin_width : float
        Histogram bin width (HU).
    partial_volume : bool
        Fit a partial-volume component too: voxels that mix fat and muscle (thin muscles,
        their borders), with a uniform mixing fraction, i.e. a plateau between the two means
        blurred by the noise. Without it the plateau pulls the muscle Gaussian toward fat.
    interior : bool
        Fit the mixtures to the soft-tissue voxels whose six neighbours are soft tissue too:
        the voxels at the borders with air and bone are partial-volume mixtures that form
        their own histogram peaks (e.g. ~-250 HU at the skin) and would be taken for fat or
        muscle. Every soft-tissue voxel is still classified.
    border : int
        Soft-tissue voxels within this many voxels (26-neighbourhood) of air, bone, teeth or
        metal are not classified by their own value: partial volume lowers it toward air
        or raises it toward bone whatever the tissue (fat on bone reads as muscle, a stiff
        shell around the skeleton; muscle at the lips' closed slit reads as fat, a soft seam
        between two muscles). They take the majority class of the other soft-tissue voxels
        in their ``max(median_size, 5)`` in-slice window (fat where there are none) and do
        not vote in the median filter. 0 classifies them by their value like any voxel.
    background : bool
        Fit a uniform background component over ``hu_range`` too: it absorbs the
        partial-volume voxels at the skin/air and soft-tissue/bone borders, which otherwise
        pull a Gaussian off the fat or muscle peak.
    min_voxels : int
        Slices with fewer soft-tissue voxels in ``hu_range`` use the pooled threshold.
    min_weight : float
        Smallest weight of the fat or muscle component for a slice's own threshold.
    max_iter, tol : int, float
        EM stops when every slice's mean log-likelihood per voxel changes less than ``tol``.
    return_mixtures : bool
        Also return the fitted :class:`SliceMixtures`.
    progress_bar : bool
        Log the stages at INFO level (otherwise DEBUG).

    Returns
    -------
    pyvista.ImageData or (pyvista.ImageData, SliceMixtures)
        A deep copy of ``image`` whose ``tissue`` is FAT or MUSCLE_TISSUE on the soft tissue.

    Raises
    ------
    TypeError
        If ``image`` is not an ImageData.
    ValueError
        If ``ct`` or ``tissue`` is missing, the image is not 3-D, there is no soft tissue, or
        an option is out of range.

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(30, 30, 4))
    >>> rng = np.random.default_rng(0)
    >>> muscle = (img.points[:, 0] > 14).astype(float)
    >>> img["ct"] = (np.where(muscle, 40.0, -100.0) + rng.normal(0, 15, img.n_points)).astype(np.float32)
    >>> img["tissue"] = np.full(img.n_points, arrays.FAT, dtype=np.uint8)
    >>> out, mix = img.cmf.classify_tissue(return_mixtures=True)
    >>> float(np.mean((out["tissue"] == arrays.MUSCLE_TISSUE) == (muscle > 0)))
    1.0
    >>> np.round(mix.pooled_means).tolist()
    [-100.0, 40.0]
    """
    say = log.info if progress_bar else log.debug
    vol, lab, soft, (lo, hi) = _check(image, median_size, n_components, hu_range, bin_width,
                                      min_weight, border)
    dims = lab.shape
    box = _soft_box(soft)  # in-slice box of the soft tissue: every slice is kept
    vol, lab, soft = vol[box], lab[box], soft[box]

    say("classify_tissue: per-slice histograms")
    edges, hist, n_voxels = _histograms(vol, lab, soft, lo, hi, bin_width, interior,
                                        image.spacing)

    # EM: first on all slices pooled (initialised at the histogram's peaks), then on every
    # slice at once, initialised at the pooled mixture (same components in every slice)
    say("classify_tissue: EM on %d slices, %d components", dims[2], n_components)
    fit = _fit(hist, edges, n_components, max_iter, tol, hi - lo if background else None,
               partial_volume)
    slice_thr, fallback, pooled_thr = _thresholds(fit, hist, n_components, partial_volume,
                                                  min_voxels, min_weight)

    # threshold, then the per-slice median (majority) filter over soft-tissue voxels
    say("classify_tissue: thresholds (%d of %d slices use the pooled one), %dx%d median",
        int(fallback[n_voxels > 0].sum()), int((n_voxels > 0).sum()), median_size, median_size)
    is_muscle = soft & (vol >= slice_thr[None, None, :].astype(vol.dtype))
    rim = _border(lab, soft, border)
    if median_size > 1:  # the border does not vote
        is_muscle = _majority(is_muscle, soft & ~rim, median_size) | (is_muscle & rim)
    if rim.any():  # partial volume with air or hard tissue: the class of the soft tissue around
        vote = _vote(is_muscle, soft & ~rim, max(median_size, 5))
        is_muscle = np.where(rim, vote > 0, is_muscle)
    full = np.asarray(image.point_data[arrays.TISSUE]).reshape(dims, order="F").copy(order="F")
    sub = full[box]
    sub[soft] = arrays.FAT
    sub[is_muscle] = arrays.MUSCLE_TISSUE
    full[box] = sub

    out = image.copy(deep=True)
    out.point_data[arrays.TISSUE] = full.ravel(order="F")
    if not return_mixtures:
        return out
    return out, _mixtures(fit, edges, hist, n_voxels, slice_thr, fallback, pooled_thr, hi - lo)


def _check(image, median_size, n_components, hu_range, bin_width, min_weight, border=0):
    """Validated inputs: the ct and tissue volumes, the soft-tissue mask and the HU window."""
    if not isinstance(image, pv.ImageData):
        raise TypeError(f"image must be a pyvista.ImageData, got {type(image).__name__}")
    ct = arrays.require_array(image, arrays.CT, "point", dtype="f", ncomp=1,
                              producer="pvcmf.read_ct or pvcmf.datasets.phantom")
    tissue = arrays.require_array(image, arrays.TISSUE, "point", dtype="u", ncomp=1,
                                  producer="pvcmf.filters.segment")
    dims = tuple(int(d) for d in image.dimensions)
    if min(dims) < 2:
        raise ValueError(f"image must be 3-D (every dimension >= 2), got dimensions {dims}")
    if not (isinstance(median_size, (int, np.integer)) and median_size >= 1 and median_size % 2):
        raise ValueError(f"median_size must be an odd integer >= 1, got {median_size!r}")
    if not (isinstance(n_components, (int, np.integer)) and n_components >= 2):
        raise ValueError(f"n_components must be an integer >= 2, got {n_components!r}")
    lo, hi = (float(v) for v in hu_range)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"hu_range must be two finite increasing HU values, got {hu_range!r}")
    if not (math.isfinite(bin_width) and 0 < bin_width <= (hi - lo) / 4):
        raise ValueError(f"bin_width must be in (0, {(hi - lo) / 4}] HU, got {bin_width!r}")
    if not (isinstance(border, (int, np.integer)) and not isinstance(border, bool)
            and border >= 0):
        raise ValueError(f"border must be an integer >= 0 (voxels), got {border!r}")
    if not 0 <= min_weight < 0.5:
        raise ValueError(f"min_weight must be in [0, 0.5), got {min_weight!r}")
    vol = np.asarray(ct).reshape(dims, order="F")
    lab = np.asarray(tissue).reshape(dims, order="F")
    soft = (lab == arrays.FAT) | (lab == arrays.MUSCLE_TISSUE)
    if not soft.any():
        raise ValueError(
            "image has no soft tissue (tissue FAT or MUSCLE) to classify; run segment first"
        )
    finite = math.isfinite(float(vol.min())) and math.isfinite(float(vol.max()))
    if not finite and not np.all(np.isfinite(vol.T[soft.T])):  # memory order
        raise ValueError("ct array 'ct' must be finite on the soft tissue, got NaN/inf values")
    return vol, lab, soft, (lo, hi)


def _soft_box(soft, margin=3):
    """Index box (all slices) around the soft tissue in-slice, ``margin`` voxels wider."""
    box = []
    for axis in (0, 1):
        hit = np.flatnonzero(soft.any(axis=(1 - axis, 2)))
        box.append(slice(max(int(hit[0]) - margin, 0),
                         min(int(hit[-1]) + margin + 1, soft.shape[axis])))
    return (*box, slice(None))


def _histograms(vol, lab, soft, lo, hi, bin_width, interior, spacing):
    """Per-slice histograms of the soft tissue that is fitted: interior voxels only (with
    ``interior``), and none near metal (its streaks falsify the values, though those voxels
    are still classified). Returns the bin edges, the histograms (n_slices, n_bins) and the
    number of fitted voxels per slice."""
    n_slices = vol.shape[2]
    n_bins = int(round((hi - lo) / bin_width))
    edges = lo + bin_width * np.arange(n_bins + 1)
    fit_mask = soft
    if interior:  # leave out partial-volume voxels at the air / bone / brain borders
        fit_mask = ndimage.binary_erosion(  # the scan's end is not a tissue border
            soft.T, structure=ndimage.generate_binary_structure(3, 1), border_value=1).T
    metal = lab == arrays.METAL
    if metal.any():
        zone_box, zone = _metal.streak_zone(metal, spacing)
        fit_mask = fit_mask.copy()
        fit_mask[zone_box] &= ~zone
    # gathered in memory order (transposed views of the Fortran-ordered image): the
    # histograms do not depend on the order
    k_index = np.broadcast_to(np.arange(n_slices, dtype=np.int32), vol.shape).T[fit_mask.T]
    values = vol.T[fit_mask.T]
    inside = (values >= edges[0]) & (values < edges[-1])
    b_index = np.floor((values[inside] - lo) / bin_width).astype(np.int64)
    hist = np.bincount(k_index[inside] * n_bins + b_index, minlength=n_slices * n_bins)
    hist = hist.reshape(n_slices, n_bins).astype(np.float64)
    n_voxels = np.bincount(k_index, minlength=n_slices)
    if hist.sum() == 0:
        raise ValueError("the soft tissue has no voxel to fit (interior, away from metal); "
                         "use interior=False")
    return edges, hist, n_voxels


def _fit(hist, edges, n_components, max_iter, tol, span, partial_volume):
    """EM on the pooled histogram, then on every slice from the pooled mixture. Returns the
    fit with the pooled one as the last row, the fat/muscle grouping and the thresholds."""
    n_slices = hist.shape[0]
    centers = 0.5 * (edges[1:] + edges[:-1])
    pooled = _em(hist.sum(axis=0, keepdims=True), centers, n_components, max_iter, tol, span,
                 pv=partial_volume)
    seed = {key: np.repeat(pooled[key], n_slices, axis=0)
            for key in ("weights", "means", "stds", "background", "partial_volume")}
    per_slice = _em(hist, centers, n_components, max_iter, tol, span, init=seed,
                    pv=partial_volume)
    fit = {key: np.concatenate([per_slice[key], pooled[key]]) for key in per_slice}
    w, m, s = fit["weights"], fit["means"], fit["stds"]
    fit["fat_group"], fit["fat"], fit["muscle"] = _fat_muscle(w, m, s)
    fit["threshold"], fit["found"] = _crossing(w, m, s, fit["fat_group"], fit["fat"],
                                               fit["muscle"])
    fit["centers"], fit["span"], fit["max_iter"], fit["tol"] = centers, span, max_iter, tol
    return fit


def _thresholds(fit, hist, n_components, partial_volume, min_voxels, min_weight):
    """Which slices have a trustworthy own threshold (clearly bimodal, near the pooled
    mixture); the others take the pooled one. Returns the per-slice thresholds, the
    fallback flags and the pooled threshold (inf when even the pool is not bimodal)."""
    rows = np.vstack([hist, hist.sum(axis=0, keepdims=True)])
    w, m, s, fat, muscle = (fit[k] for k in ("weights", "means", "stds", "fat", "muscle"))
    counts = rows.sum(axis=1)
    r = np.arange(rows.shape[0])
    m1, m2, s1, s2 = m[r, fat], m[r, muscle], s[r, fat], s[r, muscle]
    ashman = math.sqrt(2.0) * np.abs(m2 - m1) / np.sqrt(s1**2 + s2**2)
    one = _em(rows, fit["centers"], 1, fit["max_iter"], fit["tol"], fit["span"])["loglik"]
    extra = 3 * (n_components - 1) + bool(partial_volume)  # parameters in addition
    with np.errstate(divide="ignore", invalid="ignore"):
        bic_gain = 2.0 * (fit["loglik"] - one) - extra * np.log(np.maximum(counts, 1.0))
    # a slice's fat and muscle must stay within 3 pooled stds of the pooled ones
    near = (np.abs(m1 - m1[-1]) <= 3.0 * s1[-1]) & (np.abs(m2 - m2[-1]) <= 3.0 * s2[-1])
    good = (
        fit["found"]
        & (counts >= min_voxels)
        & (ashman >= 2.0)
        & (np.minimum(w[r, fat], w[r, muscle]) >= min_weight)
        & (bic_gain > 0)
        & near
    )
    pooled_ok = bool(good[-1])
    pooled_thr = float(fit["threshold"][-1]) if pooled_ok else math.inf
    if not pooled_ok:
        log.warning(
            "classify_tissue: the soft-tissue histogram is not bimodal (no fat/muscle "
            "separation found); slices without their own fit are labelled FAT"
        )
    return np.where(good[:-1], fit["threshold"][:-1], pooled_thr), ~good[:-1], pooled_thr


def _mixtures(fit, edges, hist, n_voxels, slice_thr, fallback, pooled_thr, span):
    """The :class:`SliceMixtures` of a fit (rows of empty slices NaN)."""
    empty = n_voxels == 0
    nanrow = np.where(empty[:, None], np.nan, 1.0)
    w, m, s = fit["weights"], fit["means"], fit["stds"]
    return SliceMixtures(
        edges=edges,
        hist=hist,
        n_voxels=n_voxels,
        init_weights=fit["init_weights"][:-1] * nanrow,
        init_means=fit["init_means"][:-1] * nanrow,
        init_stds=fit["init_stds"][:-1] * nanrow,
        weights=w[:-1] * nanrow,
        means=m[:-1] * nanrow,
        stds=s[:-1] * nanrow,
        fat=fit["fat"][:-1],
        muscle=fit["muscle"][:-1],
        fat_group=fit["fat_group"][:-1],
        threshold=np.where(empty, np.nan, slice_thr),
        fallback=fallback,
        iterations=fit["iterations"][:-1],
        pooled_weights=w[-1],
        pooled_means=m[-1],
        pooled_stds=s[-1],
        pooled_init_weights=fit["init_weights"][-1],
        pooled_init_means=fit["init_means"][-1],
        pooled_init_stds=fit["init_stds"][-1],
        pooled_threshold=pooled_thr,
        background=fit["background"][:-1] * nanrow[:, 0],
        pooled_background=float(fit["background"][-1]),
        partial_volume=fit["partial_volume"][:-1] * nanrow[:, 0],
        pooled_partial_volume=float(fit["partial_volume"][-1]),
        init_background=fit["init_background"][:-1] * nanrow[:, 0],
        init_partial_volume=fit["init_partial_volume"][:-1] * nanrow[:, 0],
        span=span,
    )


def _border(lab, soft, width):
    """The soft-tissue voxels within ``width`` voxels (26-neighbourhood) of air or hard
    tissue."""
    if width == 0:
        return np.zeros_like(soft)
    hard = lab == arrays.AIR
    for label in arrays.HARD_LABELS:
        hard |= lab == label
    # the transposed (C-ordered) view of the Fortran-ordered image: scipy's morphology runs
    # several times faster on it, and the result keeps the image's memory order
    near = ndimage.binary_dilation(hard.T, structure=np.ones((3, 3, 3), bool),
                                   iterations=width).T
    return soft & near


# --------------------------------------------------------------------------- EM
def _vote(is_muscle, voters, size):
    """Per-slice ``size`` x ``size`` window vote over the voxels ``voters``: muscle minus fat
    voters (> 0: muscle majority, < 0: fat, 0: tie or no voter), by two separable running
    sums (in-slice axes 0 and 1)."""
    def count(mask):
        # on the transposed view (in-slice axes 2 and 1): the memory order of the image
        c = ndimage.uniform_filter1d(mask.T.astype(np.float32), size, axis=2, mode="constant")
        c = ndimage.uniform_filter1d(c, size, axis=1, mode="constant")
        return np.rint(c * (size * size)).astype(np.int16).T

    return 2 * count(is_muscle & voters) - count(voters)


def _majority(is_muscle, soft, size):
    """Per-slice ``size`` x ``size`` median of the fat/muscle map over soft-tissue voxels
    (a tie keeps the voxel's class)."""
    vote = _vote(is_muscle, soft, size)
    return soft & ((vote > 0) | ((vote == 0) & is_muscle))
