"""The working grid of very fine scans: block means, geometry, choice of blocks, pipeline."""

import logging

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters import working_grid
from pvcmf.filters.resolution import MAX_VOXELS, working_factors


def image(dims=(12, 9, 8), spacing=(0.5, 0.5, 0.25), seed=0, direction=None):
    img = pv.ImageData(dimensions=dims, spacing=spacing, origin=(-3.0, 2.0, 5.0))
    if direction is not None:
        img.direction_matrix = direction
    img[arrays.CT] = np.random.default_rng(seed).normal(0, 500, img.n_points).astype(np.float32)
    return img


def test_block_means_equal_an_independent_reshape():
    img = image()
    out = working_grid(img, 1.0)  # blocks of 2 x 2 x 4 voxels
    assert out.field_data[arrays.WORKING_FACTORS].tolist() == [2, 2, 4]
    vol = np.asarray(img[arrays.CT], dtype=float).reshape(img.dimensions, order="F")
    expect = vol[:12, :8, :8].reshape(6, 2, 4, 2, 2, 4).mean(axis=(1, 3, 5))
    got = np.asarray(out[arrays.CT]).reshape(out.dimensions, order="F")
    assert out.dimensions == (6, 5, 2)
    np.testing.assert_allclose(got[:, :4, :], expect, rtol=0, atol=1e-3)
    # the last block along y holds one voxel row (9 = 4 * 2 + 1): its mean over that row
    last = vol[:, 8, :].reshape(6, 2, 2, 4).mean(axis=(1, 3))
    np.testing.assert_allclose(got[:, 4, :], last, rtol=0, atol=1e-3)
    assert out[arrays.CT].dtype == np.float32


@pytest.mark.parametrize("direction", [None, pv.transformations.axis_angle_rotation(
    (1, 2, 3), 40)[:3, :3]])
def test_the_image_covers_the_same_space(direction):
    """A working voxel sits at the centre of its block (in patient space, with a direction
    matrix too), and a scan constant over the blocks gives back those constants."""
    img = image(dims=(12, 8, 8), direction=direction)
    coarse = np.random.default_rng(1).normal(0, 500, (6, 4, 2)).astype(np.float32)
    fine = np.repeat(np.repeat(np.repeat(coarse, 2, 0), 2, 1), 4, 2)
    img[arrays.CT] = fine.ravel(order="F")
    out = working_grid(img, 1.0)
    pts = np.asarray(img.points).reshape(12, 8, 8, 3, order="F")
    centres = pts.reshape(6, 2, 4, 2, 2, 4, 3).mean(axis=(1, 3, 5))
    np.testing.assert_allclose(np.asarray(out.points).reshape(6, 4, 2, 3, order="F"),
                               centres, atol=1e-9)
    np.testing.assert_allclose(np.asarray(out[arrays.CT]), coarse.ravel(order="F"), atol=1e-3)
    np.testing.assert_allclose(out.spacing, (1.0, 1.0, 1.0))
    np.testing.assert_allclose(out.direction_matrix, img.direction_matrix)
    np.testing.assert_allclose(out.field_data[arrays.SCAN_SPACING], img.spacing)


def test_a_scan_within_the_budget_keeps_its_grid_as_a_copy():
    img = image()
    img.field_data["note"] = np.array([7.0])
    before = np.array(img[arrays.CT])
    out = working_grid(img)
    assert out.dimensions == img.dimensions and out.spacing == img.spacing
    np.testing.assert_array_equal(out[arrays.CT], before)
    assert not np.shares_memory(out[arrays.CT], img[arrays.CT])
    assert out.field_data[arrays.WORKING_FACTORS].tolist() == [1, 1, 1]
    assert out.field_data["note"].tolist() == [7.0]
    assert arrays.WORKING_FACTORS not in img.field_data  # the input is kept
    np.testing.assert_array_equal(img[arrays.CT], before)


def test_auto_grows_the_finest_axis_until_the_image_fits():
    img = image(dims=(12, 9, 8), spacing=(0.5, 0.5, 0.25))  # 864 voxels
    out = working_grid(img, max_voxels=300)
    f = out.field_data[arrays.WORKING_FACTORS].tolist()
    assert out.n_points <= 300 and f == [2, 1, 2]  # the 0.25 mm slices first, then x
    assert working_factors((12, 9, 8), (0.5, 0.5, 0.25), max_voxels=100) == (2, 2, 3)
    assert working_factors((512, 512, 512), (0.2, 0.2, 0.2)) == (1, 1, 1)  # 2**27: fits
    assert working_factors((600, 600, 600), (0.2,) * 3) == (2, 1, 1)
    assert working_factors((800, 800, 650), (0.2,) * 3) == (2, 2, 1)
    assert working_factors((2, 2, 2), (1, 1, 1), max_voxels=1) == (2, 2, 2)  # one voxel
    assert MAX_VOXELS == 2**27
    assert working_factors((12, 9, 8), (0.5, 0.5, 0.25), 10.0) == (12, 9, 8)  # at most all


@pytest.mark.parametrize("spacing, message", [
    ("fine", "spacing must be 'auto', a size in mm or None, got 'fine'"),
    (0.0, "a size in mm > 0"),
    (-1.0, "a size in mm > 0"), (float("nan"), "a size in mm > 0"), (True, "a size in mm")])
def test_bad_spacings_are_refused(spacing, message):
    with pytest.raises(ValueError, match=message):
        working_grid(image(), spacing)


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="max_voxels must be a positive integer, got 0"):
        working_grid(image(), max_voxels=0)
    with pytest.raises(TypeError, match="ct must be a pyvista.ImageData, got PolyData"):
        working_grid(pv.Sphere())
    img = image()
    del img.point_data[arrays.CT]
    with pytest.raises(ValueError, match="ct"):
        working_grid(img)
    img = image()
    img[arrays.CT][5] = np.nan
    with pytest.raises(ValueError, match="1 NaN/inf"):
        working_grid(img, 1.0)


def test_simulate_works_on_the_grid_asked_for_and_says_so(tmp_path):
    """The virtual patient at 1.5 mm on a 3 mm working grid is the same head as on its own
    grid (head volume within 2 %, its centroid within 0.5 mm: a working voxel off its
    block's centre by half a block moves it 0.75 mm), and the run records the blocks."""
    import json

    import pvcmf
    from pvcmf.pipeline import simulate

    fine = pvcmf.datasets.phantom(patient=1, spacing=1.5)
    res = simulate(fine.ct, fine.plan, tmp_path / "run", predict=False, figures=False,
                   working_spacing=3.0)
    ref = simulate(fine.ct, fine.plan, predict=False, figures=False, working_spacing=1.0)
    np.testing.assert_allclose(res.labels.spacing, (3.0, 3.0, 3.0))
    assert res.working_grid["factors"] == [2, 2, 2]
    assert res.working_grid["scan_voxels"] == fine.ct.n_points

    def head(labels):
        inside = np.asarray(labels[arrays.TISSUE]) != arrays.AIR
        return (inside.sum() * np.prod(labels.spacing),
                np.asarray(labels.points)[inside].mean(axis=0))

    (v, c), (v_ref, c_ref) = head(res.labels), head(ref.labels)
    assert abs(v - v_ref) <= 0.02 * v_ref, (v, v_ref)
    assert np.abs(c - c_ref).max() <= 0.5, (c, c_ref)
    assert "working grid" in res.timings and "working grid" not in res.warnings
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["working_grid"]["spacing_mm"] == [3.0, 3.0, 3.0]
    assert ref.skipped["working grid"] == "the scan's own grid" and not ref.working_grid
    np.testing.assert_allclose(ref.labels.spacing, fine.ct.spacing)


def test_auto_warns_and_none_keeps_the_grid(monkeypatch, caplog):
    import pvcmf
    from pvcmf.filters import resolution
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    monkeypatch.setattr(resolution, "MAX_VOXELS", case.ct.n_points // 4)
    caplog.set_level(logging.WARNING, logger="pvcmf")
    res = simulate(case.ct, case.plan, predict=False, figures=False)
    assert res.labels.n_points <= case.ct.n_points // 4
    assert [w for w in res.warnings if "averaged in blocks of" in w and "none" in w]
    kept = simulate(case.ct, case.plan, predict=False, figures=False, working_spacing=None)
    assert kept.labels.dimensions == case.ct.dimensions
    assert kept.skipped["working grid"] == "working_spacing=None"
    with pytest.raises(ValueError, match="^working_spacing must be 'auto'"):
        simulate(case.ct, case.plan, predict=False, working_spacing="fine")


def test_the_command_line_takes_a_working_spacing():
    from pvcmf.cli import build_parser

    parse = build_parser().parse_args
    base = ["simulate", "--ct", "x", "--plan", "p.toml", "--out", "o"]
    assert parse(base).working_spacing == "auto"
    assert parse(base + ["--working-spacing", "none"]).working_spacing is None
    assert parse(base + ["--working-spacing", "0.6"]).working_spacing == 0.6
    with pytest.raises(SystemExit):
        parse(base + ["--working-spacing", "-1"])
