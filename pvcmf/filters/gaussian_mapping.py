"""Paper 001's Gaussian mapping of a tetrahedral mesh's displacement onto a dense skin, as a
precomputed sparse operator (:class:`SurfaceMapping`; used by
:func:`pvcmf.filters.map_to_surface` with ``method="gaussian"`` and by the sweeps).

Delegates to :class:`scipy.spatial.cKDTree` (neighbours within the radius), batched
:func:`numpy.linalg.solve` (the moment matrices) and :mod:`scipy.sparse` (the operator).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

__all__ = ["SurfaceMapping"]


class SurfaceMapping:
    """The Gaussian moving least-squares mapping as a precomputed sparse operator.

    The affine fit is linear in the grid displacement (only the final clamp to the
    neighbours' range is not) and its weights depend only on the grid and skin points, so
    the mapping is a sparse matrix ``W`` (skin points x grid points) built once; each field
    then costs one sparse product and a vectorised clamp (``numpy.minimum.reduceat``). The
    fit's value at ``p``, ``c = e0 . M^-1 r``, is ``(M^-1 e0) . r`` because the moment
    matrix ``M`` is symmetric, so row ``i`` of ``W`` is
    ``w_ij (1, (x_j - p_i) / sigma) . M_i^-1 e0``; rows whose moment matrix is singular
    (condition > 1e8 after scaling) hold the Gaussian-weighted mean. Used by
    :func:`map_to_surface` and by parameter sweeps that map many fields on one mesh
    (:class:`pvcmf.sweeps.PipelineEvaluation`).

    Parameters
    ----------
    grid_points, skin_points : array_like, shape (m, 3) and (n, 3)
        Grid nodes and skin points (mm).
    sigma, radius : float
        Gaussian width and neighbourhood radius (mm), both > 0.

    Attributes
    ----------
    W : scipy.sparse.csr_matrix, shape (n, m)
    support : ndarray, shape (n,)
        Sum of the Gaussian weights of each skin point (0: no grid node within ``radius``).
    """

    def __init__(self, grid_points, skin_points, sigma, radius):
        x = np.asarray(grid_points, float)
        p = np.asarray(skin_points, float)
        n, m = len(p), len(x)
        pairs = cKDTree(p).sparse_distance_matrix(cKDTree(x), radius, output_type="ndarray")
        w = np.exp(-0.5 * (pairs["v"] / sigma) ** 2) - np.exp(-0.5 * (radius / sigma) ** 2)
        keep = w > 0
        i, j, w = pairs["i"][keep], pairs["j"][keep], w[keep]
        order = np.lexsort((j, i))
        i, j, w = i[order], j[order], w[order]
        basis = np.column_stack([np.ones(len(i)), (x[j] - p[i]) / sigma])  # well conditioned
        moments = np.empty((n, 4, 4))
        for a in range(4):  # 10 unique moments by bincount, not a loop over points
            for b in range(a, 4):
                moments[:, a, b] = moments[:, b, a] = np.bincount(i, w * basis[:, a] * basis[:, b],
                                                                  minlength=n)
        self.support = moments[:, 0, 0].copy()
        has = self.support > 0
        coef = np.zeros((n, 4))
        idx = np.flatnonzero(has)
        cond_ok = np.linalg.cond(moments[idx] / self.support[idx][:, None, None]) < 1e8
        fit, mean = idx[cond_ok], idx[~cond_ok]
        if fit.size:  # affine fit where well conditioned
            e0 = np.zeros((fit.size, 4, 1))
            e0[:, 0] = 1.0
            coef[fit] = np.linalg.solve(moments[fit], e0)[:, :, 0]
        coef[mean, 0] = 1.0 / self.support[mean]  # weighted mean elsewhere
        values = w * np.einsum("ij,ij->i", basis, coef[i])
        self.W = sp.csr_matrix((values, (i, j)), shape=(n, m))
        self._neighbours = j
        self._has = has
        self._starts = np.searchsorted(i, np.arange(n))[has]

    def __call__(self, u):
        """Skin displacement ``(n, 3)`` for the grid displacement ``u`` ``(m, 3)``."""
        u = np.asarray(u, float)
        disp = np.asarray(self.W @ u)
        if self._starts.size:
            # no new extrema: where the skin point lies outside its neighbours' cloud (the
            # edge of the mesh) the affine fit extrapolates; clamp each component to the
            # neighbours' range
            v = u[self._neighbours]
            lo = np.minimum.reduceat(v, self._starts, axis=0)
            hi = np.maximum.reduceat(v, self._starts, axis=0)
            disp[self._has] = np.clip(disp[self._has], lo, hi)
        return disp
