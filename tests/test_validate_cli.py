"""``pvcmf validate``: ICP on the unchanged face, signed distances, figures, CSV, report.

1. A post-operative skin built from a known displacement (lower face moved along its
   normals by a known amount) in a random pose: the command's statistics equal numpy's
   statistics of that displacement.
2. A virtual patient of the study (:mod:`pvcmf.study.validation`): the command on the
   study's prediction against the study's post-operative CT (and its skin) gives the
   study's distances and numbers.
"""

import json
import warnings

import numpy as np
import pandas as pd
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.cli import main
from pvcmf.io import write_landmarks, write_surface
from pvcmf.study.statistics import label_face_regions
from pvcmf.truth.postop import random_pose


def _head():
    return pv.ParametricEllipsoid(70, 95, 110, u_res=120, v_res=90).clean().triangulate()


@pytest.fixture(scope="module")
def known(tmp_path_factory):
    """Predicted skin, and the 'actual' skin: lower face 1.5 mm further out, then posed."""
    folder = tmp_path_factory.mktemp("known")
    pred = _head()
    pred.save(folder / "predicted_skin.vtp")
    normals = pred.points / np.array([70.0, 95.0, 110.0]) ** 2  # the ellipsoid's gradient
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    z = pred.points[:, 2]
    delta = 1.5 * np.clip((-20.0 - z) / 20.0, 0.0, 1.0)  # 0 above z=-20, 1.5 mm below -40
    actual = pred.copy()
    actual.points = pred.points + delta[:, None] * normals
    matrix = random_pose(np.random.default_rng(3), max_rotation=2.0, max_translation=3.0)
    write_surface(actual.transform(matrix, inplace=False), folder / "post.stl")
    return folder, pred, delta


def test_validate_known_displacement(known, capsys):
    folder, pred, delta = known
    out = folder / "out"
    assert main(["validate", "--pred", str(folder / "predicted_skin.vtp"), "--post",
                 str(folder / "post.stl"), "--out", str(out), "--no-progress"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["registration"]["converged"] and summary["registration"]["rms_mm"] < 0.05
    table = pd.read_csv(out / "regions.csv").set_index("region")
    # independent: the prediction lies delta inside the actual skin
    reg = label_face_regions(pred)[arrays.REGION]
    for name in ("face", "chin", "upper_lip", "nose"):
        d = -delta if name == "face" else -delta[reg == arrays.FACE_REGIONS[name]]
        a = np.abs(d)
        assert table.loc[name, "n"] == d.size
        np.testing.assert_allclose(table.loc[name, ["p50", "p90", "p95"]].to_numpy(float),
                                   np.percentile(a, [50, 90, 95]), atol=0.06, err_msg=name)
        assert abs(table.loc[name, "median"] - np.median(d)) < 0.06
    skin = pv.read(out / "validated_skin.vtp")
    np.testing.assert_allclose(skin[arrays.DISTANCE], -delta, atol=0.12)
    for name in ("fig6_error_map.png", "fig7_boxplot.png", "fig8_cumulative.png",
                 "postop_skin.vtp", "report.html"):
        assert (out / name).stat().st_size > 1000, name
    rows = {r["region"]: r for r in summary["regions"]}
    assert rows["chin"]["p90"] == pytest.approx(table.loc["chin", "p90"])
    assert "ICP on the unchanged region" in capsys.readouterr().out


def test_validate_judges_only_the_modelled_skin(known):
    """Skin the model does not reach (``skin_modelled`` 0) is left out of the statistics."""
    from pvcmf.study.validate import validate

    folder, pred, delta = known
    pred = pred.copy()
    modelled = pred.points[:, 2] < 0.0  # the lower half, where the face moved
    pred[arrays.SKIN_MODELLED] = modelled.astype(np.uint8)
    v = validate(pred, pv.read(folder / "post.stl"))
    face = v.table.set_index("region").loc["face"]
    a = delta[modelled]
    assert face["n"] == a.size
    np.testing.assert_allclose(face["p90"], np.percentile(a, 90), atol=0.05)
    assert np.isfinite(v.skin[arrays.DISTANCE]).all()  # the skin itself keeps every distance


def test_validate_leaves_out_the_scan_s_edge(known):
    """Skin on a cut of the pre-operative scan (``skin_cut`` 1: here the brow flattened
    by the scan's edge) is neither registered on nor judged; unmarked, it biases both."""
    from pvcmf.study.validate import validate

    folder, pred, delta = known
    flat = pred.copy()
    cut = (flat.points[:, 1] > 70.0) & (flat.points[:, 2] > 20.0)
    pts = np.array(flat.points)
    pts[cut, 1] = 70.0  # the scan's edge: a plane in front of the face
    flat.points = pts
    marked = flat.copy()
    marked[arrays.SKIN_CUT] = cut.astype(np.uint8)
    post = pv.read(folder / "post.stl")
    judged, biased = validate(marked, post), validate(flat, post)
    face = judged.table.set_index("region").loc["face"]
    assert face["n"] == int((~cut).sum())
    a = delta[~cut]
    np.testing.assert_allclose(face[["p90", "rms"]].to_numpy(float),
                               [np.percentile(a, 90), np.sqrt(np.mean(a ** 2))], atol=0.05)
    assert judged.registration["rms_mm"] < 0.05
    unmarked = biased.table.set_index("region").loc["face"]
    assert unmarked["n"] == pred.n_points and unmarked["rms"] > face["rms"] + 0.5


def test_registration_never_pairs_on_the_target_s_cut():
    """A region holding only the target's cut skin leaves no pairs; unmarked, it does."""
    from pvcmf.filters import register

    head = _head()
    cut = head.points[:, 1] > 60.0
    marked = head.copy()
    marked[arrays.SKIN_CUT] = cut.astype(np.uint8)
    with pytest.raises(ValueError, match="region leaves 0 target points"):
        register(head, marked, region=cut)
    moved = register(head.translate((0.5, 0.0, 0.0)), head, region=cut, tol=1e-4)
    assert np.abs(np.asarray(moved.points) - head.points).max() < 0.05


def test_validate_bad_input(known, tmp_path, capsys):
    folder, _, _ = known
    args = ["validate", "--pred", str(folder / "predicted_skin.vtp"), "--out", str(tmp_path)]
    assert main([*args, "--post", str(tmp_path / "missing.stl")]) == 2
    assert "--post=" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # refused by the argument parser
        main([*args, "--post", str(folder / "post.stl"), "--region", "top"])
    assert info.value.code == 2
    assert "--region: expected 'upper' or six numbers" in capsys.readouterr().err


@pytest.fixture(scope="module")
def study_case(tmp_path_factory):
    """Patient 1 at 3 mm through the study's CT path, its 'truth' method (the truth's own
    skin judged as a scan), the truth grid solved by the MTM (as tests/test_study.py:
    NGSolve's truth takes minutes; the CT path, the part judged here, is the same)."""
    from pvcmf import mtm, reference
    from pvcmf.datasets import phantom
    from pvcmf.study.validation import TRUTH_REACH, _scan, postop_ct, run_study, study_predictor

    def truth(case):
        return mtm.solve(reference._truth_grid(case, 3000, 0.5, False)[1])
    folder = tmp_path_factory.mktemp("study")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*thinner than the")
        case = phantom(1, spacing=3.0)
        grid = truth(case)
        skins, _, table = run_study(study_predictor(spacing=3.0, truth=lambda c: grid),
                                    patients=(1,), methods=("truth",))
        _, _, pre_skin, _ = _scan(case, 1, lambda c: grid, 18.0, None)
        ct, _ = postop_ct(case, grid, noise_hu=18.0, pose="random", seed=1, spacing=None,
                          extrapolate=TRUTH_REACH, extension="nearest")  # as _scan makes it
    judged = skins[1]["truth"]
    pred = pv.PolyData(judged.points, faces=judged.faces)  # the prediction, without answers
    pred.save(folder / "predicted_skin.vtp")
    pre_skin.save(folder / "skin_pre.vtp")
    ct.save(folder / "post_ct.vti")
    write_landmarks(case.landmarks, folder / "landmarks.mrk.json")
    face = table[table["region"] == "face"].iloc[0]
    return folder, judged, face


def test_validate_reproduces_the_study(study_case):
    folder, judged, face = study_case
    out = folder / "out"
    assert main(["validate", "--pred", str(folder / "predicted_skin.vtp"), "--post",
                 str(folder / "post_ct.vti"), "--landmarks", str(folder / "landmarks.mrk.json"),
                 "--out", str(out), "--no-progress", "--no-figures"]) == 0
    skin = pv.read(out / "validated_skin.vtp")
    np.testing.assert_allclose(skin[arrays.DISTANCE], judged[arrays.DISTANCE], atol=1e-6)
    row = pd.read_csv(out / "regions.csv").set_index("region").loc["face"]
    for key in ("n", "median", "p50", "p90", "p95", "within_1mm", "within_2mm"):
        assert row[key] == pytest.approx(face[key], abs=1e-6), key
