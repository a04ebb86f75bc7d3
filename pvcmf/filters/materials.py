"""Assign MTM material properties to a labelled tetrahedral mesh (paper 000 Table I, paper 001).

Reads the cell labels (``tissue``, optionally ``muscle``, ``fiber``, ``muscle_fraction``) and
writes the cell arrays ``E_fiber``, ``E_cross``, ``nu`` and ``fiber`` that
:func:`pvcmf.mtm.stiffness` and :func:`pvcmf.mtm.solve` read. Pure numpy; the tables and the
transverse-isotropy convention live in :mod:`pvcmf.mtm.materials`.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..mtm.materials import check_positive_definite, material_table
from ..progress import Progress

log = logging.getLogger(__name__)

__all__ = ["assign_materials"]


def assign_materials(grid, table="paper000", *, e_ratio=None, fat=None, muscle=None,
                     use_fraction=None, default_fiber=None, progress_bar=False):
    """Write per-tetrahedron ``E_fiber``, ``E_cross``, ``nu`` and ``fiber`` cell arrays.

    Fat cells (``tissue == FAT``) get the table's fat properties, muscle cells
    (``tissue == MUSCLE_TISSUE``) its muscle properties with the fibre from the cell array
    ``fiber`` (unit vectors, written by ``fiber_directions``). ``fiber`` is written as zero
    where a cell is isotropic (``E_fiber == E_cross``).

    Baselines (paper 000's state of the art, paper 001's voxel averages): when the grid has the
    cell array ``muscle_fraction`` ``f`` (and ``use_fraction`` is not False), every cell mixes
    linearly, ``p = (1 - f) p_fat + f p_muscle`` for each of ``E_fiber``, ``E_cross`` and
    ``nu`` (the rule of mixtures; paper 001 averages E and nu over the voxels of a tetrahedron
    the same way), and the ``tissue`` labels are not used. Cells with ``f > 0`` take the muscle
    fibre when the muscle is anisotropic. Muscle cells whose ``fiber`` is zero (muscle that
    ``fiber_directions`` knows no direction for, e.g. the tongue or a neck muscle found by
    ``classify_tissue`` outside the atlas muscles) are made isotropic with
    ``E = (E_fiber + E_cross) / 2`` and the muscle's ``nu``.

    Transverse-isotropy convention: see :mod:`pvcmf.mtm.materials` (e3 = fibre, ``nu`` over
    ``E_cross``); every cell is checked to be positive definite.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Tetrahedral mesh with cell array ``tissue`` (FAT / MUSCLE_TISSUE), or
        ``muscle_fraction`` for the baselines.
    table : str or dict
        ``'paper000'`` (Table I: fat E 0.003 MPa nu 0.46; muscle E 0.5 along / 0.79 across the
        fibre, nu 0.43), ``'paper001_homogeneous'`` (nu 0.46) or ``'paper001_inhomogeneous'``
        (nu_fat 0.485, nu_muscle 0.43, E_muscle / E_fat = ``e_ratio``); see
        :data:`pvcmf.mtm.TABLES`.
    e_ratio : float, optional
        ``E_muscle / E_fat`` (muscle made isotropic with that modulus); paper 001 sweeps 1-64.
    fat, muscle : dict, optional
        Overrides, e.g. ``fat={"nu": 0.49}`` or ``muscle={"E": 0.1}`` (``E`` sets both moduli).
    use_fraction : bool, optional
        Mix by ``muscle_fraction``; default: when that array exists.
    default_fiber : (3,) array_like, optional
        Fibre for anisotropic muscle cells when the grid has no ``fiber`` array (otherwise a
        ``ValueError`` asks for ``fiber_directions``).
    progress_bar : bool
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        A copy with the four cell arrays.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(3, 3, 3)).triangulate()
    >>> grid.cell_data[arrays.TISSUE] = np.full(grid.n_cells, arrays.FAT, dtype=np.uint8)
    >>> out = grid.cmf.assign_materials()
    >>> float(out[arrays.E_FIBER][0]), float(out[arrays.NU][0])
    (0.003, 0.46)
    """
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    props = material_table(table, e_ratio=e_ratio, fat=fat, muscle=muscle)
    m = grid.n_cells
    pf = {k: props["fat"][k] for k in ("E_fiber", "E_cross", "nu")}
    pm = {k: props["muscle"][k] for k in ("E_fiber", "E_cross", "nu")}
    muscle_aniso = pm["E_fiber"] != pm["E_cross"]
    with Progress(total=2, desc="assign_materials", enabled=progress_bar, logger=log) as bar:
        weight, needs_fiber, label = _muscle_weight(grid, use_fraction, muscle_aniso)
        out_vals = {k: (1 - weight) * pf[k] + weight * pm[k] for k in pf}
        bar.step(f"properties mixed by {label}")
        fib = _fibers(grid, needs_fiber, out_vals, default_fiber)
        iso = out_vals["E_fiber"] == out_vals["E_cross"]
        fib[iso] = 0.0
        check_positive_definite(out_vals["E_fiber"], out_vals["E_cross"], out_vals["nu"])
        out = grid.copy()  # deep: no array of the result shares the input's memory
        out.cell_data[arrays.E_FIBER] = out_vals["E_fiber"]
        out.cell_data[arrays.E_CROSS] = out_vals["E_cross"]
        out.cell_data[arrays.NU] = out_vals["nu"]
        out.cell_data[arrays.FIBER] = fib
        bar.step("fibres written")
    log.info("assign_materials(%s) by %s: %d cells, %.0f%% muscle", table if isinstance(table, str)
             else "custom", label, m, 100 * float(np.mean(weight)) if m else 0.0)
    return out


def _muscle_weight(grid, use_fraction, muscle_aniso):
    """Muscle weight per cell, the cells needing a fibre, and the array the weight came from."""
    have_fraction = arrays.MUSCLE_FRACTION in grid.cell_data.keys()
    if arrays.TISSUE in grid.cell_data.keys():
        ids = np.unique(np.asarray(grid.cell_data[arrays.TISSUE]))
        unknown = np.setdiff1d(ids, list(arrays.TISSUE_LABELS.values()))
        if unknown.size:
            raise ValueError(
                f"cell array {arrays.TISSUE!r} must hold tissue label ids "
                f"{sorted(arrays.TISSUE_LABELS.values())} (pvcmf.arrays.TISSUE_LABELS), got "
                f"unknown ids {unknown.tolist()}"
            )
    if use_fraction is None:
        use_fraction = have_fraction
    if use_fraction:
        f = np.asarray(arrays.require_array(grid, arrays.MUSCLE_FRACTION, "cell", dtype="f",
                                            ncomp=1, producer="sample_muscle_fraction"), float)
        if np.any(~((f >= 0) & (f <= 1))):
            i = int(np.flatnonzero(~((f >= 0) & (f <= 1)))[0])
            raise ValueError(
                f"cell array {arrays.MUSCLE_FRACTION!r} must lie in [0, 1], got {f[i]} at cell {i}"
            )
        weight = f
        needs_fiber = (f > 0) & muscle_aniso
        label = "muscle_fraction"
    else:
        tissue = np.asarray(arrays.require_array(grid, arrays.TISSUE, "cell", dtype="iu", ncomp=1,
                                                 producer="tetrahedralize"))
        bad = ~np.isin(tissue, (arrays.FAT, arrays.MUSCLE_TISSUE))
        if np.any(bad):
            raise ValueError(
                f"cell array {arrays.TISSUE!r} must hold only FAT ({arrays.FAT}) and "
                f"MUSCLE_TISSUE ({arrays.MUSCLE_TISSUE}) in a soft-tissue mesh, got labels "
                f"{np.unique(tissue[bad]).tolist()} (e.g. cell {int(np.flatnonzero(bad)[0])})"
            )
        weight = (tissue == arrays.MUSCLE_TISSUE).astype(float)
        needs_fiber = (weight > 0) & muscle_aniso
        label = "tissue"
    return weight, needs_fiber, label


def _fibers(grid, needs_fiber, out_vals, default_fiber):
    """Unit fibre per cell (zero where none); muscle cells without one made isotropic.

    ``out_vals`` (the mixed moduli) is updated in place for those cells.
    """
    m = grid.n_cells
    fib = np.zeros((m, 3))
    if np.any(needs_fiber):
        if arrays.FIBER in grid.cell_data.keys():
            src = np.asarray(arrays.require_array(grid, arrays.FIBER, "cell", dtype="f", ncomp=3,
                                                  producer="fiber_directions"), float)
        elif default_fiber is not None:
            v = np.asarray(default_fiber, dtype=float)
            if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.any(v):
                raise ValueError(f"default_fiber must be a finite non-zero vector of shape (3,), "
                                 f"got {default_fiber!r}")
            src = np.broadcast_to(v, (m, 3))
        else:
            raise ValueError(
                f"{int(needs_fiber.sum())} muscle cell(s) are transversely isotropic but the grid "
                f"has no cell array {arrays.FIBER!r}: run fiber_directions first or pass "
                "default_fiber=(x, y, z)"
            )
        bad = needs_fiber & ~np.isfinite(src).all(axis=1)
        if np.any(bad):
            raise ValueError(
                f"cell array {arrays.FIBER!r} must hold finite vectors, got NaN/inf in "
                f"{int(bad.sum())} muscle cell(s) (e.g. cell {int(np.flatnonzero(bad)[0])}); "
                "a zero vector marks a muscle cell without a known fibre"
            )
        norm = np.linalg.norm(src, axis=1)
        zero = needs_fiber & ~(norm > 0)
        if np.any(zero):
            # muscle with no known fibre (e.g. tongue or neck muscle found by
            # classify_tissue outside the atlas muscles): isotropic, mean of the two moduli
            e_iso = 0.5 * (out_vals["E_fiber"][zero] + out_vals["E_cross"][zero])
            out_vals["E_fiber"][zero] = e_iso
            out_vals["E_cross"][zero] = e_iso
            log.info("assign_materials: %d muscle cell(s) without a fibre direction made "
                     "isotropic (E = mean of E_fiber and E_cross)", int(zero.sum()))
            needs_fiber = needs_fiber & ~zero
        fib[needs_fiber] = src[needs_fiber] / norm[needs_fiber, None]
    return fib
