"""Element quality of tetrahedral meshes and the relocation of sliver nodes.

:func:`tet_quality` gives the dihedral angles, signed volumes and radius ratios of every
tetrahedron (vectorised numpy); :func:`_relocate_sliver_nodes` moves the interior nodes
of the few slivers that the volume mesher's optimiser leaves.
"""

from __future__ import annotations

import itertools

import numpy as np

from ... import arrays

#: field-data names written by :func:`~pvcmf.filters.meshing.tetrahedralize`
MIN_DIHEDRAL = arrays.MESH_MIN_DIHEDRAL
P1_DIHEDRAL = arrays.MESH_P1_DIHEDRAL
MIN_RADIUS_RATIO = arrays.MESH_MIN_RADIUS_RATIO
P1_RADIUS_RATIO = arrays.MESH_P1_RADIUS_RATIO
N_TETS_REQUESTED = arrays.MESH_N_TETS_REQUESTED
SURFACE_SPACING = arrays.MESH_SURFACE_SPACING
SMOOTHING_SCALE = arrays.MESH_SMOOTHING_SCALE
TIME_SURFACE = arrays.MESH_TIME_SURFACE
TIME_VOLUME = arrays.MESH_TIME_VOLUME
TIME_TOTAL = arrays.MESH_TIME_TOTAL
#: size growth deep inside (``grading``; 1.0 for the uniform meshes)
GRADING = arrays.MESH_GRADING
QUALITY_FIELDS = (
    MIN_DIHEDRAL,
    P1_DIHEDRAL,
    MIN_RADIUS_RATIO,
    P1_RADIUS_RATIO,
    N_TETS_REQUESTED,
    SURFACE_SPACING,
    SMOOTHING_SCALE,
    TIME_SURFACE,
    TIME_VOLUME,
    TIME_TOTAL,
    GRADING,
)


def tet_quality(points, tets):
    """Dihedral angles (degrees, (n, 6)), signed volumes and normalised radius ratios.

    The radius ratio is ``3 r_in / R_circ`` (1 for the regular tetrahedron, 0 for a
    degenerate one).

    Parameters
    ----------
    points : (n_points, 3) array
    tets : (n_tets, 4) int array

    Returns
    -------
    dihedral : (n_tets, 6) float array
    volume : (n_tets,) float array
    radius_ratio : (n_tets,) float array

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.meshing import tet_quality
    >>> p = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    >>> d, v, rr = tet_quality(p, np.array([[0, 1, 2, 3]]))
    >>> np.round(d, 2)[0, 0], round(float(rr[0]), 6)
    (np.float64(70.53), 1.0)
    """
    p = np.asarray(points, float)[np.asarray(tets)]
    a, b, c = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]
    volume = np.einsum("ij,ij->i", np.cross(a, b), c) / 6.0
    # outward normal of the face opposite each vertex
    opp = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))
    normals, areas = [], []
    for k, (i, j, l) in enumerate(opp):
        n = np.cross(p[:, j] - p[:, i], p[:, l] - p[:, i])
        flip = np.einsum("ij,ij->i", n, p[:, k] - p[:, i]) > 0
        n[flip] *= -1
        norm = np.linalg.norm(n, axis=1)
        areas.append(0.5 * norm)
        normals.append(n / np.maximum(norm, 1e-300)[:, None])
    dihedral = []
    for i in range(4):  # the edge (i, j) is shared by the faces opposite k and l
        for j in range(i + 1, 4):
            k, l = (m for m in range(4) if m not in (i, j))
            cos = np.einsum("ij,ij->i", normals[k], normals[l])
            dihedral.append(180.0 - np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
    r_in = 3.0 * np.abs(volume) / np.maximum(np.sum(areas, axis=0), 1e-300)
    num = (
        np.einsum("ij,ij->i", a, a)[:, None] * np.cross(b, c)
        + np.einsum("ij,ij->i", b, b)[:, None] * np.cross(c, a)
        + np.einsum("ij,ij->i", c, c)[:, None] * np.cross(a, b)
    )
    r_circ = np.linalg.norm(num, axis=1) / np.maximum(12.0 * np.abs(volume), 1e-300)
    return np.stack(dihedral, axis=1), volume, 3.0 * r_in / np.maximum(r_circ, 1e-300)


def _relocate_sliver_nodes(nodes, tets, free, worst, min_dihedral, rounds=3):
    """Move the interior nodes of the slivers below ``min_dihedral`` to better places.

    Each interior (not surface) node of a sliver is tried at 1, 1/2 and 1/4 of the way to
    the mean of its neighbours; a move is kept when the worst dihedral angle of the
    node's tetrahedra rises and none of them inverts. Only the few sliver nodes are
    visited (a handful after HXT's optimiser); surfaces and connectivity do not change.
    Returns the nodes and the updated worst angle per tetrahedron.
    """
    nodes = nodes.copy()
    worst = worst.copy()
    for _ in range(rounds):
        bad = np.flatnonzero(worst < min_dihedral)
        cand = np.unique(tets[bad])
        cand = cand[free[cand]]
        if not len(cand):
            break
        improved = False
        for v in cand:  # a handful of nodes, not a loop over the mesh
            ring = np.flatnonzero((tets == v).any(axis=1))
            neighbours = np.setdiff1d(np.unique(tets[ring]), [v])
            ring_d, ring_vol, _ = tet_quality(nodes, tets[ring])
            before = ring_d.min()
            sign = np.sign(ring_vol)  # orientation at the start: a move may not flip it
            start = nodes[v].copy()
            best, best_q = start, before
            # towards the neighbours' mean, or away from the face opposite the node in
            # its worst tetrahedron (to the height of a regular tetrahedron on it)
            worst_tet = tets[ring[np.argmin(ring_d.min(axis=1))]]
            face = nodes[worst_tet[worst_tet != v]]
            normal = np.cross(face[1] - face[0], face[2] - face[0])
            normal /= max(np.linalg.norm(normal), 1e-30)
            side = np.sign(np.dot(start - face.mean(axis=0), normal)) or 1.0
            edge = np.mean(np.linalg.norm(face - np.roll(face, 1, axis=0), axis=1))
            lifted = face.mean(axis=0) + side * np.sqrt(2.0 / 3.0) * edge * normal
            goals = [nodes[neighbours].mean(axis=0), lifted]
            for goal, t in itertools.product(goals, (1.0, 0.5, 0.25)):
                nodes[v] = start + t * (goal - start)
                d, vol, _ = tet_quality(nodes, tets[ring])
                if np.all(vol * sign > 0) and d.min() > best_q:
                    best, best_q = nodes[v].copy(), d.min()
            nodes[v] = best
            improved |= best_q > before
        touched = np.flatnonzero(np.isin(tets, cand).any(axis=1))
        worst[touched] = tet_quality(nodes, tets[touched])[0].min(axis=1)
        if not improved:
            break
    return nodes, worst

