"""FEBio input files (``.feb``, format 4.0) of an MTM grid.

:func:`write_feb` writes one static step of the grid's problem:

* ``Mesh``: ``Nodes`` (grid point ``i`` is node ``i + 1``), one ``Elements`` block of
  ``tet4`` per material (cell ``j`` is element ``j + 1`` throughout), an ``ElementSet`` per
  tissue and per muscle, ``NodeSet`` ``fixed``, ``joint``, ``sliding``.
* ``MeshDomains``: one ``SolidDomain`` per ``Elements`` block and its material.
* ``Material``: isotropic cells as ``isotropic elastic`` (``E``, ``v``); transversely
  isotropic cells as ``orthotropic elastic`` with local axis 3 along the fibre,
  ``E1 = E2 = E_cross``, ``E3 = E_fiber``, ``v12 = v23 = nu``, ``v31 = nu E_fiber /
  E_cross`` (FEBio's compliance has ``S13 = -v31 / E3``), ``G12 = E_cross / (2 (1 + nu))``,
  ``G23 = G31 = E_fiber / (2 (1 + nu))``, and per element ``mat_axis`` (``MeshData`` /
  ``ElementData type="mat_axis"``, vectors ``a = t1``, ``d = t2`` with ``t1 x t2`` = fibre).
* ``Boundary``: ``zero displacement`` on ``fixed``; ``prescribed displacement`` on
  ``joint``, one per axis, with per-node values (``NodeData`` maps ``joint_ux`` ...) under
  load controller 1 (a ramp 0 -> 1); each sliding node as one ``linear constraint``
  ``u_k = sum_j (-n_j / n_k) u_j + (bc_displacement . n) / n_k`` on its largest normal
  component ``k`` (FEBio 4's ``bc type="linear constraint"``: parent ``node``/``dof``,
  ``child_dof`` terms and ``offset``).
* ``Control``: one ``STATIC`` step, one time step; ``Output``: the plot file's
  ``displacement`` and a log file of the nodal ``ux;uy;uz``.

Which FEBio law matches the MTM: FEBio's ``isotropic elastic`` is St Venant-Kirchhoff and
its ``orthotropic elastic`` a large-deformation orthotropic law (``FEOrthoElastic``);
both linearise at zero strain to exactly the MTM's linear elastic tensor with the constants
above, so FEBio's answer equals the MTM's to first order in the displacement and differs
from it by the geometric nonlinearity of FEBio's finite-strain solver (FEBio has no
geometrically linear solid solver). FEBio's ``trans iso Mooney-Rivlin`` is a different
(hyperelastic, fibre-reinforced) law and is not used. These files are checked for
structure (well-formed XML, every referenced set, material and map defined, counts);
FEBio itself was not available to run them.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..._atomic import atomic_path
from ._model import engineering_constants, frames, model

log = logging.getLogger(__name__)

__all__ = ["write_feb", "FEB_VERSION"]

FEB_VERSION = "4.0"
_F = "%.15g"


def _sub(parent, tag, text=None, **attrib):
    el = ET.SubElement(parent, tag, {k.rstrip("_"): str(v) for k, v in attrib.items()})
    if text is not None:
        el.text = str(text)
    return el


def _vec(v, fmt="%.15g"):
    return ",".join(fmt % float(x) for x in v)


def _ids(ids):
    return ",".join(map(str, (np.asarray(ids, dtype=np.int64) + 1).tolist()))


def _materials(root, m):
    mats = _sub(root, "Material")
    consts = engineering_constants(*m.materials.T)
    for k, (ef, ec, nu) in enumerate(m.materials):
        if m.anisotropic[k]:
            el = _sub(mats, "material", id=k + 1, name=f"M{k + 1}", type="orthotropic elastic")
            _sub(el, "density", 1.0)
            for key, tag in (("E1", "E1"), ("E2", "E2"), ("E3", "E3"), ("G12", "G12"),
                             ("G23", "G23"), ("G13", "G31"), ("nu12", "v12"),
                             ("nu23", "v23"), ("nu31", "v31")):
                _sub(el, tag, _F % float(consts[key][k]))
        else:
            el = _sub(mats, "material", id=k + 1, name=f"M{k + 1}", type="isotropic elastic")
            _sub(el, "density", 1.0)
            _sub(el, "E", _F % ef)
            _sub(el, "v", _F % nu)


def _mesh(root, m):
    mesh = _sub(root, "Mesh")
    nodes = _sub(mesh, "Nodes", name="AllNodes")
    for i, p in enumerate(m.points):
        _sub(nodes, "node", _vec(p), id=i + 1)
    parts = []
    for k in range(len(m.materials)):
        members = np.flatnonzero(m.material == k)
        name = f"Part{k + 1}"
        block = _sub(mesh, "Elements", type="tet4", name=name)
        for j in members.tolist():
            _sub(block, "elem", ",".join(map(str, (m.cells[j] + 1).tolist())), id=j + 1)
        parts.append((name, k, members))
    for name, members in m.cell_sets.items():
        _sub(mesh, "ElementSet", _ids(members), name=name)
    for name, nodes_ in (("fixed", m.fixed), ("joint", m.joint), ("sliding", m.sliding)):
        if nodes_.size:
            _sub(mesh, "NodeSet", _ids(nodes_), name=name)
    return parts


def _mesh_data(root, m, parts):
    data = _sub(root, "MeshData")
    for name, k, members in parts:
        if not m.anisotropic[k]:
            continue
        R = frames(m.fiber[members])
        el = _sub(data, "ElementData", type="mat_axis", elem_set=name)
        for lid, frame in enumerate(R, start=1):
            e = _sub(el, "elem", lid=lid)
            _sub(e, "a", _vec(frame[:, 0]))
            _sub(e, "d", _vec(frame[:, 1]))
    j = m.joint
    if j.size:
        for c, axis in enumerate("xyz"):
            nd = _sub(data, "NodeData", name=f"joint_u{axis}", node_set="joint")
            for lid, value in enumerate(m.displacement[j, c].tolist(), start=1):
                _sub(nd, "node", _F % value, lid=lid)
    return data


def _boundary(root, m):
    bnd = _sub(root, "Boundary")
    if m.fixed.size:
        bc = _sub(bnd, "bc", name="fixed", node_set="fixed", type="zero displacement")
        for axis in "xyz":
            _sub(bc, f"{axis}_dof", 1)
    if m.joint.size:
        for axis in "xyz":
            bc = _sub(bnd, "bc", name=f"joint_{axis}", node_set="joint",
                      type="prescribed displacement")
            _sub(bc, "dof", axis)
            _sub(bc, "value", f"joint_u{axis}", lc=1, type="map")
            _sub(bc, "relative", 0)
    s = m.sliding
    for node, normal, value in zip(s.tolist(), m.normal[s], m.normal_values().tolist()):
        k = int(np.argmax(np.abs(normal)))
        bc = _sub(bnd, "bc", name=f"sliding_{node + 1}", type="linear constraint")
        _sub(bc, "node", node + 1)
        _sub(bc, "dof", "xyz"[k])
        _sub(bc, "offset", _F % (value / normal[k]), lc=1)
        for d in range(3):
            if d != k and normal[d] != 0.0:
                child = _sub(bc, "child_dof")
                _sub(child, "node", node + 1)
                _sub(child, "dof", "xyz"[d])
                _sub(child, "value", _F % (-normal[d] / normal[k]))


def write_feb(grid, path):
    """Write ``grid`` as an FEBio 4.0 ``.feb`` file (see the module docstring).

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with materials and ``bc`` arrays (as for :func:`pvcmf.mtm.solve`).
    path : str or pathlib.Path
        The ``.feb`` file (written atomically).

    Returns
    -------
    pathlib.Path

    Examples
    --------
    >>> import os, tempfile, numpy as np, pyvista as pv
    >>> import xml.etree.ElementTree as ET
    >>> from pvcmf import arrays
    >>> from pvcmf.io import write_feb
    >>> grid = pv.ImageData(dimensions=(2, 2, 2)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.3)
    >>> grid.point_data[arrays.BC] = np.array([1, 1, 1, 1, 0, 0, 0, 2], dtype=np.int8)
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = np.full((8, 3), 0.1)
    >>> root = ET.parse(write_feb(grid, os.path.join(tempfile.mkdtemp(), "box.feb"))).getroot()
    >>> root.get("version"), len(root.findall("Mesh/Elements/elem"))
    ('4.0', 5)
    """
    m = model(grid)
    root = ET.Element("febio_spec", version=FEB_VERSION)
    _sub(root, "Module", type="solid")
    control = _sub(root, "Control")
    _sub(control, "analysis", "STATIC")
    _sub(control, "time_steps", 1)
    _sub(control, "step_size", 1)
    _materials(root, m)
    parts = _mesh(root, m)
    domains = _sub(root, "MeshDomains")
    for name, k, _ in parts:
        _sub(domains, "SolidDomain", name=name, mat=f"M{k + 1}")
    _mesh_data(root, m, parts)
    _boundary(root, m)
    load = _sub(root, "LoadData")
    lc = _sub(load, "load_controller", id=1, name="ramp", type="loadcurve")
    _sub(lc, "interpolate", "LINEAR")
    points = _sub(lc, "points")
    _sub(points, "pt", "0,0")
    _sub(points, "pt", "1,1")
    output = _sub(root, "Output")
    plot = _sub(output, "plotfile", type="febio")
    _sub(plot, "var", type="displacement")
    logfile = _sub(output, "logfile")
    _sub(logfile, "node_data", data="ux;uy;uz", delim=",", file=f"{Path(path).stem}_u.csv")
    ET.indent(root, space=" ")
    path = Path(path)
    with atomic_path(path) as tmp:
        ET.ElementTree(root).write(tmp, encoding="ISO-8859-1", xml_declaration=True)
    log.info("wrote %s: %d nodes, %d tet4 in %d domains, %d sliding constraints", path,
             len(m.points), len(m.cells), len(parts), m.sliding.size)
    return path
