"""Boundary conditions from the surgical plan: joint, sliding and fixed nodes (paper 000 Fig. 4).

Paper 000 section III: "a sliding contact surface was defined on the teeth area ... In
the buccal region the bone displacements were projected directly on the surrounding
tissue points ... The most posterior plane of the volumetric soft-tissue model was
assumed to be spatially fixed. The remaining points are considered free."

:func:`apply_plan` writes the point arrays of :mod:`pvcmf.arrays`:

==========  ========  =====================================================================
code        ``bc``    nodes and prescribed values
==========  ========  =====================================================================
joint       2         on the soft-tissue/bone interface of a moving segment;
                      ``bc_displacement`` = that segment's rigid displacement at the node
sliding     3         on the teeth contact (lips against teeth); ``bc_displacement`` = the
                      tooth's rigid displacement at the node (zero for an unmoved jaw) of
                      which only the normal part ``bc_displacement . bc_normal`` is imposed;
                      ``bc_normal`` = unit outward normal of the hard surface (teeth and the
                      alveolar bone around them) at the node
fixed       1         within ``posterior_depth`` of the most posterior plane of the model;
                      optionally on unmoved bone (``fix_unmoved_bone``)
free        0         everything else
==========  ========  =====================================================================

Contact is decided on the boundary nodes of the tetrahedral mesh: a node touches hard
tissue when the nearest hard-tissue voxel centre of ``bones`` (bone or teeth) lies within
``contact_distance``, and it takes the class of that voxel (teeth -> sliding, bone of a
moving segment -> joint, other bone -> free or fixed). A mesh coarser than a thin bone (an
edentulous maxilla, an orbital floor, a sinus wall) covers it instead of leaving a hole
for it, and no boundary node touches it: every hard voxel whose centre lies inside a
tetrahedron is then carried by its nearest node, which takes the class of the nearest
voxel it carries, when that node is inside the mesh (not on its boundary, which contact
decides) and within ``cover_distance``. The bone inside the mesh so moves the tissue on
both of its sides, as the nodes around it sample it, and as the mesh is refined the nodes
it holds close in on it. Where several apply, joint and sliding win over fixed (a node
glued to a moving bone moves with it).

Delegates to :class:`scipy.spatial.cKDTree` (nearest hard voxel), :mod:`scipy.ndimage`
(surface voxels, the smoothed hard-tissue indicator whose gradient gives the normals, trilinear
interpolation) and VTK's surface extraction (:meth:`pyvista.DataSet.extract_surface`).
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.spatial import cKDTree

from .. import arrays
from ..plan import Plan
from ..progress import Progress
from ._checks import check_finite_points, check_image_geometry
from .osteotomy import cut_bones, segment_transforms, voxel_points

log = logging.getLogger(__name__)

__all__ = ["apply_plan", "boundary_points"]


def boundary_points(grid):
    """Indices of the points of ``grid`` that lie on its outer surface.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.filters.boundary_conditions import boundary_points
    >>> grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    >>> len(boundary_points(grid))   # all but the centre point
    26
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            surf = grid.extract_surface(pass_pointid=True, algorithm=None)
        except TypeError:  # pyvista < 0.47
            surf = grid.extract_surface(pass_pointid=True)
    return np.unique(np.asarray(surf.point_data["vtkOriginalPointIds"], dtype=np.int64))


def _positive(name, value, allow_none=False):
    if value is None and allow_none:
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return value


def _surface_normals(bones, hard_mask, points, nearest, sigma):
    """Unit outward normals of the hard-tissue surface (teeth and bone) at ``points``.

    The gradient of the Gaussian-smoothed hard-tissue indicator, on a crop around the
    points, interpolated trilinearly; where it vanishes, the direction from the nearest
    hard voxel centre ``nearest`` to the point. Teeth and the alveolar bone around them
    form one surface, so the normal of a thin tooth is not tilted by its own back face.
    """
    dims = np.asarray(bones.dimensions)
    spacing = np.asarray(bones.spacing, dtype=float)
    origin = np.asarray(bones.origin, dtype=float)
    vol = hard_mask.reshape(tuple(dims), order="F")
    ijk = (points - origin) / spacing
    pad = int(np.ceil(4 * sigma)) + 2
    lo = np.clip(np.floor(ijk.min(axis=0)).astype(int) - pad, 0, dims - 1)
    hi = np.clip(np.ceil(ijk.max(axis=0)).astype(int) + pad + 1, 1, dims)
    crop = vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float64)
    smooth = ndimage.gaussian_filter(crop, sigma, mode="nearest") if sigma > 0 else crop
    grads = np.gradient(smooth, *spacing) if min(crop.shape) > 1 else [np.zeros_like(crop)] * 3
    coords = (ijk - lo).T
    normal = -np.stack([ndimage.map_coordinates(g, coords, order=1, mode="nearest")
                        for g in grads], axis=1)
    fallback = points - nearest
    length = np.linalg.norm(normal, axis=1)
    weak = length < 1e-6 * max(float(np.abs(normal).max(initial=0.0)), 1e-300)
    normal[weak] = fallback[weak]
    length = np.linalg.norm(normal, axis=1)
    length[length == 0] = 1.0
    return normal / length[:, None]


#: :func:`apply_plan` warns when fewer than this share of the nodes end up fixed
MIN_FIXED_SHARE = 0.01


def apply_plan(grid, plan, bones=None, *, joint=True, sliding=True, fixed_posterior=True,
               posterior_depth=2.0, fix_unmoved_bone=False, contact_distance=None,
               teeth_margin=None, normal_sigma=1.0, release_margin=None, cover_distance=None,
               progress_bar=False):
    """Turn a surgical plan into the soft-tissue mesh's boundary conditions.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Soft-tissue tetrahedral mesh in the patient frame (mm), as from
        :func:`pvcmf.filters.tetrahedralize`.
    plan : pvcmf.Plan
        The surgical plan.
    bones : pyvista.ImageData
        The label image the mesh was made from, with point arrays ``bone`` (segment ids)
        and ``tissue`` (teeth = ``arrays.TEETH``). Cut planes of the plan are applied to it
        (:func:`pvcmf.filters.cut_bones`). Required.
    joint : bool, default True
        Paper 000: soft tissue on a moving bone moves with it (Fig. 4b).
    sliding : bool, default True
        Paper 000: nodes touching the teeth slide on them (Fig. 4a). With ``False`` they
        are treated like bone of their segment.
    fixed_posterior : bool, default True
        Paper 000: fix the most posterior plane of the model (Fig. 4c).
    posterior_depth : float, default 2.0
        Nodes with ``y <= min(y) + posterior_depth`` (mm) form that plane.
    fix_unmoved_bone : bool, default False
        Also fix the soft tissue that touches bone which does not move (not in the paper;
        useful for a whole-head model, where nothing else holds the scalp). Without it, a
        :class:`UserWarning` says when fewer than :data:`MIN_FIXED_SHARE` of the nodes are
        fixed (a whole head's posterior plane is a small patch: the model follows the bone).
    contact_distance : float, optional
        A boundary node touches hard tissue when the nearest hard-tissue voxel centre is
        within this distance (mm). Default: the largest voxel spacing of ``bones``.
    teeth_margin : float, optional
        Hard-tissue voxels within this distance (mm) of a tooth voxel count as tooth
        surface: a CT segmentation labels the partial-volume rim of the teeth as bone, so
        the lips touch that rim, not the enamel. The margin holds the alveolar bone round
        the roots too: on a segment that does not move, its nodes are freed near a move
        like the fixed ones (``release_margin``); pinned there (sliding with no normal
        move) they held the tissue that the moving jaw beside them shears and turned
        tetrahedra inside out. Default: the largest voxel spacing; 0 uses the ``TEETH``
        label alone.
    normal_sigma : float, default 1.0
        Gaussian sigma (voxels) smoothing the hard-tissue indicator whose gradient gives
        the sliding normals.
    release_margin : float or 'auto' or None, default None
        Fixed nodes (posterior plane, unmoved bone), and sliding nodes of an unmoved
        segment's teeth margin (see ``teeth_margin``), closer than this (mm) to a node that
        the plan moves are left free. A fixed node one element away from a node moving
        ``d`` mm tears the tissue between them (strain ``d / h``, unbounded as the mesh is
        refined; the linear model then inverts tetrahedra): near the osteotomy line the
        tissue over the unmoved bone is free, as in paper 000. ``'auto'``: twice the
        largest prescribed move (strain about 0.5 at most; :func:`pvcmf.pipeline.simulate`
        uses it); ``None`` or 0 keeps every fixed node.
    cover_distance : float, optional
        A hard voxel whose centre lies inside a tetrahedron (bone the mesh covers) is
        carried by its nearest node when that node is inside the mesh and within this
        distance (mm) of it. Default: twice ``contact_distance`` (on a 1 mm CT, the nodes
        beside a 1-2 mm bone plate that 25,000 tetrahedra over the face lay 1.5-2 mm off
        it; further nodes are held by the tissue the mesh does model between them).
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        A copy of ``grid`` with point arrays ``bc`` (int8), ``bc_displacement`` (mm) and
        ``bc_normal`` (unit, zero where not sliding).

    Raises
    ------
    TypeError
        If ``grid``, ``plan`` or ``bones`` have the wrong type.
    ValueError
        If ``bones`` is missing or lacks ``bone``/``tissue``, a planned segment is not in
        it, an option is out of range, or a moved segment holds no node of the mesh
        (the plan would move nothing).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.plan import Plan, Osteotomy
    >>> from pvcmf.filters import apply_plan
    >>> img = pv.ImageData(dimensions=(11, 11, 11), origin=(-5, -5, -5))
    >>> inner = (np.abs(img.points) <= 2).all(axis=1)
    >>> img[arrays.BONE] = np.where(inner, arrays.MANDIBLE, 0).astype(np.uint8)
    >>> img[arrays.TISSUE] = np.where(inner, arrays.BONE_TISSUE, arrays.FAT).astype(np.uint8)
    >>> soft = ~(np.abs(img.cell_centers().points) < 2).all(axis=1)
    >>> shell = img.extract_cells(np.flatnonzero(soft)).triangulate()
    >>> grid = apply_plan(shell, Plan((Osteotomy("mandible", (0, 0, 1.0)),)), img)
    >>> sorted(set(np.unique(grid[arrays.BC]).tolist()))
    [0, 1, 2]
    >>> grid[arrays.BC_DISPLACEMENT][grid[arrays.BC] == arrays.BC_JOINT][0].tolist()
    [0.0, 1.0, 0.0]
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan, got {type(plan).__name__}")
    tissue, posterior_depth, contact, teeth_margin = _check_bones(
        grid, bones, posterior_depth, contact_distance, normal_sigma, teeth_margin, release_margin)
    cover = _positive("cover_distance", cover_distance, allow_none=True)
    cover = 2.0 * contact if cover is None else cover
    with Progress(total=3, desc="apply_plan", enabled=progress_bar, logger=log) as bar:
        labels = cut_bones(bones, plan)
        transforms = segment_transforms(labels, plan)
        bar.step("bones cut and moved")
        bone = np.asarray(labels[arrays.BONE])
        points = np.asarray(grid.points, dtype=np.float64)
        n = len(points)
        code = np.full(n, arrays.BC_FREE, dtype=np.int8)
        disp = np.zeros((n, 3))
        normal = np.zeros((n, 3))
        hard, nodes, anchor, seg, is_teeth, on_teeth = _hard_contacts(
            grid, labels, bones, bone, tissue, contact, teeth_margin, cover)
        bar.step(f"{len(nodes)} nodes held by hard tissue")
        moved = np.isin(seg, list(transforms))
        # nodes on the teeth margin only (bone next to the teeth: the crown's partial-volume
        # rim, the alveolar bone round the roots): on a jaw that stays, freed near a move
        rim = np.zeros(n, dtype=bool)
        rim[nodes] = is_teeth & ~on_teeth

        def rigid(idx, segs):
            out = np.zeros((len(idx), 3))
            for s, m in transforms.items():
                sel = segs == s
                p = points[idx[sel]]
                out[sel] = p @ m[:3, :3].T + m[:3, 3] - p
            return out

        if fix_unmoved_bone:
            code[nodes[~moved & ~(is_teeth & sliding)]] = arrays.BC_FIXED
        if fixed_posterior:
            y = points[:, 1]
            back = y <= y.min() + posterior_depth
            code[back & (code == arrays.BC_FREE)] = arrays.BC_FIXED
        if joint:
            sel = moved & ~(is_teeth & sliding)
            code[nodes[sel]] = arrays.BC_JOINT
            disp[nodes[sel]] = rigid(nodes[sel], seg[sel])
        if sliding and is_teeth.any():
            sel = is_teeth
            idx = nodes[sel]
            code[idx] = arrays.BC_SLIDING
            disp[idx] = rigid(idx, seg[sel])
            normal[idx] = _surface_normals(labels, hard, points[idx], anchor[sel],
                                           normal_sigma)

        if joint or sliding:
            for s in transforms:
                if not np.any(seg == s):
                    raise ValueError(
                        f"the plan moves {arrays.BONE_NAMES[s]!r} but no mesh node lies within "
                        f"contact_distance={contact:g} mm of it (boundary nodes) or carries "
                        f"it within cover_distance={cover:g} mm (nodes inside the mesh): is "
                        f"the mesh in the same frame as bones, or should contact_distance be "
                        f"larger?"
                    )
        released = _release_near_moves(code, disp, points, release_margin,
                                       rim & (code == arrays.BC_SLIDING))
        normal[released] = 0.0
        if fixed_posterior and not fix_unmoved_bone:
            _warn_few_fixed(code, posterior_depth)
        counts = {k: int(np.sum(code == v)) for k, v in arrays.BC_CODES.items()}
        log.info("apply_plan: %s (contact %.2f mm, %d nodes held by hard tissue)",
                 counts, contact, len(nodes))
        out = grid.copy()
        out.point_data[arrays.BC] = code
        out.point_data[arrays.BC_DISPLACEMENT] = disp
        out.point_data[arrays.BC_NORMAL] = normal
        bar.step("boundary conditions written")
    return out


def _check_bones(grid, bones, posterior_depth, contact_distance, normal_sigma, teeth_margin,
                 release_margin=None):
    """Check :func:`apply_plan`'s image and distances.

    Returns the tissue labels and the posterior depth, contact distance and teeth margin
    (the defaults resolved).
    """
    if bones is None:
        raise ValueError(
            "bones must be the label image with 'bone' and 'tissue' point arrays that the "
            "mesh was made from (e.g. ct.cmf.segment() or a phantom's truth), got None"
        )
    if not isinstance(bones, pv.ImageData):
        raise TypeError(f"bones must be a pyvista.ImageData, got {type(bones).__name__}")
    if grid.n_points == 0:
        raise ValueError("grid must have points, got an empty mesh")
    check_finite_points(grid, "grid")
    check_image_geometry(bones, "bones")
    arrays.require_array(bones, arrays.BONE, "point", dtype="iu", ncomp=1, producer="segment")
    tissue = np.asarray(arrays.require_array(bones, arrays.TISSUE, "point", dtype="iu",
                                             ncomp=1, producer="segment"))
    posterior_depth = _positive("posterior_depth", posterior_depth)
    spacing = np.asarray(bones.spacing, dtype=float)
    contact = _positive("contact_distance", contact_distance, allow_none=True)
    if contact is None:
        contact = float(spacing.max())
    if not (release_margin is None or (isinstance(release_margin, str) and release_margin == "auto")
            or (isinstance(release_margin, (int, float, np.integer, np.floating))
                and not isinstance(release_margin, bool)
                and np.isfinite(release_margin) and release_margin >= 0)):
        raise ValueError(f"release_margin must be 'auto', None or a finite number >= 0 (mm), "
                         f"got {release_margin!r}")
    if not np.isfinite(normal_sigma) or normal_sigma < 0:
        raise ValueError(f"normal_sigma must be a finite number >= 0, got {normal_sigma!r}")
    if teeth_margin is None:
        teeth_margin = float(spacing.max())
    elif not np.isfinite(teeth_margin) or teeth_margin < 0:
        raise ValueError(f"teeth_margin must be a finite number >= 0 (mm), got {teeth_margin!r}")
    return tissue, posterior_depth, contact, teeth_margin


def _hard_contacts(grid, labels, bones, bone, tissue, contact, teeth_margin, cover):
    """The nodes of ``grid`` that hard tissue holds, and what holds each.

    Two ways: a boundary node within ``contact`` mm of a hard surface voxel centre takes
    the nearest one (the tissue on a bone surface); and every hard voxel whose centre lies
    inside a tetrahedron (bone the mesh covers: a mesh coarser than a thin bone covers it)
    is carried by its nearest node when that is an interior node within ``cover`` mm,
    which takes the nearest such voxel. A node held both ways keeps its contact.

    Returns the hard-tissue mask (bone or teeth voxels), the held nodes, the centre of
    the voxel that holds each, its bone segment, whether it lies within ``teeth_margin``
    of the teeth and whether it is a tooth voxel itself.
    """
    # hard tissue: bone or teeth voxels; only their surface layer can be nearest to tissue
    # outside them
    hard = (bone > 0) | np.isin(tissue, arrays.HARD_LABELS)
    dims = tuple(bones.dimensions)
    vol = hard.reshape(dims, order="F")
    if not vol.any():
        raise ValueError("bones has no bone or teeth voxels ('bone' > 0 or hard 'tissue')")
    box = _box(vol, np.zeros(3, dtype=int))  # erosion on the hard tissue's box only
    surface = np.zeros_like(vol)
    surface[box] = vol[box] & ~ndimage.binary_erosion(vol[box], border_value=0)
    surf_ids = np.flatnonzero(surface.ravel(order="F"))
    vox = voxel_points(labels, surf_ids)
    points = np.asarray(grid.points, dtype=np.float64)
    outer = boundary_points(grid)
    dist, near = cKDTree(vox).query(points[outer], distance_upper_bound=contact * (1 + 1e-9))
    touching = np.isfinite(dist)
    nodes, ids = outer[touching], surf_ids[near[touching]]
    cov_nodes, cov_ids = _covered(grid, labels, hard, points, outer, cover)
    extra = ~np.isin(cov_nodes, nodes)
    nodes = np.concatenate([nodes, cov_nodes[extra]])
    ids = np.concatenate([ids, cov_ids[extra]])
    teeth = tissue == arrays.TEETH
    at = voxel_points(labels, ids)
    if teeth_margin > 0 and teeth.any():
        # distance to the teeth on a crop around them (the margin is a few voxels)
        spacing = np.asarray(bones.spacing, dtype=float)
        vol_teeth = teeth.reshape(dims, order="F")
        box = _box(vol_teeth, np.ceil(teeth_margin / spacing).astype(int) + 1)
        near_teeth = np.zeros(dims, dtype=bool)
        near_teeth[box] = ndimage.distance_transform_edt(
            ~vol_teeth[box], sampling=spacing) <= teeth_margin * (1 + 1e-9)
        # the holding voxels are hard: within the margin is all to ask
        return hard, nodes, at, bone[ids], near_teeth.ravel(order="F")[ids], teeth[ids]
    return hard, nodes, at, bone[ids], teeth[ids], teeth[ids]


def _covered(grid, labels, hard, points, outer, cover):
    """The interior nodes that carry the hard voxels lying inside the mesh's tetrahedra:
    each such voxel goes to its nearest node, kept when that node is not on the mesh's
    boundary (the nodes ``outer``) and lies within ``cover`` mm; each of those nodes takes
    the nearest voxel it carries. Returns the nodes and the flat ids of their voxels."""
    none = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    ids = np.flatnonzero(hard)
    at = voxel_points(labels, ids)
    box = np.all((at >= lo) & (at <= hi), axis=1)  # the mesh's bounding box only
    ids, at = ids[box], at[box]
    if not len(ids):
        return none
    # the nearest node first (a cheap search): only voxels whose nearest node is interior
    # and within ``cover`` can be kept, so only they are located in the tetrahedra
    dist, node = cKDTree(points).query(at, distance_upper_bound=cover * (1 + 1e-9))
    interior = np.zeros(len(points) + 1, dtype=bool)  # (the last: no node within cover)
    interior[:-1] = True
    interior[outer] = False
    keep = interior[node]
    ids, at, dist, node = ids[keep], at[keep], dist[keep], node[keep]
    if not len(ids):
        return none
    inside = np.asarray(grid.find_containing_cell(at)) >= 0
    ids, dist, node = ids[inside], dist[inside], node[inside]
    order = np.lexsort((dist, node))  # per node, its nearest voxel first
    node, first = np.unique(node[order], return_index=True)
    return node.astype(np.int64), ids[order[first]]


def _box(mask, pad):
    """Slices of the smallest box holding the True voxels of ``mask`` (3-D, not empty),
    widened by ``pad`` voxels per axis within the array."""
    box = []
    for ax in range(3):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != ax)))
        box.append(slice(max(int(hit[0]) - int(pad[ax]), 0),
                         min(int(hit[-1]) + 1 + int(pad[ax]), mask.shape[ax])))
    return tuple(box)


def _release_near_moves(code, disp, points, margin, also=None):
    """In place: free the fixed nodes (and the ``also`` nodes that do not move) within
    ``margin`` mm of a node the plan moves; return the indices freed."""
    moving = ((code == arrays.BC_JOINT) | (code == arrays.BC_SLIDING)) & (
        np.linalg.norm(disp, axis=1) > 0)
    if isinstance(margin, str) and margin == "auto":
        margin = 2.0 * float(np.linalg.norm(disp[moving], axis=1).max(initial=0.0))
    margin = 0.0 if margin is None else float(margin)
    held = code == arrays.BC_FIXED
    if also is not None:
        held |= also & ~moving
    fixed = np.flatnonzero(held)
    if margin <= 0 or not moving.any() or not fixed.size:
        return np.zeros(0, dtype=np.int64)
    dist, _ = cKDTree(points[moving]).query(points[fixed], distance_upper_bound=margin)
    near = fixed[np.isfinite(dist)]
    code[near] = arrays.BC_FREE
    log.info("apply_plan: %d of %d fixed nodes within %.3g mm of a moving node left free",
             len(near), len(fixed), margin)
    return near


def _warn_few_fixed(code, posterior_depth):
    """Warn when fewer than :data:`MIN_FIXED_SHARE` of the nodes are fixed."""
    n_fixed = int(np.sum(code == arrays.BC_FIXED))
    if n_fixed < MIN_FIXED_SHARE * len(code):
        warnings.warn(
            f"apply_plan: only {n_fixed} of {len(code)} nodes are fixed (the posterior plane "
            f"y <= min(y) + {posterior_depth:g} mm): a model that "
            "spans the whole head is then held almost only by the moving bone and follows it. "
            "Crop it to the face (tetrahedralize(..., roi=pvcmf.pipeline.face_box(labels, 0.5)), "
            "as paper 000 and pvcmf.pipeline do) or pass fix_unmoved_bone=True",
            UserWarning, stacklevel=3,
        )
