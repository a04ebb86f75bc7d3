"""The mesh -> skin transfer built in parts: the rows of ranges of points, then joined.

Row ``i`` of the transfer before its smoothing steps (``W0`` of
:class:`pvcmf.filters.surface_mapping.Transfer`) depends on point ``i`` alone (its
containing tetrahedron, or its feet on the boundary, their affine fit and the nodal
gradients at its nearest boundary nodes), so the rows of ranges of points located
against one :class:`~pvcmf.filters.transfer_locate.MeshIndex` (:func:`transfer_rows`),
stacked in order, equal ``Transfer(grid, points).W0`` bit for bit, and so do the
smoothing steps made from them once every range is there (:func:`join_rows`: the steps
need every point's distance to the mesh). The ranges can be built anywhere (two
processes, two threads) and in any order; :mod:`pvcmf.mtm.response_transfer` shares them
between the plan response's two cores.

Delegates to :class:`~pvcmf.filters.transfer_locate.Located`, the operator assembly of
:mod:`pvcmf.filters.surface_mapping`, :func:`~pvcmf.filters.transfer_smoothing.smoothing_steps`
and :mod:`scipy.sparse`.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import scipy.sparse as sp

from .surface_mapping import DEFAULT_K, _assemble_parts, _guided, _stacked_gradients
from .transfer_locate import Located, MeshIndex, resolve_band
from .transfer_smoothing import DEFAULT_ITERATIONS, rows_product, smoothing_steps

__all__ = ["MeshIndex", "Rows", "Joined", "ranges", "prepared_index", "transfer_rows",
           "join_rows", "CHUNK"]

#: points per range (small enough that two builders finish within a range of each other
#: and that a range's arrays of (point, foot) pairs, a dozen or more feet per point
#: outside the mesh, stay in the core's cache; large enough that the per-range overhead
#: stays a few percent)
CHUNK = 2048


def ranges(n, size=CHUNK):
    """``[(start, stop), ...]`` covering ``range(n)`` in pieces of ``size`` points.

    Examples
    --------
    >>> ranges(10, 4)
    [(0, 4), (4, 8), (8, 10)]
    """
    if isinstance(size, bool) or int(size) != size or size < 1:
        raise ValueError(f"size must be a positive integer, got {size!r}")
    return [(s, min(s + int(size), n)) for s in range(0, n, int(size))]


def _mesh_view(index):
    """What the operator assembly reads of the mesh, as a ``Located``-like view."""
    return SimpleNamespace(index=index, points=index.points, tets=index.tets,
                           boundary=index.boundary, gradients=index.gradients)


def prepared_index(grid):
    """:class:`~pvcmf.filters.transfer_locate.MeshIndex` of ``grid`` with everything
    :func:`transfer_rows` and :func:`join_rows` read of it made now (the boundary
    triangles' tree, the median edge, the nodal gradient operators): one pickle of it
    serves another process."""
    index = MeshIndex(grid)
    index.triangles  # noqa: B018 - made now
    index.median_edge  # noqa: B018
    _stacked_gradients(_mesh_view(index))
    return index


class Rows:
    """The transfer's rows of a range of points before the smoothing steps: ``W0`` (CSR,
    points x mesh nodes), ``inside``, ``dist``, and for the steps' guidance term the
    range's points with feet (``outside``, into the range) with their nearest boundary
    nodes and weights (``near``, ``near_w``)."""

    def __init__(self, W0, inside, dist, outside, near, near_w):
        self.W0, self.inside, self.dist = W0, inside, dist
        self.outside, self.near, self.near_w = outside, near, near_w


def transfer_rows(index, points, k=DEFAULT_K, band=None):
    """:class:`Rows` of ``points`` (``(n, 3)``) against ``index`` (a
    :class:`~pvcmf.filters.transfer_locate.MeshIndex`): the rows
    :class:`~pvcmf.filters.surface_mapping.Transfer` gives these points before its
    smoothing steps, with its ``k`` and ``band`` (None: :func:`~pvcmf.filters.transfer_locate.mesh_band` of ``index``)."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {p.shape}")
    band = resolve_band(band, index)
    loc = Located(None, p, int(k), reach=2.0 * float(band), index=index)
    W0, _ = _assemble_parts(loc, float(band), 0)
    return Rows(W0, loc.inside, loc.dist, loc.outside, loc.near, loc.near_w)


class Joined:
    """What :class:`~pvcmf.filters.surface_mapping.Transfer` holds, from :func:`join_rows`:
    ``W0``, ``steps``, ``inside``, ``distance``, ``modelled``, ``band`` and ``W`` (the
    smoothed transfer, made on first use); ``product``: ``W0 @`` each block of ``right``
    where :func:`join_rows` was given ``right`` (a list; else None)."""

    def __init__(self, W0, steps, inside, distance, band, product=None):
        self.W0, self.steps, self.inside, self.distance = W0, steps, inside, distance
        self.band = band
        self.modelled = distance <= band
        self.product = product
        self._W = None

    @property
    def W(self):
        if self._W is None:
            self._W = self.W0 if self.steps is None else self.steps.apply(self.W0)
        return self._W


def join_rows(index, points, parts, band=None, smoothing=DEFAULT_ITERATIONS, threads=1,
              right=None):
    """The transfer of ``points`` from the :class:`Rows` of consecutive ranges ``parts``
    (in order, covering every point): ``W0`` stacked, and the smoothing steps made once
    (:func:`~pvcmf.filters.transfer_smoothing.smoothing_steps`; ``threads``: threads of its
    neighbour search). ``right``: a list of dense ``(n_mesh_points, c)`` arrays (column
    blocks); ``W0 @`` each (:func:`~pvcmf.filters.transfer_smoothing.rows_product`) is
    made on a second thread while the steps are made (``Joined.product``, a list).
    ``band``: as :func:`transfer_rows`'s. Returns :class:`Joined`."""
    p = np.asarray(points, dtype=float)
    band = resolve_band(band, index)
    sizes = [len(r.inside) for r in parts]
    if sum(sizes) != len(p):
        raise ValueError(f"parts must cover the {len(p)} points, got {sum(sizes)} rows")
    W0 = sp.vstack([r.W0 for r in parts], format="csr")
    if right is not None:
        if not isinstance(right, (list, tuple)) or not right:
            raise ValueError(f"right must be a non-empty list of arrays, got "
                             f"{type(right).__name__}")
        right = [np.asarray(r) for r in right]
        if any(r.ndim != 2 or r.shape[0] != W0.shape[1] for r in right):
            raise ValueError(f"right must hold arrays of {W0.shape[1]} rows (mesh points), "
                             f"got {[r.shape for r in right]}")
    inside = np.concatenate([r.inside for r in parts])
    dist = np.concatenate([r.dist for r in parts])
    pool = product = None
    if right is not None:  # the products beside the steps (their kernel releases the GIL)
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(1, thread_name_prefix="pvcmf-product")
        product = pool.submit(lambda: [rows_product(W0, r, 1) for r in right])
    try:
        steps = _steps(index, p, parts, dist, band, smoothing, threads, sizes)
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    return Joined(W0, steps, inside, dist, float(band),
                  None if product is None else product.result())


def _steps(index, p, parts, dist, band, smoothing, threads, sizes):
    """The smoothing steps of the joined rows (None where none move a point)."""
    offset = np.cumsum([0] + sizes[:-1])
    has = [i for i, r in enumerate(parts) if len(r.outside)]
    if not (has and smoothing):
        return None
    loc = _mesh_view(index)
    loc.p = p
    loc.outside = np.concatenate([parts[i].outside + offset[i] for i in has])
    loc.near = np.concatenate([parts[i].near for i in has])
    loc.near_w = np.concatenate([parts[i].near_w for i in has])
    D = _stacked_gradients(loc)
    guide = lambda rows, o: _guided(loc, rows, o, D, factors=True)  # noqa: E731
    return smoothing_steps(p, dist, float(band), index.median_edge, guide,
                           iterations=int(smoothing), threads=threads)
