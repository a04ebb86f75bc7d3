"""Every wrong input to a public entry point is refused with a clear pvcmf error.

Each case feeds one bad value (NaN/inf points, zero spacing, unknown labels, an empty
dataset, an out-of-range option, a bad output path, ...) on a tiny dataset and checks
that a ``ValueError`` or ``TypeError`` is raised *by pvcmf* (the raising frame lies in
the package, not in numpy/scipy/VTK) with a message naming the parameter; CLI cases
check exit status 2 and the message. Property-based cases (hypothesis) feed random
non-finite or degenerate data and accept only a clear error or finite output.
"""

from __future__ import annotations

import traceback
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays, filters, mtm
from pvcmf.cli import main
from pvcmf.filters.distance import distance_to, signed_distance
from pvcmf.filters.registration import register
from pvcmf.plan import Osteotomy, Plan, read_plan

PKG = str(Path(pvcmf.__file__).resolve().parent)


# --------------------------------------------------------------------------- tiny data
def sphere(radius=10.0, nan=0, value=np.nan):
    s = pv.Sphere(radius=radius, theta_resolution=12, phi_resolution=12)
    if nan:
        s.points[:nan] = value
    return s


def labels(spacing=(1.0, 1.0, 1.0), origin=(-5.0, -5.0, -5.0)):
    img = pv.ImageData(dimensions=(11, 11, 11), origin=origin, spacing=spacing)
    inner = (np.abs(img.points) <= 2).all(axis=1)
    img[arrays.BONE] = np.where(inner, arrays.MANDIBLE, 0).astype(np.uint8)
    img[arrays.TISSUE] = np.where(inner, arrays.BONE_TISSUE, arrays.FAT).astype(np.uint8)
    return img


def shell():
    img = labels()
    soft = ~(np.abs(img.cell_centers().points) < 2).all(axis=1)
    return img.extract_cells(np.flatnonzero(soft)).triangulate()


PLAN = Plan((Osteotomy("mandible", (0.0, 0.0, 1.0)),))


def tissue_grid(**cell):
    grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    grid.cell_data[arrays.TISSUE] = np.full(grid.n_cells, arrays.FAT, dtype=np.uint8)
    for name, value in cell.items():
        grid.cell_data[name] = value(grid.n_cells) if callable(value) else value
    return grid


def muscle_grid(fiber):
    grid = tissue_grid()
    grid.cell_data[arrays.TISSUE] = np.full(grid.n_cells, arrays.MUSCLE_TISSUE, dtype=np.uint8)
    f = np.tile([0.0, 0.0, 1.0], (grid.n_cells, 1))
    f[0] = fiber
    grid.cell_data[arrays.FIBER] = f
    return grid


def solvable(nu=0.3, E=1.0, bc=None, disp=None, normal=None):
    grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    grid.cell_data[arrays.E_FIBER] = np.full(grid.n_cells, E, dtype=float)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, nu, dtype=float)
    boundary = np.any((grid.points == 0) | (grid.points == 2), axis=1)
    code = np.where(boundary, arrays.BC_JOINT, arrays.BC_FREE).astype(np.int8)
    grid.point_data[arrays.BC] = code if bc is None else bc(code)
    d = 0.01 * np.asarray(grid.points)
    grid.point_data[arrays.BC_DISPLACEMENT] = d if disp is None else disp(d)
    if normal is not None:
        grid.point_data[arrays.BC_NORMAL] = normal(np.zeros((grid.n_points, 3)))
    return grid


def _set(a, index, value):
    a = np.array(a)
    a[index] = value
    return a


def _plan_file(tmp, text):
    path = Path(tmp) / "plan.toml"
    path.write_text(text)
    return path


# --------------------------------------------------------------------------- cases
# (id, callable(tmp_path), words the message must contain)
CASES = [
    # distance
    ("distance actual NaN", lambda t: distance_to(sphere(11), sphere(nan=3)), "actual"),
    ("distance actual inf", lambda t: distance_to(sphere(11), sphere(nan=1, value=np.inf)),
     "actual"),
    ("distance pred NaN", lambda t: distance_to(sphere(11, nan=2), sphere()), "pred"),
    ("distance actual grid", lambda t: distance_to(sphere(), shell()), "actual"),
    ("distance actual empty", lambda t: distance_to(sphere(), pv.PolyData()), "actual"),
    ("distance actual no faces", lambda t: distance_to(sphere(), pv.PolyData(np.eye(3))),
     "actual"),
    ("distance pred array", lambda t: distance_to(np.zeros((3, 3)), sphere()), "pred"),
    ("distance pred empty", lambda t: distance_to(pv.PolyData(), sphere()), "pred"),
    ("distance method", lambda t: distance_to(sphere(), sphere(), method="kd"), "method"),
    ("distance apart", lambda t: distance_to(sphere().translate((99, 0, 0)), sphere(),
                                             max_distance=1.0), "max_distance"),
    ("signed query NaN", lambda t: signed_distance([[np.nan, 0, 0]], sphere()), "query"),
    ("signed query shape", lambda t: signed_distance(np.zeros((4, 2)), sphere()), "query"),
    # registration
    ("register source NaN", lambda t: register(sphere(nan=3), sphere()), "source"),
    ("register target NaN", lambda t: register(sphere(), sphere(nan=3)), "target"),
    ("register few points", lambda t: register(pv.PolyData(np.eye(3)), sphere()), "source"),
    ("register trim 0", lambda t: register(sphere(), sphere(), trim=0.0), "trim"),
    ("register trim 2", lambda t: register(sphere(), sphere(), trim=2.0), "trim"),
    ("register iterations", lambda t: register(sphere(), sphere(), max_iterations=0),
     "max_iterations"),
    ("register initial NaN", lambda t: register(sphere(), sphere(),
                                                initial=np.full((4, 4), np.nan)), "initial"),
    ("register initial shape", lambda t: register(sphere(), sphere(), initial=np.eye(3)),
     "initial"),
    ("register source array", lambda t: register(np.zeros((9, 3)), sphere()), "source"),
    ("register region", lambda t: register(sphere(), sphere(), region="face"), "region"),
    ("register closest", lambda t: register(sphere(), sphere(), closest="edge"), "closest"),
    # materials
    ("materials grid type", lambda t: filters.assign_materials(sphere()), "grid"),
    ("materials label 7", lambda t: filters.assign_materials(
        tissue_grid(tissue=lambda n: _set(np.full(n, 1, np.uint8), 0, 7))), "7"),
    ("materials label 200", lambda t: filters.assign_materials(
        tissue_grid(tissue=lambda n: _set(np.full(n, 1, np.uint8), 1, 200))), "200"),
    ("materials fibre NaN", lambda t: filters.assign_materials(
        muscle_grid([np.nan, 0.0, 1.0])), arrays.FIBER),
    ("materials fibre inf", lambda t: filters.assign_materials(
        muscle_grid([np.inf, 0.0, 0.0])), arrays.FIBER),
    ("materials fraction 1.5", lambda t: filters.assign_materials(
        tissue_grid(muscle_fraction=lambda n: np.full(n, 1.5))), arrays.MUSCLE_FRACTION),
    ("materials fraction NaN", lambda t: filters.assign_materials(
        tissue_grid(muscle_fraction=lambda n: np.full(n, np.nan))), arrays.MUSCLE_FRACTION),
    ("materials default_fiber NaN", lambda t: filters.assign_materials(
        _drop(muscle_grid([0, 0, 1.0]), arrays.FIBER), default_fiber=(np.nan, 0, 1)),
     "default_fiber"),
    ("materials default_fiber shape", lambda t: filters.assign_materials(
        _drop(muscle_grid([0, 0, 1.0]), arrays.FIBER), default_fiber=(1, 0)), "default_fiber"),
    ("materials no fibre", lambda t: filters.assign_materials(
        _drop(muscle_grid([0, 0, 1.0]), arrays.FIBER)), arrays.FIBER),
    ("materials table", lambda t: filters.assign_materials(tissue_grid(), table="nope"),
     "nope"),
    ("materials no tissue", lambda t: filters.assign_materials(
        pv.ImageData(dimensions=(2, 2, 2)).triangulate()), arrays.TISSUE),
    # MTM
    ("solve no bc", lambda t: mtm.solve(_drop(solvable(), arrays.BC)), arrays.BC),
    ("solve bc code 9", lambda t: mtm.solve(solvable(bc=lambda c: _set(c, 0, 9))), arrays.BC),
    ("solve bc_displacement NaN", lambda t: mtm.solve(
        solvable(disp=lambda d: _set(d, 0, np.nan))), arrays.BC_DISPLACEMENT),
    ("solve E negative", lambda t: mtm.solve(solvable(E=-1.0)), "E"),
    ("solve E NaN", lambda t: mtm.solve(solvable(E=np.nan)), "E"),
    ("solve nu 0.5", lambda t: mtm.solve(solvable(nu=0.5)), "nu"),
    ("solve nu NaN", lambda t: mtm.solve(solvable(nu=np.nan)), "nu"),
    ("solve method", lambda t: mtm.solve(solvable(), method="lu"), "method"),
    ("solve tol", lambda t: mtm.solve(solvable(), tol=-1.0), "tol"),
    ("solve sliding normal zero", lambda t: mtm.solve(solvable(
        bc=lambda c: _set(c, 0, arrays.BC_SLIDING), normal=lambda n: n)), arrays.BC_NORMAL),
    ("solve rigid mode", lambda t: mtm.solve(solvable(bc=lambda c: np.zeros_like(c))),
     "rigid"),
    ("solve array", lambda t: mtm.solve(np.zeros((3, 3))), arrays.BC),
    # boundary conditions
    ("apply_plan grid type", lambda t: filters.apply_plan(sphere(), PLAN, labels()), "grid"),
    ("apply_plan plan dict", lambda t: filters.apply_plan(shell(), {"mandible": 1}, labels()),
     "plan"),
    ("apply_plan bones None", lambda t: filters.apply_plan(shell(), PLAN), "bones"),
    ("apply_plan zero spacing", lambda t: filters.apply_plan(
        shell(), PLAN, labels(spacing=(1.0, 0.0, 1.0))), "spacing"),
    ("apply_plan NaN origin", lambda t: filters.apply_plan(
        shell(), PLAN, labels(origin=(np.nan, 0.0, 0.0))), "origin"),
    ("apply_plan depth -1", lambda t: filters.apply_plan(shell(), PLAN, labels(),
                                                         posterior_depth=-1), "posterior_depth"),
    ("apply_plan depth NaN", lambda t: filters.apply_plan(
        shell(), PLAN, labels(), posterior_depth=np.nan), "posterior_depth"),
    ("apply_plan contact 0", lambda t: filters.apply_plan(shell(), PLAN, labels(),
                                                          contact_distance=0), "contact_distance"),
    ("apply_plan sigma -1", lambda t: filters.apply_plan(shell(), PLAN, labels(),
                                                         normal_sigma=-1), "normal_sigma"),
    ("apply_plan teeth_margin NaN", lambda t: filters.apply_plan(
        shell(), PLAN, labels(), teeth_margin=np.nan), "teeth_margin"),
    ("apply_plan release -1", lambda t: filters.apply_plan(
        shell(), PLAN, labels(), release_margin=-1.0), "release_margin"),
    ("apply_plan release str", lambda t: filters.apply_plan(
        shell(), PLAN, labels(), release_margin="far"), "release_margin"),
    ("apply_plan grid NaN", lambda t: filters.apply_plan(_nan_points(shell()), PLAN, labels()),
     "grid"),
    ("apply_plan no tissue", lambda t: filters.apply_plan(
        shell(), PLAN, _drop(labels(), arrays.TISSUE)), arrays.TISSUE),
    # plan
    ("plan translation 1000", lambda t: Osteotomy("maxilla", (1000.0, 0, 0)), "translation"),
    ("plan translation -51", lambda t: Osteotomy("maxilla", (0, -51.0, 0)), "50"),
    ("plan rotation 45", lambda t: Osteotomy("maxilla", rotation=(45.0, 0, 0)), "rotation"),
    ("plan translation NaN", lambda t: Osteotomy("maxilla", (np.nan, 0, 0)), "translation"),
    ("plan segment", lambda t: Osteotomy("femur", (1, 0, 0)), "segment"),
    ("plan translation 2 values", lambda t: Osteotomy("maxilla", (1.0, 2.0)), "translation"),
    ("plan pivot NaN", lambda t: Osteotomy("maxilla", pivot=(np.nan, 0, 0)), "pivot"),
    ("plan cut normal zero", lambda t: Osteotomy("maxilla", cut=(((0, 0, 0), (0, 0, 0)),)),
     "cut"),
    ("plan file unknown key", lambda t: read_plan(_plan_file(
        t, '[[osteotomy]]\nsegment = "maxilla"\ntranslaton = [1, 0, 0]\n')), "translaton"),
    ("plan file translation 1000", lambda t: read_plan(_plan_file(
        t, '[[osteotomy]]\nsegment = "maxilla"\ntranslation = [0, 0, 1000]\n')), "translation"),
    ("plan file syntax", lambda t: read_plan(_plan_file(t, "[[osteotomy]\n")), "plan"),
    ("plan file nan", lambda t: read_plan(_plan_file(
        t, '[[osteotomy]]\nsegment = "maxilla"\ntranslation = [nan, 0, 0]\n')), "translation"),
    # meshing (input checks) and the other image filters
    ("tetrahedralize zero spacing", lambda t: filters.tetrahedralize(
        labels(spacing=(0.0, 1.0, 1.0))), "spacing"),
    ("tetrahedralize inf spacing", lambda t: filters.tetrahedralize(
        labels(spacing=(np.inf, 1.0, 1.0))), "spacing"),
    ("tetrahedralize n_tets 10", lambda t: filters.tetrahedralize(labels(), n_tets=10),
     "n_tets"),
    ("tetrahedralize n_tets float", lambda t: filters.tetrahedralize(labels(), n_tets=1.5),
     "n_tets"),
    ("tetrahedralize grid", lambda t: filters.tetrahedralize(shell()), "labels"),
    ("tetrahedralize float labels", lambda t: filters.tetrahedralize(
        _retype(labels(), arrays.TISSUE, np.float32)), arrays.TISSUE),
    ("cut_bones plan dict", lambda t: filters.cut_bones(labels(), {"mandible": 1}), "plan"),
    ("move_bones output", lambda t: filters.move_bones(labels(), PLAN, output="stl"),
     "output"),
    ("face_box fraction", lambda t: pvcmf.pipeline.face_box(labels(), 2.0), "face_fraction"),
    ("simulate n_tets", lambda t: pvcmf.pipeline.simulate(pv.ImageData(), PLAN, n_tets=0),
     "n_tets"),
    ("simulate out empty", lambda t: pvcmf.pipeline.simulate(pv.ImageData(), PLAN, ""), "out"),
    ("simulate out file", lambda t: pvcmf.pipeline.simulate(
        pv.ImageData(), PLAN, _file(t)), "out"),
    ("simulate out foreign folder", lambda t: pvcmf.pipeline.simulate(
        pv.ImageData(), PLAN, _foreign(t)), "summary.json"),
]


def _drop(ds, name):
    for data in (ds.point_data, ds.cell_data):
        if name in data.keys():
            data.remove(name)
    return ds


def _retype(ds, name, dtype):
    ds.point_data[name] = np.asarray(ds.point_data[name]).astype(dtype)
    return ds


def _nan_points(ds):
    ds.points[0] = np.nan
    return ds


def _file(tmp):
    path = Path(tmp) / "a_file"
    path.write_text("x")
    return path


def _foreign(tmp):
    folder = Path(tmp) / "photos"
    folder.mkdir(exist_ok=True)
    (folder / "holiday.jpg").write_text("x")
    return folder


def _raised_in_pvcmf(err):
    """The frame that raised ``err`` lies in the pvcmf package."""
    frames = traceback.extract_tb(err.__traceback__)
    return bool(frames) and str(Path(frames[-1].filename).resolve()).startswith(PKG)


@pytest.mark.parametrize("case, words", [(c[1], c[2]) for c in CASES],
                         ids=[c[0] for c in CASES])
def test_bad_input_is_refused_clearly(case, words, tmp_path):
    with pytest.raises((ValueError, TypeError)) as info:
        case(tmp_path)
    err = info.value
    assert _raised_in_pvcmf(err), f"raised outside pvcmf: {type(err).__name__}: {err}"
    assert words.lower() in str(err).lower(), str(err)


# --------------------------------------------------------------------------- CLI
CLI_CASES = [
    ("demo --out empty", lambda t: ["demo", "--out", ""], "--out"),
    ("demo --out file", lambda t: ["demo", "--out", str(_file(t))], "--out"),
    ("demo --out under file", lambda t: ["demo", "--out", str(_file(t) / "x")], "--out"),
    ("demo --out foreign", lambda t: ["demo", "--out", str(_foreign(t))], "--out"),
    ("demo --out /proc", lambda t: ["demo", "--out", "/proc/pvcmf-out"], "--out"),
    ("demo --spacing 0", lambda t: ["demo", "--out", str(t / "o"), "--spacing", "0"], "spacing"),
    ("demo --n-tets -1", lambda t: ["demo", "--out", str(t / "o"), "--n-tets", "-1"], "n-tets"),
    ("demo --patient 9", lambda t: ["demo", "--out", str(t / "o"), "--patient", "9"], "patient"),
    ("simulate plan 1000 mm", lambda t: [
        "simulate", "--ct", str(t / "ct.nrrd"), "--out", str(t / "o"), "--plan",
        str(_plan_file(t, '[[osteotomy]]\nsegment = "maxilla"\ntranslation = [1000, 0, 0]\n'))],
     "translation"),
    ("simulate plan missing", lambda t: [
        "simulate", "--ct", str(t / "ct.nrrd"), "--out", str(t / "o"), "--plan",
        str(t / "none.toml")], "none.toml"),
    ("simulate --out file", lambda t: [
        "simulate", "--ct", "x", "--plan", "p.toml", "--out", str(_file(t))], "--out"),
    ("sweep --out folder", lambda t: [
        "sweep", "--grid", "e_ratio=1", "--out", str(t)], "--out"),
    ("sweep --out suffix", lambda t: [
        "sweep", "--grid", "e_ratio=1", "--out", str(t / "table.txt")], "--out"),
]


@pytest.mark.parametrize("argv, words", [(c[1], c[2]) for c in CLI_CASES],
                         ids=[c[0] for c in CLI_CASES])
def test_cli_refuses_bad_input_before_work(argv, words, tmp_path, capsys):
    try:
        code = main(argv(tmp_path))
    except SystemExit as exit_:  # argparse
        code = exit_.code
    err = capsys.readouterr().err
    assert code == 2, err
    assert words.lower() in err.lower(), err
    assert "Traceback" not in err
    assert not (tmp_path / "o").exists()


#: the count reported in docs/guide/reliability.md
N_BAD_INPUTS = len(CASES) + len(CLI_CASES)


def test_the_suite_covers_at_least_80_bad_inputs():
    assert N_BAD_INPUTS >= 80


# --------------------------------------------------------------------------- properties
# random data from a seeded generator (the same cases on every run): any of NaN, +-inf,
# huge, zero or ordinary values, empty and degenerate datasets
SPECIAL = np.array([np.nan, np.inf, -np.inf, 0.0, 1e300, -1e300, 1.0, -3.5])


def _random_values(rng, shape):
    values = rng.normal(0.0, 20.0, size=shape)
    mask = rng.random(shape) < 0.3
    values[mask] = rng.choice(SPECIAL, size=int(mask.sum()))
    return values


def _clear_error_or(check, func):
    try:
        out = func()
    except (ValueError, TypeError) as err:
        assert _raised_in_pvcmf(err), f"{type(err).__name__}: {err}"
        return "refused"
    check(out)
    return "finite"


@pytest.mark.parametrize("seed", range(40))
def test_distance_to_random_points_clear_error_or_finite(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 12))
    pred = pv.PolyData(_random_values(rng, (n, 3))) if n else pv.PolyData()
    actual = sphere()
    if rng.random() < 0.5:
        actual.points[rng.integers(0, actual.n_points)] = rng.choice(SPECIAL)
    _clear_error_or(lambda out: np.testing.assert_array_equal(
        np.isfinite(out[arrays.DISTANCE]), True), lambda: distance_to(pred, actual))


@pytest.mark.parametrize("seed", range(30))
def test_assign_materials_random_labels_and_fibres(seed):
    rng = np.random.default_rng(seed)
    grid = muscle_grid(_random_values(rng, 3))
    tissue = np.asarray(grid.cell_data[arrays.TISSUE]).copy()
    k = int(rng.integers(0, 4))
    tissue[:k] = rng.integers(0, 256, size=k)
    grid.cell_data[arrays.TISSUE] = tissue

    def finite(out):
        for name in (arrays.E_FIBER, arrays.E_CROSS, arrays.NU, arrays.FIBER):
            assert np.all(np.isfinite(out.cell_data[name]))

    _clear_error_or(finite, lambda: filters.assign_materials(grid))


@pytest.mark.parametrize("seed", range(30))
def test_plan_random_moves_clear_error_or_bounded(seed):
    rng = np.random.default_rng(seed)
    translation, rotation = _random_values(rng, 3), _random_values(rng, 3) / 2

    def bounded(osteotomy):
        assert max(abs(v) for v in osteotomy.translation) <= 50.0
        assert max(abs(v) for v in osteotomy.rotation) <= 30.0
        assert np.all(np.isfinite(osteotomy.matrix() if callable(getattr(
            osteotomy, "matrix", None)) else 0.0))

    _clear_error_or(bounded, lambda: Osteotomy("maxilla", translation, rotation))


@pytest.mark.parametrize("seed", range(20))
def test_register_random_clouds_clear_error_or_finite(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 40))
    source = pv.PolyData(_random_values(rng, (n, 3))) if n else pv.PolyData()

    def finite(out):
        assert np.all(np.isfinite(out.points))

    _clear_error_or(finite, lambda: register(source, sphere(), max_iterations=3))
