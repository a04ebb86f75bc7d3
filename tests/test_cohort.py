"""The cohort study's bookkeeping: cached predictions and the skin the scans cannot judge.

* :mod:`pvcmf.study.predictions`: a second run reads each prediction instead of computing
  it, a changed patient, option or code recomputes it, and a corrupt entry is recomputed,
  never trusted;
* :func:`pvcmf.study.validation.study_predictor` judges only the skin where the
  post-operative CT shows the skin the truth moved: a wall that is skin in the
  pre-operative scan only (an internal air passage open to the outside in one CT) is left
  out of every method, counted and logged.

Small synthetic surfaces, no pipeline run.
"""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.registration import ICP_MATRIX
from pvcmf.study import predictions, validation
from pvcmf.study.predictions import cached_prediction, prediction_code_hash


def _case(patient=101, thickness=1.0):
    return SimpleNamespace(patient=patient, parameters=("params", thickness), spacing=3.0,
                           plan="plan", landmarks={"pronasale": (0.0, 50.0, 0.0)},
                           ct=pv.ImageData(dimensions=(2, 2, 2)), truth=None)


def _skin(shift=0.0):
    skin = pv.Sphere(radius=20.0, theta_resolution=12, phi_resolution=12)
    skin.points = skin.points + shift
    skin.point_data[arrays.MAPPING_SUPPORT] = np.ones(skin.n_points)
    skin.point_data[arrays.DISPLACEMENT] = np.full((skin.n_points, 3), shift)
    return skin


class Counter:
    """``compute()`` of a prediction that counts its calls."""

    def __init__(self):
        self.calls = 0

    def __call__(self, shift=1.5):
        self.calls += 1
        return -10.0, _skin(shift)


@pytest.fixture(autouse=True)
def _no_package_hash(monkeypatch, request):
    """The package's code hash parses every module (seconds): a fixed one where the test
    is not about it."""
    if "code_hash" not in request.node.name:
        monkeypatch.setattr(predictions, "prediction_code_hash", lambda *a: "code")


def test_second_run_reads_the_prediction_and_changes_recompute(tmp_path):
    compute = Counter()

    def run(case=None, options=None, method="proposed"):
        return cached_prediction(compute, case or _case(), method,
                                 options or {"n_tets": 5000, "sigma": 2.0},
                                 cache_dir=tmp_path, n_points=_skin().n_points)

    y0, first = run()
    y1, again = run()
    assert compute.calls == 1  # read, not computed
    assert y0 == y1 == -10.0
    np.testing.assert_array_equal(first.points, again.points)
    np.testing.assert_array_equal(first[arrays.DISPLACEMENT], again[arrays.DISPLACEMENT])
    run(options={"n_tets": 6000, "sigma": 2.0})
    assert compute.calls == 2  # another size
    run(case=_case(thickness=1.1))
    assert compute.calls == 3  # another patient parameter
    run(method="state_of_the_art")
    assert compute.calls == 4
    run()
    assert compute.calls == 4
    assert len(list((tmp_path / "predictions").iterdir())) == 4


@pytest.mark.parametrize("damage", ["garbage", "missing", "truncated"])
def test_corrupt_prediction_entry_is_recomputed(tmp_path, damage, caplog):
    compute = Counter()

    def run():
        return cached_prediction(compute, _case(), "proposed", {"n_tets": 5000},
                                 cache_dir=tmp_path, n_points=_skin().n_points)

    run()
    (entry,) = (tmp_path / "predictions").iterdir()
    skin_file = entry / "skin.vtp"
    if damage == "garbage":
        skin_file.write_bytes(b"<VTKFile>not a skin")
    elif damage == "missing":
        skin_file.unlink()
    else:  # a smaller skin than its record says
        pv.Sphere(theta_resolution=4, phi_resolution=4).save(skin_file)
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        y0, skin = run()
    assert compute.calls == 2
    assert "ignoring unreadable entry" in caplog.text
    assert skin.n_points == _skin().n_points and y0 == -10.0
    run()
    assert compute.calls == 2  # the rewritten entry is read


def test_prediction_of_another_skin_size_is_recomputed(tmp_path):
    compute = Counter()
    cached_prediction(compute, _case(), "proposed", {}, cache_dir=tmp_path)
    cached_prediction(compute, _case(), "proposed", {}, cache_dir=tmp_path,
                      n_points=_skin().n_points + 1)
    assert compute.calls == 2


def test_prediction_code_hash_follows_the_prediction_code(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "truth").mkdir(parents=True)
    code = pkg / "pipeline.py"
    code.write_text("def simulate(x):\n    return x + 1\n")
    (pkg / "truth" / "solver.py").write_text("A = 1\n")
    (pkg / "truth" / "postop.py").write_text("B = 1\n")
    before = prediction_code_hash(pkg)
    prediction_code_hash.cache_clear()
    code.write_text('def simulate(x):\n    "doc"\n    return x + 1  # comment\n')
    assert prediction_code_hash(pkg) == before  # documentation only
    prediction_code_hash.cache_clear()
    (pkg / "truth" / "solver.py").write_text("A = 2\n")
    assert prediction_code_hash(pkg) == before  # the truth's solver predicts nothing
    for path, text in ((code, "def simulate(x):\n    return x + 2\n"),
                       (pkg / "truth" / "postop.py", "B = 2\n")):
        prediction_code_hash.cache_clear()
        path.write_text(text)
        assert prediction_code_hash(pkg) != before, path.name
        before = prediction_code_hash(pkg)
    prediction_code_hash.cache_clear()


def test_study_predictor_reads_cached_predictions(tmp_path, monkeypatch):
    """A fresh predictor (a second run) runs no pipeline; the truth's own skin is never
    cached (it depends on the truth); without ``prediction_cache`` nothing is cached."""
    calls = []

    def fake_prediction(case, method, grid, pre_skin, n_tets, sigma):
        calls.append((method, n_tets))
        return -10.0, _skin(0.5)

    monkeypatch.setattr(validation, "_scan", lambda *args: (None, None, _skin(), None))
    monkeypatch.setattr(validation, "_prediction", fake_prediction)
    monkeypatch.setattr(validation, "_judge", lambda case, reg, pred, y0, masks: pred)
    cases = {101: _case()}
    for _ in range(2):
        predict = validation.study_predictor(spacing=3.0, n_tets=5000, truth_tets=2000,
                                             truth=lambda c: None, cases=cases,
                                             cache_dir=tmp_path, prediction_cache=True)
        for method in ("proposed", "state_of_the_art_auto", "truth"):
            assert predict(101, method).n_points == _skin().n_points
    assert calls == [("proposed", 5000), ("state_of_the_art_auto", 5000), ("truth", 5000),
                     ("truth", 5000)]
    validation.study_predictor(spacing=3.0, n_tets=6000, truth_tets=2000,
                               truth=lambda c: None, cases=cases, cache_dir=tmp_path,
                               prediction_cache=True)(101, "proposed")
    assert calls[-1] == ("proposed", 6000)
    validation.study_predictor(spacing=3.0, n_tets=5000, truth_tets=2000,
                               truth=lambda c: None, cases=cases,
                               cache_dir=tmp_path / "off")(101, "proposed")
    assert calls[-1] == ("proposed", 5000) and not (tmp_path / "off").exists()


def _scans():
    """A head whose pre-operative skin has an inner wall (an air passage open to the
    outside in that scan) that the registered post-operative skin lacks."""
    head = pv.Sphere(radius=60.0, theta_resolution=40, phi_resolution=40)
    passage = pv.Sphere(radius=15.0, center=(0.0, 20.0, 0.0), theta_resolution=16,
                        phi_resolution=16)
    pre_skin = (head + passage).extract_surface(algorithm="dataset_surface")
    grid = pv.ImageData(dimensions=(14, 14, 14), spacing=(10.0, 10.0, 10.0),
                        origin=(-65.0, -65.0, -65.0)).cast_to_unstructured_grid()
    grid.point_data[arrays.DISPLACEMENT] = np.zeros((grid.n_points, 3))
    registered = head.copy()
    registered.field_data[ICP_MATRIX] = np.eye(4)
    inner = np.linalg.norm(pre_skin.points - (0.0, 20.0, 0.0), axis=1) < 16.0
    return pre_skin, grid, registered, inner


def test_skin_the_post_operative_ct_lacks_is_not_judged(caplog):
    pre_skin, grid, registered, inner = _scans()
    case = _case()
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        covered, apart = validation._judgeable(case, 101, grid, registered, pre_skin)
    assert covered.all()
    np.testing.assert_array_equal(apart, inner)  # the passage wall, nothing else
    assert f"{inner.sum()} of {pre_skin.n_points} skin points" in caplog.text
    pred = pre_skin.copy()
    pred.point_data[arrays.MAPPING_SUPPORT] = np.ones(pred.n_points)
    judged = validation._judge(case, registered, pred, -100.0, (covered, apart))
    assert judged.n_points == (~inner).sum()
    assert int(judged.field_data[arrays.STUDY_EXCLUDED][0]) == inner.sum()
    assert np.abs(judged[arrays.DISTANCE]).max() < 0.5  # the head's own skin: no error
    np.testing.assert_array_equal(np.sort(judged[arrays.SKIN_POINT_ID]), np.flatnonzero(~inner))


def test_skin_every_scan_shows_is_all_judged(caplog):
    pre_skin, grid, _, _ = _scans()
    registered = pre_skin.copy()
    registered.field_data[ICP_MATRIX] = np.eye(4)
    with caplog.at_level(logging.WARNING, logger="pvcmf"):
        covered, apart = validation._judgeable(_case(), 101, grid, registered, pre_skin)
    assert covered.all() and not apart.any() and "not judged" not in caplog.text
