"""Small irregular tetrahedral meshes and an independent constitutive law for the MTM tests."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from pvcmf import arrays

VOIGT = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))


def jittered_box(shape=(7, 5, 5), size=(6.0, 4.0, 4.0), jitter=0.3, seed=0):
    """A box split into tetrahedra with every interior node moved at random (irregular)."""
    spacing = [s / (d - 1) for s, d in zip(size, shape)]
    grid = pv.ImageData(dimensions=shape, spacing=spacing).triangulate()
    pts = np.array(grid.points, dtype=float)
    interior = np.all((pts > 1e-9) & (pts < np.array(size) - 1e-9), axis=1)
    rng = np.random.default_rng(seed)
    pts[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 3)) * spacing
    grid.points = pts
    return grid


def delaunay_box(n=250, seed=1):
    """Delaunay tetrahedra of random points in the unit cube (slivers included)."""
    rng = np.random.default_rng(seed)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
    faces = rng.random((60, 3))
    axis = rng.integers(0, 3, 60)
    faces[np.arange(60), axis] = rng.integers(0, 2, 60)
    pts = np.vstack([corners, faces, 0.05 + 0.9 * rng.random((n, 3))])
    grid = pv.PolyData(pts).delaunay_3d().clean()
    grid.points = np.asarray(grid.points, dtype=float)
    return grid


def boundary_nodes(grid):
    surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface")
    mask = np.zeros(grid.n_points, bool)
    mask[surf["vtkOriginalPointIds"]] = True
    return mask


def set_materials(grid, ef, ec, nu, fiber=None):
    m = grid.n_cells
    grid.cell_data[arrays.E_FIBER] = np.broadcast_to(np.asarray(ef, float), (m,)).copy()
    grid.cell_data[arrays.E_CROSS] = np.broadcast_to(np.asarray(ec, float), (m,)).copy()
    grid.cell_data[arrays.NU] = np.broadcast_to(np.asarray(nu, float), (m,)).copy()
    f = np.zeros((m, 3)) if fiber is None else np.broadcast_to(np.asarray(fiber, float), (m, 3))
    grid.cell_data[arrays.FIBER] = np.array(f)
    return grid


def set_bc(grid, bc, disp=None, normal=None):
    n = grid.n_points
    grid.point_data[arrays.BC] = np.asarray(bc, dtype=np.int8)
    grid.point_data[arrays.BC_DISPLACEMENT] = np.zeros((n, 3)) if disp is None else np.asarray(disp, float)
    grid.point_data[arrays.BC_NORMAL] = np.zeros((n, 3)) if normal is None else np.asarray(normal, float)
    return grid


def frame(fiber):
    """Orthonormal Q with Q[:, 2] = fiber (any completion: the material is transversely isotropic)."""
    a = np.asarray(fiber, float) / np.linalg.norm(fiber)
    h = np.eye(3)[np.argmin(np.abs(a))]
    t1 = np.cross(a, h)
    t1 /= np.linalg.norm(t1)
    return np.column_stack([t1, np.cross(a, t1), a])


def reference_C(ef, ec, nu, fiber=None):
    """6x6 global stiffness built independently: invert the issue's compliance, rotate the tensor."""
    S = np.zeros((6, 6))
    S[:3, :3] = [[1 / ec, -nu / ec, -nu / ec], [-nu / ec, 1 / ec, -nu / ec], [-nu / ec, -nu / ec, 1 / ef]]
    gf = ef / (2 * (1 + nu))
    S[3, 3] = S[4, 4] = 1 / gf
    S[5, 5] = 2 * (1 + nu) / ec
    C = np.linalg.inv(S)
    if fiber is None or not np.any(fiber):
        return C
    T = np.zeros((3, 3, 3, 3))
    for p, (i, j) in enumerate(VOIGT):
        for q, (k, l) in enumerate(VOIGT):
            for a, b in {(i, j), (j, i)}:
                for c, d in {(k, l), (l, k)}:
                    T[a, b, c, d] = C[p, q]
    Q = frame(fiber)
    Tg = np.einsum("ia,jb,kc,ld,abcd->ijkl", Q, Q, Q, Q, T)
    return np.array([[Tg[i, j, k, l] for (k, l) in VOIGT] for (i, j) in VOIGT])


def skfem_stiffness(grid):
    """Stiffness assembled by scikit-fem (P1 vector elements) with :func:`reference_C`.

    Returns (K, nodal_dofs) with nodal_dofs[c, i] the dof of component c at node i.
    """
    import skfem
    from skfem.helpers import sym_grad

    cells = np.asarray(grid.cell_connectivity).reshape(-1, 4)
    mesh = skfem.MeshTet(np.array(grid.points).T.copy(), cells.T.copy())
    basis = skfem.Basis(mesh, skfem.ElementVectorH1(skfem.ElementTetP1()), intorder=1)
    ef, ec, nu = grid[arrays.E_FIBER], grid[arrays.E_CROSS], grid[arrays.NU]
    fib = grid[arrays.FIBER]
    C = np.array([reference_C(ef[e], ec[e], nu[e], fib[e]) for e in range(grid.n_cells)])
    nqp = basis.X.shape[1]
    w = {f"c{p}{q}": np.repeat(C[:, p, q][:, None], nqp, axis=1) for p in range(6) for q in range(6)}

    def voigt(e):
        return [e[0, 0], e[1, 1], e[2, 2], 2 * e[1, 2], 2 * e[0, 2], 2 * e[0, 1]]

    @skfem.BilinearForm
    def form(u, v, w):
        eu, ev = voigt(sym_grad(u)), voigt(sym_grad(v))
        return sum(w[f"c{p}{q}"] * eu[q] * ev[p] for p in range(6) for q in range(6))

    return skfem.asm(form, basis, **w).tocsr(), basis.nodal_dofs
