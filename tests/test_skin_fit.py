"""The mesh's skin pushed out around a dense skin (pvcmf.filters.meshing.fit_to_skin)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import pyvista as pv
from scipy.spatial import cKDTree

from pvcmf import arrays
from pvcmf.filters.meshing import fit_to_skin, tet_quality
from pvcmf.filters import surface_mapping
from pvcmf.filters.surface_mapping import Transfer, crumple_metric
from pvcmf.filters.meshing.skin_fit import dense_skin


def _sphere_points(r, n):
    """``n`` nearly even points on a sphere of radius ``r`` (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return r * np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi),
                                np.cos(phi)])


def _tets(grid):
    return np.asarray(grid.cells_dict[pv.CellType.TETRA])


@pytest.fixture(scope="module")
def shell():
    """A tetrahedral shell between radii 4 (the "bone") and 10 mm (the skin), about 1.5 mm
    elements (Delaunay of points on concentric spheres)."""
    radii = np.linspace(4.0, 10.0, 5)
    pts = np.vstack([_sphere_points(r, int(4 * np.pi * r * r / 1.5**2)) for r in radii])
    g = pv.PolyData(pts).delaunay_3d()
    keep = np.linalg.norm(g.cell_centers().points, axis=1) > 4.0
    g = g.extract_cells(np.flatnonzero(keep)).clean()
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: g.cells_dict[pv.CellType.TETRA]},
                               np.asarray(g.points, dtype=float))
    bone = np.linalg.norm(grid.points, axis=1) < 4.5
    return grid, bone


def _dimple(p, depth, width=0.5):
    """Points moved inward by a Gaussian dimple around +y (scaled with the radius)."""
    r = np.linalg.norm(p, axis=1, keepdims=True)
    d = p / np.maximum(r, 1e-12)
    angle = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
    return p - depth * np.exp(-(angle / width) ** 2)[:, None] * d * (r / 10.0)


def _field(points):
    """A smooth, non-affine displacement field (mm)."""
    x, y, z = points.T
    return np.column_stack([np.sin(x / 2), np.cos(z / 3) * np.sin(y / 2), 0.02 * y**2])


def _check_fit(grid, fitted, skin, pinned):
    tets = _tets(grid)
    _, vol, _ = tet_quality(fitted.points, tets)
    _, vol0, _ = tet_quality(grid.points, tets)
    assert (vol0 > 0).all()
    assert vol.min() > 0, "an element inverted"
    assert np.array_equal(fitted.points[pinned], grid.points[pinned])
    assert not np.shares_memory(fitted.points, grid.points)
    assert arrays.SKIN_FIT_PUSH not in grid.point_data
    push = np.asarray(fitted[arrays.SKIN_FIT_PUSH])
    assert np.allclose(fitted.points - grid.points, push)
    return Transfer(fitted, skin)


def test_sphere_mesh_inside_a_larger_skin(shell):
    grid, bone = shell
    before = grid.copy(deep=True)
    skin = pv.Sphere(radius=10.4, theta_resolution=90, phi_resolution=60)
    assert not Transfer(grid, skin).inside.any()
    fitted = fit_to_skin(grid, skin, fixed=bone)
    assert np.array_equal(grid.points, before.points)  # input not mutated
    transfer = _check_fit(grid, fitted, skin, bone)
    assert transfer.inside.all()
    assert fitted.field_data[arrays.SKIN_FIT_OUTSIDE_AFTER][0] == 0
    assert fitted.field_data[arrays.SKIN_FIT_OUTSIDE_BEFORE][0] == skin.n_points
    # the push is what the skin needs (0.4 mm + margin, a bit more between the nodes),
    # not more
    assert 0.4 < fitted.field_data[arrays.SKIN_FIT_MAX_PUSH][0] < 1.5
    r = np.linalg.norm(fitted.points, axis=1)
    assert r.max() < 11.0


def test_skin_normals_gate_the_push(shell):
    """With the skin's normals, only skin facing the way its closest mesh face does pushes
    (skin over a crack of the mesh faces the crack's walls sideways)."""
    grid, bone = shell
    skin = pv.Sphere(radius=10.4, theta_resolution=40, phi_resolution=30)
    skin = skin.compute_normals(point_normals=True, cell_normals=False, split_vertices=False,
                                auto_orient_normals=True)
    normals = np.asarray(skin.point_data[arrays.NORMALS])
    assert np.einsum("ij,ij->i", normals, skin.points).min() > 0  # outward
    facing = fit_to_skin(grid, skin, fixed=bone)
    assert facing.field_data[arrays.SKIN_FIT_OUTSIDE_AFTER][0] == 0
    sideways = skin.copy()
    sideways.point_data[arrays.NORMALS] = np.cross(normals, [0.0, 0.0, 1.0]) + 1e-9
    held = fit_to_skin(grid, sideways, fixed=bone)
    assert held.field_data[arrays.SKIN_FIT_NODES][0] == 0
    assert held.field_data[arrays.SKIN_FIT_OUTSIDE_AFTER][0] == skin.n_points


def test_concave_skin_and_the_crumple_metric(shell, monkeypatch):
    """A mesh whose dimple is deeper than the skin's: the skin's points in the dimple lie
    outside the mesh. Blending the feet's values with the nodal gradient (the fit's limit
    of a stiff slope) stretches edges there beyond the mesh's gradients, and so does a
    nearest-node copy; the affine fit to the feet does not; after the skin fit the points
    interpolate inside and no edge violates."""
    grid, bone = shell
    mesh = grid.copy()
    mesh.points = _dimple(grid.points, 3.0)
    sphere = pv.Sphere(radius=10.0, theta_resolution=140, phi_resolution=100)
    skin = sphere.copy()
    skin.points = _dimple(sphere.points, 2.0) * 1.03
    u = _field(mesh.points)
    transfer = Transfer(mesh, skin)
    loose = crumple_metric(skin, transfer(u), mesh, u, transfer=transfer)
    assert loose[arrays.CRUMPLE_VIOLATIONS] == 0
    near = cKDTree(mesh.points).query(skin.points)[1]
    assert crumple_metric(skin, u[near], mesh, u, transfer=transfer)[arrays.CRUMPLE_VIOLATIONS] > 0
    monkeypatch.setattr(surface_mapping, "FIT_STIFFNESS", 1e6)
    stiff = Transfer(mesh, skin, smoothing=0)  # the fit alone, before the smoothing steps
    blended = crumple_metric(skin, stiff(u), mesh, u, transfer=stiff)
    assert blended[arrays.CRUMPLE_VIOLATIONS] > 0
    monkeypatch.undo()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # a few slivers of the input may limit it
        fitted = fit_to_skin(mesh, skin, fixed=bone)
    transfer = _check_fit(mesh, fitted, skin, bone)
    assert transfer.inside.mean() > 0.97
    tight = crumple_metric(skin, transfer(u), fitted, u, transfer=transfer)
    assert tight[arrays.CRUMPLE_VIOLATIONS] == 0


def test_affine_field_stays_exact_after_the_fit(shell):
    grid, bone = shell
    skin = pv.Sphere(radius=10.6, theta_resolution=40, phi_resolution=30)
    fitted = fit_to_skin(grid, skin, fixed=bone)
    rng = np.random.default_rng(3)
    B, c = rng.normal(size=(3, 3)) * 0.2, rng.normal(size=3)
    far = np.array([[0.0, 0.0, 12.5], [11.8, 0.0, 0.0]])  # outside the fitted mesh
    for pts in (skin.points, far):
        got = Transfer(fitted, pts)(fitted.points @ B.T + c)
        assert np.abs(got - (pts @ B.T + c)).max() < 1e-9


def test_labels_keep_the_bone_interface_and_box_keeps_the_cut(shell):
    """Nodes next to bone in the label image and on the box's planes do not move."""
    grid, _ = shell
    half = grid.extract_cells(np.flatnonzero(grid.cell_centers().points[:, 1] > 0.0))
    half = pv.UnstructuredGrid({pv.CellType.TETRA: _tets(half)}, np.asarray(half.points))
    img = pv.ImageData(dimensions=(49, 49, 49), spacing=(0.5,) * 3, origin=(-12.0,) * 3)
    r = np.linalg.norm(img.points, axis=1)
    img[arrays.TISSUE] = np.select([r < 4.0, r < 10.0], [arrays.BONE_TISSUE, arrays.FAT],
                                   arrays.AIR).astype(np.uint8)
    skin = pv.Sphere(radius=10.4, theta_resolution=60, phi_resolution=40)
    skin = skin.extract_points(skin.points[:, 1] > 1.0, adjacent_cells=False)
    box = (-12.0, 12.0, 0.0, 12.0, -12.0, 12.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # slivers along the cut may limit it
        fitted = fit_to_skin(half, skin, labels=img, box=box)
    p = half.points
    on_bone = np.linalg.norm(p, axis=1) < 4.3
    on_cut = np.abs(p[:, 1] - box[2]) <= 0.5
    assert on_bone.sum() > 20 and on_cut.sum() > 20
    moved = np.linalg.norm(fitted.points - p, axis=1) > 0
    assert not moved[on_bone].any() and not moved[on_cut].any()
    assert moved.sum() > 50
    transfer = Transfer(fitted, skin)
    assert transfer.inside.mean() > 0.95


def test_bad_inputs(shell):
    grid, _ = shell
    skin = pv.Sphere(radius=10.4)
    with pytest.raises(ValueError, match="margin"):
        fit_to_skin(grid, skin, margin=-1.0)
    with pytest.raises(ValueError, match="reach"):
        fit_to_skin(grid, skin, reach=0)
    with pytest.raises(ValueError, match="iterations"):
        fit_to_skin(grid, skin, iterations=0)
    with pytest.raises(ValueError, match="fixed"):
        fit_to_skin(grid, skin, fixed=np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="box"):
        fit_to_skin(grid, skin, box=(1, 0, 0, 1, 0, 1))
    with pytest.raises(ValueError, match="skin"):
        fit_to_skin(grid, np.zeros((0, 3)))
    with pytest.raises(TypeError, match="grid"):
        fit_to_skin(skin, skin)


def test_dense_skin_within_the_box_only():
    """The pipeline's dense skin: clipped to the model's box, and a cavity that the box cuts
    (air enclosed in the whole head) shows no wall."""
    img = pv.ImageData(dimensions=(41, 41, 41), spacing=(1.0,) * 3, origin=(-20.0,) * 3)
    r = np.linalg.norm(img.points, axis=1)
    cavity = np.linalg.norm(img.points - np.array([0.0, 0.0, 0.0]), axis=1) < 5.0
    img[arrays.TISSUE] = np.where((r < 15.0) & ~cavity, arrays.FAT, arrays.AIR).astype(np.uint8)
    box = (-20.0, 20.0, 2.0, 20.0, -20.0, 20.0)  # cuts the cavity open
    skin = dense_skin(img, box)
    p = np.asarray(skin.points)
    assert p[:, 1].min() >= box[2]
    radius = np.linalg.norm(p, axis=1)
    assert np.abs(radius - 15.0).max() < 1.0  # the outer skin only: no cavity wall (r 5)
    whole = dense_skin(img, None)
    assert whole.n_points > 1.5 * skin.n_points


def test_simulate_fits_the_mesh_on_request(tmp_path):
    """``simulate(fit_skin=True)``: the fit runs after meshing and is recorded; the skin is
    the whole head's, unmoved beyond what the transfer reaches from the face box."""
    import json

    from pvcmf import datasets
    from pvcmf.filters.skin_prediction import transfer_reach
    from pvcmf.filters.surface_mapping import mesh_band
    from pvcmf.pipeline import face_box, simulate

    case = datasets.phantom(patient=3, spacing=3.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = simulate(case.ct, case.plan, tmp_path / "run", bones=case.truth, n_tets=4000,
                       muscles=False, classify=False, figures=False, fit_skin={"iterations": 2})
    assert "skin fit" in res.timings
    assert set(res.skin_fit) == set(arrays.SKIN_FIT_FIELDS)
    assert res.skin_fit[arrays.SKIN_FIT_OUTSIDE_AFTER] < res.skin_fit[arrays.SKIN_FIT_OUTSIDE_BEFORE]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary[arrays.SKIN_FIT_NODES] == res.skin_fit[arrays.SKIN_FIT_NODES] > 0
    assert arrays.SKIN_FIT_PUSH in res.mesh.point_data
    box = face_box(res.labels, 0.5)
    reach = transfer_reach(mesh_band(res.mesh))  # beyond what the mesh's transfer reaches
    back = res.skin_pre.points[:, 1] < box[2] - reach
    assert back.any() and not np.asarray(res.skin_pre[arrays.DISPLACEMENT])[back].any()
    assert arrays.NORMALS not in res.skin_post.point_data
