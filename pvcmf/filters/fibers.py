"""Muscle fibre directions from oriented bounding boxes (paper 000, Fig. 3).

Each muscle of a label image (point array ``muscle``) or of a tetrahedral mesh (cell
array ``muscle``) is boxed by an oriented bounding box (OBB); the long axis of a box is the
fibre direction of every voxel/cell inside it. As in the paper, the masseter gets one box
and the other muscles two-level boxes: the muscle is split at the middle of its long axis
and each half gets its own box, whose long axis is the fibre direction of that half.

The OBB axes are the principal axes (PCA, :func:`numpy.linalg.eigh` of the weighted
covariance) of the voxel centres / cell centres (weighted by cell volume); its extent is
the range of the points along those axes. Cell sizes come from PyVista's
``compute_cell_sizes``; everything else is vectorised numpy.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..progress import Progress

log = logging.getLogger(__name__)

#: boxes per muscle kind: 1 = one OBB, 2 = two-level OBB (halves along the long axis)
DEFAULT_LEVELS = {kind: (1 if kind == "masseter" else 2) for kind in arrays.MUSCLE_KINDS}


def _canonical_sign(v):
    """Flip unit vectors (rows) so that they point superior (+z), else anterior, else left."""
    v = np.array(v, dtype=float)
    tol = 1e-9
    key = np.where(
        np.abs(v[..., 2]) > tol,
        v[..., 2],
        np.where(np.abs(v[..., 1]) > tol, v[..., 1], v[..., 0]),
    )
    return v * np.where(key < 0, -1.0, 1.0)[..., None]


def oriented_bounding_box(points, weights=None):
    """Oriented bounding box of a point set by principal component analysis.

    The axes are the eigenvectors of the (weighted) covariance of the points; the box
    spans the full range of the points along each axis, so every point lies inside.
    Axes are sorted by decreasing half-length (longest first: the fibre direction). The
    sign of each axis is deterministic: it points superior (+z), or anterior (+y) where
    its z component vanishes, else left (+x); the frame may therefore be left-handed.

    Parameters
    ----------
    points : array_like, shape (n, 3)
        At least 2 distinct points (e.g. voxel centres of one muscle).
    weights : array_like, shape (n,), optional
        Non-negative weights (e.g. cell volumes) for the covariance.

    Returns
    -------
    center : numpy.ndarray, shape (3,)
        Centre of the box (not the centroid of the points).
    axes : numpy.ndarray, shape (3, 3)
        Rows are the unit box axes, longest first.
    half_lengths : numpy.ndarray, shape (3,)
        Half-extents along ``axes``, decreasing.

    Raises
    ------
    ValueError
        If ``points`` is not ``(n, 3)``, has fewer than 2 points, non-finite values, or
        ``weights`` has the wrong shape or negative/zero total.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters import oriented_bounding_box
    >>> pts = np.random.default_rng(0).uniform(-1, 1, (2000, 3)) * [1, 10, 2]
    >>> center, axes, half = oriented_bounding_box(pts)
    >>> bool(abs(axes[0] @ [0, 1, 0]) > 0.99)
    True
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {pts.shape}")
    if len(pts) < 2:
        raise ValueError(f"points must hold at least 2 points, got {len(pts)}")
    if not np.isfinite(pts).all():
        raise ValueError("points must be finite, got NaN or infinite coordinates")
    if weights is None:
        w = np.full(len(pts), 1.0 / len(pts))
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (len(pts),) or (w < 0).any() or not np.isfinite(w).all() or w.sum() <= 0:
            raise ValueError(
                f"weights must be {len(pts)} finite non-negative numbers with a positive sum, "
                f"got shape {w.shape}"
            )
        w = w / w.sum()
    mean = w @ pts
    centred = pts - mean
    cov = (centred * w[:, None]).T @ centred
    _, vecs = np.linalg.eigh(cov)
    axes = _canonical_sign(vecs.T[::-1])  # rows, decreasing variance
    proj = centred @ axes.T
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    half = 0.5 * (hi - lo)
    order = np.argsort(-half, kind="stable")
    axes, half, mid = axes[order], half[order], (0.5 * (hi + lo))[order]
    center = mean + mid @ axes
    return center, axes, half


def obb_polydata(center, axes, half_lengths):
    """The box of :func:`oriented_bounding_box` as a hexahedral surface (for plotting).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.filters.fibers import obb_polydata
    >>> box = obb_polydata(np.zeros(3), np.eye(3), np.array([3.0, 2.0, 1.0]))
    >>> [float(b) for b in box.bounds]
    [-3.0, 3.0, -2.0, 2.0, -1.0, 1.0]
    """
    box = pv.Box(bounds=(-1, 1, -1, 1, -1, 1))
    local = np.asarray(box.points) * np.asarray(half_lengths)
    box.points = np.asarray(center) + local @ np.asarray(axes)
    return box


def _levels_for(levels):
    if levels is None:
        return {name: DEFAULT_LEVELS[_kind(name)] for name in arrays.MUSCLES}
    if isinstance(levels, (int, np.integer)) and not isinstance(levels, bool):
        if levels < 1:
            raise ValueError(f"levels must be >= 1, got {levels}")
        return dict.fromkeys(arrays.MUSCLES, int(levels))
    if isinstance(levels, dict):
        out = {name: DEFAULT_LEVELS[_kind(name)] for name in arrays.MUSCLES}
        for key, val in levels.items():
            targets = [n for n in arrays.MUSCLES if n == key or _kind(n) == key]
            if not targets:
                raise ValueError(
                    f"levels: unknown muscle {key!r}; expected a name of arrays.MUSCLES or a "
                    f"kind of arrays.MUSCLE_KINDS"
                )
            if not isinstance(val, (int, np.integer)) or val < 1:
                raise ValueError(f"levels[{key!r}] must be an int >= 1, got {val!r}")
            out.update(dict.fromkeys(targets, int(val)))
        return out
    raise TypeError(f"levels must be None, an int or a dict, got {type(levels).__name__}")


def _kind(name):
    for side in arrays.SIDES:
        if name.endswith("_" + side):
            return name[: -len(side) - 1]
    return name


def _split(points, weights, index, level):
    """Recursive OBB split: list of (index array, (center, axes, half)) leaves."""
    box = oriented_bounding_box(points[index], None if weights is None else weights[index])
    if level <= 1 or len(index) < 8:
        return [(index, box)]
    center, axes, _ = box
    s = (points[index] - center) @ axes[0]
    lo, hi = index[s < 0], index[s >= 0]
    if len(lo) < 2 or len(hi) < 2:
        return [(index, box)]
    return _split(points, weights, lo, level - 1) + _split(points, weights, hi, level - 1)


def _muscle_ids(dataset):
    """(association, muscle ids) of a label image or a mesh."""
    if isinstance(dataset, pv.ImageData):
        ids = arrays.require_array(
            dataset, arrays.MUSCLE, "point", dtype="iu", ncomp=1, producer="embed_muscles"
        )
        return "point", ids
    if isinstance(dataset, pv.UnstructuredGrid):
        ids = arrays.require_array(
            dataset, arrays.MUSCLE, "cell", dtype="iu", ncomp=1, producer="tetrahedralize"
        )
        return "cell", ids
    raise TypeError(
        f"dataset must be a pyvista.ImageData (label image) or UnstructuredGrid (mesh), "
        f"got {type(dataset).__name__}"
    )


def muscle_boxes(dataset, *, levels=None):
    """Leaf OBBs of every muscle present: ``{name: [(center, axes, half_lengths), ...]}``.

    Parameters
    ----------
    dataset : pyvista.ImageData or pyvista.UnstructuredGrid
        Label image with point array ``muscle`` or mesh with cell array ``muscle``.
    levels : None, int or dict
        Box levels: ``1`` one box, ``2`` the muscle split in two halves along its long
        axis (one box each), ``n`` recursively ``2**(n-1)`` boxes. ``None`` = paper 000:
        1 for the masseter, 2 for the others. A dict maps muscle names or kinds
        (``'masseter'``) to levels, others keep the default.

    Returns
    -------
    dict
        Muscle name -> list of boxes, in :data:`pvcmf.arrays.MUSCLES` order.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.fibers import muscle_boxes
    >>> img = pv.ImageData(dimensions=(20, 6, 4))
    >>> img[arrays.MUSCLE] = np.full(img.n_points, arrays.MUSCLE_IDS["masseter_left"], np.uint8)
    >>> [len(b) for b in muscle_boxes(img).values()]
    [1]
    """
    return {name: [box for _, box in leaves] for name, leaves in _leaves(dataset, levels).items()}


def _leaves(dataset, levels):
    assoc, ids = _muscle_ids(dataset)
    lv = _levels_for(levels)
    if assoc == "point":
        centres = np.asarray(dataset.points)
        weights = None
    else:
        centres = np.asarray(dataset.cell_centers().points)
        sizes = dataset.compute_cell_sizes(length=False, area=False, volume=True)
        weights = np.abs(np.asarray(sizes.cell_data["Volume"]))
        if weights.sum() <= 0:
            weights = None
    out = {}
    present = set(np.unique(ids).tolist()) - {arrays.MUSCLE_NONE}
    unknown = sorted(present - set(arrays.MUSCLE_IDS.values()))
    if unknown:
        raise ValueError(
            f"{assoc} array {arrays.MUSCLE!r} holds ids {unknown} that are not in "
            f"arrays.MUSCLE_IDS (1..{len(arrays.MUSCLES)})"
        )
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    for name in arrays.MUSCLES:
        mid = arrays.MUSCLE_IDS[name]
        if mid not in present:
            continue
        a, b = np.searchsorted(sorted_ids, [mid, mid + 1])
        index = order[a:b]
        if len(index) < 2:
            log.warning("muscle %s has %d %s(s); no fibre direction", name, len(index), assoc)
            continue
        out[name] = _split(centres, weights, index, lv[name])
    return out


def fiber_directions(dataset, *, levels=None, progress_bar=False):
    """Fibre direction of every muscle voxel or cell from oriented bounding boxes.

    Parameters
    ----------
    dataset : pyvista.ImageData or pyvista.UnstructuredGrid
        Label image with point array ``muscle`` (from ``embed_muscles``) or tetrahedral
        mesh with cell array ``muscle`` (from ``tetrahedralize``).
    levels : None, int or dict
        Boxes per muscle, see :func:`muscle_boxes`; default 1 for the masseter, 2 for the
        other muscles (paper 000, Fig. 3).
    progress_bar : bool
        Show the steps, one per muscle (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.ImageData or pyvista.UnstructuredGrid
        A copy with ``fiber`` ((n, 3) float64 unit vectors, zero outside muscle) as point
        data (image) or cell data (mesh). Directions point superior (see
        :func:`oriented_bounding_box`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> img = pv.ImageData(dimensions=(20, 6, 4))
    >>> img[arrays.MUSCLE] = np.full(img.n_points, arrays.MUSCLE_IDS["masseter_left"], np.uint8)
    >>> out = img.cmf.fiber_directions()
    >>> np.round(out[arrays.FIBER][0], 6).tolist()
    [1.0, 0.0, 0.0]
    """
    leaves = _leaves(dataset, levels)
    assoc, ids = _muscle_ids(dataset)
    fiber = np.zeros((len(ids), 3))
    with Progress(total=len(leaves), desc="fiber_directions", enabled=progress_bar,
                  logger=log) as bar:
        for name, parts in leaves.items():
            for index, (_, axes, _) in parts:
                fiber[index] = axes[0]
            bar.step(f"{name}: {len(parts)} box(es)")
    out = dataset.copy()
    if assoc == "point":
        out.point_data[arrays.FIBER] = fiber
    else:
        out.cell_data[arrays.FIBER] = fiber
    return out
