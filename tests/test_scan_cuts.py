"""A head cut by the scan (flat, or by the round field of view): found, warned about, kept
with the run, marked on the skin and drawn apart in the face figures."""

import json

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.field_of_view import (cut_planes, cuts_array, fov_circles, fov_cuts,
                                         on_scan_cuts)


@pytest.fixture(scope="module")
def cut_run(tmp_path_factory):
    """A virtual patient's CT cut 20 mm into the face by the image's front end."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    ct = case.ct
    y = np.asarray(ct.points)[:, 1]
    front = float(np.percentile(y[np.asarray(ct[arrays.CT]) > -300], 99)) - 20.0
    j = int((front - ct.origin[1]) / ct.spacing[1])
    voi = [0, ct.dimensions[0] - 1, 0, j, 0, ct.dimensions[2] - 1]
    out = tmp_path_factory.mktemp("cut")
    res = simulate(ct.extract_subset(voi), case.plan, out, predict=False, figures=False)
    return res, out, ct.origin[1] + j * ct.spacing[1]


def test_a_face_cut_by_the_scan_is_in_the_summary_and_the_report(cut_run):
    from pvcmf.report import write_report

    res, out, _ = cut_run
    flat = [w for w in res.warnings if "cut flat on the anterior" in w]
    assert len(flat) == 1, res.warnings
    summary = json.loads((out / "summary.json").read_text())
    assert flat[0] in summary["warnings"]
    page = write_report(out, result=res).read_text()
    assert "<h2>Warnings</h2>" in page and "cut flat on the anterior" in page


def test_the_skin_on_the_cut_is_marked_and_nothing_else(cut_run):
    res, _, end = cut_run
    cuts = np.asarray(res.labels.field_data[arrays.SCAN_CUTS]).reshape(-1, 8)
    assert cuts.shape == (1, 8) and cuts[0, :2].tolist() == [1.0, 1.0]  # +y, the face
    assert cuts[0, 2] == pytest.approx(end) and cuts[0, 7] == 0.0  # the image's end
    skin = res.skin_pre
    cut = np.asarray(skin[arrays.SKIN_CUT]).astype(bool)
    y = np.asarray(skin.points)[:, 1]
    assert cut.sum() > 50
    assert y[cut].min() >= end - 1.5 * res.labels.spacing[1] - 1e-9
    # the skin is open at the scan's end: its points there all lie on the cut
    assert np.all(cut[y >= end - 0.5 * res.labels.spacing[1]])


def test_the_crumple_metric_leaves_the_scan_s_edge_out(cut_run, monkeypatch):
    """The skin on the cut is modelled (it moves with the face) but is no skin to crumple:
    the crumple metric checks none of its edges, and the summary's modelled points still
    count it."""
    from scipy.spatial import cKDTree

    from pvcmf.filters import skin_prediction
    from pvcmf.pipeline import simulate

    res, _, _ = cut_run
    seen = []

    def spy(skin, *args, modelled=None, **kwargs):
        seen.append((np.array(skin.points), np.array(modelled)))
        return metric(skin, *args, modelled=modelled, **kwargs)

    metric = skin_prediction.crumple_metric
    monkeypatch.setattr(skin_prediction, "crumple_metric", spy)
    run = simulate(None, res.plan, labels=res.labels, n_tets=3000, muscles=False,
                   figures=False)
    skin = run.skin_post
    cut = np.asarray(skin[arrays.SKIN_CUT]).astype(bool)
    modelled = np.asarray(skin[arrays.SKIN_MODELLED]).astype(bool)
    assert (cut & modelled).sum() > 20  # the cut moves with the face
    (points, checked), = seen
    gap, near = cKDTree(np.asarray(run.skin_pre.points)).query(points)
    assert gap.max() < 1e-6
    assert checked.any() and not np.any(checked & cut[near])
    assert skin.field_data[arrays.SKIN_MODELLED_POINTS][0] == modelled.sum()


def test_without_cuts_nothing_is_on_a_cut():
    labels = pv.ImageData(dimensions=(5, 5, 5))
    assert not on_scan_cuts(np.zeros((4, 3)), labels).any()
    with pytest.raises(ValueError, match=r"points must have shape \(n, 3\), got \(4, 2\)"):
        on_scan_cuts(np.zeros((4, 2)), labels)


def test_cut_planes_name_the_edge_of_the_field_of_view_apart_from_the_image_end():
    """A cut inside the image with the scanner's padding beyond it is the field of view's
    edge; the skin on it is marked within one and a half voxels of its plane."""
    head = np.zeros((40, 40, 40), bool)
    head[5:35, 5:30, 5:35] = True
    vol = np.where(head, 0.0, -1000.0)
    vol[:, 30:, :] = -3024.0  # padding beyond y = 30
    c, = cut_planes(head, (1.0, 1.0, 1.0), vol=vol)
    assert (c["axis"], c["sign"], c["at"], c["edge"]) == (1, 1, 29.0, True)
    assert "field of view's edge" in c["message"]
    labels = pv.ImageData(dimensions=(40, 40, 40))
    labels.field_data[arrays.SCAN_CUTS] = cuts_array([c])
    on = on_scan_cuts([[20, 29, 20], [20, 27.4, 20], [20, 27.6, 20], [2, 29, 20]], labels)
    assert on.tolist() == [True, False, True, False]


def test_face_views_draw_the_cut_skin_in_its_own_colour():
    from pvcmf.figures import face_views as fv

    skin = pv.Sphere(radius=80.0, theta_resolution=60, phi_resolution=60)
    plain = fv.face_comparison(skin, skin, ("frontal",), window_size=(400, 220))
    before = plain.screenshot(return_img=True)[..., :3].astype(int)
    plain.close()
    marked = skin.copy()
    marked.point_data[arrays.SKIN_CUT] = (np.asarray(skin.points)[:, 2] > 30).astype(np.uint8)
    p = fv.face_comparison(marked, marked, ("frontal",), window_size=(400, 220))
    after = p.screenshot(return_img=True)[..., :3].astype(int)
    p.close()
    bluish = lambda img: int(((img[..., 2] - img[..., 0]) > 20).sum())  # noqa: E731
    assert bluish(before) == 0 and bluish(after) > 500


def _padded_slices(n=96, centre=(45.0, 50.0), radius=40.0, nz=5, seed=0):
    """CT slices of noisy air clipped at -1024 inside a circle, -1024 padding outside."""
    i, j = np.mgrid[:n, :n]
    inside = (i - centre[0]) ** 2 + (j - centre[1]) ** 2 <= radius ** 2
    noise = np.random.default_rng(seed).normal(-1000.0, 25.0, (n, n, nz))
    return np.where(inside[:, :, None], np.maximum(noise, -1024.0), -1024.0), i, j


def test_fov_circles_find_the_reconstruction_circle_in_clipped_air():
    vol, _, _ = _padded_slices()
    c = fov_circles(vol, -400.0, spacing=(0.5, 0.5, 2.0))
    assert np.allclose(c[:, :2], [22.5, 25.0], atol=0.1)  # mm
    assert np.allclose(c[:, 2], 20.0, atol=0.1)  # the boundary, half a voxel beyond the rim
    vol[:, :, 2] = np.maximum(np.random.default_rng(1).normal(-1000.0, 25.0, vol.shape[:2]),
                              -1024.0)  # a slice without padding: its clipped air is no circle
    assert np.isnan(fov_circles(vol, -400.0)[2]).all()
    vol[:, 80:, 3] = -1024.0  # padding beyond a straight edge: no circle, and no error
    vol[:, :80, 3] = np.maximum(vol[:, :80, 3], -1023.0)
    assert np.isnan(fov_circles(vol, -400.0)[3]).all()


def test_a_head_outlined_on_padding_valued_air_is_no_field_of_view():
    """Uniform air at the image's minimum around a round head: the rim is all head."""
    _, i, j = _padded_slices()
    ball = np.hypot(i - 48.0, j - 48.0) < 30.0
    vol = np.where(ball[:, :, None], 40.0, -1000.0) * np.ones((1, 1, 4))
    assert np.isnan(fov_circles(vol, -400.0)).all()


def test_fov_cuts_keep_the_slices_whose_circle_cuts_the_head_and_mark_their_skin():
    vol, i, j = _padded_slices(nz=6)
    circles = fov_circles(vol, -400.0)  # centre (45, 50), radius 40 voxels, 1 mm
    head = np.zeros(vol.shape, bool)
    head[:, :, 1:5] = (np.hypot(i - 45.0, j - 70.0) < 25.0)[:, :, None]  # out to j = 95
    head &= vol > -1024.0  # the scan holds only what lies inside its circle
    rows, message = fov_cuts(circles, head, (1.0, 1.0, 1.0), origin=(0.0, 0.0, 10.0))
    assert rows[:, 0].tolist() == [11.0, 12.0, 13.0, 14.0]  # z of the slices 1-4
    assert np.allclose(rows[:, 1:], [45.0, 50.0, 40.0], atol=0.5)
    assert "round field of view (radius 40 mm) from z = 11 to 14 mm" in message
    assert fov_cuts(circles, head & (np.hypot(i - 45.0, j - 50.0) < 30.0)[:, :, None],
                    (1.0, 1.0, 1.0))[1] is None  # the head inside the circle: no cut
    labels = pv.ImageData(dimensions=vol.shape, origin=(0.0, 0.0, 10.0))
    labels.field_data[arrays.SCAN_FOV] = rows.ravel()
    on = on_scan_cuts([[45, 89.5, 12], [45, 88.0, 12.4], [45, 89.5, 16], [45, 70, 12],
                       [45, 88.8, 14.5]], labels)
    assert on.tolist() == [True, False, False, False, True]


@pytest.fixture(scope="module")
def round_fov_run(tmp_path_factory):
    """A virtual patient's CT whose round field of view cuts 15 mm into the nose."""
    import pvcmf
    from pvcmf.pipeline import simulate

    case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
    ct = case.ct.copy()
    pts = np.asarray(ct.points)
    values = np.asarray(ct[arrays.CT]).copy()
    body = pts[values > -300]
    # a circle 20 mm behind the middle of the head, through a point 15 mm behind its front
    centre = np.array([0.5 * (body[:, 0].min() + body[:, 0].max()),
                       0.5 * (body[:, 1].min() + body[:, 1].max()) - 20.0])
    radius = float(body[:, 1].max() - centre[1]) - 15.0
    values[np.hypot(*(pts[:, :2] - centre).T) > radius] = -2048.0
    ct[arrays.CT] = values
    res = simulate(ct, case.plan, tmp_path_factory.mktemp("round"), predict=False,
                   figures=False)
    return res, centre, radius


def test_a_face_cut_by_the_round_field_of_view_is_warned_about_and_marked(round_fov_run):
    res, centre, radius = round_fov_run
    assert any("round field of view" in w for w in res.warnings), res.warnings
    rows = np.asarray(res.labels.field_data[arrays.SCAN_FOV]).reshape(-1, 4)
    assert np.allclose(rows[:, 1:3], centre, atol=1.0) and np.allclose(rows[:, 3], radius, atol=1.5)
    skin = res.skin_pre
    cut = np.asarray(skin[arrays.SKIN_CUT]).astype(bool)
    rho = np.hypot(*(np.asarray(skin.points)[:, :2] - centre).T)
    assert cut.sum() > 50
    reach = 1.5 * res.labels.spacing[0]
    assert rho[cut].min() >= radius - reach - 1.5  # (the circle fitted to within a voxel)
    z = np.asarray(skin.points)[:, 2]
    in_cut_slices = (z >= rows[:, 0].min()) & (z <= rows[:, 0].max())
    assert np.all(cut[(rho >= radius - 0.5) & in_cut_slices])  # the skin on the circle


def test_skin_seen_through_an_opening_of_a_flat_cut_is_marked():
    """A sinus the cut opened: its walls are the scan's edge seen through the cut, not the
    patient's skin; a closed pocket behind the cut and the skin beside it are not."""
    head = np.zeros((40, 40, 40), bool)
    head[5:35, 5:30, 5:35] = True  # cut flat at y = 29
    head[15:25, 20:30, 15:25] = False  # a sinus open at the cut
    head[8:12, 18:25, 8:12] = False  # a pocket closed by 4 voxels of tissue
    head[18:22, 10:14, 18:22] = False  # a pocket behind the sinus' back wall
    vol = np.where(head, 0.0, -1000.0)
    vol[:, 30:, :] = -3024.0
    c, = cut_planes(head, (1.0, 1.0, 1.0), vol=vol)
    labels = pv.ImageData(dimensions=head.shape)
    labels.field_data[arrays.SCAN_CUTS] = cuts_array([c])
    labels.point_data[arrays.TISSUE] = np.where(head, arrays.FAT, arrays.AIR).astype(
        np.uint8).ravel(order="F")
    points = [[20, 19.5, 20],  # the sinus' back wall, facing the opening
              [15.5, 24, 17],  # its side wall: looks out along the cut's normal
              [10, 17.5, 10],  # the closed pocket's back wall
              [4.5, 20, 20],  # the head's side, beside the cut
              [20, 9.5, 20]]  # behind the sinus, its ray blocked by the back wall
    on = on_scan_cuts(points, labels)
    assert on.tolist() == [True, True, False, False, False]
    del labels.point_data[arrays.TISSUE]  # without the labels' tissue: the plane alone
    assert not on_scan_cuts(points, labels)[:2].any()


def test_the_profile_overlay_marks_the_silhouette_on_the_scan_s_edge():
    """The midsagittal silhouette over skin marked as cut gets a band of the cut colour;
    the skin itself keeps its arrays."""
    import matplotlib.colors as mcolors

    from pvcmf.figures.profiles import anterior_profile, profile_overlay
    from pvcmf.figures.skin_marks import CUT_COLOR

    skin = pv.Sphere(radius=80.0, theta_resolution=90, phi_resolution=90)
    marked = skin.copy()
    marked.point_data[arrays.SKIN_CUT] = (np.asarray(skin.points)[:, 2] > 40).astype(np.uint8)
    line, on = anterior_profile(marked, 0.0, on_cut=True)
    assert on.any() and np.all(line[on, 1] > 36.0) and np.all(on[line[:, 1] > 44.0])
    assert "_on_cut" not in marked.point_data
    assert not anterior_profile(skin, 0.0, on_cut=True)[1].any()
    rgb = np.array(mcolors.to_rgb(CUT_COLOR)) * 255

    def cut_pixels(fig):
        fig.canvas.draw()
        img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(float)
        return int((np.abs(img - rgb).max(axis=2) < 12).sum())

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    plain, cut = profile_overlay(skin, skin), profile_overlay(marked, marked)
    FigureCanvasAgg(plain), FigureCanvasAgg(cut)
    assert cut_pixels(plain) == 0 and cut_pixels(cut) > 200
    assert "the scan's edge (cut)" in [t.get_text() for t in cut.legends[0].get_texts()]


def test_the_run_s_pre_operative_faces_draw_the_cut_skin_in_its_own_colour():
    """``face_pre.png`` (written with or without a prediction) colours the cut as the
    comparisons do."""
    from types import SimpleNamespace

    from pvcmf.outputs import render

    skin = pv.Sphere(radius=80.0, theta_resolution=60, phi_resolution=60)
    marked = skin.copy()
    marked.point_data[arrays.SKIN_CUT] = (np.asarray(skin.points)[:, 1] > 30).astype(np.uint8)
    bluish = lambda img: int(((img[..., 2].astype(int) - img[..., 0]) > 20).sum())  # noqa: E731
    shots = [render(SimpleNamespace(skin_pre=s, skin_post=None, skeleton=None, labels=None))
             ["face_pre.png"] for s in (skin, marked)]
    assert bluish(shots[0]) == 0 and bluish(shots[1]) > 500


def test_displacement_maps_draw_the_cut_skin_apart_and_leave_it_out_of_the_range():
    """The cut's points take the cut colour instead of the map's, set no colour range, and
    the caption names the colour; a skin without cuts keeps its colours and caption."""
    from pvcmf.figures import face_views as fv

    skin = pv.Sphere(radius=80.0, theta_resolution=60, phi_resolution=60)
    pts = np.asarray(skin.points)
    u = np.zeros_like(pts)
    u[:, 1] = np.where(pts[:, 2] > 30, 6.0, 0.5 * pts[:, 2] / 80.0)  # the cut moves most
    skin.point_data[arrays.DISPLACEMENT] = u
    marked = skin.copy()
    marked.point_data[arrays.SKIN_CUT] = (pts[:, 2] > 30).astype(np.uint8)
    assert fv.displacement_limit(skin, "ap") == pytest.approx(6.0)
    assert fv.displacement_limit(marked, "ap") < 0.6

    def shot(s):
        p = fv.displacement_views(s, "ap", ("frontal",), window_size=(300, 360), limit=6.0)
        texts = [t.GetInput() for t in p.renderers[1].GetViewProps()
                 if t.IsA("vtkTextActor") and t.GetInput()]
        img = p.screenshot(return_img=True)[:280, :, :3].astype(int)  # the view, not the bar
        p.close()
        return img, texts

    (plain, plain_texts), (cut, cut_texts) = shot(skin), shot(marked)
    red = lambda img: int(((img[..., 0] - img[..., 2]) > 60).sum())  # noqa: E731
    assert red(plain) > 2000 and red(cut) == 0
    assert dark_grey(top(cut)) > max(1000, 10 * dark_grey(top(plain)))  # (text is grey)
    assert any("dark grey: the scan's edge" in t for t in cut_texts)
    assert not any("scan's edge" in t for t in plain_texts)


def test_fig6_draws_the_scan_s_edge_apart_and_fig7_8_leave_it_out(tmp_path):
    """The validation figures of a case: the error map colours the cut in the cut colour
    (not as a 6 mm error) and says so; the box plot and curve count the rest only."""
    from pvcmf.figures.validation import fig6_error_maps
    from pvcmf.report.figures import judged_distances

    skin = pv.Sphere(radius=80.0, theta_resolution=60, phi_resolution=60)
    pts = np.asarray(skin.points)
    skin.point_data[arrays.DISTANCE] = np.where(pts[:, 2] > 30, 6.0, 0.0)
    marked = skin.copy()
    marked.point_data[arrays.SKIN_CUT] = (pts[:, 2] > 30).astype(np.uint8)

    def shot(s):
        pl = fig6_error_maps({1: {"proposed": s}}, window_size=(300, 340))
        texts = [t.GetInput() for t in pl.renderer.GetViewProps()
                 if t.IsA("vtkTextActor") and t.GetInput()]
        img = pl.screenshot(return_img=True)[:250, :, :3].astype(int)  # above the bar
        pl.close()
        return img, texts

    (plain, plain_texts), (cut, cut_texts) = shot(skin), shot(marked)
    deep = lambda img: int(((img[..., 2] - img[..., 0]) > 90).sum())  # noqa: E731 (+6 mm)
    assert deep(plain) > 2000 and deep(cut) == 0
    assert dark_grey(top(cut)) > max(1000, 10 * dark_grey(top(plain)))  # (text is grey)
    assert any("the scan's edge" in t for t in cut_texts)
    assert not any("the scan's edge" in t for t in plain_texts)
    assert judged_distances(marked).size == int((pts[:, 2] <= 30).sum())
    assert judged_distances(skin).size == skin.n_points


def dark_grey(img):
    """Pixels in the colour maps' cut colour (a neutral dark grey), whatever the shading."""
    spread = img.max(axis=2) - img.min(axis=2)
    mean = img.mean(axis=2)
    return int(((spread < 12) & (mean > 30) & (mean < 120)).sum())


def top(img):
    """The upper quarter of the rows the skin covers (where the tests' cut lies): a shaded
    surface turned away from the light is grey too, lower down."""
    rows = np.flatnonzero((img.min(axis=2) < 250).any(axis=1))
    return img[rows[0]:rows[0] + (rows[-1] - rows[0]) // 4]
