"""An independent truth: the virtual patient's true anatomy meshed and constrained on its own.

:func:`independent_truth_grid` shares with the models it judges neither the mesher, nor
the labels, nor the boundary model:

* geometry: the exact level sets of the patient (:mod:`pvcmf.truth.anatomy`; atlas signed
  distances through the patient warp), never the voxel labels. The meshed soft tissue is
  inside the skin, outside every bone, tooth, air cavity, the tongue (with the oral air it
  is the oral cavity, a free surface: a tongue joined to the lips by thin bridges of
  tissue between the teeth would hang on bridges that every lattice resolves differently)
  and the brain case, in front of the coronal plane of the face box (``face_fraction``);
* mesher: a Freudenthal lattice (six tetrahedra per cube, spacing from ``n_tets``), not
  :func:`pvcmf.filters.tetrahedralize`. Tetrahedra with an edge across a gap of the
  anatomy thinner than the lattice are not meshed (:data:`GAP_RATIO`); boundary nodes are
  snapped onto the exact surfaces by Newton projection; elements that the snap flattens
  with all four nodes on one surface (caps) are dropped, interior nodes next to other
  flattened elements are smoothed, and the snaps still flattening an element are undone;
  pieces of the lattice that hang on the body by an edge or a vertex are dropped (they
  would hinge freely). The lattice meshes less of the soft tissue the coarser it is (the
  thin tissue of the face is about one lattice cell thick); ``mesher="conforming"``
  (:func:`pvcmf.truth.conform.conforming_mesh`, gmsh on the exact surface) meshes the same
  volume at every size; ``mesher="graded"`` (:func:`pvcmf.truth.graded.graded_mesh`) is
  that mesh refined in the face that the plan moves;
* materials: the muscle fraction of each tetrahedron (the twelve facial muscles,
  temporalis, neck muscles; the eyes excluded), sampled at points inside it, mixes Table I
  fat and muscle (rule of mixtures), so a muscle sheet thinner than the elements keeps its
  stiffness on every mesh; muscle isotropic (the truth's fibre term vanishes for Table I).
  With ``materials="field"`` the mixture is a field of the position instead
  (:func:`material_field`: the muscle indicator sampled every :data:`MATERIAL_MM` mm and
  smoothed), projected onto quadratic polynomials on each element by the solver, so the
  stiffness varies inside an element and every mesh integrates the same material;
* boundary model, no :func:`pvcmf.filters.apply_plan`: soft tissue is tied to the bone
  surfaces it touches (periosteum): a node on a bone surface moves by the plan's rigid
  moves of the segments (``segment_transforms`` of the cut bones; unmoved bone: none)
  blended by smooth weights of the position (:data:`BLEND_MM`; a displacement that jumps
  across a line of the tied surface has no finite-energy solution, and a band left free
  node by node moves with the mesh); nodes on the posterior plane are held, except within
  :data:`CLEARANCE_MM` of a moved bone. Tooth surfaces and air cavities (mouth, airway,
  sinuses) are free surfaces: **no contact is modelled** (lips and cheeks neither slide on
  nor are pushed by the teeth; a lip that would enter a moved tooth is not stopped);
* law and solver: :func:`pvcmf.truth.solver.solve_reference` (compressible neo-Hookean,
  P2, load stepping, damped Newton).

The study uses it with ``study_predictor(truth="independent")``. The refinement study of
``benchmarks/study.py --refinement`` (measured on the exact skin by
:mod:`pvcmf.truth.refinement`) shows it converged on the four phantoms with
``mesher="graded"``, ``materials="field"`` and ``face_margin_mm=30``; the study's default
truth is still :func:`pvcmf.truth.grid.truth_grid`, which the gallery's figures use.
"""

from __future__ import annotations

import hashlib
import logging

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .. import arrays, filters
from ..atlas.muscles import _muscle_models
from ..atlas.shapes import F32
from ..atlas.soft_tissue import eyes_sdf, neck_muscles_sdf, temporalis_sdf, tongue_sdf
from ..cache import cache_root
from ..filters.model_region import face_box
from ..filters.osteotomy import cut_bones, segment_transforms, voxel_points
from .anatomy import _warp
from .conform import conforming_mesh
from .exact import _BOUNDARY, _fields, _labelled_grid, _materials, _project, _region, _volumes  # noqa: F401,E501 (re-exported)
from .graded import face_size, graded_mesh
from .grid import cached, grid_hash
from .solver import solve_reference

log = logging.getLogger("pvcmf.reference")

__all__ = ["independent_truth_grid", "soft_tissue_mesh", "truth_problem"]

#: width (mm, Gaussian sigma) over which the tied bone surface's data blends from one
#: segment's rigid move to the next across an osteotomy (a field of the position, the same
#: on every mesh)
BLEND_MM = 4.0
#: distance (mm) from a moved bone segment within which the posterior plane is free
CLEARANCE_MM = 20.0
#: a lattice edge whose midpoint bulges out of the soft tissue by more than this share of
#: the spacing crosses a gap of the anatomy: its tetrahedra are not meshed
GAP_RATIO = 0.25
#: sampling step (mm) and Gaussian smoothing (sigma, mm) of the muscle indicator whose
#: rule-of-mixtures materials the truth evaluates at its quadrature points
MATERIAL_MM, MATERIAL_SIGMA_MM = 1.5, 1.0

def _lattice(box, h):
    """Freudenthal lattice of ``box`` (x0, x1, y0, y1, z0, z1) at spacing ``h``: points
    and tetrahedra (six per cube, conforming)."""
    axes = [np.arange(box[2 * i], box[2 * i + 1] + h, h) for i in range(3)]
    n = [len(a) for a in axes]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    idx = np.arange(np.prod(n)).reshape(n)
    c = idx[:-1, :-1, :-1].ravel()
    sx, sy, sz = n[1] * n[2], n[2], 1
    corner = {(i, j, k): c + i * sx + j * sy + k * sz for i in (0, 1) for j in (0, 1)
              for k in (0, 1)}
    paths = [((1, 0, 0), (1, 1, 0)), ((1, 0, 0), (1, 0, 1)), ((0, 1, 0), (1, 1, 0)),
             ((0, 1, 0), (0, 1, 1)), ((0, 0, 1), (1, 0, 1)), ((0, 0, 1), (0, 1, 1))]
    tets = np.concatenate([np.column_stack([corner[(0, 0, 0)], corner[a], corner[b],
                                            corner[(1, 1, 1)]]) for a, b in paths])
    flip = _volumes(grid, tets) < 0  # positive orientation
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    return grid, tets


def _main_parts(tets, share=0.02):
    """The tetrahedra of the face-connected parts that hold at least ``share`` of them.

    The lattice leaves small pieces hanging on the body by an edge or a vertex (a thin
    part of the anatomy coarser than the lattice); such a piece hinges freely (a
    near-singular Newton system) and which pieces there are changes with every lattice:
    they go, so every mesh is one solid (or a few large ones)."""
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]],
                                    tets[:, [0, 2, 3]], tets[:, [1, 2, 3]]]), axis=1)
    owner = np.tile(np.arange(len(tets)), 4)
    _, inv = np.unique(faces, axis=0, return_inverse=True)
    order = np.argsort(inv.ravel(), kind="stable")
    same = np.flatnonzero(np.diff(inv.ravel()[order]) == 0)  # interior faces: two owners
    a, b = owner[order][same], owner[order][same + 1]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(tets), len(tets)))
    _, part = connected_components(graph, directed=False)
    size = np.bincount(part)
    return tets[size[part] >= share * len(tets)]


def _bridges(warp, x, r, tets, h, ratio=GAP_RATIO):
    """Tetrahedra with an edge that crosses a gap of the anatomy (boolean mask).

    An edge whose midpoint lies outside the soft tissue by more than ``ratio * h`` beyond
    the mean of its ends' region values spans something thinner than the lattice (the
    oral air between tongue and palate, a thin bone wall, a tooth, a skin fold): kept, it
    would glue the tissue on both sides together on one lattice and not on the next."""
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    a, b = tets[:, pairs[:, 0]], tets[:, pairs[:, 1]]
    mid, _ = _region(_fields(warp, ((x[a] + x[b]) / 2).reshape(-1, 3)))
    mid = mid.reshape(a.shape)
    return ((mid > 0) & (mid - (r[a] + r[b]) / 2 > ratio * h)).any(axis=1)


def _snap(warp, x, tets, nodes, boundary, h, steps=4, dh=0.2, rounds=10):
    """Boundary ``nodes`` projected onto their active surface (Newton, at most ``h`` each).

    Returns the moved points and a mask of the tetrahedra to keep. A snap flattens an
    element below a tenth of its volume where all four of its nodes are on the boundary
    and land on one surface (a cap over the surface; no mesh of the exact anatomy holds
    it): such elements are dropped. Elsewhere the interior nodes next to a flattened element
    move to the mean of their neighbours (Laplacian smoothing, a few rounds), and the snaps
    of the elements still flattened after that are undone. ``boundary`` lists every
    boundary node (never smoothed)."""
    y = x.copy()
    p = _project(warp, x[nodes], steps, dh)
    ok = np.linalg.norm(p - x[nodes], axis=1) <= h
    y[nodes[ok]] = p[ok]
    v0 = _volumes(x, tets)
    n = len(x)
    movable = np.ones(n, dtype=bool)
    movable[boundary] = False
    keep = ~((_volumes(y, tets) < 0.1 * v0) & ~movable[tets].any(axis=1))
    t = tets[keep]
    a, b = t[:, [0, 0, 0, 1, 1, 2]].ravel(), t[:, [1, 2, 3, 2, 3, 3]].ravel()
    adj = coo_matrix((np.ones(2 * len(a)), (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.maximum(np.asarray(adj.sum(axis=1)).ravel(), 1.0)
    for _ in range(rounds):  # smoothing rounds, each vectorised over the nodes
        bad = _volumes(y, t) < 0.1 * v0[keep]
        if not bad.any():
            return y, keep
        near = np.zeros(n, dtype=bool)
        near[t[bad]] = True
        near |= adj @ near.astype(float) > 0
        sel = near & movable
        y[sel] = (adj @ y)[sel] / deg[sel, None]
    for _ in range(100):  # undo what smoothing could not save, each round vectorised
        bad = _volumes(y, t) < 0.1 * v0[keep]
        if not bad.any():
            break
        back = np.unique(t[bad])
        y[back] = x[back]
    return y, keep


def soft_tissue_mesh(case, *, n_tets=30_000, face_fraction=0.5, progress_bar=False):
    """The patient's true soft tissue meshed by the lattice-and-snap mesher (module doc).

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient.
    n_tets : int, default 30000
        About how many tetrahedra (sets the lattice spacing).
    face_fraction : float, default 0.5
        Anterior share of the head that is meshed.
    progress_bar : bool, default False
        Unused (one vectorised pass); kept for the common signature.

    Returns
    -------
    pyvista.UnstructuredGrid
        Linear tetrahedra with cell arrays ``arrays.TISSUE`` (FAT / MUSCLE_TISSUE) and
        ``arrays.MUSCLE`` (facial muscle ids, 0 elsewhere) and point array ``boundary``
        (index into ``("interior", "skin", "bone", "teeth", "air", "brain", "plane")``).
    """
    warp = _warp(case)
    box = face_box(case.truth, face_fraction)
    soft = np.isin(np.asarray(case.truth[arrays.TISSUE]), arrays.SOFT_LABELS)
    pts = voxel_points(case.truth, np.flatnonzero(soft))
    volume = float(np.count_nonzero(pts[:, 1] >= box[2])) * float(np.prod(case.truth.spacing))
    h = (6.0 * volume / n_tets) ** (1 / 3)
    lo, hi = pts[pts[:, 1] >= box[2]].min(axis=0) - h, pts.max(axis=0) + h
    x, tets = _lattice((lo[0], hi[0], box[2], hi[1], lo[2], hi[2]), h)
    r, _ = _region(_fields(warp, x))
    tets = tets[r[tets].mean(axis=1) < 0]
    tets = _main_parts(tets[~_bridges(warp, x, r, tets, h)])
    used = np.unique(tets)
    remap = np.full(len(x), -1)
    remap[used] = np.arange(len(used))
    x, tets, r = x[used], remap[tets], r[used]
    surf = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, x).extract_surface(
        pass_pointid=True, algorithm="dataset_surface")
    on = np.unique(np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS]))
    plane = on[np.isclose(x[on, 1], box[2])]
    free = np.setdiff1d(on, plane)
    x, keep = _snap(warp, x, tets, free, on, h)
    tets = _main_parts(tets[keep])
    used = np.unique(tets)
    remap = np.full(len(x), -1)
    remap[used] = np.arange(len(used))
    x, tets, free, plane = x[used], remap[tets], remap[free], remap[plane]
    free, plane = free[free >= 0], plane[plane >= 0]
    on = np.union1d(free, plane)
    grid = _labelled_grid(x, tets, free, plane, warp)
    log.info("independent truth mesh: %d tetrahedra at %.2f mm, %d boundary nodes",
             grid.n_cells, h, len(on))
    return grid


def _muscle_indicator(warp, x):
    """1 inside a muscle (the twelve facial muscles, temporalis, neck muscles, tongue; the
    eyes excluded), 0 elsewhere, at patient points ``x`` (n, 3)."""
    X = tuple(x[:, i].astype(F32) for i in range(3))
    s = warp.soft(warp.base_inverse(X))
    inside = np.minimum.reduce([np.asarray(fn(s), float)
                                for fn in (tongue_sdf, temporalis_sdf, neck_muscles_sdf)]) < 0
    for model in _muscle_models().values():  # twelve muscles, vectorised inside
        inside |= np.asarray(model(s)) < 0
    return (inside & ~(np.asarray(eyes_sdf(s), float) < 0)).astype(np.float32)


def material_field(case, grid, *, step=MATERIAL_MM, sigma=MATERIAL_SIGMA_MM):
    """The truth's materials as fields of the position (``materials`` of
    :func:`pvcmf.truth.solver.solve_reference`): Table I fat and muscle mixed by the muscle
    indicator of the exact anatomy, sampled every ``step`` mm over the grid's bounding box
    and smoothed by a Gaussian of ``sigma`` mm, so every mesh integrates the same material
    (a per-element muscle fraction would change with the elements). The lattice is the
    whole multiples of ``step`` in the patient frame over the grid's bounds (and four steps
    beyond), so every mesh samples the same points: a lattice starting at each grid's own
    bounds was offset between two meshes, and with a muscle up to some 260 times stiffer
    than fat the two trilinear interpolants differed by up to about ten times at a
    muscle's edge.

    Returns
    -------
    dict
        ``origin``, ``end`` (mm), ``e_cross``, ``nu`` (nz, ny, nx) and ``fraction``.
    """
    warp = _warp(case)
    b = np.asarray(grid.bounds, dtype=float).reshape(3, 2)
    # whole multiples of the step: every mesh samples the same lattice points
    lo, hi = np.floor(b[:, 0] / step) - 4, np.ceil(b[:, 1] / step) + 4
    axes = [step * np.arange(lo[i], hi[i] + 1) for i in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")  # x fastest
    p = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    f = np.empty(len(p), dtype=np.float32)
    for i in range(0, len(p), 250_000):  # chunks bound the memory of the level sets
        f[i:i + 250_000] = _muscle_indicator(warp, p[i:i + 250_000])
    f = np.clip(ndimage.gaussian_filter(f.reshape(x.shape), sigma / step), 0.0, 1.0)
    # Table I fat (fraction 0) and muscle (1), mixed as assign_materials mixes them
    two = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3], [0, 1, 2, 3]])},
                              np.vstack([np.zeros(3), np.eye(3)]))
    two.cell_data[arrays.TISSUE] = np.array([arrays.FAT, arrays.MUSCLE_TISSUE], np.uint8)
    two.cell_data[arrays.MUSCLE_FRACTION] = np.array([0.0, 1.0])
    two = filters.assign_materials(two, default_fiber=(0.0, 0.0, 1.0))
    e, nu = (np.asarray(two.cell_data[k], float) for k in (arrays.E_CROSS, arrays.NU))
    return {"origin": (axes[0][0], axes[1][0], axes[2][0]),
            "end": (axes[0][-1], axes[1][-1], axes[2][-1]), "fraction": f,
            "e_cross": e[0] + f * (e[1] - e[0]), "nu": nu[0] + f * (nu[1] - nu[0])}


def _segment_weights(labels, segments, x, sigma=BLEND_MM):
    """Smooth partition of unity over the bone segments at points ``x`` (n, 3): (n, k).

    Every voxel of the cut labels takes the segment of its nearest bone voxel (exact
    Euclidean distance transform), each segment's indicator is smoothed by a Gaussian of
    ``sigma`` mm and interpolated trilinearly at the points: a field of the position alone,
    one minus the others' weight inside a segment farther than about ``3 sigma`` from the
    next, blending across an osteotomy over about ``+-2 sigma``."""
    spacing = np.asarray(labels.spacing, dtype=float)
    bone = np.asarray(labels[arrays.BONE]).reshape(labels.dimensions, order="F")
    idx = ndimage.distance_transform_edt(bone == 0, sampling=spacing, return_distances=False,
                                         return_indices=True)
    nearest = bone[tuple(idx)]
    ijk = ((np.asarray(x, dtype=float) - np.asarray(labels.origin, dtype=float)) / spacing).T
    w = np.column_stack([ndimage.map_coordinates(
        ndimage.gaussian_filter((nearest == s).astype(np.float32), sigma / spacing,
                                mode="nearest"), ijk, order=1, mode="nearest")
        for s in segments])  # a few segments
    return w / np.maximum(w.sum(axis=1, keepdims=True), np.finfo(np.float32).tiny)


def _boundary_conditions(case, grid, blend=BLEND_MM, clearance=CLEARANCE_MM):
    """Point arrays bc / bc_displacement of the truth's own boundary model (module doc).

    Every node on a bone surface is tied (periosteum): its displacement is the blend
    ``sum_s w_s(x) (T_s x - x)`` of the segments' rigid moves of the plan (unmoved bone:
    the identity) with the smooth weights of :func:`_segment_weights` (Gaussian ``blend``
    mm). The data is a smooth field of the position, so every mesh interpolates the same
    boundary data (a displacement that jumps across a line of the tied surface has no
    finite-energy solution, and a band switched free node by node moves with the mesh).
    Nodes of the posterior plane are held, except within ``clearance`` mm of a moved bone
    segment, where they are free (the back cut is artificial: held next to a moving bone it
    would shear the tissue between them by the whole bone move)."""
    labels = cut_bones(case.truth, case.plan)
    moves = segment_transforms(labels, case.plan)
    bone_ids = np.asarray(labels[arrays.BONE])
    ids = np.flatnonzero(bone_ids > 0)
    kind = np.asarray(grid.point_data["boundary"])
    x = np.asarray(grid.points, dtype=float)
    bc = np.full(len(x), arrays.BC_FREE, dtype=np.int8)
    disp = np.zeros((len(x), 3))
    on_bone = np.flatnonzero(kind == 1 + _BOUNDARY.index("bone"))
    p = x[on_bone]
    segments = np.unique(bone_ids[ids])
    w = _segment_weights(labels, segments, p, blend)
    eye = np.eye(4)
    for j, s in enumerate(segments):  # a few bone segments
        m = moves.get(s, eye)
        disp[on_bone] += w[:, j:j + 1] * (p @ m[:3, :3].T + m[:3, 3] - p)
    bc[on_bone] = arrays.BC_JOINT
    plane = np.flatnonzero(kind == len(_BOUNDARY) + 1)
    mobile = [s for s in segments if not np.allclose(moves.get(s, eye), eye)]
    near = np.zeros(len(plane), dtype=bool)
    for s in mobile:  # the artificial back cut is left free near a moved bone
        tree = cKDTree(voxel_points(labels, ids[bone_ids[ids] == s]))
        near |= tree.query(x[plane])[0] < clearance
    bc[plane[~near]] = arrays.BC_FIXED
    grid.point_data[arrays.BC] = bc
    grid.point_data[arrays.BC_DISPLACEMENT] = disp
    log.info("independent truth: %d bone nodes tied (segment moves blended over %.1f mm), "
             "%d of %d plane nodes free near a moved bone", len(on_bone), blend,
             int(near.sum()), len(plane))
    return grid


def independent_truth_grid(case, *, n_tets=30_000, order=2, steps=4, face_fraction=0.5,
                           cache=True, cache_dir=None, mesher="lattice", reuse_factor=False,
                           materials="cells", face_mm=3.0, blend_mm=BLEND_MM,
                           face_margin_mm=0.0, progress_bar=False):
    """The solved independent truth of a virtual patient (module docstring).

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient (``truth`` labels for the bone segments, ``plan``).
    n_tets : int, default 30000
        About how many tetrahedra (P2 elements).
    order, steps :
        See :func:`pvcmf.truth.solver.solve_reference`.
    face_fraction : float, default 0.5
        Anterior share of the head that is meshed.
    cache : bool, default True
        Read / write the on-disk cache (``reference/independent_<key>.vtu``, keyed by
        :func:`pvcmf.truth.grid_hash` of the planned grid and the options).
    cache_dir : path, optional
        Cache folder.
    mesher : {'lattice', 'conforming', 'graded'}, default 'lattice'
        ``'lattice'``: :func:`soft_tissue_mesh` (the lattice-and-snap mesher);
        ``'conforming'``: :func:`pvcmf.truth.conform.conforming_mesh` (gmsh, conforming to
        the exact surfaces: the same meshed volume at every size; ``n_tets`` sets its
        surface spacing); ``'graded'``: :func:`pvcmf.truth.graded.graded_mesh` (as
        ``'conforming'``, ``face_mm`` fine in the ball of the moved bones, the
        conforming spacing of ``n_tets`` elsewhere). Same boundary model and materials on
        all.
    materials : {'cells', 'field'}, default 'cells'
        ``'cells'``: each tetrahedron mixes fat and muscle by its sampled muscle fraction;
        ``'field'``: the mixture is a field of the position (:func:`material_field`)
        evaluated at the quadrature points: the same material on every mesh.
    face_mm : float or dict, default 3.0
        With ``mesher='graded'``: the size (mm) of the surface sampling in the face, or a
        size per moved segment (``{"maxilla": 3.2, "mandible": 4.0}``: the smallest of the
        segments the plan moves, :func:`pvcmf.truth.graded.face_size`).
    face_margin_mm : float, default 0.0
        With ``mesher='graded'``: the fine ball also holds the soft tissue within this
        distance (mm) of the moved bones (:func:`pvcmf.truth.graded.face_ball`).
    blend_mm : float, default :data:`BLEND_MM`
        Width (mm, Gaussian sigma) over which the tied bone surface's data blends from one
        segment's move to the next across an osteotomy (a modelling choice of the truth:
        ``benchmarks/study.py --blend-mm`` measures how far the skin depends on it).
    reuse_factor : bool, default False
        Passed to :func:`pvcmf.truth.solver.solve_reference` (conjugate gradients
        preconditioned by the last factorisation between refactorisations; the same
        converged answer, fewer factorisations on large meshes).
    progress_bar : bool, default False
        Show the solver's load steps.

    Returns
    -------
    pyvista.UnstructuredGrid
        The planned grid (pre-operative frame) with point array ``arrays.DISPLACEMENT``.

    Examples
    --------
    >>> import pvcmf                                                            # doctest: +SKIP
    >>> from pvcmf.truth.independent import independent_truth_grid              # doctest: +SKIP
    >>> g = independent_truth_grid(pvcmf.datasets.phantom(1, spacing=2.0))      # doctest: +SKIP
    """
    grid, field, params = truth_problem(case, n_tets=n_tets, order=order, steps=steps,
                                        face_fraction=face_fraction, mesher=mesher,
                                        materials=materials, face_mm=face_mm,
                                        blend_mm=blend_mm, face_margin_mm=face_margin_mm)
    key = grid_hash(grid, params)
    path = cache_root("reference", cache_dir) / f"independent_{key}.vtu"
    return cached(path, lambda: solve_reference(grid, order=order, steps=steps,
                                                reuse_factor=reuse_factor, materials=field,
                                                progress_bar=progress_bar), cache=cache)


def truth_problem(case, *, n_tets=30_000, order=2, steps=4, face_fraction=0.5,
                  mesher="lattice", materials="cells", face_mm=3.0, blend_mm=BLEND_MM,
                  face_margin_mm=0.0):
    """What :func:`independent_truth_grid` solves, unsolved: the planned grid with its
    materials, the material field (None with ``materials='cells'``) and the solver
    parameters of the cache key (the options are :func:`independent_truth_grid`'s).

    Examples
    --------
    >>> import pvcmf                                                            # doctest: +SKIP
    >>> from pvcmf.truth.independent import truth_problem                       # doctest: +SKIP
    >>> grid, field, _ = truth_problem(pvcmf.datasets.phantom(1, spacing=3.0))  # doctest: +SKIP
    """
    if materials not in ("cells", "field"):
        raise ValueError(f"materials must be 'cells' or 'field', got {materials!r}")
    try:
        blend = float(blend_mm) if not isinstance(blend_mm, bool) else np.nan
    except (TypeError, ValueError):
        blend = np.nan
    if not (np.isfinite(blend) and blend > 0):
        raise ValueError(f"blend_mm must be a positive finite width in mm, got {blend_mm!r}")
    if face_margin_mm and mesher != "graded":
        raise ValueError(f"face_margin_mm applies to mesher 'graded' only (0 with mesher "
                         f"{mesher!r}), got {face_margin_mm!r}")
    if mesher == "lattice":
        grid = soft_tissue_mesh(case, n_tets=n_tets, face_fraction=face_fraction)
    elif mesher == "conforming":
        grid = conforming_mesh(case, n_tets=n_tets, face_fraction=face_fraction)
    elif mesher == "graded":
        grid = graded_mesh(case, n_tets=n_tets, face_mm=face_size(face_mm, case.plan),
                           face_fraction=face_fraction, face_margin_mm=face_margin_mm)
    else:
        raise ValueError(f"mesher must be 'lattice', 'conforming' or 'graded', got {mesher!r}")
    grid = _boundary_conditions(case, grid, blend=blend)
    # Table I; the fibre direction is immaterial to the truth's law for Table I (its fibre
    # term vanishes where the muscle is softer along the fibre than across)
    grid = filters.assign_materials(grid, default_fiber=(0.0, 0.0, 1.0))
    field, params = None, f"independent|order={order}|steps={steps}"
    if materials == "field":
        field = material_field(case, grid)
        params += "|materials=" + hashlib.sha256(
            np.ascontiguousarray(field["fraction"]).tobytes()
            + np.asarray(field["origin"] + field["end"]).tobytes()).hexdigest()[:16]
    return grid, field, params
