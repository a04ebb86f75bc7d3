"""Exports: .inp / .feb structure and numbering, meshio round trips, bad extensions."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.io import export, write_feb, write_inp, write_mesh
from pvcmf.io.exporters._model import engineering_constants, frames
from pvcmf.mtm import constitutive_matrix


def mixed_box(nx=7, ny=6, nz=5, seed=0, fiber_tilt=0.4):
    """A jittered tetrahedral box: fat (x < 6) and a transversely isotropic muscle
    (x > 6, fibres turning with y), fixed bottom, joint top (non-uniform move), sliding
    side x = 0 with a tilted normal and a nonzero normal displacement."""
    g = pv.ImageData(dimensions=(nx, ny, nz), spacing=(2.0, 1.6, 1.5)).triangulate()
    rng = np.random.default_rng(seed)
    pts = np.asarray(g.points).copy()
    inner = np.all((pts > 0.1) & (pts < pts.max(axis=0) - 0.1), axis=1)
    pts[inner] += rng.uniform(-0.2, 0.2, (inner.sum(), 3))
    g.points = pts
    c = np.asarray(g.cell_centers().points)
    muscle = c[:, 0] > 6
    g.cell_data[arrays.TISSUE] = np.where(muscle, arrays.MUSCLE_TISSUE, arrays.FAT).astype(np.uint8)
    g.cell_data[arrays.MUSCLE] = np.where(muscle, arrays.MUSCLE_IDS["masseter_left"], 0
                                          ).astype(np.uint8)
    g.cell_data[arrays.E_FIBER] = np.where(muscle, 0.5, 0.3)
    g.cell_data[arrays.E_CROSS] = np.where(muscle, 0.79, 0.3)
    g.cell_data[arrays.NU] = np.where(muscle, 0.43, 0.46)
    ang = 0.3 * c[:, 1]
    fib = np.column_stack([np.cos(ang), np.sin(ang), np.full_like(ang, fiber_tilt)])
    g.cell_data[arrays.FIBER] = np.where(muscle[:, None], fib, 0.0)
    p = np.asarray(g.points, dtype=float)
    bc = np.zeros(g.n_points, np.int8)
    bc[p[:, 2] < 1e-9] = arrays.BC_FIXED
    top = p[:, 2] > p[:, 2].max() - 1e-9
    bc[top] = arrays.BC_JOINT
    side = (p[:, 0] < 1e-9) & (bc == arrays.BC_FREE)
    bc[side] = arrays.BC_SLIDING
    d = np.zeros((g.n_points, 3))
    d[top] = [0.2, -0.1, 0.3] + 0.02 * p[top][:, [1, 0, 2]]
    n = np.zeros((g.n_points, 3))
    n[side] = [-1.0, 0.3, 0.2]
    d[side] = 0.05 * np.array([-1.0, 0.3, 0.2])
    g.point_data[arrays.BC] = bc
    g.point_data[arrays.BC_DISPLACEMENT] = d
    g.point_data[arrays.BC_NORMAL] = n
    return g


@pytest.fixture(scope="module")
def box():
    return mixed_box()


def test_engineering_constants_give_the_mtm_stiffness():
    """The orthotropic constants in the fibre frame, rotated, equal the MTM's 6x6 tensor."""
    ef, ec, nu = 0.5, 0.79, 0.43
    fiber = np.array([0.3, -0.5, 0.8])
    c = {k: float(v) for k, v in engineering_constants(ef, ec, nu).items()}
    S = np.zeros((6, 6))
    E = [c["E1"], c["E2"], c["E3"]]
    nus = {(0, 1): c["nu12"], (0, 2): c["nu13"], (1, 2): c["nu23"]}
    for i in range(3):
        S[i, i] = 1 / E[i]
    for (i, j), v in nus.items():
        S[i, j] = S[j, i] = -v / E[i]  # Abaqus: S_ij = -nu_ij / E_i
    S[3, 3], S[4, 4], S[5, 5] = 1 / c["G23"], 1 / c["G13"], 1 / c["G12"]
    assert np.isclose(c["nu31"] / c["E3"], c["nu13"] / c["E1"])  # FEBio's v31 is symmetric
    local = constitutive_matrix([ef], [ec], [nu], [[0.0, 0.0, 1.0]])[0]
    assert np.allclose(np.linalg.inv(S), local, rtol=1e-12)
    # the frame used for the orientation puts the fibre on local axis 3
    R = frames([fiber])[0]
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(R[:, 2], fiber / np.linalg.norm(fiber))


def test_inp_structure_and_numbering(box, tmp_path):
    text = write_inp(box, tmp_path / "box.inp").read_text()
    lines = text.splitlines()
    start = lines.index("*NODE, NSET=NGRID") + 1
    first = [float(v) for v in lines[start].split(",")]
    assert first[0] == 1 and np.allclose(first[1:], box.points[0])
    e = lines.index("*ELEMENT, TYPE=C3D4, ELSET=EALL") + 1
    ids = [int(v) for v in lines[e].split(",")]
    assert ids == [1, *(np.asarray(box.cell_connectivity[:4]) + 1).tolist()]
    assert "*ELSET, ELSET=FAT" in text and "*ELSET, ELSET=MASSETER_LEFT" in text
    assert text.count("*MATERIAL") == 2 and "TYPE=ENGINEERING CONSTANTS" in text
    n_aniso = int(np.sum(box.cell_data[arrays.E_FIBER] != box.cell_data[arrays.E_CROSS]))
    dist = lines.index("*DISTRIBUTION, NAME=FIBERS")
    assert lines[dist + 2 + n_aniso] == "*ORIENTATION, NAME=FIBER, SYSTEM=RECTANGULAR"
    assert text.count("*EQUATION") == int(np.sum(box[arrays.BC] == arrays.BC_SLIDING))
    assert max(len(line) for line in lines) <= 132  # ccx's card length


def test_feb_structure(box, tmp_path):
    root = ET.parse(write_feb(box, tmp_path / "box.feb")).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    nodes = root.findall("Mesh/Nodes/node")
    assert [int(n.get("id")) for n in nodes] == list(range(1, box.n_points + 1))
    elems = root.findall("Mesh/Elements/elem")
    assert sorted(int(e.get("id")) for e in elems) == list(range(1, box.n_cells + 1))
    conn = np.asarray(box.cell_connectivity).reshape(-1, 4) + 1
    for e in elems[:20]:
        assert [int(v) for v in e.text.split(",")] == conn[int(e.get("id")) - 1].tolist()
    materials = {m.get("name"): m for m in root.findall("Material/material")}
    parts = {b.get("name"): b for b in root.findall("Mesh/Elements")}
    for dom in root.findall("MeshDomains/SolidDomain"):  # every domain: a block and a material
        assert dom.get("name") in parts and dom.get("mat") in materials
    assert {m.get("type") for m in materials.values()} == {"isotropic elastic",
                                                          "orthotropic elastic"}
    node_sets = {s.get("name"): s.text.split(",") for s in root.findall("Mesh/NodeSet")}
    for bc in root.findall("Boundary/bc"):
        if bc.get("node_set"):
            assert bc.get("node_set") in node_sets
        value = bc.find("value")
        if value is not None and value.get("type") == "map":
            data = root.find(f"MeshData/NodeData[@name='{value.text}']")
            assert data is not None and data.get("node_set") == bc.get("node_set")
            assert len(data) == len(node_sets[bc.get("node_set")])
        for tag in ("value", "offset"):
            el = bc.find(tag)
            if el is not None and el.get("lc"):
                assert root.find(f"LoadData/load_controller[@id='{el.get('lc')}']") is not None
    for data in root.findall("MeshData/ElementData"):
        assert data.get("type") == "mat_axis" and data.get("elem_set") in parts
        assert len(data) == len(parts[data.get("elem_set")])
    n_aniso = int(np.sum(box.cell_data[arrays.E_FIBER] != box.cell_data[arrays.E_CROSS]))
    assert sum(len(d) for d in root.findall("MeshData/ElementData")) == n_aniso
    sliding = int(np.sum(box[arrays.BC] == arrays.BC_SLIDING))
    assert len(root.findall("Boundary/bc[@type='linear constraint']")) == sliding
    assert len(node_sets["joint"]) == int(np.sum(box[arrays.BC] == arrays.BC_JOINT))


def test_feb_sliding_constraint_is_the_normal_equation(box, tmp_path):
    """Each linear constraint, read back, says n . u = bc_displacement . n."""
    root = ET.parse(write_feb(box, tmp_path / "box.feb")).getroot()
    axis = {"x": 0, "y": 1, "z": 2}
    for bc in root.findall("Boundary/bc[@type='linear constraint']"):
        node = int(bc.find("node").text) - 1
        k = axis[bc.find("dof").text]
        coef = np.zeros(3)
        coef[k] = 1.0
        for child in bc.findall("child_dof"):
            assert int(child.find("node").text) - 1 == node
            coef[axis[child.find("dof").text]] = -float(child.find("value").text)
        n = box[arrays.BC_NORMAL][node] / np.linalg.norm(box[arrays.BC_NORMAL][node])
        scale = n[k]
        assert np.allclose(coef * scale, n)
        assert np.isclose(float(bc.find("offset").text) * scale,
                          box[arrays.BC_DISPLACEMENT][node] @ n)


@pytest.mark.parametrize("suffix", [".vtu", ".vtk", ".msh"])
def test_meshio_reads_back(box, tmp_path, suffix):
    grid = box.copy()
    grid.field_data["landmark_names"] = np.array(["nasion", "pogonion"])  # VTK: 'String'
    grid.field_data["landmark_points"] = np.ones((2, 3))
    grid.save(tmp_path / "vtk_native.vtu")
    with pytest.raises((Exception, SystemExit)):  # meshio on VTK's own writer
        meshio.read(tmp_path / "vtk_native.vtu")
    mesh = meshio.read(export(grid, tmp_path / f"grid{suffix}"))
    assert np.allclose(mesh.points, grid.points)
    assert np.array_equal(mesh.cells_dict["tetra"], np.asarray(grid.cell_connectivity).reshape(-1, 4))
    if suffix != ".msh":  # gmsh keeps its own data model
        assert np.allclose(mesh.point_data[arrays.BC_DISPLACEMENT], grid[arrays.BC_DISPLACEMENT])
        assert np.allclose(mesh.cell_data[arrays.FIBER][0], grid.cell_data[arrays.FIBER])


def test_polydata_reads_back(tmp_path):
    skin = pv.Sphere(theta_resolution=8, phi_resolution=8)
    skin.point_data["distance"] = np.arange(skin.n_points, dtype=float)
    mesh = meshio.read(export(skin, tmp_path / "skin.vtu"))
    assert np.allclose(mesh.point_data["distance"], skin["distance"])
    assert mesh.cells_dict["triangle"].shape == (skin.n_cells, 3)


def test_bad_input(box, tmp_path):
    with pytest.raises(ValueError, match="unknown extension '.xyz1'"):
        export(box, tmp_path / "a.xyz1")
    with pytest.raises(ValueError, match="linear tetrahedra"):
        write_inp(pv.ImageData(dimensions=(2, 2, 2)).cast_to_unstructured_grid(), tmp_path / "a.inp")
    grid = box.copy()
    del grid.cell_data[arrays.FIBER]
    with pytest.raises(ValueError, match="fiber"):
        write_feb(grid, tmp_path / "a.feb")
    assert not (tmp_path / "a.feb").exists()


def test_run_outputs_read_back_in_meshio(tmp_path):
    """The deformed mesh a run writes reads back in meshio, string field data and all."""
    from test_cli import _small_result

    from pvcmf.outputs import write_outputs

    result = _small_result()
    result.post.field_data[arrays.LANDMARK_NAMES] = np.array(["nasion", "pogonion"])
    files = write_outputs(result, tmp_path)
    mesh = meshio.read(files["deformed_mesh"])
    assert len(mesh.points) == result.post.n_points
    assert sum(len(c.data) for c in mesh.cells) == result.post.n_cells
    np.testing.assert_allclose(mesh.point_data[arrays.DISPLACEMENT],
                               result.post[arrays.DISPLACEMENT])
    assert arrays.LANDMARK_NAMES in result.post.field_data  # input untouched
