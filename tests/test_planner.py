"""Tests of the interactive planner (pvcmf.planner).

* sliders <-> plan conversion against hand-written plans;
* the prepared model on a coarse virtual patient: a plan that moves nothing predicts
  nothing, the moved skeleton is the plan's rigid transform, the signed displacement is
  the normal component;
* the web page end to end: ``pvcmf plan`` serves on 127.0.0.1, headless Chromium
  (driven by Playwright) moves a slider with the keyboard, the 3D view must be non-blank
  and change, and *Save plan* must write the plan the sliders show. Skipped with the
  reason when Playwright, trame or a Chromium binary is missing.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import pyvista as pv

import pvcmf
from pvcmf import arrays
from pvcmf.plan import TABLE_II, Osteotomy, Plan, read_plan
from pvcmf.planner import PlanSliders, prepare_model, signed_displacement, slider_key
from pvcmf.planner.views import profile_segments

ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- sliders
def test_slider_keys_and_round_trip():
    sliders = PlanSliders()
    assert len(sliders.keys) == 12 and slider_key("mandible", "r", "v") in sliders.keys
    plan = Plan((Osteotomy("maxilla", (1.0, -2.0, 3.5), (0.5, -1.0, 2.0)),
                 Osteotomy("mandible", (0.0, 0.0, 5.0))), name="x")
    values = sliders.from_plan(plan)
    assert values["maxilla_t_h"] == 1.0 and values["maxilla_t_v"] == -2.0
    assert values["maxilla_t_ap"] == 3.5 and values["maxilla_r_ap"] == 2.0
    assert values["mandible_t_ap"] == 5.0 and values["mandible_r_h"] == 0.0
    assert sliders.to_plan(values, name="x") == plan


def test_sliders_keep_template_cuts_and_drop_unmoved():
    cut = (((0.0, 0.0, 84.0), (0.0, 0.0, -1.0)),)
    template = Plan((Osteotomy("maxilla", (0.0, 1.0, 3.0), cut=cut, pivot=(1.0, 2.0, 3.0)),),
                    name="start")
    sliders = PlanSliders(template=template)
    values = sliders.from_plan(template)
    values["maxilla_t_ap"] = -2.0
    plan = sliders.to_plan(values)
    assert plan.name == "start" and plan.segments == ("maxilla",)
    assert plan.osteotomies[0].cut == cut and plan.osteotomies[0].pivot == (1.0, 2.0, 3.0)
    assert plan.osteotomies[0].translation == (0.0, 1.0, -2.0)
    values["mandible_r_v"] = 3.0
    assert sliders.to_plan(values).segments == ("maxilla", "mandible")
    assert PlanSliders().to_plan({}).segments == ("maxilla", "mandible")  # nothing moved
    with pytest.raises(ValueError, match="unknown slider"):
        sliders.to_plan({"maxilla_t_x": 1.0})
    with pytest.raises(ValueError, match="rotation"):
        sliders.to_plan({"maxilla_r_h": 45.0})


def test_signed_displacement_and_profile():
    sphere = pv.Sphere(radius=10.0, theta_resolution=60, phi_resolution=60)
    inward = -0.2 * np.asarray(sphere.points)  # 2 mm inward
    assert np.allclose(signed_displacement(sphere, inward), -2.0, atol=0.05)
    segs = profile_segments(sphere, x=0.0)
    assert segs.shape[1:] == (2, 2) and len(segs) > 20
    assert np.allclose(np.linalg.norm(segs.reshape(-1, 2), axis=1), 10.0, atol=0.1)


def test_profile_marks_the_scan_s_cut():
    """The planner's profile lays a band of the cut colour under the silhouette where it
    runs over skin on a cut of the scan, and none without one."""
    import io

    import matplotlib.colors as mcolors
    from PIL import Image

    from pvcmf.figures.skin_marks import CUT_COLOR
    from pvcmf.planner.views import profile_png, profile_segments

    sphere = pv.Sphere(radius=60.0, theta_resolution=80, phi_resolution=80)
    marked = sphere.copy()
    marked.point_data[arrays.SKIN_CUT] = (sphere.points[:, 1] > 40).astype(np.uint8)
    segs, cut = profile_segments(marked, 0.0, on_cut=True)
    assert cut.any() and np.all(segs[cut][:, :, 0] > 38.0)
    assert not profile_segments(sphere, 0.0, on_cut=True)[1].any()
    rgb = np.array(mcolors.to_rgb(CUT_COLOR)) * 255

    def cut_pixels(skin):
        img = np.asarray(Image.open(io.BytesIO(profile_png(skin, skin))).convert("RGB"), float)
        return int((np.abs(img - rgb).max(axis=2) < 12).sum())

    assert cut_pixels(sphere) == 0 and cut_pixels(marked) > 100


def test_profile_cuts_the_head_midline_not_the_shoulders_centre():
    """As the PNG overlay: with shoulders reaching further to one side, the planner's
    profile is the head's midsagittal section, not the one through the skin's centre."""
    from pvcmf.figures.profiles import midline_x
    from pvcmf.planner.views import profile_png

    head = pv.ParametricEllipsoid(72.0, 95.0, 115.0, u_res=40, v_res=40, w_res=40)
    shoulders = pv.Cylinder(center=(60.0, -70.0, -150.0), direction=(0.0, 0.0, 1.0),
                            radius=160.0, height=30.0)
    skin = pv.merge([m.triangulate().clean() for m in (head, shoulders)])
    assert abs(midline_x(skin)) < 1.0 < abs(0.5 * (skin.bounds[0] + skin.bounds[1]))
    assert profile_png(skin, skin) == profile_png(skin, skin, x=midline_x(skin))
    assert profile_png(skin, skin) != profile_png(skin, skin,
                                                  x=0.5 * (skin.bounds[0] + skin.bounds[1]))


# --------------------------------------------------------------------------- scene
class _FakeModel:
    """A head whose right half (patient frame x < 0) bulges out by 4 mm, and a bone block
    on the patient's right only: what the scene draws, without preparing a model."""

    segments = ("mandible",)

    def __init__(self):
        self.skin = pv.ParametricEllipsoid(70.0, 95.0, 110.0, u_res=60,
                                           v_res=60).triangulate().clean()
        for name in list(self.skin.point_data.keys()):
            del self.skin.point_data[name]
        self.skin = self.skin.compute_normals(cell_normals=False, auto_orient_normals=True)
        self.bones = pv.MultiBlock({"mandible": pv.Box((-60.0, -20.0, 0.0, 40.0, -60.0, -20.0),
                                                       level=2).triangulate()})

    def displacement(self, plan):
        x = np.asarray(self.skin.points)
        return np.where(x[:, [0]] < -20.0, 4.0 * np.asarray(self.skin.point_normals), 0.0)

    def skeleton(self, plan):
        return self.bones


def _scene_image(scene):
    scene.update(Plan((Osteotomy("mandible"),)))
    scene.set_view("frontal")
    img = np.asarray(scene.screenshot(), dtype=int)
    scene.close()
    return img


def test_scene_shows_the_patient_as_a_photograph():
    """The planner's frontal view shows the patient's right (x < 0 in the patient frame) on
    the viewer's left, as the face figures do: the face pushed out on the right side is red
    on the left of its panel, and the bone on the patient's right lies on the left of the
    skeleton panel."""
    from pvcmf.planner.views import Scene

    model = _FakeModel()
    scene = Scene(model, window_size=(800, 400))
    img = _scene_image(scene)
    # the prediction the profile is cut from stays in the patient frame
    assert np.allclose(scene.predicted.points[:, 0].min(), model.skin.points[:, 0].min() - 4.0,
                       atol=0.5)
    face = img[40:-60, 400:]  # the face panel, above its colour bar
    red = (face[..., 0] > 150) & (face[..., 0] - face[..., 2] > 60)
    assert red.sum() > 200
    assert np.nonzero(red)[1].mean() < 0.45 * face.shape[1]
    skeleton = img[40:, :400]
    blue = (skeleton[..., 2] > 150) & (skeleton[..., 2] - skeleton[..., 0] > 60)
    assert blue.sum() > 200 and np.nonzero(blue)[1].mean() < 0.45 * skeleton.shape[1]
    with pytest.raises(ValueError, match="view must be one of"):
        Scene(model).set_view("top")


def test_scene_draws_the_scan_s_cut_apart():
    """Skin on a cut of the scan takes the cut colour, not the displacement map's: the
    bulging right half, marked as cut, shows no red."""
    from pvcmf.planner.views import Scene

    model = _FakeModel()
    model.skin.point_data[arrays.SKIN_CUT] = (model.skin.points[:, 0] < -20.0).astype(np.uint8)
    scene = Scene(model, window_size=(800, 400))
    img = _scene_image(scene)
    face = img[40:-60, 400:]
    red = (face[..., 0] > 150) & (face[..., 0] - face[..., 2] > 60)
    spread, mean = face.max(axis=2) - face.min(axis=2), face.mean(axis=2)
    grey = (spread < 12) & (mean > 30) & (mean < 120)  # the maps' cut colour
    assert red.sum() == 0 and grey.sum() > 200
    assert scene.on_cut.sum() == int((model.skin.points[:, 0] < -20.0).sum())


# --------------------------------------------------------------------------- model
@pytest.fixture(scope="module")
def model():
    case = pvcmf.datasets.phantom(patient=1, spacing=4.0)
    return prepare_model(case.ct, case.plan, bones=case.truth, n_tets=2000, muscles=False)


def test_model_predicts_and_moves_the_skeleton(model):
    assert model.segments == ("maxilla", "mandible")
    still = Plan((Osteotomy("mandible"),))
    assert not np.any(model.predict(still)[arrays.DISPLACEMENT])
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 5.0)),))
    face = model.predict(plan)
    disp = np.asarray(face[arrays.DISPLACEMENT])
    assert np.allclose(face.points, np.asarray(model.skin.points) + disp)
    # the chin goes forward with the mandible, nothing moves more than the bone
    # the skin in front of the chin may bulge a little beyond the bone's 5 mm (nearly
    # incompressible tissue), never by much
    assert 2.0 < disp[:, 1].max() <= 5.0 * 1.2 and np.abs(disp).max() <= 5.0 * 1.2
    bones = model.skeleton(plan)
    shift = np.asarray(bones["mandible"].points) - np.asarray(model.bones["mandible"].points)
    assert np.allclose(shift, [0.0, 5.0, 0.0])
    assert np.allclose(bones["maxilla"].points, model.bones["maxilla"].points)


def test_model_takes_a_plan_in_the_occlusal_axes(model):
    """The skeleton and the face of a plan along the occlusal plane are those of the same
    move written in the image's axes."""
    from pvcmf.filters.face_axes import occlusal_axes

    F = occlusal_axes(model.labels)
    along = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 5.0)),), axes="occlusal")
    forward = 5.0 * F[:, 1]
    same = Plan((Osteotomy("mandible", translation=tuple(forward[[0, 2, 1]])),))
    assert abs(forward[2]) > 0.05  # the phantom's arch is not level
    bones = model.skeleton(along)
    shift = np.asarray(bones["mandible"].points) - np.asarray(model.bones["mandible"].points)
    assert np.allclose(shift, forward)
    np.testing.assert_allclose(model.predict(along)[arrays.DISPLACEMENT],
                               model.predict(same)[arrays.DISPLACEMENT], atol=1e-9)


def test_planner_switches_the_axes_its_sliders_move_in(model, tmp_path):
    """The page's axes buttons (Planner.set_axes): the same slider values move the mandible
    along the occlusal plane; axes the labels cannot give are refused, the plan kept."""
    from pvcmf.filters.face_axes import occlusal_axes
    from pvcmf.planner.app import Planner

    planner = Planner(model, tmp_path / "plan.toml")
    values = {**planner.values, "mandible_t_ap": 5.0}
    planner.set_values(values)
    before = model.skeleton(planner.plan)["mandible"].points.copy()
    planner.set_axes("occlusal")
    assert planner.plan.axes == "occlusal" and 'axes = "occlusal"' in planner.plan_toml()
    assert planner.sliders.from_plan(planner.plan) == planner.values
    after = model.skeleton(planner.plan)["mandible"].points
    turned = occlusal_axes(model.labels)
    assert np.allclose(after - before, 5.0 * (turned[:, 1] - [0.0, 1.0, 0.0]), atol=1e-9)
    # the profile is cut from both skins turned into those axes, at their midline
    pre, post, x = planner.profile_surfaces()
    centre = np.asarray(model.skin.center)
    np.testing.assert_allclose(pre.points, (np.asarray(model.skin.points) - centre) @ turned
                               + centre, atol=1e-9)
    moved = np.asarray(post[arrays.DISPLACEMENT])
    np.testing.assert_allclose(moved, np.asarray(planner.scene.predicted[arrays.DISPLACEMENT])
                               @ turned, atol=1e-12)
    assert abs(x - (pre.bounds[0] + pre.bounds[1]) / 2) < 30.0
    with pytest.raises(ValueError, match="need the landmarks"):
        planner.set_axes("frankfort")  # no muscle fit, no landmarks given
    assert planner.plan.axes == "occlusal"
    with pytest.raises(ValueError, match="axes must be one of"):
        planner.set_axes("scanner")


def test_model_takes_a_frankfort_plan_with_its_landmarks():
    """A start plan in the Frankfort axes: the planner stores the landmarks given (no muscle
    fit) and moves the skeleton along their horizontal."""
    from pvcmf.filters.face_axes import frankfort_axes

    case = pvcmf.datasets.phantom(patient=1, spacing=4.0)
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 5.0)),), axes="frankfort")
    turned = {k: np.asarray(v) @ np.array([[1, 0, 0], [0, 0.96, 0.28], [0, -0.28, 0.96]])
              for k, v in case.landmarks.items()}  # the face pitched 16 degrees
    model = prepare_model(case.ct, plan, bones=case.truth, landmarks=turned, n_tets=2000,
                          muscles=False)
    bones = model.skeleton(plan)
    shift = np.asarray(bones["mandible"].points) - np.asarray(model.bones["mandible"].points)
    assert np.allclose(shift, 5.0 * frankfort_axes(turned)[:, 1])
    assert abs(shift[0, 2]) > 1.0
    with pytest.raises(ValueError, match="need the landmarks"):
        prepare_model(case.ct, plan, bones=case.truth, n_tets=2000, muscles=False)


# --------------------------------------------------------------------------- web page
def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_http(url, proc, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the planner exited with {proc.returncode}")
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            time.sleep(0.5)
    raise TimeoutError(f"no answer from {url} within {timeout} s")


def _image(png):
    from PIL import Image
    import io
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=float)


@pytest.fixture()
def planner_server(tmp_path):
    for module in ("trame", "trame_vtk", "trame_vuetify"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (pip install 'pvcmf[planner]')")
    port = _free_port()
    save = tmp_path / "planned.toml"
    env = {**os.environ, "PYVISTA_OFF_SCREEN": "true", "PYTHONPATH": str(ROOT)}
    log = open(tmp_path / "server.log", "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "pvcmf.cli", "plan", "--ct", "phantom:1", "--spacing", "4",
         "--n-tets", "2000", "--no-muscles", "--port", str(port), "--save", str(save)],
        stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
    try:
        _wait_http(f"http://127.0.0.1:{port}/", proc, timeout=240)
        yield f"http://127.0.0.1:{port}/", save
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=15)
        log.close()


def _stable_image(locator, timeout=60.0):
    """A screenshot of ``locator`` once two taken 1 s apart agree (streaming has settled)."""
    deadline, last = time.monotonic() + timeout, _image(locator.screenshot())
    while time.monotonic() < deadline:
        time.sleep(1.0)
        now = _image(locator.screenshot())
        if now.shape == last.shape and np.abs(now - last).mean() < 0.05:
            return now
        last = now
    raise TimeoutError(f"the 3D view did not settle within {timeout} s")


def _slider_values(page, keys):
    return {k: float(page.locator(f"#slider-{k} [role=slider]").get_attribute("aria-valuenow"))
            for k in keys}


@pytest.mark.slow
def test_page_slider_updates_view_and_saves_plan(planner_server):
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    chromium = _chromium()
    if chromium is None:
        pytest.skip("no Chromium binary (apt-get install chromium)")
    url, save = planner_server
    keys = PlanSliders().keys
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=chromium, timeout=60_000,
                                     args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.set_default_timeout(60_000)
            page.goto(url)
            page.wait_for_selector("#view3d img")
            view = page.locator("#view3d")
            page.wait_for_function(  # the first streamed image has arrived
                "() => { const i = document.querySelector('#view3d img');"
                " return i && i.complete && i.naturalWidth > 100; }")
            before = _stable_image(view)
            assert before.std() > 10.0, "the 3D view is blank"
            thumb = page.locator("#slider-maxilla_t_ap [role=slider]")
            start = float(thumb.get_attribute("aria-valuenow"))
            thumb.focus()
            for _ in range(4):
                page.keyboard.press("ArrowRight")
            values = _slider_values(page, keys)
            assert values["maxilla_t_ap"] == start + 2.0
            expected = PlanSliders(template=TABLE_II[1]).to_plan(values)
            line = "translation = " + str(list(expected.osteotomies[0].translation))
            page.wait_for_function(  # the server has predicted the last slider value
                f"() => document.querySelector('#plan-toml').innerText.includes('{line}')")
            after = _stable_image(view)
            diff = np.abs(after - before).mean() if after.shape == before.shape else 99.0
            assert diff >= 0.2, f"the 3D view did not change (mean difference {diff:.2f})"
            assert after.std() > 10.0
            page.click("#save-button")
            page.wait_for_function(
                "() => document.querySelector('#saved').innerText.startsWith('saved')")
            page.click("#axes-occlusal")  # the same sliders along the occlusal plane
            page.wait_for_function(
                "() => document.querySelector('#plan-toml').innerText"
                ".includes('axes = \"occlusal\"')")
        finally:
            browser.close()
    saved = read_plan(save)
    assert saved == expected
    assert PlanSliders(template=TABLE_II[1]).from_plan(saved) == values


def test_plan_help_describes_the_command_and_its_exit_statuses(capsys, tmp_path):
    """``pvcmf plan --help`` says what the command does and its exit statuses, like the
    other subcommands; a CT that does not exist is bad input (status 2, before any work)."""
    from pvcmf.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["plan", "--help"])
    assert stop.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "serve a planner page" in text and "Save plan" in text
    assert "Exit status: 0 the server stopped, 2 bad input" in text
    assert main(["plan", "--ct", str(tmp_path / "missing.nrrd")]) == 2
    assert "pvcmf plan: error:" in capsys.readouterr().err


def test_plan_axes_option_sets_the_sliders_axes(monkeypatch, tmp_path):
    """``pvcmf plan --axes occlusal`` starts from a plan in those axes (one that moves
    nothing without --plan), and refuses a starting plan given in other axes."""
    from pvcmf import cli
    from pvcmf.planner import app

    seen = []

    def fake_prepare(ct_, plan, **options):
        seen.append(plan)
        raise SystemExit(0)

    monkeypatch.setattr(app, "prepare_model", fake_prepare)
    monkeypatch.setattr(pvcmf.io, "read_ct", lambda path, **options: pv.ImageData())
    with pytest.raises(SystemExit):
        app.run_plan(cli.build_parser().parse_args(
            ["plan", "--ct", str(tmp_path), "--axes", "occlusal"]))
    assert seen[-1] == Plan((), axes="occlusal")
    start = tmp_path / "start.toml"
    Plan((Osteotomy("mandible", translation=(0.0, 0.0, 3.0)),)).to_file(start)
    with pytest.raises(ValueError, match="--axes frankfort contradicts the starting plan's"):
        app.run_plan(cli.build_parser().parse_args(
            ["plan", "--ct", str(tmp_path), "--plan", str(start), "--axes", "frankfort"]))
    with pytest.raises(SystemExit):
        app.run_plan(cli.build_parser().parse_args(
            ["plan", "--ct", str(tmp_path), "--plan", str(start), "--axes", "image"]))
    assert seen[-1] == Plan.from_file(start)
    with pytest.raises(SystemExit):
        cli.build_parser().parse_args(["plan", "--ct", "x", "--axes", "scanner"])


def test_plan_checks_the_units_and_axes_of_a_ct_it_reads(monkeypatch, tmp_path):
    """``pvcmf plan --ct FILE`` checks the scan's units and axes as ``pvcmf simulate`` does
    (``--units``/``--orient``, 'auto' by default), headsq's axes only, and a virtual
    patient not at all; ``prepare_model`` hands them to ``simulate``."""
    from pvcmf import cli
    from pvcmf.planner import app, model

    ct = pv.ImageData(dimensions=(3, 3, 3))
    monkeypatch.setattr(pvcmf.io, "read_ct", lambda path, **options: ct)
    seen = []

    def fake_prepare(ct_, plan, **options):
        seen.append({k: options.get(k) for k in ("units", "orient")})
        raise SystemExit(0)

    monkeypatch.setattr(app, "prepare_model", fake_prepare)
    for argv, expected in (([], ("auto", "auto")),
                           (["--units", "rescale", "--orient", "lpi"], ("rescale", "LPI")),
                           (["--units", "-1024"], (-1024.0, "auto"))):
        args = cli.build_parser().parse_args(["plan", "--ct", str(tmp_path), *argv])
        with pytest.raises(SystemExit):
            app.run_plan(args)
        assert (seen[-1]["units"], seen[-1]["orient"]) == expected
    monkeypatch.setattr(pvcmf.datasets, "headsq", lambda: ct)
    with pytest.raises(SystemExit):
        app.run_plan(cli.build_parser().parse_args(["plan", "--ct", "headsq"]))
    assert seen[-1] == {"units": "hu", "orient": "auto"}
    with pytest.raises(SystemExit):
        app.run_plan(cli.build_parser().parse_args(["plan", "--ct", "phantom:1"]))
    assert seen[-1] == {"units": None, "orient": None}

    calls = []

    def fake_simulate(ct_, plan, **options):
        calls.append({k: options.get(k) for k in ("units", "orient")})
        raise SystemExit(0)

    monkeypatch.setattr(model, "simulate", fake_simulate)
    with pytest.raises(SystemExit):
        model.prepare_model(ct, Plan(()), units="rescale", orient="auto")
    assert calls == [{"units": "rescale", "orient": "auto"}]
