"""Paper 001 Fig. 1: per-slice Gaussian mixture + EM fat/muscle classification.

Three matplotlib panels for one axial slice of a segmented CT: (a) the histogram of the
slice's soft-tissue HU with the initial and the EM-fitted Gaussians and the threshold where
the fat and muscle posteriors cross, (b) the slice after thresholding, (c) after the 5x5
median filter. The numbers come from :func:`pvcmf.filters.classify_tissue` (its
``SliceMixtures``); drawing delegates to matplotlib.
"""

from __future__ import annotations

import logging

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure

from .. import arrays
from ..filters.classify import classify_tissue

log = logging.getLogger(__name__)

#: label colours of the slice panels (paper: fat orange, muscle white)
COLORS = {
    arrays.AIR: "#000000",
    arrays.FAT: "#f28e2b",
    arrays.MUSCLE_TISSUE: "#ffffff",
    arrays.BONE_TISSUE: "#4e79a7",
    arrays.TEETH: "#9ecae9",
    arrays.INTRACRANIAL: "#555555",
}


def pick_slice(mixtures):
    """The slice with its own fit whose fat and muscle are most balanced: the largest
    ``n_voxels * min(fat weight, muscle weight)`` (a slice through the face, not the neck)."""
    fat = (mixtures.weights * mixtures.fat_group).sum(axis=1)
    muscle = (mixtures.weights * ~mixtures.fat_group).sum(axis=1)
    score = np.nan_to_num(np.minimum(fat, muscle) * mixtures.n_voxels)
    score[mixtures.fallback] = -1.0
    return int(np.argmax(score))


def fig1_gmm(image, *, slice_index=None, n_components=2, figsize=(13.0, 4.4), **options):
    """Draw paper 001 Fig. 1 for one axial slice of a segmented CT.

    Parameters
    ----------
    image : pyvista.ImageData
        Output of :func:`pvcmf.filters.segment` (arrays ``ct`` and ``tissue``).
    slice_index : int, optional
        Index (axis 2) of the slice to show; default :func:`pick_slice`.
    n_components : int
        Gaussians per slice, passed to :func:`pvcmf.filters.classify_tissue`.
    figsize : (float, float)
        Figure size in inches.
    **options
        Further keyword arguments of :func:`pvcmf.filters.classify_tissue`.

    Returns
    -------
    matplotlib.figure.Figure

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.figures.gmm import fig1_gmm
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)  # doctest: +SKIP
    >>> fig = fig1_gmm(case.ct.cmf.segment())  # doctest: +SKIP
    """
    median_size = options.pop("median_size", 5)
    raw, mix = classify_tissue(image, n_components=n_components, median_size=1,
                               return_mixtures=True, **options)
    final = classify_tissue(image, n_components=n_components, median_size=median_size,
                            **options)
    dims = image.dimensions
    k = pick_slice(mix) if slice_index is None else int(slice_index)
    if not 0 <= k < dims[2]:
        raise ValueError(f"slice_index must be in [0, {dims[2] - 1}], got {slice_index!r}")
    if mix.n_voxels[k] == 0:
        raise ValueError(f"slice {k} has no soft tissue to show")
    log.debug("fig1_gmm: slice %d", k)

    fig = Figure(figsize=figsize)  # fixed layout: new numbers do not move the axes
    ax_h, ax_t, ax_m = fig.subplots(1, 3, width_ratios=[1.35, 1, 1])
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.12, top=0.92, wspace=0.3)

    _histogram_panel(ax_h, mix, k)
    _slice_panels((ax_t, ax_m), image, raw, final, k, median_size)
    return fig


def _histogram_panel(ax_h, mix, k):
    """Panel (a): slice ``k``'s soft-tissue histogram, initial and EM-fitted Gaussians."""
    x = mix.centers
    ax_h.plot(x, mix.hist[k], color="black", lw=1.0, zorder=2, label="histogram (soft tissue)")
    fine = np.linspace(mix.edges[0], mix.edges[-1], 600)
    init = mix.densities(k, fine, initial=True)
    fitted = mix.densities(k, fine)
    for j in range(init.shape[1]):
        ax_h.plot(fine, init[:, j], color="0.55", ls=":", lw=1.3,
                  label="initial Gaussians" if j == 0 else None)
    ax_h.plot(fine, init.sum(axis=1) + mix.floor(k, initial=True), color="0.35", ls="--",
              lw=1.2, label="initial mixture")
    for j in range(fitted.shape[1]):
        is_fat = bool(mix.fat_group[k, j])
        ax_h.plot(fine, fitted[:, j], color="#e67e22" if is_fat else "#c0392b", lw=2.0, zorder=3,
                  label=("EM fat" if is_fat else "EM muscle")
                  if j in (mix.fat[k], mix.muscle[k]) else None)
    pv_curve = mix.partial_volume_density(k, fine)
    if np.any(pv_curve > 0):
        ax_h.plot(fine, pv_curve, color="#8e44ad", lw=1.2, ls="-",
                  label="EM fat/muscle partial volume")
    ax_h.plot(fine, fitted.sum(axis=1) + pv_curve + mix.floor(k), color="#1f77b4", lw=1.0,
              ls="--", zorder=1, label="EM mixture (+ uniform background)")
    ax_h.axvline(mix.threshold[k], color="black", lw=1.0, ls="-.",
                 label=f"threshold {mix.threshold[k]:.0f} HU")
    ax_h.set_xlim(mix.edges[0], mix.edges[-1])
    ax_h.set_ylim(0, 1.6 * max(mix.hist[k].max(), fitted.sum(axis=1).max()))  # room for legend
    ax_h.set_xlabel("CT value (HU)")
    ax_h.set_ylabel(f"voxels per {mix.edges[1] - mix.edges[0]:g} HU bin")
    ax_h.set_title(
        f"(a) slice {k}: fat {mix.fat_mean[k]:.0f} HU, muscle {mix.muscle_mean[k]:.0f} HU"
        + (" (pooled threshold)" if mix.fallback[k] else ""), fontsize=10)
    ax_h.legend(fontsize=7, loc="upper left", frameon=False)


def _slice_panels(axes, image, raw, final, k, median_size):
    """Panels (b), (c): slice ``k`` after the threshold and after the median filter."""
    ax_t, ax_m = axes
    dims = image.dimensions
    ids = sorted(COLORS)
    cmap = ListedColormap([COLORS[i] for i in range(max(ids) + 1)])
    sx, sy = image.spacing[0], image.spacing[1]
    extent = (image.origin[0] - sx / 2, image.origin[0] + (dims[0] - 0.5) * sx,
              image.origin[1] - sy / 2, image.origin[1] + (dims[1] - 0.5) * sy)
    head = final.point_data[arrays.TISSUE].reshape(dims, order="F")[:, :, k] != arrays.AIR
    ii, jj = np.nonzero(head)
    pad = 4
    xlim = (image.origin[0] + (ii.min() - pad) * sx, image.origin[0] + (ii.max() + pad) * sx)
    ylim = (image.origin[1] + (jj.min() - pad) * sy, image.origin[1] + (jj.max() + pad) * sy)
    for ax, img, title in (
        (ax_t, raw, "(b) threshold per slice"),
        (ax_m, final, f"(c) after {median_size}x{median_size} median"),
    ):
        lab = img.point_data[arrays.TISSUE].reshape(dims, order="F")[:, :, k]
        ax.imshow(lab.T, origin="lower", cmap=cmap, vmin=-0.5, vmax=max(ids) + 0.5,
                  interpolation="nearest", extent=extent)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm, anterior up)")
