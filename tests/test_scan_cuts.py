"""A head cut flat by the scan: found, warned about, kept with the run, marked on the skin
and drawn apart in the face figures."""

import json

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters.field_of_view import cut_planes, cuts_array, on_scan_cuts


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
