"""The paper's relaxation for the MTM: ``u_j <- -K_jj^-1 sum_k K_jk u_k`` at every vertex.

Vectorised as a multicolour block Gauss-Seidel (a Jones-Plassmann colouring of the node
graph; one colour at a time, all vertices of a colour at once), with over-relaxation
``omega``. It converges slowly, and not usefully for ``nu`` near 0.5; it is kept as the
paper's reference method. Pure numpy / scipy.sparse.
"""

from __future__ import annotations

import logging

import numpy as np

from ...progress import Progress
from .._common import ConvergenceError
from .cg import masked_diag_inverse

log = logging.getLogger(__name__)


def colour(indptr, indices, active, seed=0):
    """Vectorised Jones-Plassmann colouring of the node graph (only ``active`` nodes)."""
    n = len(indptr) - 1
    rng = np.random.default_rng(seed)
    weight = rng.random(n)
    out = np.full(n, -1)
    out[~active] = -2
    rows = np.repeat(np.arange(n), np.diff(indptr))
    off = rows != indices
    rows, cols = rows[off], indices[off]
    c = 0
    while np.any(out == -1):
        todo = out == -1
        w = np.where(todo, weight, -1.0)
        nb = np.full(n, -1.0)
        np.maximum.at(nb, rows, w[cols])
        out[todo & (w > nb)] = c
        c += 1
    return out


class Relaxation:
    """Multicolour block Gauss-Seidel of one :class:`~pvcmf.mtm.Solver`."""

    #: sweeps between two residual checks
    check = 10

    def __init__(self, solver):
        self.s = solver
        self.colours = None

    def setup(self, refactor=True):
        s = self.s
        asm, cons = s.assembler, s.constraints
        n = asm.n_points
        fm = cons.free.reshape(n, 3)
        A = asm.bsr(s._data * (fm[asm.rows][:, :, None] & fm[asm.indices][:, None, :])).tocsr()
        self.dinv = masked_diag_inverse(s)
        if self.colours is None:
            c = colour(asm.indptr, asm.indices, asm.used & fm.any(axis=1))
            self.colours = [np.flatnonzero(c == k) for k in range(c.max() + 1)]
            log.debug("relaxation: %d colours", len(self.colours))
        self.rows = []
        for nodes in self.colours:
            r = (3 * nodes[:, None] + np.arange(3)).ravel()
            self.rows.append((nodes, r, A[r]))

    def solve(self, b, nb, y0, info):
        s = self.s
        cons = s.constraints
        maxiter = 20000 if s.maxiter is None else int(s.maxiter)
        bfull = np.zeros(3 * cons.n_points)
        bfull[s.F] = b
        y = cons.prescribed.copy()
        if y0 is not None:
            y[s.F] = y0
        # the masked A has no coupling to prescribed dofs (that is in b) and the residual is
        # masked to the unknowns, so prescribed values stay where they start
        dinv, omega, free = self.dinv, s.omega, cons.free
        res, sweeps = np.inf, 0
        with Progress(total=maxiter, desc="MTM relaxation", enabled=s.progress_bar,
                      unit="sweep") as bar:
            while sweeps < maxiter:
                for nodes, rows, Ar in self.rows:
                    r = (bfull[rows] - Ar @ y).reshape(-1, 3)
                    r *= free[rows].reshape(-1, 3)
                    y[rows] += omega * np.einsum("nij,nj->ni", dinv[nodes], r).ravel()
                sweeps += 1
                bar.step()
                if sweeps % self.check == 0 or sweeps == maxiter:
                    res = s._residual(y[s.F], b, nb)
                    if not np.isfinite(res) or res <= s.tol:
                        break
        info.update(residual=float(res), iterations=sweeps)
        if not res <= s.tol:
            raise ConvergenceError(
                f"relaxation did not reach tol {s.tol:.0e} in {sweeps} sweeps (relative "
                f"residual {res:.2e}); the paper's local method converges slowly, and not at all "
                "usefully for nu near 0.5: use method='direct' or 'cg'"
            )
        return y[s.F]
