"""Muscle share of each tetrahedron of a homogeneous mesh: the two baselines.

* :func:`sample_muscle_fraction` — paper 000's state of the art (Fig. 1): random points
  drawn uniformly inside every tetrahedron (barycentric coordinates from a flat Dirichlet
  distribution, all cells at once with numpy) are looked up in the label image (nearest
  voxel); the muscle share is the fraction of points that fall in muscle.
* :func:`average_voxels` — paper 001's per-tetrahedron average over the voxels whose
  centres lie inside the tetrahedron. The voxel-to-tetrahedron assignment is VTK's
  ``vtkProbeFilter`` (the image points are probed in the mesh, cell by cell); the averages
  are ``numpy.bincount`` sums. A tetrahedron that contains no voxel centre takes the value
  of the voxel at its centroid.

Both write ``arrays.MUSCLE_FRACTION`` (float64 in [0, 1]) and the dominant muscle id
``arrays.MUSCLE`` (uint8, 0 where the tetrahedron holds no muscle) on a copy of the grid;
``arrays.TISSUE`` is left as it is (``FAT`` on the homogeneous mesh of
:func:`pvcmf.filters.tetrahedralize` with ``conforming=False``). Material assignment
weights the properties by the fraction.
"""

from __future__ import annotations

import logging
import numbers
import time

import numpy as np
import pyvista as pv

from .. import arrays
from ..progress import Progress

log = logging.getLogger(__name__)

_N_IDS = len(arrays.MUSCLES) + 1
#: most sample points handled at once (memory ~ 100 bytes per point)
_CHUNK = 2_000_000


def _check_inputs(grid, labels):
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    if grid.n_cells == 0 or not np.all(grid.celltypes == pv.CellType.TETRA):
        raise ValueError(
            "grid must hold linear tetrahedra only (VTK_TETRA), got cell types "
            f"{sorted(set(np.asarray(grid.celltypes).tolist()))}"
        )
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    if not np.allclose(labels.direction_matrix, np.eye(3)):
        raise ValueError("labels must be axis aligned (identity direction_matrix)")
    tissue = arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu", producer="segment")
    muscle = arrays.require_array(
        labels, arrays.MUSCLE, "point", dtype="iu", producer="embed_muscles"
    )
    return np.asarray(tissue), np.asarray(muscle)


def _voxel_values(labels, tissue, muscle, points, relative=False):
    """(is_muscle, muscle id) of the voxel nearest to each point (outside: no muscle).

    ``relative``: the points are already relative to the image origin.
    """
    origin = 0.0 if relative else np.asarray(labels.origin)
    ijk = np.rint((points - origin) / np.asarray(labels.spacing, dtype=points.dtype)).astype(np.int64)
    dims = np.asarray(labels.dimensions)
    inside = np.all((ijk >= 0) & (ijk < dims), axis=-1)
    flat = ijk[..., 0] + dims[0] * (ijk[..., 1] + dims[1] * ijk[..., 2])
    flat = np.where(inside, flat, 0)
    is_muscle = inside & (tissue[flat] == arrays.MUSCLE_TISSUE)
    ids = np.where(is_muscle, muscle[flat], 0).astype(np.int64)
    return is_muscle, np.clip(ids, 0, _N_IDS - 1)


def _write(grid, fraction, id_counts):
    out = grid.copy()
    best = np.argmax(id_counts[:, 1:], axis=1) + 1
    dominant = np.where(id_counts[:, 1:].max(axis=1) > 0, best, 0)
    out.cell_data[arrays.MUSCLE_FRACTION] = fraction.astype(np.float64)
    out.cell_data[arrays.MUSCLE] = dominant.astype(np.uint8)
    if arrays.TISSUE not in out.cell_data.keys():
        out.cell_data[arrays.TISSUE] = np.full(out.n_cells, arrays.FAT, dtype=np.uint8)
    return out


def sample_muscle_fraction(grid, labels, *, n_points=100, seed=0, progress_bar=False):
    """Muscle share of every tetrahedron from random points (paper 000, Fig. 1).

    ``n_points`` points are drawn uniformly inside every tetrahedron (barycentric
    coordinates from a flat Dirichlet distribution) and looked up in the label image
    (nearest voxel, i.e. the voxel that contains the point). The share is the fraction of
    points in ``MUSCLE_TISSUE``; its error is about ``sqrt(f (1 - f) / n_points)``.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra (the homogeneous mesh, ``tetrahedralize(conforming=False)``).
    labels : pyvista.ImageData
        Label image with integer point arrays ``arrays.TISSUE`` and ``arrays.MUSCLE``.
    n_points : int, default 100
        Points per tetrahedron (the speed/accuracy knob).
    seed : int, default 0
        Seed of ``numpy.random.default_rng``.
    progress_bar : bool, default False
        Show the progress per chunk of points (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        Copy of ``grid`` with cell arrays ``arrays.MUSCLE_FRACTION`` (float64) and
        ``arrays.MUSCLE`` (uint8, the muscle with most points, 0 if none).

    Examples
    --------
    >>> from pvcmf import arrays
    >>> from pvcmf.filters import sample_muscle_fraction, tetrahedralize
    >>> from pvcmf.filters.meshing import shell_labels
    >>> labels = shell_labels(spacing=2.0)
    >>> grid = tetrahedralize(labels, n_tets=5_000, conforming=False)
    >>> out = sample_muscle_fraction(grid, labels, n_points=50)
    >>> bool(0 < out[arrays.MUSCLE_FRACTION].max() <= 1)
    True
    """
    tissue, muscle = _check_inputs(grid, labels)
    if isinstance(n_points, bool) or not isinstance(n_points, numbers.Integral) or n_points < 1:
        raise ValueError(f"n_points must be a positive integer, got {n_points!r}")
    t0 = time.perf_counter()
    rng = np.random.default_rng(seed)
    corners = np.asarray(grid.points, float)[grid.cells_dict[pv.CellType.TETRA]]  # (n, 4, 3)
    n = len(corners)
    corners32 = (corners - np.asarray(labels.origin)).astype(np.float32)  # image frame
    hits = np.zeros(n, dtype=np.int64)
    id_counts = np.zeros(n * _N_IDS, dtype=np.int64)
    per_chunk = max(1, _CHUNK // n)
    cell = np.arange(n)[:, None]
    done = 0
    bar = Progress(total=n_points, desc="sample_muscle_fraction", enabled=progress_bar,
                   unit="point", logger=log)
    while done < n_points:
        k = min(per_chunk, n_points - done)
        lam = rng.standard_exponential(size=(n, k, 4), dtype=np.float32)
        lam /= lam.sum(axis=2, keepdims=True)
        pts = np.einsum("nkj,njd->nkd", lam, corners32)
        is_muscle, ids = _voxel_values(labels, tissue, muscle, pts, relative=True)
        hits += is_muscle.sum(axis=1)
        id_counts += np.bincount((cell * _N_IDS + ids).ravel(), minlength=n * _N_IDS)
        done += k
        bar.step(f"{done} / {n_points} points per tetrahedron", n=k)
    bar.close()
    out = _write(grid, hits / n_points, id_counts.reshape(n, _N_IDS))
    log.info(
        "sample_muscle_fraction: %d tets x %d points in %.2f s", n, n_points, time.perf_counter() - t0
    )
    return out


def voxel_cells(grid, labels):
    """Index of the tetrahedron that contains each voxel centre (-1 outside the mesh).

    Delegates to VTK's ``vtkProbeFilter`` (image points probed in the mesh).

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
    labels : pyvista.ImageData

    Returns
    -------
    numpy.ndarray
        int64 array of length ``labels.n_points``.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.filters.fractions import voxel_cells
    >>> img = pv.ImageData(dimensions=(3, 3, 3), spacing=(0.5, 0.5, 0.5))
    >>> import numpy as np
    >>> tet = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]])},
    ...                           np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 2.0]]))
    >>> int((voxel_cells(tet, img) == 0).sum())  # x + y + z <= 2, faces included
    23
    """
    import vtk

    source = pv.UnstructuredGrid({pv.CellType.TETRA: grid.cells_dict[pv.CellType.TETRA]}, grid.points)
    source.cell_data[arrays.SCRATCH_CELL_ID] = np.arange(grid.n_cells, dtype=np.int64)
    result = np.full(labels.n_points, -1, dtype=np.int64)
    # probe only the block of voxels inside the mesh's bounding box
    dims = np.asarray(labels.dimensions)
    origin, spacing = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    b = np.asarray(grid.bounds, float).reshape(3, 2)
    lo = np.clip(np.ceil((b[:, 0] - origin) / spacing - 1e-9).astype(int), 0, dims - 1)
    hi = np.clip(np.floor((b[:, 1] - origin) / spacing + 1e-9).astype(int), 0, dims - 1)
    if np.any(hi < lo):
        return result
    probe = pv.ImageData(dimensions=hi - lo + 1, spacing=spacing, origin=origin + lo * spacing)
    f = vtk.vtkProbeFilter()
    f.SetInputData(probe)
    f.SetSourceData(source)
    f.Update()
    out = pv.wrap(f.GetOutput())
    cid = np.asarray(out.point_data[arrays.SCRATCH_CELL_ID]).astype(np.int64)
    valid = np.asarray(out.point_data[f.GetValidPointMaskArrayName()]).astype(bool)
    i, j, k = np.meshgrid(*(np.arange(lo[a], hi[a] + 1) for a in range(3)), indexing="ij")
    flat = (i + dims[0] * (j + dims[1] * k)).ravel(order="F")  # probe points, x fastest
    result[flat] = np.where(valid, cid, -1)
    return result


def average_voxels(grid, labels, *, progress_bar=False):
    """Muscle share of every tetrahedron averaged over the voxels inside it (paper 001).

    Every voxel centre is assigned to the tetrahedron that contains it; the share is the
    fraction of those voxels that are ``MUSCLE_TISSUE``. A tetrahedron without any voxel
    centre inside (smaller than a voxel) takes the voxel at its centroid.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra (the homogeneous mesh).
    labels : pyvista.ImageData
        Label image with integer point arrays ``arrays.TISSUE`` and ``arrays.MUSCLE``.
    progress_bar : bool, default False
        Show the step (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        Copy of ``grid`` with cell arrays ``arrays.MUSCLE_FRACTION`` (float64) and
        ``arrays.MUSCLE`` (uint8, the muscle with most voxels, 0 if none).

    Examples
    --------
    >>> from pvcmf import arrays
    >>> from pvcmf.filters import average_voxels, tetrahedralize
    >>> from pvcmf.filters.meshing import shell_labels
    >>> labels = shell_labels(spacing=2.0)
    >>> grid = tetrahedralize(labels, n_tets=5_000, conforming=False)
    >>> out = average_voxels(grid, labels)
    >>> bool(0 < out[arrays.MUSCLE_FRACTION].max() <= 1)
    True
    """
    tissue, muscle = _check_inputs(grid, labels)
    t0 = time.perf_counter()
    n = grid.n_cells
    cid = voxel_cells(grid, labels)
    inside = cid >= 0
    cells = cid[inside]
    is_muscle = tissue[inside] == arrays.MUSCLE_TISSUE
    ids = np.where(is_muscle, np.clip(muscle[inside].astype(np.int64), 0, _N_IDS - 1), 0)
    count = np.bincount(cells, minlength=n)
    hits = np.bincount(cells, weights=is_muscle, minlength=n)
    id_counts = np.bincount(cells * _N_IDS + ids, minlength=n * _N_IDS).reshape(n, _N_IDS)
    empty = np.flatnonzero(count == 0)
    if empty.size:
        centroid = np.asarray(grid.points, float)[grid.cells_dict[pv.CellType.TETRA][empty]].mean(axis=1)
        m, mid = _voxel_values(labels, tissue, muscle, centroid)
        count[empty] = 1
        hits[empty] = m
        id_counts[empty, mid] += 1
    out = _write(grid, hits / count, id_counts)
    with Progress(total=1, desc="average_voxels", enabled=progress_bar, logger=log) as bar:
        bar.step(f"{n} tets ({empty.size} without a voxel centre)")
    log.info(
        "average_voxels: %d tets (%d without a voxel centre) in %.2f s",
        n, empty.size, time.perf_counter() - t0,
    )
    return out
