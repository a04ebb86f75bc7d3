"""An open skin's normals point out of the head on every piece, however its triangles
arrive wound (a non-manifold edge or a separate piece stops VTK's consistency pass)."""

import numpy as np
import pyvista as pv
from scipy import ndimage

from pvcmf import arrays
from pvcmf.filters.skin import _open_outward_normals

CENTRES = np.array([[20.0, 20.0, 20.0], [42.0, 20.0, 20.0]])
RADII = (10.0, 4.0)


def _two_balls():
    x, y, z = np.meshgrid(*(np.arange(n, dtype=float) for n in (60, 40, 40)), indexing="ij")
    mask = np.zeros(x.shape, dtype=bool)
    for c, r in zip(CENTRES, RADII):
        mask |= (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < r ** 2
    field = ndimage.gaussian_filter(mask.astype(np.float32), 1.0)
    grid = pv.ImageData(dimensions=field.shape)
    grid.point_data["f"] = field.transpose(2, 1, 0).ravel()
    surf = grid.contour([0.5], scalars="f").triangulate().clean()
    return surf, field


def _outward_share(surf):
    tri = surf.faces.reshape(-1, 4)[:, 1:]
    p = np.asarray(surf.points)
    a, b, c = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    n = np.cross(b - a, c - a)
    centre = (a + b + c) / 3
    ball = np.argmin(np.linalg.norm(centre[:, None] - CENTRES[None], axis=2), axis=1)
    return np.einsum("ij,ij->i", n, centre - CENTRES[ball]) > 0, ball


def test_a_piece_wound_inward_is_turned_out_on_its_own():
    surf, field = _two_balls()
    outward, ball = _outward_share(surf)
    tri = surf.faces.reshape(-1, 4)[:, 1:].copy()
    # wind the big ball outward and the small one inward, as a broken pass might leave them
    wrong = (ball == 1) == outward
    fix = (ball == 0) & ~outward
    tri[wrong | fix] = tri[wrong | fix][:, ::-1]
    mixed = pv.PolyData(surf.points.copy(), np.column_stack([np.full(len(tri), 3), tri]).ravel())
    assert not _outward_share(mixed)[0][ball == 1].any()
    result = _open_outward_normals(mixed, field, np.zeros(3), np.ones(3))
    out, ball = _outward_share(result)
    assert out.all(), f"{int((~out).sum())} of {len(out)} triangles point into the head"
    n = np.asarray(result.point_data[arrays.NORMALS])
    p = np.asarray(result.points)
    near = np.argmin(np.linalg.norm(p[:, None] - CENTRES[None], axis=2), axis=1)
    assert np.all(np.einsum("ij,ij->i", n, p - CENTRES[near]) > 0)
    assert mixed.n_cells == result.n_cells  # the input surface is left as it was
    assert not _outward_share(mixed)[0][ball == 1].any()
