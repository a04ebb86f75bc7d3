"""What every export needs from a grid: tetrahedra, material groups, fibres and bc sets.

Pure numpy. The grid's arrays follow :mod:`pvcmf.arrays`; the material convention is the
MTM's (:mod:`pvcmf.mtm.materials`): ``E_cross`` defaults to ``E_fiber``, a cell with
``E_fiber != E_cross`` is transversely isotropic about its ``fiber``, any other is isotropic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyvista as pv

from ... import arrays
from ...mtm.materials import check_positive_definite

__all__ = ["Model", "model", "frames", "engineering_constants"]


def frames(directions):
    """Right-handed orthonormal frames ``[t1, t2, d]`` (k, 3, 3; columns) with ``t1 x t2 = d``.

    ``d`` is the normalised direction; ``t1`` is perpendicular to it, chosen from the
    coordinate axis least aligned with ``d`` (the same construction as the MTM's sliding
    frames).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.io.exporters._model import frames
    >>> R = frames([[0.0, 0.0, 3.0]])[0]
    >>> bool(np.allclose(np.cross(R[:, 0], R[:, 1]), [0, 0, 1]))
    True
    """
    d = np.asarray(directions, dtype=float).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1)[:, None]
    pick = np.zeros_like(d)
    pick[np.arange(len(d)), np.argmin(np.abs(d), axis=1)] = 1.0
    t1 = np.cross(d, pick)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(d, t1)
    return np.stack([t1, t2, d], axis=2)


def engineering_constants(E_fiber, E_cross, nu):
    """Orthotropic engineering constants of the MTM law with local axis 3 along the fibre.

    Returns ``dict`` with ``E1, E2, E3, nu12, nu13, nu23, nu31, G12, G13, G23`` (arrays),
    where ``nu_ij`` is the Abaqus/CalculiX ratio (compliance ``S_ij = -nu_ij / E_i``) and
    ``nu31 = nu13 E3 / E1`` is the one FEBio's ``orthotropic elastic`` asks for.

    Examples
    --------
    >>> from pvcmf.io.exporters._model import engineering_constants
    >>> c = engineering_constants(0.5, 0.79, 0.43)
    >>> float(c["E3"]), float(c["nu13"]), round(float(c["G13"]), 6)
    (0.5, 0.43, 0.174825)
    """
    ef, ec, nu = (np.asarray(x, dtype=float) for x in (E_fiber, E_cross, nu))
    g_fiber = ef / (2.0 * (1.0 + nu))
    return {"E1": ec, "E2": ec, "E3": ef, "nu12": nu, "nu13": nu, "nu23": nu,
            "nu31": nu * ef / ec, "G12": ec / (2.0 * (1.0 + nu)), "G13": g_fiber,
            "G23": g_fiber}


@dataclass
class Model:
    """Arrays of a grid in the form the writers use (0-based; writers add 1)."""

    points: np.ndarray  #: (n, 3)
    cells: np.ndarray  #: (m, 4) int
    material: np.ndarray  #: (m,) index into ``materials``
    materials: np.ndarray  #: (k, 3) unique (E_fiber, E_cross, nu)
    anisotropic: np.ndarray  #: (k,) bool, E_fiber != E_cross
    fiber: np.ndarray  #: (m, 3) unit fibre (zero where isotropic)
    used: np.ndarray  #: (n,) bool, point is in some tetrahedron
    bc: np.ndarray  #: (n,) int8 codes
    displacement: np.ndarray  #: (n, 3) prescribed displacement
    normal: np.ndarray  #: (n, 3) unit sliding normal (zero elsewhere)
    cell_sets: dict  #: name -> (j,) cell indices (tissue and muscle sets)

    @property
    def fixed(self):
        return np.flatnonzero(self.used & (self.bc == arrays.BC_FIXED))

    @property
    def joint(self):
        return np.flatnonzero(self.used & (self.bc == arrays.BC_JOINT))

    @property
    def sliding(self):
        return np.flatnonzero(self.used & (self.bc == arrays.BC_SLIDING))

    def normal_values(self):
        """Prescribed normal displacement ``bc_displacement . n`` at the sliding nodes."""
        s = self.sliding
        return np.einsum("ij,ij->i", self.displacement[s], self.normal[s])


def _cell_sets(grid):
    sets = {}
    names = {v: k for k, v in arrays.TISSUE_LABELS.items()}
    if arrays.TISSUE in grid.cell_data.keys():
        tissue = np.asarray(grid.cell_data[arrays.TISSUE]).astype(int)
        for t in np.unique(tissue):
            sets[names.get(int(t), f"tissue{int(t)}")] = np.flatnonzero(tissue == t)
    if arrays.MUSCLE in grid.cell_data.keys():
        muscle = np.asarray(grid.cell_data[arrays.MUSCLE]).astype(int)
        for mid in np.unique(muscle[muscle > 0]):
            name = (arrays.MUSCLES[mid - 1] if 0 < mid <= len(arrays.MUSCLES)
                    else f"muscle{int(mid)}")
            sets[name] = np.flatnonzero(muscle == mid)
    return sets


def _cell_scalar(grid, name, default=None):
    if name not in grid.cell_data.keys() and default is not None:
        return default
    return np.asarray(arrays.require_array(grid, name, "cell", dtype="f", ncomp=1,
                                           producer="assign_materials"), dtype=float)


def _boundary(grid, n):
    bc = np.asarray(arrays.require_array(grid, arrays.BC, "point", dtype="iu", ncomp=1,
                                         producer="apply_plan")).astype(np.int8)
    bad = ~np.isin(bc, list(arrays.BC_CODES.values()))
    if bad.any():
        raise ValueError(f"point array {arrays.BC!r} must hold codes {arrays.BC_CODES}, got "
                         f"{int(bc[bad][0])} at point {int(np.flatnonzero(bad)[0])}")
    disp = np.zeros((n, 3))
    if arrays.BC_DISPLACEMENT in grid.point_data.keys():
        disp = np.array(arrays.require_array(grid, arrays.BC_DISPLACEMENT, "point", dtype="f",
                                             ncomp=3, producer="apply_plan"), dtype=float)
    normal = np.zeros((n, 3))
    sliding = bc == arrays.BC_SLIDING
    if sliding.any():
        raw = np.asarray(arrays.require_array(grid, arrays.BC_NORMAL, "point", dtype="f",
                                              ncomp=3, producer="apply_plan"), dtype=float)
        length = np.linalg.norm(raw[sliding], axis=1)
        if not np.all(length > 0) or not np.all(np.isfinite(length)):
            raise ValueError(f"point array {arrays.BC_NORMAL!r} must be a nonzero finite "
                             "vector at every sliding point")
        normal[sliding] = raw[sliding] / length[:, None]
    return bc, disp, normal


def model(grid):
    """Collect a grid's tetrahedra, materials and boundary conditions (see :class:`Model`).

    Raises
    ------
    TypeError, ValueError
        Not an UnstructuredGrid of linear tetrahedra; missing ``E_fiber``/``nu``/``bc``
        arrays; an indefinite material; an anisotropic cell without a fibre.
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid of linear tetrahedra, got "
                        f"{type(grid).__name__}")
    types = np.asarray(grid.celltypes)
    if grid.n_cells == 0 or np.any(types != pv.CellType.TETRA):
        raise ValueError(f"grid must hold only linear tetrahedra (VTK type "
                         f"{int(pv.CellType.TETRA)}), got cell types "
                         f"{np.unique(types).tolist()} in {grid.n_cells} cells")
    cells = np.asarray(grid.cell_connectivity, dtype=np.int64).reshape(-1, 4)
    n = grid.n_points
    ef = _cell_scalar(grid, arrays.E_FIBER)
    ec = _cell_scalar(grid, arrays.E_CROSS, default=ef)
    nu = _cell_scalar(grid, arrays.NU)
    check_positive_definite(ef, ec, nu)
    table = np.stack([ef, ec, nu], axis=1)
    materials, material = np.unique(table, axis=0, return_inverse=True)
    aniso_cell = ef != ec
    fiber = np.zeros((grid.n_cells, 3))
    if aniso_cell.any():
        raw = np.asarray(arrays.require_array(grid, arrays.FIBER, "cell", dtype="f", ncomp=3,
                                              producer="assign_materials"), dtype=float)
        length = np.linalg.norm(raw[aniso_cell], axis=1)
        if not np.all(length > 0):
            bad = np.flatnonzero(aniso_cell)[~(length > 0)]
            raise ValueError(f"cell array {arrays.FIBER!r} must be nonzero where E_fiber != "
                             f"E_cross; {bad.size} cell(s) have none, e.g. cell {int(bad[0])}")
        fiber[aniso_cell] = raw[aniso_cell] / length[:, None]
    used = np.zeros(n, dtype=bool)
    used[cells.ravel()] = True
    bc, disp, normal = _boundary(grid, n)
    return Model(points=np.asarray(grid.points, dtype=float), cells=cells,
                 material=material.ravel(), materials=materials,
                 anisotropic=materials[:, 0] != materials[:, 1], fiber=fiber, used=used,
                 bc=bc, displacement=disp, normal=normal, cell_sets=_cell_sets(grid))
