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
                              capture_output=True, text=True, timeout=28)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"an unguarded script hangs instead of failing: {err}")
    assert proc.returncode != 0 and "ROWS" not in proc.stdout
    last = proc.stderr.strip().splitlines()[-1]
    assert "LocalClusterStartError" in last
    assert 'if __name__ == "__main__":' in last and 'scheduler="synchronous"' in last
