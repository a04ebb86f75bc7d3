"""Plan response operator: equals apply_plan + solve + transfer for random plans."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.filters import apply_plan, cut_bones
from pvcmf.filters.surface_mapping import Transfer, transfer_operator
from pvcmf.mtm import solve
from pvcmf.mtm.response import PlanResponseWarning, plan_response
from pvcmf.plan import Osteotomy, Plan


@pytest.fixture(scope="module")
def block():
    """Soft-tissue shell around a two-segment bone block (maxilla above, mandible below,
    teeth between them) and a skin sphere partly outside the mesh."""
    img = pv.ImageData(dimensions=(15, 15, 15), origin=(-7, -7, -7))
    p = np.asarray(img.points)
    inner = (np.abs(p) <= 3).all(axis=1)
    bone = np.where(inner, np.where(p[:, 2] > 0, arrays.MAXILLA, arrays.MANDIBLE), 0)
    img[arrays.BONE] = bone.astype(np.uint8)
    tissue = np.where(inner, arrays.BONE_TISSUE, arrays.FAT)
    tissue[inner & (np.abs(p[:, 2]) <= 0) & (p[:, 1] >= 3)] = arrays.TEETH
    img[arrays.TISSUE] = tissue.astype(np.uint8)
    soft = ~(np.abs(img.cell_centers().points) < 3).all(axis=1)
    grid = img.extract_cells(np.flatnonzero(soft)).triangulate().clean()
    grid.clear_data()
    grid.cell_data[arrays.E_FIBER] = np.full(grid.n_cells, 3e-3)
    grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.45)
    skin = pv.Sphere(radius=7.3, theta_resolution=30, phi_resolution=20)
    return grid, img, skin


def _random_plan(rng, segments=("maxilla", "mandible")):
    return Plan(tuple(Osteotomy(s, tuple(rng.uniform(-3, 3, 3)), tuple(rng.uniform(-30, 30, 3)))
                      for s in segments))


def _row_bounds(resp, grid, skin, s):
    """``|row| s`` per skin point and component ``(n_skin, 3)``: ``|T R| s`` for rows with
    more than :data:`SPARSE_MAX_NNZ` transfer weights, ``|T| (|R| s)`` for the others."""
    from pvcmf.mtm.response_operator import SPARSE_MAX_NNZ

    T = transfer_operator(grid, skin)
    R = np.transpose(resp.nodal, (1, 0, 2))  # (n, 3, K)
    dense = np.abs(np.einsum("ij,jck->ick", T.toarray(), R)) @ s
    sparse = abs(T) @ (np.abs(R) @ s)
    few = np.diff(T.indptr) <= SPARSE_MAX_NNZ
    return np.where(few[:, None], sparse, dense)


def test_predict_equals_full_solve(block):
    grid, img, skin = block
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts)
    T = transfer_operator(grid, skin)
    op = resp.skin_operator  # both kinds of rows: inside (4 weights) and outside the mesh
    assert len(op.sparse_rows) > 20 and len(op.dense_rows) > 20
    assert np.all(np.diff(T.indptr)[op.dense_rows] > 8)
    steps = Transfer(grid, skin).steps  # smoothed rows: folded first, smoothed after
    assert steps is not None and np.isin(steps.rows, op.dense_rows).all()
    rng = np.random.default_rng(3)
    for segments in (("maxilla", "mandible"), ("mandible",)):
        plan = _random_plan(rng, segments)
        full = solve(apply_plan(grid, plan, img, **opts))
        u = np.asarray(full[arrays.DISPLACEMENT])
        assert np.abs(u).max() > 0.5
        pred = resp.predict(plan)
        assert np.abs(pred[arrays.DISPLACEMENT] - T @ u).max() < 1e-9
        dense = T @ np.stack([resp.nodal[c] @ resp.parameters(plan) for c in range(3)], axis=1)
        assert np.abs(pred[arrays.DISPLACEMENT] - dense).max() < 1e-9
        assert np.allclose(pred.points, skin.points + pred[arrays.DISPLACEMENT])
        assert np.abs(resp.predict_nodes(plan) - u[resp.surface_ids]).max() < 1e-9
    stats = resp.statistics([_random_plan(rng) for _ in range(5)])
    assert stats.shape == (5, 3) and np.all(stats[:, 0] >= stats[:, 1])


def test_other_boundary_types_fall_back(block):
    grid, img, skin = block
    resp = plan_response(grid, img, skin=skin, dtype="float64",
                         bc_options={"fix_unmoved_bone": True},
                         plan=Plan((Osteotomy("maxilla"),)))
    plan = _random_plan(np.random.default_rng(4))  # moves the mandible too
    with pytest.warns(PlanResponseWarning):
        pred = resp.predict_displacement(plan)
    full = solve(apply_plan(grid, plan, img, fix_unmoved_bone=True))
    assert np.abs(pred - transfer_operator(grid, skin) @ full[arrays.DISPLACEMENT]).max() < 1e-9


def test_float32_storage_keeps_a_micrometre(block):
    """``dtype='auto'`` stores the skin operator in float32 only where the product stays
    within 1e-6 mm of float64; the statistics equal the magnitudes computed point by point
    over the modelled skin."""
    grid, img, skin = block
    opts = {"fix_unmoved_bone": True}
    auto = plan_response(grid, img, skin=skin, bc_options=opts)
    exact = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts)
    assert auto.float32_error is not None
    assert (auto.skin_response.dtype == np.float32) == (auto.float32_error <= 1e-6)
    # the decision follows the operator's bound, computed here: (K + 2) u |T R| s for a
    # dense row, (K + 2) u |T| |R| s for a row evaluated from the nodal response
    s = np.tile([0.5, 0.5, 0.5, 20.0], 6)
    u = np.finfo(np.float32).eps / 2
    assert np.isclose(auto.float32_error, 26 * u * _row_bounds(exact, grid, skin, s).max(),
                      rtol=1e-6)
    rng = np.random.default_rng(5)
    plans = [_random_plan(rng) for _ in range(6)]
    worst = max(np.abs(auto.predict_displacement(p) - exact.predict_displacement(p)).max()
                for p in plans)
    assert worst <= 1e-6
    stats = exact.statistics(plans)
    for row, plan in zip(stats, plans):
        mag = np.linalg.norm(exact.predict_displacement(plan)[exact.modelled], axis=1)
        assert np.allclose(row, [mag.max(), mag.mean(), np.sqrt((mag ** 2).mean())], rtol=1e-12)


def test_statistics_leave_out_the_scan_s_cut(block):
    """Skin on a cut of the scan (``skin_cut`` 1) is not the patient's: the statistics of
    the modelled skin leave it out, with or without a full solve."""
    grid, img, skin = block
    marked = skin.copy()
    z = np.asarray(skin.points)[:, 2]
    marked.point_data[arrays.SKIN_CUT] = (z > np.median(z)).astype(np.uint8)
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, img, skin=marked, dtype="float64", bc_options=opts,
                         plan=Plan((Osteotomy("maxilla"),)))
    judged = resp.modelled & (z <= np.median(z))
    assert 0 < judged.sum() < resp.modelled.sum()
    rng = np.random.default_rng(6)
    plans = [_random_plan(rng, ("maxilla",)) for _ in range(3)] + [_random_plan(rng)]
    with pytest.warns(PlanResponseWarning):  # the last moves the mandible: a full solve
        stats = resp.statistics(plans)
    for row, plan in zip(stats, plans):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PlanResponseWarning)
            mag = np.linalg.norm(resp.predict_displacement(plan)[judged], axis=1)
        assert np.allclose(row, [mag.max(), mag.mean(), np.sqrt((mag ** 2).mean())], rtol=1e-12)


def test_plan_sweep_finds_the_advancement(block):
    """A sweep of mandible advancements on one operator: the advancements that bring a lip
    point within 2 mm of a target are those the full solve finds."""
    from pvcmf.mtm.response import plan_grid

    grid, img, skin = block
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts,
                         plan=Plan((Osteotomy("mandible"),)))
    x = np.asarray(skin.points)
    lip = int(np.argmax(x[:, 1] - 5 * np.abs(x[:, 0]) - 5 * np.abs(x[:, 2] + 2)))
    target = x[lip] + [0.0, 4.0, 0.0]
    advance = np.arange(0.0, 8.01, 0.5)
    plans = plan_grid("mandible", translations=[[0.0, 0.0, a] for a in advance])
    u = resp.displacements(plans, points=[lip])[:, 0]
    for p, v in zip(plans[::4], u[::4]):
        assert np.abs(v - resp.predict_displacement(p)[lip]).max() < 1e-12
    miss = np.linalg.norm(x[lip] + u - target, axis=1)
    ok = miss <= 2.0
    assert ok.any() and not ok.all()
    T = transfer_operator(grid, skin)
    for i in (int(np.argmax(ok)), int(np.argmax(ok)) - 1):  # first inside, last outside
        full = solve(apply_plan(grid, plans[i], img, **opts))
        v = (T @ full[arrays.DISPLACEMENT])[lip]
        assert (np.linalg.norm(x[lip] + v - target) <= 2.0) == ok[i]
    with pytest.raises(ValueError, match="translations"):
        plan_grid("mandible", translations=[1.0, 2.0])


def test_predict_in_place_equals_a_new_surface(block):
    """``predict(plan, out=previous)`` updates the earlier surface in place and equals a new
    prediction; ``predict_displacement(out=)`` overwrites whatever the buffer held; skin
    beyond the transfer's reach stays at rest."""
    grid, img, skin = block
    skin = skin.merge(pv.Sphere(radius=2.0, center=(30.0, 0.0, 0.0)))  # far: unreached
    resp = plan_response(grid, img, skin=skin, dtype="float64",
                         bc_options={"fix_unmoved_bone": True})
    rng = np.random.default_rng(6)
    first, second = _random_plan(rng), _random_plan(rng)
    surf = resp.predict(first)
    again = resp.predict(second, out=surf)
    fresh = resp.predict(second)
    assert again is surf
    assert np.array_equal(again[arrays.DISPLACEMENT], fresh[arrays.DISPLACEMENT])
    assert np.allclose(again.points, fresh.points, rtol=0, atol=1e-12)
    buf = np.full((skin.n_points, 3), np.nan)
    assert resp.predict_displacement(second, out=buf) is buf
    assert np.array_equal(buf, fresh[arrays.DISPLACEMENT])
    assert len(resp.reached) < skin.n_points  # some skin lies beyond the transfer's reach
    assert np.all(buf[np.setdiff1d(np.arange(skin.n_points), resp.reached)] == 0)
    with pytest.raises(ValueError, match="out must be"):
        resp.predict_displacement(second, out=np.zeros((skin.n_points, 3), dtype=np.float32))
    with pytest.raises(ValueError, match="out must be"):
        resp.predict(second, out=pv.Sphere())


def test_float32_error_within_the_rounding_bound(block):
    """The float32 operator's error is within the rounding bound of a float32 product,
    ``(k + 2) eps |R| |a|`` (k terms per row, one rounding of storage and one of the
    parameters), and the statistics over every skin point equal the point-by-point ones."""
    grid, img, skin = block
    exact = plan_response(grid, img, skin=skin, dtype="float64",
                          bc_options={"fix_unmoved_bone": True})
    single = exact.astype(np.float32)
    eps = np.finfo(np.float32).eps / 2
    rng = np.random.default_rng(7)
    plans = [_random_plan(rng) for _ in range(4)]
    for plan in plans:
        a = exact.parameters(plan)
        bound = (len(a) + 2) * eps * _row_bounds(exact, grid, skin, np.abs(a)).T.ravel()
        err = np.abs(single.predict_displacement(plan) - exact.predict_displacement(plan))
        assert np.all(err.T.ravel() <= bound + 1e-300)
        assert err.max() > 0  # float32 is really used
    stats = exact.statistics(plans, chunk=3, modelled=False)
    for row, plan in zip(stats, plans):
        mag = np.linalg.norm(exact.predict_displacement(plan), axis=1)
        assert np.allclose(row, [mag.max(), mag.mean(), np.sqrt((mag ** 2).mean())], rtol=1e-12)


def test_auto_dtype_follows_the_bound(block, monkeypatch):
    """``dtype='auto'`` takes float32 exactly when the measured bound is within the
    tolerance (a larger tolerance switches the same operator to float32), and the float32
    error of random plans in the range stays within the bound."""
    from pvcmf.mtm import response

    grid, img, skin = block
    opts = {"fix_unmoved_bone": True}
    plan = Plan((Osteotomy("mandible"),))
    exact = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts, plan=plan)
    bound = exact.skin_operator.float32_error(1)
    assert bound > 1e-6  # the block's operator at 20 mm shifts: float64
    assert plan_response(grid, img, skin=skin, bc_options=opts, plan=plan).skin_response.dtype == np.float64
    monkeypatch.setattr(response, "FLOAT32_TOLERANCE", 1.01 * bound)
    auto = plan_response(grid, img, skin=skin, bc_options=opts, plan=plan)
    assert auto.skin_response.dtype == np.float32 and np.isclose(auto.float32_error, bound)
    rng = np.random.default_rng(8)
    for _ in range(5):  # within 30 degrees and 20 mm of centroid shift
        p = Plan((Osteotomy("mandible", tuple(rng.uniform(-10, 10, 3)), tuple(rng.uniform(-20, 20, 3))),))
        err = np.abs(auto.predict_displacement(p) - exact.predict_displacement(p)).max()
        assert 0 < err <= bound


def test_results_are_independent(block):
    """A predicted surface owns its points and data arrays: editing one result (points,
    displacement, the skin's own arrays, faces, in-place filters) changes neither the next
    result nor the input skin, and no result shares memory with the input skin."""
    grid, img, skin = block
    skin = skin.copy()
    skin.point_data["tag"] = np.arange(skin.n_points, dtype=float)
    skin.cell_data["cell_tag"] = np.arange(skin.n_cells, dtype=float)
    before = skin.copy(deep=True)
    resp = plan_response(grid, img, skin=skin, dtype="float64",
                         bc_options={"fix_unmoved_bone": True})
    plan = _random_plan(np.random.default_rng(9))
    first = resp.predict(plan)
    reference = (first.points.copy(), first[arrays.DISPLACEMENT].copy(), first.faces.copy())
    for name in ("tag", arrays.DISPLACEMENT):
        assert not np.shares_memory(first.point_data[name], skin.point_data["tag"])
    assert not np.shares_memory(first.points, skin.points)
    first.points[:] += 5.0
    first[arrays.DISPLACEMENT][:] = 9.0
    first.point_data["tag"][:] = -1.0
    first.cell_data["cell_tag"][:] = -1.0
    first.flip_faces(inplace=True)
    first.translate((1.0, 2.0, 3.0), inplace=True)
    second = resp.predict(plan)
    assert np.array_equal(second.points, reference[0])
    assert np.array_equal(second[arrays.DISPLACEMENT], reference[1])
    assert np.array_equal(second.faces, reference[2])
    assert np.array_equal(second.point_data["tag"], before.point_data["tag"])
    assert np.array_equal(second.cell_data["cell_tag"], before.cell_data["cell_tag"])
    first.faces = np.zeros(4, dtype=int) + [3, 0, 1, 2]  # a new connectivity of its own
    third = resp.predict(plan)
    assert np.array_equal(third.faces, reference[2]) and third.n_cells == skin.n_cells
    assert skin == before  # the input is untouched


def test_point_location_equals_brute_force():
    """The transfer's containing tetrahedra (binned boxes) equal a brute-force search over
    every tetrahedron: same inside/outside split, and the chosen tetrahedron's barycentric
    coordinates reproduce the point."""
    from pvcmf.filters.transfer_locate import INSIDE_TOL, Located, tet_gradients, tetra

    grid = pv.ImageData(dimensions=(6, 5, 4), spacing=(1.0, 1.3, 0.8)).triangulate()
    grid.points = grid.points + np.random.default_rng(10).normal(0, 0.1, (grid.n_points, 3))
    pts, tets = tetra(grid)
    rng = np.random.default_rng(11)
    p = np.vstack([rng.uniform(-0.5, 5.5, (400, 3)), pts[tets[:50]].mean(axis=1),
                   0.5 * (pts[tets[:40, 0]] + pts[tets[:40, 1]])])  # centroids, edge midpoints
    loc = Located(grid, p)
    inv, _ = tet_gradients(pts, tets)
    lam = np.einsum("tia,nti->nta", inv, p[:, None, :] - pts[tets[:, 0]][None])
    b = np.concatenate([1 - lam.sum(axis=2, keepdims=True), lam], axis=2)  # (n, m, 4)
    inside = b.min(axis=2).max(axis=1) >= -INSIDE_TOL
    assert inside.sum() > 100 and (~inside).sum() > 50
    assert np.array_equal(loc.inside, inside)
    ins = np.flatnonzero(inside)
    assert np.all(loc.bary[ins].min(axis=1) >= -INSIDE_TOL)
    back = np.einsum("na,nai->ni", loc.bary[ins], pts[tets[loc.cell[ins]]])
    assert np.abs(back - p[ins]).max() < 1e-12


def test_feet_equal_the_region_test():
    """The feet measured from each triangle's Gram entries (chunked) equal Ericson's region
    test on the corners, and each foot is the closest point of its triangle: no point of a
    dense sample of the triangle is closer; degenerate triangles give finite feet."""
    from pvcmf.filters.transfer_locate import _Triangles, closest_on_triangles

    rng = np.random.default_rng(12)
    corners = rng.normal(0, 1, (60, 3, 3))
    corners[0, 2] = corners[0, 1]  # two corners coincide
    corners[1, 2] = 0.5 * (corners[1, 0] + corners[1, 1])  # collinear
    p = rng.normal(0, 2, (200, 3))
    rows, tris = np.repeat(np.arange(200), 60), np.tile(np.arange(60), 200)
    frames = _Triangles(corners)
    frames.CHUNK = 1000  # several chunks
    d, q, b = frames.closest(p, rows, tris)
    q0, b0 = closest_on_triangles(p[rows], *(corners[tris, i] for i in range(3)))
    assert d.shape == (len(rows),) and q.shape == b.shape == (len(rows), 3)
    assert np.isfinite(q).all() and np.isfinite(b).all()
    assert np.abs(q - q0).max() < 1e-12 and np.abs(b - b0).max() < 1e-12
    assert np.allclose(d, np.linalg.norm(q0 - p[rows], axis=1), rtol=0, atol=1e-12)
    s = rng.dirichlet(np.ones(3), 400)  # samples of every triangle
    sample = np.einsum("sk,tkc->tsc", s, corners)
    brute = np.linalg.norm(sample[tris] - p[rows][:, None], axis=2).min(axis=1)
    assert np.all(d <= brute + 1e-12)


def test_basis_solves_skip_only_the_checks(block):
    """``Solver.solve(checks=False)`` (the operator's basis solves) returns the same
    displacement, with the checks' fields NaN and no SolutionWarning."""
    import warnings

    from pvcmf.mtm import Solver

    grid, img, _ = block
    ref = apply_plan(grid, _random_plan(np.random.default_rng(13)), img, fix_unmoved_bone=True)
    solver = Solver(ref, precision="double")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the plan may invert a few tetrahedra: checked
        u = solver.solve()
    assert np.isfinite(solver.info["inverted"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        v = solver.solve(np.asarray(ref[arrays.BC_DISPLACEMENT]) * 50.0, checks=False)
    assert np.isnan(solver.info["inverted"]) and np.isnan(solver.info["free_ratio"])
    assert np.abs(v - 50.0 * u).max() < 1e-9 * np.abs(v).max()


def test_cut_planes_and_labelled_segments(block):
    """The operator cuts the label image only when the template has cut planes: a labelled
    template uses the image as it is (not modified), a cut template the cut segments, and
    both predict what apply_plan + solve + transfer give."""
    from pvcmf.mtm.response import _segmented

    grid, img, skin = block
    before = img.copy(deep=True)
    labelled = Plan((Osteotomy("mandible"),))
    assert _segmented(img, labelled) is img
    cut = (((0.0, 0.0, 1.5), (0.0, 0.0, 1.0)),)  # the upper part of the maxilla block
    template = Plan((Osteotomy("maxilla", cut=cut),))
    segmented = _segmented(img, template)
    assert segmented is not img
    assert np.array_equal(segmented[arrays.BONE], cut_bones(img, template)[arrays.BONE])
    opts = {"fix_unmoved_bone": True}
    resp = plan_response(grid, img, skin=skin, dtype="float64", bc_options=opts, plan=template)
    rng = np.random.default_rng(14)
    plan = Plan((Osteotomy("maxilla", tuple(rng.uniform(-2, 2, 3)), tuple(rng.uniform(-10, 10, 3)),
                           cut=cut),))
    full = solve(apply_plan(grid, plan, img, **opts))
    u = np.asarray(full[arrays.DISPLACEMENT])
    assert np.abs(u).max() > 0.3
    T = transfer_operator(grid, skin)
    assert np.abs(resp.predict_displacement(plan) - T @ u).max() < 1e-9
    assert img == before


def test_skin_operator_equals_the_sparse_product():
    """Sparse rows on the nodal response plus dense rows equal ``W R a`` for any sparse
    ``W`` (empty rows, rows of one to forty weights, duplicate entries): one plan, the
    dense rows of chosen points, the blocks of many plans (each reached point once), float32
    storage within its rounding bound."""
    import scipy.sparse as sp

    from pvcmf.mtm.response_operator import SPARSE_MAX_NNZ, SkinOperator

    rng = np.random.default_rng(15)
    n, m, K = 300, 50, 24
    counts = rng.choice([0, 1, 4, SPARSE_MAX_NNZ, SPARSE_MAX_NNZ + 1, 20, 40], n)
    rows = np.repeat(np.arange(n), counts)
    cols = np.concatenate([rng.choice(m, c, replace=False) for c in counts])
    rows, cols = np.r_[rows, rows[:30]], np.r_[cols, cols[:30]]  # 30 duplicates (summed)
    W = sp.csr_matrix((rng.normal(size=len(rows)), (rows, cols)), shape=(n, m))
    W.data[:5] = 0.0  # explicit zeros: dropped from the operator, kept in W
    Wd = W.toarray()
    R = rng.normal(size=(m, 3, K))
    before = (W.data.copy(), W.indices.copy(), W.indptr.copy())
    op = SkinOperator(W, R)
    assert all(np.array_equal(x, y) for x, y in zip(before, (W.data, W.indices, W.indptr)))
    assert len(op.sparse_rows) and len(op.dense_rows) and len(op.reached) < n
    exact = np.einsum("ij,jck->ick", Wd, R)  # (n, 3, K)
    a = rng.normal(size=K)
    out = np.full(3 * n, np.nan)
    assert op.apply(a, out) is out
    assert np.abs(out.reshape(n, 3) - exact @ a).max() < 1e-12
    from concurrent.futures import ThreadPoolExecutor

    many = rng.normal(size=(24, K))  # concurrent plans on one operator
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda b: op.apply(b, np.empty(3 * n)).reshape(n, 3), many))
    assert max(np.abs(g - exact @ b).max() for g, b in zip(got, many)) < 1e-12
    ids = rng.choice(n, 40)
    assert np.abs(op.rows(ids) - np.transpose(exact[ids], (2, 0, 1))).max() < 1e-12
    A = rng.normal(size=(K, 5))
    seen = np.zeros(n, dtype=int)
    for got, U in op.blocks(A):
        seen[got] += 1
        assert np.abs(U - np.einsum("ick,kp->icp", exact[got], A)).max() < 1e-12
    assert np.array_equal(seen, (np.diff(W.indptr) > 0).astype(int))
    single = op.astype(np.float32)
    s = np.abs(a)
    u = np.finfo(np.float32).eps / 2
    few = (np.diff(W.indptr) <= SPARSE_MAX_NNZ)[:, None]
    bound = (K + 2) * u * np.where(few, np.abs(Wd) @ (np.abs(R) @ s), np.abs(exact) @ s)
    err = np.abs(single.apply(a, np.empty(3 * n)).reshape(n, 3) - exact @ a)
    assert err.max() > 0 and np.all(err <= 1.0001 * bound)


def test_transfer_in_background_equals_the_transfer(block):
    """The transfer built by a partner (forked process, or thread) and the calling thread,
    in ranges of points, equals :class:`Transfer` built here bit for bit, however the
    ranges are shared (both build some); ranges a dead partner had taken are built by the
    caller; an error of the build reaches the caller; a cancelled build leaves no child
    process behind."""
    import os
    import threading

    from pvcmf.filters.surface_mapping import Transfer
    from pvcmf.mtm import response_transfer

    grid, _, skin = block
    here = Transfer(grid, skin.points)
    chunk, default = response_transfer.CHUNK, response_transfer.BUILD_IN
    for where, size in (("process", chunk), ("thread", chunk), ("process", 37), ("thread", 37)):
        response_transfer.BUILD_IN, response_transfer.CHUNK = where, size
        try:
            pending = response_transfer.transfer_in_background(grid, skin)
            transfer, timings = pending.result()
        finally:
            response_transfer.BUILD_IN, response_transfer.CHUNK = default, chunk
        assert (pending.where == "second process") == (where == "process" and hasattr(os, "fork"))
        assert (transfer.W != here.W).nnz == 0 and (transfer.W0 != here.W0).nnz == 0
        assert np.array_equal(transfer.W0.data, here.W0.data)
        assert np.array_equal(transfer.W0.indices, here.W0.indices)
        assert np.array_equal(transfer.inside, here.inside)
        assert np.array_equal(transfer.modelled, here.modelled)
        n_ranges = -(-skin.n_points // size)
        assert sum(pending.ranges.values()) == n_ranges
        assert timings[f"transfer rows, CPU time ({pending.where})"] >= 0
    # a partner that took ranges and died: the caller builds them
    builder = response_transfer._Builder(grid, np.asarray(skin.points, dtype=float))
    builder.ranges = response_transfer.ranges(skin.n_points, 37)
    claims = response_transfer._Claims(len(builder.ranges), threading.Lock())
    taken = [claims.front(), claims.front()]
    dead = type("Dead", (), {"where": "second process", "cancel": lambda self: None,
                             "close": lambda self: None,
                             "result": lambda self: ({}, 0.0, 0.0)})()
    pending = response_transfer._Pending(builder, claims, dead)
    transfer, timings = pending.result()
    assert taken == [0, 1] and pending.ranges["calling thread"] == len(builder.ranges)
    assert (transfer.W != here.W).nnz == 0
    with pytest.raises(ValueError, match="points must have shape"):
        response_transfer.transfer_in_background(grid, pv.PolyData()).result()
    response_transfer.BUILD_IN = "process"
    try:
        pending = response_transfer.transfer_in_background(grid, skin)
    finally:
        response_transfer.BUILD_IN = default
    pending.cancel()
    if pending.where == "second process":
        with pytest.raises(ChildProcessError):
            os.waitpid(pending.partner.pid, 0)  # already reaped


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs os.fork")
def test_ranges_a_dead_child_wrote_are_kept(block, caplog):
    """The forked partner writes each range as it builds it: where it died after writing
    two of the three ranges it had taken (a torn record last), the parent keeps those two
    and builds the third with the rest, and the transfer equals :class:`Transfer`; an
    error the child sent reaches the caller."""
    import os
    import pickle
    import tempfile
    import threading

    from pvcmf.filters.surface_mapping import Transfer
    from pvcmf.mtm import response_transfer

    grid, _, skin = block
    here = Transfer(grid, skin.points)
    builder = response_transfer._Builder(grid, np.asarray(skin.points, dtype=float))
    builder.ranges = response_transfer.ranges(skin.n_points, 37)
    claims = response_transfer._Claims(len(builder.ranges), threading.Lock())
    taken = [claims.front() for _ in range(3)]

    def dead_child(records, tail=b""):
        proc = response_transfer._Process.__new__(response_transfer._Process)
        proc._file, proc._index_file = tempfile.TemporaryFile(), tempfile.TemporaryFile()
        for record in records:
            pickle.dump(record, proc._file, protocol=pickle.HIGHEST_PROTOCOL)
        proc._file.write(tail)
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        proc.pid = pid
        return proc

    written = {i: response_transfer.transfer_rows(builder.index(),
                                                  builder.x[slice(*builder.ranges[i])])
               for i in taken[:2]}
    torn = pickle.dumps(("range", taken[2], written[taken[0]]))[:50]
    partner = dead_child([("range", i, r) for i, r in written.items()], torn)
    with caplog.at_level("WARNING", logger="pvcmf.mtm.response_transfer"):
        pending = response_transfer._Pending(builder, claims, partner)
        transfer, _ = pending.result()
    assert "ended without an answer" in caplog.text
    assert pending.ranges["second process"] == 2
    assert pending.ranges["calling thread"] == len(builder.ranges) - 2
    assert (transfer.W != here.W).nnz == 0 and (transfer.W0 != here.W0).nnz == 0
    claims = response_transfer._Claims(len(builder.ranges), threading.Lock())
    partner = dead_child([("error", ValueError("from the child"))])
    with pytest.raises(ValueError, match="from the child"):
        response_transfer._Pending(builder, claims, partner).result()


def test_fold_on_several_threads_equals_one(block, monkeypatch):
    """The skin operator's fold split among threads (rows of its sparse products) gives the
    same numbers, bit for bit, as on one thread."""
    from pvcmf.filters import transfer_smoothing
    from pvcmf.filters.surface_mapping import Transfer
    from pvcmf.mtm.response_operator import SkinOperator

    grid, _, skin = block
    tr = Transfer(grid, skin.points)
    assert tr.steps is not None
    nodal = np.random.default_rng(3).normal(size=(grid.n_points, 3, 12))
    one = SkinOperator(tr.W0, nodal, steps=tr.steps, threads=1)
    monkeypatch.setattr(transfer_smoothing, "ROWS_PER_THREAD", 5)
    two = SkinOperator(tr.W0, nodal, steps=tr.steps, threads=3)
    assert np.array_equal(one.D, two.D) and np.array_equal(one.Ru, two.Ru)
    assert np.array_equal(transfer_smoothing.rows_product(tr.W0, nodal[:, 0], 3),
                          tr.W0 @ nodal[:, 0])


def test_fold_from_the_product_made_beside_the_join(block):
    """The transfer joined with ``right`` (its products with column blocks made on a second
    thread beside the smoothing steps) gives those products bit for bit, and the skin
    operator folded from them (one displacement component at a time) equals the one that
    makes its own products; products of another shape, or given with a transfer that
    needs tidying (an explicit zero out of order), are not used."""
    import scipy.sparse as sp

    from pvcmf.filters.transfer_locate import tetra
    from pvcmf.filters.transfer_parts import join_rows, prepared_index, ranges, transfer_rows
    from pvcmf.mtm.response_operator import SkinOperator

    grid, _, skin = block
    points, tets = tetra(grid)
    index = prepared_index(pv.UnstructuredGrid({pv.CellType.TETRA: tets}, points))
    x = np.asarray(skin.points, dtype=float)
    parts = [transfer_rows(index, x[a:b]) for a, b in ranges(len(x), 97)]
    nodal = np.random.default_rng(8).normal(size=(grid.n_points, 3, 12))
    right = [np.ascontiguousarray(nodal[:, c]) for c in range(3)]
    plain = join_rows(index, x, parts)
    joined = join_rows(index, x, parts, right=right)
    assert plain.product is None and joined.steps is not None
    assert all(np.array_equal(p, joined.W0 @ r) for p, r in zip(joined.product, right))
    assert (joined.W0 != plain.W0).nnz == 0
    own = SkinOperator(joined.W0, nodal, steps=joined.steps)
    assert np.abs(own.rows(np.arange(len(x))) - np.einsum(
        "ij,jck->kic", joined.W.toarray(), nodal)).max() < 1e-12 * np.abs(nodal).max()
    for threads in (1, 2):
        got = SkinOperator(joined.W0, nodal, steps=joined.steps, threads=threads,
                           product=joined.product)
        assert np.array_equal(got.D, own.D) and np.array_equal(got.Ru, own.Ru)
    wrong = SkinOperator(joined.W0, nodal, steps=joined.steps, product=joined.product[:-1])
    assert np.array_equal(wrong.D, own.D)
    # the same operator with an explicit zero (unsorted) in its last row: tidied, so a
    # product (here a wrong one) is not used
    dup = sp.csr_matrix((np.r_[joined.W0.data, [0.0]], np.r_[joined.W0.indices, [0]],
                         np.r_[joined.W0.indptr[:-1], [joined.W0.nnz + 1]]), joined.W0.shape)
    assert not (dup.has_canonical_format and np.all(dup.data))
    zeros = [np.zeros_like(p) for p in joined.product]
    tidy = SkinOperator(dup, nodal, steps=joined.steps, product=zeros)
    assert np.array_equal(tidy.D, own.D)
    with pytest.raises(ValueError, match="right must hold"):
        join_rows(index, x, parts, right=[r[:-1] for r in right])
    with pytest.raises(ValueError, match="right must be a non-empty list"):
        join_rows(index, x, parts, right=right[0])


def test_auto_release_margin_is_fixed_from_the_plan_given(block):
    """``release_margin='auto'`` frees the fixed nodes within twice the plan's largest move:
    the operator fixes that margin from the plan it is built with and equals apply_plan's
    'auto' for that plan; built without motions it refuses."""
    grid, img, skin = block
    opts = {"fix_unmoved_bone": True, "release_margin": "auto"}
    plan = Plan((Osteotomy("mandible", (0.8, 0.3, -0.2), (2.0, 0.0, 1.0)),))
    resp = plan_response(grid, img, skin=skin, plan=plan, dtype="float64", bc_options=opts)
    ref = apply_plan(grid, plan, img, **opts)
    plain = apply_plan(grid, plan, img, fix_unmoved_bone=True)
    # the margin frees nodes here, so a margin left at 'auto' per unit probe would differ
    assert np.sum(ref[arrays.BC] == arrays.BC_FREE) > np.sum(plain[arrays.BC] == arrays.BC_FREE)
    u = np.asarray(solve(ref)[arrays.DISPLACEMENT])
    T = transfer_operator(grid, skin)
    assert np.abs(resp.predict(plan)[arrays.DISPLACEMENT] - T @ u).max() < 1e-9
    moving = np.isin(ref[arrays.BC], (arrays.BC_JOINT, arrays.BC_SLIDING))
    assert resp.release_margin == pytest.approx(
        2 * np.linalg.norm(ref[arrays.BC_DISPLACEMENT][moving], axis=1).max())
    with pytest.raises(ValueError, match="release_margin='auto'"):
        plan_response(grid, img, skin=skin, plan=Plan((Osteotomy("mandible"),)),
                      bc_options=opts)
