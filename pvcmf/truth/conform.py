"""A surface-conforming mesh of the virtual patient's true soft tissue (gmsh).

The lattice mesher of :mod:`pvcmf.truth.independent` keeps a lattice tetrahedron by where
its corners fall and drops the ones across a gap thinner than the lattice, so the meshed
volume (and the bone surface the tissue is tied to) changes with the spacing. Here the
meshed domain is the same at every size:

* the soft tissue's region function (the exact level sets of
  :func:`pvcmf.truth.independent._region`, closed by the face box's coronal plane) is
  sampled on a regular grid of ``spacing`` mm and its zero set triangulated (VTK flying
  edges: a closed, manifold, self-intersection-free surface; sample values within a fifth
  of the spacing of zero are pushed off it, so that no triangle degenerates at a sample);
  the largest connected piece is the domain;
* gmsh fills it with tetrahedra (3-D Delaunay, the surface triangles kept, sizes
  interpolated from the surface inwards, optimised);
* the boundary nodes are moved onto the exact surfaces (Newton projection), each move
  undone where it would flatten a tetrahedron below a tenth of its volume;
* boundary kinds and muscle fractions as the lattice mesh
  (:func:`pvcmf.truth.independent.soft_tissue_mesh`), so the boundary model and the
  materials are the same functions of the position.

Delegates to VTK (flying edges, via pyvista), gmsh (volume mesh) and numpy.
"""

from __future__ import annotations

import logging
import os
import tempfile

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.model_region import face_box
from ..filters.osteotomy import voxel_points
from .anatomy import _warp
from .exact import _fields, _labelled_grid, _project, _region, _volumes

log = logging.getLogger("pvcmf.reference")

__all__ = ["conforming_mesh", "surface_spacing"]

#: tetrahedra of the conforming mesh of a face of :data:`_REF_VOLUME` mm^3 at a surface
#: spacing of :data:`_REF_SPACING` mm, and how the count grows as the spacing shrinks
#: (the surface holds most nodes: about spacing^-2.2); sets the spacing for ``n_tets``
_REF_TETS, _REF_SPACING, _REF_VOLUME, _EXPONENT = 22_700, 6.0, 875e3, 2.2


def surface_spacing(volume, n_tets):
    """Sampling spacing (mm) of the surface for about ``n_tets`` tetrahedra in a soft
    tissue of ``volume`` mm^3 (calibrated on virtual patient 1).

    Examples
    --------
    >>> from pvcmf.truth.conform import surface_spacing
    >>> round(surface_spacing(875e3, 22_700), 1)
    6.0
    """
    if n_tets <= 0 or volume <= 0:
        raise ValueError(f"n_tets and volume must be > 0, got {n_tets!r} and {volume!r}")
    return (_REF_SPACING * (_REF_TETS / n_tets) ** (1 / _EXPONENT)
            * (volume / _REF_VOLUME) ** (1 / 3))


def _surface(warp, lo, hi, y0, spacing):
    """Closed triangulated zero set of the soft tissue's region function, sampled at
    ``spacing`` over the box ``lo``-``hi`` and closed by the plane ``y = y0``."""
    axes = [np.arange(lo[i], hi[i] + spacing, spacing) for i in range(3)]
    img = pv.ImageData(dimensions=[len(a) for a in axes], spacing=(spacing,) * 3, origin=lo)
    p = np.asarray(img.points)
    r = np.empty(len(p))
    for i in range(0, len(p), 250_000):  # chunks bound the memory of the level sets
        r[i:i + 250_000] = _region(_fields(warp, p[i:i + 250_000]))[0]
    r = np.maximum(r, y0 - p[:, 1])
    eps = 0.2 * spacing
    img["r"] = np.where(np.abs(r) < eps, np.where(r < 0, -eps, eps), r)
    surf = img.contour([0.0], scalars="r", method="flying_edges")
    surf = surf.connectivity("largest")
    return pv.PolyData(np.asarray(surf.points), faces=surf.faces).clean()


def _gmsh_volume(surf):
    """gmsh's tetrahedra of the volume bounded by the closed triangle surface ``surf``:
    (points (n, 3), tets (m, 4))."""
    import gmsh

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "surface.stl")
        surf.save(path, binary=False)
        own = not gmsh.isInitialized()
        if own:
            gmsh.initialize(interruptible=False)
        try:
            gmsh.option.setNumber("General.Verbosity", 1)
            gmsh.option.setNumber("General.NumThreads", 1)
            gmsh.model.add("pvcmf_truth")
            gmsh.merge(path)
            faces = gmsh.model.getEntities(2)
            loop = gmsh.model.geo.addSurfaceLoop([tag for _, tag in faces])
            gmsh.model.geo.addVolume([loop])
            gmsh.model.geo.synchronize()
            gmsh.option.setNumber("Mesh.Optimize", 1)
            gmsh.model.mesh.generate(3)
            tags, coords, _ = gmsh.model.mesh.getNodes()
            _, nodes = gmsh.model.mesh.getElementsByType(4)
            gmsh.model.remove()
        finally:
            if own:
                gmsh.finalize()
    index = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    index[tags.astype(np.int64)] = np.arange(len(tags))
    tets = index[np.asarray(nodes, dtype=np.int64).reshape(-1, 4)]
    points = np.asarray(coords, dtype=float).reshape(-1, 3)
    used = np.unique(tets)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(len(used))
    return points[used], remap[tets]


def _soft_points(case, box):
    """The soft-tissue voxel centres in front of the face box's coronal plane and their
    volume (mm^3)."""
    soft = np.isin(np.asarray(case.truth[arrays.TISSUE]), arrays.SOFT_LABELS)
    pts = voxel_points(case.truth, np.flatnonzero(soft))
    pts = pts[pts[:, 1] >= box[2]]
    return pts, float(len(pts)) * float(np.prod(case.truth.spacing))


def _volume_mesh(surf):
    """gmsh's tetrahedra (positively oriented) of the volume bounded by ``surf``: points,
    tets and the ids of the boundary nodes."""
    x, tets = _gmsh_volume(surf)
    flip = _volumes(x, tets) < 0
    tets[flip] = tets[flip][:, [0, 2, 1, 3]]
    surface = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, x).extract_surface(
        pass_pointid=True, algorithm="dataset_surface")
    return x, tets, np.unique(np.asarray(surface.point_data[arrays.ORIGINAL_POINT_IDS]))


def _to_exact(warp, x, tets, nodes, spacing):
    """Boundary ``nodes`` projected onto the exact surfaces (at most ``spacing`` each);
    the projections that flatten a tetrahedron below a tenth of its volume undone."""
    y = x.copy()
    p = _project(warp, x[nodes], steps=4)
    ok = np.linalg.norm(p - x[nodes], axis=1) <= spacing
    y[nodes[ok]] = p[ok]
    v0 = _volumes(x, tets)
    for _ in range(100):  # undo rounds, each vectorised
        bad = _volumes(y, tets) < 0.1 * v0
        if not bad.any():
            break
        back = np.unique(tets[bad])
        y[back] = x[back]
    return y


def conforming_mesh(case, *, n_tets=20_000, spacing=None, face_fraction=0.5,
                    progress_bar=False):
    """The patient's true soft tissue meshed conforming to its surfaces (module doc).

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient.
    n_tets : int, default 20000
        About how many tetrahedra (sets ``spacing`` by :func:`surface_spacing`).
    spacing : float, optional
        Sampling spacing (mm) of the surface; overrides ``n_tets``.
    face_fraction : float, default 0.5
        Anterior share of the head that is meshed.
    progress_bar : bool, default False
        Unused (a few vectorised passes); kept for the common signature.

    Returns
    -------
    pyvista.UnstructuredGrid
        As :func:`pvcmf.truth.independent.soft_tissue_mesh`: linear tetrahedra with cell
        arrays ``tissue``, ``muscle``, ``muscle_fraction`` and point array ``boundary``.

    Examples
    --------
    >>> import pvcmf                                                            # doctest: +SKIP
    >>> from pvcmf.truth.conform import conforming_mesh                         # doctest: +SKIP
    >>> g = conforming_mesh(pvcmf.datasets.phantom(1, spacing=3.0), n_tets=8000)  # doctest: +SKIP
    """
    warp = _warp(case)
    box = face_box(case.truth, face_fraction)
    pts, volume = _soft_points(case, box)
    h = float(spacing) if spacing is not None else surface_spacing(volume, n_tets)
    if not h > 0:
        raise ValueError(f"spacing must be > 0, got {spacing!r}")
    lo, hi = pts.min(axis=0) - h, pts.max(axis=0) + h
    lo[1] = box[2] - 0.5 * h
    x, tets, on = _volume_mesh(_surface(warp, lo, hi, box[2], h))
    plane = on[np.abs(x[on, 1] - box[2]) < 1e-3 * h]
    free = np.setdiff1d(on, plane)
    x = _to_exact(warp, x, tets, free, h)
    grid = _labelled_grid(x, tets, free, plane, warp)
    log.info("conforming truth mesh: %d tetrahedra, surface sampled at %.2f mm, %d boundary "
             "nodes", grid.n_cells, h, len(on))
    return grid
