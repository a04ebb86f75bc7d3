"""Plans in the face's axes (``Plan.axes``, :mod:`pvcmf.filters.face_axes`): a move given
along the occlusal plane or the Frankfort horizontal turns with the head, so a head scanned
tilted gets the move the surgeon means, not the scanner's."""

from __future__ import annotations

import dataclasses
import logging
import warnings

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

import pvcmf
from pvcmf import arrays, datasets
from pvcmf.filters import apply_plan, find_jaws, plan_axes
from pvcmf.filters.bone_segments import occlusal_normal, occlusal_plane
from pvcmf.filters.face_axes import (FRANKFORT_LANDMARKS, frankfort_axes, occlusal_axes,
                                     with_plan_axes)
from pvcmf.filters.jaw_pose import MIN_ARCH_SPAN_MM, check_pose
from pvcmf.filters.osteotomy import segment_transforms
from pvcmf.mtm import solve
from pvcmf.mtm.response import plan_grid, plan_response
from pvcmf.plan import Osteotomy, Plan
from pvcmf.planner.state import PlanSliders

from ct_helpers import turned_labels

MARKS = {"porion_left": (62.0, 0.0, 0.0), "porion_right": (-60.0, 1.0, 0.5),
         "orbitale_left": (33.0, 80.0, -7.0), "orbitale_right": (-31.0, 81.0, -8.0)}


def _turned_marks(rotation, marks=MARKS):
    return {k: rotation @ np.asarray(v) for k, v in marks.items()}


def test_frankfort_axes_turn_with_the_landmarks():
    """Landmarks turned by R give axes turned by R (to round-off); the axes are a rotation
    whose horizontal joins the porions and whose vertical is normal to the plane through
    them and the orbitales' midpoint."""
    base = frankfort_axes(MARKS)
    np.testing.assert_allclose(base.T @ base, np.eye(3), atol=1e-12)
    assert np.linalg.det(base) == pytest.approx(1.0)
    pl, pr = np.asarray(MARKS["porion_left"]), np.asarray(MARKS["porion_right"])
    np.testing.assert_allclose(base[:, 0], (pl - pr) / np.linalg.norm(pl - pr))
    mid = (np.asarray(MARKS["orbitale_left"]) + np.asarray(MARKS["orbitale_right"])) / 2
    for p in (pl, pr, mid):  # the three points lie in the plane normal to the vertical
        assert abs((p - pl) @ base[:, 2]) < 1e-9
    for seed in range(5):
        R = Rotation.from_rotvec(np.random.default_rng(seed).uniform(-0.4, 0.4, 3)).as_matrix()
        np.testing.assert_allclose(frankfort_axes(_turned_marks(R)), R @ base, atol=1e-12)


def test_frankfort_axes_refuse_what_spans_no_frame():
    with pytest.raises(ValueError, match=r"need the landmarks \['orbitale_right'\]"):
        frankfort_axes({k: v for k, v in MARKS.items() if k != "orbitale_right"})
    with pytest.raises(ValueError, match="3 finite numbers"):
        frankfort_axes({**MARKS, "porion_left": (np.nan, 0.0, 0.0)})
    with pytest.raises(ValueError, match="span no plane: porions 1.0 mm apart"):
        frankfort_axes({**MARKS, "porion_left": (-59.0, 1.0, 0.5)})
    swapped = {**MARKS, "porion_left": MARKS["porion_right"],
               "porion_right": MARKS["porion_left"]}
    with pytest.raises(ValueError, match="180 degrees from the image's axes"):
        frankfort_axes(swapped)
    with pytest.raises(ValueError, match="label image holds none"):
        frankfort_axes(pv.ImageData(dimensions=(2, 2, 2)))
    with pytest.raises(ValueError, match="axes must be one of"):
        plan_axes(pv.ImageData(dimensions=(2, 2, 2)), "scanner")


def test_a_move_in_turned_axes_is_the_move_turned():
    """Osteotomy.matrix in axes F equals the move made in F's coordinates and turned back
    (an independent route: points into F's frame, the plan there, points back)."""
    o = Osteotomy("maxilla", translation=(1.5, -2.0, 4.0), rotation=(6.0, -3.0, 9.0))
    c = np.array([3.0, 60.0, -20.0])
    x = np.random.default_rng(0).normal(size=(20, 3)) * 30
    for seed in range(4):
        F = Rotation.from_rotvec(np.random.default_rng(seed).uniform(-0.5, 0.5, 3)).as_matrix()
        M = o.matrix(c, axes=F)
        local = o.matrix(F.T @ c)
        expected = ((x @ F) @ local[:3, :3].T + local[:3, 3]) @ F.T
        np.testing.assert_allclose(x @ M[:3, :3].T + M[:3, 3], expected, atol=1e-9)
    np.testing.assert_array_equal(o.matrix(c, axes=np.eye(3)), o.matrix(c))
    with pytest.raises(ValueError, match="3x3 rotation"):
        o.matrix(c, axes=np.diag([1.0, 1.0, -1.0]))


def test_plan_files_keep_their_axes(tmp_path):
    plan = Plan((Osteotomy("maxilla", (0.0, 1.0, 3.0)),), name="p", axes="occlusal")
    assert Plan.from_file(plan.to_file(tmp_path / "p.toml")) == plan
    assert Plan.from_file(plan.to_file(tmp_path / "p.json")) == plan
    assert 'axes = "occlusal"' in (tmp_path / "p.toml").read_text()
    assert "axes" not in dataclasses.replace(plan, axes="image").to_dict()
    with pytest.raises(ValueError, match=r"axes must be one of \['image', 'occlusal', "):
        Plan((Osteotomy("maxilla"),), axes="scanner")
    (tmp_path / "bad.toml").write_text('axes = "face"\n[[osteotomy]]\nsegment = "maxilla"\n')
    with pytest.raises(ValueError, match="bad.toml: plan axes must be one of"):
        Plan.from_file(tmp_path / "bad.toml")
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(ValueError, match="a matrix is in the image's frame"):
        Plan.from_dict({"axes": "occlusal", "osteotomy": [{"segment": "maxilla",
                                                            "matrix": eye}]})
    # plans made from a plan keep its axes: sweeps and the planner's sliders
    assert {p.axes for p in plan_grid("maxilla", translations=[[0, 0, 1], [0, 0, 2]],
                                      base=plan)} == {"occlusal"}
    state = PlanSliders(("maxilla", "mandible"), template=plan)
    assert state.to_plan(state.from_plan(plan)).axes == "occlusal"
    from pvcmf.study.pipeline_evaluation import PipelineEvaluation

    swept = PipelineEvaluation.plan_of({"plan": plan, "labels": object()},
                                       {"mandible_t_ap": 3.0})
    assert swept.axes == "occlusal" and swept.segments == ("maxilla", "mandible")


def _turn_labels(labels, degrees_x, degrees_y, degrees_z=0.0):
    """``labels``'s tissue turned about its centre (nearest voxel) on a grid padded so
    nothing leaves it, and the rotation (image coordinates)."""
    R = Rotation.from_euler("xyz", [degrees_x, degrees_y, degrees_z], degrees=True).as_matrix()
    return turned_labels(labels, R), R


@pytest.fixture(scope="module")
def upright_and_turned():
    case = datasets.phantom(patient=1, spacing=2.0)
    upright, _ = _turn_labels(case.truth, 0.0, 0.0)
    turned, R = _turn_labels(case.truth, -15.0, 8.0, 10.0)  # chin down 15, rolled 8, turned 10
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return find_jaws(upright), find_jaws(turned), R


def test_occlusal_axes_turn_with_the_head(upright_and_turned):
    """The virtual patient's labels turned 15 degrees chin down, rolled 8 and turned 10 about
    the vertical: the occlusal axes found on them are the upright ones turned (within 1.5
    degrees; the arch's normal gives the tilt, the skull's mirror plane the turn), a mandible
    advance
    given along them moves the turned mandible as the upright one turned, and the same plan
    in the image's axes does not (it is off by the tilt)."""
    upright, turned, R = upright_and_turned
    a, b = occlusal_axes(upright), occlusal_axes(turned)
    off = Rotation.from_matrix(b.T @ R @ a).magnitude()
    assert np.degrees(off) < 1.5, np.degrees(off)  # (nearest-voxel turn of 2 mm voxels)
    assert np.degrees(Rotation.from_matrix(b).magnitude()) > 10.0  # the head is tilted
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 6.0), rotation=(4.0, 0, 0)),),
                axes="occlusal")
    moved = {}
    for name, labels in (("upright", upright), ("turned", turned)):
        for axes in ("occlusal", "image"):
            moved[name, axes] = segment_transforms(
                labels, dataclasses.replace(plan, axes=axes))[arrays.MANDIBLE]
    # the move's translation part at the (turned) centroid: the upright one turned
    for axes, close in (("occlusal", True), ("image", False)):
        up, tu = moved["upright", axes], moved["turned", axes]
        diff = np.linalg.norm(tu[:3, :3] @ R - R @ up[:3, :3])
        pivot_up = segment_centroid(upright)
        step_up = up[:3, :3] @ pivot_up + up[:3, 3] - pivot_up
        pivot_tu = segment_centroid(turned)
        step_tu = tu[:3, :3] @ pivot_tu + tu[:3, 3] - pivot_tu
        miss = np.linalg.norm(step_tu - R @ step_up)
        if close:
            assert miss < 0.35 and diff < 0.06, (miss, diff)
        else:
            assert miss > 1.0, miss


def segment_centroid(labels):
    bone = np.asarray(labels[arrays.BONE])
    return np.asarray(labels.points)[bone == arrays.MANDIBLE].mean(axis=0)


def test_occlusal_normal_is_measured_where_find_jaws_did_not_keep_it(upright_and_turned):
    _, turned, _ = upright_and_turned
    bare = turned.copy()
    bare.field_data.clear()
    np.testing.assert_allclose(occlusal_normal(bare), occlusal_normal(turned), atol=1e-9)
    # simulate measures it once and keeps it for every later step (a copy: bare unchanged)
    kept = with_plan_axes(bare, Plan((Osteotomy("mandible"),), axes="occlusal"))
    assert arrays.ARCH_NORMAL not in bare.field_data
    np.testing.assert_allclose(kept.field_data[arrays.ARCH_NORMAL], occlusal_normal(turned),
                               atol=1e-9)


def test_a_row_of_front_teeth_gives_no_occlusal_axes(upright_and_turned):
    """Teeth that span a row (the back teeth missing, or below the scan's teeth level, as on
    the Visible Human female) give no plane to plan in: the plane of a row may turn about
    it. The arch kept in the labels is refused the same way."""
    upright, _, _ = upright_and_turned
    _, span = occlusal_plane(upright)
    assert span > 1.5 * MIN_ARCH_SPAN_MM  # the virtual patient's whole arch
    row = upright.copy()
    row.field_data.clear()
    tissue = np.asarray(row[arrays.TISSUE]).copy()
    p = np.asarray(row.points)
    teeth = np.isin(tissue, (arrays.TEETH, arrays.METAL))
    front = p[teeth, 1].max() - 8.0  # the front 8 mm of the teeth
    tissue[teeth & (p[:, 1] < front)] = arrays.BONE_TISSUE
    row[arrays.TISSUE] = tissue
    with pytest.raises(ValueError, match="across their row .*a row of front teeth"):
        occlusal_axes(row)
    kept = upright.copy()
    kept.field_data[arrays.ARCH_SPAN] = [3.0]
    with pytest.raises(ValueError, match="spread 3.0 mm across their row"):
        plan_axes(kept, "occlusal")


def test_a_tilted_head_is_not_warned_about_for_a_plan_in_the_face_s_axes(caplog):
    labels = pv.ImageData(dimensions=(2, 2, 2))
    labels.field_data[arrays.ARCH_PITCH] = [40.0]
    with caplog.at_level(logging.INFO, logger="pvcmf"):
        assert "axes = \"occlusal\"" in check_pose(labels)
        assert check_pose(labels, "occlusal") is None
    levels = [r.levelname for r in caplog.records]
    assert levels == ["WARNING", "INFO"], levels


def _tilted(labels, degrees, turn=0.0):
    """A shallow copy of ``labels`` whose upper arch descends ``degrees`` anteriorly and
    whose head is turned ``turn`` degrees about the vertical (its mirror plane's normal)."""
    out = labels.copy(deep=False)
    a, t = np.radians(degrees), np.radians(turn)
    out.field_data[arrays.ARCH_NORMAL] = [0.0, np.sin(a), np.cos(a)]
    out.field_data[arrays.ARCH_SPAN] = [13.0]  # mm across the row: an arch
    out.field_data[arrays.MIRROR_NORMAL] = [np.cos(t), np.sin(t), 0.0]
    return out


def test_plan_response_equals_the_full_solve_in_occlusal_axes():
    """The plan response operator takes a plan in the occlusal axes as apply_plan + solve
    does (1e-9 mm), and its prediction differs from the same numbers in the image's axes."""
    img = pv.ImageData(dimensions=(15, 15, 15), origin=(-7, -7, -7))
    p = np.asarray(img.points)
    inner = (np.abs(p) <= 3).all(axis=1)
    img[arrays.BONE] = np.where(inner, np.where(p[:, 2] > 0, arrays.MAXILLA, arrays.MANDIBLE),
                                0).astype(np.uint8)
    img[arrays.TISSUE] = np.where(inner, arrays.BONE_TISSUE, arrays.FAT).astype(np.uint8)
    soft = ~(np.abs(img.cell_centers().points) < 3).all(axis=1)
    grid = img.extract_cells(np.flatnonzero(soft)).triangulate().clean()
    grid.clear_data()
    grid.cell_data[arrays.E_FIBER] = np.full(grid.n_cells, 3e-3)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.45)
    labels = _tilted(img, 20.0, turn=10.0)
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, labels, bc_options=opts)
    plan = Plan((Osteotomy("maxilla", (0.5, -1.0, 2.0), (5.0, -4.0, 3.0)),
                 Osteotomy("mandible", (0.0, 1.0, 3.0), (-6.0, 2.0, 0.0))), axes="occlusal")
    u = np.asarray(solve(apply_plan(grid, plan, labels, **opts))[arrays.DISPLACEMENT])
    assert np.abs(resp.predict_nodes(plan) - u[resp.surface_ids]).max() < 1e-9
    image = resp.predict_nodes(dataclasses.replace(plan, axes="image"))
    assert np.abs(image - u[resp.surface_ids]).max() > 0.3


def test_simulate_frankfort_plan_needs_its_landmarks(tmp_path):
    """A Frankfort plan without landmarks and without the atlas fit is refused before any
    work; with landmarks it moves the mandible along their horizontal."""
    case = datasets.phantom(patient=1, spacing=4.0)
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 4.0)),), axes="frankfort")
    with pytest.raises(ValueError, match="plan axes 'frankfort' need the landmarks"):
        pvcmf.pipeline.simulate(case.ct, plan, tmp_path / "out", muscles=False)
    assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="span no plane"):
        pvcmf.pipeline.simulate(case.ct, plan, muscles=False,
                                landmarks={**MARKS, "porion_left": MARKS["porion_right"]})
    R = Rotation.from_euler("x", -12.0, degrees=True).as_matrix()
    marks = _turned_marks(R)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = pvcmf.pipeline.simulate(case.ct, plan, bones=case.truth, muscles=False,
                                      landmarks=marks, n_tets=2000, solve=False,
                                      figures=False)
    code = np.asarray(res.mesh[arrays.BC])
    disp = np.asarray(res.mesh[arrays.BC_DISPLACEMENT])[code == arrays.BC_JOINT]
    expected = 4.0 * (R @ frankfort_axes(MARKS))[:, 1]  # forward along their horizontal
    assert np.degrees(np.arcsin(-expected[2] / 4.0)) > 15.0  # far from the image's forward
    np.testing.assert_allclose(disp, np.broadcast_to(expected, disp.shape), atol=1e-9)
    assert set(FRANKFORT_LANDMARKS) <= set(res.labels.field_data[arrays.LANDMARK_NAMES])
    np.testing.assert_allclose(plan_axes(res.labels, plan), R @ frankfort_axes(MARKS),
                               atol=1e-12)


def test_fitted_frankfort_landmarks_are_warned_with_their_roll_from_the_teeth():
    """Landmarks the labels hold (an atlas fit's) are used with a warning that says how far
    their horizontal rolls from the upper arch's plane; landmarks given win over them."""
    labels = pv.ImageData(dimensions=(2, 2, 2))
    labels.field_data[arrays.ARCH_NORMAL] = [0.0, 0.0, 1.0]  # a level arch
    labels.field_data[arrays.ARCH_SPAN] = [13.0]
    R = Rotation.from_euler("y", 6.0, degrees=True).as_matrix()  # one porion 13 mm higher
    fitted = _turned_marks(R)
    names = sorted(fitted)
    labels.field_data[arrays.LANDMARK_NAMES] = names
    labels.field_data[arrays.LANDMARK_POINTS] = [fitted[n] for n in names]
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 5.0)),), axes="frankfort")
    roll = np.degrees(np.arcsin(frankfort_axes(fitted)[2, 0]))
    assert abs(roll) > 5.0
    with pytest.warns(UserWarning, match=f"rolls {roll:+.1f} degrees from the upper dental"):
        same = with_plan_axes(labels, plan)
    assert same is labels
    # a skull whose mirror plane's normal lies 4 degrees anterior of the fitted porions'
    # line on the left (the line turns -4 degrees from it): said too
    F = frankfort_axes(fitted)
    mirrored = labels.copy(deep=False)
    a = np.radians(4.0)
    mirrored.field_data[arrays.MIRROR_NORMAL] = np.cos(a) * F[:, 0] + np.sin(a) * F[:, 1]
    with pytest.warns(UserWarning, match=r"dental arch's plane and turns -4\.0 degrees from "
                                         "the skull's mirror plane"):
        with_plan_axes(mirrored, plan)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        given = with_plan_axes(labels, plan, MARKS)
    np.testing.assert_allclose(plan_axes(given, plan), frankfort_axes(MARKS), atol=1e-12)
    np.testing.assert_allclose(plan_axes(labels, plan), frankfort_axes(fitted), atol=1e-12)


def test_figures_show_a_turned_head_upright_in_the_plans_axes(upright_and_turned):
    """The face figures of a plan in the occlusal axes show the surfaces turned into those
    axes: the turned head's skin then lies on the upright head's (p90 distance within two
    voxels, once both are centred), where as the scan holds it, it is far off; vectors turn
    with the points, the input keeps its own, and a plan in the image's axes keeps the
    image's."""
    from types import SimpleNamespace

    from scipy.spatial import cKDTree

    from pvcmf.figures.plan_frame import figure_frame, turned_into
    from pvcmf.filters import extract_skin
    from pvcmf.outputs import _in_plan_frame

    upright, turned, R = upright_and_turned
    plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 6.0)),), axes="occlusal")
    skins = {}
    for name, labels in (("upright", upright), ("turned", turned)):
        skin = extract_skin(labels)
        skin.point_data[arrays.DISPLACEMENT] = np.tile(R[:, 1] if name == "turned"
                                                       else [0.0, 1.0, 0.0], (skin.n_points, 1))
        result = SimpleNamespace(skin_pre=skin, skin_post=skin, skeleton=None, labels=labels,
                                 plan=plan)
        pre, post, _, note = _in_plan_frame(result)
        assert note == ", occlusal axes"
        skins[name] = (skin, pre)

    def p90(a, b):
        a, b = a - a.mean(axis=0), b - b.mean(axis=0)
        return max(np.percentile(cKDTree(b).query(a)[0], 90),
                   np.percentile(cKDTree(a).query(b)[0], 90))

    up, tu = (np.asarray(skins[n][1].points) for n in ("upright", "turned"))
    assert p90(up, tu) < 4.0, p90(up, tu)
    as_held = p90(np.asarray(skins["upright"][0].points), np.asarray(skins["turned"][0].points))
    assert as_held > 10.0, as_held
    # the turned head's forward (its R y) becomes the figures' forward, near (0, 1, 0)
    forward = np.asarray(skins["turned"][1][arrays.DISPLACEMENT])[0]
    assert forward[1] > 0.99, forward
    np.testing.assert_array_equal(np.asarray(skins["turned"][0][arrays.DISPLACEMENT])[0], R[:, 1])
    assert figure_frame(turned, dataclasses.replace(plan, axes="image")) is None
    with pytest.raises(ValueError, match="frame must be a 3x3 rotation"):
        turned_into(skins["turned"][0], 2.0 * np.eye(3), (0, 0, 0))
    block = pv.MultiBlock({"mandible": skins["turned"][0]})
    moved = turned_into(block, R, (0.0, 0.0, 0.0))
    np.testing.assert_allclose(moved["mandible"].points,
                               np.asarray(skins["turned"][0].points) @ R, atol=1e-9)
