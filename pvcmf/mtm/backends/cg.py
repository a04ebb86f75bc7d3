"""Conjugate gradient for the MTM, preconditioned by algebraic multigrid or block Jacobi.

One V-cycle of pyamg's smoothed aggregation (the rigid translations, in the local frames of
the sliding nodes, as near-null space; :data:`AMG_OPTIONS`) or the inverses of the node
blocks (block Jacobi) precondition :func:`scipy.sparse.linalg.cg`. Warm-startable.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ...progress import Progress
from .._common import ConvergenceError

#: near-null space of the AMG: the first 3 rigid modes (translations) or all 6 (+ rotations)
AMG_NEAR_NULL = 3
#: pyamg smoothed-aggregation options: energy-minimising prolongation, one forward
#: Gauss-Seidel sweep before and one backward after the coarse correction
AMG_OPTIONS = dict(
    symmetry="symmetric",
    improve_candidates=None,
    smooth=("energy", {"degree": 1, "maxiter": 2}),
    presmoother=("gauss_seidel", {"sweep": "forward"}),
    postsmoother=("gauss_seidel", {"sweep": "backward"}),
)


def rigid_modes(points):
    """(3 n, 6) translations and small rotations about the centroid."""
    x = points - points.mean(axis=0)
    n = len(points)
    B = np.zeros((n, 3, 6))
    B[:, [0, 1, 2], [0, 1, 2]] = 1.0
    for k, w in enumerate(np.eye(3)):
        B[:, :, 3 + k] = np.cross(w, x)
    return B.reshape(3 * n, 6)


class VCycle(spla.LinearOperator):
    """One V-cycle of a pyamg hierarchy as a preconditioner, from a zero initial guess.

    ``MultilevelSolver.aspreconditioner`` also computes ``||b - A x||`` before and after the
    cycle (two extra products with the fine matrix per CG iteration); this cycle does not.
    """

    def __init__(self, ml):
        A = ml.levels[0].A
        super().__init__(dtype=A.dtype, shape=A.shape)
        self.ml = ml

    def _cycle(self, lvl, b):
        levels = self.ml.levels
        level = levels[lvl]
        x = np.zeros_like(b)
        level.presmoother(level.A, x, b)
        coarse_b = level.R @ (b - level.A @ x)
        if lvl == len(levels) - 2:
            coarse_x = self.ml.coarse_solver(levels[-1].A, coarse_b)
        else:
            coarse_x = self._cycle(lvl + 1, coarse_b)
        x += level.P @ coarse_x
        level.postsmoother(level.A, x, b)
        return x

    def _matvec(self, b):
        b = np.ravel(b)
        if len(self.ml.levels) == 1:
            return self.ml.coarse_solver(self.ml.levels[0].A, b)
        return self._cycle(0, b)


def masked_diag_inverse(solver):
    """Inverses of the node blocks of K (local frame), identity-scaled on prescribed dofs."""
    asm = solver.assembler
    n = asm.n_points
    diag_pos = np.flatnonzero(asm.rows == asm.indices)
    D = np.zeros((n, 3, 3))
    D[asm.rows[diag_pos]] = solver._data[diag_pos]
    fm = solver.constraints.free.reshape(n, 3)
    D *= fm[:, :, None] & fm[:, None, :]
    scale = np.where(fm, 0.0, np.maximum(np.abs(np.trace(D, axis1=1, axis2=2)) / 3, 1.0)[:, None])
    scale[~asm.used] = 1.0
    D[:, [0, 1, 2], [0, 1, 2]] += scale
    return np.linalg.inv(D)


def _has_pyamg():
    try:
        import pyamg  # noqa: F401
    except ImportError:
        return False
    return True


class CG:
    """Preconditioned CG of one :class:`~pvcmf.mtm.Solver` (``preconditioner`` 'amg',
    'jacobi' or None: AMG when pyamg imports)."""

    def __init__(self, solver):
        self.s = solver
        self.name = None
        self.M = None

    def setup(self, refactor=True):
        s = self.s
        use_amg = s.preconditioner == "amg" or (s.preconditioner is None and _has_pyamg())
        if use_amg:
            import pyamg

            modes = rigid_modes(s.points)[:, :AMG_NEAR_NULL]
            B = np.stack([s.constraints.to_local(c.reshape(-1, 3)) for c in modes.T],
                         axis=1)[s.F]
            self.ml = pyamg.smoothed_aggregation_solver(s.K_ff, B=B, **AMG_OPTIONS)
            self.M, self.name = VCycle(self.ml), "amg"
        else:
            dinv = masked_diag_inverse(s)
            n = s.assembler.n_points
            D = sp.bsr_matrix((dinv, np.arange(n), np.arange(n + 1)), shape=(3 * n, 3 * n)).tocsr()
            self.M, self.name = D[s.F][:, s.F], "jacobi"

    def solve(self, b, nb, y0, info):
        s = self.s
        maxiter = 2000 if s.maxiter is None else int(s.maxiter)
        count = [0]
        with Progress(total=maxiter, desc="MTM cg", enabled=s.progress_bar,
                      unit="iteration") as bar:
            def cb(_):
                count[0] += 1
                bar.step()

            y, flag = spla.cg(s.K_ff, b, x0=y0, rtol=s.tol, atol=0.0, maxiter=maxiter,
                              M=self.M, callback=cb)
        res = s._residual(y, b, nb)
        info.update(residual=res, iterations=count[0], preconditioner=self.name)
        if flag != 0 or not np.isfinite(res) or res > 10 * s.tol:
            raise ConvergenceError(
                f"cg ({self.name}) did not reach tol {s.tol:.0e} in {count[0]} "
                f"iterations (relative residual {res:.2e}); raise maxiter or use method='direct'"
            )
        return y
