"""The outer skin surface of a label image, a CT, or a tetrahedral soft-tissue grid.

* Image (``tissue`` labels, or ``ct`` thresholded): the air/head boundary, on the head's box
  (a margin of air wider than the smoothing kernel: a scan's field of view is mostly air).
  Everything that is not air, plus every cavity enclosed by the head (sinuses, airway
  pockets: the air :func:`scipy.ndimage.label` does not connect to the box's border, as
  :func:`scipy.ndimage.binary_fill_holes` fills), lightly smoothed
  (:func:`scipy.ndimage.gaussian_filter`) and contoured at one half by VTK's flying edges
  (:meth:`pyvista.ImageDataFilters.contour`); the largest connected piece is kept
  (``vtkPolyDataConnectivityFilter``), the voxel terraces the contour still has are
  removed by windowed-sinc smoothing (``vtkWindowedSincPolyDataFilter`` via
  :meth:`pyvista.PolyDataFilters.smooth_taubin`: a low-pass filter that does not shrink
  the surface), and outward point normals are added (``vtkPolyDataNormals``).
  The image is padded with air first, so the surface is closed where the head leaves the
  field of view; with ``open_boundary=True`` it is padded with its own edge values instead
  (the head goes on beyond the image), and the surface is clipped to the image's bounds
  (``vtkClipPolyData``): it is left open where the scan ends, with no cap. The outward side of
  such an open surface is found from the head mask (the smoothed mask falls along the
  outward normal).
* Tetrahedral grid: its boundary triangles (``vtkDataSetSurfaceFilter`` via
  :meth:`pyvista.DataSet.extract_surface`), oriented outward, restricted to the *skin*
  part: the faces whose three points are free (``bc == BC_FREE``) when the grid carries
  boundary conditions — the faces touching bone (joint / sliding) and the fixed posterior
  cut are left out — or else, given ``labels``, the faces that face air in the label
  image. Without either, the whole boundary is returned (and a warning logged). Either way
  the grid's skin also holds the free walls of the cavities the mesh leaves open (mouth,
  airway) and the cuts of the region of interest: good for display and for the grid
  correspondence, but measure errors on the dense image skin (``labels.cmf.skin()``, with the
  grid's displacement carried by :func:`pvcmf.filters.map_to_surface`).
  The skin keeps its correspondence with the grid through the point array
  ``vtkOriginalPointIds`` (grid point ids) and carries the grid's point arrays, so
  displacements carry over; with ``warp=True`` (default) the points are moved by the
  grid's ``displacement`` when it has one (the predicted skin).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy import ndimage

from .. import arrays
from ..progress import Progress
from .morphology import _box, _fill, _smoothing_margin

log = logging.getLogger(__name__)

#: point array of a grid skin: index of each skin point in the tetrahedral grid
ORIGINAL_POINT_IDS = "vtkOriginalPointIds"
#: default windowed-sinc iterations on an image skin (0: the contour as it is)
SINC_ITERATIONS = 40
#: pass band of the windowed-sinc filter (VTK's units; smaller smooths more)
SINC_PASS_BAND = 0.05
#: an open skin's cut on the image's planes: points within this fraction of the smallest
#: voxel spacing of a plane go onto it, and points as close are merged (no sliver triangles)
SLIVER_FRACTION = 0.1
#: an open skin's triangle is turned outward on its own when the smoothed head mask (0 in
#: air, 1 in the head) rises along its normal by more than this between one voxel outside
#: and one voxel inside (a clear rise, not the noise of a flat or thin place)
ORIENT_MARGIN = 0.1


def _outward_normals(surface):
    """Point normals (and consistent winding) of a closed surface, pointing outward."""
    return surface.compute_normals(
        cell_normals=False, point_normals=True, split_vertices=False,
        consistent_normals=True, auto_orient_normals=True,
    )


def _image_skin(image, threshold, smooth, fill_holes, sinc, open_boundary=False):
    if arrays.TISSUE in image.point_data:
        lab = arrays.require_array(image, arrays.TISSUE, "point", dtype="iu", ncomp=1)
        head = lab != arrays.AIR
    elif arrays.CT in image.point_data:
        ct = arrays.require_array(image, arrays.CT, "point", dtype="f", ncomp=1)
        head = ct > threshold
    else:
        raise ValueError(
            f"extract_skin needs point array {arrays.TISSUE!r} (produced by segment) or "
            f"{arrays.CT!r} on the image; it has {sorted(image.point_data.keys())}"
        )
    dims = tuple(int(d) for d in image.dimensions)
    if min(dims) < 2:
        raise ValueError(f"image must be 3-D, got dimensions {dims}")
    vol = head.reshape(dims[::-1]).transpose(2, 1, 0)  # VTK x-fastest -> (x, y, z)
    if not vol.any():
        raise ValueError("image has no head voxels (all air): no skin to extract")
    # the head's box with a margin of air wider than the smoothing kernel: the filling,
    # smoothing and contour of the whole image give the same surface there, and a scan's
    # field of view is mostly air around the head
    box = _box(vol, _smoothing_margin(smooth))
    vol, corner = vol[box], np.array([b.start for b in box], dtype=float)
    vol = np.ascontiguousarray(vol)
    if open_boundary:  # the head goes on beyond the image: no cap where it leaves it
        vol = np.pad(_fill(vol, None) if fill_holes else vol, 2, mode="edge")
    else:
        vol = np.pad(vol, 2, constant_values=False)
        if fill_holes:
            vol = _fill(vol, None)
    field = vol.astype(np.float32)
    if smooth:
        field = ndimage.gaussian_filter(field, smooth)
    spacing = np.asarray(image.spacing, dtype=float)
    origin = np.asarray(image.origin, dtype=float) - 2 * spacing
    if hasattr(image, "direction_matrix") and not np.allclose(image.direction_matrix, np.eye(3)):
        raise ValueError("extract_skin supports axis-aligned images only (identity direction)")
    grid = pv.ImageData(dimensions=field.shape, spacing=spacing, origin=origin)
    first = corner.astype(int)  # the box's voxels keep their points (origin + index spacing)
    grid.extent = tuple(int(v) for pair in zip(first, first + np.asarray(field.shape) - 1)
                        for v in pair)
    grid.point_data[arrays.SCRATCH_HEAD] = field.transpose(2, 1, 0).ravel()
    surf = grid.contour([0.5], scalars=arrays.SCRATCH_HEAD, method="flying_edges", progress_bar=False)
    if surf.n_points == 0:
        raise ValueError("the head mask produced an empty contour (too small an object?)")
    surf = surf.connectivity("largest").extract_surface(algorithm="dataset_surface")
    surf = surf.triangulate().clean()
    surf.clear_data()
    if sinc:
        surf = surf.smooth_taubin(n_iter=int(sinc), pass_band=SINC_PASS_BAND,
                                  normalize_coordinates=True, progress_bar=False)
    if not open_boundary:
        return _outward_normals(surf)
    surf = _within(surf, np.asarray(image.bounds, dtype=float), 1e-3 * float(spacing.min()),
                   snap=SLIVER_FRACTION * float(spacing.min()))
    return _open_outward_normals(surf, field, origin + corner * spacing, spacing)


def _within(surface, bounds, tol, snap=0.0):
    """The largest connected piece of ``surface`` clipped to ``bounds`` (``vtkClipPolyData``
    on each plane of the bounds that ``surface`` crosses by more than ``tol``): the
    surface ends on the planes, with a straight edge. Points within ``snap`` of a plane
    are first moved onto it, and points closer than ``snap`` merged after the clips, so
    that the cut leaves no sliver triangles (edges of a few micrometres beside a contour
    point that lay just beyond the plane)."""
    b = np.asarray(bounds, dtype=float)
    for axis in range(3):
        for side, sign in ((0, -1.0), (1, 1.0)):
            p = np.asarray(surface.points)
            if not len(p):
                raise ValueError("the head's contour has no triangle within the image")
            if not np.any(sign * (p[:, axis] - b[2 * axis + side]) > tol):
                continue
            near = np.abs(p[:, axis] - b[2 * axis + side]) < snap
            if near.any():  # onto the plane: the clip then makes no sliver beside them
                p = p.copy()
                p[near, axis] = b[2 * axis + side]
                surface = surface.copy()
                surface.points = p
            normal = np.zeros(3)
            normal[axis] = sign  # the clip removes the side the normal points to
            origin = np.zeros(3)
            origin[axis] = b[2 * axis + side]
            surface = surface.clip(normal=normal, origin=origin, progress_bar=False)
    if not surface.n_cells:
        raise ValueError("the head's contour has no triangle within the image")
    surface = surface.triangulate().clean(tolerance=snap, absolute=True)
    if not surface.is_all_triangles:  # the merge made degenerate triangles into lines
        surface = surface.extract_cells_by_type(pv.CellType.TRIANGLE).extract_surface(
            algorithm="dataset_surface")
    return surface.clean().connectivity("largest").extract_surface(
        algorithm="dataset_surface").clean()


def _open_outward_normals(surface, field, origin, spacing):
    """Point normals of an open surface, pointing to where the smoothed head mask ``field``
    (array (x, y, z) on the grid ``origin``, ``spacing``) falls.

    The triangles are first wound consistently (VTK's normal pass) and the whole surface
    turned outward by the field; then every triangle along whose normal the field clearly
    rises (by more than :data:`ORIENT_MARGIN` over one voxel on either side) is turned on
    its own: a non-manifold edge stops the consistency pass, which would otherwise leave a
    whole patch wound inward."""
    surf = surface.compute_normals(cell_normals=False, point_normals=True, split_vertices=False,
                                   consistent_normals=True, auto_orient_normals=False)
    tri = surf.faces.reshape(-1, 4)[:, 1:].copy()
    pts = np.asarray(surf.points, dtype=float)
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
    step = normal * float(spacing.max())
    centre = (a + b + c) / 3.0
    at = [((centre + sign * step - origin) / spacing).T for sign in (1.0, -1.0)]
    out, inn = (ndimage.map_coordinates(field, p, order=1, mode="nearest") for p in at)
    rise = out - inn  # > 0: the mask grows along the normal, which points into the head
    if np.sum(rise) > 0:  # most of the surface wound inward: turn it all
        tri, rise = tri[:, ::-1], -rise
    inward = rise > ORIENT_MARGIN
    tri[inward] = tri[inward][:, ::-1]
    if inward.any():
        log.info("extract_skin: %d of %d triangles turned outward on their own (a "
                 "non-manifold edge stopped the consistent winding)", int(inward.sum()),
                 len(tri))
    faces = np.column_stack([np.full(len(tri), 3), tri]).ravel()
    oriented = pv.PolyData(pts.copy(), faces)
    return oriented.compute_normals(cell_normals=False, point_normals=True,
                                    split_vertices=False, consistent_normals=False,
                                    auto_orient_normals=False)


def _boundary_faces(grid):
    """Boundary triangles of a tetrahedral grid as grid point ids, wound outward."""
    surf = grid.extract_surface(
        pass_pointid=True, pass_cellid=True, algorithm="dataset_surface"
    ).triangulate()
    faces = surf.faces.reshape(-1, 4)[:, 1:]
    pid = np.asarray(surf.point_data[ORIGINAL_POINT_IDS], dtype=np.int64)
    cid = np.asarray(surf.cell_data["vtkOriginalCellIds"], dtype=np.int64)
    tri = pid[faces]
    pts = np.asarray(grid.points, dtype=float)
    # orient each face away from the centroid of the tetrahedron it bounds
    cells = grid.cells_dict[pv.CellType.TETRA] if pv.CellType.TETRA in grid.cells_dict else None
    if cells is None or len(cells) != grid.n_cells:
        raise ValueError("extract_skin of a grid needs an all-tetrahedral UnstructuredGrid")
    tet_centre = pts[cells[cid]].mean(axis=1)
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    normal = np.cross(b - a, c - a)
    flip = np.einsum("ij,ij->i", normal, (a + b + c) / 3 - tet_centre) < 0
    tri[flip] = tri[flip][:, ::-1]
    return tri


def _grid_skin(grid, labels, warp, part):
    if grid.n_cells == 0:
        raise ValueError("grid is empty: no skin to extract")
    tri = _boundary_faces(grid)
    if part == "skin":
        if arrays.BC in grid.point_data:
            bc = arrays.require_array(grid, arrays.BC, "point", dtype="iu", ncomp=1)
            keep = (bc[tri] == arrays.BC_FREE).all(axis=1)
        elif labels is not None:
            keep = _faces_air(grid.points, tri, labels)
        else:
            log.warning(
                "extract_skin: grid has no %r array and no labels were given; returning the "
                "whole boundary (faces touching bone included)", arrays.BC,
            )
            keep = np.ones(len(tri), dtype=bool)
        tri = tri[keep]
        if not len(tri):
            raise ValueError("no boundary face of the grid is skin (all touch bone or are fixed)")
    ids, local = np.unique(tri, return_inverse=True)
    local = local.reshape(-1, 3)
    pts = np.asarray(grid.points, dtype=float)[ids]
    skin = pv.PolyData(pts, np.column_stack([np.full(len(local), 3), local]).ravel())
    for name in grid.point_data.keys():
        skin.point_data[name] = np.asarray(grid.point_data[name])[ids]
    skin.point_data[ORIGINAL_POINT_IDS] = ids
    if warp and arrays.DISPLACEMENT in grid.point_data:
        u = arrays.require_array(grid, arrays.DISPLACEMENT, "point", dtype="f", ncomp=3)
        skin.points = pts + u[ids]
    return skin.compute_normals(
        cell_normals=False, split_vertices=False, consistent_normals=False,
        auto_orient_normals=False,
    )


def _faces_air(points, tri, labels, step=1.5):
    """Faces whose outward neighbourhood is air in the label image."""
    arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu", ncomp=1, producer="segment")
    pts = np.asarray(points, dtype=float)
    a, b, c = pts[tri[:, 0]], pts[tri[:, 1]], pts[tri[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-30)[:, None]
    h = step * float(np.max(labels.spacing))
    probe = pv.PolyData((a + b + c) / 3 + h * n).sample(labels, progress_bar=False)
    valid = np.asarray(probe["vtkValidPointMask"], dtype=bool)
    # outside the image counts as air
    return ~valid | (np.asarray(probe[arrays.TISSUE]) == arrays.AIR)


def extract_skin(dataset, *, threshold=-300.0, smooth=1.0, fill_holes=True, labels=None,
                 warp=True, part="skin", sinc=SINC_ITERATIONS, open_boundary=False,
                 progress_bar=False):
    """The outer skin surface of a label image / CT, or of a tetrahedral grid.

    Parameters
    ----------
    dataset : pyvista.ImageData or pyvista.UnstructuredGrid
        Label image with point array ``arrays.TISSUE`` (or a CT with ``arrays.CT``), or
        a tetrahedral soft-tissue grid.
    threshold : float, default -300.0
        HU threshold of the head when an image has ``ct`` but no ``tissue``.
    smooth : float, default 1.0
        Gaussian smoothing (in voxels) of the head mask before contouring; 0 keeps the
        voxel staircase.
    fill_holes : bool, default True
        Fill enclosed air (sinuses, pockets) so only the outer skin is contoured.
    labels : pyvista.ImageData, optional
        Grid only, when it has no ``bc`` array: the label image used to keep the faces
        that face air.
    warp : bool, default True
        Grid only: move the skin points by the grid's ``displacement`` (the predicted
        skin). The rest skin is ``extract_skin(grid, warp=False)``.
    part : {'skin', 'boundary'}, default 'skin'
        Grid only: the skin faces (see the module docs) or the whole boundary.
    sinc : int, default 40
        Image only: windowed-sinc smoothing iterations of the contour (removes the voxel
        terraces without shrinking the surface); 0 keeps the contour.
    open_boundary : bool, default False
        Image only: leave the surface open where the head leaves the image (the scan's
        field of view ends across the neck, the vertex or the face): the surface is
        clipped to the image's bounds instead of being closed with a cap.
    progress_bar : bool, default False
        Show the step (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.PolyData
        Triangle surface with outward point normals. From a grid it also has the grid's
        point arrays and ``vtkOriginalPointIds`` (grid point ids).

    Raises
    ------
    TypeError
        Neither an ImageData nor an UnstructuredGrid.
    ValueError
        Missing arrays, an all-air image, an empty grid, or no skin faces.

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(30, 30, 30), spacing=(2.0, 2.0, 2.0))
    >>> r = np.linalg.norm(img.points - img.center, axis=1)
    >>> img[arrays.TISSUE] = (r < 20).astype(np.uint8)
    >>> skin = img.cmf.skin()
    >>> bool(abs(np.linalg.norm(skin.points - img.center, axis=1).mean() - 20) < 1)
    True
    """
    if part not in ("skin", "boundary"):
        raise ValueError(f"part must be 'skin' or 'boundary', got {part!r}")
    if not isinstance(dataset, (pv.ImageData, pv.UnstructuredGrid)):
        raise TypeError(
            f"dataset must be a pyvista.ImageData (labels / CT) or an UnstructuredGrid "
            f"(tetrahedra), got {type(dataset).__name__}"
        )
    with Progress(total=1, desc="extract_skin", enabled=progress_bar, logger=log) as bar:
        if isinstance(dataset, pv.ImageData):
            if isinstance(sinc, bool) or int(sinc) != sinc or sinc < 0:
                raise ValueError(f"sinc must be a non-negative integer, got {sinc!r}")
            skin = _image_skin(dataset, threshold, smooth, fill_holes, sinc,
                               bool(open_boundary))
        else:
            skin = _grid_skin(dataset, labels, warp, part)
        bar.step(f"{skin.n_points} skin points")
    return skin


#: mm of neck kept under the model's box by :func:`head_skin`: the fade of the mesh ->
#: skin transfer (8 mm beyond a mesh the skin fit may push 4 mm out) and some unmoved neck
NECK_BELOW_BOX = 20.0


def head_skin(labels, box=None, below=NECK_BELOW_BOX):
    """The skin a prediction shows: the whole head as the scan has it.

    The dense skin of the label image (:func:`extract_skin`, sub-voxel), left open where
    the scan's field of view ends (no cap over a cut neck, vertex or face:
    ``open_boundary=True``). Given the model's ``box``, the neck and shoulders more than
    ``below`` mm under it are cut off (``vtkClipPolyData``, the largest piece kept; the
    shoulders would otherwise set the figures' framing); the back of the head, outside the
    model, is kept.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image (point array ``tissue``).
    box : tuple of 6 floats, optional
        The model's box (xmin, xmax, ymin, ymax, zmin, zmax), e.g.
        :func:`pvcmf.filters.model_region.face_box`.
    below : float, default NECK_BELOW_BOX
        Depth (mm) of neck kept under the box.

    Returns
    -------
    pyvista.PolyData
        Triangle surface with its outward unit point normals (``arrays.NORMALS``) only.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(30, 30, 20), spacing=(2.0, 2.0, 2.0), origin=(-29, -29, -9))
    >>> img[arrays.TISSUE] = (np.linalg.norm(img.points, axis=1) < 20).astype(np.uint8)
    >>> skin = head_skin(img)  # the ball leaves the image at z = -9: open there
    >>> round(float(skin.bounds[4]), 1), skin.n_open_edges > 0
    (-9.0, True)
    """
    skin = extract_skin(labels, open_boundary=True)
    if box is not None:
        if not float(below) >= 0:
            raise ValueError(f"below must be a number >= 0 (mm), got {below!r}")
        cut = float(box[4]) - float(below)
        if np.asarray(skin.points)[:, 2].min() < cut:
            skin = skin.clip(normal=(0.0, 0.0, -1.0), origin=(0.0, 0.0, cut), progress_bar=False)
            if not skin.n_cells:
                raise ValueError(f"the skin has no triangle above z = {cut} mm")
            skin = skin.triangulate().clean().connectivity("largest").extract_surface(
                algorithm="dataset_surface")
    out = pv.PolyData(np.asarray(skin.points, dtype=float), skin.faces)
    out.point_data[arrays.NORMALS] = np.asarray(skin.point_data[arrays.NORMALS], dtype=float)
    return out


def sub_surface(surface, tri):
    """The triangles ``tri`` (point ids of ``surface``, shape (n, 3)) as a surface of their
    points with ``surface``'s point arrays, and the ids of those points in ``surface``.

    Examples
    --------
    >>> import pyvista as pv
    >>> plane = pv.Plane(i_resolution=2, j_resolution=2).triangulate()
    >>> part, ids = sub_surface(plane, plane.faces.reshape(-1, 4)[:2, 1:])
    >>> part.n_cells, len(ids) == part.n_points
    (2, True)
    """
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    ids, local = np.unique(tri, return_inverse=True)
    out = pv.PolyData(np.asarray(surface.points)[ids],
                      np.column_stack([np.full(len(tri), 3), local.reshape(-1, 3)]).ravel())
    for name in surface.point_data.keys():
        out.point_data[name] = np.asarray(surface.point_data[name])[ids]
    return out, ids


def coarsen_outside(surface, keep, reduction):
    """``surface`` with its triangles that have a point outside ``keep`` decimated.

    The triangles whose three points are in ``keep`` stay as they are; the others are
    decimated by ``reduction`` (VTK's ``vtkDecimatePro`` via
    :meth:`pyvista.PolyDataFilters.decimate_pro`, topology kept and no boundary point
    deleted: the seam between the two parts and any open end of the surface stay in
    place, so that the parts join again without a crack). Used to draw the skin far from
    the model (which does not move) with fewer triangles.

    Parameters
    ----------
    surface : pyvista.PolyData
        Triangle surface.
    keep : array_like of bool
        One value per point of ``surface``.
    reduction : float
        Share in [0, 1) of the outer part's triangles to remove.

    Returns
    -------
    pyvista.PolyData
        A new triangle surface, without point or cell arrays.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> sphere = pv.Sphere(theta_resolution=60, phi_resolution=60)
    >>> out = coarsen_outside(sphere, np.asarray(sphere.points)[:, 1] > 0, 0.75)
    >>> out.n_points < sphere.n_points, out.n_open_edges
    (True, 0)
    """
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (surface.n_points,):
        raise ValueError(f"keep must have one value per point ({surface.n_points}), "
                         f"got shape {keep.shape}")
    if not 0.0 <= float(reduction) < 1.0:
        raise ValueError(f"reduction must be in [0, 1), got {reduction!r}")
    tri = surface.faces.reshape(-1, 4)[:, 1:]
    inner = keep[tri].all(axis=1)
    if inner.all() or float(reduction) == 0.0:
        return pv.PolyData(np.array(surface.points, dtype=float), np.array(surface.faces))
    outer, _ = sub_surface(surface, tri[~inner])
    outer.clear_data()
    outer = outer.decimate_pro(float(reduction), preserve_topology=True, splitting=False,
                               boundary_vertex_deletion=False)
    if not inner.any():
        return outer
    near, _ = sub_surface(surface, tri[inner])
    near.clear_data()
    return near.merge(outer, merge_points=True).extract_surface(algorithm="dataset_surface")
