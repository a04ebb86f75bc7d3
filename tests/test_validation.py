"""Validation: skin extraction, ICP, exact signed distance, surface mapping, statistics, Figs 6-8.

Every check is against an analytic answer or an independent implementation (VTK's
implicit distance), on small synthetic inputs.
"""

from __future__ import annotations

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import pvcmf
from pvcmf import arrays
from pvcmf.filters.distance import signed_distance
from pvcmf.filters.registration import (
    ICP_OVERLAP,
    RegistrationError,
    registration_result,
)
from pvcmf.figures.validation import (
    error_colormap,
    fig6_error_maps,
    fig7_boxplots,
    fig8_cumulative,
)
from pvcmf.validation import error_statistics, label_face_regions, run_study, summary


def face_like(u_res=160, v_res=110):
    """Closed, smooth, non-symmetric head-like surface (ellipsoid + nose + waves), mm."""
    s = pv.ParametricEllipsoid(70, 90, 110, u_res=u_res, v_res=v_res).triangulate().clean()
    s.clear_data()
    p = np.asarray(s.points, dtype=float)
    nose = 12 * np.exp(-((p[:, 0] / 15) ** 2 + ((p[:, 2] - 5) / 22) ** 2)) * (p[:, 1] > 0)
    p[:, 1] += nose + 2 * np.sin(p[:, 0] / 15 + 0.3) * np.cos(p[:, 2] / 20)
    p[:, 0] += 1.5 * np.sin(p[:, 2] / 17)
    s.points = p
    return s


@pytest.fixture(scope="module")
def face():
    return face_like()


def pose(angles_deg, shift):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()
    m[:3, 3] = shift
    return m


def pose_error(matrix, truth):
    """(translation error mm at the surface scale, rotation error deg) of matrix vs truth^-1."""
    e = matrix @ truth
    angle = np.degrees(np.linalg.norm(Rotation.from_matrix(e[:3, :3]).as_rotvec()))
    return float(np.linalg.norm(e[:3, 3])), float(angle)


# ----------------------------------------------------------------------------- ICP
def test_icp_recovers_known_pose_cropped_noisy(face):
    rng = np.random.default_rng(3)
    front = face.extract_points(face.points[:, 1] > -30, adjacent_cells=False)
    scan = front.extract_surface(algorithm="dataset_surface")
    scan.points = scan.points + rng.normal(0, 0.2, scan.points.shape)
    truth = pose([3.0, -2.0, 4.0], [4.0, -3.0, 2.0])
    moved = scan.transform(truth, inplace=False)
    before = moved.points.copy()
    out = moved.cmf.register(face)
    matrix, rms, ok = registration_result(out)
    dt, dr = pose_error(matrix, truth)
    assert ok
    assert dt < 0.05 and dr < 0.05, (dt, dr)
    assert 0.15 < rms < 0.25  # the point-to-plane RMS is the added noise (0.2 mm)
    np.testing.assert_array_equal(moved.points, before)  # input untouched
    np.testing.assert_allclose(out.points, scan.points, atol=0.1)


def test_icp_region_ignores_changed_part(face):
    """Only the unchanged upper face is used: the moved jaw region must not bias the pose."""
    post = face.copy()
    p = post.points.copy()
    jaw = p[:, 2] < -20
    p[jaw, 1] += 6.0  # 'surgery': the lower face moves 6 mm forward
    post.points = p
    truth = pose([0.0, 2.0, -3.0], [-2.0, 1.0, 3.0])
    moved = post.transform(truth, inplace=False)
    # region in the target (pre-op) frame as bounds, as a mask and as a callable
    for region in ((-80, 80, -100, 120, 0, 120), face.points[:, 2] > 0,
                   lambda pts: pts[:, 2] > 0):
        matrix, _, ok = registration_result(moved.cmf.register(face, region=region))
        dt, dr = pose_error(matrix, truth)
        assert ok and dt < 0.05 and dr < 0.05, (dt, dr)
    # without the region, the moved jaw biases the pose
    matrix, _, _ = registration_result(moved.cmf.register(face, trim=1.0))
    assert max(pose_error(matrix, truth)) > 0.1


def test_icp_not_converged_is_flagged_or_raises(face):
    moved = face.transform(pose([5.0, 0.0, 0.0], [3.0, 0.0, 0.0]), inplace=False)
    with pytest.raises(RegistrationError, match="did not converge in max_iterations=2"):
        moved.cmf.register(face, max_iterations=2)
    out = moved.cmf.register(face, max_iterations=2, allow_unconverged=True)
    assert registration_result(out)[2] is False


def test_icp_bad_input(face):
    far = face.translate((0.0, 0.0, 1000.0), inplace=False)
    with pytest.raises(RegistrationError, match="overlap"):
        far.cmf.register(face)
    plane = pv.Plane(i_size=50, j_size=50, i_resolution=30, j_resolution=30).triangulate()
    with pytest.raises(RegistrationError, match="degenerate"):
        plane.translate((1.0, 0, 0), inplace=False).cmf.register(plane)
    with pytest.raises(ValueError, match="at least 6 points"):
        pv.PolyData().cmf.register(face)
    with pytest.raises(ValueError, match="region mask"):
        face.cmf.register(face, region=np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match="region leaves 0"):
        face.cmf.register(face, region=(0, 1, 0, 1, 500, 501))
    with pytest.raises(ValueError, match="PolyData surface with polygons"):
        face.cmf.register(pv.PolyData(face.points))
    with pytest.raises(ValueError, match="trim"):
        face.cmf.register(face, trim=0.0)


# ----------------------------------------------------------------------------- distance
def test_signed_distance_concentric_spheres():
    truth = pv.Sphere(radius=12.0, theta_resolution=120, phi_resolution=120)
    # the tessellated truth lies within 2 x 12 (1 - cos(pi / 120)) ~ 8e-3 mm inside the sphere
    tess = 12.0 * (1 - np.cos(np.pi / 120)) * 2
    inner = pv.Sphere(radius=10.0).cmf.distance_to(truth)
    outer = pv.Sphere(radius=14.0).cmf.distance_to(truth)
    np.testing.assert_allclose(inner[arrays.DISTANCE], -2.0, atol=tess)  # inside: posterior
    np.testing.assert_allclose(outer[arrays.DISTANCE], 2.0, atol=tess)  # outside: anterior
    # the sign follows outward orientation even if the truth is wound inward
    flipped = truth.copy()
    flipped.faces = np.column_stack([np.full(flipped.n_cells, 3),
                                     flipped.faces.reshape(-1, 4)[:, 1:][:, ::-1]]).ravel()
    np.testing.assert_allclose(pv.Sphere(radius=14.0).cmf.distance_to(flipped)[arrays.DISTANCE],
                               2.0, atol=tess)
    # ... or inconsistently wound (every other face flipped)
    tri = truth.faces.reshape(-1, 4)[:, 1:].copy()
    tri[::2] = tri[::2, ::-1]
    mixed = pv.PolyData(truth.points, np.column_stack([np.full(len(tri), 3), tri]).ravel())
    np.testing.assert_allclose(pv.Sphere(radius=10.0).cmf.distance_to(mixed)[arrays.DISTANCE],
                               -2.0, atol=tess)


def test_distance_exact_on_coarse_target_not_nearest_vertex():
    plane = pv.Plane(i_size=100, j_size=100, i_resolution=2, j_resolution=2).triangulate()
    rng = np.random.default_rng(0)
    q = np.column_stack([rng.uniform(-40, 40, (500, 2)), rng.uniform(-3, 3, 500)])
    d = signed_distance(q, plane)
    np.testing.assert_allclose(d, q[:, 2], atol=1e-9)  # the plane's normal is +z
    nearest_vertex, _ = cKDTree(plane.points).query(q)
    assert (nearest_vertex - np.abs(q[:, 2])).max() > 10  # nearest vertex is far off


def test_distance_matches_brute_force_closest_points():
    """Curved coarse target, points near and far: an independent exact brute force agrees."""
    target = pv.Icosphere(radius=20.0, nsub=2)
    rng = np.random.default_rng(1)
    dirs = rng.normal(size=(1500, 3))
    q = dirs / np.linalg.norm(dirs, axis=1)[:, None] * rng.uniform(5, 35, 1500)[:, None]
    d = signed_distance(q, target)
    tri = target.faces.reshape(-1, 4)[:, 1:]
    pts = np.asarray(target.points, dtype=float)
    cp, _ = closest_point_on_triangles(q[:, None, :], pts[tri[:, 0]][None], pts[tri[:, 1]][None],
                                       pts[tri[:, 2]][None])
    brute = np.linalg.norm(cp - q[:, None, :], axis=2).min(axis=1)
    np.testing.assert_allclose(np.abs(d), brute, atol=1e-9)
    # the icosphere is convex, its vertices at r = 20, its faces beyond r = 18
    r = np.linalg.norm(q, axis=1)
    assert (d[r < 18] < 0).all() and (d[r > 20] > 0).all()


def closest_point_on_triangles(p, a, b, c):
    """Brute-force reference: closest point on triangles (Ericson 5.1.5), vectorised."""
    def dot(u, v):
        return np.einsum("...i,...i->...", u, v)

    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    shape = np.broadcast_shapes(p.shape, a.shape)[:-1]
    # default: face interior, barycentric (u, v, w) weights of a, b, c
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        feature = np.full(shape, 0, dtype=np.int8)
        # edge bc
        d43, d56 = d4 - d3, d5 - d6
        m = (va <= 0) & (d43 >= 0) & (d56 >= 0)
        t = d43 / (d43 + d56)
        v = np.where(m, 1 - t, v)
        w = np.where(m, t, w)
        feature[m] = 5
        # edge ca
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        t = d2 / (d2 - d6)
        v = np.where(m, 0.0, v)
        w = np.where(m, t, w)
        feature[m] = 6
        # later assignments take precedence, in Ericson's order of tests reversed
        m = (d6 >= 0) & (d5 <= d6)
        v, w = np.where(m, 0.0, v), np.where(m, 1.0, w)
        feature[m] = 3
        # edge ab
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        t = d1 / (d1 - d3)
        v = np.where(m, t, v)
        w = np.where(m, 0.0, w)
        feature[m] = 4
    m = (d3 >= 0) & (d4 <= d3)
    v, w = np.where(m, 1.0, v), np.where(m, 0.0, w)
    feature[m] = 2
    m = (d1 <= 0) & (d2 <= 0)
    v, w = np.where(m, 0.0, v), np.where(m, 0.0, w)
    feature[m] = 1
    closest = a + ab * v[..., None] + ac * w[..., None]
    return closest, feature




def test_distance_to_bad_input_and_no_mutation():
    s = pv.Sphere()
    with pytest.raises(ValueError, match="actual must be a non-empty surface"):
        s.cmf.distance_to(pv.PolyData(s.points))
    with pytest.raises(TypeError, match="actual must be a pyvista.PolyData"):
        s.cmf.distance_to(pv.ImageData(dimensions=(3, 3, 3)))
    with pytest.raises(ValueError, match="pred must have points"):
        pv.PolyData().cmf.distance_to(s)
    far = s.translate((100.0, 0, 0), inplace=False)
    with pytest.raises(ValueError, match="do not overlap"):
        far.cmf.distance_to(s, max_distance=5.0)
    out = s.cmf.distance_to(s)
    assert arrays.DISTANCE not in s.point_data and arrays.DISTANCE in out.point_data


# ----------------------------------------------------------------------------- statistics
def test_statistics_of_uniform_distribution():
    # |d| is uniform on [0, 4]: exact percentiles and shares
    d = np.linspace(-4.0, 4.0, 400_001)
    s = summary(d)
    assert s["n"] == d.size
    assert s["median"] == pytest.approx(0.0, abs=1e-9)
    assert s["mean_abs"] == pytest.approx(2.0, rel=1e-4)
    assert s["rms"] == pytest.approx(4.0 / np.sqrt(3.0), rel=1e-4)
    assert (s["p50"], s["p90"], s["p95"]) == pytest.approx((2.0, 3.6, 3.8), rel=1e-4)
    assert (s["within_1mm"], s["within_2mm"]) == pytest.approx((25.0, 50.0), rel=1e-3)


def test_statistics_of_normal_distribution():
    from scipy import stats

    mu, sd = 0.4, 1.2
    d = np.random.default_rng(5).normal(mu, sd, 400_000)
    s = summary(d)
    folded = stats.foldnorm(mu / sd, scale=sd)
    assert s["median"] == pytest.approx(mu, abs=0.01)
    assert s["p90"] == pytest.approx(folded.ppf(0.9), rel=0.01)
    assert s["p95"] == pytest.approx(folded.ppf(0.95), rel=0.01)
    assert s["within_1mm"] == pytest.approx(100 * folded.cdf(1.0), abs=0.3)
    assert s["within_2mm"] == pytest.approx(100 * folded.cdf(2.0), abs=0.3)


def test_cheeks_split_at_the_face_midline_not_at_a_bent_nose():
    """A nose bent 7 mm to the patient's left: the cheeks are split at the middle of the
    face's width (x = 0, by construction), or at the midline landmarks when given."""
    head = pv.ParametricEllipsoid(70, 90, 110, u_res=160, v_res=110).triangulate().clean()
    p = np.asarray(head.points, dtype=float)
    p[:, 1] += 14 * np.exp(-(((p[:, 0] - 7) / 12) ** 2 + ((p[:, 2] - 5) / 22) ** 2)) \
        * (p[:, 1] > 0)
    head.points = p
    ids = arrays.FACE_REGIONS
    reg = np.asarray(label_face_regions(head)[arrays.REGION])
    assert p[np.argmax(p[:, 1]), 0] > 5  # the tip is off the midline
    left, right = p[reg == ids["cheek_left"]], p[reg == ids["cheek_right"]]
    assert len(left) > 50 and len(left) == pytest.approx(len(right), rel=0.05)
    assert left[:, 0].min() == pytest.approx(-right[:, 0].max(), abs=1.5)  # both 24 mm out
    assert left[:, 0].min() == pytest.approx(24.0, abs=1.5)
    marks = {"stomion": (4.0, 90.0, -40.0), "pogonion": (4.0, 85.0, -80.0)}
    reg = np.asarray(label_face_regions(head, landmarks=marks)[arrays.REGION])
    left, right = p[reg == ids["cheek_left"]], p[reg == ids["cheek_right"]]
    assert left[:, 0].min() == pytest.approx(28.0, abs=1.5)
    assert right[:, 0].max() == pytest.approx(-20.0, abs=1.5)


def test_face_regions_and_table(face):
    labelled = label_face_regions(face)
    reg = labelled[arrays.REGION]
    ids = arrays.FACE_REGIONS
    tip = np.argmax(face.points[:, 1])
    assert reg[tip] == ids["nose"]
    for name in ("upper_lip", "lower_lip", "chin", "cheek_left", "cheek_right"):
        assert (reg == ids[name]).sum() > 10, name
    z = {name: face.points[reg == ids[name], 2].mean() for name in ids if name != "other"}
    assert z["nose"] > z["upper_lip"] > z["lower_lip"] > z["chin"]
    assert (face.points[reg == ids["cheek_left"], 0] > 0).all()
    assert (face.points[reg == ids["cheek_right"], 0] < 0).all()
    assert (face.points[reg > 0, 1] > 0).all()  # only the front of the head
    labelled[arrays.DISTANCE] = np.where(reg == ids["chin"], 3.0, 0.5)
    table = error_statistics(labelled, patient=2, method="proposed")
    assert list(table["region"]) == ["face", "upper_lip", "lower_lip", "chin", "nose",
                                     "cheek_left", "cheek_right"]
    chin = table.set_index("region").loc["chin"]
    assert chin["median"] == 3.0 and chin["within_2mm"] == 0.0
    assert (table["patient"] == 2).all() and (table["method"] == "proposed").all()
    with pytest.raises(ValueError, match="no point array 'distance'"):
        error_statistics(face)


def test_run_study_is_reproducible():
    def predict(patient, method):
        s = pv.Sphere(radius=50.0)
        rng = np.random.default_rng(patient * 10 + len(method))
        s[arrays.DISTANCE] = rng.normal(0, patient, s.n_points)
        return s

    skins, d1, t1 = run_study(predict, patients=(1, 2), regions=False)
    _, d2, t2 = run_study(predict, patients=(1, 2), regions=False)
    assert list(t1["patient"]) == [1, 1, 2, 2]
    assert t1.equals(t2)
    np.testing.assert_array_equal(d1[2]["proposed"], d2[2]["proposed"])
    assert skins[1]["state_of_the_art"].n_points == d1[1]["state_of_the_art"].size
    with pytest.raises(TypeError, match="predict must be callable"):
        run_study(None)


# ----------------------------------------------------------------------------- skin
def test_skin_of_label_image_is_outer_surface_with_cavity_filled():
    img = pv.ImageData(dimensions=(36, 36, 36), spacing=(1.5, 1.5, 1.5))
    r = np.linalg.norm(img.points - img.center, axis=1)
    tissue = np.where(r < 22.0, arrays.FAT, arrays.AIR).astype(np.uint8)
    tissue[r < 8.0] = arrays.AIR  # an enclosed cavity (a sinus) must not give a surface
    tissue[r < 4.0] = arrays.BONE_TISSUE
    img[arrays.TISSUE] = tissue
    before = img[arrays.TISSUE].copy()
    skin = pvcmf.filters.extract_skin(img)
    radius = np.linalg.norm(skin.points - img.center, axis=1)
    assert abs(radius.mean() - 22.0) < 0.5 and radius.min() > 20.0
    outward = np.einsum("ij,ij->i", skin["Normals"], skin.points - img.center)
    assert (outward > 0).all()
    np.testing.assert_array_equal(img[arrays.TISSUE], before)
    # a CT without labels is thresholded
    ct = pv.ImageData(dimensions=img.dimensions, spacing=img.spacing)
    ct[arrays.CT] = np.where(r < 22.0, 40.0, -1000.0).astype(np.float32)
    assert abs(np.linalg.norm(ct.cmf.skin().points - img.center, axis=1).mean() - 22) < 0.5
    empty = pv.ImageData(dimensions=(4, 4, 4))
    empty[arrays.TISSUE] = np.zeros(64, np.uint8)
    with pytest.raises(ValueError, match="all air"):
        empty.cmf.skin()
    with pytest.raises(ValueError, match="'tissue'.*segment"):
        pv.ImageData(dimensions=(4, 4, 4)).cmf.skin()
    with pytest.raises(TypeError, match="ImageData"):
        pv.Sphere().cmf.skin()


@pytest.fixture(scope="module")
def shell_grid():
    """Tetrahedral spherical shell r in [10, 18]: inner side on 'bone' (joint bc)."""
    img = pv.ImageData(dimensions=(21, 21, 21), spacing=(2, 2, 2), origin=(-20, -20, -20))
    img.cell_data["r"] = np.linalg.norm(img.cell_centers().points, axis=1)
    grid = img.threshold((10, 18), scalars="r").triangulate()
    grid.clear_data()
    bc = np.zeros(grid.n_points, np.int8)
    bc[np.linalg.norm(grid.points, axis=1) < 13] = arrays.BC_JOINT
    grid[arrays.BC] = bc
    return grid


def test_skin_of_grid_keeps_correspondence_and_leaves_bone(shell_grid):
    grid = shell_grid.copy()
    grid[arrays.DISPLACEMENT] = np.tile([0.0, 1.0, 0.0], (grid.n_points, 1))
    rest = grid.cmf.skin(warp=False)
    ids = rest["vtkOriginalPointIds"]
    np.testing.assert_array_equal(rest.points, grid.points[ids])
    assert np.linalg.norm(rest.points, axis=1).min() > 14  # no face on the inner (bone) side
    moved = grid.cmf.skin()
    np.testing.assert_allclose(moved.points - rest.points, [[0.0, 1.0, 0.0]] * rest.n_points)
    outward = np.einsum("ij,ij->i", rest["Normals"], rest.points)
    assert (outward > 0).all()
    whole = grid.cmf.skin(part="boundary")
    assert np.linalg.norm(whole.points, axis=1).min() < 13  # the inner side is there
    # without bc, a label image decides which faces look at air
    img = pv.ImageData(dimensions=(41, 41, 41), spacing=(1, 1, 1), origin=(-20, -20, -20))
    r = np.linalg.norm(img.points, axis=1)
    labels = np.where(r < 19, arrays.FAT, arrays.AIR).astype(np.uint8)
    labels[r < 11] = arrays.BONE_TISSUE
    img[arrays.TISSUE] = labels
    nobc = shell_grid.copy()
    del nobc.point_data[arrays.BC]
    by_labels = nobc.cmf.skin(labels=img)
    assert np.linalg.norm(by_labels.points, axis=1).min() > 14
    with pytest.raises(ValueError, match="part must be"):
        grid.cmf.skin(part="face")


# ----------------------------------------------------------------------------- mapping
@pytest.fixture(scope="module")
def block_grid():
    img = pv.ImageData(dimensions=(16, 16, 16), spacing=(2, 2, 2), origin=(-15, -15, -15))
    return img.cast_to_unstructured_grid().triangulate()


def test_map_to_surface_reproduces_linear_field(block_grid):
    grid = block_grid.copy()
    a = np.array([[0.02, -0.01, 0.03], [0.0, 0.05, -0.02], [0.01, 0.0, -0.04]])
    grid[arrays.DISPLACEMENT] = grid.points @ a.T + [0.5, -1.0, 2.0]
    skin = pv.Sphere(radius=13.0, theta_resolution=40, phi_resolution=40)
    skin.points = skin.points.astype(np.float64)
    out = grid.cmf.map_to_surface(skin, method="gaussian", sigma=2.0)
    expect = skin.points @ a.T + [0.5, -1.0, 2.0]
    np.testing.assert_allclose(out[arrays.DISPLACEMENT], expect, atol=1e-9)
    np.testing.assert_allclose(out.points, skin.points + expect, atol=1e-9)
    assert arrays.DISPLACEMENT not in skin.point_data  # input untouched


def test_map_to_surface_smooths_noise(block_grid):
    grid = block_grid.copy()
    rng = np.random.default_rng(2)
    linear = 0.05 * grid.points
    grid[arrays.DISPLACEMENT] = linear + rng.normal(0, 0.5, linear.shape)
    skin = pv.Sphere(radius=10.0, theta_resolution=60, phi_resolution=60)
    err, slope = {}, {}
    for sigma in (1.0, 3.0):
        out = grid.cmf.map_to_surface(skin, method="gaussian", sigma=sigma)
        err[sigma] = np.abs(out[arrays.DISPLACEMENT] - 0.05 * skin.points).std()
        # smoothness: largest change of the mapped displacement per mm along skin edges
        edges = out.extract_all_edges()
        line = edges.lines.reshape(-1, 3)[:, 1:]
        du = np.diff(edges[arrays.DISPLACEMENT][line], axis=1)[:, 0]
        dx = np.diff(edges.points[line], axis=1)[:, 0]
        slope[sigma] = (np.linalg.norm(du, axis=1) / np.linalg.norm(dx, axis=1)).max()
    # the noise (0.5 mm per node) is averaged away; the field's own slope is 0.05 * sqrt(3)
    assert err[3.0] < 0.5 * err[1.0] and err[3.0] < 0.05
    assert slope[3.0] < 0.15 < slope[1.0]
    # at the edge of the mesh (a skin reaching 3 mm beyond it) nothing is extrapolated
    curved = block_grid.copy()
    curved[arrays.DISPLACEMENT] = 0.02 * curved.points ** 2
    edge = curved.cmf.map_to_surface(pv.Sphere(radius=18.0), method="gaussian", sigma=2.0)
    u = edge[arrays.DISPLACEMENT][edge["mapping_support"] > 0]
    assert u.min() >= 0.0 and u.max() <= 0.02 * 15.0 ** 2 + 1e-12
    far = pv.Sphere(radius=2.0, center=(100.0, 0, 0))
    for method in ("gaussian", "interpolate"):  # a skin the grid cannot reach is refused
        with pytest.raises(ValueError, match="none of its .* points lies near the grid"):
            grid.cmf.map_to_surface(far, method=method, sigma=1.0)
    with pytest.raises(ValueError, match="no point array 'displacement'"):
        block_grid.cmf.map_to_surface(skin)
    with pytest.raises(ValueError, match="sigma must be > 0"):
        grid.cmf.map_to_surface(skin, method="gaussian", sigma=0)


# ----------------------------------------------------------------------------- figures
def synthetic_study():
    """Deterministic skins and distances for two patients and both methods."""
    face = face_like(u_res=90, v_res=60)
    front = face.extract_points(face.points[:, 1] > 10, adjacent_cells=False)
    front = front.extract_surface(algorithm="dataset_surface")
    p = front.points
    skins, dists = {}, {}
    for patient, amp in ((1, 3.0), (2, 5.0)):
        skins[patient], dists[patient] = {}, {}
        for method, gain in (("proposed", 1.0), ("state_of_the_art", 1.4)):
            d = gain * amp * np.exp(-((p[:, 2] + 40) / 25) ** 2) * np.sin(p[:, 0] / 20)
            d = d + gain * (1.2 * np.sin(p[:, 2] / 9) * np.cos(p[:, 0] / 11) - 0.3)
            s = front.copy()
            s[arrays.DISTANCE] = d
            skins[patient][method] = s
            dists[patient][method] = d
    return skins, dists


@pytest.fixture(scope="module")
def study():
    return synthetic_study()


def test_error_colormap_white_band():
    cmap = error_colormap(limit=6.0, acceptable=2.0, n=241)  # one colour per 0.05 mm
    v = np.linspace(-6, 6, 241)
    rgb = cmap(np.arange(241))[:, :3]
    assert np.allclose(rgb[np.abs(v) <= 2.0], 1.0)
    assert (rgb[v < -2.05, 0] > rgb[v < -2.05, 2]).all()  # red posterior (negative)
    assert (rgb[v > 2.05, 2] > rgb[v > 2.05, 0]).all()  # blue anterior (positive)
    with pytest.raises(ValueError, match="acceptable"):
        error_colormap(limit=1.0, acceptable=2.0)


def test_fig6_error_maps(study, verify_image_cache):
    skins, _ = study
    pl = fig6_error_maps(skins, window_size=(480, 520))
    assert pl.shape == (2, 2)
    pl.show()


def test_fig7_boxplots(study, verify_chart):
    _, dists = study
    fig = fig7_boxplots(dists)
    texts = [t.get_text() for t in fig.axes[0].texts]
    med = np.median(np.abs(dists[2]["state_of_the_art"]))
    assert f"{med:.2f}" in texts
    assert "whiskers: 5th-95th percentiles" in fig.axes[0].get_xlabel()
    assert "1.5 IQR" in fig7_boxplots(dists, whis=1.5).axes[0].get_xlabel()
    verify_chart(fig)


def test_fig8_cumulative(study, verify_chart):
    _, dists = study
    fig = fig8_cumulative(dists)
    assert len(fig.axes) == 2
    share = 100 * np.mean(np.abs(dists[1]["proposed"]) <= 1.0)
    assert f"{share:.0f}%" in [t.get_text() for t in fig.axes[0].texts]
    verify_chart(fig)
    with pytest.raises(ValueError, match="expected"):
        fig8_cumulative({1: {"proposed": [1.0]}, 2: {"other": [1.0]}})


def _blue_columns(image):
    """Mean column (pixels from the left) of the clearly blue pixels of an RGB image."""
    rgb = np.asarray(image, dtype=float)[..., :3]
    blue = (rgb[..., 2] > 120) & (rgb[..., 2] > rgb[..., 0] + 60)
    return np.nonzero(blue)[1]


def test_fig6_shows_the_patients_right_on_the_viewers_left():
    """Fig. 6 is drawn as the face figures and a clinical photograph: an error on the
    patient's left (+x) appears on the viewer's right."""
    skin = pv.Sphere(radius=60.0, theta_resolution=60, phi_resolution=60)
    skin[arrays.DISTANCE] = np.where(skin.points[:, 0] > 20.0, 5.0, 0.0)
    pl = fig6_error_maps({1: {"proposed": skin}}, window_size=(400, 440))
    image = pl.screenshot(return_img=True)
    pl.close()
    cols = _blue_columns(image[: int(0.8 * image.shape[0])])  # above the colour bar
    assert cols.size > 100 and cols.mean() > 0.6 * image.shape[1], cols.mean()


def test_fig6_to_8_name_a_case_that_is_no_patient_number(study):
    """A case named by a word is written as it is; a patient number as P<n>."""
    skins, dists = study
    fig = fig8_cumulative({"female head": dists[1], 2: dists[2]})
    assert [ax.get_title() for ax in fig.axes] == ["female head", "P2"]
    fig = fig7_boxplots({"female head": dists[1]})
    assert [t.get_text() for t in fig.axes[0].get_xticklabels()] == ["female head"]
    pl = fig6_error_maps({"female head": skins[1]}, window_size=(480, 260))
    names = set()
    for renderer in pl.renderers:
        props = renderer.GetViewProps()
        props.InitTraversal()
        for _ in range(props.GetNumberOfItems()):
            a = props.GetNextProp()
            if a.IsA("vtkCornerAnnotation"):
                names.add(a.GetText(2))
            elif a.IsA("vtkTextActor"):
                names.add(a.GetInput())
    pl.close()
    assert "female head  proposed" in names and not any("Pfemale" in str(n) for n in names)
    assert any("white within \u00b12" in str(n) for n in names)


def test_validation_figures_count_the_modelled_skin_only(tmp_path, monkeypatch):
    """Figs. 7 and 8 judge the skin the model predicts, as regions.csv does: the unmodelled
    back of the head (distance 0) does not raise the share of small errors."""
    from matplotlib.figure import Figure

    import pvcmf.report.figures as rf

    seen = {}

    def capture(name):
        def draw(data, **kwargs):
            seen[name] = next(iter(next(iter(data.values())).values()))
            return Figure()
        return draw

    monkeypatch.setattr(rf, "fig7_boxplots", capture("fig7"))
    monkeypatch.setattr(rf, "fig8_cumulative", capture("fig8"))
    skin = pv.Sphere(theta_resolution=20, phi_resolution=20)
    front = skin.points[:, 1] > 0
    skin[arrays.DISTANCE] = np.where(front, 3.0, 0.0)
    skin[arrays.SKIN_MODELLED] = front.astype(np.uint8)
    rf.validation_figures(skin, tmp_path, case="c")
    for name in ("fig7", "fig8"):
        np.testing.assert_array_equal(seen[name], np.full(front.sum(), 3.0))
