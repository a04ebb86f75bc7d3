"""Virtual post-operative CT, and validation from a post-operative CT.

No public pair of pre/post-operative scans exists, so pvcmf makes the post-operative
scan of its virtual patients and then runs the path a real scan would take
(paper 000 sec. V): segment -> skin -> ICP on the unchanged upper face -> signed
distances -> statistics.

* :func:`postop_ct` warps the pre-operative CT by a post-operative truth: a tetrahedral
  soft-tissue grid with a point array ``displacement`` (e.g. :func:`reference_grid`, or
  any solved grid) and the plan's rigid bone moves. It is a *backward* warp: each output
  voxel ``x`` takes the pre-operative value at the point ``X`` with ``X + u(X) = x``,
  found by probing the *displaced* grid (``points + u``) with ``u`` (VTK's
  ``vtkProbeFilter`` through :meth:`pyvista.DataSet.sample`; exact for linear
  tetrahedra, whose map is affine in each cell). Voxels of a moved bone segment take
  ``M^-1 x`` (the segment masks looked up with :func:`scipy.ndimage.map_coordinates`,
  nearest neighbour); space the soft tissue or a bone left behind becomes air or
  soft tissue; everything else stays put. The values are resampled trilinearly
  (:func:`scipy.ndimage.map_coordinates`, order 1), Gaussian noise is added, and the
  whole patient is given a rigid pose (the patient lies differently in the scanner).
* :func:`validate_from_ct` segments the post-operative CT (:func:`pvcmf.filters.segment`),
  extracts its skin (:func:`pvcmf.filters.extract_skin`), registers it onto the
  pre-operative skin with point-to-plane ICP restricted to the upper face
  (:func:`pvcmf.filters.register`), measures the predicted skin against it
  (:func:`pvcmf.filters.distance_to`) and tabulates the errors
  (:func:`pvcmf.validation.error_statistics`).
* :func:`reference_grid` is the volumetric truth: the same fine mesh and
  large-deformation model as :func:`pvcmf.reference.postop_skin`, returned as the solved
  tetrahedral grid (:func:`pvcmf.reference.truth_grid`, NGSolve; optional extra; cached
  on disk).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from . import arrays

log = logging.getLogger(__name__)

__all__ = ["postop_ct", "random_pose", "reference_grid", "refine_skin", "skin_from_ct",
           "upper_face_region", "validate_from_ct"]

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
    >>> from pvcmf.postop import random_pose
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
    valid = np.asarray(probe["vtkValidPointMask"], dtype=bool)
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
              labels=None, extrapolate=5.0, progress_bar=False):
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
    3. outside the displaced grid but within ``2 * extrapolate`` mm of it (skin a coarse
       mesh does not reach): ``X = x - w u_n``, ``u_n`` the displacement of the nearest
       displaced node (as :func:`pvcmf.reference.postop_skin` moves skin points outside
       its mesh), ``w`` 1 up to ``extrapolate`` mm and fading to 0 at twice that;
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
    extrapolate : float, default 5.0
        Reach (mm) of the grid's displacement outside the grid (step 3); 0 for none.
    progress_bar : bool, default False
        Log the steps at INFO level.

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
    >>> from pvcmf.postop import postop_ct
    >>> case = pvcmf.datasets.phantom(1, spacing=4.0)
    >>> ct, pose = postop_ct(case, noise_hu=0.0)  # bones move, soft tissue does not
    >>> ct[arrays.CT].dtype, pose.shape
    (dtype('float32'), (4, 4))
    """
    from scipy.spatial import cKDTree

    from .filters.osteotomy import cut_bones, segment_transforms

    _check_case(case)
    pre = case.ct
    hu = np.asarray(pre[arrays.CT])
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
    matrix = _pose_matrix(pose, seed, np.asarray(pre.center))

    # patient (post-operative) point of every output voxel
    from .filters.osteotomy import voxel_points

    inv_pose = np.linalg.inv(matrix)
    y = voxel_points(out, np.arange(out.n_points))
    x = y @ inv_pose[:3, :3].T + inv_pose[:3, 3]
    src = x.copy()
    done = np.zeros(len(x), dtype=bool)
    fill = np.full(len(x), np.nan)

    # 1. moved bone segments: rigid, nearest-neighbour segment lookup
    transforms = segment_transforms(labels, case.plan)
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

    # 2. soft tissue: backward warp through the displaced grid
    if displacement_grid is not None and displacement_grid.n_points:
        displaced = pv.UnstructuredGrid(displacement_grid.cells, displacement_grid.celltypes,
                                        np.asarray(displacement_grid.points, float) + disp)
        todo = np.flatnonzero(~done)
        u, inside = _probe(x[todo], displaced, disp)
        hit = todo[inside]
        src[hit] = x[hit] - u[inside]
        done[hit] = True
        fill[hit] = np.nan
        # 3. just outside the grid (tissue the mesh does not reach): the displacement of
        # the nearest displaced node, fading from 1 at `extrapolate` mm to 0 at twice that
        rest = np.flatnonzero(~done & np.isnan(fill))
        if extrapolate > 0:
            dist, idx = cKDTree(displaced.points).query(x[rest], distance_upper_bound=2 * extrapolate,
                                                         workers=-1)
            near = np.isfinite(dist)
            w = np.clip((2 * extrapolate - dist[near]) / extrapolate, 0.0, 1.0)
            src[rest[near]] = x[rest[near]] - w[:, None] * disp[idx[near]]
        # 4. material the grid moved away (the source lies in the undisplaced grid): air
        _, was = _probe(src[rest], displacement_grid, np.zeros((displacement_grid.n_points, 1)))
        fill[rest[was]] = AIR_HU
        log.info("postop_ct: %d voxels warped by the soft tissue, %d vacated", hit.size,
                 int(was.sum()))
    values = _sample(pre, hu.astype(np.float64), src, 1, AIR_HU)
    values = np.where(np.isnan(fill), values, fill).astype(np.float32)
    if noise_hu > 0:
        rng = np.random.default_rng(seed)
        values += rng.standard_normal(values.shape, dtype=np.float32) * np.float32(noise_hu)
    out.point_data[arrays.CT] = values
    log.info("postop_ct: %s voxels at %.3g mm, %d bone segment(s) moved, noise %.3g HU",
             tuple(out.dimensions), float(out.spacing[0]), len(transforms), noise_hu)
    return out, matrix


def upper_face_region(landmarks=None, *, below_nasion=15.0):
    """Region of the pre-operative skin that jaw surgery does not change, for ICP.

    The anterior skin above ``below_nasion`` mm under the soft-tissue nasion: forehead,
    orbits and nose bridge (paper 000 registers on the unchanged region). Without
    landmarks, the anterior skin above 62 % of the skin's height.

    Parameters
    ----------
    landmarks : dict, optional
        Patient landmarks (``soft_tissue_nasion`` or ``nasion``, mm).
    below_nasion : float, default 15.0
        How far below the nasion the region reaches (mm).

    Returns
    -------
    callable
        ``f(points) -> bool mask`` for :func:`pvcmf.filters.register`'s ``region``.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.postop import upper_face_region
    >>> f = upper_face_region({"nasion": (0.0, 80.0, 30.0)})
    >>> f(np.array([[0.0, 90.0, 40.0], [0.0, 90.0, -20.0]])).tolist()
    [True, False]
    """
    lm = dict(landmarks or {})
    nasion = lm.get("soft_tissue_nasion", lm.get("nasion"))

    def region(points):
        p = np.asarray(points, dtype=float)
        if nasion is not None:
            z0 = float(nasion[2]) - below_nasion
        else:
            z0 = p[:, 2].min() + 0.62 * np.ptp(p[:, 2])
        return (p[:, 2] >= z0) & (p[:, 1] >= np.median(p[:, 1]))

    return region


def refine_skin(skin, ct, *, level=-500.0, reach=1.5, step=0.125):
    """Move each skin point along its normal onto the CT's ``level`` iso-surface.

    A skin contoured from a label image sits on the voxel staircase (smoothed); the CT's
    air/skin edge locates it to a fraction of a voxel. Each point's CT profile along its
    normal, over ``[-reach, reach]`` voxels, is sampled trilinearly
    (:func:`scipy.ndimage.map_coordinates`, all points at once) and the point moves to the
    crossing of ``level`` (from inside above to outside below) nearest to it, by linear
    interpolation between samples; a point whose profile has no crossing stays put.

    Parameters
    ----------
    skin : pyvista.PolyData
        Skin with outward point normals (``'Normals'``, as :func:`pvcmf.filters.extract_skin`
        gives; computed otherwise).
    ct : pyvista.ImageData
        CT with point array ``arrays.CT`` (HU) the skin was extracted from.
    level : float, default -500.0
        HU of the air/skin edge (half way between air and soft tissue).
    reach : float, default 1.5
        Search distance along the normal, in voxels.
    step : float, default 0.125
        Sampling step along the normal, in voxels.

    Returns
    -------
    pyvista.PolyData
        Copy of ``skin`` with moved points (normals kept).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.postop import refine_skin
    >>> img = pv.ImageData(dimensions=(40, 40, 40), origin=(-20, -20, -20))
    >>> r = np.linalg.norm(img.points, axis=1)
    >>> img[arrays.CT] = np.clip((12.3 - r) * 500 - 500, -1000, 0).astype(np.float32)
    >>> out = refine_skin(pv.Sphere(radius=12.0), img)
    >>> bool(abs(np.linalg.norm(out.points, axis=1).mean() - 12.3) < 0.03)
    True
    """
    hu = np.asarray(arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                         producer="read_ct / postop_ct"), dtype=np.float64)
    out = skin.copy()
    if "Normals" in skin.point_data:
        normals = np.asarray(skin.point_data["Normals"], dtype=float)
    else:
        normals = np.asarray(skin.compute_normals(cell_normals=False,
                                                  split_vertices=False)["Normals"], float)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    h = float(np.min(ct.spacing))
    t = np.arange(-reach, reach + step / 2, step) * h  # (m,) offsets along the normal, mm
    p = np.asarray(skin.points, dtype=float)
    samples = p[:, None, :] + t[None, :, None] * normals[:, None, :]
    prof = _sample(ct, hu, samples.reshape(-1, 3), 1, AIR_HU).reshape(len(p), len(t)) - level
    # crossings inside -> outside: prof[k] >= 0 > prof[k + 1]
    cross = (prof[:, :-1] >= 0) & (prof[:, 1:] < 0)
    mid = (t[:-1] + t[1:]) / 2
    cost = np.where(cross, np.abs(mid)[None, :], np.inf)
    k = np.argmin(cost, axis=1)
    has = np.isfinite(cost[np.arange(len(p)), k])
    a, b = prof[np.arange(len(p)), k], prof[np.arange(len(p)), k + 1]
    frac = np.where(has, a / np.where(a - b != 0, a - b, 1.0), 0.0)
    shift = np.where(has, t[k] + frac * step * h, 0.0)
    out.points = p + shift[:, None] * normals
    log.debug("refine_skin: %d of %d points moved, median |shift| %.3f mm", int(has.sum()),
              len(p), float(np.median(np.abs(shift[has]))) if has.any() else 0.0)
    return out


def skin_from_ct(ct, *, refine=True, segment_options=None, skin_options=None, name="ct"):
    """Skin surface of a CT as for a real scan: segment -> extract_skin -> refine.

    Parameters
    ----------
    ct : pyvista.ImageData
        CT with point array ``arrays.CT`` (HU).
    refine : bool, default True
        Move the points onto the CT's air/skin edge (:func:`refine_skin`).
    segment_options, skin_options : dict, optional
        Keyword arguments of :func:`pvcmf.filters.segment` and
        :func:`pvcmf.filters.extract_skin`.
    name : str, default 'ct'
        Name of the CT in error messages.

    Returns
    -------
    pyvista.PolyData
        Outward skin with point normals.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.postop import skin_from_ct
    >>> skin_from_ct(pvcmf.datasets.phantom(1, spacing=4.0).ct).n_points > 1000
    True
    """
    from . import filters

    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"{name} must be a pyvista.ImageData CT, got {type(ct).__name__}")
    arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1, producer="read_ct / postop_ct")
    labels = filters.segment(ct, **(segment_options or {}))
    skin = filters.extract_skin(labels, **(skin_options or {}))
    if skin.n_points == 0:
        raise ValueError(f"{name} has no skin: segmentation found no head (all air?)")
    return refine_skin(skin, ct) if refine else skin


def validate_from_ct(pre_case, postop_ct, predicted_skin, *, region=None, pre_skin=None,
                     landmarks=None, max_distance=10.0, segment_options=None,
                     skin_options=None, icp_options=None, regions=True, refine=True,
                     progress_bar=False):
    """Judge a predicted skin against a post-operative CT, as for a real scan.

    segment (:func:`pvcmf.filters.segment`) -> skin (:func:`pvcmf.filters.extract_skin`)
    of the post-operative CT -> rigid point-to-plane ICP of that skin onto the
    pre-operative skin on ``region`` (:func:`pvcmf.filters.register`) -> signed distance
    of the prediction to it (:func:`pvcmf.filters.distance_to`, + anterior) -> statistics
    (:func:`pvcmf.validation.error_statistics`, face regions from the landmarks).

    Parameters
    ----------
    pre_case : pvcmf.datasets.Case
        Pre-operative patient (``ct``, ``landmarks``): its CT gives the pre-operative skin
        (unless ``pre_skin`` is given), i.e. the frame of the prediction.
    postop_ct : pyvista.ImageData
        Post-operative CT with point array ``arrays.CT`` (e.g. :func:`postop_ct`), in any pose.
    predicted_skin : pyvista.DataSet
        Predicted post-operative skin in the pre-operative patient frame.
    region : None, mask, bounds or callable, optional
        ICP region on the pre-operative skin (see :func:`pvcmf.filters.register`);
        default :func:`upper_face_region` of the landmarks.
    pre_skin : pyvista.PolyData, optional
        Pre-operative skin (default: :func:`skin_from_ct` of ``pre_case.ct``).
    landmarks : dict, optional
        Default ``pre_case.landmarks``.
    max_distance : float, default 10.0
        Median |distance| (mm) above which the surfaces are said not to overlap (error).
    segment_options, skin_options, icp_options : dict, optional
        Keyword arguments of ``segment``, ``extract_skin`` and ``register``. ICP's
        ``tol`` defaults to 5 um here (on skins of 2-3 mm voxels the last updates cycle
        around the optimum by a few um) and ``closest`` to ``'auto'`` (closest points on
        the triangles at the end when libigl is installed: coarse skins).
    regions : bool, default True
        Per-region rows in the table.
    refine : bool, default True
        Put the skins on the CTs' air/skin edge (:func:`refine_skin`): sub-voxel skins,
        so that ICP and the distances are not limited by the voxel staircase.
    progress_bar : bool, default False
        Log the steps at INFO level.

    Returns
    -------
    tuple
        ``(surface, table)``: copy of ``predicted_skin`` with point arrays
        ``arrays.DISTANCE`` and ``arrays.REGION`` and the ICP result in its field data
        (:func:`pvcmf.filters.registration.registration_result` reads it: the matrix maps
        the post-operative CT's frame onto the pre-operative one), and the
        :class:`pandas.DataFrame` of :func:`pvcmf.validation.error_statistics`.

    Raises
    ------
    TypeError
        If a CT is not an ImageData or the prediction is not a dataset.
    ValueError
        If a skin is empty or the surfaces do not overlap.
    pvcmf.filters.registration.RegistrationError
        If ICP does not converge.

    Examples
    --------
    >>> import pvcmf                                                   # doctest: +SKIP
    >>> from pvcmf.postop import postop_ct, validate_from_ct           # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=3.0)                  # doctest: +SKIP
    >>> ct, pose = postop_ct(case, pose="random")                      # doctest: +SKIP
    >>> skin = case.ct.cmf.segment().cmf.skin()                # doctest: +SKIP
    >>> surface, table = validate_from_ct(case, ct, skin)              # doctest: +SKIP
    """
    from . import filters
    from .filters.registration import ICP_MATRIX, registration_result
    from .validation import error_statistics, label_face_regions

    _check_case(pre_case, "pre_case")
    if not isinstance(predicted_skin, pv.DataSet):
        raise TypeError(f"predicted_skin must be a pyvista dataset, got "
                        f"{type(predicted_skin).__name__}")
    if predicted_skin.n_points == 0:
        raise ValueError("predicted_skin must have points, got an empty dataset")
    opts = dict(refine=refine, segment_options=segment_options, skin_options=skin_options)
    post_skin = skin_from_ct(postop_ct, name="postop_ct", **opts)
    if pre_skin is None:
        pre_skin = skin_from_ct(pre_case.ct, name="pre_case.ct", **opts)
    landmarks = getattr(pre_case, "landmarks", None) if landmarks is None else landmarks
    if region is None:
        region = upper_face_region(landmarks)
    icp = {"tol": 5e-3, "closest": "auto", **(icp_options or {})}
    registered = filters.register(post_skin, pre_skin, region=region, **icp)
    matrix, rms, converged = registration_result(registered)
    log.info("validate_from_ct: ICP RMS %.3f mm, converged %s", rms, converged)
    target = pv.PolyData(registered.points, faces=registered.faces)
    out = filters.distance_to(predicted_skin, target, max_distance=max_distance)
    out = label_face_regions(out, landmarks=landmarks)
    for key in registered.field_data.keys():
        out.field_data[key] = registered.field_data[key]
    assert ICP_MATRIX in out.field_data.keys()
    table = error_statistics(out, regions=regions)
    return out, table


def reference_grid(case, *, n_tets=16_000, order=2, steps=4, face_fraction=0.5, cache=True,
                   cache_dir=None, progress_bar=False):
    """The volumetric post-operative truth of a virtual patient (solved tetrahedral grid).

    :func:`pvcmf.reference.truth_grid`: the same fine mesh, materials, boundary conditions
    and model as :func:`pvcmf.reference.postop_skin` (true labels cut by the plan,
    conforming mesh of the anterior face, fibres, Table I, ``apply_plan`` with unmoved bone
    fixed), solved by :func:`pvcmf.reference.solve_reference` (NGSolve, ``pip install
    pvcmf[reference]``) and returned as the grid with point array ``arrays.DISPLACEMENT``
    for :func:`postop_ct`. Cached on disk by the hash of the solver's input grid (the
    cache ``postop_skin`` reads too): a cached truth is read without re-solving, and
    without NGSolve.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient (``truth``, ``plan``).
    n_tets, order, steps, face_fraction, cache, cache_dir :
        See :func:`pvcmf.reference.truth_grid`.
    progress_bar : bool, default False
        Log the steps at INFO level.

    Returns
    -------
    pyvista.UnstructuredGrid
        Solved soft-tissue grid (pre-operative frame) with ``arrays.DISPLACEMENT``.

    Examples
    --------
    >>> import pvcmf                                                   # doctest: +SKIP
    >>> grid = pvcmf.postop.reference_grid(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    from .reference import truth_grid

    if not isinstance(getattr(case, "truth", None), pv.ImageData):
        raise TypeError(f"case must be a virtual patient with a truth label image, got "
                        f"{type(case).__name__}")
    return truth_grid(case, n_tets=n_tets, order=order, steps=steps,
                      face_fraction=face_fraction, cache=cache, cache_dir=cache_dir,
                      progress_bar=progress_bar)
