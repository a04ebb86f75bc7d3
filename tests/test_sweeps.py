"""Parameter sweeps (pvcmf.sweeps) on Dask and paper 001's Figs. 2-5 (pvcmf.figures.parameter_studies).

The engine is tested with the cheap deterministic ``synthetic_evaluate`` (pure numpy), so
these tests do not depend on the pipeline. Cluster tests run a real Dask scheduler with two
Dask processes over loopback; a watchdog (faulthandler) ends the run instead of hanging CI.
"""

from __future__ import annotations

import faulthandler
import os
import signal
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

pd = pytest.importorskip("pandas")
distributed = pytest.importorskip("distributed")

import pvcmf  # noqa: E402
from pvcmf import sweeps  # noqa: E402
from pvcmf.figures import parameter_studies as ps  # noqa: E402
from pvcmf.sweeps import synthetic_evaluate, synthetic_skin  # noqa: E402

# functions and classes of this module travel to the Dask processes by value
import cloudpickle  # noqa: E402

cloudpickle.register_pickle_by_value(sys.modules[__name__])

METRIC_COLS = ["case", "nu", "n_tets", "p50", "p90", "p95", "mean_abs", "rms", "within_1mm",
               "within_2mm", "n_skin", "n_cells"]
GRID = {"n_tets": [8000, 30000], "nu": [0.0, 0.3, 0.46, 0.49]}


class CountingEvaluation(sweeps.Evaluation):
    """Synthetic evaluation that records every prepare/evaluate call as a file."""

    def __init__(self, folder):
        self.folder = str(folder)

    def identity(self):
        return {"name": "counting", "version": 1}

    def _mark(self, kind):
        Path(self.folder, f"{kind}-{uuid.uuid4().hex}").touch()

    def prepare(self, case, **group):
        self._mark("prepare")
        return case, group

    def evaluate(self, state, **params):
        self._mark("evaluate")
        case, group = state
        return synthetic_evaluate(case, **group, **params)


def count(folder, kind):
    return len(list(Path(folder).glob(f"{kind}-*")))


class KillOnce:
    """Kill the Dask process the first time case ``victim`` is evaluated (marker file)."""

    def __init__(self, folder, victim=2):
        self.folder, self.victim = str(folder), victim

    def identity(self):
        return {"name": "kill-once", "version": 1}

    def __call__(self, case, **params):
        marker = Path(self.folder, "killed")
        if case == self.victim and not marker.exists():
            marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        Path(self.folder, f"evaluate-{uuid.uuid4().hex}").touch()
        return synthetic_evaluate(case, **params)


@pytest.fixture()
def watchdog():
    """Dump tracebacks and exit if a cluster test hangs (no pytest-timeout needed)."""
    faulthandler.dump_traceback_later(240, exit=True)
    yield
    faulthandler.cancel_dump_traceback_later()


@pytest.fixture(scope="module")
def client():
    """A real Dask scheduler with two single-threaded Dask processes over loopback."""
    faulthandler.dump_traceback_later(240, exit=True)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None, memory_limit="1GiB",
                                  host="127.0.0.1") as cluster:
        with distributed.Client(cluster, timeout="60s") as c:
            faulthandler.cancel_dump_traceback_later()
            yield c


@pytest.fixture(scope="module")
def local_table():
    return pvcmf.sweep([1, 2, 3], GRID, evaluate=synthetic_evaluate, scheduler="synchronous")


# --------------------------------------------------------------------------- grid validation


@pytest.mark.parametrize("grid, words", [
    ({"nu": [0.2, 0.5]}, ["'nu'", "[0, 0.5)", "0.5"]),
    ({"nu": [0.499, 0.6]}, ["'nu'", "0.6"]),
    ({"nu": [-0.1]}, ["'nu'", "-0.1"]),
    ({"nu_fat": [0.3], "nu_muscle": [0.51]}, ["'nu_muscle'", "0.51"]),
    ({"E_ratio": [1, 0]}, ["'E_ratio'", "> 0", "0"]),
    ({"E_ratio": [-4]}, ["'E_ratio'", "-4"]),
    ({"E_fat": [float("nan")]}, ["'E_fat'", "nan"]),
    ({"nu": []}, ["'nu'", "empty"]),
    ({"n_tets": [0]}, ["'n_tets'", "positive integers"]),
    ({"n_tets": [30000.5]}, ["'n_tets'"]),
    ({"poisson": [0.3]}, ["unknown parameter 'poisson'", "nu"]),
    ({}, ["at least one parameter"]),
    ({"nu": [0.3, 0.3]}, ["duplicated"]),
    ({"nu": [0.3], "nu_fat": [0.4]}, ["either"]),
])
def test_invalid_grid_refused_before_anything_runs(tmp_path, grid, words):
    evaluation = CountingEvaluation(tmp_path)
    with pytest.raises(ValueError) as info:
        # a bad address would fail too if anything tried to start: validation comes first
        pvcmf.sweep([1, 2], grid, evaluate=evaluation, scheduler="tcp://127.0.0.1:9",
                    cache_dir=tmp_path / "cache")
    for word in words:
        assert word in str(info.value)
    assert count(tmp_path, "prepare") == count(tmp_path, "evaluate") == 0
    assert not (tmp_path / "cache").exists()


def test_bad_cases_and_scheduler_refused(tmp_path):
    with pytest.raises(ValueError, match="at least one case"):
        pvcmf.sweep([], {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler="synchronous")
    with pytest.raises(ValueError, match="distinct"):
        pvcmf.sweep([1, 1], {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler="synchronous")
    with pytest.raises(ValueError, match="scheduler must be"):
        pvcmf.sweep([1], {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler="gpu-cluster")
    with pytest.raises(TypeError, match="scheduler"):
        pvcmf.sweep([1], {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler=42)


def test_validate_grid_normalises():
    assert sweeps.validate_grid({"nu": np.array([0.1, 0.2]), "n_tets": 30000, "roi": [None, 20]}) == {
        "nu": (0.1, 0.2), "n_tets": (30000,), "roi": (None, 20.0)}


# --------------------------------------------------------------------------- table, grouping


def test_table_is_tidy_and_in_grid_order(local_table):
    df = local_table
    assert len(df) == 3 * 2 * 4
    assert list(df.columns[:3]) == ["case", "n_tets", "nu"]
    assert df[["case", "n_tets", "nu"]].drop_duplicates().shape[0] == len(df)
    assert df["case"].tolist()[:8] == ["P1"] * 8
    assert df["nu"].tolist()[:4] == GRID["nu"]
    for col in ("p50", "p90", "p95", "within_1mm", "within_2mm", "t_prepare", "t_eval"):
        assert col in df
    assert (df["p50"] <= df["p90"]).all() and (df["p90"] <= df["p95"]).all()
    assert not df["cached"].any()
    # each row equals a direct evaluation of its point (nothing mixed up between points)
    row = df[(df["case"] == "P2") & (df["n_tets"] == 8000) & (df["nu"] == 0.3)].iloc[0]
    direct = synthetic_evaluate(2, n_tets=8000, nu=0.3)
    assert row["p90"] == direct["p90"] and row["within_2mm"] == direct["within_2mm"]


def test_one_prepare_per_case_and_mesh(tmp_path):
    """Each task prepares its case's mesh once and loops over the solve-level values."""
    pvcmf.sweep([1, 2], {"nu": [0.1, 0.2, 0.3], "E_ratio": [1, 4], "n_tets": [5000, 9000]},
                evaluate=CountingEvaluation(tmp_path), scheduler="synchronous")
    assert count(tmp_path, "prepare") == 2 * 2
    assert count(tmp_path, "evaluate") == 2 * 2 * 3 * 2


def test_error_statistics_known_distribution():
    d = np.linspace(-3.0, 3.0, 60001)  # |d| uniform on [0, 3]
    s = sweeps.error_statistics(d)
    np.testing.assert_allclose([s["p50"], s["p90"], s["p95"]], [1.5, 2.7, 2.85], atol=1e-3)
    assert s["within_1mm"] == pytest.approx(100 / 3, abs=0.01)
    assert s["within_2mm"] == pytest.approx(200 / 3, abs=0.01)
    assert s["rms"] == pytest.approx(np.sqrt(3.0), rel=1e-4)
    with pytest.raises(ValueError, match="finite"):
        sweeps.error_statistics([np.nan])


# --------------------------------------------------------------------------- cache


def test_cached_rerun_computes_nothing(tmp_path):
    marks, cache = tmp_path / "marks", tmp_path / "cache"
    marks.mkdir()
    evaluation = CountingEvaluation(marks)
    grid = {"nu": [0.2, 0.46], "n_tets": [9000]}
    first = pvcmf.sweep([1, 2], grid, evaluate=evaluation, scheduler="synchronous", cache_dir=cache)
    assert count(marks, "evaluate") == 4 and count(marks, "prepare") == 2
    again = pvcmf.sweep([1, 2], grid, evaluate=evaluation, scheduler="synchronous", cache_dir=cache)
    assert count(marks, "evaluate") == 4 and count(marks, "prepare") == 2  # nothing recomputed
    assert again["cached"].all() and again.attrs["n_computed"] == 0
    pd.testing.assert_frame_equal(first[METRIC_COLS], again[METRIC_COLS])
    # one more value: only its points are computed
    pvcmf.sweep([1, 2], {**grid, "nu": [0.2, 0.46, 0.49]}, evaluate=evaluation,
                scheduler="synchronous", cache_dir=cache)
    assert count(marks, "evaluate") == 6
    # another code version recomputes
    pvcmf.sweep([1, 2], grid, evaluate=evaluation, scheduler="synchronous", cache_dir=cache,
                version="other")
    assert count(marks, "evaluate") == 10


def test_corrupt_cache_entry_is_recomputed(tmp_path):
    cache = tmp_path / "cache"
    pvcmf.sweep(1, {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler="synchronous", cache_dir=cache)
    (entry,) = cache.rglob("*.npz")
    entry.write_bytes(b"not a npz")
    df = pvcmf.sweep(1, {"nu": [0.3]}, evaluate=synthetic_evaluate, scheduler="synchronous",
                     cache_dir=cache)
    assert not df["cached"].any()
    assert df["p90"].iloc[0] == synthetic_evaluate(1, nu=0.3)["p90"]


def test_arrays_round_trip_through_cache(tmp_path):
    kw = dict(evaluate=synthetic_evaluate, scheduler="synchronous", cache_dir=tmp_path, keep_arrays=True)
    a = pvcmf.sweep(1, {"nu": [0.1, 0.4]}, **kw)
    b = pvcmf.sweep(1, {"nu": [0.1, 0.4]}, **kw)
    assert b["cached"].all()
    for x, y in zip(a["distance"], b["distance"]):
        np.testing.assert_array_equal(x, y)


# --------------------------------------------------------------------------- Dask


def test_cluster_gives_the_local_table(client, local_table, tmp_path, watchdog):
    df = pvcmf.sweep([1, 2, 3], GRID, evaluate=synthetic_evaluate, scheduler=client)
    pd.testing.assert_frame_equal(df[METRIC_COLS], local_table[METRIC_COLS])
    assert df.attrs["n_tasks"] == 3 * 2
    # the same through the scheduler's address, as a remote cluster is given
    df2 = pvcmf.sweep([1, 2, 3], GRID, evaluate=synthetic_evaluate, scheduler=client.scheduler.address)
    pd.testing.assert_frame_equal(df2[METRIC_COLS], local_table[METRIC_COLS])


def test_killed_process_is_retried_and_nothing_lost(client, local_table, tmp_path, watchdog):
    cache = tmp_path / "cache"
    df = pvcmf.sweep([1, 2, 3], GRID, evaluate=KillOnce(tmp_path), scheduler=client, cache_dir=cache,
                     retries=2)
    assert (tmp_path / "killed").exists()  # a Dask process really died mid-sweep
    pd.testing.assert_frame_equal(df[METRIC_COLS], local_table[METRIC_COLS])
    n = count(tmp_path, "evaluate")
    assert n >= len(df)
    again = pvcmf.sweep([1, 2, 3], GRID, evaluate=KillOnce(tmp_path), scheduler=client, cache_dir=cache)
    assert again["cached"].all() and count(tmp_path, "evaluate") == n  # computes nothing
    client.wait_for_workers(2, timeout=60)


def test_failing_task_reports_case_and_keeps_finished_results(client, tmp_path, watchdog):
    def fragile(case, **params):
        if case == 3:
            raise FloatingPointError("diverged")
        return synthetic_evaluate(case, **params)

    cache = tmp_path / "cache"
    with pytest.raises(RuntimeError, match="'P3'.*FloatingPointError: diverged"):
        pvcmf.sweep([1, 2, 3], {"nu": [0.3]}, evaluate=fragile, scheduler=client, cache_dir=cache,
                    retries=1)
    assert len(list(cache.rglob("*.npz"))) <= 2


def _fragile(case, **params):
    if case == 3:
        raise FloatingPointError("diverged")
    return synthetic_evaluate(case, **params)


def test_on_error_skip_finishes_the_others_and_caches_no_failure(tmp_path):
    cache = tmp_path / "cache"
    df = pvcmf.sweep([1, 3, 2], {"nu": [0.3, 0.4]}, evaluate=_fragile, scheduler="synchronous",
                     cache_dir=cache, on_error="skip")
    bad = df["case"] == "P3"
    assert df.loc[bad, "p90"].isna().all() and df.loc[~bad, "p90"].notna().all()
    assert (df.loc[bad, "error"] == "FloatingPointError: diverged").all()
    assert df.attrs["n_failed"] == 2 and len(list(cache.rglob("*.npz"))) == 4
    with pytest.raises(RuntimeError, match="'P3'.*diverged"):
        pvcmf.sweep([3], {"nu": [0.3]}, evaluate=_fragile, scheduler="synchronous")
    with pytest.raises(ValueError, match="on_error"):
        pvcmf.sweep([3], {"nu": [0.3]}, evaluate=_fragile, on_error="ignore")


# --------------------------------------------------------------------------- saving, CLI


def test_save_and_load_csv(local_table, tmp_path):
    path = sweeps.save_table(local_table, tmp_path / "out" / "table.csv")
    back = sweeps.load_table(path)
    pd.testing.assert_frame_equal(back[METRIC_COLS], local_table[METRIC_COLS], check_dtype=False)
    with pytest.raises(ValueError, match=r"\.csv or \.parquet"):
        sweeps.save_table(local_table, tmp_path / "table.xlsx")


def test_save_parquet_with_arrays(tmp_path):
    pytest.importorskip("pyarrow")
    df = pvcmf.sweep(1, {"nu": [0.1, 0.4]}, evaluate=synthetic_evaluate, scheduler="synchronous",
                     keep_arrays=True)
    back = sweeps.load_table(sweeps.save_table(df, tmp_path / "t.parquet"))
    np.testing.assert_allclose(np.asarray(back["distance"].iloc[1]), df["distance"].iloc[1])


def test_parquet_without_pyarrow_says_how_to_get_it(local_table, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)  # import pyarrow -> ImportError
    with pytest.raises(ImportError, match="pip install pyarrow"):
        sweeps.save_table(local_table, tmp_path / "t.parquet")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_parse_grid_and_cli(tmp_path, monkeypatch):
    assert sweeps.parse_grid(["nu=0:0.495:4", "E_ratio=1,64", "roi=none,20"]) == {
        "nu": (0.0, 0.165, 0.33, 0.495), "E_ratio": (1.0, 64.0), "roi": (None, 20.0)}
    with pytest.raises(ValueError, match="'nu'"):
        sweeps.parse_grid(["nu=0:0.5:3"])
    with pytest.raises(ValueError, match="NAME=V1"):
        sweeps.parse_grid(["nu"])
    import argparse

    parser = argparse.ArgumentParser(prog="pvcmf")
    sweeps.add_sweep_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["sweep", "--patients", "1", "2", "--grid", "nu=0.3,0.46",
                              "--out", str(tmp_path / "t.csv"), "--scheduler", "synchronous",
                              "--synthetic", "--no-progress"])
    path, df = args.func(args)
    assert path.exists() and len(sweeps.load_table(path)) == 4


def test_pvcmf_sweep_command(tmp_path, capsys):
    from pvcmf.cli import main

    out = tmp_path / "poisson.csv"
    argv = ["sweep", "--patients", "1", "2", "--grid", "nu=0:0.45:4", "--out", str(out),
            "--scheduler", "synchronous", "--synthetic", "--no-progress",
            "--cache-dir", str(tmp_path / "cache")]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "8 rows (8 computed, 0 from the cache, 0 failed)" in text and str(out) in text
    assert sweeps.load_table(out)["nu"].tolist() == [0.0, 0.15, 0.3, 0.45] * 2
    assert main(argv) == 0
    assert "(0 computed, 8 from the cache" in capsys.readouterr().out
    bad = ["sweep", "--grid", "nu=0.2,0.5", "--out", str(tmp_path / "bad.csv"), "--synthetic"]
    assert main(bad) == 2
    err = capsys.readouterr().err
    assert "'nu'" in err and "0.5" in err and not (tmp_path / "bad.csv").exists()


def test_pvcmf_sweep_without_dask_names_the_extra(tmp_path, monkeypatch):
    """Without ``distributed`` the command says which extra to install and writes nothing;
    ``--scheduler synchronous`` still runs."""
    from pvcmf.cli import main

    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    out = tmp_path / "t.csv"
    argv = ["sweep", "--grid", "nu=0.3", "--out", str(out), "--synthetic", "--no-progress"]
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert 'pip install "pvcmf[sweep]"' in str(info.value) and "synchronous" in str(info.value)
    assert not out.exists()
    assert main([*argv, "--scheduler", "synchronous"]) == 0 and out.exists()


@pytest.mark.parametrize("tqdm_installed", [True, False])
def test_progress_bar_counts_every_point(tmp_path, monkeypatch, caplog, capsys, tqdm_installed):
    """progress_bar=True shows a tqdm bar over all points (cached ones included), or logs
    each step at INFO when tqdm is missing; progress_bar=False shows nothing."""
    import logging

    if tqdm_installed:
        pytest.importorskip("tqdm")
    else:
        monkeypatch.setitem(sys.modules, "tqdm", None)
        monkeypatch.setitem(sys.modules, "tqdm.auto", None)
    kw = dict(evaluate=synthetic_evaluate, scheduler="synchronous", cache_dir=tmp_path)
    pvcmf.sweep([1, 2], {"nu": [0.3]}, **kw)
    capsys.readouterr()
    with caplog.at_level(logging.INFO, logger="pvcmf"):
        pvcmf.sweep([1, 2, 3], {"nu": [0.3], "n_tets": [8000, 9000]}, progress_bar=True, **kw)
    err = capsys.readouterr().err
    steps = [r.getMessage() for r in caplog.records if r.getMessage().startswith("sweep [")]
    if tqdm_installed:
        assert "6/6" in err and not steps
    else:
        assert steps[-1].startswith("sweep [6/6]") and "6/6" not in err
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="pvcmf"):
        pvcmf.sweep([1, 2, 3], {"nu": [0.3]}, progress_bar=False, **kw)
    assert "/3" not in capsys.readouterr().err
    assert not [r for r in caplog.records if r.getMessage().startswith("sweep [")]


# --------------------------------------------------------------------------- figures


NUS = [0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.43, 0.45, 0.46, 0.47, 0.48, 0.49, 0.495]


@pytest.fixture(scope="module")
def poisson_table():
    return pvcmf.sweep([1, 2, 3, 4], {"nu": NUS}, evaluate=synthetic_evaluate,
                       scheduler="synchronous", keep_arrays=True)


def test_poisson_optimum_matches_table(poisson_table):
    opt = ps.poisson_optimum(poisson_table)
    for case in ("P1", "P2", "P3", "P4"):
        sub = poisson_table[poisson_table["case"] == case]
        assert opt.loc[case, "nu_opt"] == sub.loc[sub["p90"].idxmin(), "nu"]
        assert opt.loc[case, "d_046"] >= 0
    mean = poisson_table.groupby("nu")["p90"].mean()
    assert opt.loc["average", "nu_opt"] == mean.idxmin()


def test_fig2_poisson(poisson_table, verify_chart):
    verify_chart(ps.fig2_poisson(poisson_table))


def _mesh_table():
    df = pvcmf.sweep([1, 2, 4], {"n_tets": [2000, 5000, 10000, 20000, 30000, 60000, 120000, 240000]},
                     evaluate=synthetic_evaluate, scheduler="synchronous")
    df["t_eval"] = df["n_cells"] * 7e-5 * (1 + 0.1 * df["case"].str[1:].astype(int))  # deterministic
    return df


def test_mesh_size_table():
    df = _mesh_table()
    table = ps.mesh_size_table(df)
    assert list(table.index) == ["P1", "P2", "P4", "Average"]
    assert (table.loc[["P1", "P2", "P4"], "N_tetra"] == 30000).all()
    p1 = df[df["case"] == "P1"].set_index("n_tets")
    assert table.loc["P1", "D90"] == pytest.approx(p1.loc[30000, "p90"] - p1.loc[240000, "p90"])
    assert table.loc["Average", "D90"] == pytest.approx(table["D90"].iloc[:3].abs().mean())


def test_fig3_mesh_size(verify_chart):
    verify_chart(ps.fig3_mesh_size(_mesh_table()))


def test_fig4_inhomogeneous(verify_chart):
    g = [0.0, 0.1, 0.2, 0.3, 0.4, 0.43, 0.46, 0.485, 0.495]
    df = pvcmf.sweep([1, 2], {"E_ratio": [1, 4, 16, 64], "nu_fat": g, "nu_muscle": g},
                     evaluate=synthetic_evaluate, scheduler="synchronous")
    table = ps.inhomogeneous_table(df, case="P2")
    sub = df[(df["case"] == "P2") & (df["E_ratio"] == 4.0)]
    assert table.loc[4.0, "p90_max"] == sub["p90"].max()
    assert table.loc[4.0, "p50_min"] == sub["p50"].min()
    verify_chart(ps.fig4_inhomogeneous(df))


def test_optimal_poisson_per_point(poisson_table):
    skin = synthetic_skin()
    face = ps.optimal_poisson(poisson_table, skin, case="P1", neighbours=1)
    maps = np.stack(list(poisson_table[poisson_table["case"] == "P1"]["distance"]))
    i = 123
    assert face["nu_opt"][i] == NUS[int(np.argmin(np.abs(maps[:, i])))]
    assert face["p90_spread"][i] == pytest.approx(np.abs(maps[:, i]).std())
    with pytest.raises(ValueError, match="points"):
        ps.optimal_poisson(poisson_table, synthetic_skin(500))


def test_fig5_optimal_poisson(poisson_table, verify_image_cache):
    pl = ps.fig5_optimal_poisson(poisson_table, synthetic_skin(), case="P2")
    pl.show()


def test_figures_refuse_tables_without_their_columns(local_table):
    with pytest.raises(ValueError, match="E_ratio"):
        ps.fig4_inhomogeneous(local_table)
    with pytest.raises(TypeError, match="DataFrame"):
        ps.fig2_poisson({"nu": [0.3]})


# --------------------------------------------------------------------------- the pipeline evaluation


def test_pipeline_materials_homogeneous_and_inhomogeneous():
    import pyvista as pv

    from pvcmf import arrays

    grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    tissue = np.where(np.arange(grid.n_cells) % 3 == 0, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    grid.cell_data[arrays.TISSUE] = tissue
    m = sweeps.PipelineEvaluation.materials
    assert m(grid) == {}
    assert m(grid, nu=0.3) == {"E_fiber": 1.0, "E_cross": 1.0, "nu": 0.3}
    out = m(grid, nu_fat=0.49, nu_muscle=0.2, E_ratio=8.0)
    muscle = tissue == arrays.MUSCLE_TISSUE
    np.testing.assert_array_equal(out["nu"], np.where(muscle, 0.2, 0.49))
    np.testing.assert_array_equal(out["E_fiber"], np.where(muscle, 8.0, 1.0))
    grid.cell_data[arrays.MUSCLE_FRACTION] = np.full(grid.n_cells, 0.25)  # baseline: mixed cells
    out = m(grid, nu_fat=0.4, nu_muscle=0.2, E_ratio=5.0)
    np.testing.assert_allclose(out["nu"], 0.35)
    np.testing.assert_allclose(out["E_cross"], 2.0)


def _squeezed_cube():
    """A cube squeezed between two plates (joint nodes), sides free; its skin; and the
    exact nu = 0 answer (uniform strain u_z = -0.1 z, no lateral bulge) as the truth."""
    import pyvista as pv

    from pvcmf import arrays

    grid = pv.ImageData(dimensions=(6, 6, 6), spacing=(1.0, 1.0, 1.0)).triangulate()
    grid = grid.cast_to_unstructured_grid()
    z = grid.points[:, 2]
    grid.point_data[arrays.BC] = np.where((z == 0) | (z == 5), arrays.BC_JOINT, arrays.BC_FREE).astype(np.int8)
    disp = np.zeros((grid.n_points, 3))
    disp[z == 5, 2] = -0.5
    grid.point_data[arrays.BC_DISPLACEMENT] = disp
    grid.point_data[arrays.BC_NORMAL] = np.zeros((grid.n_points, 3))
    grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.3)
    skin = grid.extract_surface(algorithm="dataset_surface").triangulate().clean()
    truth = skin.copy()
    truth.points = truth.points + np.c_[np.zeros((truth.n_points, 2)), -0.1 * truth.points[:, 2]]
    return {"grid": grid, "skin": skin, "postop": truth, "solvers": {}}


def _need_mtm():
    try:
        from pvcmf import filters, mtm

        mtm.Solver, filters.distance_to  # noqa: B018
    except (ImportError, AttributeError) as err:
        pytest.skip(f"MTM solver or distance filter not available yet: {err}")


def test_pipeline_evaluation_reuses_solver_and_finds_the_exact_ratio():
    """With nu = 0 the squeezed cube's exact answer is the truth: ~0 error there and more as
    nu grows, with one solver refactorised for all ratios."""
    _need_mtm()
    state = _squeezed_cube()
    grid, skin = state["grid"], state["skin"]
    ev = sweeps.PipelineEvaluation(keep_distance=True)
    rows = [ev.evaluate(state, nu=nu) for nu in (0.0, 0.2, 0.45)]
    assert len(state["solvers"]) == 1  # one solver, refactorised per ratio
    assert rows[0]["p95"] < 1e-6
    assert rows[0]["p90"] < rows[1]["p90"] < rows[2]["p90"]
    assert rows[2]["n_cells"] == grid.n_cells and rows[2]["distance"].shape == (skin.n_points,)


class CubePipeline(sweeps.PipelineEvaluation):
    """PipelineEvaluation whose preparation is the squeezed cube, counted by marker files."""

    def __init__(self, marks, **kw):
        super().__init__(**kw)
        self.marks = str(marks)

    def _prepare(self, case, **group):
        Path(self.marks, f"prepare-{uuid.uuid4().hex}").touch()
        return _squeezed_cube()


def test_prepared_cases_are_cached_on_disk(tmp_path):
    _need_mtm()
    ev = CubePipeline(tmp_path, cache_dir=tmp_path / "prepared")
    a = pvcmf.sweep([1], {"nu": [0.0, 0.3]}, evaluate=ev, scheduler="synchronous")
    b = pvcmf.sweep([1], {"nu": [0.0, 0.3], "E_fat": [2.0]}, evaluate=ev, scheduler="synchronous")
    assert count(tmp_path, "prepare") == 1  # the second sweep loaded the mesh, skin and truth
    # ... and reports what preparing it cost, not what loading it cost
    assert b["t_prepare"].iloc[0] == a["t_prepare"].iloc[0]
    assert b["cpu_prepare"].iloc[0] == a["cpu_prepare"].iloc[0]
    np.testing.assert_allclose(b["p90"], a["p90"], rtol=1e-9, atol=1e-12)  # E does not matter
    assert a["p95"].iloc[0] < 1e-6
    pvcmf.sweep([1], {"nu": [0.0], "n_tets": [5000]}, evaluate=ev, scheduler="synchronous")
    assert count(tmp_path, "prepare") == 2  # another mesh-level setting is another preparation


def test_face_only_keeps_the_face_regions():
    import pyvista as pv

    from pvcmf import arrays

    head = pv.ParametricEllipsoid(70, 95, 110).triangulate()
    face = sweeps._face_only(head, None)
    assert 0 < face.n_points < head.n_points and face.is_all_triangles
    assert (face[arrays.REGION] > 0).all()
    assert face.points[:, 1].min() > 0  # anterior half only


def test_partial_arguments_enter_the_cache_key(tmp_path):
    import functools

    kw = dict(scheduler="synchronous", cache_dir=tmp_path)
    a = pvcmf.sweep(1, {"nu": [0.3]}, evaluate=functools.partial(synthetic_evaluate, n_skin=500), **kw)
    b = pvcmf.sweep(1, {"nu": [0.3]}, evaluate=functools.partial(synthetic_evaluate, n_skin=800), **kw)
    assert not b["cached"].any() and (a["n_skin"].iloc[0], b["n_skin"].iloc[0]) == (500, 800)


# --------------------------------------------------------------------------- reused operators


def _mls_one_point(p, x, u, sigma, radius):
    """Independent reference: one skin point's Gaussian-weighted affine least-squares fit
    (numpy.linalg.lstsq on sqrt(w)-scaled rows), clamped to the neighbours' range."""
    d = np.linalg.norm(x - p, axis=1)
    w = np.exp(-0.5 * (d / sigma) ** 2) - np.exp(-0.5 * (radius / sigma) ** 2)
    near = (d <= radius) & (w > 0)
    if not near.any():
        return np.zeros(3)
    A = np.column_stack([np.ones(near.sum()), x[near] - p]) * np.sqrt(w[near])[:, None]
    b = u[near] * np.sqrt(w[near])[:, None]
    if np.linalg.matrix_rank(A) < 4:
        c = (w[near, None] * u[near]).sum(0) / w[near].sum()
    else:
        c = np.linalg.lstsq(A, b, rcond=None)[0][0]
    return np.clip(c, u[near].min(0), u[near].max(0))


def test_skin_mapping_operator_matches_independent_fit():
    """The sweep's precomputed sparse mapping (built once per mesh) equals a point-by-point
    weighted least-squares fit and map_to_surface, for curved and noisy fields, with the
    clamp at the mesh edge and zero beyond the radius."""
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters import map_to_surface

    grid = pv.ImageData(dimensions=(7, 7, 7), spacing=(2.0, 2.0, 2.0)).triangulate()
    skin = pv.Sphere(radius=7.0, center=(6.0, 6.0, 6.0), theta_resolution=12, phi_resolution=12)
    skin = skin.merge(pv.Sphere(radius=1.0, center=(60.0, 0.0, 0.0), theta_resolution=4,
                                phi_resolution=4))  # far from every node
    x = np.asarray(grid.points)
    p = np.asarray(skin.points)
    op = sweeps._skin_mapping(x, p, 1.5, "gaussian")
    rng = np.random.default_rng(3)
    for u in (np.c_[np.sin(x[:, 0] / 5), x[:, 1] ** 2 / 50, np.cos(x[:, 2] / 3)],
              rng.normal(size=x.shape)):
        ref = np.array([_mls_one_point(q, x, u, 1.5, 4.5) for q in p])
        np.testing.assert_allclose(op(u), ref, rtol=0, atol=1e-6)  # O(1) fields; edge fits amplify round-off
        g = grid.copy()
        g.point_data[arrays.DISPLACEMENT] = u
        np.testing.assert_allclose(map_to_surface(g, skin, method="gaussian", sigma=1.5)[arrays.DISPLACEMENT], ref,
                                   rtol=0, atol=1e-6)
    assert np.abs(op(u)[-6:]).max() == 0.0  # beyond the radius: not moved
    with pytest.raises(ValueError, match="sigma"):
        sweeps._skin_mapping(x, p, 0.0, "gaussian")


def test_skin_mapping_interpolate_is_the_pipelines_transfer():
    """The sweep's default operator is the pipeline's transfer (map_to_surface's default):
    the same displacement for a curved field, exact for an affine one inside and near the
    mesh; PipelineEvaluation builds it once per mesh and refuses a Gaussian width."""
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters import map_to_surface
    from pvcmf.filters.surface_mapping import SurfaceMapping, Transfer

    grid = pv.ImageData(dimensions=(7, 7, 7), spacing=(2.0, 2.0, 2.0)).triangulate()
    grid = grid.cast_to_unstructured_grid()
    skin = pv.Sphere(radius=7.0, center=(6.0, 6.0, 6.0), theta_resolution=12, phi_resolution=12)
    x = np.asarray(grid.points)
    op = sweeps._skin_mapping(grid, skin.points)
    curved = np.c_[np.sin(x[:, 0] / 5), x[:, 1] ** 2 / 50, np.cos(x[:, 2] / 3)]
    g = grid.copy()
    g.point_data[arrays.DISPLACEMENT] = curved
    np.testing.assert_allclose(op(curved), map_to_surface(g, skin)[arrays.DISPLACEMENT],
                               rtol=0, atol=1e-12)
    affine = x @ np.array([[0.1, 0.02, 0.0], [0.0, -0.05, 0.03], [0.01, 0.0, 0.08]]) + 0.5
    expected = np.asarray(skin.points) @ np.array([[0.1, 0.02, 0.0], [0.0, -0.05, 0.03],
                                                   [0.01, 0.0, 0.08]]) + 0.5
    assert (np.linalg.norm(skin.points - 6.0, axis=1) > 6.0).any()  # partly outside the grid
    np.testing.assert_allclose(op(affine), expected, atol=1e-9)
    with pytest.raises(ValueError, match="mapping"):
        sweeps._skin_mapping(grid, skin.points, mapping="nearest")
    with pytest.raises(ValueError, match="mapping"):
        sweeps.PipelineEvaluation(mapping="nearest")
    _need_mtm()
    state = _squeezed_cube()
    ev = sweeps.PipelineEvaluation()
    ev.evaluate(state, nu=0.0)
    ev.evaluate(state, nu=0.3)
    assert list(state["mappings"]) == [("interpolate", None)]  # one operator for the mesh
    assert isinstance(state["mappings"][("interpolate", None)], Transfer)
    with pytest.raises(ValueError, match="sigma applies to mapping='gaussian'"):
        ev.evaluate(state, nu=0.0, sigma=2.0)
    gauss = sweeps.PipelineEvaluation(mapping="gaussian")
    gauss.evaluate(state, nu=0.0, sigma=1.5)
    assert isinstance(state["mappings"][("gaussian", 1.5)], SurfaceMapping)
    assert ev.identity()["mapping"] == "interpolate" != gauss.identity()["mapping"]


def test_truth_surface_distance_equals_distance_to():
    """The cropped, once-oriented truth measures the exact distances distance_to measures
    (both orientations of the truth's winding), for points near the face it was cropped to."""
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters import distance_to

    truth = pv.ParametricEllipsoid(70, 95, 110, u_res=80, v_res=80).triangulate().clean()
    assert truth.n_open_edges == 0
    face = np.asarray(truth.points)[truth.points[:, 1] > 60]
    rng = np.random.default_rng(0)
    query = face + rng.normal(0.0, 2.0, face.shape)
    ref = np.asarray(distance_to(pv.PolyData(query), truth)[arrays.DISTANCE])
    for surface in (truth, truth.flip_faces()):
        t = sweeps._TruthSurface(surface, face, margin=20.0)
        assert t.closed and t.surface.n_points < 0.6 * truth.n_points  # cropped
        np.testing.assert_allclose(t.distance(query), ref, atol=1e-9)
    assert (ref > 0).any() and (ref < 0).any()  # both signs were exercised


def test_truth_surface_falls_back_for_an_open_truth():
    import pyvista as pv

    from pvcmf import arrays
    from pvcmf.filters import distance_to

    cap = pv.Sphere(radius=50.0, theta_resolution=60, phi_resolution=60).clip("y", invert=False)
    query = np.asarray(cap.points)[::7] * 1.02
    t = sweeps._TruthSurface(cap, query, margin=10.0)
    assert not t.closed
    ref = np.asarray(distance_to(pv.PolyData(query), cap)[arrays.DISTANCE])
    np.testing.assert_allclose(t.distance(query), ref, atol=1e-12)


def test_cache_identity_ignores_figure_code_but_not_pipeline_code(monkeypatch):
    """Editing figure or CLI code keeps cached sweeps; the pipeline's sources are in the key."""
    assert "figures" not in sweeps.RESULT_SOURCES and "cli.py" not in sweeps.RESULT_SOURCES
    assert {"filters", "mtm", "datasets", "pipeline.py"} <= set(sweeps.RESULT_SOURCES)
    before = sweeps.PipelineEvaluation().identity()
    monkeypatch.setitem(sweeps._SOURCE_HASHES, sweeps.RESULT_SOURCES, "changed")
    after = sweeps.PipelineEvaluation().identity()
    assert before["code"] != after["code"] == "changed"
    assert sweeps.code_version() == pvcmf.__version__


def test_study_settings_from_environment(monkeypatch, tmp_path):
    for name in ("PVCMF_GALLERY_OUT", "PVCMF_SYNTHETIC", "PVCMF_SCHEDULER", "PVCMF_STUDY_PATIENTS",
                 "PVCMF_STUDY_SPACING", "PVCMF_STUDY_TRUTH_TETS"):
        monkeypatch.delenv(name, raising=False)
    s = ps.study_settings(tmp_path)
    assert s["out"] == tmp_path / "_out" and s["patients"] == [1, 2, 3, 4]
    assert s["study"] == {"spacing": pvcmf.sweeps.STUDY_SPACING, "truth_tets": 16_000}
    assert not s["synthetic"] and s["scheduler"] is None
    monkeypatch.setenv("PVCMF_STUDY_PATIENTS", "2,4")
    monkeypatch.setenv("PVCMF_STUDY_SPACING", "3")
    monkeypatch.setenv("PVCMF_STUDY_TRUTH_TETS", "4000")
    monkeypatch.setenv("PVCMF_SYNTHETIC", "1")
    s = ps.study_settings(tmp_path)
    assert s["patients"] == [2, 4] and s["study"] == {"spacing": 3.0, "truth_tets": 4000}
    assert s["synthetic"] and s["title"] == "synthetic evaluation"
