"""Boundary conditions of the MTM by elimination, and the rigid-mode check.

``bc`` codes (from :mod:`pvcmf.arrays`): free, fixed (``u = 0``), joint
(``u = bc_displacement``) and sliding (``u . n = bc_displacement . n`` with ``n = bc_normal``,
tangential part free). At a sliding node the displacement is written in a local frame
``u = R y`` with ``R = [t1, t2, n]``; ``y3`` is prescribed and ``y1, y2`` stay unknowns, so
the reduced system ``R^T K R`` restricted to the unknowns stays symmetric positive definite.

Before solving, every connected component of the mesh is checked for rigid motions that no
constraint removes (an unconstrained component, or one held only along a line, or only by
sliding nodes on a plane): each constraint direction ``d`` at point ``x`` removes the rigid
modes with ``[d, x x d] . [t, w] != 0``, so the 6x6 Gram matrix of those rows per component
must have full rank. Delegates to numpy and ``scipy.sparse.csgraph.connected_components``.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .. import arrays

log = logging.getLogger(__name__)

__all__ = ["Constraints", "RigidModeError", "SolutionWarning", "sliding_frames", "solution_checks"]


class RigidModeError(ValueError):
    """The constraints leave a rigid motion of a part of the mesh free."""


def sliding_frames(normals):
    """Orthonormal frames ``R = [t1, t2, n]`` (columns) for normals ``n`` (k, 3).

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.mtm import sliding_frames
    >>> R = sliding_frames([[0.0, 0.0, 2.0]])[0]
    >>> bool(np.allclose(R.T @ R, np.eye(3))), R[:, 2].tolist()
    (True, [0.0, 0.0, 1.0])
    """
    n = np.asarray(normals, dtype=float)
    n = n / np.linalg.norm(n, axis=1)[:, None]
    axis = np.zeros_like(n)
    axis[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    t1 = np.cross(n, axis)
    t1 /= np.linalg.norm(t1, axis=1)[:, None]
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


class Constraints:
    """Elimination data for a grid's ``bc`` arrays.

    Attributes
    ----------
    bc : (n,) int8 codes
    sliding : (k,) indices of sliding nodes; ``frames`` (k, 3, 3) their ``[t1, t2, n]``
    free : (3 n,) bool, unknown dofs in local coordinates
    prescribed : (3 n,) float, prescribed local values (zero on unknown dofs)

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.mtm import Constraints
    >>> grid = pv.ImageData(dimensions=(2, 2, 2)).triangulate()
    >>> grid.point_data[arrays.BC] = np.array([1, 0, 0, 0, 0, 0, 0, 3], dtype=np.int8)
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = np.ones((8, 3))
    >>> grid.point_data[arrays.BC_NORMAL] = np.tile([0.0, 0.0, 1.0], (8, 1))
    >>> c = Constraints(grid)
    >>> int(c.free.sum()), float(c.prescribed[-1])    # 3 fixed + 1 normal dof prescribed
    (20, 1.0)
    """

    def __init__(self, grid, used=None):
        n = grid.n_points
        bc = np.asarray(arrays.require_array(grid, arrays.BC, "point", dtype="iu", ncomp=1,
                                             producer="apply_plan"))
        bad = ~np.isin(bc, list(arrays.BC_CODES.values()))
        if np.any(bad):
            raise ValueError(
                f"point array {arrays.BC!r} must hold codes {arrays.BC_CODES}, got value "
                f"{int(bc[bad][0])} at point {int(np.flatnonzero(bad)[0])}"
            )
        self.n_points = n
        self.bc = bc.astype(np.int8)
        self.sliding = np.flatnonzero(self.bc == arrays.BC_SLIDING)
        if self.sliding.size:
            nrm = np.asarray(arrays.require_array(grid, arrays.BC_NORMAL, "point", dtype="f",
                                                  ncomp=3, producer="apply_plan"), dtype=float)
            ns = nrm[self.sliding]
            zero = ~(np.linalg.norm(ns, axis=1) > 0) | ~np.all(np.isfinite(ns), axis=1)
            if np.any(zero):
                raise ValueError(
                    f"point array {arrays.BC_NORMAL!r} must be a nonzero finite vector at sliding "
                    f"points; {int(zero.sum())} are not, e.g. point {int(self.sliding[zero][0])}"
                )
            self.frames = sliding_frames(ns)
        else:
            self.frames = np.zeros((0, 3, 3))
        free = np.ones((n, 3), dtype=bool)
        free[(self.bc == arrays.BC_FIXED) | (self.bc == arrays.BC_JOINT)] = False
        free[self.sliding, 2] = False
        self.used = np.ones(n, dtype=bool) if used is None else np.asarray(used, dtype=bool)
        # points in no tetrahedron are not part of the system: they keep their prescribed value
        free[~self.used] = False
        self.free = free.ravel()
        self.set_displacement(grid)

    def set_displacement(self, grid_or_array):
        """(Re)compute the prescribed local values from ``bc_displacement`` (array or grid)."""
        n = self.n_points
        needs = np.any((self.bc == arrays.BC_JOINT) | (self.bc == arrays.BC_SLIDING))
        if hasattr(grid_or_array, "point_data"):
            if needs:
                d = np.asarray(arrays.require_array(grid_or_array, arrays.BC_DISPLACEMENT, "point",
                                                    dtype="f", ncomp=3, producer="apply_plan"),
                               dtype=float)
            else:
                d = np.zeros((n, 3))
        else:
            d = np.asarray(grid_or_array, dtype=float)
            if d.shape != (n, 3):
                raise ValueError(f"bc_displacement must have shape ({n}, 3), got {d.shape}")
        y = np.zeros((n, 3))
        joint = self.bc == arrays.BC_JOINT
        y[joint] = d[joint]
        if self.sliding.size:
            y[self.sliding, 2] = np.einsum("ij,ij->i", d[self.sliding], self.frames[:, :, 2])
        if not np.all(np.isfinite(y)):
            raise ValueError(f"point array {arrays.BC_DISPLACEMENT!r} must be finite at joint "
                             "and sliding points")
        self.prescribed = y.ravel()
        self.prescribed[self.free] = 0.0
        return self.prescribed

    # ------------------------------------------------------------------ frames
    def rotate_blocks(self, data, rows, cols):
        """In place: ``K_ij <- R_i^T K_ij R_j`` for the blocks touching sliding nodes."""
        if not self.sliding.size:
            return data
        slot = np.full(self.n_points, -1)
        slot[self.sliding] = np.arange(self.sliding.size)
        sr, sc = slot[rows], slot[cols]
        left = np.flatnonzero(sr >= 0)
        data[left] = np.einsum("bji,bjk->bik", self.frames[sr[left]], data[left])
        right = np.flatnonzero(sc >= 0)
        data[right] = np.einsum("bij,bjk->bik", data[right], self.frames[sc[right]])
        return data

    def to_global(self, y):
        """Displacements ``u = R y`` (n, 3) from local values ``y`` (3 n,)."""
        u = np.array(y, dtype=float).reshape(-1, 3)
        if self.sliding.size:
            u[self.sliding] = np.einsum("bij,bj->bi", self.frames, u[self.sliding])
        return u

    def to_local(self, u):
        """Local values ``y = R^T u`` (3 n,) from displacements (n, 3)."""
        y = np.array(u, dtype=float).reshape(-1, 3)
        if self.sliding.size:
            y[self.sliding] = np.einsum("bji,bj->bi", self.frames, y[self.sliding])
        return y.ravel()

    # ------------------------------------------------------------------ checks
    def check_rigid_modes(self, points, indptr, indices):
        """Raise :class:`RigidModeError` if a connected part keeps a free rigid motion.

        ``indptr, indices`` are the node adjacency (the block pattern of the stiffness).
        """
        n = self.n_points
        adj = sp.csr_matrix((np.ones(indices.size, dtype=np.int8), indices, indptr), shape=(n, n))
        ncomp, label = connected_components(adj, directed=False)
        used = self.used
        # constraint rows: fixed/joint -> x, y, z; sliding -> n
        held = used & ((self.bc == arrays.BC_FIXED) | (self.bc == arrays.BC_JOINT))
        hn = np.flatnonzero(held)
        node = np.concatenate([np.repeat(hn, 3), self.sliding[used[self.sliding]]])
        dirs = np.concatenate([np.tile(np.eye(3), (hn.size, 1)),
                               self.frames[used[self.sliding], :, 2]])
        comp = label[node]
        pts = np.asarray(points, dtype=float)
        counts = np.bincount(label[used], minlength=ncomp).astype(float)
        centre = np.stack([np.bincount(label[used], weights=pts[used, k], minlength=ncomp)
                           for k in range(3)], axis=1) / np.maximum(counts, 1)[:, None]
        rel = pts - centre[label]
        size = np.sqrt(np.bincount(label[used], weights=np.einsum("ij,ij->i", rel, rel)[used],
                                   minlength=ncomp) / np.maximum(counts, 1))
        size[size == 0] = 1.0
        rows = np.concatenate([dirs, np.cross(rel[node] / size[comp][:, None], dirs)], axis=1)
        outer = (rows[:, :, None] * rows[:, None, :]).reshape(-1, 36)
        # per-component sums of the 6x6 outer products: one sparse product (no BLAS)
        member = sp.csr_matrix((np.ones(comp.size), comp, np.arange(comp.size + 1)),
                               shape=(comp.size, ncomp)).T.tocsr()
        gram = np.asarray(member @ outer).reshape(ncomp, 6, 6)
        active = np.flatnonzero(counts > 0)
        ev = np.linalg.eigvalsh(gram[active])
        free_modes = np.sum(ev <= 1e-9 * np.maximum(ev[:, -1:], 1e-300), axis=1)
        bad = active[free_modes > 0]
        if bad.size:
            c = bad[0]
            members = np.flatnonzero((label == c) & used)
            k = int(free_modes[np.searchsorted(active, c)])
            nh = int(np.sum(held[members]))
            ns = int(np.sum(self.bc[members] == arrays.BC_SLIDING))
            raise RigidModeError(
                f"connected component {int(c)} of the mesh ({members.size} nodes, e.g. node "
                f"{int(members[0])}) keeps {k} rigid motion(s) that no boundary condition removes: "
                f"it has {nh} fixed/joint and {ns} sliding nodes. Fix or join at least three "
                f"non-collinear nodes of every part (or remove the part)"
                + (f"; {bad.size - 1} more component(s) are unconstrained" if bad.size > 1 else "")
            )
        return ncomp


class SolutionWarning(UserWarning):
    """A solution that real tissue cannot follow: inverted tetrahedra, runaway free nodes."""


#: :func:`solution_checks` warns when a free node moves more than this many times the
#: largest prescribed move (linear elasticity held by moving bone rarely exceeds 1)
MAX_FREE_RATIO = 1.5


def solution_checks(points, cells, u, bc, bc_displacement, *, warn=True):
    """Count inverted tetrahedra and the free-to-prescribed displacement ratio.

    A tetrahedron is inverted when its signed volume after the move has the opposite sign
    of (or is zero against) its rest volume. The ratio is the largest displacement of a
    free or sliding node over the largest prescribed ``bc_displacement`` of a joint or
    sliding node (NaN when nothing is prescribed to move). Warns
    (:class:`SolutionWarning`) when a tetrahedron is inverted or the ratio exceeds
    :data:`MAX_FREE_RATIO`.

    Returns
    -------
    (int, float)

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.mtm.constraints import solution_checks
    >>> pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    >>> u = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, -2.0]])   # apex through the base
    >>> solution_checks(pts, np.array([[0, 1, 2, 3]]), u, np.array([1, 1, 1, 2]), u, warn=False)
    (1, 0.0)
    """
    pts = np.asarray(points, dtype=float)
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 4)
    u = np.asarray(u, dtype=float)

    def volumes(x):
        a = x[cells[:, 0]]
        return np.einsum("ij,ij->i", np.cross(x[cells[:, 1]] - a, x[cells[:, 2]] - a),
                         x[cells[:, 3]] - a)

    rest, moved = volumes(pts), volumes(pts + u)
    inverted = int(np.sum(np.sign(moved) != np.sign(rest)))
    bc = np.asarray(bc)
    mag = np.linalg.norm(u, axis=1)
    driven = (bc == arrays.BC_JOINT) | (bc == arrays.BC_SLIDING)
    loose = (bc == arrays.BC_FREE) | (bc == arrays.BC_SLIDING)
    top = float(np.linalg.norm(np.asarray(bc_displacement, float)[driven], axis=1).max(initial=0))
    ratio = float(mag[loose].max(initial=0.0) / top) if top > 0 else float("nan")
    if warn and (inverted or ratio > MAX_FREE_RATIO):
        warnings.warn(
            f"the MTM solution inverts {inverted} of {len(cells)} tetrahedra and moves a free "
            f"node {ratio:.2f} times the largest prescribed move ({top:.3g} mm); field data "
            f"{arrays.MTM_INVERTED!r} and {arrays.MTM_FREE_RATIO!r} hold both. A linear model "
            "is not valid there: check the boundary conditions (tissue torn between fixed and "
            "moving nodes one element apart) or refine the mesh",
            SolutionWarning, stacklevel=3,
        )
    return inverted, ratio
