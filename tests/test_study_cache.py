"""The cohort study's warm cache: cached patients and judged skins.

* :func:`pvcmf.study.cohort.virtual_patient` with ``cache=True``: the patient read back
  is the patient built (image bytes, landmarks), a second call builds nothing, and a
  changed parameter, plan, voxel size, number or code builds again;
* :func:`pvcmf.study.validation.study_predictor` with ``prediction_cache=True`` and a
  named truth: a second run reads each judged skin (bit-identical) and runs neither the
  truth, the post-operative CT nor the judging; a changed option of the truth or the
  judging, or a changed code, judges again; with a truth callable nothing is judged
  from the cache;
* :func:`pvcmf.study.predictions.judged_code_hash` follows the truth's and the judging's
  code, not their documentation.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.registration import ICP_MATRIX
from pvcmf.study import cohort, predictions, validation
from pvcmf.study.cohort import cohort_parameters, virtual_patient
from pvcmf.study.predictions import _image_digest, judged_code_hash, prediction_code_hash


@pytest.fixture
def fixed_code(monkeypatch):
    """The package's code hash parses every module (seconds): a fixed one, changeable."""
    code = {"hash": "code"}
    monkeypatch.setattr(cohort, "judged_code_hash", lambda *a: code["hash"])
    monkeypatch.setattr(predictions, "judged_code_hash", lambda *a: code["hash"])
    monkeypatch.setattr(predictions, "prediction_code_hash", lambda *a: "prediction")
    return code


# ------------------------------------------------------------------------ patients
def test_cached_patient_is_the_built_one_and_changes_rebuild(tmp_path, monkeypatch,
                                                             fixed_code):
    built = []
    build = cohort._build

    def counting(*args):
        built.append(args[3])
        return build(*args)

    monkeypatch.setattr(cohort, "_build", counting)
    (params, plan), (params2, plan2) = cohort_parameters(2, seed=5)
    fresh = virtual_patient(params, plan, spacing=4.0, number=101)
    first = virtual_patient(params, plan, spacing=4.0, number=101, cache=True,
                            cache_dir=tmp_path)
    again = virtual_patient(params, plan, spacing=4.0, number=101, cache=True,
                            cache_dir=tmp_path)
    assert built == [101, 101]  # the uncached build and the first cached one
    for case in (first, again):
        assert _image_digest(case.ct) == _image_digest(fresh.ct)
        assert _image_digest(case.truth) == _image_digest(fresh.truth)
        assert case.ct.point_data[arrays.CT].dtype == fresh.ct.point_data[arrays.CT].dtype
        assert sorted(case.landmarks) == sorted(fresh.landmarks)
        for name, value in fresh.landmarks.items():
            np.testing.assert_array_equal(case.landmarks[name], value)
        assert (case.name, case.patient, case.spacing, case.plan, case.parameters) == (
            fresh.name, fresh.patient, fresh.spacing, fresh.plan, fresh.parameters)
    # every part of the key builds again: parameters, plan, number, voxel size, code
    for kwargs in (dict(params=params2, plan=plan), dict(params=params, plan=plan2),
                   dict(params=params, plan=plan, number=102),
                   dict(params=params, plan=plan, spacing=3.9)):
        n = len(built)
        virtual_patient(**{"spacing": 4.0, "number": 101, **kwargs}, cache=True,
                        cache_dir=tmp_path)
        assert len(built) == n + 1, kwargs
    fixed_code["hash"] = "other code"
    virtual_patient(params, plan, spacing=4.0, number=101, cache=True, cache_dir=tmp_path)
    assert len(built) == 7


def test_corrupt_cached_patient_is_rebuilt(tmp_path, monkeypatch, fixed_code):
    built = []
    build = cohort._build
    monkeypatch.setattr(cohort, "_build", lambda *a: built.append(1) or build(*a))
    params, plan = cohort_parameters(1, seed=5)[0]
    case = virtual_patient(params, plan, spacing=4.0, cache=True, cache_dir=tmp_path)
    (entry,) = (tmp_path / "cases").iterdir()
    damaged = case.ct.copy()
    damaged.point_data[arrays.CT][0] += 1.0
    damaged.save(entry / "ct.vti")  # no longer the CT its record names
    again = virtual_patient(params, plan, spacing=4.0, cache=True, cache_dir=tmp_path)
    assert len(built) == 2 and _image_digest(again.ct) == _image_digest(case.ct)


# -------------------------------------------------------------------- judged skins
def _case():
    img = pv.ImageData(dimensions=(3, 3, 3))
    img.point_data[arrays.CT] = np.arange(27, dtype=np.float32)
    return cohort._phantom.Case(name="p", patient=101, spacing=3.0, ct=img, truth=img.copy(),
                                landmarks={"pronasale": np.array([0.0, 50.0, 0.0])},
                                plan="plan", parameters="params")


def _judged(pred):
    out = pred.copy()
    out.point_data[arrays.DISTANCE] = np.linspace(-1.0, 2.0, out.n_points) / 3.0
    out.point_data[arrays.REGION] = (np.arange(out.n_points) % 7).astype(np.uint8)
    out.point_data[arrays.SKIN_POINT_ID] = np.arange(out.n_points, dtype=np.int64)
    out.field_data[ICP_MATRIX] = np.eye(4) * 1.1
    out.field_data[arrays.STUDY_EXCLUDED] = np.array([3])
    return out


def test_second_study_reads_judged_skins_and_changes_judge_again(tmp_path, monkeypatch,
                                                                  fixed_code):
    calls = {"scan": 0, "judge": 0}

    def scan(*args):
        calls["scan"] += 1
        skin = pv.Sphere(radius=20.0, theta_resolution=10, phi_resolution=10)
        return None, None, skin, None

    def prediction(case, method, grid, pre_skin, n_tets, sigma):
        pred = pre_skin.copy()
        pred.point_data[arrays.MAPPING_SUPPORT] = np.ones(pred.n_points)
        return -10.0, pred

    def judge(case, registered, pred, y0, masks):
        calls["judge"] += 1
        return _judged(pred)

    monkeypatch.setattr(validation, "_scan", scan)
    monkeypatch.setattr(validation, "_prediction", prediction)
    monkeypatch.setattr(validation, "_judge", judge)
    cases = {101: _case()}

    def run(**options):
        predict = validation.study_predictor(**{
            "spacing": 3.0, "n_tets": 5000, "truth_tets": 2000, "truth": "independent",
            "cases": cases, "cache_dir": tmp_path, "prediction_cache": True, **options})
        return {m: predict(101, m) for m in ("proposed", "truth")}

    cold = run()
    assert calls == {"scan": 1, "judge": 2}
    warm = run()
    assert calls == {"scan": 1, "judge": 2}  # no truth, CT, registration or judging
    for method, a in cold.items():
        b = warm[method]
        np.testing.assert_array_equal(a.points, b.points)
        assert sorted(a.point_data.keys()) == sorted(b.point_data.keys())
        for name in a.point_data.keys():
            np.testing.assert_array_equal(a.point_data[name], b.point_data[name])
            assert a.point_data[name].dtype == b.point_data[name].dtype
        for name in a.field_data.keys():
            np.testing.assert_array_equal(a.field_data[name], b.field_data[name])
    # every option of the truth and the judging, and the code, judge again
    for options in (dict(truth_tets=3000), dict(noise_hu=10.0), dict(ct_spacing=2.0),
                    dict(truth=None), dict(n_tets=6000), dict(sigma=3.0),
                    dict(truth_mesher="conforming"), dict(truth_materials="field"),
                    dict(truth_mesher="graded", truth_face_mm=4.0),
                    dict(truth_mesher="graded", truth_face_mm=3.2)):
        n = calls["judge"]
        run(**options)
        assert calls["judge"] == n + 2, options
    fixed_code["hash"] = "other code"
    n = calls["judge"]
    run()
    assert calls["judge"] == n + 2
    # a truth callable cannot be keyed: always judged
    n = calls["judge"]
    run(truth=lambda case: None)
    run(truth=lambda case: None)
    assert calls["judge"] == n + 4


def test_judged_code_hash_follows_the_truth_and_the_judging(tmp_path):
    pkg = tmp_path / "pkg"
    for folder in ("truth", "study", "figures"):
        (pkg / folder).mkdir(parents=True)
    files = {"pipeline.py": "def f(x):\n    return x\n",
             "truth/solver.py": "A = 1\n", "study/statistics.py": "B = 1\n",
             "study/cohort.py": "C = 1\n", "study/claims.py": "D = 1\n",
             "figures/plot.py": "E = 1\n"}
    for name, text in files.items():
        (pkg / name).write_text(text)

    def hashes():
        judged_code_hash.cache_clear()
        prediction_code_hash.cache_clear()
        return judged_code_hash(pkg), prediction_code_hash(pkg)

    try:
        before = hashes()
        (pkg / "truth/solver.py").write_text('"""doc"""\nA = 1  # comment\n')
        assert hashes() == before  # documentation only
        for name in ("study/claims.py", "figures/plot.py"):  # never in a judged skin
            (pkg / name).write_text("D = 2\n")
            assert hashes() == before, name
        for name in ("truth/solver.py", "study/statistics.py", "study/cohort.py"):
            (pkg / name).write_text("A = 3\n")
            now = hashes()
            assert now[0] != before[0] and now[1] == before[1], name
            before = now
        (pkg / "pipeline.py").write_text("def f(x):\n    return x + 1\n")
        now = hashes()
        assert now[0] != before[0] and now[1] != before[1]
    finally:
        judged_code_hash.cache_clear()
        prediction_code_hash.cache_clear()


# ------------------------------------------------------------- the cohort page's text
def _benchmark():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "study.py"
    spec = importlib.util.spec_from_file_location("_study_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cohort_page_quotes_the_refinement_page_it_reads(tmp_path):
    """The truth's convergence on the cohort page comes from the refinement table, not
    from numbers typed into the script."""
    bench = _benchmark()
    page = tmp_path / "truth_refinement.md"
    head = ("| patient | tetrahedra | edge mm | dofs | Newton | factorisations | solve s "
            "| released | skin compared | change p50 mm | p90 mm | max mm |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|\n")
    rows = ("| 1 | 3000 | 9.0 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan | nan |\n"
            "| 1 | 6100 | 7.0 | 1 | 1 | 1 | 1 | 0 | 90 % | 0.011 | 0.321 | 1.0 |\n"
            "| 2 | 2900 | 9.0 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan | nan |\n"
            "| 2 | 6050 | 7.0 | 1 | 1 | 1 | 1 | 0 | 90 % | 0.022 | 0.654 | 1.0 |\n")
    page.write_text("Mesher ``lattice``: ...\n\n" + head + rows + "\nCost scaling:\n")
    text = bench.truth_note("independent", 2000, page=page)
    assert "p90 0.32-0.65 mm" in text and "median 0.011-0.022 mm" in text
    assert "2900-3000 and 6050-6100 tetrahedra" in text and "not converged" in text
    assert "mesher ``conforming``" not in text and "finer than this run's 2000" in text
    page.write_text("Mesher ``conforming`` ...\n\n" + head + rows.replace("0.654", "0.05")
                    .replace("0.321", "0.08"))
    text = bench.truth_note("independent", 4000, page=page)
    assert "has converged" in text and "mesher ``conforming``, not this run's" in text
    page.write_text("Mesher ``conforming`` ... Mesher ``graded`` ...\n\n" + head + rows)
    assert "mesher ``graded``, not this run's" in bench.truth_note("independent", 4000,
                                                                   page=page)
    page.write_text("Mesher ``conforming`` ...\n\n" + head + rows + "\nA finer truth, patient 2 "
                    "(``--fine 12000``): 11900 tetrahedra (edge 5.0 mm), 9 dofs; skin change "
                    "from the 6000 truth above over 96 % of the skin: p50 0.004 mm, p90 "
                    "0.097 mm, max 1.0 mm.\n")
    text = bench.truth_note("independent", 2000, page=page)  # the finer truth takes over
    assert "p90 0.10-0.32 mm" in text and "3000-6050 and 6100-11900 tetrahedra" in text
    graded = ("| patient | tetrahedra | face mm | edge mm | dofs | Newton | factorisations "
              "| solve s | released | skin compared | change p50 mm | p90 mm | max mm |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
              "| 1 | 44000 | 4.0 | 5.9 | 1 | 1 | 1 | 1 | 3 | nan % | nan | nan | nan |\n"
              "| 1 | 66000 | 3.2 | 5.1 | 1 | 1 | 1 | 1 | 0 | 99 % | 0.009 | 0.174 | 1.8 |\n"
              "| 1 | 99000 | 2.56 | 4.4 | 1 | 1 | 1 | 1 | 0 | 99 % | 0.004 | 0.081 | 0.9 |\n")
    page.write_text("Mesher ``conforming`` ... Mesher ``graded`` ...\n\n" + graded)
    text = bench.truth_note("independent", 2000, page=page)  # the face mm column is read
    assert "66000 and 99000 tetrahedra" in text and "p90 0.08 mm" in text, text
    missing = bench.truth_note("independent", 2000, page=tmp_path / "none.md")
    assert "not measured" in missing and "p90" not in missing


# -------------------------------------------------------------- the independent truth
def _recorded_truth(monkeypatch):
    """``independent_truth_grid`` replaced by one that records the options it gets."""
    received = []

    def truth(case, **options):
        received.append(options)
        return None

    monkeypatch.setattr(validation, "independent_truth_grid", truth)
    return received


def test_independent_truth_gets_the_options_of_the_refinement_study(tmp_path, monkeypatch):
    """The graded truth is solved with the options the refinement study solves it with
    (mesher, materials, face size, reuse_factor), the default one as before."""
    received = _recorded_truth(monkeypatch)

    def scan(case, patient, truth, *args):  # the truth is solved, nothing judged
        truth(case)
        raise StopIteration

    monkeypatch.setattr(validation, "_scan", scan)
    cases = {101: _case()}
    for options, expected in (
            ({}, {"mesher": "lattice", "materials": "cells"}),
            ({"truth_mesher": "graded", "truth_face_mm": 4.0, "truth_materials": "field"},
             {"mesher": "graded", "materials": "field", "face_mm": 4.0,
              "reuse_factor": True}),
            ({"truth_mesher": "graded", "truth_face_mm": 4.0, "truth_face_margin_mm": 30},
             {"mesher": "graded", "materials": "cells", "face_mm": 4.0,
              "face_margin_mm": 30.0, "reuse_factor": True}),
            ({"truth_mesher": "graded", "truth_face_mm": {"mandible": 4, "maxilla": 3.2}},
             {"mesher": "graded", "materials": "cells", "reuse_factor": True,
              "face_mm": {"mandible": 4.0, "maxilla": 3.2}}),
            ({"truth_mesher": "conforming"},
             {"mesher": "conforming", "materials": "cells", "reuse_factor": True})):
        predict = validation.study_predictor(spacing=3.0, n_tets=5000, truth_tets=30000,
                                             truth="independent", cases=cases,
                                             cache_dir=tmp_path, **options)
        with pytest.raises(StopIteration):
            predict(101, "proposed")
        assert received[-1] == {"n_tets": 30000, "cache": True, "cache_dir": tmp_path,
                                **expected}, options
    assert len(received) == 5


def test_judged_skins_of_one_truth_are_not_read_for_another(tmp_path, monkeypatch,
                                                             fixed_code):
    """The cache key of a judged skin holds the truth's mesher, face size and materials."""
    keys = []
    monkeypatch.setattr(validation, "cached_judged",
                        lambda judge, case, method, options, **k: keys.append(options))
    cases = {101: _case()}
    for options in ({}, {"truth_mesher": "conforming"},
                    {"truth_mesher": "graded", "truth_face_mm": 4.0},
                    {"truth_mesher": "graded", "truth_face_mm": 3.2},
                    {"truth_mesher": "graded", "truth_face_mm": 3.2, "truth_materials": "field"},
                    {"truth_mesher": "graded", "truth_face_mm": 3.2, "truth_materials": "field",
                     "truth_face_margin_mm": 30.0},
                    {"truth_materials": "field"},
                    {"truth_mesher": "graded", "truth_face_mm": {"maxilla": 3.2, "mandible": 4}},
                    {"truth_mesher": "graded", "truth_face_mm": {"maxilla": 3.2,
                                                                  "mandible": 3.2}}):
        validation.study_predictor(spacing=3.0, truth="independent", cases=cases,
                                   cache_dir=tmp_path, prediction_cache=True,
                                   **options)(101, "proposed")
    assert len({repr(sorted(k.items())) for k in keys}) == len(keys) == 9
    # no margin: the key of the judged skins cached before the option existed
    assert not any("truth_face_margin_mm" in k for k in keys[:5])


@pytest.mark.parametrize("options, message", [
    ({"truth_mesher": "gmsh"}, "truth_mesher must be 'lattice', 'conforming' or 'graded', "
                               "got 'gmsh'"),
    ({"truth_materials": "voxels"}, "truth_materials must be 'cells' or 'field', got "
                                    "'voxels'"),
    ({"truth_mesher": "graded"}, "truth_face_mm must be a size > 0 mm, or a mapping of the "
                                 "moved segments to sizes, with truth_mesher 'graded', got "
                                 "None"),
    ({"truth_mesher": "graded", "truth_face_mm": {"maxilla": 3.2, "chin": 4.0}},
     "got {'maxilla': 3.2, 'chin': 4.0}"),
    ({"truth_mesher": "graded", "truth_face_mm": {"maxilla": 0.0}}, "got {'maxilla': 0.0}"),
    ({"truth_mesher": "graded", "truth_face_mm": -1.0}, "got -1.0"),
    ({"truth_face_mm": 4.0}, "truth_face_mm applies to truth_mesher 'graded' only"),
    ({"truth": None, "truth_mesher": "graded", "truth_face_mm": 4.0},
     "apply to truth 'independent' only"),
    ({"truth_face_margin_mm": 30.0}, "truth_face_margin_mm applies to truth_mesher 'graded' "
                                     "only (0 with truth_mesher 'lattice'), got 30.0"),
    ({"truth_mesher": "graded", "truth_face_mm": 4.0, "truth_face_margin_mm": -5.0},
     "truth_face_margin_mm must be a distance >= 0 mm, got -5.0"),
    ({"truth_mesher": "graded", "truth_face_mm": 4.0, "truth_face_margin_mm": float("nan")},
     "truth_face_margin_mm must be a distance >= 0 mm, got nan"),
])
def test_independent_truth_options_are_checked(options, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        validation.study_predictor(**{"truth": "independent", **options})


def test_cohort_passes_the_truth_options_on(monkeypatch, tmp_path):
    """``study.py --cohort --truth-mesher graded ...`` reaches ``study_predictor``."""
    bench = _benchmark()
    got = {}

    def predictor(**kwargs):
        got.update(kwargs)
        raise StopIteration

    monkeypatch.setattr(bench, "study_predictor", predictor)
    monkeypatch.setattr(bench, "virtual_patient",
                        lambda *a, **k: type("Case", (), {"patient": 101})())
    with pytest.raises(StopIteration):
        bench.main(["--cohort", "1", "--truth-mesher", "graded", "--truth-face-mm", "4.0",
                    "--truth-materials", "field", "--truth-face-margin-mm", "30",
                    "--cache-dir", str(tmp_path)])
    assert (got["truth"], got["truth_mesher"], got["truth_face_mm"], got["truth_materials"],
            got["truth_face_margin_mm"]) == ("independent", "graded", 4.0, "field", 30.0)
    got.clear()
    with pytest.raises(StopIteration):
        bench.main(["--cohort", "1", "--truth-mesher", "graded", "--truth-face-mm",
                    "maxilla=3.2, mandible=4", "--cache-dir", str(tmp_path)])
    assert got["truth_face_mm"] == {"mandible": 4.0, "maxilla": 3.2}
    for bad in ("chin=3", "maxilla=-1", "maxilla:3", "maxilla=3=4", "thin"):
        with pytest.raises(SystemExit):
            bench.main(["--cohort", "1", "--truth-mesher", "graded", "--truth-face-mm", bad])
    got.clear()
    with pytest.raises(StopIteration):
        bench.main(["--cohort", "1", "--cache-dir", str(tmp_path)])
    assert (got["truth_mesher"], got["truth_face_mm"], got["truth_materials"],
            got["truth_face_margin_mm"]) == ("lattice", None, "cells", 0.0)


def test_cohort_page_says_whether_the_refinement_is_of_its_graded_truth(tmp_path):
    """A graded truth's refinement is quoted as this truth's only for the same mesher,
    materials, count outside the face and a face size of the two finest truths; patients
    that converged and those that did not are told apart."""
    bench = _benchmark()
    page = tmp_path / "truth_refinement.md"
    page.write_text(
        "Command: `python benchmarks/study.py --refinement --mesher graded --materials field "
        "--patients 1 3 --spacing 3 --counts 30000 --face-mm 4.0 3.2 -v`\n\n"
        "Model ...; materials ``field`` (...). Mesher ``conforming`` ... Mesher ``graded`` "
        "...\n\n| patient | tetrahedra | face mm | edge mm | dofs | Newton | factorisations "
        "| solve s | released | skin compared | change p50 mm | p90 mm | max mm "
        "| p90 mm, any closest triangle |\n" + "|---" * 14 + "|\n"
        "| 1 | 44294 | 4.0 | 5.9 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan | nan | nan |\n"
        "| 1 | 66484 | 3.2 | 5.1 | 1 | 1 | 1 | 1 | 0 | 99 % | 0.009 | 0.174 | 1.8 | 0.2 |\n"
        "| 3 | 64494 | 4.0 | 5.8 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan | nan | nan |\n"
        "| 3 | 108055 | 3.2 | 4.8 | 1 | 1 | 1 | 1 | 0 | 99 % | 0.003 | 0.054 | 0.6 | 0.1 |\n")
    text = bench.truth_note("independent", 30000, page, "graded", 4.0, "field")
    assert "mesher ``graded``, face 4 mm" in text and "materials ``field``" in text
    assert text.count("not this run's") == 1  # only "not this run's patients"
    assert "Its refinement" in text
    assert "face 4 mm is the coarser of the two finest for patient(s) 1, 3" in text
    assert "converged there (p90 <= 0.1 mm) for patient(s) 3, not for patient(s) 1" in text
    assert "p90 0.05-0.17 mm" in text
    assert "the finer of the two finest" in bench.truth_note("independent", 30000, page,
                                                             "graded", 3.2, "field")
    between = bench.truth_note("independent", 30000, page, "graded", 3.5, "field")
    assert "3.5 mm is between the two finest for patient(s) 1, 3" in between
    mixed = page.read_text().replace("| 1 | 44294 | 4.0 |", "| 1 | 44294 | 3.2 |").replace(
        "| 1 | 66484 | 3.2 |", "| 1 | 66484 | 2.56 |")
    mixed_page = page.with_name("mixed.md")
    mixed_page.write_text(mixed)
    text = bench.truth_note("independent", 30000, mixed_page, "graded", 4.0, "field")
    assert ("coarser than the two finest for patient(s) 1; the coarser of the two finest "
            "for patient(s) 3") in text, text
    for args, phrase in (((20000, page, "graded", 4.0, "field"), "not this run's 20000"),
                         ((30000, page, "graded", 4.0, "cells"), "materials ``field``, not"),
                         ((30000, page, "conforming", None, "field"), "mesher ``graded``, "
                                                                      "not this run's")):
        text = bench.truth_note("independent", *args)
        assert phrase in text and "Its refinement" not in text, args
        assert "A refinement of the independent truth" in text
    # a page refined with a face margin is this truth's only with the same margin
    text = bench.truth_note("independent", 30000, page, "graded", 4.0, "field", 30.0)
    assert "face margin of 0 mm, not this run's 30 mm" in text
    assert "face 4 mm within 30 mm of the moved bones" in text
    wide = page.with_name("wide.md")
    wide.write_text(page.read_text().replace("--face-mm 4.0 3.2", "--face-mm 4.0 3.2 "
                                             "--face-margin-mm 30"))
    rows = sys.modules["truth_refinement"].refinement_rows
    assert (rows(wide)["margin"], rows(page)["margin"]) == (30.0, 0.0)
    assert "Its refinement" in bench.truth_note("independent", 30000, wide, "graded", 4.0,
                                                "field", 30.0)
    # every patient converged, but in another truth than this run's: said so, with the caveat
    done = wide.with_name("done.md")
    done.write_text(wide.read_text().replace("| 0.174 | 1.8 |", "| 0.074 | 1.8 |"))
    own = bench.truth_note("independent", 30000, done, "graded", 4.0, "field", 30.0)
    assert own.endswith("it has converged there (p90 <= 0.1 mm); a truth of this run's face "
                        "4 mm changes the skin from the next finer one by p90 0.05-0.07 mm "
                        "for patient(s) 1, 3 (within 0.1 mm)."), own
    finest = bench.truth_note("independent", 30000, done, "graded", 3.2, "field", 30.0)
    assert finest.endswith("as fine as the finest truth or finer for patient(s) 1, 3."), finest
    # every patient's finest truths converged, but this run's face is a coarser level of
    # one patient whose step from it is not: the errors are not called converged
    deep = wide.with_name("deep.md")
    deep.write_text(done.read_text().replace("--face-mm 4.0 3.2", "--face-mm 4.8 4.0 3.2")
                    .replace("| 1 | 44294 | 4.0 | 5.9 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan "
                             "| nan | nan |\n",
                             "| 1 | 30000 | 4.8 | 6.9 | 1 | 1 | 1 | 1 | 0 | nan % | nan | nan "
                             "| nan | nan |\n| 1 | 44294 | 4.0 | 5.9 | 1 | 1 | 1 | 1 | 0 | 99 % "
                             "| 0.02 | 0.25 | 2.0 | 0.3 |\n"))
    coarse = bench.truth_note("independent", 30000, deep, "graded", 4.8, "field", 30.0)
    assert ("converged there (p90 <= 0.1 mm) at its finest truths; a truth of this run's face "
            "4.8 mm changes the skin from the next finer one by p90 0.25 mm for patient(s) 1 "
            "(more: there this run's truth is coarser than the converged one); the change "
            "from a truth of face 4.8 mm is not measured for patient(s) 3, so the errors "
            "below") in coarse, coarse
    other = bench.truth_note("independent", 30000, done, "graded", 4.0, "field")
    assert ("that truth has converged there (p90 <= 0.1 mm); this run's truth is not that "
            "one, so how far it has converged is not measured: the errors below") in other
    assert "not this run's 0 mm" in bench.truth_note("independent", 30000, wide, "graded",
                                                     4.0, "field")


def test_cohort_page_judges_a_face_size_per_moved_segment_per_patient(tmp_path):
    """With a face size per moved segment, each refinement patient is read at the size of
    the segment its plan moves (patient 1: the maxilla, patient 3: the mandible)."""
    bench = _benchmark()
    row = "| {} | {} | {} | 5 | 1 | 1 | 1 | 1 | 0 | {} | {} | {} | 1.0 | {} |\n"
    page = tmp_path / "truth_refinement.md"
    page.write_text(
        "Command: `python benchmarks/study.py --refinement --mesher graded --materials field "
        "--patients 1 3 --spacing 3 --counts 30000 --face-mm 4.8 4.0 3.2 --face-margin-mm 30 "
        "-v`\n\nModel ...; materials ``field`` (...). Mesher ``graded`` ...\n\n"
        "| patient | tetrahedra | face mm | edge mm | dofs | Newton | factorisations "
        "| solve s | released | skin compared | change p50 mm | p90 mm | max mm "
        "| p90 mm, any closest triangle |\n" + "|---" * 14 + "|\n"
        + row.format(1, 30000, 4.8, "nan %", "nan", "nan", "nan")
        + row.format(1, 44000, 4.0, "99 %", 0.02, 0.25, 0.25)
        + row.format(1, 66000, 3.2, "99 %", 0.01, 0.074, 0.074)
        + row.format(3, 30000, 4.8, "nan %", "nan", "nan", "nan")
        + row.format(3, 44000, 4.0, "99 %", 0.01, 0.054, 0.054))
    per_segment = {"maxilla": 4.0, "mandible": 4.8}
    text = bench.truth_note("independent", 30000, page, "graded", per_segment, "field", 30.0)
    assert "face 4 mm where the maxilla moves, 4.8 mm where the mandible moves, within 30 mm" \
        in text, text
    assert "the coarser of the two finest for patient(s) 1, 3" in text, text
    assert text.endswith("it has converged there (p90 <= 0.1 mm); a truth of this run's face "
                         "4 mm where the maxilla moves, 4.8 mm where the mandible moves "
                         "changes the skin from the next finer one by p90 0.05-0.07 mm for "
                         "patient(s) 1, 3 (within 0.1 mm)."), text
    uniform = bench.truth_note("independent", 30000, page, "graded", 4.8, "field", 30.0)
    assert "by p90 0.25 mm for patient(s) 1 (more:" in uniform, uniform


def test_refinement_takes_cohort_patients_with_their_own_plans():
    """Patients from 101 on are the cohort's (seed 0): their plans decide their face size,
    and the cohort page names them as the cohort's."""
    _benchmark()
    refine = sys.modules["truth_refinement"]
    draw = cohort.cohort_parameters(4, seed=0)
    assert refine.patient_plan(102) == draw[1][1] and refine.patient_plan(103) == draw[2][1]
    assert refine.patient_plan(1) is refine.TABLE_II[1]
    sizes = {"maxilla": 3.2, "mandible": 4.0}
    assert [refine._patient_face(sizes, p) for p in ("1", "3", "102", "103")] == [
        3.2, 4.0, 3.2, 4.0]
    assert refine.patients_text(["1", "102"]) == (
        "patients 1 of ``pvcmf.datasets.phantom`` and patients 102 of the cohort (seed 0)")


def test_face_size_per_moved_segment():
    from pvcmf.plan import Osteotomy, Plan
    from pvcmf.truth.graded import face_size

    both = Plan([Osteotomy("maxilla", translation=(0, 0, 3)),
                 Osteotomy("mandible", translation=(0, 0, -2))])
    sizes = {"maxilla": 3.2, "mandible": 4.0}
    assert face_size(sizes, both) == 3.2
    assert face_size(sizes, Plan([Osteotomy("mandible", translation=(0, 0, 2))])) == 4.0
    assert face_size(4, both) == 4.0
    with pytest.raises(ValueError, match="a size for every segment the plan moves"):
        face_size({"maxilla": 3.2}, both)
    with pytest.raises(ValueError, match="a size for every segment the plan moves"):
        face_size(sizes, None)


def _blend_rows(p90_ref, p90_wide, spread):
    refinement = [{"patient": 1, "blend": b, "faces": (4.0, 3.2), "tets": (44000, 66000),
                   "folded": (28, 26), "p50": 0.01, "p90": p, "max": 1.0}
                  for b, p in ((4.0, p90_ref), (8.0, p90_wide))]
    cross = [{"patient": 1, "face": f, "blends": (4.0, 8.0), "p50": 0.01, "p90": s,
              "max": 1.0} for f, s in ((4.0, spread - 0.01), (3.2, spread))]
    return refinement, cross


def test_blend_page_says_what_its_numbers_say():
    """The truth-blend page's verdict is made from its rows: whether a blend converges,
    and whether the blend moves the skin more than the refinement does."""
    bench = _benchmark()
    ref, cross = _blend_rows(0.174, 0.166, 0.267)
    text = bench.truth_blend.verdict(ref, cross)
    assert "No blend width tried brings the truth under 0.1 mm" in text
    assert "p90 0.267 mm, more than refining the face at blend 4 mm (0.174 mm)" in text
    ref, cross = _blend_rows(0.174, 0.06, 0.05)
    text = bench.truth_blend.verdict(ref, cross)
    assert "converges with blend width(s) 8 mm only" in text and "No blend" not in text
    assert "p90 0.050 mm, less than refining" in text
    page = bench.truth_blend.blend_page(ref, cross, "python benchmarks/study.py --blend-mm 4 8",
                                        "x86_64")
    assert "| 1 | 8 | 4 -> 3.2 | 44000 -> 66000 | 28 -> 26 | 0.010 | 0.060 | 1.000 |" in page
    assert "| 1 | 3.2 | 4 -> 8 | 0.010 | 0.050 | 1.000 |" in page


@pytest.mark.parametrize("blend", [0.0, -1.0, float("nan"), float("inf"), "wide", True, None])
def test_truth_rejects_a_bad_blend_width(blend):
    from pvcmf.truth.independent import independent_truth_grid

    with pytest.raises(ValueError, match="blend_mm must be a positive finite width"):
        independent_truth_grid(object(), blend_mm=blend)


def test_truth_ties_the_bone_with_the_blend_width_asked(monkeypatch):
    """``blend_mm`` reaches the truth's boundary model (not its default)."""
    from pvcmf.truth import independent

    seen = {}

    class Stop(Exception):
        pass

    def boundary(case, grid, blend=None, **_):
        seen["blend"] = blend
        raise Stop

    monkeypatch.setattr(independent, "soft_tissue_mesh", lambda case, **_: "grid")
    monkeypatch.setattr(independent, "_boundary_conditions", boundary)
    with pytest.raises(Stop):
        independent.independent_truth_grid(object(), blend_mm=7.5)
    assert seen["blend"] == 7.5


def test_blend_study_needs_two_widths_and_two_face_sizes():
    bench = _benchmark()
    with pytest.raises(ValueError, match="need two blend widths and two face sizes"):
        bench.truth_blend.blend_rows(1, 3.0, 30000, [4.0], [4.0, 8.0])
    with pytest.raises(ValueError, match="need two blend widths and two face sizes"):
        bench.truth_blend.blend_rows(1, 3.0, 30000, [4.0, 3.2], [4.0])


def test_blend_study_holds_one_truth_mesh_at_a_time(monkeypatch):
    """Nine fine truths do not fit in memory together: each is measured, then let go."""
    import gc
    import weakref

    bench = _benchmark()
    module = sys.modules["truth_blend"]
    alive, most = set(), [0]

    def truth(case, *, face_mm, blend_mm, **_):
        grid = pv.ImageData(dimensions=(4, 4, 4), spacing=(3.0,) * 3)
        grid = grid.cast_to_unstructured_grid().triangulate()
        grid[arrays.DISPLACEMENT] = 0.01 * blend_mm * grid.points
        grid.field_data[arrays.REFERENCE_FOLDED] = np.arange(int(blend_mm))
        gc.collect()
        alive.add(id(grid))
        weakref.finalize(grid, alive.discard, id(grid))
        most[0] = max(most[0], len(alive))
        return grid

    top = np.column_stack([np.linspace(1.0, 8.0, 30), np.full(30, 5.0), np.full(30, 9.0)])
    monkeypatch.setattr(module.pvcmf.datasets, "phantom", lambda *a, **k: object())
    monkeypatch.setattr(module, "exact_skin_samples", lambda case: top)
    monkeypatch.setattr(module, "exact_skin_normals", lambda case, p: np.tile([0, 0, 1.0],
                                                                              (len(p), 1)))
    monkeypatch.setattr(module, "independent_truth_grid", truth)
    refinement, cross = module.blend_rows(1, 3.0, 1000, [4.0, 3.2], [4.0, 8.0, 2.0])
    assert most[0] == 1
    assert [r["folded"] for r in refinement] == [(4, 4), (8, 8), (2, 2)]
    assert [r["tets"] for r in refinement] == [(162, 162)] * 3
    # same field at both sizes: no refinement change; the blends differ by 0.01 mm/mm
    assert max(r["p90"] for r in refinement) < 1e-12
    assert [c["blends"] for c in cross] == [(4.0, 8.0), (4.0, 2.0)] * 2
    np.testing.assert_allclose([c["p50"] for c in cross],
                               0.04 * np.median(np.linalg.norm(top, axis=1)) *
                               np.array([1, 0.5, 1, 0.5]), rtol=1e-9)


def test_refinement_passes_the_face_margin_on(monkeypatch):
    """``study.py --refinement --mesher graded --face-margin-mm M`` reaches the truth."""
    bench = _benchmark()
    module = sys.modules["truth_refinement"]
    got = []

    def truth(case, **kwargs):
        got.append(kwargs)
        raise StopIteration

    monkeypatch.setattr(module, "independent_truth_grid", truth)
    monkeypatch.setattr(module, "exact_skin_samples", lambda case: np.zeros((1, 3)))
    monkeypatch.setattr(module, "exact_skin_normals", lambda case, p: np.zeros((1, 3)))
    monkeypatch.setattr(module.pvcmf.datasets, "phantom", lambda p, spacing: object())
    for extra, margin in ((["--face-margin-mm", "30"], 30.0), ([], 0.0)):
        with pytest.raises(StopIteration):
            bench.main(["--refinement", "--mesher", "graded", "--materials", "field",
                        "--patients", "1", "--spacing", "3", "--counts", "30000",
                        "--face-mm", "4.0", "3.2", *extra])
        assert (got[-1]["mesher"], got[-1]["face_mm"], got[-1]["face_margin_mm"],
                got[-1]["n_tets"]) == ("graded", 4.0, margin, 30000)
