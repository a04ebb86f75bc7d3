"""Model exports: Abaqus/CalculiX ``.inp``, FEBio ``.feb`` and meshio-readable meshes.

:func:`export` picks the format from the file's extension:

``.inp``
    Abaqus / CalculiX deck of the MTM problem (:func:`write_inp`): solved by ``ccx`` it
    reproduces :func:`pvcmf.mtm.solve` (:func:`run_calculix` runs it).
``.feb``
    FEBio 4.0 model of the same problem (:func:`write_feb`).
``.vtu``, ``.vtk``, ``.xdmf``, ``.msh``, ``.med``, ``.mesh``, ... (any meshio format)
    The grid through :func:`write_mesh` (meshio): points, cells, and every numeric point,
    cell and field array, so that ``meshio.read`` (and ParaView, gmsh, ...) read it back.

In every export grid point ``i`` is node ``i + 1`` and cell ``j`` is element ``j + 1`` (the
meshio formats keep VTK's 0-based order). Delegates to meshio and :mod:`xml.etree`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..._atomic import atomic_path
from .abaqus import calculix_available, read_calculix_dat, run_calculix, write_inp
from .febio import FEB_VERSION, write_feb

log = logging.getLogger(__name__)

__all__ = ["export", "check_export", "write_mesh", "write_inp", "write_feb", "run_calculix",
           "read_calculix_dat", "calculix_available", "FEB_VERSION", "WRITERS"]

#: extension -> writer of the solver formats; any other extension meshio knows goes to
#: :func:`write_mesh`
WRITERS = {".inp": write_inp, ".feb": write_feb}


def _numeric(name, values, where):
    arr = np.asarray(values)
    if arr.dtype.kind in "biuf":
        return arr
    log.info("write_mesh: %s array %r (dtype %s) is not numeric; meshio cannot hold it, "
             "left out", where, name, arr.dtype)
    return None


def write_mesh(dataset, path, *, file_format=None, binary=True):
    """Write a PyVista dataset with meshio, so that ``meshio.read(path)`` reads it back.

    VTK's own writers store string field data (e.g. ``landmark_names``) as
    ``type="String"`` arrays that meshio refuses ("Illegal data type 'String'"). Here only
    numeric arrays are written (string arrays are left out and logged); point data,
    cell data (one block per cell type) and field data keep their names.

    Parameters
    ----------
    dataset : pyvista.DataSet
        An UnstructuredGrid or PolyData (anything ``pyvista.to_meshio`` converts); other
        datasets are cast to an UnstructuredGrid first.
    path : str or pathlib.Path
        Output file; the format comes from its extension unless ``file_format`` is given.
    file_format : str, optional
        A meshio format name (``"vtu"``, ``"xdmf"``, ``"gmsh"``, ...).
    binary : bool
        Binary where the format has a choice (VTU: zlib-compressed base64).

    Returns
    -------
    pathlib.Path

    Examples
    --------
    >>> import os, tempfile, numpy as np, pyvista as pv, meshio
    >>> from pvcmf.io import write_mesh
    >>> grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    >>> grid.field_data["landmark_names"] = np.array(["nasion", "pogonion"])
    >>> grid.point_data["u"] = np.ones((grid.n_points, 3))
    >>> path = write_mesh(grid, os.path.join(tempfile.mkdtemp(), "grid.vtu"))
    >>> mesh = meshio.read(path)
    >>> mesh.points.shape, sorted(mesh.point_data)
    ((27, 3), ['u'])
    """
    import meshio
    import pyvista as pv

    if not isinstance(dataset, (pv.UnstructuredGrid, pv.PolyData)):
        if not hasattr(dataset, "cast_to_unstructured_grid"):
            raise TypeError(f"dataset must be a pyvista.DataSet, got {type(dataset).__name__}")
        dataset = dataset.cast_to_unstructured_grid()
    grid = dataset if isinstance(dataset, pv.UnstructuredGrid) else \
        dataset.cast_to_unstructured_grid()
    points = np.asarray(grid.points, dtype=float)
    types = np.asarray(grid.celltypes)
    conn = np.asarray(grid.cell_connectivity)
    offsets = np.asarray(grid.cell_offsets if hasattr(grid, "cell_offsets") else grid.offset)
    blocks, order = [], []
    for vtk_type in dict.fromkeys(types.tolist()):  # first-appearance order
        name = meshio._vtk_common.vtk_to_meshio_type.get(int(vtk_type))
        if name is None:
            raise ValueError(f"write_mesh: VTK cell type {vtk_type} has no meshio equivalent")
        idx = np.flatnonzero(types == vtk_type)
        size = int(offsets[idx[0] + 1] - offsets[idx[0]])
        cells = conn[offsets[idx][:, None] + np.arange(size)[None, :]]
        blocks.append(meshio.CellBlock(name, cells))
        order.append(idx)
    point_data = {k: v for k in grid.point_data.keys()
                  if (v := _numeric(k, grid.point_data[k], "point")) is not None}
    cell_data = {}
    for k in grid.cell_data.keys():
        v = _numeric(k, grid.cell_data[k], "cell")
        if v is not None:
            cell_data[k] = [v[idx] for idx in order]
    field_data = {k: v for k in grid.field_data.keys()
                  if (v := _numeric(k, grid.field_data[k], "field")) is not None}
    mesh = meshio.Mesh(points, blocks, point_data=point_data, cell_data=cell_data,
                       field_data=field_data)
    path = Path(path)
    kwargs = {}
    fmt = file_format or meshio._helpers._filetypes_from_path(path)[0]
    if fmt in ("vtu", "vtk"):
        kwargs["binary"] = binary
    elif fmt == "xdmf":  # one file (no HDF5 sidecar named after the temporary file)
        kwargs["data_format"] = "XML"
    with atomic_path(path) as tmp:
        meshio.write(tmp, mesh, file_format=fmt, **kwargs)
    return path


def check_export(path):
    """``path`` as a :class:`pathlib.Path` if :func:`export` knows its extension, else a
    ValueError listing the known ones; checked before any work.

    Examples
    --------
    >>> from pvcmf.io import check_export
    >>> check_export("model.inp").suffix
    '.inp'
    """
    import meshio

    path = Path(path)
    if path.suffix.lower() in WRITERS:
        return path
    try:
        meshio._helpers._filetypes_from_path(path)
    except (ValueError, KeyError, meshio.ReadError):
        known = sorted(set(WRITERS) | set(meshio.extension_to_filetypes))
        raise ValueError(f"export: unknown extension {path.suffix!r} of {str(path)!r}; "
                         f"known: {', '.join(known)}") from None
    return path


def export(grid, path, *, file_format=None):
    """Export a grid for another tool; the format comes from ``path``'s extension.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid or pyvista.DataSet
        For ``.inp`` and ``.feb``: the MTM grid (linear tetrahedra, materials, ``bc``
        arrays), as :func:`pvcmf.mtm.solve` takes it. For mesh formats: any dataset.
    path : str or pathlib.Path
        ``.inp`` (Abaqus/CalculiX), ``.feb`` (FEBio 4.0) or a meshio format (``.vtu``,
        ``.vtk``, ``.xdmf``, ``.msh``, ``.med``, ...).
    file_format : str, optional
        A meshio format name, overriding the extension (mesh formats only).

    Returns
    -------
    pathlib.Path

    Raises
    ------
    ValueError
        An extension no writer knows (the message lists the known ones).

    Examples
    --------
    >>> import os, tempfile, pyvista as pv
    >>> from pvcmf.io import export
    >>> export(pv.Sphere(), os.path.join(tempfile.mkdtemp(), "s.vtu")).suffix
    '.vtu'
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in WRITERS and file_format is None:
        return WRITERS[suffix](grid, path)
    if file_format is None:
        check_export(path)
    return write_mesh(grid, path, file_format=file_format)
