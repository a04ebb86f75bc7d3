"""Exports of the predicted skin for planning software (``pvcmf.io.write_surface``).

Read back with an independent reader (meshio) and with :func:`pvcmf.io.read_surface`.
"""

import meshio
import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.io import read_surface, write_surface


@pytest.fixture
def skin():
    s = pv.ParametricEllipsoid(70, 95, 110, u_res=40, v_res=30).clean().triangulate()
    s[arrays.DISPLACEMENT] = np.tile([0.0, -1.0, 0.5], (s.n_points, 1))
    return s


def _rows(points):
    p = np.asarray(points, dtype=float)
    return p[np.lexsort(p.T[::-1])]


@pytest.mark.parametrize("ext", ["obj", "ply", "vtp"])
def test_point_for_point_formats(skin, tmp_path, ext):
    path = write_surface(skin, tmp_path / f"skin.{ext}")
    assert path.exists() and not list(tmp_path.glob(".*part*"))
    back = read_surface(path)
    np.testing.assert_allclose(back.points, skin.points, rtol=0, atol=1e-4)
    assert back.n_cells == skin.n_cells
    if ext != "vtp":  # meshio, an independent reader
        np.testing.assert_allclose(meshio.read(path).points, skin.points, rtol=0, atol=1e-4)


@pytest.mark.parametrize("binary", [True, False])
def test_stl_same_points_and_triangles(skin, tmp_path, binary):
    path = write_surface(skin, tmp_path / "skin.STL", binary=binary)
    back = read_surface(path)
    assert back.n_points == skin.n_points and back.n_cells == skin.n_cells
    np.testing.assert_allclose(_rows(back.points), _rows(skin.points), rtol=0, atol=1e-4)
    np.testing.assert_allclose(_rows(meshio.read(path).points), _rows(skin.points), rtol=0,
                               atol=1e-4)
    # the triangles are the same triangles (as sets of corner coordinates)
    tri_a = np.sort(skin.points[skin.regular_faces].sum(axis=1), axis=0)
    tri_b = np.sort(back.points[back.regular_faces].sum(axis=1), axis=0)
    np.testing.assert_allclose(tri_a, tri_b, atol=1e-3)


def test_bad_input(skin, tmp_path):
    with pytest.raises(ValueError, match=r"path must end in one of .stl, .obj"):
        write_surface(skin, tmp_path / "skin.xyz")
    with pytest.raises(TypeError, match="surface must be a pyvista dataset"):
        write_surface(np.zeros((3, 3)), tmp_path / "a.stl")
    with pytest.raises(FileNotFoundError, match="surface file not found"):
        read_surface(tmp_path / "missing.ply")
    assert not list(tmp_path.iterdir())
