"""Virtual post-operative CT: the pre-operative CT warped by a post-operative truth.

No public pair of pre/post-operative scans exists, so pvcmf makes the post-operative scan
of its virtual patients (:func:`postop_ct`) and then judges predictions by the path a real
scan would take (:mod:`pvcmf.study.from_ct`).

:func:`postop_ct` is a *backward* warp: each output voxel ``x`` takes the pre-operative
value at the point ``X`` with ``X + u(X) = x``, found by probing the *displaced* truth grid
(``points + u``) with ``u`` (VTK's ``vtkProbeFilter`` through
:meth:`pyvista.DataSet.sample`; exact for linear tetrahedra). Voxels of a moved bone
segment take ``M^-1 x`` (segment masks looked up with
:func:`scipy.ndimage.map_coordinates`, nearest neighbour); space the soft tissue or a bone
left behind becomes air or soft tissue; everything else stays put. Values are resampled
trilinearly, Gaussian noise is added and the patient is given a rigid pose.
:func:`reference_grid` is the volumetric truth it warps with (:func:`pvcmf.truth.truth_grid`).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.osteotomy import cut_bones, segment_transforms, voxel_points
from ..filters.surface_mapping import DEFAULT_BAND, Transfer
from .grid import truth_grid

log = logging.getLogger("pvcmf.postop")

__all__ = ["AIR_HU", "GAP_HU", "postop_ct", "random_pose", "reference_grid"]

#: HU of air (outside the body, and where the face moved away)
AIR_HU = -1000.0
#: HU given to the space a moved bone segment left behind (fresh soft tissue / blood)
GAP_HU = 40.0


def random_pose(rng, max_rotation=5.0, max_translation=10.0, centre=(0.0, 0.0, 0.0)):
    """Random rigid 4x4 pose: a rotation about ``centre`` and a translation.

    Parameters
    ----------
    rng : numpy.random.Generator or int
        Random generator or seed.
    max_rotation : float, default 5.0
        Rotation angle drawn uniformly in ``[-max_rotation, max_rotation]`` degrees about a
        uniformly random axis.
    max_translation : float, default 10.0
        Each translation component drawn uniformly in ``[-max_translation, max_translation]`` mm.
    centre : sequence of 3 floats, default origin
        Centre of the rotation (mm).

    Returns
    -------
    numpy.ndarray
        ``(4, 4)`` rigid transform.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.truth import random_pose
    >>> m = random_pose(0)
    >>> bool(np.allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3)))
    True
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(rng)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(-max_rotation, max_rotation))
    rot = Rotation.from_rotvec(axis * angle).as_matrix()
    centre = np.asarray(centre, dtype=float)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = centre - rot @ centre + rng.uniform(-max_translation, max_translation, 3)
    return out


def _check_case(case, name="case"):
    for attr in ("ct", "plan"):
        if not hasattr(case, attr):
            raise TypeError(
                f"{name} must be a pvcmf.datasets.Case (with .ct and .plan), got "
                f"{type(case).__name__} without .{attr}"
            )
    if not isinstance(case.ct, pv.ImageData):
        raise TypeError(f"{name}.ct must be a pyvista.ImageData, got {type(case.ct).__name__}")
    arrays.require_array(case.ct, arrays.CT, "point", dtype="f", ncomp=1, producer="read_ct")


def _pose_matrix(pose, seed, centre):
    if pose is None:
        return np.eye(4)
    if isinstance(pose, str):
        if pose != "random":
            raise ValueError(f"pose must be None, 'random' or a 4x4 matrix, got {pose!r}")
        return random_pose(seed, centre=centre)
    matrix = np.asarray(pose, dtype=float)
    if matrix.shape != (4, 4):
        raise ValueError(f"pose must be None, 'random' or a 4x4 matrix, got shape {matrix.shape}")
    rot = matrix[:3, :3]
    if not (np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) and np.isclose(np.linalg.det(rot), 1)
            and np.allclose(matrix[3], (0, 0, 0, 1))):
        raise ValueError("pose must be a rigid transform (orthonormal rotation, det +1, "
                         "last row 0 0 0 1)")
    return matrix


def _probe(points, grid, values):
    """Interpolate point array ``values`` of ``grid`` at ``points``; (values, inside mask).

    VTK's probe filter (linear inside the tetrahedra); only points in the grid's bounding
    box are probed.
    """
    lo, hi = np.asarray(grid.bounds).reshape(3, 2).T
    box = np.all((points >= lo - 1e-9) & (points <= hi + 1e-9), axis=1)
    out = np.zeros((len(points), values.shape[1]))
    inside = np.zeros(len(points), dtype=bool)
    if not box.any():
        return out, inside
    src = pv.UnstructuredGrid(grid.cells, grid.celltypes, grid.points)
    src.point_data["v"] = values
    probe = pv.PolyData(np.ascontiguousarray(points[box])).sample(src, progress_bar=False)
    valid = np.asarray(probe[arrays.VALID_POINT_MASK], dtype=bool)
    ids = np.flatnonzero(box)
    inside[ids] = valid
    out[ids] = np.asarray(probe["v"]).reshape(-1, values.shape[1])
    out[~inside] = 0.0
    return out, inside


def _sample(image, values, points, order, cval):
    """Values of a point array of ``image`` at ``points`` (map_coordinates, voxel index)."""
    from scipy import ndimage

    dims = tuple(int(d) for d in image.dimensions)
    vol = np.asarray(values).reshape(dims, order="F")
    idx = ((points - np.asarray(image.origin)) / np.asarray(image.spacing)).T
    return ndimage.map_coordinates(vol, idx, order=order, mode="constant", cval=cval,
                                   prefilter=False)


def postop_ct(case, displacement_grid=None, *, noise_hu=18.0, pose=None, seed=0, spacing=None,
              labels=None, extrapolate=DEFAULT_BAND, extension="transfer", progress_bar=False):
    """Virtual post-operative CT: the pre-operative CT warped by a post-operative truth.

    For each output voxel ``y`` (scanner frame) the patient point is ``x = pose^-1 y`` and
    its pre-operative origin ``X``:

    1. on a moved bone segment of the plan (``M`` from
       :func:`pvcmf.filters.osteotomy.segment_transforms`): ``X = M^-1 x`` when the
       pre-operative ``bone`` label there is that segment; on bone (or teeth) that the plan
       does not move: ``X = x``;
    2. inside the displaced soft-tissue grid: ``X = x - u``, with ``u`` probed on the
       displaced grid (``points + displacement``): backward warping, exact for linear
       tetrahedra;
    3. outside the displaced grid (skin a coarse mesh does not reach), ``extension``
       ``'transfer'``: ``X + T(X) u = x``, ``T`` the transfer operator the prediction's
       skin is moved by (:class:`pvcmf.filters.surface_mapping.Transfer` with
       ``band=extrapolate``: exact for affine fields up to ``extrapolate`` mm from the
       grid, fading to 0 at twice that), solved by fixed-point iteration; ``'nearest'``:
       ``X = x - w u_n``, ``u_n`` the displacement of the nearest displaced node (as
       :func:`pvcmf.truth.postop_skin` moves skin points outside its mesh), ``w`` 1 up
       to ``extrapolate`` mm and fading to 0 at twice that;
    4. elsewhere ``X = x`` (stays put). Where ``X`` is material that moved elsewhere
       (inside the undisplaced grid: e.g. the lip retreated; on a moved segment: the bone
       left) the voxel is air (``AIR_HU``) or soft tissue (``GAP_HU``).

    The value is the pre-operative CT at ``X`` (trilinear; air outside the image), plus
    Gaussian noise.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Pre-operative patient: ``ct`` (HU), ``plan`` and, unless ``labels`` is given,
        ``truth`` (its ``bone`` array names the segments the plan moves).
    displacement_grid : pyvista.UnstructuredGrid, optional
        Tetrahedral soft-tissue grid in the pre-operative patient frame with point array
        ``arrays.DISPLACEMENT`` (mm): the truth (e.g. :func:`reference_grid`). ``None``:
        the soft tissue does not move (only the bones do).
    noise_hu : float, default 18.0
        Standard deviation of the added Gaussian noise (HU); 0 for none.
    pose : None, 'random' or (4, 4) array_like, default None
        Rigid transform from the post-operative patient frame to the scanner frame. 'random'
        draws one (:func:`random_pose` from ``seed``: up to 5 degrees about the image centre,
        10 mm).
    seed : int, default 0
        Seed of the noise and the random pose.
    spacing : float, optional
        Isotropic voxel size (mm) of the output over the pre-operative image's bounds;
        default the pre-operative grid.
    labels : pyvista.ImageData, optional
        Label image with the ``bone`` array on the CT's grid (default ``case.truth``, cut
        by the plan with :func:`pvcmf.filters.cut_bones`).
    extrapolate : float, default 4.0
        Reach (mm) of the grid's displacement outside the grid (step 3; the transfer's
        ``band``, default its smallest, ``DEFAULT_BAND``); 0 for none.
    extension : {'transfer', 'nearest'}, default 'transfer'
        How the displacement is extended outside the grid (step 3): ``'transfer'`` as the
        predicted skin (a CT warped by a model's own displacement then matches that
        model's skin), ``'nearest'`` as :func:`pvcmf.truth.postop_skin`. ``'transfer'``
        needs a grid of tetrahedra.
    progress_bar : bool, default False
        Accepted for symmetry with the other long steps; the warp is one vectorised pass
        and logs its summary at INFO.

    Returns
    -------
    tuple
        ``(ct, pose)``: ``pyvista.ImageData`` with point array ``arrays.CT`` (float32, HU)
        and the 4x4 pose applied (numpy array).

    Raises
    ------
    TypeError
        If ``case`` has no image CT or ``displacement_grid`` is not an UnstructuredGrid.
    ValueError
        If an array is missing, the pose is not rigid, or the spacing is not positive.

    Examples
    --------
    >>> import numpy as np, pvcmf
    >>> from pvcmf import arrays
    >>> from pvcmf.truth import postop_ct
    >>> case = pvcmf.datasets.phantom(1, spacing=4.0)
    >>> ct, pose = postop_ct(case, noise_hu=0.0)  # bones move, soft tissue does not
    >>> ct[arrays.CT].dtype, pose.shape
    (dtype('float32'), (4, 4))
    """
    out, labels, bone, disp = _postop_inputs(case, displacement_grid, labels, noise_hu,
                                             extrapolate, spacing)
    if extension not in ("transfer", "nearest"):
        raise ValueError(f"extension must be 'transfer' or 'nearest', got {extension!r}")
    pre = case.ct
    matrix = _pose_matrix(pose, seed, np.asarray(pre.center))
    inv_pose = np.linalg.inv(matrix)
    y = voxel_points(out, np.arange(out.n_points))  # patient point of every output voxel
    x = y @ inv_pose[:3, :3].T + inv_pose[:3, 3]
    src, done, fill, n_moved = _warp_bones(x, labels, bone, case.plan)
    if displacement_grid is not None and displacement_grid.n_points:
        _warp_soft_tissue(x, src, done, fill, displacement_grid, disp, extrapolate,
                          extension)
    values = _sample(pre, np.asarray(pre[arrays.CT]).astype(np.float64), src, 1, AIR_HU)
    values = np.where(np.isnan(fill), values, fill).astype(np.float32)
    if noise_hu > 0:
        rng = np.random.default_rng(seed)
        values += rng.standard_normal(values.shape, dtype=np.float32) * np.float32(noise_hu)
    out.point_data[arrays.CT] = values
    log.info("postop_ct: %s voxels at %.3g mm, %d bone segment(s) moved, noise %.3g HU",
             tuple(out.dimensions), float(out.spacing[0]), n_moved, noise_hu)
    return out, matrix


def _postop_inputs(case, displacement_grid, labels, noise_hu, extrapolate, spacing):
    """Check :func:`postop_ct`'s inputs; (output image, labels, bone ids, displacement)."""
    _check_case(case)
    pre = case.ct
    if labels is None:
        if not isinstance(getattr(case, "truth", None), pv.ImageData):
            raise TypeError("case has no truth label image: pass labels= (an ImageData with "
                            f"the {arrays.BONE!r} array on the CT grid)")
        labels = cut_bones(case.truth, case.plan)
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    if tuple(labels.dimensions) != tuple(pre.dimensions) or not np.allclose(
            labels.spacing, pre.spacing) or not np.allclose(labels.origin, pre.origin):
        raise ValueError(
            f"labels must lie on the CT's grid (dimensions {tuple(pre.dimensions)}, spacing "
            f"{tuple(pre.spacing)}), got {tuple(labels.dimensions)}, {tuple(labels.spacing)}")
    bone = np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu", ncomp=1,
                                           producer="segment / cut_bones"))
    disp = None
    if displacement_grid is not None:
        if not isinstance(displacement_grid, pv.UnstructuredGrid):
            raise TypeError("displacement_grid must be a pyvista.UnstructuredGrid, got "
                            f"{type(displacement_grid).__name__}")
        disp = np.asarray(arrays.require_array(
            displacement_grid, arrays.DISPLACEMENT, "point", dtype="f", ncomp=3,
            producer="reference_grid / mtm.solve"), dtype=float)
    if noise_hu < 0:
        raise ValueError(f"noise_hu must be >= 0, got {noise_hu}")
    if extrapolate < 0:
        raise ValueError(f"extrapolate must be >= 0 mm, got {extrapolate}")
    if spacing is None:
        out = pv.ImageData(dimensions=pre.dimensions, spacing=pre.spacing, origin=pre.origin)
    else:
        if not float(spacing) > 0:
            raise ValueError(f"spacing must be a positive voxel size in mm, got {spacing}")
        lo, hi = np.asarray(pre.bounds).reshape(3, 2).T
        dims = np.floor((hi - lo) / float(spacing) + 1e-9).astype(int) + 1
        out = pv.ImageData(dimensions=dims, spacing=(float(spacing),) * 3, origin=lo)
    return out, labels, bone, disp


def _warp_bones(x, labels, bone, plan):
    """Steps 1 and 4 for bone: (source points, done mask, fill values, moved segments)."""
    src = x.copy()
    done = np.zeros(len(x), dtype=bool)
    fill = np.full(len(x), np.nan)
    # moved bone segments: rigid, nearest-neighbour segment lookup
    transforms = segment_transforms(labels, plan)
    for seg, m in transforms.items():
        inv = np.linalg.inv(m)
        back = x @ inv[:3, :3].T + inv[:3, 3]
        on = _sample(labels, (bone == seg).astype(np.uint8), back, 0, 0).astype(bool) & ~done
        src[on] = back[on]
        done |= on
        log.debug("postop_ct: segment %d covers %d voxels", seg, int(on.sum()))
    # space a moved segment left behind (not re-covered): soft tissue
    moved_ids = np.fromiter(transforms, dtype=np.int64)
    bone_x = _sample(labels, bone, x, 0, 0)
    left = np.isin(bone_x, moved_ids) & ~done
    fill[left] = GAP_HU
    # bone that does not move stays put (no soft-tissue warp or extrapolation into it)
    done |= (bone_x > 0) & ~np.isin(bone_x, moved_ids)
    return src, done, fill, len(transforms)


def _warp_soft_tissue(x, src, done, fill, displacement_grid, disp, extrapolate, extension):
    """Steps 2-4 for soft tissue, in place on ``src``, ``done`` and ``fill``."""
    # 2. backward warp through the displaced grid
    displaced = pv.UnstructuredGrid(displacement_grid.cells, displacement_grid.celltypes,
                                    np.asarray(displacement_grid.points, float) + disp)
    todo = np.flatnonzero(~done)
    u, inside = _probe(x[todo], displaced, disp)
    hit = todo[inside]
    src[hit] = x[hit] - u[inside]
    done[hit] = True
    fill[hit] = np.nan
    # 3. just outside the grid (tissue the mesh does not reach)
    rest = np.flatnonzero(~done & np.isnan(fill))
    if extrapolate > 0 and rest.size:
        src[rest] = _extend(x[rest], displacement_grid, displaced, disp, extrapolate, extension)
    # 4. material the grid moved away (the source lies in the undisplaced grid): air
    _, was = _probe(src[rest], displacement_grid, np.zeros((displacement_grid.n_points, 1)))
    fill[rest[was]] = AIR_HU
    log.info("postop_ct: %d voxels warped by the soft tissue, %d vacated", hit.size,
             int(was.sum()))


#: fixed-point iterations of the inverse of the extension outside the grid, and the step
#: (mm) under which a point counts as converged
EXTEND_ITERATIONS = 12
EXTEND_TOLERANCE = 1e-3


def _extend(x, grid, displaced, disp, extrapolate, extension):
    """Step 3: the source ``X`` of points ``x`` outside the displaced grid.

    ``'nearest'``: ``X = x - w u_n`` (nearest displaced node, ``w`` 1 up to ``extrapolate``
    mm, 0 at twice that). ``'transfer'``: ``X + T(X) u = x`` with ``T`` the prediction's
    transfer operator (:class:`pvcmf.filters.surface_mapping.Transfer` of the grid at rest,
    ``band=extrapolate``), solved by the fixed-point iteration ``X <- x - T(X) u`` from the
    nearest-node guess (a contraction where the displacement gradient is below 1).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(grid.points, dtype=float)
    tree = cKDTree(displaced.points)
    dist, idx = tree.query(x, distance_upper_bound=2 * extrapolate, workers=-1)
    near = np.isfinite(dist)
    guess = x.copy()
    w = np.clip((2 * extrapolate - dist[near]) / extrapolate, 0.0, 1.0)
    guess[near] -= w[:, None] * disp[idx[near]]
    if extension == "nearest":
        return guess
    # points a source within the transfer's reach (2 extrapolate) can move to
    cells = grid.cells_dict
    cells = np.asarray(cells.get(pv.CellType.TETRA, cells.get(int(pv.CellType.TETRA), [[0] * 4])))
    h = float(np.linalg.norm(pts[cells[:, 1:]] - pts[cells[:, :1]], axis=2).max(initial=0.0))
    bound = 2 * extrapolate + h + 2 * float(np.linalg.norm(disp, axis=1).max(initial=0.0))
    cand = np.flatnonzero(tree.query(x, distance_upper_bound=bound, workers=-1)[0] <= bound)
    src, target = guess[cand], x[cand]
    active = np.arange(cand.size)
    for _ in range(EXTEND_ITERATIONS):
        if not active.size:
            break
        new = target[active] - Transfer(grid, src[active], band=extrapolate)(disp)
        step = np.linalg.norm(new - src[active], axis=1)
        src[active] = new
        active = active[step > EXTEND_TOLERANCE]
    if active.size:
        log.warning("postop_ct: %d of %d voxels outside the grid did not converge to their "
                    "source within %.3g mm", active.size, cand.size, EXTEND_TOLERANCE)
    guess[cand] = src
    return guess


def reference_grid(case, *, n_tets=16_000, order=2, steps=4, face_fraction=0.5, cache=True,
                   cache_dir=None, progress_bar=False):
    """The volumetric post-operative truth of a virtual patient (solved tetrahedral grid).

    :func:`pvcmf.truth.truth_grid`: the same fine mesh, materials, boundary conditions
    and model as :func:`pvcmf.truth.postop_skin` (true labels cut by the plan,
    conforming mesh of the anterior face, fibres, Table I, ``apply_plan`` with unmoved bone
    fixed), solved by :func:`pvcmf.truth.solve_reference` (NGSolve, ``pip install
    pvcmf[reference]``) and returned as the grid with point array ``arrays.DISPLACEMENT``
    for :func:`postop_ct`. Cached on disk by the hash of the solver's input grid (the
    cache ``postop_skin`` reads too): a cached truth is read without re-solving, and
    without NGSolve.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient (``truth``, ``plan``).
    n_tets, order, steps, face_fraction, cache, cache_dir :
        See :func:`pvcmf.truth.truth_grid`.
    progress_bar : bool, default False
        Show the meshing and solver steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        Solved soft-tissue grid (pre-operative frame) with ``arrays.DISPLACEMENT``.

    Examples
    --------
    >>> import pvcmf                                                   # doctest: +SKIP
    >>> grid = pvcmf.truth.reference_grid(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    if not isinstance(getattr(case, "truth", None), pv.ImageData):
        raise TypeError(f"case must be a virtual patient with a truth label image, got "
                        f"{type(case).__name__}")
    return truth_grid(case, n_tets=n_tets, order=order, steps=steps,
                      face_fraction=face_fraction, cache=cache, cache_dir=cache_dir,
                      progress_bar=progress_bar)
