"""The face figures: view conventions, visibility-based colour ranges, image baselines."""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.figures import face_views as fv

RED = np.array([255, 0, 0])


def _head():
    """An ellipsoidal 'head' in the patient frame (x left, y anterior, z superior), a nose."""
    head = pv.ParametricEllipsoid(70.0, 90.0, 100.0, u_res=60, v_res=60, w_res=60)
    nose = pv.Cone(center=(0.0, 95.0, 0.0), direction=(0.0, 1.0, 0.0), height=25.0,
                   radius=12.0, resolution=24)
    return head.triangulate().clean(), nose.triangulate().clean()


def _marker_columns(view):
    """Image columns of a red marker on the patient's LEFT cheek (+x), seen from ``view``."""
    head, _ = _head()
    marker = pv.Sphere(radius=10.0, center=(45.0, 65.0, -10.0))
    p = pv.Plotter(off_screen=True, window_size=[300, 300])
    p.set_background("white")
    fv.add_patient_mesh(p, head, color="peachpuff", lighting=False)
    fv.add_patient_mesh(p, marker, color="red", lighting=False)
    fv.set_view(p, fv.to_display(head).bounds, view)
    img = p.screenshot(return_img=True)
    p.close()
    red = np.all(np.abs(img[..., :3].astype(int) - RED) < 30, axis=-1)
    assert red.sum() > 20, "the marker is not in the image"
    return np.nonzero(red)[1], img.shape[1]


def test_frontal_view_shows_patient_left_on_viewer_right():
    cols, width = _marker_columns("frontal")
    assert cols.mean() > 0.6 * width


def test_profile_view_faces_right_and_shows_the_right_side():
    head, nose = _head()
    p = pv.Plotter(off_screen=True, window_size=[300, 300])
    fv.add_patient_mesh(p, head, color="peachpuff", lighting=False)
    fv.add_patient_mesh(p, nose, color="red", lighting=False)
    fv.set_view(p, fv.to_display(head + nose).bounds, "profile")
    img = p.screenshot(return_img=True)
    p.close()
    red = np.all(np.abs(img[..., :3].astype(int) - RED) < 30, axis=-1)
    assert np.nonzero(red)[1].mean() > 0.7 * img.shape[1]  # anterior on the viewer's right
    # a marker on the patient's left cheek is hidden behind the head in the right profile
    with pytest.raises(AssertionError, match="not in the image"):
        _marker_columns("profile")


def test_visible_points_hides_the_back_and_the_inside():
    outer = pv.Sphere(radius=50.0, theta_resolution=40, phi_resolution=40)
    inner = pv.Sphere(radius=20.0, theta_resolution=20, phi_resolution=20)
    both = outer.merge(inner)
    seen = fv.visible_points(both, "frontal")
    pts = np.asarray(both.points)
    r = np.linalg.norm(pts, axis=1)
    assert not seen[r < 30].any()  # inner sphere: hidden
    front = (r > 30) & (pts[:, 1] > 10.0)
    back = (r > 30) & (pts[:, 1] < -10.0)
    assert seen[front].mean() > 0.95
    assert not seen[back].any()


def test_colour_range_ignores_hidden_points():
    outer = pv.Sphere(radius=50.0, theta_resolution=40, phi_resolution=40)
    inner = pv.Sphere(radius=20.0, theta_resolution=20, phi_resolution=20)
    skin = outer.merge(inner)
    pts = np.asarray(skin.points)
    u = np.zeros((skin.n_points, 3))
    u[:, 1] = np.clip(pts[:, 1] / 50.0, 0.0, None)  # up to 1 mm on the visible front
    inside = np.linalg.norm(pts, axis=1) < 30
    u[inside, 1] = -100.0  # a large move where no camera sees it (the mouth's inside)
    back = pts[:, 1].argmin()
    u[back, 1] = 500.0  # and on the back of the head
    skin.point_data[arrays.DISPLACEMENT] = u
    limit = fv.displacement_limit(skin, "ap", views=("frontal", "three_quarter"))
    assert 0.5 < limit <= 1.0
    everything = fv.symmetric_limit(u[:, 1], np.ones(skin.n_points, bool))
    assert everything > 50.0  # what an all-points range would have been


def test_signed_displacement_components():
    sphere = pv.Sphere(radius=10.0, theta_resolution=24, phi_resolution=24)
    sphere.point_data[arrays.DISPLACEMENT] = 2.0 * np.asarray(sphere.points) / 10.0
    assert np.allclose(fv.signed_displacement(sphere, "normal"), 2.0, atol=0.05)
    assert np.allclose(fv.signed_displacement(sphere, "magnitude"), 2.0)
    assert np.allclose(fv.signed_displacement(sphere, "ap"), 0.2 * sphere.points[:, 1])
    with pytest.raises(ValueError, match="component"):
        fv.signed_displacement(sphere, "sideways")


def test_anterior_profile_is_the_front_outline():
    head, nose = _head()
    line = fv.anterior_profile(head + nose, 0.0)
    assert line[:, 0].max() == pytest.approx(95.0 + 25.0 / 2, abs=1.0)  # the nose tip
    assert np.all(np.diff(line[:, 1]) > 0)
    with pytest.raises(ValueError, match="does not cut"):
        fv.anterior_profile(head, 500.0)


def _pre_post():
    head, nose = _head()
    pre = (head + nose).triangulate().clean()
    pts = np.asarray(pre.points)
    # a chin setback: points low and anterior move back by up to 4 mm
    u = np.zeros_like(pts)
    u[:, 1] = -4.0 * np.clip((-pts[:, 2] - 20.0) / 60.0, 0, 1) * np.clip(pts[:, 1] / 90.0, 0, 1)
    pre.point_data[arrays.DISPLACEMENT] = u
    post = pre.copy()
    post.points = pts + u
    return pre, post


def test_face_comparison(verify_image_cache):
    pre, post = _pre_post()
    fv.face_comparison(pre, post, views=("frontal", "profile"), window_size=(440, 500)).show()


def test_displacement_views(verify_image_cache):
    pre, _ = _pre_post()
    fv.displacement_views(pre, "ap", window_size=(600, 400)).show()


def test_profile_overlay(verify_chart):
    pre, post = _pre_post()
    verify_chart(fv.profile_overlay(pre, post, figsize=(3.5, 4.5)))


def test_profile_overlay_legend_covers_no_line():
    """The legend lies below the axes, so no part of either silhouette is hidden (a
    legend inside the axes covered the neck's end of a real scan's predicted line)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    pre, post = _pre_post()
    for size in ((3.5, 4.5), (4.5, 6.0)):
        fig = fv.profile_overlay(pre, post, figsize=size)
        FigureCanvasAgg(fig).draw()
        renderer = fig.canvas.get_renderer()
        (legend,) = fig.legends
        box, axes = legend.get_window_extent(renderer), fig.axes[0].get_window_extent(renderer)
        labels = fig.axes[0].xaxis.label.get_window_extent(renderer)
        assert box.y1 <= min(axes.y0, labels.y0) and box.y0 >= 0.0, (box, axes, labels)
        assert [t.get_text() for t in legend.get_texts()] == ["pre-operative", "predicted"]


def test_views_are_checked():
    head, _ = _head()
    with pytest.raises(ValueError, match="view"):
        fv.visible_points(head, "top")
    with pytest.raises(ValueError, match="visible"):
        fv.symmetric_limit(np.zeros(3), np.ones(2, bool))


def test_carry_to_skin_bridges_gaps_between_regions():
    skin = pv.Plane(i_size=100.0, j_size=100.0, i_resolution=50, j_resolution=50)
    x = np.asarray(skin.points)[:, 0]
    # two boxes with a 6 mm gap between them, and nothing beyond x = 30
    patch = skin.extract_points((np.abs(x) > 3.0) & (x < 30.0), adjacent_cells=False)
    patch.point_data["v"] = np.asarray(patch.points)[:, 0].copy()
    out = fv.carry_to_skin(patch, skin, ["v"], gap=5.0)
    v = np.asarray(out["v"])
    gap = np.abs(x) < 3.0
    assert np.isfinite(v[gap]).all() and np.abs(v[gap]).max() < 6.0
    assert np.isnan(v[x > 36.0]).all()
    kept = (np.abs(x) > 3.0) & (x < 30.0)
    assert np.allclose(v[kept], x[kept], atol=1e-6)


def test_fig5_optimal_poisson_shows_patient_left_on_viewer_right():
    """Paper 001 Fig. 5 in the photographic convention: a region on the patient's left cheek
    (+x) whose optimal ratio is high (yellow on viridis) appears on the viewer's right of
    each panel."""
    import pandas as pd

    from pvcmf.figures.parameter_studies import fig5_optimal_poisson

    head, _ = _head()
    x = np.asarray(head.points)
    left_cheek = (x[:, 0] > 30.0) & (x[:, 1] > 40.0)
    low = np.where(left_cheek, 0.1, 1.0)  # small error at nu = 0.4 on the left cheek only
    df = pd.DataFrame({"case": ["P"] * 2, "nu": [0.1, 0.4],
                       "distance": [1.0 - low + 0.05, low]})
    pl = fig5_optimal_poisson(df, head, neighbours=1, window_size=(600, 300))
    img = pl.screenshot(return_img=True)
    pl.close()
    panel = img[:, : img.shape[1] // 2, :3].astype(int)
    yellow = (panel[..., 0] > 120) & (panel[..., 1] > 120) & (panel[..., 2] < 0.5 * panel[..., 1])
    cols = np.nonzero(yellow[: int(0.8 * panel.shape[0])])[1]  # above the colour bar
    assert cols.size > 20, "the left-cheek region is not in the image"
    assert cols.mean() > 0.6 * panel.shape[1]


def test_shaded_display_once_per_geometry_and_culling_keeps_the_picture():
    """Normals are computed once per geometry; a closed skin wound inward is turned
    outward and drawn with its back faces culled, giving the picture drawn without culling;
    an open surface is not culled."""
    head, _ = _head()
    inward = head.copy()
    inward.faces = head.faces.reshape(-1, 4)[:, [0, 1, 3, 2]].ravel()  # every face flipped
    first, closed = fv.shaded_display(inward)
    again, _ = fv.shaded_display(inward.copy())
    assert closed and np.shares_memory(first.points, again.points)
    tri = first.faces.reshape(-1, 4)[:, 1:]
    x = np.asarray(first.points)
    assert np.einsum("ij,ij->i", x[tri[:, 0]], np.cross(x[tri[:, 1]], x[tri[:, 2]])).sum() > 0
    images = []
    for cull in (True, False):
        p = pv.Plotter(off_screen=True, window_size=[240, 240])
        actor = fv.add_patient_mesh(p, inward, color="peachpuff")
        assert actor.prop.culling == "back"
        if not cull:
            actor.prop.culling = "none"
        fv.set_view(p, fv.to_display(head).bounds, "three_quarter")
        images.append(p.screenshot(return_img=True).astype(int))
        p.close()
    assert (np.abs(images[0] - images[1]).max(axis=-1) > 40).sum() < 20
    opened = head.clip(normal=(0.0, 0.0, 1.0), origin=(0.0, 0.0, 50.0))
    p = pv.Plotter(off_screen=True, window_size=[100, 100])
    assert fv.add_patient_mesh(p, opened.extract_surface(algorithm=None), color="red").prop.culling != "back"
    p.close()


def test_colour_range_ignores_points_the_model_does_not_cover():
    """Skin the model does not cover (the back of a whole head, the transfer's fading
    extension) sets no range, though a camera sees it."""
    skin = pv.Sphere(radius=50.0, theta_resolution=40, phi_resolution=40)
    pts = np.asarray(skin.points)
    u = np.zeros((skin.n_points, 3))
    face = pts[:, 1] > 0.0
    u[face, 1] = 2.0  # the modelled face moves 2 mm forward
    u[~face, 1] = 5.0  # not modelled: whatever it holds sets no range
    skin.point_data[arrays.DISPLACEMENT] = u
    assert fv.displacement_limit(skin, "ap") == pytest.approx(5.0)  # seen in the profile
    skin.point_data[arrays.SKIN_MODELLED] = face.astype(np.uint8)
    assert fv.displacement_limit(skin, "ap") == pytest.approx(2.0)
    assert np.array_equal(fv.modelled_points(skin), face)


def test_frame_bounds_frame_the_head_not_the_shoulders():
    head = pv.ParametricEllipsoid(75.0, 95.0, 110.0).triangulate().clean()
    shoulders = pv.Cylinder(center=(0.0, -20.0, -120.0), direction=(0.0, 0.0, 1.0),
                            radius=220.0, height=30.0).triangulate().clean()
    both = head.merge(shoulders)
    b = np.asarray(fv.frame_bounds(both))
    assert b[1] - b[0] == pytest.approx(150.0, abs=2.0)  # the head's width, not 440 mm
    assert b[3] - b[2] == pytest.approx(190.0, abs=2.0)
    assert b[4] == pytest.approx(-135.0, abs=0.5) and b[5] == pytest.approx(110.0, abs=1.0)
    assert np.allclose(fv.frame_bounds(head), fv.display_bounds(head))  # no shoulders


def _long_nosed_head():
    """A head with a nose 45 mm long and a chin 20 mm in front of the jaw, in the patient
    frame, on shoulders twice as wide (frame_bounds leaves those out of the width)."""
    head = pv.ParametricEllipsoid(72.0, 95.0, 115.0, u_res=40, v_res=40, w_res=40)
    nose = pv.Cone(center=(0.0, 110.0, 10.0), direction=(0.0, 1.0, -0.3), height=45.0,
                   radius=14.0, resolution=24)
    chin = pv.Sphere(radius=20.0, center=(0.0, 75.0, -95.0))
    shoulders = pv.Cylinder(center=(0.0, -70.0, -150.0), direction=(0.0, 0.0, 1.0),
                            radius=160.0, height=30.0)
    return pv.merge([m.triangulate().clean() for m in (head, nose, chin, shoulders)])


def _screen_coordinates(plotter, points):
    """Normalised device coordinates (-1..1 across the panel) of display-frame points."""
    aspect = plotter.renderer.GetTiledAspectRatio()
    m = plotter.camera.GetCompositeProjectionTransformMatrix(aspect, -1.0, 1.0)
    m = np.array([[m.GetElement(i, j) for j in range(4)] for i in range(4)])
    h = np.c_[points, np.ones(len(points))] @ m.T
    return h[:, :2] / h[:, 3:]


@pytest.mark.parametrize("view", ["frontal", "three_quarter", "profile"])
@pytest.mark.parametrize("window", [(300, 500), (500, 300), (400, 400)])
@pytest.mark.parametrize("fit_points", [True, False])
def test_views_fit_the_whole_head_with_a_margin(view, window, fit_points):
    """The head above the shoulders, nose and chin included, lies inside every panel with
    the margin free on each side and the title band free at the top (no image drawn),
    fitted on the skin's points or on the box of frame_bounds alone."""
    skin = _long_nosed_head()
    shown = fv.to_display(skin)
    bounds = fv.frame_bounds(skin)
    head = np.asarray(shown.points)
    head = head[head[:, 2] > -135.0]  # above the shoulders
    assert head[:, 1].max() > 130.0 and head[:, 2].min() < -114.0  # nose tip, chin
    p = pv.Plotter(off_screen=True, window_size=list(window))
    try:
        fv.set_view(p, bounds, view, points=shown.points if fit_points else None)
        xy = _screen_coordinates(p, head)
        lo, hi = np.asarray(bounds).reshape(3, 2).T
        framed = np.asarray(shown.points)
        framed = _screen_coordinates(p, framed[np.all((framed >= lo) & (framed <= hi), axis=1)])
    finally:
        p.close()
    m, t = 2.0 * fv.FRAME_MARGIN, 2.0 * fv.FRAME_TITLE
    tol = 1e-6
    assert xy[:, 0].min() >= -1.0 + m - tol and xy[:, 0].max() <= 1.0 - m + tol
    assert xy[:, 1].min() >= -1.0 + m - tol and xy[:, 1].max() <= 1.0 - m - t + tol
    # and what is framed fills the panel: it reaches the margins across or along
    fills = max(np.ptp(framed[:, 0]) / (2.0 - 2 * m), np.ptp(framed[:, 1]) / (2.0 - 2 * m - t))
    assert fills > (0.999 if fit_points or view != "three_quarter" else 0.6)


def test_fit_parallel_checks_its_inputs():
    with pytest.raises(ValueError, match="up"):
        fv.fit_parallel((0, 1, 0, 1, 0, 1), (0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="margin"):
        fv.fit_parallel((0, 1, 0, 1, 0, 1), (0.0, 1.0, 0.0), margin=0.6)


def test_profile_overlay_cuts_the_head_midline_not_the_shoulders_centre():
    """A scan whose shoulders reach further to one side: the default midsagittal plane is
    the head's centre (frame_bounds), not the centre of all the skin."""
    head = pv.ParametricEllipsoid(72.0, 95.0, 115.0, u_res=40, v_res=40, w_res=40)
    shoulders = pv.Cylinder(center=(60.0, -70.0, -150.0), direction=(0.0, 0.0, 1.0),
                            radius=160.0, height=30.0)
    skin = pv.merge([m.triangulate().clean() for m in (head, shoulders)])
    assert abs(0.5 * (skin.bounds[0] + skin.bounds[1])) > 50.0
    fig = fv.profile_overlay(skin, skin)
    x = float(fig.axes[0].get_title().split("x = ")[1].split(" mm")[0])
    assert abs(x) < 1.0


def test_prediction_summary_greys_only_the_predicted_skin_the_mesh_does_not_reach():
    pre, post = _pre_post()
    back = np.asarray(post.points)[:, 1] < 0.0  # the back of the head: not modelled
    post.point_data[arrays.SKIN_MODELLED] = (~back).astype(np.uint8)
    image = fv.prediction_summary(pre, post, panel=(300, 240))
    assert image.shape[0] == 480 and image.dtype == np.uint8
    w = fv._panel_width(pre, post, 240, ("frontal", "profile"))
    assert w < 300  # narrowed to the head's proportions

    def grey(block):
        c = block.astype(int)
        flat = (np.ptp(c, axis=-1) < 8) & (c.max(axis=-1) < 235) & (c.min(axis=-1) > 60)
        return flat.sum()

    # the profile row below the titles: the pre-operative skin holds only the grey of
    # anti-aliased outlines, the predicted one the back of the head
    pre_grey, post_grey = grey(image[270:480, :w]), grey(image[270:480, w:2 * w])
    assert post_grey > 5 * pre_grey + 2000
    plain = fv.prediction_summary(pre, post, panel=(300, 240), unmodelled=None)
    assert grey(plain[270:480, w:2 * w]) < 2 * pre_grey + 100


def test_culling_keeps_a_piece_wound_the_other_way():
    """A closed skin of two pieces wound opposite ways (the head inward, the nose outward,
    as PyVista makes them): each piece is turned outward, so the culled back faces are the
    hidden ones and the nose shows in the frontal view."""
    head, nose = _head()

    def volume(mesh):
        tri, x = mesh.faces.reshape(-1, 4), np.asarray(mesh.points)
        return np.einsum("ij,ij->i", x[tri[:, 1]], np.cross(x[tri[:, 2]], x[tri[:, 3]])).sum()

    assert volume(head) * volume(nose) < 0 and abs(volume(head)) > abs(volume(nose))
    skin = head.merge(nose)
    skin.point_data["nose"] = np.where(np.asarray(skin.points)[:, 1] > 90.0, 1.0, 0.0)
    p = pv.Plotter(off_screen=True, window_size=[300, 300])
    actor = fv.add_patient_mesh(p, skin, scalars="nose", cmap=["peachpuff", "red"],
                                lighting=False, show_scalar_bar=False)
    assert actor.prop.culling == "back"
    fv.set_view(p, fv.to_display(skin).bounds, "frontal")
    img = p.screenshot(return_img=True)
    p.close()
    red = np.all(np.abs(img[..., :3].astype(int) - RED) < 30, axis=-1)
    assert red.sum() > 100  # the nose's tip, seen end on


def _texts(plotter):
    """Every text a plotter's panels show (corner annotations and text actors)."""
    out = []
    for renderer in plotter.renderers:
        props = renderer.GetViewProps()
        props.InitTraversal()
        for _ in range(props.GetNumberOfItems()):
            a = props.GetNextProp()
            if a.IsA("vtkCornerAnnotation"):
                out += [a.GetText(i) for i in range(8) if a.GetText(i)]
            elif a.IsA("vtkTextActor"):
                out.append(a.GetInput())
    return out


def test_displacement_bar_says_when_its_colours_saturate():
    """The range is a percentile: when shown values lie beyond it the figure says where the
    colours end and gives the largest value; when none do it says nothing."""
    pre, _ = _pre_post()
    u = np.asarray(pre[arrays.DISPLACEMENT]).copy()
    front = int(np.argmax(pre.points[:, 1]))  # the nose tip: seen from the front
    u[front, 1] = 9.0
    pre.point_data[arrays.DISPLACEMENT] = u
    p = fv.displacement_views(pre, "ap", window_size=(600, 400))
    notes = [t for t in _texts(p) if "colours end at" in t]
    p.close()
    assert len(notes) == 1 and "; colours end at \u00b1" in notes[0], notes
    assert notes[0].endswith(" mm; largest 9.0 mm"), notes
    p = fv.displacement_views(pre, "ap", window_size=(600, 400), limit=10.0)
    assert not [t for t in _texts(p) if "colours end at" in t]
    p.close()


def test_one_skin_row_fills_every_panel():
    """``face_pre.png`` / ``face_post.png``: in each view the head fills its panel as
    :func:`pvcmf.figures.framing.fit_parallel` promises (the three-quarter view too, whose
    box corners reach further out than the head)."""
    from pvcmf.figures.framing import FRAME_MARGIN, FRAME_TITLE
    from pvcmf.outputs import _row

    head, nose = _head()
    p = _row((head + nose).triangulate().clean(), tuple(fv.VIEWS), "pre-operative")
    image = np.asarray(p.screenshot(return_img=True), dtype=float)
    p.close()
    width = image.shape[1] // len(fv.VIEWS)
    for k, view in enumerate(fv.VIEWS):
        panel = image[:, k * width:(k + 1) * width]
        skin = panel.min(axis=2) < 200  # the skin, not the white
        skin[: int(FRAME_TITLE * panel.shape[0]) + 1] = False  # nor the title
        rows, cols = np.nonzero(skin)
        fill = max((rows.max() - rows.min()) / ((1 - 2 * FRAME_MARGIN - FRAME_TITLE)
                                                 * panel.shape[0]),
                   (cols.max() - cols.min()) / ((1 - 2 * FRAME_MARGIN) * panel.shape[1]))
        assert fill > 0.93, (view, fill)


def test_plan_sequence_is_drawn_as_a_photograph():
    """The planner's sequence figure uses the photographic convention: skin pushed out on
    the patient's left (+x) shows red on the viewer's right in a frontal view, and the
    colour bar lies in its own strip under the faces."""
    from pvcmf.figures.plan_sequence import plan_sequence

    head, _ = _head()
    out = np.asarray(head.points) / np.linalg.norm(head.points, axis=1, keepdims=True)
    face = head.copy()
    u = np.where(head.points[:, [0]] > 20.0, 4.0 * out, 0.0)
    face.points = np.asarray(head.points) + u
    face.point_data[arrays.DISPLACEMENT] = u
    still = head.copy()
    still.point_data[arrays.DISPLACEMENT] = np.zeros_like(u)
    p = plan_sequence([still, face], ["+0", "+4"], view="frontal", window_size=(600, 360))
    img = np.asarray(p.screenshot(return_img=True), dtype=int)
    p.close()
    panel = img[: int(0.85 * img.shape[0]), 300:]  # the second face, above the bar's strip
    red = (panel[..., 0] > 150) & (panel[..., 0] - panel[..., 2] > 60)
    assert red.sum() > 100
    assert np.nonzero(red)[1].mean() > 0.55 * panel.shape[1]
    assert not red[:, : panel.shape[1] // 3].any()


def test_normal_component_ignores_stale_normals():
    """A skin carrying an active ``Normals`` array that is not its unit outward normal (a
    parametric surface's, or a moved skin's old ones) still gets its own normals."""
    head = pv.ParametricEllipsoid(70.0, 90.0, 100.0, u_res=40, v_res=40).triangulate().clean()
    assert arrays.NORMALS in head.point_data  # VTK's parametric normals, not unit length
    out = np.asarray(head.points) / np.linalg.norm(head.points, axis=1, keepdims=True)
    head.point_data[arrays.DISPLACEMENT] = 2.0 * out
    value = fv.signed_displacement(head, "normal")
    assert np.all((value > 1.0) & (value <= 2.0 + 1e-6)), (value.min(), value.max())
