"""classify_tissue: the per-slice EM recovers known Gaussian mixtures (checked against the
analytic parameters and an independent maximum-likelihood fit), thresholds sit where the
posteriors cross, the 5x5 median is a per-slice majority, other labels are untouched."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy import ndimage, optimize, stats

import pvcmf
from pvcmf import arrays
from pvcmf.filters.classify import SliceMixtures

NX, NY, NZ = 60, 60, 6
FAT = (-100.0, 20.0)  # mean, std (HU)


def muscle_params(k):
    """Per-slice muscle mean/std and muscle share: every slice differs."""
    return 30.0 + 6.0 * k, 12.0 + 1.5 * k, 0.2 + 0.05 * k


def mixture_image(seed=0, background=0.0, spatial=False):
    """Slices of samples from known fat/muscle Gaussians; ``tissue`` all FAT.

    ``spatial`` puts the muscle in one block (x > NX * (1 - share)) instead of at random.
    """
    rng = np.random.default_rng(seed)
    img = pv.ImageData(dimensions=(NX, NY, NZ), spacing=(1.0, 1.0, 2.0))
    vol = np.empty((NX, NY, NZ))
    truth = np.zeros((NX, NY, NZ), dtype=bool)
    for k in range(NZ):  # building the test input, one slice at a time
        m, s, share = muscle_params(k)
        if spatial:
            is_m = np.broadcast_to(np.arange(NX)[:, None] >= NX * (1 - share), (NX, NY))
        else:
            is_m = rng.random((NX, NY)) < share
        vals = np.where(is_m, rng.normal(m, s, (NX, NY)), rng.normal(*FAT, (NX, NY)))
        if background:
            tail = rng.random((NX, NY)) < background
            vals = np.where(tail, rng.uniform(-400.0, 300.0, (NX, NY)), vals)
        vol[:, :, k] = vals
        truth[:, :, k] = is_m
    img[arrays.CT] = vol.astype(np.float32).ravel(order="F")
    img[arrays.TISSUE] = np.full(img.n_points, arrays.FAT, dtype=np.uint8)
    return img, vol, truth


def posterior_crossing(w1, m1, s1, w2, m2, s2):
    """Independent root finding of w1 N1 = w2 N2 between the means."""
    f = lambda t: np.log(w1 * stats.norm.pdf(t, m1, s1)) - np.log(w2 * stats.norm.pdf(t, m2, s2))  # noqa: E731
    return optimize.brentq(f, m1, m2)


@pytest.fixture(scope="module")
def fitted():
    img, vol, truth = mixture_image()
    out, mix = pvcmf.filters.classify_tissue(img, return_mixtures=True, median_size=1)
    return img, vol, truth, out, mix


def test_recovers_known_mixtures(fitted):
    _, _, _, _, mix = fitted
    assert isinstance(mix, SliceMixtures)
    assert not mix.fallback.any()
    for k in range(NZ):
        m, s, share = muscle_params(k)
        f, u = mix.fat[k], mix.muscle[k]
        assert mix.means[k, f] == pytest.approx(FAT[0], abs=2.0)
        assert mix.stds[k, f] == pytest.approx(FAT[1], rel=0.08)
        assert mix.means[k, u] == pytest.approx(m, abs=2.5)
        assert mix.stds[k, u] == pytest.approx(s, rel=0.12)
        assert mix.weights[k, u] == pytest.approx(share, abs=0.03)
        # the threshold is the crossing of the fitted weighted densities ...
        w = mix.weights[k]
        t = posterior_crossing(w[f], mix.means[k, f], mix.stds[k, f], w[u], mix.means[k, u],
                               mix.stds[k, u])
        assert mix.threshold[k] == pytest.approx(t, abs=0.01)
        # ... and close to the crossing of the true ones
        t_true = posterior_crossing(1 - share, *FAT, share, m, s)
        assert mix.threshold[k] == pytest.approx(t_true, abs=4.0)


def test_matches_independent_maximum_likelihood(fitted):
    """scipy's Nelder-Mead on the exact (unbinned) likelihood of one slice's voxels."""
    _, vol, _, _, mix = fitted
    k = 2
    x = vol[:, :, k].ravel()

    def nll(p):
        w = 1.0 / (1.0 + np.exp(-p[0]))
        dens = w * stats.norm.pdf(x, p[1], np.exp(p[2])) + (1 - w) * stats.norm.pdf(
            x, p[3], np.exp(p[4]))
        return -np.sum(np.log(dens + 1e-300))

    m, s, share = muscle_params(k)
    res = optimize.minimize(nll, [0.0, -90.0, np.log(25.0), 30.0, np.log(20.0)],
                            method="Nelder-Mead", options={"maxiter": 4000, "xatol": 1e-4,
                                                           "fatol": 1e-6})
    ml_fat, ml_muscle = res.x[1], res.x[3]
    assert mix.fat_mean[k] == pytest.approx(ml_fat, abs=1.0)
    assert mix.muscle_mean[k] == pytest.approx(ml_muscle, abs=1.0)
    assert mix.stds[k, mix.muscle[k]] == pytest.approx(np.exp(res.x[4]), rel=0.05)


def test_classification_follows_threshold(fitted):
    img, vol, _, out, mix = fitted
    lab = out[arrays.TISSUE].reshape(img.dimensions, order="F")
    expect = np.where(vol >= mix.threshold[None, None, :], arrays.MUSCLE_TISSUE, arrays.FAT)
    np.testing.assert_array_equal(lab, expect)


def test_background_and_paper_five_components():
    img, _, _ = mixture_image(seed=3, background=0.08)
    for n in (2, 5):
        _, mix = pvcmf.filters.classify_tissue(img, n_components=n, return_mixtures=True)
        for k in range(NZ):
            assert mix.fat_mean[k] == pytest.approx(FAT[0], abs=5.0)
            assert mix.muscle_mean[k] == pytest.approx(muscle_params(k)[0], abs=5.0)
    # without the background component the tails pull the Gaussians off the peaks
    _, mix = pvcmf.filters.classify_tissue(img, background=False, return_mixtures=True)
    err = np.abs(mix.muscle_mean - [muscle_params(k)[0] for k in range(NZ)])
    assert np.max(err) > 5.0


def test_median_is_per_slice_majority():
    img, vol, truth = mixture_image(seed=5, spatial=True)
    raw = pvcmf.filters.classify_tissue(img, median_size=1)[arrays.TISSUE]
    out = pvcmf.filters.classify_tissue(img, median_size=5)[arrays.TISSUE]
    raw_m = (raw == arrays.MUSCLE_TISSUE).reshape(img.dimensions, order="F")
    med_m = (out == arrays.MUSCLE_TISSUE).reshape(img.dimensions, order="F")
    # independent: scipy's median filter of the binary map, 5x5 in-slice, away from borders
    ref = ndimage.median_filter(raw_m.astype(np.uint8), size=(5, 5, 1)) > 0
    inner = (slice(2, -2), slice(2, -2), slice(None))
    np.testing.assert_array_equal(med_m[inner], ref[inner])
    # and it removes the salt-and-pepper misclassification of the noisy threshold
    assert (med_m != truth).mean() < 0.5 * (raw_m != truth).mean()


def test_other_labels_untouched_and_input_unchanged():
    img, _, _ = mixture_image(seed=7)
    tissue = img[arrays.TISSUE].copy()
    tissue[:500] = arrays.BONE_TISSUE
    tissue[500:700] = arrays.INTRACRANIAL
    tissue[700:800] = arrays.MUSCLE_TISSUE  # re-classified like FAT
    img[arrays.TISSUE] = tissue
    before = {k: np.array(img.point_data[k]) for k in img.point_data.keys()}
    out = img.cmf.classify_tissue()
    for k, v in before.items():
        np.testing.assert_array_equal(img.point_data[k], v)
    t = out[arrays.TISSUE]
    np.testing.assert_array_equal(t[:700], tissue[:700])
    assert set(np.unique(t[700:])) == {arrays.FAT, arrays.MUSCLE_TISSUE}
    np.testing.assert_array_equal(out[arrays.CT], img[arrays.CT])


def rim_image(seed=0):
    """Bone (x < 10, 1200 HU) beside soft tissue; the two voxel layers next to it read half
    and a quarter bone (partial volume and blur, ~550 and ~230 HU) whatever they are. Below
    y = 20 fat lies on the bone (muscle from x = 25), above muscle does. Returns the image
    and the true muscle map."""
    rng = np.random.default_rng(seed)
    dims = (40, 40, 4)
    x, y = np.meshgrid(np.arange(dims[0]), np.arange(dims[1]), indexing="ij")
    x, y = np.repeat(x[..., None], dims[2], 2), np.repeat(y[..., None], dims[2], 2)
    muscle = (x >= 10) & ((x >= 25) | (y >= 20))
    hu = np.where(muscle, rng.normal(40.0, 12.0, dims), rng.normal(-100.0, 15.0, dims))
    hu = np.where(x < 10, 1200.0, hu)
    hu = np.where(x == 10, 0.5 * (hu + 1200.0), hu)  # the partial-volume rim
    hu = np.where(x == 11, 0.75 * hu + 0.25 * 1200.0, hu)
    img = pv.ImageData(dimensions=dims)
    img[arrays.CT] = hu.astype(np.float32).ravel(order="F")
    img[arrays.TISSUE] = np.where(x < 10, arrays.BONE_TISSUE, arrays.FAT).astype(
        np.uint8).ravel(order="F")
    return img, muscle


def test_soft_tissue_on_a_border_takes_the_class_around_it():
    """The partial-volume rim on the bone reads above the threshold: by its value it would
    be a muscle shell around the skeleton; it takes the class of the soft tissue beside it
    instead (fat on fat, muscle on muscle). The same for muscle beside air, which reads as
    fat by its value."""
    img, muscle = rim_image()
    rows = np.r_[3:17, 23:37]  # away from the fat/muscle border at y = 20
    for border, expect_fat_rim in ((1, True), (0, False)):
        out = pvcmf.filters.classify_tissue(img, border=border)
        got = (np.asarray(out[arrays.TISSUE]) == arrays.MUSCLE_TISSUE).reshape(
            muscle.shape, order="F")
        if expect_fat_rim:
            np.testing.assert_array_equal(got[10:12][:, rows], muscle[10:12][:, rows])
        else:  # by their values alone (and the median) the rim voxels on fat are muscle
            assert got[10:12][:, 3:17].all()
        # the rest is classified as before, and the bone is left alone
        np.testing.assert_array_equal(got[12:][:, rows], muscle[12:][:, rows])
        assert not got[:10].any()
    # the same at an air border: muscle beside air reads half and a quarter air (~-480 and
    # ~-220 HU), fat by its value
    air = rim_image(seed=1)[0]
    hu = np.asarray(air[arrays.CT]).reshape(muscle.shape, order="F")
    hu = np.where(hu > 900, -1000.0, hu)
    hu[10] = 0.5 * (hu[12] - 1000.0)
    hu[11] = 0.75 * hu[13] - 250.0
    air[arrays.CT] = hu.astype(np.float32).ravel(order="F")
    tissue = np.asarray(air[arrays.TISSUE]).reshape(muscle.shape, order="F").copy()
    tissue[tissue == arrays.BONE_TISSUE] = arrays.AIR
    air[arrays.TISSUE] = tissue.ravel(order="F")
    for border in (1, 0):
        got = (np.asarray(pvcmf.filters.classify_tissue(air, border=border)[arrays.TISSUE])
               == arrays.MUSCLE_TISSUE).reshape(muscle.shape, order="F")
        assert got[10:12][:, 23:37].all() == bool(border)
    with pytest.raises(ValueError, match="border must be an integer >= 0"):
        pvcmf.filters.classify_tissue(img, border=-1)


def test_fat_only_slice_uses_pooled_threshold():
    img, vol, truth = mixture_image(seed=11)
    rng = np.random.default_rng(0)
    vol[:, :, 0] = rng.normal(*FAT, (NX, NY))  # slice 0: fat only
    img[arrays.CT] = vol.astype(np.float32).ravel(order="F")
    out, mix = pvcmf.filters.classify_tissue(img, return_mixtures=True, median_size=1)
    assert mix.fallback[0] and not mix.fallback[1:].any()
    assert mix.threshold[0] == mix.pooled_threshold
    lab0 = out[arrays.TISSUE].reshape(img.dimensions, order="F")[:, :, 0]
    assert (lab0 == arrays.MUSCLE_TISSUE).mean() < 0.01


# --------------------------------------------------------------------------- virtual patients
@pytest.fixture(scope="module")
def phantom_fits(segmented_patients):
    """Virtual patients at 2 mm, segmented once (conftest), then classified."""
    out = {}
    for p, (case, segmented) in segmented_patients.items():
        labelled, mix = segmented.cmf.classify_tissue(return_mixtures=True)
        out[p] = (case, labelled, mix, segmented)
    return out


@pytest.mark.parametrize("patient", [1, 2, 3, 4])
def test_phantom_fat_muscle_hu(phantom_fits, patient):
    from pvcmf.datasets.phantom import HU

    case, labelled, mix, _ = phantom_fits[patient]
    own = (mix.n_voxels > 0) & ~mix.fallback
    assert own.sum() >= 10  # slices through the muscles get their own mixture
    fat = np.average(mix.fat_mean[own], weights=mix.n_voxels[own])
    muscle = np.average(mix.muscle_mean[own], weights=mix.n_voxels[own])
    assert abs(fat - HU["fat"]) <= 15.0, f"fat {fat:.1f} HU"
    assert abs(muscle - HU["muscle"]) <= 15.0, f"muscle {muscle:.1f} HU"
    # the whole-volume fit (two Gaussians, sorted by mean: fat, muscle)
    assert abs(mix.pooled_means[0] - HU["fat"]) <= 15.0
    assert abs(mix.pooled_means[1] - HU["muscle"]) <= 15.0
    # the labels follow. Floors, not targets: at 2 mm the muscles are 1-3 voxels thick, so
    # many of their voxels mix with fat. Fat voxels next to bone are brightened by it: by
    # their values alone (border=0) fat recall stays below 0.92; the border rule lifts it
    t, c = case.truth[arrays.TISSUE], labelled[arrays.TISSUE]
    soft = np.isin(t, arrays.SOFT_LABELS) & np.isin(c, arrays.SOFT_LABELS)
    assert np.mean(c[soft & (t == arrays.FAT)] == arrays.FAT) > 0.94
    assert np.mean(c[soft & (t == arrays.MUSCLE_TISSUE)] == arrays.MUSCLE_TISSUE) > 0.9


def test_fig1_gmm_chart(phantom_fits, verify_chart):
    """Paper 001 Fig. 1 on virtual patient 1 (the gallery draws it at 1 mm)."""
    from pvcmf.figures.gmm import fig1_gmm, pick_slice

    _, _, mix, segmented = phantom_fits[1]
    k = pick_slice(mix)
    assert not mix.fallback[k] and mix.n_voxels[k] > 0
    fig = fig1_gmm(segmented, slice_index=k)
    verify_chart(fig)


def test_bad_input():
    img, _, _ = mixture_image()
    with pytest.raises(TypeError, match="ImageData"):
        pvcmf.filters.classify_tissue(pv.Sphere())
    no_tissue = img.copy()
    del no_tissue.point_data[arrays.TISSUE]
    with pytest.raises(ValueError, match="no point array 'tissue'.*segment"):
        pvcmf.filters.classify_tissue(no_tissue)
    air = img.copy()
    air[arrays.TISSUE] = np.zeros(img.n_points, dtype=np.uint8)
    with pytest.raises(ValueError, match="no soft tissue"):
        pvcmf.filters.classify_tissue(air)
    with pytest.raises(ValueError, match="median_size must be an odd"):
        pvcmf.filters.classify_tissue(img, median_size=4)
    with pytest.raises(ValueError, match="n_components"):
        pvcmf.filters.classify_tissue(img, n_components=1)
    with pytest.raises(ValueError, match="hu_range"):
        pvcmf.filters.classify_tissue(img, hu_range=(100.0, -100.0))


def test_peak_prominences_match_scipy():
    """The initialisation's peak finder against scipy.signal.find_peaks (independent)."""
    from scipy.signal import find_peaks

    from pvcmf.filters.classify import _prominences

    rng = np.random.default_rng(0)
    for _ in range(50):
        row = np.convolve(rng.random(60), np.ones(3), "same") * (rng.random(60) > 0.2)
        idx, props = find_peaks(np.concatenate([[0.0], row, [0.0]]), prominence=0.0)
        mine, prom = _prominences(row)
        np.testing.assert_array_equal(mine, idx - 1)
        np.testing.assert_allclose(prom, props["prominences"])
