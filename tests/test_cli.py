"""The ``pvcmf`` command line and the end-to-end pipeline: outputs, errors, atomic writing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.cli import main
from pvcmf.pipeline import STEPS, Result, simulate, write_outputs
from pvcmf.plan import TABLE_II, Osteotomy, Plan

ROOT = Path(__file__).resolve().parents[1]


def test_help_and_argument_errors(capsys):
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    assert "simulate" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["demo"])  # --out is required
    assert info.value.code == 2
    with pytest.raises(SystemExit):
        main(["demo", "--out", "x", "--n-tets", "-5"])
    assert "positive integer" in capsys.readouterr().err


def test_bad_plan_file_fails_cleanly_before_anything_is_written(tmp_path, capsys):
    plan = tmp_path / "plan.toml"
    plan.write_text('[[osteotomy]]\nsegment = "maxilla"\nrotation = [0, 90, 0]\n')
    out = tmp_path / "out"
    code = main(["simulate", "--ct", str(tmp_path / "ct.nrrd"), "--plan", str(plan),
                 "--out", str(out), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert "plan.toml" in err and "rotation must be within" in err
    assert not out.exists()


def _small_result():
    skin = pv.Sphere(radius=10.0, theta_resolution=12, phi_resolution=12)
    grid = pv.ImageData(dimensions=(4, 4, 4), spacing=(3.0,) * 3).triangulate()
    grid.point_data[arrays.DISPLACEMENT] = np.tile([0.0, 1.0, 0.0], (grid.n_points, 1))
    skin.point_data[arrays.DISPLACEMENT] = np.tile([0.0, 1.0, 0.0], (skin.n_points, 1))
    return Result(plan=TABLE_II[4], post=grid, skin_pre=skin, skin_post=skin,
                  timings={"solve": 0.1})


def test_write_outputs(tmp_path):
    files = write_outputs(_small_result(), tmp_path, {"face_post.png": np.zeros((8, 8, 3), np.uint8)})
    assert {"predicted_skin", "skin_pre", "deformed_mesh", "face_post", "summary"} <= set(files)
    mesh = pv.read(files["deformed_mesh"])
    start = pv.ImageData(dimensions=(4, 4, 4), spacing=(3.0,) * 3).points
    np.testing.assert_allclose(mesh.points, start + [0.0, 1.0, 0.0])  # deformed
    summary = json.loads(files["summary"].read_text())
    assert summary["plan"] == TABLE_II[4].to_dict() and summary["complete"]
    assert summary["max_displacement_mm"] == pytest.approx(1.0)


def test_interrupted_write_leaves_no_partial_file(tmp_path, monkeypatch):
    """An exception in the middle of writing the mesh: no .vtu, no temporary file left."""
    real_save = pv.UnstructuredGrid.save

    def crash(self, filename, *args, **kwargs):
        Path(filename).write_bytes(b"<VTKFile half written")
        raise KeyboardInterrupt

    monkeypatch.setattr(pv.UnstructuredGrid, "save", crash)
    with pytest.raises(KeyboardInterrupt):
        write_outputs(_small_result(), tmp_path)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "deformed_mesh.vtu" not in names
    assert not [n for n in names if ".part" in n], names
    # what was finished before the interruption is complete and readable
    assert pv.read(tmp_path / "predicted_skin.vtp").n_points > 0
    monkeypatch.setattr(pv.UnstructuredGrid, "save", real_save)


def test_simulate_validates_before_running(tmp_path):
    with pytest.raises(TypeError, match="plan must be a pvcmf.Plan"):
        simulate(pv.ImageData(), {"maxilla": 1}, tmp_path / "o")
    with pytest.raises(ValueError, match="n_tets must be a positive integer"):
        simulate(pv.ImageData(), TABLE_II[1], n_tets=0)
    with pytest.raises(ValueError, match="face_fraction"):
        simulate(pv.ImageData(), TABLE_II[1], face_fraction=2.0)
    with pytest.raises(ValueError, match="no point array 'ct'"):
        simulate(pv.ImageData(dimensions=(3, 3, 3)), TABLE_II[1])
    assert not (tmp_path / "o").exists()


def test_simulate_without_mesh_draws_the_plan(tmp_path):
    """Given labels and no mesh step, the pipeline still writes the skin and the plan."""
    from test_boundary_conditions import synthetic_head

    labels, _ = synthetic_head()
    res = simulate(None, Plan((Osteotomy("mandible", (0, 0, 3.0)),)), tmp_path, labels=labels,
                   muscles=False, predict=False, figures=True)
    assert res.skeleton is not None and res.skin_pre is not None
    for name in ("skin_pre.vtp", "osteotomy.png", "face_pre.png", "summary.json"):
        assert (tmp_path / name).is_file(), name
    assert set(res.timings) >= {"skin", "skeleton", "figures", "write"}


def _run(argv, capsys):
    """Run the CLI with tracebacks on (-vv) and return (exit code, stdout)."""
    code = main(argv + ["-vv"])
    return code, capsys.readouterr().out


def test_classification_is_on_unless_no_classify(tmp_path, capsys, monkeypatch):
    """``demo`` and ``simulate`` classify fat/muscle by default; ``--no-classify`` turns it
    off; ``--classify`` (the default) is accepted. summary.json says which ran."""
    from pvcmf.cli import build_parser

    parser = build_parser()
    for command in (["demo"], ["simulate", "--ct", "c", "--plan", "p.toml"]):
        base = command + ["--out", "o"]
        assert parser.parse_args(base).classify is True
        assert parser.parse_args(base + ["--classify"]).classify is True
        assert parser.parse_args(base + ["--no-classify"]).classify is False
    for flags, classified in (([], True), (["--no-classify"], False)):
        out = tmp_path / ("on" if classified else "off")
        code, text = _run(["demo", "--out", str(out), "--spacing", "4", "--no-predict",
                           "--no-progress", "--no-figures", "--no-report"] + flags, capsys)
        assert code == 0, text
        summary = json.loads((out / "summary.json").read_text())
        assert summary["classified"] is classified
        assert ("classify" in summary["seconds"]) is classified
        assert ("classify" in summary["skipped"]) is not classified


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path, capsys):
    # muscles off: the atlas fit is tested in test_muscles.py and costs ~30 s here
    code, out = _run(["demo", "--out", str(tmp_path), "--spacing", "3", "--n-tets", "6000",
                      "--no-progress", "--no-muscles", "--patient", "3"], capsys)
    assert code == 0, out
    assert "seconds per step" in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    for name in ("face_pre.png", "osteotomy.png", "skin_pre.vtp"):
        assert (tmp_path / name).is_file()
    assert summary["complete"], summary["skipped"]
    for name in ("predicted_skin.vtp", "deformed_mesh.vtu", "face_post.png",
                 "displacement.png"):
        assert (tmp_path / name).is_file()
    skin = pv.read(tmp_path / "predicted_skin.vtp")
    u = np.linalg.norm(skin[arrays.DISPLACEMENT], axis=1)
    assert 0.5 < u.max() < 12.0  # Table II moves patient 3's mandible by ~5.6 mm
    # the chin moves forward with the mandible (+5.47 mm anterior), the forehead stays
    pts = skin.points
    chin = pts[:, 2] < np.percentile(pts[:, 2], 15)
    front = pts[:, 1] > np.percentile(pts[:, 1], 80)
    assert np.median(skin[arrays.DISPLACEMENT][chin & front, 1]) > 1.0
    top = pts[:, 2] > np.percentile(pts[:, 2], 85)
    assert np.abs(skin[arrays.DISPLACEMENT][top]).max() < 0.5


def test_headsq_plan_cuts_and_draws(data_dir, tmp_path, capsys):
    """The real CT with the example plan: segmentation, Le Fort I + BSSO cuts, figures."""
    nhdr = data_dir / "headsq" / "quarter.nhdr"
    if not nhdr.is_file():
        pytest.skip(f"{nhdr} not found")
    code = main(["simulate", "--ct", str(nhdr), "--plan", str(ROOT / "examples" / "headsq_plan.toml"),
                 "--out", str(tmp_path), "--no-progress", "--offset", "-1000", "--flip", "yz",
                 "--no-predict"])
    assert code == 0, capsys.readouterr()
    for name in ("skin_pre.vtp", "face_pre.png", "osteotomy.png", "summary.json"):
        assert (tmp_path / name).is_file(), name
    skin = pv.read(tmp_path / "skin_pre.vtp")
    # the face looks forward: the nose tip (most anterior skin point) is in the upper half
    tip = skin.points[np.argmax(skin.points[:, 1])]
    assert tip[2] > np.mean(skin.bounds[4:6]) - 10


@pytest.mark.slow
def test_simulate_headsq(data_dir, tmp_path, capsys):
    nhdr = data_dir / "headsq" / "quarter.nhdr"
    if not nhdr.is_file():
        pytest.skip(f"{nhdr} not found")
    code, out = _run(
        ["simulate", "--ct", "headsq", "--plan", str(ROOT / "examples" / "headsq_plan.toml"),
         "--out", str(tmp_path), "--n-tets", "15000", "--no-progress", "--no-muscles"], capsys)
    assert code == 0, out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["complete"], summary["skipped"]
    for name in ("predicted_skin.vtp", "deformed_mesh.vtu", "skin_pre.vtp", "face_pre.png",
                 "face_post.png", "displacement.png", "osteotomy.png"):
        assert (tmp_path / name).is_file(), name
    mesh = pv.read(tmp_path / "deformed_mesh.vtu")
    assert mesh.n_cells == summary["n_tets"] and arrays.BC in mesh.point_data
    # the chin follows the 5 mm mandibular advancement, the skull top does not move
    skin = pv.read(tmp_path / "predicted_skin.vtp")
    pts, u = skin.points - skin[arrays.DISPLACEMENT], skin[arrays.DISPLACEMENT]
    low = pts[:, 2] < np.percentile(pts[:, 2], 25)  # the skin is the face box's: the front
    chin = low & (pts[:, 1] > np.percentile(pts[low, 1], 85))  # of its lowest quarter
    assert 1.0 < np.median(u[chin, 1]) < 6.0
    top = pts[:, 2] > np.percentile(pts[:, 2], 90)
    assert np.abs(u[top]).max() < 0.5


def test_drop_floating_parts():
    """A mesh island without constraints is removed; held parts and their arrays stay."""
    from pvcmf.pipeline import drop_floating_parts

    held = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    island = held.translate((10.0, 0.0, 0.0), inplace=False)
    grid = held.merge(island, merge_points=False)
    bc = np.zeros(grid.n_points, dtype=np.int8)
    bc[grid.points[:, 0] < 0.5] = arrays.BC_FIXED
    grid.point_data[arrays.BC] = bc
    out = drop_floating_parts(grid)
    assert out.n_points == held.n_points and out.n_cells == held.n_cells
    assert out.points[:, 0].max() <= 2.0
    np.testing.assert_array_equal(np.sort(out[arrays.BC]), np.sort(bc[grid.points[:, 0] <= 2.0]))
    assert drop_floating_parts(out) is out  # nothing to drop: the same mesh


def test_drop_floating_parts_drops_a_tetrahedron_hinged_on_an_edge():
    """A tetrahedron sharing only an edge (or a vertex) with the held mesh turns about it:
    its own part, dropped, where a node graph would count it as held."""
    from pvcmf.pipeline import drop_floating_parts

    held = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    pts = np.asarray(held.points)
    a = int(np.flatnonzero((pts == [2, 2, 2]).all(axis=1))[0])
    b = int(np.flatnonzero((pts == [2, 2, 1]).all(axis=1))[0])
    new = np.vstack([pts, [[3.0, 2.0, 2.0], [3.0, 3.0, 1.5]]])
    cells = np.hstack([np.asarray(held.cells), [4, a, b, len(pts), len(pts) + 1]])
    types = np.full(held.n_cells + 1, pv.CellType.TETRA, dtype=np.uint8)
    grid = pv.UnstructuredGrid(cells, types, new)
    bc = np.zeros(grid.n_points, dtype=np.int8)
    bc[grid.points[:, 0] < 0.5] = arrays.BC_FIXED
    bc[[a, b]] = arrays.BC_FIXED  # the hinge itself held: still a line, the tet turns
    grid.point_data[arrays.BC] = bc
    out = drop_floating_parts(grid)
    assert out.n_cells == held.n_cells and out.n_points == held.n_points
    assert out.points[:, 0].max() <= 2.0


def test_flip_axes_is_a_rotation_for_two_axes():
    from pvcmf.pipeline import flip_axes

    img = pv.ImageData(dimensions=(4, 5, 6), spacing=(1.0, 2.0, 3.0))
    img["z"] = img.points[:, 2].astype(np.float32)
    img["v"] = img.points.copy()
    out = flip_axes(img, "yz")
    assert out.bounds == img.bounds
    np.testing.assert_allclose(out["z"], img.bounds[5] - img.points[:, 2])  # z reversed
    np.testing.assert_array_equal(flip_axes(out, "zy")["v"], img["v"])       # involution
    np.testing.assert_array_equal(img["z"], img.points[:, 2])                # input untouched
    with pytest.raises(ValueError, match="axes must be distinct letters"):
        flip_axes(img, "yy")
    with pytest.raises(ValueError, match="axes must be distinct letters"):
        flip_axes(img, "w")


def test_progress_bar_without_tqdm(monkeypatch, caplog):
    """Without tqdm, progress_bar=True logs every step at INFO up to the last; off, nothing."""
    import builtins
    import logging

    from test_boundary_conditions import synthetic_head

    real_import = builtins.__import__

    def no_tqdm(name, *args, **kwargs):
        if name.startswith("tqdm"):
            raise ImportError("no tqdm here")
        return real_import(name, *args, **kwargs)

    labels, _ = synthetic_head()
    plan = Plan((Osteotomy("mandible", (0, 0, 3.0)),))
    caplog.set_level(logging.INFO, logger="pvcmf")
    simulate(None, plan, labels=labels, predict=False)
    assert not [r for r in caplog.records if r.getMessage().startswith("simulate [")]
    caplog.clear()
    monkeypatch.setattr(builtins, "__import__", no_tqdm)
    simulate(None, plan, labels=labels, predict=False, progress_bar=True)
    steps = [r.getMessage() for r in caplog.records if r.getMessage().startswith("simulate [")]
    n = len(STEPS)
    assert len(steps) == n and steps[-1].startswith(f"simulate [{n}/{n}]")


def test_simulate_options_are_refused_before_the_ct_is_read(tmp_path, capsys, monkeypatch):
    """A misspelt --units, --orient, --flip or --export, or --export with --no-predict, is
    refused naming the option before the CT is read (a 1 mm DICOM folder takes seconds)
    and before anything is written."""
    import pvcmf.cli as cli

    def no_read(*args, **kwargs):
        raise AssertionError("the CT was read before the options were checked")

    monkeypatch.setattr(cli, "read_ct", no_read)
    monkeypatch.setattr(cli, "headsq", no_read)
    plan = tmp_path / "plan.toml"
    plan.write_text('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [0, 0, 3]\n')
    out = tmp_path / "out"
    base = ["simulate", "--ct", str(tmp_path / "ct.nrrd"), "--plan", str(plan), "--out",
            str(out), "--no-progress"]
    for extra, words in ((["--units", "foo"], ["--units", "'foo'"]),
                         (["--orient", "XYZ"], ["--orient", "'XYZ'"]),
                         (["--orient", "LLS"], ["--orient", "'LLS'"]),
                         (["--flip", "q"], ["--flip", "'q'"]),
                         (["--flip", "yy"], ["--flip", "'yy'"]),
                         (["--export", str(tmp_path / "model.xyz")], ["--export", "'.xyz'"])):
        with pytest.raises(SystemExit) as info:
            main(base + extra)
        assert info.value.code == 2, extra
        err = capsys.readouterr().err
        assert all(w in err for w in words), (extra, err)
    code = main(base + ["--export", str(tmp_path / "model.inp"), "--no-predict"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--export=" in err and "--no-predict" in err
    assert not out.exists() and not (tmp_path / "model.inp").exists()
    parser = cli.build_parser()
    args = parser.parse_args(base + ["--units", "-1024", "--orient", "lpi", "--flip", "YZ"])
    assert (args.units, args.orient, args.flip) == (-1024.0, "LPI", "yz")


def test_missing_plan_file_is_named(tmp_path, capsys):
    out = tmp_path / "out"
    code = main(["simulate", "--ct", "headsq", "--plan", str(tmp_path / "plan.toml"),
                 "--out", str(out), "--no-progress"])
    assert code == 2
    err = capsys.readouterr().err
    assert "plan file" in err and "plan.toml" in err and "does not exist" in err
    assert not out.exists()


def test_validate_inputs_are_named_before_any_work(tmp_path, capsys):
    skin = tmp_path / "predicted_skin.vtp"
    pv.Sphere().save(skin)
    plan = tmp_path / "plan.toml"
    plan.write_text("")
    out = tmp_path / "out"
    for argv, words in ((["--pred", str(tmp_path / "no.vtp"), "--post", str(skin)],
                         ["--pred=", "no.vtp", "does not exist"]),
                        (["--pred", str(skin), "--post", str(tmp_path / "no.stl")],
                         ["--post=", "no.stl", "does not exist"]),
                        (["--pred", str(plan), "--post", str(skin)],
                         ["--pred=", "plan.toml", ".vtp"]),
                        (["--pred", str(skin), "--post", str(skin), "--pre", str(tmp_path)],
                         ["--pre=", ".vtp"])):
        assert main(["validate", *argv, "--out", str(out), "--no-progress"]) == 2, argv
        err = capsys.readouterr().err
        assert all(w in err for w in words), (argv, err)
    with pytest.raises(SystemExit) as info:
        main(["validate", "--pred", str(skin), "--post", str(skin), "--out", str(out),
              "--region", "1,2,3"])
    assert info.value.code == 2
    assert "--region" in capsys.readouterr().err
    assert not out.exists()


def test_validate_names_the_case_by_its_run_folder():
    from pvcmf.cli import _case_name

    assert _case_name(Path("runs/female/predicted_skin.vtp")) == "female"
    assert _case_name(Path("scans/patient7_post.stl")) == "patient7_post"


def test_validate_prints_which_columns_are_signed(capsys):
    """The printed region table names the signed median and the unsigned percentiles
    (regions.csv's 'median' and 'p50' differ by the sign alone)."""
    from types import SimpleNamespace

    import pandas as pd

    from pvcmf.cli import _report_validation

    table = pd.DataFrame([{"region": "face", "n": 10, "median": -0.5, "mean_abs": 0.5,
                           "p50": 0.5, "p90": 0.9, "p95": 1.0, "within_1mm": 90.0,
                           "within_2mm": 100.0}])
    v = SimpleNamespace(table=table, registration={"rms_mm": 0.01, "converged": True},
                        files={})
    _report_validation(v)
    out = capsys.readouterr().out
    header = out.splitlines()[0]
    assert "signed median" in header and "|d| p90" in header and "% within 2 mm" in header
