"""A lower bound on the crumple violations that no mesh -> skin extension can avoid.

:func:`pvcmf.filters.surface_mapping.crumple_metric` counts the skin edges that the mapped
displacement stretches beyond the steepest tetrahedron around them. Inside the mesh the
mapping is the finite-element interpolation, fixed; outside, it is an extension that
could be chosen otherwise. :func:`unavoidable_crumples` tells the violations that belong
to the mesh and its solution (any extension has them) from those of the extension: a
Lipschitz-extension argument on the skin's edge graph, with shortest paths from
:func:`scipy.sparse.csgraph.dijkstra` and patches from
:func:`scipy.sparse.csgraph.connected_components`.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from .. import arrays
from .surface_mapping import DEFAULT_FLOOR, DEFAULT_K, Transfer, _edge_limits

__all__ = ["unavoidable_crumples"]


def unavoidable_crumples(skin_pre, grid, u_nodes, *, k=DEFAULT_K, band=None, slack=0.1,
                         floor=DEFAULT_FLOOR, transfer=None, modelled=None):
    """A lower bound on the crumple violations of *any* extension of the mesh's field.

    The skin points inside the mesh take the finite-element interpolation, so their values
    are fixed; a point outside may take any value. An edge violates
    (:func:`~pvcmf.filters.surface_mapping.crumple_metric`) when its jump exceeds ``w = max((1 + slack) bound, floor)``
    times its length. Along a path of edges ``|u_a - u_b|`` is at most the sum of the
    ``w``: if two fixed points ``a, b`` joined through outside points only have
    ``e . (u_b - u_a)`` above the shortest such path (for a unit vector ``e``), some edge on
    every such path violates, whatever the outside values. Counted: edges between two
    fixed points that violate, plus the connected patches of outside points with such a
    pair on their rim (one violation each at least). Shortest paths:
    :func:`scipy.sparse.csgraph.dijkstra` from a super source joined to the rim points
    with the weight ``e . u_a`` (13 directions, both signs).

    Parameters
    ----------
    skin_pre, grid, u_nodes, k, band, slack, floor, transfer, modelled
        As :func:`~pvcmf.filters.surface_mapping.crumple_metric` (``transfer`` fixes which points lie inside the mesh
        and the tetrahedra around every point).

    Returns
    -------
    dict
        ``arrays.CRUMPLE_UNAVOIDABLE`` (the lower bound), ``"inside_edges"`` (violating
        edges between two fixed points), ``"patches"`` (patches of outside points that
        must hold a violation) and ``"points"`` (bool per point: in such a patch).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.crumple_bound import unavoidable_crumples
    >>> grid = pv.ImageData(dimensions=(6, 6, 6)).triangulate()
    >>> u = 0.1 * grid.points                                   # an affine field
    >>> skin = pv.Sphere(radius=3.0, center=(2.5, 2.5, 2.5))    # partly outside
    >>> unavoidable_crumples(skin, grid, u)[arrays.CRUMPLE_UNAVOIDABLE]
    0
    """
    if transfer is None:
        transfer = Transfer(grid, skin_pre.points, k=k, band=band)
    e, length, limit, modelled, _ = _edge_limits(skin_pre, grid, u_nodes, k, band, transfer,
                                                 modelled)
    loc, n = transfer._loc, skin_pre.n_points
    u_nodes = np.asarray(u_nodes, dtype=float)
    fixed = loc.inside
    val = np.zeros((n, 3))
    ins = np.flatnonzero(fixed)
    val[ins] = np.einsum("pa,pac->pc", loc.bary[ins], u_nodes[loc.tets[loc.cell[ins]]])
    w = np.maximum(np.maximum((1.0 + slack) * limit, floor) * length, 1e-300)
    both = fixed[e].all(axis=1)
    jump = np.linalg.norm(val[e[both, 0]] - val[e[both, 1]], axis=1)
    inside_edges = int(np.sum(jump > w[both]))
    e, w = e[~both], w[~both]
    free_free = ~fixed[e].any(axis=1)
    ff = e[free_free]
    graph = sp.coo_matrix((np.ones(len(ff)), (ff[:, 0], ff[:, 1])), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    rim = e[~free_free]  # (fixed a, free v) after ordering
    flip = fixed[rim[:, 1]]
    rim = np.where(flip[:, None], rim[:, ::-1], rim)
    wr = w[~free_free]
    # nodes: 0..n-1 the points (a fixed point only as a start), n..2n-1 fixed points as
    # ends, 2n the super source
    rows = np.concatenate([ff[:, 0], ff[:, 1], rim[:, 0], rim[:, 1]])
    cols = np.concatenate([ff[:, 1], ff[:, 0], rim[:, 1], n + rim[:, 0]])
    wts = np.concatenate([w[free_free], w[free_free], wr, wr])
    starts = np.unique(rim[:, 0])
    flagged = np.zeros(n, dtype=bool)
    axes = np.array([v for v in np.ndindex(3, 3, 3) if v != (1, 1, 1)], dtype=float) - 1.0
    axes = axes[: len(axes) // 2]  # 13 directions, one of each +- pair
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    scale = float(np.abs(val).max(initial=0.0)) + 1.0
    for direction in np.concatenate([axes, -axes]) if len(starts) else []:
        phi = val @ direction
        base = phi[starts].min() - scale  # keeps the source's weights positive
        g = sp.csr_matrix((np.concatenate([wts, phi[starts] - base]),
                           (np.concatenate([rows, np.full(len(starts), 2 * n)]),
                            np.concatenate([cols, starts]))), shape=(2 * n + 1, 2 * n + 1))
        dist = dijkstra(g, directed=True, indices=2 * n) + base
        conflict = phi[rim[:, 0]] > dist[rim[:, 1]] + wr + 1e-9 * scale
        flagged[np.isin(comp, comp[rim[conflict, 1]])] = True
    flagged &= ~fixed
    patches = int(len(np.unique(comp[flagged])))
    return {arrays.CRUMPLE_UNAVOIDABLE: inside_edges + patches, "inside_edges": inside_edges,
            "patches": patches, "points": flagged}
