"""Gaussian mixtures of CT histograms for the fat / muscle classification (paper 001, Fig. 1).

Expectation-maximisation on per-slice histograms, all slices at once as
``(slice, bin, component)`` arrays, with an optional uniform partial-volume component;
deterministic initialisation from the most prominent histogram peaks; the fat / muscle
threshold where the two groups' weighted densities cross. Used by
:func:`pvcmf.filters.classify_tissue`. numpy and scipy only.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy import ndimage, special

log = logging.getLogger("pvcmf.filters.classify")

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _em(hist, x, k, max_iter, tol, span=None, init=None, pv=False):
    """EM for 1-D Gaussian mixtures on weighted histograms, every row at once.

    ``hist`` (R, B) counts at bin centres ``x`` (B,). With ``span`` (the width of the
    histogram window) a uniform background component of density ``1 / span`` is fitted too;
    with ``pv`` a partial-volume component between the fat and the muscle Gaussian (see
    :func:`_pv_density`), whose weight is fitted while its shape follows the two Gaussians
    (a generalised EM step). ``init`` (weights, means, stds, background, partial_volume)
    replaces the default start at the ``k`` most prominent peaks of each row.
    Returns the (R, k) parameters sorted by mean, the background and partial-volume weights
    (R,), and the total log-likelihood (R,).
    """
    n_rows, _ = hist.shape
    total = hist.sum(axis=1)
    ok = total > 0
    safe_total = np.where(ok, total, 1.0)
    width = float(x[1] - x[0]) if x.size > 1 else 1.0
    floor = width  # std floor: one bin
    mean = (hist @ x) / safe_total
    spread = np.sqrt(np.maximum((hist @ x**2) / safe_total - mean**2, 0.0))
    pv = bool(pv and k >= 2)
    if init is None:
        means = _peaks(hist, x, k, np.maximum(spread, 2 * width))
        stds = np.repeat(np.maximum(spread / k, floor)[:, None], k, axis=1)
        bg = np.full(n_rows, 0.1 if span else 0.0)
        pvw = np.full(n_rows, 0.1 if pv else 0.0)
        weights = np.repeat(((1.0 - bg - pvw) / k)[:, None], k, axis=1)
        order = np.argsort(means, axis=1)
        means = np.take_along_axis(means, order, axis=1)
    else:
        weights, means, stds, bg, pvw = (
            np.array(init[key], dtype=float)
            for key in ("weights", "means", "stds", "background", "partial_volume"))
    start = (weights.copy(), means.copy(), stds.copy(), bg.copy(), pvw.copy())
    log_bg_density = -math.log(span) if span else 0.0

    loglik = np.full(n_rows, -np.inf)
    iterations = np.zeros(n_rows, dtype=int)
    active = np.flatnonzero(ok)
    xb = x[None, :, None]
    for it in range(1, max_iter + 1):
        if active.size == 0:
            break
        h, w, m, sd = hist[active], weights[active], means[active], stds[active]
        logp = np.log(w / sd)[:, None, :] - _LOG_SQRT_2PI - 0.5 * ((xb - m[:, None, :]) / sd[:, None, :]) ** 2
        top = logp.max(axis=2)
        lse = top + np.log(np.exp(logp - top[..., None]).sum(axis=2))  # (R, B)
        if span:
            lse = np.logaddexp(lse, (np.log(bg[active]) + log_bg_density)[:, None])
        if pv:
            fat, muscle = _pair(w, m, sd)
            log_pv = np.log(pvw[active])[:, None] + np.log(_pv_density(x, m, sd, fat, muscle))
            lse = np.logaddexp(lse, log_pv)
        resp = np.exp(logp - lse[..., None]) * h[..., None]  # weighted responsibilities
        new_ll = (h * lse).sum(axis=1)
        nk = resp.sum(axis=1)  # (R, k)
        nk_safe = np.maximum(nk, 1e-12)
        new_means = (resp * xb).sum(axis=1) / nk_safe
        var = (resp * (xb - new_means[:, None, :]) ** 2).sum(axis=1) / nk_safe
        means[active] = new_means
        stds[active] = np.sqrt(np.maximum(var, floor**2))
        weights[active] = np.maximum(nk / safe_total[active, None], 1e-12)
        n_pv = 0.0
        if pv:
            n_pv = (np.exp(log_pv - lse) * h).sum(axis=1)
            pvw[active] = np.maximum(n_pv / safe_total[active], 1e-12)
        if span:
            bg[active] = np.maximum(1.0 - (nk.sum(axis=1) + n_pv) / safe_total[active], 1e-12)
        change = np.abs(new_ll - loglik[active]) / safe_total[active]
        loglik[active] = new_ll
        iterations[active] = it
        active = active[~(change < tol)]
    if active.size:
        log.debug("classify_tissue: EM hit max_iter=%d on %d rows", max_iter, active.size)
    order = np.argsort(means, axis=1)

    def take(a):
        return np.take_along_axis(a, order, axis=1)

    return {
        "weights": take(weights), "means": take(means), "stds": take(stds), "background": bg,
        "partial_volume": pvw,
        "init_weights": start[0], "init_means": start[1], "init_stds": start[2],
        "init_background": start[3], "init_partial_volume": start[4],
        "loglik": np.where(ok, loglik, 0.0), "iterations": iterations,
    }


def _pv_density(x, means, stds, fat, muscle):
    """Density of fat/muscle partial-volume voxels: a uniform mixing fraction between the two
    means, blurred by their noise: ``(Phi((x - m_f) / s) - Phi((x - m_m) / s)) / (m_m - m_f)``
    with ``s^2 = (s_f^2 + s_m^2) / 2``. Returns (R, B).
    """
    r = np.arange(means.shape[0])
    m_f, m_m = means[r, fat][:, None], means[r, muscle][:, None]
    s = np.sqrt(0.5 * (stds[r, fat] ** 2 + stds[r, muscle] ** 2))[:, None]
    lo, hi = np.minimum(m_f, m_m), np.maximum(m_f, m_m)
    dens = (special.ndtr((x[None, :] - lo) / s) - special.ndtr((x[None, :] - hi) / s)) / (
        np.maximum(hi - lo, 1e-6))
    return np.maximum(dens, 1e-300)


def _pair(weights, means, stds):
    """Fat and muscle columns: the pair of components, muscle the higher mean, separated by
    at least the larger std, whose lower peak height (weight / std) is the highest."""
    n_rows, k = weights.shape
    if k == 2:
        hi = (means[:, 1] > means[:, 0]).astype(int)
        return 1 - hi, hi
    height = weights / stds
    i, j = np.triu_indices(k, 1)
    lo_col = np.where(means[:, i] <= means[:, j], i, j)  # (R, P)
    hi_col = np.where(means[:, i] <= means[:, j], j, i)
    sep = np.abs(means[:, i] - means[:, j]) >= np.maximum(stds[:, i], stds[:, j])
    score = np.where(sep, np.minimum(height[:, i], height[:, j]), -np.inf)
    best = np.argmax(score, axis=1)
    r = np.arange(n_rows)
    return lo_col[r, best], hi_col[r, best]


def _peaks(hist, x, k, separation):
    """Deterministic initial means: the ``k`` most prominent peaks of each smoothed row.

    Peaks are local maxima ranked by their topographic prominence (as
    :func:`scipy.signal.peak_prominences` defines it, see :func:`_prominences`), so the shoulder of a big peak is never taken for a
    second tissue. Rows with fewer than ``k`` peaks get the rest greedily: the maximum of the
    histogram damped by ``1 - exp(-d^2 / (2 separation^2))`` around the means already chosen.
    """
    smooth = ndimage.gaussian_filter1d(hist, 2.0, axis=1, mode="constant")
    means = np.full((hist.shape[0], k), np.nan)
    for r, row in enumerate(smooth):  # one row per slice (or the pooled one), not voxels
        idx, prom = _prominences(row)
        best = idx[np.argsort(prom, kind="stable")[::-1][:k]]
        means[r, : best.size] = x[best]
        score = row.copy()
        for j in range(k):
            if j >= best.size:
                means[r, j] = x[np.argmax(score)]
            score = score * -np.expm1(-0.5 * ((x - means[r, j]) / separation[r]) ** 2)
    return means


def _prominences(row):
    """Local maxima of a 1-D array (zero beyond its ends) and their prominences: the height
    above the higher of the two lowest points between the peak and the nearest higher point
    on each side. (``scipy.signal.find_peaks`` does the same, but importing scipy.signal
    costs seconds.)"""
    h = np.concatenate([[0.0], row, [0.0]])
    left, right = h[:-2], h[2:]
    idx = np.flatnonzero((h[1:-1] > left) & (h[1:-1] >= right)) + 1
    prom = np.empty(idx.size)
    for n, i in enumerate(idx):  # a few peaks per histogram
        higher_left = np.flatnonzero(h[:i] > h[i])
        higher_right = np.flatnonzero(h[i + 1:] > h[i])
        lo = higher_left[-1] if higher_left.size else 0
        hi = i + 1 + higher_right[0] if higher_right.size else h.size - 1
        prom[n] = h[i] - max(h[lo:i + 1].min(), h[i:hi + 1].min())
    return idx - 1, prom


def _fat_muscle(weights, means, stds):
    """Fat and muscle components (:func:`_pair`) and the fat group: the components whose
    mean is below the midpoint of the fat and muscle means (the rest are muscle)."""
    fat, muscle = _pair(weights, means, stds)
    r = np.arange(weights.shape[0])
    mid = 0.5 * (means[r, fat] + means[r, muscle])
    return means < mid[:, None], fat, muscle


def _crossing(weights, means, stds, fat_group, fat, muscle):
    """Value between the fat and muscle means where the two groups' posteriors are equal.

    Two components: the root of the quadratic ``log(w_f N_f) = log(w_m N_m)``. More: the
    first sign change of ``log sum_fat w N - log sum_muscle w N`` on a 0.05 HU grid, refined
    linearly.
    """
    r = np.arange(weights.shape[0])
    m1, m2 = means[r, fat], means[r, muscle]
    if weights.shape[1] == 2:
        return _crossing_two(weights, means, stds, fat, muscle)
    steps = np.linspace(0.0, 1.0, 2001)
    x = m1[:, None] + (m2 - m1)[:, None] * steps[None, :]  # (R, S)
    logp = (np.log(weights / stds)[:, None, :] - 0.5 * ((x[..., None] - means[:, None, :])
            / stds[:, None, :]) ** 2)
    big = logp.max(axis=2, keepdims=True)
    dens = np.exp(logp - big)
    g = np.log(np.maximum((dens * fat_group[:, None, :]).sum(axis=2), 1e-300)) - np.log(
        np.maximum((dens * ~fat_group[:, None, :]).sum(axis=2), 1e-300))
    change = (g[:, :-1] > 0) & (g[:, 1:] <= 0)
    found = change.any(axis=1) & (m2 > m1)
    i = np.argmax(change, axis=1)
    g0, g1 = g[r, i], g[r, i + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(g0 != g1, g0 / (g0 - g1), 0.5)
    thr = x[r, i] + frac * (x[r, i + 1] - x[r, i])
    return np.where(found, thr, 0.5 * (m1 + m2)), found


def _crossing_two(weights, means, stds, fat, muscle):
    r = np.arange(weights.shape[0])
    w1, m1, s1 = weights[r, fat], means[r, fat], stds[r, fat]
    w2, m2, s2 = weights[r, muscle], means[r, muscle], stds[r, muscle]
    # log(w1 N1(t)) - log(w2 N2(t)) = a t^2 + b t + c
    a = 0.5 / s2**2 - 0.5 / s1**2
    b = m1 / s1**2 - m2 / s2**2
    c = 0.5 * m2**2 / s2**2 - 0.5 * m1**2 / s1**2 + np.log(w1 * s2 / (w2 * s1))
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = np.sqrt(np.maximum(b**2 - 4 * a * c, 0.0))
        roots = np.stack([(-b - disc) / (2 * a), (-b + disc) / (2 * a)], axis=1)
        linear = -c / b
    small = np.abs(a) < 1e-12 * np.maximum(np.abs(b), 1e-300)
    roots = np.where(small[:, None], linear[:, None], roots)
    real = (b**2 - 4 * a * c >= 0) | small
    between = real[:, None] & (roots >= m1[:, None]) & (roots <= m2[:, None])
    found = between.any(axis=1)
    pick = np.argmax(between, axis=1)
    thr = np.where(found, roots[r, pick], 0.5 * (m1 + m2))
    return thr, found & (m2 > m1)
