"""Surgical plans: file format, validation, cutting and moving the bone segments."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

from pvcmf import arrays
from pvcmf.filters import cut_bones, move_bones
from pvcmf.filters.osteotomy import segment_transforms
from pvcmf.plan import TABLE_II, MAX_ROTATION_DEG, Osteotomy, Plan, read_plan, write_plan


# --------------------------------------------------------------------------- file format
@pytest.mark.parametrize("fmt", ["toml", "json"])
@pytest.mark.parametrize("patient", sorted(TABLE_II))
def test_table_ii_round_trips(tmp_path, patient, fmt):
    plan = TABLE_II[patient]
    path = write_plan(plan, tmp_path / f"plan.{fmt}")
    back = read_plan(path)
    assert back == plan
    # the file states Table II's numbers as written in the paper
    text = path.read_text()
    o = plan.osteotomies[0]
    assert o.segment in text
    assert all(repr(v) in text for v in o.translation)


def test_round_trip_with_cut_planes_and_pivot(tmp_path):
    plan = Plan((Osteotomy("maxilla", (1.5, -2.0, 3.25), (0.0, 1.0, -2.0),
                           pivot=(0.0, 60.0, -30.0),
                           cut=(((0.0, 0.0, -20.0), (0.0, 0.0, -1.0)),)),
                 Osteotomy("mandible", (0.0, 0.0, 4.0))), name="bimaxillary")
    for suffix in ("toml", "json"):
        assert Plan.from_file(plan.to_file(tmp_path / f"p.{suffix}")) == plan


def test_file_without_rotation_means_zero(tmp_path):
    (tmp_path / "p.toml").write_text('[[osteotomy]]\nsegment = "mandible"\n'
                                     'translation = [0.67, 0.61, -3.24]\n')
    plan = read_plan(tmp_path / "p.toml")
    assert plan == Plan((Osteotomy("mandible", (0.67, 0.61, -3.24)),))
    assert plan.osteotomies[0].rotation == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("text, match", [
    ('[[osteotomy]]\nsegment = "maxilla"\ntranslaton = [1, 2, 3]\n', r"unknown key.*translaton"),
    ('colour = "red"\n[[osteotomy]]\nsegment = "maxilla"\n', r"unknown key.*colour"),
    ('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [1, nan, 3]\n', r"translation.*finite"),
    ('[[osteotomy]]\nsegment = "maxilla"\nrotation = [0, 45, 0]\n', r"rotation.*30"),
    ('[[osteotomy]]\nsegment = "maxilla"\nrotation = [0, inf, 0]\n', r"rotation.*finite"),
    ('[[osteotomy]]\nsegment = "maxilla"\ntranslation = [1, 2]\n', r"translation.*3 finite"),
    ('[[osteotomy]]\nsegment = "nose"\n', r"segment must be one of"),
    ('[[osteotomy]]\ntranslation = [1, 2, 3]\n', r"needs a 'segment'"),
    ('name = "empty"\n', r"at least one \[\[osteotomy\]\]"),
    ('[[osteotomy]]\nsegment = "maxilla"\n[[osteotomy]]\nsegment = "maxilla"\n', r"once per plan"),
    ('[[osteotomy]]\nsegment = "maxilla"\n[[osteotomy.cut]]\npoint = [0, 0, 0]\n',
     r"cut\[0\] is missing key\(s\) \['normal'\]"),
    ('[[osteotomy]]\nsegment = "maxilla"\n[[osteotomy.cut]]\npoint = [0, 0, 0]\n'
     'normal = [0, 0, 0]\n', r"normal must be non-zero"),
    ('[[osteotomy]\nsegment = "maxilla"\n', r"not a valid TOML"),
])
def test_invalid_toml_plans_raise_clearly(tmp_path, text, match):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as info:
        read_plan(path)
    assert "bad.toml" in str(info.value)  # the message names the file


@pytest.mark.parametrize("text, match", [
    ('{"osteotomy": [{"segment": "mandible", "translation": [NaN, 0, 0]}]}', "non-finite"),
    ('{"osteotomy": [{"segment": "mandible", "translation": [Infinity, 0, 0]}]}', "non-finite"),
    ('{"osteotomy": [{"segment": "mandible", "rotation": [0, 0, -31]}]}', "rotation"),
    ('{"osteotomy": [{"segment": "mandible", "shift": [0, 0, 1]}]}', "unknown key.*shift"),
    ('{"osteotomy": [{"segment": "mandible"}', "not a valid JSON"),
    ('[1, 2]', "must be a table/object"),
])
def test_invalid_json_plans_raise_clearly(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_plan(path)


def test_file_format_and_type_errors(tmp_path):
    with pytest.raises(ValueError, match="format must be 'toml' or 'json'"):
        write_plan(TABLE_II[1], tmp_path / "plan.yaml")
    with pytest.raises(TypeError, match="plan must be a pvcmf.Plan"):
        write_plan({"osteotomy": []}, tmp_path / "plan.toml")
    with pytest.raises(FileNotFoundError):
        read_plan(tmp_path / "missing.toml")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_rotation_limit_is_inclusive():
    Osteotomy("maxilla", rotation=(MAX_ROTATION_DEG, 0, -MAX_ROTATION_DEG))
    with pytest.raises(ValueError, match="rotation must be within"):
        Osteotomy("maxilla", rotation=(0, 0, MAX_ROTATION_DEG + 0.01))


def test_write_is_atomic(tmp_path, monkeypatch):
    """An exception in the middle of writing leaves the old file and no temporary file."""
    path = write_plan(TABLE_II[1], tmp_path / "plan.json")
    before = path.read_text()

    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    import pvcmf.plan

    monkeypatch.setattr(pvcmf.plan.json, "dumps", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        write_plan(TABLE_II[2], path)
    assert path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["plan.json"]


# --------------------------------------------------------------------------- matrices
@pytest.mark.parametrize("patient", sorted(TABLE_II))
def test_matrix_matches_scipy_rotation(patient):
    """Table II's convention checked against scipy: extrinsic x, then z, then y."""
    o = TABLE_II[patient].osteotomies[0]
    pivot = np.array([3.0, -40.0, 12.0])
    m = o.matrix(pivot)
    rx, rz, ry = o.rotation  # (horizontal, vertical, anterior-posterior) axes = (x, z, y)
    rot = Rotation.from_euler("xzy", [rx, rz, ry], degrees=True).as_matrix()
    np.testing.assert_allclose(m[:3, :3], rot, atol=1e-12)
    h, v, ap = o.translation
    np.testing.assert_allclose(m[:3, :3] @ pivot + m[:3, 3], pivot + [h, ap, v], atol=1e-12)


# --------------------------------------------------------------------------- bone segments
@pytest.fixture(scope="module")
def skull():
    """A 1 mm label image: one bone block (cranium label) with upper/lower halves."""
    img = pv.ImageData(dimensions=(21, 21, 31), origin=(-10, -10, -15))
    p = img.points
    bone = np.zeros(img.n_points, dtype=np.uint8)
    block = (np.abs(p[:, 0]) <= 6) & (np.abs(p[:, 1]) <= 6) & (np.abs(p[:, 2]) <= 12)
    bone[block] = arrays.CRANIUM
    img[arrays.BONE] = bone
    img[arrays.TISSUE] = np.where(block, arrays.BONE_TISSUE, arrays.FAT).astype(np.uint8)
    return img


def test_cut_bones_by_planes(skull):
    plan = Plan((Osteotomy("maxilla", cut=(((0, 0, 4.5), (0, 0, -1)), ((0, 0, -0.5), (0, 0, 1)))),
                 Osteotomy("mandible", cut=(((0, 0, -0.5), (0, 0, -1)), ((0, 2.5, 0), (0, 1, 0))))))
    before = skull[arrays.BONE].copy()
    out = cut_bones(skull, plan)
    np.testing.assert_array_equal(skull[arrays.BONE], before)  # input untouched
    p, bone = out.points, out[arrays.BONE]
    block = before > 0
    np.testing.assert_array_equal(bone == arrays.MAXILLA, block & (p[:, 2] >= 0) & (p[:, 2] <= 4))
    np.testing.assert_array_equal(bone == arrays.MANDIBLE, block & (p[:, 2] <= -1) & (p[:, 1] >= 3))
    assert np.all(bone[block & (p[:, 2] > 4)] == arrays.CRANIUM)
    assert np.all(bone[~block] == 0)


def test_cut_bones_errors(skull):
    with pytest.raises(ValueError, match="moves segment 'mandible'.*only \\['cranium'\\]"):
        cut_bones(skull, TABLE_II[3])  # no mandible label and no planes
    outside = Plan((Osteotomy("maxilla", cut=(((0, 0, 100), (0, 0, 1)),)),))
    with pytest.raises(ValueError, match="contain no bone"):
        cut_bones(skull, outside)
    with pytest.raises(TypeError, match="plan must be a pvcmf.Plan"):
        cut_bones(skull, {"maxilla": 1})
    with pytest.raises(ValueError, match="no point array 'bone'"):
        cut_bones(pv.ImageData(dimensions=(2, 2, 2)), TABLE_II[1])


def test_segment_surface_on_its_box_is_that_of_the_whole_image():
    """A segment's surface is contoured on the segment's box (plus a margin wider than the
    smoothing) instead of the whole image: the same points, bit for bit, for a segment
    inside the image and one the image's border cuts."""
    from scipy import ndimage

    from pvcmf.filters.osteotomy import _segment_surface

    img = pv.ImageData(dimensions=(70, 60, 50), spacing=(1.0, 0.8, 1.25), origin=(-30, -20, -25))
    p = np.asarray(img.points)
    for mask in ((p[:, 0] / 12) ** 2 + (p[:, 1] / 9) ** 2 + (p[:, 2] / 10) ** 2 <= 1,
                 (np.abs(p[:, 0] - 20) <= 20) & (np.abs(p[:, 1]) <= 8) & (p[:, 2] < -5)):
        ours = _segment_surface(img, mask, 0.6)
        vol = ndimage.gaussian_filter(mask.reshape(img.dimensions, order="F").astype(np.float32),
                                      0.6, mode="constant")
        whole = pv.ImageData(dimensions=np.asarray(img.dimensions) + 2, spacing=img.spacing,
                             origin=np.asarray(img.origin) - np.asarray(img.spacing))
        whole["m"] = np.pad(vol, 1).ravel(order="F")
        reference = whole.contour([0.5], scalars="m", method="flying_edges")
        assert ours.n_points == reference.n_points > 100
        np.testing.assert_array_equal(ours.points, reference.points)
        np.testing.assert_array_equal(ours.faces, reference.faces)


def test_move_bones_surfaces_and_labels(skull):
    plan = Plan((Osteotomy("mandible", (1.0, -2.0, 3.0), (4.0, 0.0, 0.0),
                           cut=(((0, 0, -0.5), (0, 0, -1)),)),))
    labels = cut_bones(skull, plan)
    mandible = labels[arrays.BONE] == arrays.MANDIBLE
    centroid = labels.points[mandible].mean(axis=0)
    rot = Rotation.from_euler("x", 4.0, degrees=True).as_matrix()

    post = move_bones(skull, plan)
    assert set(post.keys()) == {"cranium", "mandible"}
    pre_pts = post["mandible"].points - post["mandible"]["displacement"]
    expect = (pre_pts - centroid) @ rot.T + centroid + [1.0, 3.0, -2.0]
    np.testing.assert_allclose(post["mandible"].points, expect, atol=1e-9)
    assert post["mandible"].field_data["moved"][0] == 1
    assert post["cranium"].field_data["moved"][0] == 0
    np.testing.assert_allclose(post["cranium"]["displacement"], 0.0)
    # the closed surface encloses the segment's volume (1 mm voxels)
    assert post["mandible"].volume == pytest.approx(mandible.sum(), rel=0.15)

    moved = move_bones(skull, plan, output="labels")
    assert isinstance(moved, pv.ImageData)
    new = moved[arrays.BONE] == arrays.MANDIBLE
    assert abs(int(new.sum()) - int(mandible.sum())) <= 0.1 * mandible.sum()
    np.testing.assert_allclose(moved.points[new].mean(axis=0),
                               centroid + [1.0, 3.0, -2.0], atol=0.3)
    assert not np.any(moved[arrays.BONE][mandible & ~new] == arrays.MANDIBLE)
    with pytest.raises(ValueError, match="output must be"):
        move_bones(skull, plan, output="mesh")


def test_segment_transforms_pivot_default_and_given(skull):
    labels = cut_bones(skull, Plan((Osteotomy("maxilla", cut=(((0, 0, 0), (0, 0, 1)),)),)))
    plan = Plan((Osteotomy("maxilla", rotation=(0, 10, 0)),))
    m = segment_transforms(labels, plan)[arrays.MAXILLA]
    c = labels.points[labels[arrays.BONE] == arrays.MAXILLA].mean(axis=0)
    np.testing.assert_allclose(m[:3, :3] @ c + m[:3, 3], c, atol=1e-9)  # centroid fixed
    given = Plan((Osteotomy("maxilla", rotation=(0, 10, 0), pivot=(1, 2, 3)),))
    m = segment_transforms(labels, given)[arrays.MAXILLA]
    np.testing.assert_allclose(m[:3, :3] @ [1, 2, 3] + m[:3, 3], [1, 2, 3], atol=1e-9)


def test_check_segments_json_dict(skull):
    data = json.loads(json.dumps(TABLE_II[1].to_dict()))
    assert Plan.from_dict(data) == TABLE_II[1]
    with pytest.raises(ValueError, match="'maxilla'.*has only \\['cranium'\\]"):
        TABLE_II[1].check_segments(skull)
