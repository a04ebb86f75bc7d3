"""Abaqus / CalculiX input decks (``.inp``) of an MTM grid, and a CalculiX cross-check.

:func:`write_inp` writes one linear static problem that CalculiX (``ccx``) and Abaqus solve
exactly as the MTM does (same linear tetrahedra, same law, same constraints):

* ``*NODE`` (grid point ``i`` is node ``i + 1``) and ``*ELEMENT, TYPE=C3D4`` (cell ``j``
  is element ``j + 1``); element sets ``EALL``, one per tissue (``FAT``, ``MUSCLE``) and
  one per muscle (``MASSETER_LEFT``, ...).
* One ``*MATERIAL`` per distinct ``(E_fiber, E_cross, nu)`` (element set ``MAT<k>``):
  isotropic cells as ``*ELASTIC`` (E, nu); transversely isotropic cells as ``*ELASTIC,
  TYPE=ENGINEERING CONSTANTS`` with local axis 3 along the fibre: ``E1 = E2 = E_cross``,
  ``E3 = E_fiber``, ``nu12 = nu13 = nu23 = nu``, ``G12 = E_cross / (2 (1 + nu))``,
  ``G13 = G23 = E_fiber / (2 (1 + nu))`` (the compliance of :mod:`pvcmf.mtm.materials`).
* The fibre of every anisotropic element through one ``*DISTRIBUTION`` (one line per
  element: points ``a = t1``, ``b = t2`` with ``t1 x t2 = fiber``) referenced by one
  ``*ORIENTATION``; so the deck has one section per material, not one per element.
* Fixed and joint nodes: ``*BOUNDARY`` with their displacement. Sliding nodes: one
  ``*EQUATION`` each, ``n . u = bc_displacement . n``; the right-hand side is carried by one
  extra node (number ``n_points + 1``, not in any element) whose x displacement is
  prescribed to 1, since ``*EQUATION`` is homogeneous.
* One linear ``*STATIC`` step with ``*NODE PRINT`` (``.dat``) and ``*NODE FILE`` (``.frd``)
  of ``U``.

Points in no tetrahedron get no boundary condition (the MTM keeps them at their prescribed
value). :func:`run_calculix` runs ``ccx`` on a deck and reads the ``.dat`` displacements
back (:func:`read_calculix_dat`). Numbers are written with 15 significant digits
(orientation points with 10, to keep ``ccx``'s line length).
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from ..._atomic import atomic_path
from ._model import engineering_constants, frames, model

log = logging.getLogger(__name__)

__all__ = ["write_inp", "run_calculix", "read_calculix_dat", "calculix_available"]

_F = "%.15g"


def _name(text):
    return re.sub(r"[^A-Za-z0-9_]", "_", str(text)).upper()[:70]


def _lines_of_ids(ids, per_line=16):
    ids = np.asarray(ids, dtype=np.int64) + 1
    out = []
    for start in range(0, ids.size, per_line):
        out.append(", ".join(map(str, ids[start:start + per_line].tolist())) + ",")
    return out


def _table(rows, fmt):
    """Format a 2-D array as comma-separated lines (vectorised through ``np.savetxt``)."""
    import io

    buf = io.StringIO()
    np.savetxt(buf, rows, fmt=fmt, delimiter=", ")
    return buf.getvalue().rstrip("\n").split("\n") if len(rows) else []


def _materials(m):
    lines = []
    consts = engineering_constants(*m.materials.T)
    for k, (ef, ec, nu) in enumerate(m.materials):
        lines.append(f"*MATERIAL, NAME=M{k + 1}")
        if m.anisotropic[k]:
            c = {key: float(v[k]) for key, v in consts.items()}
            lines.append("*ELASTIC, TYPE=ENGINEERING CONSTANTS")
            lines.append(",".join(_F % c[key] for key in
                                  ("E1", "E2", "E3", "nu12", "nu13", "nu23", "G12", "G13")))
            lines.append(f"{_F % c['G23']},0.")
        else:
            lines.append("*ELASTIC")
            lines.append(f"{_F % ef}, {_F % nu}")
    return lines


def _sections(m):
    lines = []
    aniso_cells = np.flatnonzero(m.anisotropic[m.material])
    if aniso_cells.size:
        R = frames(m.fiber[aniso_cells])
        rows = np.column_stack([aniso_cells + 1, R[:, :, 0], R[:, :, 1]])
        lines += ["*DISTRIBUTION, NAME=FIBERS", ", 1., 0., 0., 0., 1., 0."]
        lines += _table(rows, ["%d"] + ["%.10g"] * 6)
        lines += ["*ORIENTATION, NAME=FIBER, SYSTEM=RECTANGULAR", "FIBERS"]
    for k in range(len(m.materials)):
        members = np.flatnonzero(m.material == k)
        lines.append(f"*ELSET, ELSET=MAT{k + 1}")
        lines += _lines_of_ids(members)
        orient = ", ORIENTATION=FIBER" if m.anisotropic[k] else ""
        lines.append(f"*SOLID SECTION, ELSET=MAT{k + 1}, MATERIAL=M{k + 1}{orient}")
    return lines


def _boundary(m):
    n = m.points.shape[0]
    lines = ["*BOUNDARY"]
    lines += [f"{i + 1}, 1, 3, 0." for i in m.fixed.tolist()]
    j = m.joint
    if j.size:
        rows = np.column_stack([np.repeat(j + 1, 3), np.tile([1, 2, 3], j.size),
                                np.tile([1, 2, 3], j.size), m.displacement[j].ravel()])
        lines += _table(rows, ["%d", "%d", "%d", _F])
    s = m.sliding
    equations = []
    if s.size:
        lines.append(f"{n + 1}, 1, 1, 1.")  # the right-hand-side carrier
        lines.append(f"{n + 1}, 2, 3, 0.")
        values = m.normal_values()
        for node, normal, value in zip((s + 1).tolist(), m.normal[s], values.tolist()):
            order = np.argsort(-np.abs(normal))  # dependent dof first: the largest component
            terms = [(node, int(d) + 1, float(normal[d])) for d in order if normal[d] != 0.0]
            if value != 0.0:
                terms.append((n + 1, 1, -value))
            equations.append("*EQUATION")
            equations.append(str(len(terms)))
            for start in range(0, len(terms), 2):
                equations.append(", ".join(f"{a}, {b}, {_F % c}"
                                           for a, b, c in terms[start:start + 2]) + ",")
    return lines, equations


def write_inp(grid, path):
    """Write ``grid`` as an Abaqus/CalculiX input deck (see the module docstring).

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with ``E_fiber``, ``nu`` (optional ``E_cross``, ``fiber``) cell
        arrays and ``bc`` (with ``bc_displacement``, ``bc_normal``) point arrays.
    path : str or pathlib.Path
        The ``.inp`` file (written atomically).

    Returns
    -------
    pathlib.Path

    Examples
    --------
    >>> import os, tempfile, numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.io import write_inp
    >>> grid = pv.ImageData(dimensions=(2, 2, 2)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.3)
    >>> grid.point_data[arrays.BC] = np.array([1, 1, 1, 1, 0, 0, 0, 2], dtype=np.int8)
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = np.full((8, 3), 0.1)
    >>> text = write_inp(grid, os.path.join(tempfile.mkdtemp(), "box.inp")).read_text()
    >>> text.count("C3D4"), "*STATIC" in text
    (1, True)
    """
    m = model(grid)
    n = m.points.shape[0]
    lines = ["*HEADING", "pvcmf MTM model: linear tetrahedra, transversely isotropic law",
             "*NODE, NSET=NGRID"]
    lines += _table(np.column_stack([np.arange(1, n + 1), m.points]), ["%d"] + [_F] * 3)
    boundary, equations = _boundary(m)
    if m.sliding.size:  # the right-hand-side node of the sliding equations
        lines += ["*NODE, NSET=NRHS", f"{n + 1}, 0., 0., 0."]
    lines.append("*ELEMENT, TYPE=C3D4, ELSET=EALL")
    lines += _table(np.column_stack([np.arange(1, len(m.cells) + 1), m.cells + 1]),
                    "%d")
    for name, members in m.cell_sets.items():
        lines.append(f"*ELSET, ELSET={_name(name)}")
        lines += _lines_of_ids(members)
    for code, nodes in (("FIXED", m.fixed), ("JOINT", m.joint), ("SLIDING", m.sliding)):
        if nodes.size:
            lines.append(f"*NSET, NSET={code}")
            lines += _lines_of_ids(nodes)
    lines += _materials(m) + _sections(m) + equations
    lines += ["*STEP", "*STATIC"] + (boundary if len(boundary) > 1 else [])
    lines += ["*NODE PRINT, NSET=NGRID", "U", "*NODE FILE", "U", "*END STEP"]
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n", encoding="ascii")
    log.info("wrote %s: %d nodes, %d C3D4, %d materials, %d sliding equations", path, n,
             len(m.cells), len(m.materials), m.sliding.size)
    return path


def calculix_available(executable="ccx"):
    """Path of the CalculiX executable, or None when it is not installed."""
    return shutil.which(executable)


def read_calculix_dat(path, n_points):
    """Read the ``U`` block of a CalculiX ``.dat`` file as an ``(n_points, 3)`` array.

    Nodes the file does not list (e.g. points in no element) stay zero.
    """
    text = Path(path).read_text(encoding="latin-1")
    match = re.search(r"displacements \(vx,vy,vz\)[^\n]*\n", text)
    if match is None:
        raise ValueError(f"{path}: no displacement block (*NODE PRINT U) found")
    u = np.zeros((n_points, 3))
    for line in text[match.end():].splitlines():
        parts = line.split()
        if not parts:
            if u.any():
                break
            continue
        if len(parts) != 4 or not parts[0].isdigit():
            break
        node = int(parts[0]) - 1
        if node < n_points:
            u[node] = [float(p) for p in parts[1:]]
    return u


def run_calculix(grid_or_inp, workdir=None, *, executable="ccx", timeout=600):
    """Solve a grid (or an existing ``.inp``) with CalculiX; return ``(displacement, seconds)``.

    Parameters
    ----------
    grid_or_inp : pyvista.UnstructuredGrid or path
        A grid (exported with :func:`write_inp` first) or a deck written by it.
    workdir : path, optional
        Where ``ccx`` runs and leaves its ``.dat``/``.frd``; a temporary folder by default
        (removed afterwards).
    executable : str
        The CalculiX binary.
    timeout : float
        Seconds before ``ccx`` is stopped.

    Returns
    -------
    displacement : numpy.ndarray, (n_points, 3)
    seconds : float
        Wall time of ``ccx`` alone.

    Raises
    ------
    FileNotFoundError
        ``ccx`` is not installed (``apt-get install calculix-ccx``).
    RuntimeError
        ``ccx`` failed; the message quotes the end of its output.
    """
    exe = calculix_available(executable)
    if exe is None:
        raise FileNotFoundError(f"CalculiX executable {executable!r} not found on PATH "
                                "(Debian/Ubuntu: apt-get install calculix-ccx)")
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="pvcmf-ccx-")
        workdir = tmp.name
    try:
        workdir = Path(workdir)
        workdir.mkdir(parents=True, exist_ok=True)
        if hasattr(grid_or_inp, "points"):
            n = grid_or_inp.n_points
            inp = write_inp(grid_or_inp, workdir / "model.inp")
        else:
            inp = Path(grid_or_inp)
            text = inp.read_text(encoding="ascii")
            n = int(re.search(r"\*NODE, NSET=NGRID\n(?:.*\n)*?(\d+),[^\n]*\n\*", text).group(1))
            if inp.parent.resolve() != workdir.resolve():
                shutil.copy(inp, workdir / inp.name)
        start = time.perf_counter()
        proc = subprocess.run([exe, "-i", inp.stem], cwd=workdir, capture_output=True,
                              text=True, timeout=timeout,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
        seconds = time.perf_counter() - start
        dat = workdir / f"{inp.stem}.dat"
        if proc.returncode != 0 or "*ERROR" in proc.stdout or not dat.exists():
            tail = (proc.stdout + proc.stderr)[-2000:]
            raise RuntimeError(f"ccx failed on {inp.name} (exit {proc.returncode}):\n{tail}")
        return read_calculix_dat(dat, n), seconds
    finally:
        if tmp is not None:
            tmp.cleanup()
