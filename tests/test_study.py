"""Paper 000's validation study on the virtual patients (``validation.study_predictor``):
a small version of the whole study (coarse patient, MTM and truth meshes) gives the same
numbers twice, the second time with the truth recomputed from scratch, and a third time
from the truth's disk cache. Skipped without the optional extra ``pvcmf[reference]``."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pvcmf import arrays
from pvcmf.validation import STAT_COLUMNS, run_study, study_predictor

pytest.importorskip("ngsolve")

SMALL = dict(spacing=3.0, n_tets=2000, truth_tets=4000)


def small_study(cache_dir):
    with warnings.catch_warnings():  # coarse meshes drop the thinnest muscles (warned)
        warnings.filterwarnings("ignore", message=".*thinner than the")
        return run_study(study_predictor(**SMALL, cache_dir=cache_dir), patients=(1,))


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    first, second = tmp_path_factory.mktemp("truth1"), tmp_path_factory.mktemp("truth2")
    return first, small_study(first), small_study(second)


def test_small_study_is_reproducible(two_runs):
    _, (skins1, d1, t1), (skins2, d2, t2) = two_runs
    assert set(t1["method"]) == {"proposed", "state_of_the_art"}
    face = t1[t1["region"] == "face"]
    assert (face["n"] > 1000).all()  # a real face was judged
    assert (face["p90"] < 10).all() and (face["p50"] > 0).all()
    for method in ("proposed", "state_of_the_art"):
        np.testing.assert_allclose(d1[1][method], d2[1][method], rtol=0, atol=1e-9)
        np.testing.assert_array_equal(skins1[1][method][arrays.REGION],
                                      skins2[1][method][arrays.REGION])
    assert list(t1.columns) == list(t2.columns)
    num = list(STAT_COLUMNS)
    np.testing.assert_allclose(t1[num].to_numpy(float), t2[num].to_numpy(float),
                               rtol=0, atol=1e-9)


def test_small_study_from_cached_truth(two_runs):
    cache, (_, d1, _), _ = two_runs
    assert len(list(cache.glob("postop_skin_*.vtp"))) == 1
    _, d3, _ = small_study(cache)
    np.testing.assert_allclose(d3[1]["proposed"], d1[1]["proposed"], rtol=0, atol=1e-6)


def test_study_predictor_bad_input():
    with pytest.raises(ValueError, match="spacing must be > 0 mm, got -1"):
        study_predictor(spacing=-1)
    with pytest.raises(ValueError, match="truth_tets must be an integer >= 100, got 5"):
        study_predictor(truth_tets=5)
    with pytest.raises(ValueError, match="method must be 'proposed' or 'state_of_the_art'"):
        study_predictor(**SMALL)(1, "magic")
