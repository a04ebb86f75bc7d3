"""Boundary conditions from a plan (paper 000 Fig. 4) and what the MTM makes of them.

The synthetic model: a 1 mm label image with a maxilla block (upper teeth in front), a
mandible block (lower teeth in front) and a cranium block behind them, wrapped in a 4 mm
soft-tissue layer; the soft-tissue voxels' cells become the tetrahedral mesh.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial.transform import Rotation

from pvcmf import arrays
from pvcmf.filters import apply_plan
from pvcmf.plan import Osteotomy, Plan


def synthetic_head(cranium=True, spacing=1.0, half_width=8, thickness=4):
    """Label image (bone, tissue) and soft-tissue tetrahedral mesh of a toy jaw."""
    img = pv.ImageData(dimensions=(27, 27, 31), origin=(-13, -13, -15),
                       spacing=(spacing,) * 3)
    x, y, z = (img.points / spacing).T
    bone = np.zeros(img.n_points, dtype=np.uint8)
    tissue = np.zeros(img.n_points, dtype=np.uint8)
    inx = np.abs(x) <= half_width
    maxilla = inx & (y >= -4) & (y <= 6) & (z >= 1) & (z <= 7)
    mandible = inx & (y >= -4) & (y <= 6) & (z >= -9) & (z <= -1)
    upper_teeth = inx & (y >= 7) & (y <= 8) & (z >= 1) & (z <= 7)
    lower_teeth = inx & (y >= 7) & (y <= 8) & (z >= -7) & (z <= -1)
    hard = maxilla | mandible | upper_teeth | lower_teeth
    if cranium:
        skull = inx & (y >= -8) & (y <= -5) & (z >= -9) & (z <= 7)
        bone[skull] = arrays.CRANIUM
        hard |= skull
    bone[maxilla | upper_teeth] = arrays.MAXILLA
    bone[mandible | lower_teeth] = arrays.MANDIBLE
    tissue[hard] = arrays.BONE_TISSUE
    tissue[upper_teeth | lower_teeth] = arrays.TEETH
    # 4 mm of soft tissue around the hard tissue (chebyshev distance)
    from scipy import ndimage

    vol = hard.reshape(img.dimensions, order="F")
    soft = ndimage.binary_dilation(vol, np.ones((3, 3, 3)), iterations=thickness) & ~vol
    tissue[soft.ravel(order="F")] = arrays.FAT
    img[arrays.BONE] = bone
    img[arrays.TISSUE] = tissue
    # mesh: cells whose 8 corners are soft tissue or touch hard tissue at most on a face
    cells = img.cell_centers().points
    idx = np.round((cells - img.origin) / spacing - 0.5).astype(int)  # lower corner
    lab = tissue.reshape(img.dimensions, order="F")
    corners = np.stack([lab[idx[:, 0] + i, idx[:, 1] + j, idx[:, 2] + k]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)], axis=1)
    keep = np.all(np.isin(corners, [arrays.FAT, arrays.BONE_TISSUE, arrays.TEETH]), axis=1) \
        & np.any(corners == arrays.FAT, axis=1) \
        & ~np.all(np.isin(corners, [arrays.BONE_TISSUE, arrays.TEETH]), axis=1)
    grid = img.extract_cells(np.flatnonzero(keep)).triangulate().clean()
    grid.clear_data()
    grid.cell_data[arrays.TISSUE] = np.full(grid.n_cells, arrays.FAT, dtype=np.uint8)
    grid.cell_data[arrays.MUSCLE] = np.zeros(grid.n_cells, dtype=np.uint8)
    return img, grid


@pytest.fixture(scope="module")
def head():
    return synthetic_head()


def rigid(points, plan, labels):
    """Independent rigid displacement: scipy rotations about the voxel centroid."""
    o = plan.osteotomies[0]
    c = labels.points[labels[arrays.BONE] == o.segment_id].mean(axis=0)
    rx, rz, ry = o.rotation
    rot = Rotation.from_euler("xzy", [rx, rz, ry], degrees=True).as_matrix()
    h, v, ap = o.translation
    return (points - c) @ rot.T + c + [h, ap, v] - points


def test_bc_types_and_values(head):
    labels, grid = head
    plan = Plan((Osteotomy("mandible", (1.07, -0.74, 5.47), (0.0, 2.71, 0.0)),))
    before = grid.copy(deep=True)
    out = apply_plan(grid, plan, labels)
    assert grid == before and arrays.BC not in grid.point_data  # input untouched
    bc = arrays.require_array(out, arrays.BC, dtype=np.int8, ncomp=1)
    disp = arrays.require_array(out, arrays.BC_DISPLACEMENT, dtype="f", ncomp=3)
    normal = arrays.require_array(out, arrays.BC_NORMAL, dtype="f", ncomp=3)
    p = out.points
    counts = {k: int(np.sum(bc == v)) for k, v in arrays.BC_CODES.items()}
    assert all(counts[k] > 0 for k in arrays.BC_CODES), counts

    # joint: on the mandible's bone surface (x within the blocks, not teeth), moved rigidly
    joint = bc == arrays.BC_JOINT
    assert np.all(p[joint, 2] <= 0.0) and np.all(p[joint, 2] >= -10.0)
    np.testing.assert_allclose(disp[joint], rigid(p[joint], plan, labels), atol=1e-12)
    # ... and every soft-tissue node that sits on the mandible's bone is joint
    mand = labels.points[(labels[arrays.BONE] == arrays.MANDIBLE)
                         & (labels[arrays.TISSUE] == arrays.BONE_TISSUE)]
    from scipy.spatial import cKDTree

    on_mandible = cKDTree(mand).query(p)[0] < 1e-9
    assert np.all(joint[on_mandible & (bc != arrays.BC_SLIDING)])

    # sliding: on the teeth (front faces y = 8 and their sides), unit normals pointing out
    slide = bc == arrays.BC_SLIDING
    assert np.all(p[slide, 1] >= 6.0)
    np.testing.assert_allclose(np.linalg.norm(normal[slide], axis=1), 1.0, atol=1e-12)
    # away from the teeth's edges (1 voxel of smoothing) the normal is the face's, +y
    front = slide & (np.abs(p[:, 1] - 8.0) < 1e-9) & (np.abs(p[:, 0]) < 6) \
        & (np.abs(p[:, 2]) >= 3) & (np.abs(p[:, 2]) <= 5)
    assert front.sum() > 10
    np.testing.assert_allclose(normal[front], np.tile([0, 1, 0], (front.sum(), 1)), atol=0.1)
    lower = slide & (p[:, 2] < 0)
    upper = slide & (p[:, 2] > 0)
    np.testing.assert_allclose(disp[lower], rigid(p[lower], plan, labels), atol=1e-12)
    np.testing.assert_allclose(disp[upper], 0.0)  # the maxilla does not move
    assert np.all(normal[~slide] == 0)

    # fixed: exactly the nodes within 2 mm of the most posterior plane
    np.testing.assert_array_equal(bc == arrays.BC_FIXED, p[:, 1] <= p[:, 1].min() + 2.0)
    assert np.all(disp[bc == arrays.BC_FREE] == 0)


def test_options_switch_each_bc_off(head):
    labels, grid = head
    plan = Plan((Osteotomy("maxilla", (6.0, 5.0, -4.0), (0.0, 2.0, 5.0)),))
    base = apply_plan(grid, plan, labels)[arrays.BC]
    no_slide = apply_plan(grid, plan, labels, sliding=False)[arrays.BC]
    assert not np.any(no_slide == arrays.BC_SLIDING)
    # upper teeth now move with the maxilla (joint), lower teeth are free
    assert np.sum(no_slide == arrays.BC_JOINT) > np.sum(base == arrays.BC_JOINT)
    no_fixed = apply_plan(grid, plan, labels, fixed_posterior=False)[arrays.BC]
    assert not np.any(no_fixed == arrays.BC_FIXED)
    bone_fixed = apply_plan(grid, plan, labels, fixed_posterior=False,
                            fix_unmoved_bone=True)
    fixed = bone_fixed[arrays.BC] == arrays.BC_FIXED
    assert fixed.any() and np.all(bone_fixed[arrays.BC_DISPLACEMENT][fixed] == 0)
    # those fixed nodes touch cranium or mandible bone, never the moved maxilla
    assert not np.any(fixed & (base == arrays.BC_JOINT))
    deeper = apply_plan(grid, plan, labels, posterior_depth=5.0)[arrays.BC]
    assert np.sum(deeper == arrays.BC_FIXED) > np.sum(base == arrays.BC_FIXED)


def test_teeth_rim_labelled_bone_still_slides(head):
    """A CT segmentation labels the teeth's partial-volume rim as bone: the lips on that rim
    slide with the default teeth_margin (one voxel) and are joint with teeth_margin=0."""
    labels, grid = head
    rim = labels.copy()
    tissue = rim[arrays.TISSUE].copy()
    front = (np.abs(rim.points[:, 1] - 8.0) < 1e-9) & (tissue == arrays.TEETH)
    tissue[front] = arrays.BONE_TISSUE  # only y = 7 keeps the TEETH label
    rim[arrays.TISSUE] = tissue
    plan = Plan((Osteotomy("mandible", (0, 0, 2.0)),))
    lips = (np.abs(grid.points[:, 1] - 8.0) < 1e-9) & (np.abs(grid.points[:, 0]) < 6) \
        & (np.abs(grid.points[:, 2]) >= 2) & (np.abs(grid.points[:, 2]) <= 6)
    assert lips.sum() > 10
    assert np.all(apply_plan(grid, plan, rim)[arrays.BC][lips] == arrays.BC_SLIDING)
    strict = apply_plan(grid, plan, rim, teeth_margin=0)[arrays.BC][lips]
    assert not np.any(strict == arrays.BC_SLIDING)
    lower = grid.points[lips, 2] < 0
    assert np.all(strict[lower] == arrays.BC_JOINT)  # on the moving mandible's "bone"


def test_zero_plan_prescribes_zero(head):
    labels, grid = head
    out = apply_plan(grid, Plan((Osteotomy("mandible"),)), labels)
    assert np.sum(out[arrays.BC] == arrays.BC_JOINT) > 0
    np.testing.assert_array_equal(out[arrays.BC_DISPLACEMENT], 0.0)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"bones": None}, ValueError, "bones must be the label image"),
    ({"contact_distance": -1}, ValueError, "contact_distance must be a finite number > 0"),
    ({"contact_distance": "far"}, TypeError, "contact_distance must be a number"),
    ({"posterior_depth": np.nan}, ValueError, "posterior_depth must be a finite"),
    ({"normal_sigma": -1}, ValueError, "normal_sigma"),
    ({"teeth_margin": -1.0}, ValueError, "teeth_margin must be a finite number >= 0"),
    ({"cover_distance": 0}, ValueError, "cover_distance must be a finite number > 0"),
])
def test_bad_arguments(head, kwargs, error, match):
    labels, grid = head
    kwargs = {"bones": labels, **kwargs}
    with pytest.raises(error, match=match):
        apply_plan(grid, Plan((Osteotomy("mandible"),)), **kwargs)


def test_bad_inputs(head):
    labels, grid = head
    plan = Plan((Osteotomy("mandible"),))
    no_tissue = labels.copy()
    no_tissue.point_data.remove(arrays.TISSUE)
    with pytest.raises(ValueError, match="no point array 'tissue'"):
        apply_plan(grid, plan, no_tissue)
    with pytest.raises(TypeError, match="grid must be a pyvista.UnstructuredGrid"):
        apply_plan(labels, plan, labels)
    with pytest.raises(TypeError, match="plan must be a pvcmf.Plan"):
        apply_plan(grid, "plan.toml", labels)
    moved_away = grid.translate((500.0, 0, 0), inplace=False)
    with pytest.raises(ValueError, match="no mesh node lies within"):
        apply_plan(moved_away, plan, labels)
    only_cranium = labels.copy()
    only_cranium[arrays.BONE] = np.where(labels[arrays.BONE] > 0, arrays.CRANIUM, 0).astype(np.uint8)
    # no teeth either: the mandible cannot be found from the anatomy
    tissue = np.asarray(labels[arrays.TISSUE])
    only_cranium[arrays.TISSUE] = np.where(tissue == arrays.TEETH, arrays.BONE_TISSUE,
                                           tissue).astype(np.uint8)
    with pytest.raises(ValueError, match="moves segment 'mandible'"):
        apply_plan(grid, plan, only_cranium)


def test_accessor_delegates(head):
    labels, grid = head
    plan = Plan((Osteotomy("mandible", (0, 0, 1.0)),))
    np.testing.assert_array_equal(grid.cmf.apply_plan(plan, labels)[arrays.BC],
                                  apply_plan(grid, plan, labels)[arrays.BC])


# --------------------------------------------------------------------------- with the MTM
@pytest.fixture(scope="module")
def small_head():
    """A narrower jaw with 2 mm of soft tissue: a few thousand tetrahedra for the solver."""
    return synthetic_head(half_width=3, thickness=2)


def _solver():
    return importlib.import_module("pvcmf.mtm").solve


def _materials(grid):
    grid = grid.copy()
    n = grid.n_cells
    grid.cell_data[arrays.E_FIBER] = np.full(n, 0.003)
    grid.cell_data[arrays.E_CROSS] = np.full(n, 0.003)
    grid.cell_data[arrays.NU] = np.full(n, 0.46)
    grid.cell_data[arrays.FIBER] = np.zeros((n, 3))
    return grid


def test_zero_plan_predicts_zero_displacement(small_head):
    solve = _solver()
    labels, grid = small_head
    post = solve(apply_plan(_materials(grid), Plan((Osteotomy("maxilla"),)), labels))
    np.testing.assert_allclose(post[arrays.DISPLACEMENT], 0.0, atol=1e-12)


def test_uniform_translation_moves_everything_uniformly():
    """Every constrained node translated by t (no fixed plane) -> u = t everywhere."""
    solve = _solver()
    labels, grid = synthetic_head(cranium=False, half_width=3, thickness=2)
    t = (1.5, -0.5, 2.0)
    plan = Plan((Osteotomy("maxilla", t), Osteotomy("mandible", t)))
    bc = apply_plan(_materials(grid), plan, labels, fixed_posterior=False)
    post = solve(bc)
    want = np.array([t[0], t[2], t[1]])  # (horizontal, vertical, AP) -> (x, z, y)
    np.testing.assert_allclose(post[arrays.DISPLACEMENT],
                               np.tile(want, (post.n_points, 1)), atol=1e-8)


def test_joint_nodes_move_exactly_with_the_mandible(small_head):
    solve = _solver()
    labels, grid = small_head
    plan = Plan((Osteotomy("mandible", (1.07, -0.74, 5.47), (0.0, 2.71, 0.0)),))
    post = solve(apply_plan(_materials(grid), plan, labels))
    joint = post[arrays.BC] == arrays.BC_JOINT
    u = post[arrays.DISPLACEMENT]
    np.testing.assert_allclose(u[joint], rigid(post.points[joint], plan, labels), atol=1e-10)
    slide = post[arrays.BC] == arrays.BC_SLIDING
    n = post[arrays.BC_NORMAL][slide]
    np.testing.assert_allclose(np.sum(u[slide] * n, axis=1),
                               np.sum(post[arrays.BC_DISPLACEMENT][slide] * n, axis=1),
                               atol=1e-10)
    assert np.abs(u[post[arrays.BC] == arrays.BC_FREE]).max() > 0.1  # the tissue follows


# --------------------------------------------------------------------------- figures
def test_figure_4_boundary_conditions(head, verify_image_cache):
    """Paper 000 Fig. 4 on the synthetic jaw: teeth sliding, mandible joint, posterior fixed."""
    from pvcmf.figures.boundary_conditions import figure_4

    labels, grid = head
    bc = apply_plan(grid, Plan((Osteotomy("mandible", (0, 0, 3.0)),)), labels)
    figure_4(bc, labels, window_size=(900, 320), point_size=5).show()


def test_figure_5_osteotomy(head, verify_image_cache):
    """Paper 000 Fig. 5 layout: face next to white (pre) and green (planned) segments."""
    from pvcmf.figures.osteotomy import figure_5
    from pvcmf.plan import TABLE_II

    labels, _ = head
    figure_5([(labels, TABLE_II[1]), (labels, TABLE_II[3])], window_size=(1000, 300)).show()
    with pytest.raises(ValueError, match="at least one"):
        figure_5([])


def test_osteotomy_panel_draws_the_scan_s_cut_apart(head):
    """``osteotomy.png``'s face, like the face figures, draws skin on a cut of the scan in
    the cut colour."""
    from pvcmf.figures.osteotomy import osteotomy_panel
    from pvcmf.filters.skin import extract_skin
    from pvcmf.plan import TABLE_II

    labels, _ = head
    skin = extract_skin(labels)
    marked = skin.copy()
    top = np.asarray(skin.points)[:, 2]
    marked.point_data[arrays.SKIN_CUT] = (top > np.percentile(top, 60)).astype(np.uint8)
    bluish = []
    for s in (skin, marked):
        p = osteotomy_panel(labels, TABLE_II[1], skin=s, window_size=(600, 300))
        img = p.screenshot(return_img=True)[:, :300, :3].astype(int)  # the face's panel
        p.close()
        bluish.append(int(((img[..., 2] - img[..., 0]) > 20).sum()))
    assert bluish[0] == 0 and bluish[1] > 300, bluish


def test_warns_when_almost_nothing_is_fixed(head):
    """A model whose posterior plane is a small tip (e.g. a whole head) is held almost only
    by the moving bone: apply_plan says so and names the two ways out."""
    import warnings

    labels, grid = head
    plan = Plan((Osteotomy("maxilla", (6.0, 5.0, -4.0), (0.0, 2.0, 5.0)),))
    c = grid.cell_centers().points
    y0 = grid.points[:, 1].min()
    tip = (c[:, 1] > y0 + 3.0) | ((np.abs(c[:, 0]) < 1.0) & (np.abs(c[:, 2] - 8.0) < 1.0))
    thin = grid.extract_cells(np.flatnonzero(tip)).cast_to_unstructured_grid()
    with pytest.warns(UserWarning, match="only .* nodes are fixed.*face_box.*fix_unmoved_bone"):
        out = apply_plan(thin, plan, labels)
    assert np.sum(out[arrays.BC] == arrays.BC_FIXED) < 0.01 * thin.n_points
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        apply_plan(thin, plan, labels, fix_unmoved_bone=True)  # held by the cranium: quiet
        apply_plan(grid, plan, labels)  # the toy's posterior plane is a real plane: quiet


def _rim_labelled_bone(labels):
    """The labels with the teeth's front layer (y = 8) labelled bone, as a CT segmentation
    labels the partial-volume rim of the enamel."""
    rim = labels.copy()
    tissue = rim[arrays.TISSUE].copy()
    tissue[(np.abs(rim.points[:, 1] - 8.0) < 1e-9) & (tissue == arrays.TEETH)] = \
        arrays.BONE_TISSUE
    rim[arrays.TISSUE] = tissue
    return rim


def test_teeth_margin_of_a_jaw_that_stays_is_freed_near_a_move(head):
    """The nodes on the teeth margin of a jaw that stays (bone within a voxel of its teeth:
    the crown's rim, the alveolar bone) are freed near the moving jaw like its fixed nodes;
    those on its TEETH voxels, and all of them without release_margin, still slide."""
    labels, grid = head
    rim = _rim_labelled_bone(labels)
    plan = Plan((Osteotomy("maxilla", (0, 0, 4.0)),))
    p = grid.points
    front = (np.abs(p[:, 0]) < 6) & (np.abs(p[:, 1] - 8.0) < 1e-9)
    lower = front & (p[:, 2] <= -2) & (p[:, 2] >= -6)
    upper = front & (p[:, 2] >= 2) & (p[:, 2] <= 6)
    assert lower.sum() > 10 and upper.sum() > 10
    out = apply_plan(grid, plan, rim, fix_unmoved_bone=True, release_margin="auto")
    bc = out[arrays.BC]
    assert np.all(bc[upper] == arrays.BC_SLIDING)  # rim of the moving maxilla
    assert np.all(bc[lower] == arrays.BC_FREE)  # rim of the mandible, which stays
    assert np.all(out[arrays.BC_NORMAL][lower] == 0)
    kept = apply_plan(grid, plan, rim, fix_unmoved_bone=True)[arrays.BC]
    assert np.all(kept[lower] == arrays.BC_SLIDING)  # no release_margin: pinned
    exact = apply_plan(grid, plan, labels, fix_unmoved_bone=True, release_margin="auto")
    assert np.all(exact[arrays.BC][lower] == arrays.BC_SLIDING)  # on TEETH voxels


def _volume_ratios(post):
    cells = post.cells_dict[pv.CellType.TETRA]

    def volumes(p):
        a = p[cells[:, 0]]
        return np.einsum("ij,ij->i", np.cross(p[cells[:, 1]] - a, p[cells[:, 2]] - a),
                         p[cells[:, 3]] - a)

    p = np.asarray(post.points)
    return volumes(p + np.asarray(post[arrays.DISPLACEMENT])) / volumes(p)


@pytest.mark.parametrize("rim", [False, True])
def test_maxilla_moved_up_and_back_inverts_no_tetrahedron(small_head, rim):
    """The maxilla 4 mm up and 4 mm back over 2 mm of tissue, the pipeline's boundary
    options: no tetrahedron turns inside out (the lower teeth's margin pinned as sliding
    held the tissue beside the moving jaw and inverted 14 of them)."""
    solve = _solver()
    labels, grid = small_head
    labels = _rim_labelled_bone(labels) if rim else labels
    plan = Plan((Osteotomy("maxilla", (0, 4.0, -4.0)),))
    bc = apply_plan(_materials(grid), plan, labels, fix_unmoved_bone=True,
                    release_margin="auto")
    post = solve(bc)
    ratios = _volume_ratios(post)
    assert ratios.min() > 0.1, f"volume ratio {ratios.min():.3f}"
    assert int(post.field_data[arrays.MTM_INVERTED][0]) == 0


def test_figure_4_is_drawn_as_a_photograph():
    """Fig. 4 draws the patient as a photograph: seen from behind (panel c), nodes on the
    patient's left lie on the viewer's left."""
    from pvcmf.figures.boundary_conditions import figure_4

    grid = pv.ImageData(dimensions=(9, 9, 9), spacing=(10.0, 10.0, 10.0),
                        origin=(-40.0, -40.0, -40.0)).triangulate()
    bc = np.full(grid.n_points, arrays.BC_CODES["free"], dtype=np.int8)
    bc[grid.points[:, 0] > 25.0] = arrays.BC_CODES["fixed"]  # the patient's left side
    grid.point_data[arrays.BC] = bc
    p = figure_4(grid, window_size=(900, 320), point_size=6)
    img = np.asarray(p.screenshot(return_img=True), dtype=int)[..., :3]
    p.close()
    panel = img[40:, 600:]  # panel c), below its title
    coloured = np.nonzero(panel.max(axis=-1) - panel.min(axis=-1) > 90)[1]
    assert coloured.size > 20 and coloured.mean() < 0.45 * panel.shape[1], coloured.mean()


# --------------------------------------------------------------------------- covered bone
def plate_in_a_coarse_mesh():
    """A 1 mm thick maxilla plate (|x| < 10, y = 0, |z| < 3) inside a block of fat, and a
    tetrahedral mesh of the block with 4 mm edges that covers the plate: no node lies
    within 1 mm of it (the nearest are 1.5 mm away, at y = -1.5). The mesh is
    mirror-symmetric about x = 0 (one half and its mirror image); the voxel centres lie
    off the mid-planes between nodes, so each has one nearest node."""
    img = pv.ImageData(dimensions=(30, 27, 26), origin=(-14.5, -13, -12.5))
    x, y, z = img.points.T
    plate = (np.abs(x) <= 10) & (y == 0) & (np.abs(z) <= 3)
    img[arrays.BONE] = np.where(plate, arrays.MAXILLA, 0).astype(np.uint8)
    img[arrays.TISSUE] = np.where(plate, arrays.BONE_TISSUE, arrays.FAT).astype(np.uint8)
    half = pv.ImageData(dimensions=(4, 6, 6), spacing=(4, 4, 4), origin=(0, -9.5, -10))
    half = half.cast_to_unstructured_grid().triangulate()
    tets = half.cells_dict[pv.CellType.TETRA]
    pts = np.asarray(half.points, dtype=float)
    mirror = pts * [-1, 1, 1]
    cells = np.vstack([tets, tets[:, [1, 0, 2, 3]] + len(pts)])  # mirrored, same orientation
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: cells}, np.vstack([pts, mirror])).clean()
    return img, grid


def test_bone_covered_by_the_mesh_moves_the_nodes_around_it():
    """A bone thinner than the elements lies inside them: each of its voxels is carried by
    its nearest node, which moves with it; by contact alone no node touches the plate."""
    from scipy.spatial import cKDTree

    labels, grid = plate_in_a_coarse_mesh()
    plan = Plan((Osteotomy("maxilla", (0.0, 0.0, 4.0)),))
    out = apply_plan(grid, plan, labels)
    bc = np.asarray(out[arrays.BC])
    plate = labels.points[labels[arrays.BONE] == arrays.MAXILLA]
    carriers = np.unique(cKDTree(grid.points).query(plate)[1])
    assert len(carriers) == 10  # x 0, +-4, +-8 and z +-2, at y = -1.5
    joint = np.flatnonzero(bc == arrays.BC_JOINT)
    np.testing.assert_array_equal(joint, carriers)
    np.testing.assert_allclose(out[arrays.BC_DISPLACEMENT][joint],
                               np.tile([0.0, 4.0, 0.0], (len(joint), 1)), atol=1e-12)
    np.testing.assert_allclose(grid.points[joint, 1], -1.5)
    with pytest.raises(ValueError, match="cover_distance=1 mm"):  # the nodes are 1.5 mm off
        apply_plan(grid, plan, labels, cover_distance=1.0)


def test_symmetric_covered_bone_gives_a_symmetric_response():
    solve = _solver()
    labels, grid = plate_in_a_coarse_mesh()
    plan = Plan((Osteotomy("maxilla", (0.0, 0.0, 4.0)),))
    post = solve(apply_plan(_materials(grid), plan, labels))
    p, u = post.points, np.asarray(post[arrays.DISPLACEMENT])
    mirror = cKDTree_query(p, p * [-1, 1, 1])
    np.testing.assert_allclose(u[mirror] * [-1, 1, 1], u, atol=1e-9)
    free = post[arrays.BC] == arrays.BC_FREE
    assert u[free, 1].max() > 1.0  # the tissue round the plate follows it


def test_plan_response_equals_the_full_solve_on_covered_bone():
    """The nodes a covered bone carries move rigidly with it in the plan-response operator
    as in the full solve (rotations too: the carried nodes' positions enter its basis)."""
    from pvcmf.mtm.response import plan_response

    labels, grid = plate_in_a_coarse_mesh()
    grid = _materials(grid)
    resp = plan_response(grid, labels, plan=Plan((Osteotomy("maxilla", (0.0, 0.0, 1.0)),)))
    plan = Plan((Osteotomy("maxilla", (0.7, -1.2, 3.1), (4.0, -2.5, 3.0)),))
    full = _solver()(apply_plan(grid, plan, labels))
    u = np.asarray(full[arrays.DISPLACEMENT])
    carried = np.asarray(full[arrays.BC]) == arrays.BC_JOINT
    assert carried.sum() == 10 and np.abs(u[~carried]).max() > 0.5
    np.testing.assert_allclose(resp.predict_mesh(plan), u, atol=1e-9)


def cKDTree_query(points, targets):
    """Index of the point of ``points`` at each of ``targets`` (they coincide)."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(targets)
    assert dist.max() < 1e-9
    return idx
