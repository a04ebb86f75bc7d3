"""The virtual patient's true anatomy as level sets, and a mesh's accuracy against it.

A virtual patient is the analytic atlas head (signed-distance shapes of
:mod:`pvcmf.atlas`) through a smooth invertible patient warp
(:mod:`pvcmf.datasets.template`). The *true* soft-tissue interfaces of patient ``p`` are
the zero sets of ``phi(T(x))``, ``phi`` an atlas signed distance and ``T`` the warp's
patient -> template map (:meth:`PatientWarp.inverse`, the map the soft tissue follows):
exact, with no voxel staircase.

* :func:`true_level_set` -> ``phi(T(x))`` of one structure (a facial muscle, the tongue,
  temporalis, neck muscles, the eyes, the skin) at patient points;
* :func:`interface_distance` -> distance (mm) of a labelled tetrahedral mesh's muscle
  interfaces (faces between a facial muscle and other soft tissue, and between generic
  muscle tissue and fat) to the true ones: the length of three Newton projections onto
  the zero set of ``f = phi o T`` (gradient by central differences);
* :func:`interface_distance_by_muscle` -> the facial-muscle distances per muscle;
* :func:`label_interface_distance` -> the same for the label image itself: its voxel
  faces between a facial muscle and other soft tissue (the staircase any mesher of the
  labels starts from), at their centres and corners;
* :func:`muscle_volume_errors` -> each facial muscle's mesh volume against the true volume
  of the muscle inside the same mesh (each tetrahedron near the muscle sampled at 20
  barycentric points).

Delegates to the atlas (analytic shapes), the warp, numpy and pyvista.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..atlas.muscles import _muscle_models
from ..atlas.soft_tissue import eyes_sdf, neck_muscles_sdf, skin_sdf, temporalis_sdf, tongue_sdf
from ..datasets import template

log = logging.getLogger("pvcmf.reference")

__all__ = ["GENERIC_MUSCLES", "interface_distance", "interface_distance_by_muscle",
           "label_interface_distance",
           "muscle_volume_errors", "true_level_set"]

#: the generic muscle tissue of the atlas (``tissue == MUSCLE_TISSUE``, no facial muscle id)
GENERIC_MUSCLES = {"tongue": tongue_sdf, "temporalis": temporalis_sdf,
                   "neck": neck_muscles_sdf}
_OTHER = {"eyes": eyes_sdf, "skin": skin_sdf, **GENERIC_MUSCLES}


def _warp(patient):
    """The patient warp of a patient number (1-4) or a Case (its ``parameters``)."""
    if getattr(patient, "parameters", None) is not None:  # a Case, e.g. of a cohort
        return template.PatientWarp(patient.parameters)
    if hasattr(patient, "patient"):
        patient = patient.patient
    return template.patient_warp(int(patient))


def true_level_set(patient, name, points):
    """``phi(T(x))``: an atlas signed distance at patient points (negative inside).

    Parameters
    ----------
    patient : int or pvcmf.datasets.Case
        Virtual patient (1-4, or a Case whose ``parameters`` define its warp).
    name : str
        A facial muscle of ``arrays.MUSCLES``, ``'tongue'``, ``'temporalis'``, ``'neck'``,
        ``'eyes'`` or ``'skin'``.
    points : array_like, shape (n, 3)
        Patient-frame points (mm).

    Returns
    -------
    numpy.ndarray
        ``(n,)`` float64, the atlas signed distance (mm, template frame) at ``T(x)``; zero
        on the true surface.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.truth.anatomy import true_level_set
    >>> true_level_set(1, "skin", np.array([[0.0, 0.0, 0.0], [0.0, 400.0, 0.0]])).tolist()[1] > 0
    True
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (n, 3), got {points.shape}")
    if name in arrays.MUSCLE_IDS:
        fn = _muscle_models()[name]
    elif name in _OTHER:
        fn = _OTHER[name]
    else:
        raise ValueError(f"name must be a muscle of arrays.MUSCLES or one of {sorted(_OTHER)}, "
                         f"got {name!r}")
    if len(points) == 0:
        return np.zeros(0)
    s = _warp(patient).inverse(points)
    return np.asarray(fn(tuple(s[:, i].astype(np.float32) for i in range(3))), dtype=float)


def _distance(patient, name, points, h=0.25, steps=3):
    """Distance (mm) to the zero set of ``f = phi o T``: the length of ``steps`` Newton
    projections ``x <- x - f grad f / |grad f|^2`` (gradient by central differences with
    step ``h``), exact to second order where ``f`` is smooth."""
    x = np.array(points, dtype=float)
    for _ in range(steps):  # a few Newton steps, each vectorised over the points
        f = true_level_set(patient, name, x)
        grad = np.column_stack([(true_level_set(patient, name, x + h * e)
                                 - true_level_set(patient, name, x - h * e)) / (2 * h)
                                for e in np.eye(3)])
        x = x - (f / np.maximum(np.einsum("ij,ij->i", grad, grad), 1e-12))[:, None] * grad
    return np.linalg.norm(x - points, axis=1)


def _internal_faces(tets):
    """(faces (k, 3), left cell, right cell) of the faces shared by two tetrahedra."""
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 2, 3]], tets[:, [0, 1, 3]],
                            tets[:, [0, 1, 2]]])
    owner = np.tile(np.arange(len(tets)), 4)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])
    key, owner, faces = key[order], owner[order], faces[order]
    same = np.all(key[1:] == key[:-1], axis=1)
    i = np.flatnonzero(same)
    return faces[i], owner[i], owner[i + 1]


def interface_distance(grid, patient):
    """Distances (mm) of a mesh's muscle interfaces to the patient's true ones.

    The sample points are the centroids and vertices of the internal faces between a cell
    of facial muscle ``m`` and a soft-tissue cell of another label (true interface: the
    muscle's surface, or the eye's where the muscle meets it), and between generic muscle
    tissue and fat (true interface: the nearest of the tongue, temporalis and neck
    surfaces). Faces between two facial muscles are left out.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh with cell arrays ``arrays.TISSUE`` and ``arrays.MUSCLE``
        (``tetrahedralize``), patient frame.
    patient : int or pvcmf.datasets.Case
        The virtual patient it was meshed from.

    Returns
    -------
    dict
        ``"muscle"`` and ``"generic"``: 1-D float arrays of distances (mm) at the sample
        points of each kind of interface.

    Examples
    --------
    >>> import pvcmf                                                         # doctest: +SKIP
    >>> from pvcmf.truth.anatomy import interface_distance                   # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)                        # doctest: +SKIP
    >>> d = interface_distance(pvcmf.filters.tetrahedralize(case.truth), 1)  # doctest: +SKIP
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    tets = np.asarray(grid.cells_dict[pv.CellType.TETRA], dtype=np.int64)
    muscle = np.asarray(arrays.require_array(grid, arrays.MUSCLE, "cell", dtype="iu", ncomp=1,
                                             producer="tetrahedralize"))
    tissue = np.asarray(arrays.require_array(grid, arrays.TISSUE, "cell", dtype="iu", ncomp=1,
                                             producer="tetrahedralize"))
    points = np.asarray(grid.points, dtype=float)
    faces, a, b = _internal_faces(tets)
    ma, mb = muscle[a], muscle[b]
    out = {}
    one = (ma > 0) != (mb > 0)  # exactly one side is a facial muscle
    m = np.where(ma > 0, ma, mb)[one]
    f = faces[one]
    samples = np.concatenate([points[f].mean(axis=1), points[f[:, 0]], points[f[:, 1]],
                              points[f[:, 2]]])
    ids = np.tile(m, 4)
    dist = np.full(len(samples), np.inf)
    for name, mid in arrays.MUSCLE_IDS.items():  # twelve muscles, vectorised inside
        sel = ids == mid
        if sel.any():
            dist[sel] = _distance(patient, name, samples[sel])
    dist = np.minimum(dist, _distance(patient, "eyes", samples))
    out["muscle"] = dist
    ta, tb = tissue[a], tissue[b]
    generic = (ma == 0) & (mb == 0) & (
        ((ta == arrays.FAT) & (tb == arrays.MUSCLE_TISSUE))
        | ((tb == arrays.FAT) & (ta == arrays.MUSCLE_TISSUE)))
    g = faces[generic]
    gs = np.concatenate([points[g].mean(axis=1), points[g[:, 0]], points[g[:, 1]],
                         points[g[:, 2]]]) if len(g) else np.zeros((0, 3))
    out["generic"] = (np.min([_distance(patient, name, gs) for name in GENERIC_MUSCLES], axis=0)
                      if len(gs) else np.zeros(0))
    return out


def interface_distance_by_muscle(grid, patient):
    """Distances (mm) of a mesh's facial-muscle interfaces to the true ones, per muscle.

    The samples of :func:`interface_distance`'s ``"muscle"`` distances (centroids and
    vertices of the faces between a facial muscle and other soft tissue), grouped by the
    muscle on the face.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh with cell array ``arrays.MUSCLE``, patient frame.
    patient : int or pvcmf.datasets.Case
        The virtual patient it was meshed from.

    Returns
    -------
    dict
        Muscle name (``arrays.MUSCLES`` order) -> 1-D float array of distances (mm);
        empty for a muscle the mesh lacks.
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    tets = np.asarray(grid.cells_dict[pv.CellType.TETRA], dtype=np.int64)
    muscle = np.asarray(arrays.require_array(grid, arrays.MUSCLE, "cell", dtype="iu", ncomp=1,
                                             producer="tetrahedralize"))
    points = np.asarray(grid.points, dtype=float)
    faces, a, b = _internal_faces(tets)
    one = (muscle[a] > 0) != (muscle[b] > 0)
    m = np.where(muscle[a] > 0, muscle[a], muscle[b])[one]
    f = faces[one]
    out = {}
    for name, mid in arrays.MUSCLE_IDS.items():  # twelve muscles, vectorised inside
        g = f[m == mid]
        x = np.concatenate([points[g].mean(axis=1), points[g].reshape(-1, 3)])
        out[name] = (np.minimum(_distance(patient, name, x), _distance(patient, "eyes", x))
                     if len(x) else np.zeros(0))
    return out


def label_interface_distance(labels, patient):
    """Distances (mm) of a label image's facial-muscle interfaces to the true ones.

    The interfaces are the voxel faces between a voxel of a facial muscle and a
    soft-tissue voxel (fat or muscle tissue) of no facial muscle; each is sampled at its centre and
    its four corners, and measured like :func:`interface_distance` (to the muscle's
    true surface, or the eyes' where nearer).

    Parameters
    ----------
    labels : pyvista.ImageData
        Axis-aligned label image with point arrays ``arrays.TISSUE`` and
        ``arrays.MUSCLE`` (e.g. a virtual patient's ``truth``).
    patient : int or pvcmf.datasets.Case
        The virtual patient the labels show.

    Returns
    -------
    dict
        ``"centres"`` and ``"corners"``: 1-D float arrays of distances (mm).

    Examples
    --------
    >>> import pvcmf                                                          # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)                         # doctest: +SKIP
    >>> d = label_interface_distance(case.truth, case)                        # doctest: +SKIP
    """
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    shape = tuple(labels.dimensions[::-1])
    tissue = np.asarray(arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu",
                                             producer="segment")).reshape(shape)
    muscle = np.asarray(arrays.require_array(labels, arrays.MUSCLE, "point", dtype="iu",
                                             producer="embed_muscles")).reshape(shape)
    soft = np.isin(tissue, arrays.SOFT_LABELS)
    origin, sp = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    centres, ids = [], []
    for ax in range(3):  # array axes z, y, x: faces between a voxel and the next one
        lo = tuple(slice(0, -1) if k == ax else slice(None) for k in range(3))
        hi = tuple(slice(1, None) if k == ax else slice(None) for k in range(3))
        ma, mb = muscle[lo], muscle[hi]
        hit = (ma != mb) & soft[lo] & soft[hi] & ((ma == 0) | (mb == 0))
        for mid in (ma, mb):  # the muscle on one side, other soft tissue on the other
            sel = hit & (mid > 0)
            iz, iy, ix = np.nonzero(sel)
            xyz = np.stack([ix, iy, iz], axis=1).astype(float)
            xyz[:, 2 - ax] += 0.5
            centres.append((origin + xyz * sp, 2 - ax))
            ids.append(mid[sel])
    out = {"centres": [], "corners": []}
    for (c, axis), m in zip(centres, ids):
        u, v = [k for k in range(3) if k != axis]
        corners = np.concatenate([c + 0.5 * (a * sp[u] * np.eye(3)[u] + b * sp[v] * np.eye(3)[v])
                                  for a in (-1, 1) for b in (-1, 1)])
        for key, pts, mm in (("centres", c, m), ("corners", corners, np.tile(m, 4))):
            d = np.full(len(pts), np.inf)
            for name, mid in arrays.MUSCLE_IDS.items():  # twelve muscles, vectorised inside
                sel = mm == mid
                if sel.any():
                    d[sel] = _distance(patient, name, pts[sel])
            out[key].append(np.minimum(d, _distance(patient, "eyes", pts)) if len(pts) else d)
    return {k: np.concatenate(v) for k, v in out.items()}


def _barycentric_samples(k=4):
    """Barycentric coordinates (m, 4) of ``k (k+1) (k+2) / 6`` points strictly inside a
    tetrahedron (a regular lattice, shifted off the faces)."""
    idx = np.array([(i, j, m) for i in range(k) for j in range(k - i) for m in range(k - i - j)],
                   dtype=float)
    lam = (idx + 0.25) / k
    return np.column_stack([lam, 1 - lam.sum(axis=1)])


def muscle_volume_errors(grid, patient):
    """Each facial muscle's mesh volume against its true volume inside the same mesh.

    The true volume of muscle ``m`` is the volume of ``{phi_m(T(x)) < 0}`` outside the eyes
    within the mesh, integrated over the tetrahedra within reach of the muscle (label ``m``
    or centroid within 1.5 edge lengths of its surface) at 20 interior barycentric points
    each.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh with cell array ``arrays.MUSCLE``, patient frame.
    patient : int or pvcmf.datasets.Case
        The virtual patient it was meshed from.

    Returns
    -------
    pandas.DataFrame
        One row per muscle: ``muscle``, ``true_mm3``, ``mesh_mm3``, ``error`` (relative,
        ``mesh / true - 1``).
    """
    import pandas as pd

    tets = np.asarray(grid.cells_dict[pv.CellType.TETRA], dtype=np.int64)
    muscle = np.asarray(arrays.require_array(grid, arrays.MUSCLE, "cell", dtype="iu", ncomp=1,
                                             producer="tetrahedralize"))
    p = np.asarray(grid.points, dtype=float)[tets]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]),
                           p[:, 3] - p[:, 0])) / 6
    edge = float(np.median(np.linalg.norm(p[:, 1] - p[:, 0], axis=1)))
    centroid = p.mean(axis=1)
    lam = _barycentric_samples()
    rows = []
    for name, mid in arrays.MUSCLE_IDS.items():  # twelve muscles, vectorised inside
        near = (muscle == mid) | (true_level_set(patient, name, centroid) < 1.5 * edge)
        q = np.einsum("sk,tkd->tsd", lam, p[near]).reshape(-1, 3)
        inside = ((true_level_set(patient, name, q) < 0)
                  & (true_level_set(patient, "eyes", q) >= 0)).reshape(-1, len(lam))
        true = float((vol[near] * inside.mean(axis=1)).sum())
        mesh = float(vol[muscle == mid].sum())
        rows.append({"muscle": name, "true_mm3": true, "mesh_mm3": mesh,
                     "error": mesh / true - 1 if true > 0 else np.nan})
    return pd.DataFrame(rows)
