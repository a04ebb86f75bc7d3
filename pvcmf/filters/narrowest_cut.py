"""The narrowest cut through a voxel mask between two sets of its voxels.

Two bones that touch in a scan (a condyle in its fossa when the joint space is lost to
thick slices, partial volume or arthrosis; teeth in contact) are joined through the
narrowest passages of the hard tissue: :func:`narrowest_cut` finds the set of voxel faces of
least total area (mm^2) whose removal separates the ``source`` voxels from the ``sink``
voxels of a mask, a minimum s-t cut on the graph of the mask's voxels, each pair of
face-neighbours joined by an edge of capacity the shared face's area (anisotropic voxels
weigh each direction by its own face area). The cut follows the anatomy's necks whatever
the bones' thickness, where an erosion would first break thin cortical bone into pieces.

Delegates the maximum flow to :func:`scipy.sparse.csgraph.maximum_flow` (Dinic's
algorithm) and the source side, the voxels the residual graph still reaches from the
source, to :func:`scipy.sparse.csgraph.breadth_first_order`; the graph is built with numpy
(no loop over voxels).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, maximum_flow

log = logging.getLogger(__name__)

__all__ = ["narrowest_cut"]

#: integer capacity of the smallest voxel face (the flow's integer units); larger faces
#: are scaled by their area ratio
FACE_UNITS = 20


def narrowest_cut(mask, source, sink, spacing=(1.0, 1.0, 1.0)):
    """Split ``mask`` into the source's side and the rest along the cut of least area.

    Parameters
    ----------
    mask : numpy.ndarray
        3-D boolean voxel mask (6-connected through shared faces).
    source, sink : numpy.ndarray
        Boolean masks of the same shape: voxels that must end on either side (only their
        voxels inside ``mask`` count; a voxel in both is a source voxel).
    spacing : sequence of 3 float
        Voxel size (mm) along each axis: a face's area is the product of the other two.

    Returns
    -------
    side : numpy.ndarray
        Boolean mask of the voxels of ``mask`` on the source's side of the cut (a new
        array).
    area : float
        Area (mm^2) of the cut: 0 where nothing joins source and sink.

    Raises
    ------
    ValueError
        If the masks are not 3-D of one shape, or ``spacing`` is not 3 positive sizes.

    Examples
    --------
    Two 4 x 4 x 4 blocks joined by a 1 x 2 x 1 neck of voxels 1 x 1 x 2 mm: the cut
    crosses the neck, two faces of 1 x 2 mm.

    >>> import numpy as np
    >>> from pvcmf.filters.narrowest_cut import narrowest_cut
    >>> m = np.zeros((9, 4, 4), bool)
    >>> m[:4] = m[5:] = True
    >>> m[4, :2, 0] = True
    >>> s, t = np.zeros_like(m), np.zeros_like(m)
    >>> s[0], t[-1] = True, True
    >>> side, area = narrowest_cut(m, s, t, (1.0, 1.0, 2.0))
    >>> int(side.sum()), area
    (64, 4.0)
    """
    mask, source, sink = (np.asarray(a, dtype=bool) for a in (mask, source, sink))
    if mask.ndim != 3 or source.shape != mask.shape or sink.shape != mask.shape:
        raise ValueError(f"narrowest_cut: mask, source and sink must be 3-D arrays of one "
                         f"shape, got {mask.shape}, {source.shape} and {sink.shape}")
    spacing = np.asarray(spacing, dtype=float)
    if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise ValueError(f"narrowest_cut: spacing must be 3 positive sizes (mm), got "
                         f"{spacing.tolist()}")
    src, snk = source & mask, sink & mask & ~source
    if not src.any() or not snk.any():
        return src.copy(), 0.0
    index = np.full(mask.shape, -1, dtype=np.int64)
    n = int(np.count_nonzero(mask))
    index[mask] = np.arange(n)
    graph, unit = _graph(mask, index, src, snk, spacing)
    flow = maximum_flow(graph, n, n + 1, method="dinic")
    residual = graph - flow.flow
    residual.data = (residual.data > 0).astype(np.int8)
    residual.eliminate_zeros()
    reached = breadth_first_order(residual, n, directed=True, return_predecessors=False)
    on_side = np.zeros(n + 2, dtype=bool)
    on_side[reached] = True
    side = np.zeros(mask.shape, dtype=bool)
    side[mask] = on_side[:n]
    area = float(flow.flow_value) / unit
    log.debug("narrowest_cut: %d of %d voxels on the source's side, cut %.1f mm^2",
              int(side.sum()), n, area)
    return side, area


def _graph(mask, index, src, snk, spacing):
    """Capacities (CSR, int32) of the voxels' face graph plus a source (node n) joined to
    ``src`` and a sink (node n + 1) joined to ``snk`` by edges no cut can afford; and the
    capacity of one mm^2."""
    areas = np.array([spacing[1] * spacing[2], spacing[0] * spacing[2],
                      spacing[0] * spacing[1]])
    unit = FACE_UNITS / float(areas.min())
    n = int(index.max()) + 1
    rows, cols, caps = [], [], []
    for axis in range(3):
        lo = tuple(slice(0, -1) if a == axis else slice(None) for a in range(3))
        hi = tuple(slice(1, None) if a == axis else slice(None) for a in range(3))
        both = mask[lo] & mask[hi]
        i, j = index[lo][both], index[hi][both]
        cap = np.full(len(i), int(round(areas[axis] * unit)), dtype=np.int64)
        rows += [i, j]
        cols += [j, i]
        caps += [cap, cap]
    # no cut may cross a terminal edge: more than every face of the mask together
    sure = int(sum(int(c.sum()) for c in caps[::2])) + 1
    if sure >= np.iinfo(np.int32).max:
        raise ValueError(f"narrowest_cut: the mask's faces ({sure - 1} capacity units) "
                         "exceed 32-bit capacities")
    s, t = index[src], index[snk]
    rows += [np.full(len(s), n), t]
    cols += [s, np.full(len(t), n + 1)]
    caps += [np.full(len(s), sure), np.full(len(t), sure)]
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    # maximum_flow wants each edge's reverse stored too (zero capacity where one-way)
    rows, cols = np.concatenate([rows, cols]), np.concatenate([cols, rows])
    caps = np.concatenate(caps + [np.zeros(len(np.concatenate(caps)), dtype=np.int64)])
    graph = sparse.csr_matrix((caps.astype(np.int32), (rows, cols)), shape=(n + 2, n + 2))
    graph.sum_duplicates()
    return graph, unit
