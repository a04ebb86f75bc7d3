"""Nothing silent in the sweeps: bad inputs are refused before any work, with messages that
name the input; a NaN metric is a failed point; a script without a main guard is told so;
plan parameters reuse one plan-response operator per case and equal full solves."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pandas")

import pvcmf  # noqa: E402
from pvcmf.study import engine  # noqa: E402
from pvcmf.study.cli import add_sweep_parser  # noqa: E402
from pvcmf.study.engine import NonFiniteResultError, sweep  # noqa: E402
from pvcmf.study.evaluation import error_statistics, synthetic_evaluate  # noqa: E402
from pvcmf.study.parameters import parse_grid, validate_grid  # noqa: E402
from pvcmf.study.pipeline_evaluation import PipelineEvaluation  # noqa: E402

ROOT = Path(pvcmf.__file__).resolve().parent.parent


def _parse(argv):
    import argparse

    parser = argparse.ArgumentParser(prog="pvcmf")
    add_sweep_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(["sweep", *argv])


def _never(*args, **kwargs):  # an evaluation that must not run
    raise AssertionError("the sweep computed something before refusing its inputs")


# --------------------------------------------------------------------------- workers


@pytest.mark.parametrize("n", [-1, 0, 1.5, True])
def test_non_positive_worker_count_refused_at_once(n):
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=rf"n_workers must be a positive integer.*got {n!r}"):
        sweep([1], {"nu": [0.3]}, evaluate=_never, n_workers=n)
    assert time.perf_counter() - t0 < 5  # refused, not a cluster that never starts


def test_cli_workers_minus_one_refused(tmp_path):
    from pvcmf.cli import main

    out = tmp_path / "t.csv"
    t0 = time.perf_counter()
    assert main(["sweep", "--grid", "nu=0.3", "--out", str(out), "--synthetic",
                 "--no-progress", "--workers", "-1"]) == 2
    assert time.perf_counter() - t0 < 10 and not out.exists()


# --------------------------------------------------------------------------- cases


@pytest.mark.parametrize("cases, bad", [([9], "9"), ([1, 0], "0"), ([{"patient": 7}], "7")])
def test_unknown_patient_refused_before_any_work(cases, bad):
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=rf"virtual patient number \[1, 2, 3, 4\].*got {bad}"):
        sweep(cases, {"nu": [0.3]}, evaluate=_never)  # default scheduler: no cluster started
    assert time.perf_counter() - t0 < 5


def test_cli_unknown_patient_refused(tmp_path, capsys):
    from pvcmf.cli import main

    assert main(["sweep", "--patients", "9", "--grid", "nu=0.3", "--out",
                 str(tmp_path / "t.csv"), "--no-progress"]) == 2
    assert "--patients" in capsys.readouterr().err


# --------------------------------------------------------------------------- grid strings


@pytest.mark.parametrize("item, words", [
    ("nu=0:0.4:abc", ["'nu=0:0.4:abc'", "NUM", "positive integer", "'abc'"]),
    ("nu=0:0.4:0", ["NUM", "'0'"]),
    ("nu=a:0.4:3", ["START", "a number", "'a'"]),
    ("nu=0:x:3", ["STOP", "'x'"]),
    ("nu=0:0.4", ["START:STOP:NUM", "2 parts"]),
    ("nu=0.1,abc", ["'nu'", "'abc'"]),
    ("maxilla_t_ap=0:80:3", ["'maxilla_t_ap'", "50 mm"]),
])
def test_grid_strings_name_the_item_and_what_was_expected(item, words):
    with pytest.raises(ValueError) as info:
        parse_grid([item])
    for w in words:
        assert w in str(info.value), (w, str(info.value))


# --------------------------------------------------------------------------- NaN results


def _nan_at(case, nu=0.3, **params):
    out = synthetic_evaluate(case, nu=nu, **params)
    if nu == 0.2:
        out = {**out, "p90": float("nan")}
    if nu == 0.25:
        out = {**out, "rms": float("inf")}
    return out


def test_nan_metric_is_a_failed_point_not_cached(tmp_path):
    grid = {"nu": [0.1, 0.2, 0.25, 0.3]}
    df = sweep([1], grid, evaluate=_nan_at, scheduler="synchronous", cache_dir=tmp_path,
               on_error="skip")
    assert df.attrs["n_failed"] == 2
    err = df.set_index("nu")["error"]
    assert "p90=nan" in err[0.2] and "rms=inf" in err[0.25]
    assert err[[0.1, 0.3]].isna().all()
    assert np.isnan(df.set_index("nu").loc[0.2, "p50"])  # no half row
    again = sweep([1], grid, evaluate=_nan_at, scheduler="synchronous", cache_dir=tmp_path,
                  on_error="skip")
    assert again["cached"].tolist() == [True, False, False, True]  # failures were not cached
    with pytest.raises(NonFiniteResultError, match=r"case 'P1' with \{'nu': 0.2\}.*p90=nan"):
        sweep([1], grid, evaluate=_nan_at, scheduler="synchronous", cache_dir=tmp_path)


def test_nan_cache_entry_is_not_a_result(tmp_path):
    """An entry with a NaN metric (written before NaN was a failure) is computed again."""
    def fine(case, nu=0.3):
        return error_statistics([nu, -nu, 2 * nu])

    df = sweep([1], {"nu": [0.3]}, evaluate=fine, scheduler="synchronous", cache_dir=tmp_path)
    (entry,) = list(tmp_path.rglob("*.npz"))
    engine._write_result({**df.iloc[0].to_dict(), "p50": float("nan")}, entry)
    again = sweep([1], {"nu": [0.3]}, evaluate=fine, scheduler="synchronous",
                  cache_dir=tmp_path)
    assert not again["cached"].iloc[0] and np.isfinite(again["p50"].iloc[0])


# --------------------------------------------------------------------------- output paths


@pytest.mark.parametrize("kind, words", [
    ("folder", ["is a folder"]),
    ("under a file", ["which is a file"]),
    ("extension", ["must end in one of", ".xlsx"]),
    ("parquet", ["pip install pyarrow"]),
])
def test_output_path_refused_before_any_work(tmp_path, monkeypatch, kind, words):
    out = {"folder": tmp_path,
           "under a file": tmp_path / "afile" / "t.csv",
           "extension": tmp_path / "t.xlsx",
           "parquet": tmp_path / "t.parquet"}[kind]
    (tmp_path / "afile").write_text("x")
    if kind == "parquet":
        monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow -> ImportError
    monkeypatch.setattr("pvcmf.study.cli.synthetic_evaluate", _never)
    args = _parse(["--grid", "nu=0.3", "--out", str(out), "--synthetic", "--no-progress",
                   "--scheduler", "synchronous"])
    with pytest.raises(ValueError) as info:
        args.func(args)
    for w in words:
        assert w in str(info.value)
    assert "--out" in str(info.value)


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root writes anywhere: no unwritable folder to test with")
def test_unwritable_output_folder_refused_before_any_work(tmp_path, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    monkeypatch.setattr("pvcmf.study.cli.synthetic_evaluate", _never)
    try:
        args = _parse(["--grid", "nu=0.3", "--out", str(ro / "t.csv"), "--synthetic",
                       "--no-progress", "--scheduler", "synchronous"])
        with pytest.raises(ValueError, match="cannot write"):
            args.func(args)
    finally:
        ro.chmod(0o700)


# --------------------------------------------------------------------------- main guard


def test_script_without_main_guard_is_told_why(tmp_path):
    """The README's example pasted into a script without ``if __name__ == "__main__":``:
    the local cluster's spawned processes re-import the script; the error says so."""
    script = tmp_path / "unguarded.py"
    script.write_text(textwrap.dedent("""
        import pvcmf
        from pvcmf.study.evaluation import synthetic_evaluate

        df = pvcmf.sweep([1], {"nu": [0.3]}, evaluate=synthetic_evaluate, n_workers=1)
        print("ROWS", len(df))
    """))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
    try:
        proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"an unguarded script hangs instead of failing: {err}")
    assert proc.returncode != 0 and "ROWS" not in proc.stdout
    last = proc.stderr.strip().splitlines()[-1]
    assert "LocalClusterStartError" in last
    assert 'if __name__ == "__main__":' in last and 'scheduler="synchronous"' in last


# --------------------------------------------------------------------------- plan sweeps


def _block_case():
    """A small case: a soft-tissue shell around a two-segment bone block (maxilla above,
    mandible below), its label image, a skin sphere, a truth sphere, and a maxilla plan;
    the grid carries the boundary conditions of that plan (as a prepared case does)."""
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters import apply_plan
    from pvcmf.plan import Osteotomy, Plan

    img = pv.ImageData(dimensions=(13, 13, 13), origin=(-6, -6, -6))
    p = np.asarray(img.points)
    inner = (np.abs(p) <= 3).all(axis=1)
    img[arrays.BONE] = np.where(inner, np.where(p[:, 2] > 0, arrays.MAXILLA, arrays.MANDIBLE),
                                0).astype(np.uint8)
    tissue = np.where(inner, arrays.BONE_TISSUE, arrays.FAT)
    tissue[inner & (p[:, 2] == 0) & (p[:, 1] >= 3)] = arrays.TEETH
    img[arrays.TISSUE] = tissue.astype(np.uint8)
    soft = ~(np.abs(img.cell_centers().points) < 3).all(axis=1)
    grid = img.extract_cells(np.flatnonzero(soft)).triangulate().clean()
    grid.clear_data()
    grid.cell_data[arrays.E_FIBER] = np.full(grid.n_cells, 3e-3)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.45)
    plan = Plan((Osteotomy("maxilla", (0.5, 1.0, 2.0), (0.0, 3.0, 0.0)),), name="block")
    grid = apply_plan(grid, plan, img, fix_unmoved_bone=True, release_margin="auto")
    skin = pv.Sphere(radius=6.2, theta_resolution=24, phi_resolution=16)
    truth = pv.Sphere(radius=6.5, theta_resolution=30, phi_resolution=20)
    return {"grid": grid, "skin": skin, "postop": truth, "labels": img, "plan": plan}


class _BlockPipeline(PipelineEvaluation):
    """The pipeline evaluation on the block case (no virtual patient built)."""

    def _prepare(self, case, **group):
        return _block_case()


@pytest.mark.filterwarnings("ignore:the MTM solution inverts")
def test_plan_sweep_equals_full_predictions_with_one_operator_per_case(monkeypatch):
    from pvcmf import arrays
    from pvcmf.filters import apply_plan
    from pvcmf.filters.surface_mapping import transfer_operator
    from pvcmf.mtm import solve
    from pvcmf.mtm import response as response_module
    from pvcmf.plan import Osteotomy, Plan
    from pvcmf.study import pipeline_evaluation

    builds = []

    def counted(*args, **kwargs):
        builds.append(kwargs.get("plan"))
        return response_module.plan_response(*args, **kwargs)

    monkeypatch.setattr(pipeline_evaluation, "plan_response", counted)
    grid = {"maxilla_t_ap": [-1.0, 2.0, 4.0], "maxilla_r_pitch": [0.0, 5.0]}
    df = sweep(["A", "B"], grid, evaluate=_BlockPipeline(keep_distance=True, region="skin"),
               scheduler="synchronous", keep_arrays=True)
    assert len(df) == 12 and len(builds) == 2  # one operator per case, 6 plans each
    assert df["error"].isna().all() if "error" in df else True

    # independent reference: the case's plan with the swept components replaced, boundary
    # conditions with the release margin the case's own plan had, a full solve, transfer
    case = _block_case()
    g, img, skin = case["grid"], case["labels"], case["skin"]
    moving = np.isin(np.asarray(g[arrays.BC]), (arrays.BC_JOINT, arrays.BC_SLIDING))
    margin = 2 * np.linalg.norm(np.asarray(g[arrays.BC_DISPLACEMENT])[moving], axis=1).max()
    T = transfer_operator(g, skin)
    for _, row in df[df["case"] == "A"].iterrows():
        plan = Plan((Osteotomy("maxilla", (0.5, 1.0, row["maxilla_t_ap"]),
                               (row["maxilla_r_pitch"], 3.0, 0.0)),))
        bcs = apply_plan(g, plan, img, fix_unmoved_bone=True, release_margin=margin)
        u = np.asarray(T @ np.asarray(solve(bcs)[arrays.DISPLACEMENT]))
        assert np.abs(u).max() > 0.5
        assert np.abs(row[arrays.DISPLACEMENT] - u).max() < 1e-9
    a, b = (np.stack(df[df["case"] == c][arrays.DISPLACEMENT].tolist()) for c in "AB")
    np.testing.assert_array_equal(a, b)  # the same case under two names


def test_plan_parameters_validated():
    assert validate_grid({"mandible_r_pitch": [0, 5]}) == {"mandible_r_pitch": (0.0, 5.0)}
    with pytest.raises(ValueError, match=r"'maxilla_r_yaw'.*30 degrees.*45"):
        validate_grid({"maxilla_r_yaw": [45]})
    with pytest.raises(ValueError, match="twice"):
        validate_grid({"maxilla_r_h": [1], "maxilla_r_pitch": [2]})
