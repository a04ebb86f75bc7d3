"""The per-case report (``pvcmf.report``): contents, size, and a real headless browser.

The browser tests open the page in Debian's Chromium (headless, WebGL on SwiftShader):
no console error, the 3D view shows a non-blank face (screenshot pixels inside the
viewer), and the tables hold the numbers of ``summary.json`` (DOM after the scripts
ran). They skip where no Chromium is installed (CI installs it).
"""

import json
import re

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.report import disabled, write_report
from pvcmf.report.browser import check_page, find_chromium
from pvcmf.report.scene import pack_skin

needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no Chromium (apt-get install chromium) to open "
                                           "the report in")


def _head(u_res=80, v_res=60):
    head = pv.ParametricEllipsoid(70, 95, 110, u_res=u_res, v_res=v_res).clean().triangulate()
    z = head.points[:, 2]
    head[arrays.DISPLACEMENT] = np.c_[0 * z, -np.clip(-z / 25.0, 0, None), 0 * z]
    return head


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A prediction folder: skins, one PNG and a summary.json with timings and a plan."""
    folder = tmp_path_factory.mktemp("case")
    head = _head()
    pre = head.copy()
    pre.point_data.clear()
    pre.save(folder / "skin_pre.vtp")
    moved = head.copy()
    moved.points = head.points + head[arrays.DISPLACEMENT]
    moved.save(folder / "predicted_skin.vtp")
    pl = pv.Plotter(off_screen=True, window_size=(120, 100))
    pl.add_mesh(head)
    pl.screenshot(folder / "face_post.png")
    pl.close()
    summary = {"plan": {"name": "test plan", "osteotomy": [
        {"segment": "mandible", "translation": [0.0, 0.0, -5.0], "rotation": [0.0, 0.0, 0.0]}]},
        "seconds": {"segment": 1.25, "mesh": 3.5, "solve": 0.75}}
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder, summary


def _cells(dom, table_id):
    m = re.search(rf'<table id="{table_id}">(.*?)</table>', dom, re.S)
    assert m, f"no table {table_id}"
    rows = re.findall(r"<tr>(.*?)</tr>", m.group(1), re.S)
    return [re.findall(r"<t[dh]>(.*?)</t[dh]>", r, re.S) for r in rows]


def test_report_is_self_contained(case):
    folder, summary = case
    page = write_report(folder)
    text = page.read_text(encoding="utf-8")
    assert page.name == "report.html"
    # offline: no fetched script, style, image or font
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", text)
    assert "data:image/png;base64," in text and "vtkGenericRenderWindow" in text
    timings = dict((r[0], r[1]) for r in _cells(text, "timings")[1:])
    assert timings == {**{k: f"{v:.2f}" for k, v in summary["seconds"].items()}, "total": "5.50"}
    assert _cells(text, "plan")[1] == ["mandible", "0, 0, -5", "0, 0, 0"]
    assert [r[0] for r in _cells(text, "versions")[1:3]] == ["pvcmf", "python"]


def test_region_table_against_numpy(case):
    folder, _ = case
    text = write_report(folder).read_text(encoding="utf-8")
    rows = {r[0]: r[1:] for r in _cells(text, "regions")[1:]}
    from pvcmf.study.statistics import label_face_regions
    pre = pv.read(folder / "skin_pre.vtp")
    reg = label_face_regions(pre)[arrays.REGION]
    u = np.linalg.norm(_head()[arrays.DISPLACEMENT], axis=1)
    for name in ("chin", "nose", "all skin"):
        a = u if name == "all skin" else u[reg == arrays.FACE_REGIONS[name]]
        want = [str(a.size), *(f"{v:.2f}" for v in np.percentile(a, [50, 90, 95])),
                f"{100 * np.mean(a <= 1):.2f}", f"{100 * np.mean(a <= 2):.2f}"]
        assert rows[name] == want, name


def test_region_table_counts_only_the_modelled_skin(tmp_path):
    """A whole-head prediction: the unmoved back of the head (``skin_modelled`` 0) is left
    out of the table, so its zeros do not pull the percentiles down."""
    head = _head()
    head[arrays.SKIN_MODELLED] = (head.points[:, 1] > 0).astype(np.uint8)  # the front half
    head.save(tmp_path / "predicted_skin.vtp")
    rows = {r[0]: r[1:] for r in _cells(write_report(tmp_path).read_text(encoding="utf-8"),
                                         "regions")[1:]}
    assert "all skin" not in rows
    u = np.linalg.norm(head[arrays.DISPLACEMENT], axis=1)[head.points[:, 1] > 0]
    want = [str(u.size), *(f"{v:.2f}" for v in np.percentile(u, [50, 90, 95])),
            f"{100 * np.mean(u <= 1):.2f}", f"{100 * np.mean(u <= 2):.2f}"]
    assert rows["modelled skin"] == want


def test_disabled_writes_nothing(tmp_path):
    _head().save(tmp_path / "predicted_skin.vtp")
    with disabled():
        assert write_report(tmp_path) is None
    assert not (tmp_path / "report.html").exists()
    with pytest.raises(FileNotFoundError, match="existing case folder"):
        write_report(tmp_path / "missing")


def test_size_of_a_100k_point_skin():
    skin = pv.Sphere(radius=100, theta_resolution=400, phi_resolution=250)
    assert skin.n_points > 99_000
    rng = np.random.default_rng(0)
    skin.points = skin.points + rng.normal(0, 0.3, skin.points.shape)  # a rough real skin
    packed = pack_skin(skin, {"u": rng.random(skin.n_points)})
    size = len(json.dumps(packed))
    assert size < 5e6, size  # two such skins + 2.5 MB of vtk.js stay far below 15 MB
    assert packed["n_points"] == skin.n_points
    small = pack_skin(skin, max_points=20_000)
    assert small["n_points"] <= 21_000


@needs_chromium
def test_report_in_headless_chromium(case, tmp_path):
    folder, summary = case
    page = write_report(folder)
    shot = tmp_path / "shot.png"
    check = check_page(page, shot, size=(1280, 900))
    assert check.errors == [], check.errors
    assert 'data-viewer="ready"' in check.dom, check.dom[-2000:]
    # the numbers of summary.json, as the browser shows them
    timings = dict((r[0], r[1]) for r in _cells(check.dom, "timings")[1:])
    assert timings["mesh"] == f"{summary['seconds']['mesh']:.2f}"
    # the 3D view: the viewer's box (about x 40-800, y 160-720 at this width) is not blank
    from PIL import Image
    img = np.asarray(Image.open(shot).convert("RGB"), dtype=int)
    view = img[200:650, 100:740]
    coloured = np.abs(view - 255).sum(axis=2) > 60
    assert 0.05 < coloured.mean() < 0.9, coloured.mean()
    # the displacement map is on: more than one colour in the face
    assert len(np.unique(view[coloured] // 32, axis=0)) > 3


@needs_chromium
def test_browser_check_sees_errors(tmp_path):
    page = tmp_path / "broken.html"
    page.write_text("<html><body><script>undefinedFunction();</script></body></html>")
    check = check_page(page, budget_ms=1000)
    assert any("undefinedFunction" in e for e in check.errors), check.console


def test_write_report_of_a_written_result(tmp_path):
    """The command line writes the page after ``write_outputs``; not when disabled."""
    from test_cli import _small_result

    from pvcmf.outputs import write_outputs
    from pvcmf.report import write_report

    result = _small_result()
    files = write_outputs(result, tmp_path / "a")
    assert "report" not in files
    page = write_report(tmp_path / "a", result=result)
    text = page.read_text(encoding="utf-8")
    assert page.name == "report.html" and "<table id=\"plan\">" in text
    with disabled():
        assert write_report(tmp_path / "a", result=result) is None


def test_skin_with_lines_is_packed_and_decimated():
    """A skin that also holds line cells (a contour's open edges) packs its triangles, and a
    large one is decimated with its scalars carried over."""
    skin = pv.Sphere(theta_resolution=60, phi_resolution=60).merge(pv.Line((0, 0, 0), (1, 1, 1)))
    assert skin.n_lines == 1
    packed = pack_skin(skin, {"z": np.asarray(skin.points)[:, 2]}, max_points=500)
    assert 0 < packed["n_points"] <= 600 and packed["n_triangles"] > 0


def _unpack(packed):
    import base64
    import gzip

    q = np.frombuffer(gzip.decompress(base64.b64decode(packed["points"])), np.uint16)
    points = np.asarray(packed["origin"]) + q.reshape(-1, 3) * np.asarray(packed["step"])
    tri = np.frombuffer(gzip.decompress(base64.b64decode(packed["triangles"])), np.uint32)
    return points, tri.reshape(-1, 3)


def test_viewer_shows_the_patient_as_a_photograph():
    """The 3D view's points are in the display frame (x -> -x): its front view (camera on +y,
    z up) shows the patient's right on the viewer's left; the triangles stay wound outward."""
    sphere = pv.Sphere(radius=50.0, center=(30.0, 0.0, 0.0))  # on the patient's left
    points, tri = _unpack(pack_skin(sphere))
    assert points[:, 0].mean() == pytest.approx(-30.0, abs=0.5)
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    centre = (a + b + c) / 3.0 - points.mean(axis=0)
    assert (np.einsum("ij,ij->i", normal, centre) > 0).mean() > 0.99  # outward


def _cut_case(folder, marked=True):
    """A predicted head whose upper half moves most and, ``marked``, lies on a cut."""
    head = _head()
    z = head.points[:, 2]
    head[arrays.DISPLACEMENT] = np.c_[0 * z, np.where(z > 40, 8.0, -np.clip(-z / 25, 0, 4)),
                                      0 * z]
    if marked:
        head[arrays.SKIN_CUT] = (z > 40).astype(np.uint8)
    head.save(folder / "predicted_skin.vtp")
    return head


def test_region_table_leaves_out_the_scan_s_edge(tmp_path):
    """Skin on a cut of the scan is not the patient's: the table does not count it."""
    head = _cut_case(tmp_path)
    rows = {r[0]: r[1:] for r in _cells(write_report(tmp_path).read_text(encoding="utf-8"),
                                         "regions")[1:]}
    u = np.linalg.norm(head[arrays.DISPLACEMENT], axis=1)[head.points[:, 2] <= 40]
    assert rows["modelled skin"][:3] == [str(u.size), *(f"{v:.2f}" for v in
                                                        np.percentile(u, [50, 90]))]


def test_error_map_leaves_out_the_scan_s_edge(tmp_path):
    """After ``validate``: the signed error of the cut skin is NaN in the packed scene (the
    viewer's NaN colour, the maps' cut colour) and its colour bar names that colour."""
    import base64
    import gzip

    from pvcmf.report.case import _scene, _skins

    head = _cut_case(tmp_path)
    head[arrays.DISTANCE] = np.linspace(-3.0, 3.0, head.n_points)
    (tmp_path / "predicted_skin.vtp").unlink()
    head.save(tmp_path / "validated_skin.vtp")
    scene, bars, _, _ = _scene(_skins(tmp_path, None), 10 ** 6)
    packed = json.loads(scene)
    values = np.frombuffer(gzip.decompress(base64.b64decode(
        packed["skins"]["predicted"]["scalars"]["error"]["values"])), np.float32)
    cut = np.asarray(head[arrays.SKIN_CUT]).astype(bool)
    assert np.isnan(values).sum() == cut.sum() and cut.sum() > 100
    assert packed["colourings"]["error"]["nan"] == packed["colourings"]["displacement"]["nan"]
    assert all("the scan" in b for b in bars)


@needs_chromium
def test_report_view_draws_the_scan_s_edge_in_its_own_colour(tmp_path):
    """In the 3D view the cut takes the cut colour instead of the displacement map's, the
    map's range ends at the rest's largest move, and the colour bar names the colour."""
    from PIL import Image

    near = []
    for marked in (False, True):
        folder = tmp_path / str(marked)
        folder.mkdir()
        _cut_case(folder, marked)
        page = write_report(folder)
        check = check_page(page, folder / "shot.png", size=(1280, 900))
        assert check.errors == [], check.errors
        bar = re.search(r'data-colouring="displacement"><div class="cb-title">(.*?)</div>',
                        check.dom).group(1)
        assert ("the scan&#x27;s edge" in bar or "the scan's edge" in bar) == marked
        img = np.asarray(Image.open(folder / "shot.png").convert("RGB"), dtype=float)
        view = img[200:650, 100:740]
        # the maps' cut colour, a neutral dark grey, whatever the shading
        spread, mean = view.max(axis=2) - view.min(axis=2), view.mean(axis=2)
        near.append(int(((spread < 12) & (mean > 30) & (mean < 120)).sum()))
    assert near[1] > 3000 and near[1] > 20 * near[0], near
