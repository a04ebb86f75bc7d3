"""The part of the head the soft-tissue model covers, and the parts a plan holds.

* :func:`face_box` - the box of the head's anterior share that is meshed (the model is
  the face in front of a coronal plane, paper 000 Fig. 4c, and above an axial plane
  ``BELOW_MANDIBLE_MM`` under the mandible: no shoulders);
* :func:`drop_floating_parts` - remove mesh parts the boundary conditions do not hold
  (tetrahedra joined through shared faces, by
  :func:`scipy.sparse.csgraph.connected_components`: a part hinged to the rest by an edge
  or a vertex only is a part of its own, since it can turn about that hinge).

Shared by the pipeline (:mod:`pvcmf.pipeline`) and the virtual post-operative truth
(:mod:`pvcmf.truth`), which must build its model without the pipeline it judges.
"""

from __future__ import annotations

import logging
import numbers

import numpy as np

from .. import arrays
from .bone_segments import find_jaws

log = logging.getLogger("pvcmf.pipeline")

__all__ = ["BELOW_MANDIBLE_MM", "drop_floating_parts", "face_box"]

#: depth (mm) of the neck kept in the model under the mandible's lowest point: the submental
#: and submandibular soft tissue that follows the chin, down past the hyoid (15-20 mm under
#: the mandible's lower border); the shoulders lie lower and are left out
BELOW_MANDIBLE_MM = 30.0


def face_box(labels, face_fraction, below_mandible=BELOW_MANDIBLE_MM):
    """Box (xmin, xmax, ymin, ymax, zmin, zmax) of the head's anterior ``face_fraction``.

    The model is the face in front of a coronal plane, as in paper 000 where the most
    posterior plane of the soft-tissue model is fixed (Fig. 4c), and above an axial plane
    ``below_mandible`` mm under the mandible's lowest point: the neck under the chin, not the
    shoulders. The mandible is the ``bone`` array's where it has one (the plan's segments),
    else found from the anatomy (:func:`pvcmf.filters.find_jaws`) where there are teeth.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image (point array ``tissue``; ``bone`` optional).
    face_fraction : float
        Share (0, 1] of the head's anterior-posterior extent kept, from the front.
    below_mandible : float or None, default ``BELOW_MANDIBLE_MM``
        Depth (mm) kept under the mandible; None keeps the whole height.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(4, 4, 100))
    >>> img[arrays.TISSUE] = np.full(img.n_points, arrays.FAT, dtype=np.uint8)
    >>> bone = np.zeros((100, 4, 4), dtype=np.uint8)
    >>> bone[60:70] = arrays.MANDIBLE
    >>> img[arrays.BONE] = bone.ravel()
    >>> [float(z) for z in face_box(img, 1.0)[4:]]  # 30 mm under the mandible (z 60)
    [30.0, 100.0]
    """
    if not (isinstance(face_fraction, numbers.Real) and 0 < face_fraction <= 1):
        raise ValueError(f"face_fraction must be a number in (0, 1], got {face_fraction!r}")
    if below_mandible is not None and not (isinstance(below_mandible, numbers.Real)
                                           and below_mandible >= 0):
        raise ValueError(f"below_mandible must be a number >= 0 (mm) or None, got "
                         f"{below_mandible!r}")
    head = np.asarray(labels[arrays.TISSUE]) != arrays.AIR
    if not head.any():
        raise ValueError("labels has no tissue: the 'tissue' array is all air")
    lo, hi = _extent(labels, head)
    pad = np.asarray(labels.spacing)
    y0 = hi[1] - face_fraction * (hi[1] - lo[1])
    z0 = lo[2] - pad[2]
    mandible = _mandible(labels) if below_mandible is not None else None
    if mandible is not None:
        if mandible.any():
            z_jaw = _extent(labels, mandible)[0][2]
            if z_jaw - below_mandible > z0:
                log.info("face box: %.0f mm under the mandible's lowest point (z %.1f mm): "
                         "the tissue below z %.1f mm is left out", below_mandible, z_jaw,
                         z_jaw - below_mandible)
            z0 = max(z0, z_jaw - below_mandible)
    return (lo[0] - pad[0], hi[0] + pad[0], y0, hi[1] + pad[1], z0, hi[2] + pad[2])


def _mandible(labels):
    """Point mask of the mandible: the labels' ``bone`` array, else found from the anatomy
    (:func:`pvcmf.filters.bone_segments.find_jaws`) where the tissue holds teeth; None where
    there is none."""
    if arrays.BONE in labels.point_data:
        mandible = np.asarray(labels[arrays.BONE]) == arrays.MANDIBLE
        if mandible.any():
            return mandible
    tissue = np.asarray(labels[arrays.TISSUE])
    if not np.any(tissue == arrays.TEETH) or not hasattr(labels, "dimensions"):
        return None
    try:
        found = find_jaws(labels)
    except ValueError as err:
        log.info("face box: no mandible found (%s); the box keeps the whole height", err)
        return None
    mandible = np.asarray(found[arrays.BONE]) == arrays.MANDIBLE
    return mandible if mandible.any() else None


def _extent(labels, mask):
    """Lowest and highest physical coordinates (x, y, z) of the non-empty point ``mask``."""
    direction = getattr(labels, "direction_matrix", None)
    if direction is None or np.allclose(direction, np.eye(3)):
        # index bounds from the mask's projections (no (n, 3) point array: a 1 mm head
        # image has ~30M voxels)
        grid = mask.reshape(labels.dimensions[::-1])  # (z, y, x)
        lo_idx, hi_idx = [], []
        for axis in (2, 1, 0):  # x, y, z
            other = tuple(a for a in range(3) if a != axis)
            hit = np.flatnonzero(grid.any(axis=other))
            lo_idx.append(hit[0])
            hi_idx.append(hit[-1])
        origin, spacing = np.asarray(labels.origin), np.asarray(labels.spacing)
        return origin + spacing * lo_idx, origin + spacing * hi_idx
    pts = np.asarray(labels.points)[mask]
    return pts.min(axis=0), pts.max(axis=0)


def drop_floating_parts(grid, min_constrained=3, collinear_tol=0.05):
    """Remove connected parts of a mesh that the boundary conditions do not hold.

    A part with fewer than ``min_constrained`` fixed/joint/sliding nodes, or with all of
    them (nearly) on one line, would keep rigid motions the solver cannot remove (small
    islands a mesher leaves behind, e.g. tissue in a nostril, or slivers cut off on the
    fixed posterior plane); the MTM's answer does not depend on them elsewhere, so they go.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Mesh with the point array ``bc``.
    min_constrained : int, default 3
    collinear_tol : float, default 0.05
        A part whose constrained nodes lie within this fraction of their extent of one
        line (second singular value of their centred coordinates below ``collinear_tol``
        times the first) is not held: it could rotate about that line.

    Returns
    -------
    pyvista.UnstructuredGrid
        The mesh itself when every part is held, else a new mesh without the others.
    """
    bc = np.asarray(arrays.require_array(grid, arrays.BC, "point", producer="apply_plan"))
    conn_ids = np.asarray(grid.cell_connectivity, dtype=np.int64)
    offsets = np.asarray(grid.cell_offsets, dtype=np.int64)
    cell_region = _cell_parts(grid.n_points, conn_ids, offsets)
    n_regions = int(cell_region.max(initial=-1)) + 1
    # (part, node) pairs: a hinge node belongs to every part it touches
    pair = np.unique(np.repeat(cell_region, np.diff(offsets)) * np.int64(grid.n_points) + conn_ids)
    pair_part, pair_node = pair // grid.n_points, pair % grid.n_points
    constrained = bc[pair_node] != arrays.BC_FREE
    held = np.bincount(pair_part[constrained], minlength=n_regions) >= min_constrained
    # constrained nodes (nearly) on one line leave the rotation about it free (slivers cut
    # off on the fixed posterior plane, a tetrahedron hinged on a fixed edge): not held
    pts = np.asarray(grid.points, float)
    for part in np.flatnonzero(held):  # a loop over the few parts, not over points
        c = pts[pair_node[constrained & (pair_part == part)]]
        sv = np.linalg.svd(c - c.mean(axis=0), compute_uv=False)
        held[part] = sv[1] > collinear_tol * sv[0]
    keep_cells = held[cell_region]
    if keep_cells.all():
        return grid
    dropped = np.unique(cell_region[~keep_cells])
    log.warning("dropping %d mesh part(s) held by fewer than %d non-collinear constrained "
                "nodes (%d cells in all)", len(dropped), min_constrained,
                int((~keep_cells).sum()))
    out = grid.extract_cells(np.flatnonzero(keep_cells))
    for name in (arrays.ORIGINAL_POINT_IDS, "vtkOriginalCellIds"):
        for data in (out.point_data, out.cell_data):
            if name in data:
                data.remove(name)
    return out


_TET_FACES = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])


def _cell_parts(n_points, conn_ids, offsets):
    """Part index of every cell: tetrahedra sharing a face are one part (a mesh of other
    cells: cells sharing a node)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    sizes = np.diff(offsets)
    n_cells = len(sizes)
    if n_cells and np.all(sizes == 4):
        tets = conn_ids.reshape(-1, 4)
        faces = np.sort(tets[:, _TET_FACES].reshape(-1, 3), axis=1)
        n = np.int64(n_points)
        key = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
        owner = np.repeat(np.arange(n_cells), 4)
        order = np.argsort(key, kind="stable")
        key, owner = key[order], owner[order]
        same = key[1:] == key[:-1]  # an inner face: its two tetrahedra
        graph = coo_matrix((np.ones(int(same.sum()), dtype=np.int8),
                            (owner[:-1][same], owner[1:][same])), shape=(n_cells, n_cells))
        return connected_components(graph, directed=False)[1]
    first = np.repeat(conn_ids[offsets[:-1]], sizes)
    graph = coo_matrix((np.ones(first.size, dtype=np.int8), (first, conn_ids)),
                       shape=(n_points, n_points))
    return connected_components(graph, directed=False)[1][conn_ids[offsets[:-1]]]
