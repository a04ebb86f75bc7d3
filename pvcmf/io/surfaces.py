"""Skin surfaces for planning software: STL, OBJ, PLY, VTP and VTK, chosen by extension.

:func:`write_surface` writes a (triangulated) surface atomically (temporary file in the
same folder + ``os.replace``); :func:`read_surface` reads one back as a
:class:`pyvista.PolyData`. Both delegate to VTK's readers and writers through PyVista
(``vtkSTLWriter`` binary, ``vtkOBJWriter``, ``vtkPLYWriter`` binary, XML ``.vtp``), which
keep every point in its order. STL stores triangle corners (float32) only: readers merge
coincident corners back into points (:func:`read_surface` does), which gives the same set
of points, ordered as the triangles first use them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from .._atomic import atomic_path

__all__ = ["SURFACE_FORMATS", "read_surface", "write_surface"]

#: extensions :func:`write_surface` and :func:`read_surface` accept
SURFACE_FORMATS = (".stl", ".obj", ".ply", ".vtp", ".vtk")


def _suffix(path, name="path"):
    suffix = Path(path).suffix.lower()
    if suffix not in SURFACE_FORMATS:
        raise ValueError(f"{name} must end in one of {', '.join(SURFACE_FORMATS)}, "
                         f"got {str(path)!r}")
    return suffix


def write_surface(surface, path, *, binary=True):
    """Write a surface (e.g. the predicted skin) for planning software.

    Parameters
    ----------
    surface : pyvista.DataSet
        Surface; non-PolyData is reduced to its outer surface, polygons are triangulated
        for STL (which stores triangles only).
    path : str or pathlib.Path
        Output file; its extension chooses the format: ``.stl``, ``.obj``, ``.ply``,
        ``.vtp`` or ``.vtk``. Point arrays are kept in VTP/VTK; PLY keeps the points and
        faces (and colours), STL and OBJ the geometry only. Units stay millimetres.
    binary : bool, default True
        Binary STL/PLY (smaller); ``False`` writes ASCII.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import tempfile, pathlib, pyvista as pv
    >>> from pvcmf.io import read_surface, write_surface
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "skin.ply"
    >>> read_surface(write_surface(pv.Sphere(), path)).n_points == pv.Sphere().n_points
    True
    """
    if not isinstance(surface, pv.DataSet):
        raise TypeError(f"surface must be a pyvista dataset, got {type(surface).__name__}")
    if surface.n_points == 0:
        raise ValueError("surface must have points, got an empty dataset")
    path = Path(path)
    suffix = _suffix(path)
    poly = surface if isinstance(surface, pv.PolyData) else surface.extract_surface(
        algorithm="dataset_surface")
    if suffix == ".stl":
        poly = poly.triangulate()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:  # keeps the suffix: VTK picks the writer by it
        poly.save(tmp, binary=binary)
    return path


def read_surface(path):
    """Read a surface written by :func:`write_surface` (or any STL/OBJ/PLY/VTP/VTK file).

    Parameters
    ----------
    path : str or pathlib.Path
        Surface file.

    Returns
    -------
    pyvista.PolyData
        The surface; STL's repeated triangle corners merged back into shared points (in
        the order the triangles first use them: the same set of points as written).

    Examples
    --------
    >>> import tempfile, pathlib, pyvista as pv
    >>> from pvcmf.io import read_surface, write_surface
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "skin.stl"
    >>> read_surface(write_surface(pv.Sphere(), path)).n_points
    842
    """
    path = Path(path)
    suffix = _suffix(path)
    if not path.exists():
        raise FileNotFoundError(f"surface file not found: {path}")
    mesh = pv.read(path)
    if not isinstance(mesh, pv.PolyData):
        mesh = mesh.extract_surface(algorithm="dataset_surface")
    if suffix == ".stl":
        mesh = _merge_corners(mesh)
    return mesh


def _merge_corners(mesh):
    """Merge exactly coincident points, keeping the order of first occurrence."""
    pts = np.asarray(mesh.points)
    _, first, inverse = np.unique(pts, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    new_index = rank[inverse.ravel()]
    faces = np.asarray(mesh.faces).reshape(-1, 4)  # STL: triangles only
    faces = np.column_stack([faces[:, :1], new_index[faces[:, 1:]]])
    return pv.PolyData(pts[first[order]], faces=faces.ravel())
