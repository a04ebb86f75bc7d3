"""Map tetrahedral displacements to a dense skin surface with Gaussian smoothing (paper 001).

Paper 001 computes the deformation on a coarse tetrahedral mesh of the tissue that moves
and maps it to a dense surface of the whole skin, "with some kind of Gaussian smoothing",
so that meshes of any size are compared on the same skin. Its reference [3] gives no
formula; pvcmf uses a Gaussian-weighted *moving least-squares* fit:

for each skin point ``p`` the displacements ``u_j`` of the grid nodes ``x_j`` within
``radius`` (default ``3 sigma``) are fitted by an affine field
``u(x) = c + G (x - p)`` minimising ``sum_j w_j |u(x_j) - u_j|^2`` with
``w_j = max(exp(-|x_j - p|^2 / 2 sigma^2) - exp(-radius^2 / 2 sigma^2), 0)``, and ``p``
moves by ``c``. The weight goes continuously to zero at ``radius``, so the mapped field is
continuous and smooth (it is a smooth function of ``p`` wherever neighbours exist).
Properties: an affine displacement field is reproduced exactly (no smoothing bias); for
a curved field the bias is of order ``sigma^2 |d^2 u|`` (second derivatives), which is the
smoothing; noise of the grid field is averaged over the ~``sigma``-ball.
Where a skin point has too few neighbours for the affine fit (a singular 4x4 moment
matrix: fewer than four non-coplanar nodes), the Gaussian-weighted mean is used; the
result is clamped, per component, to the range of the neighbours' displacements (no new
extrema: at the edge of the mesh the affine fit would extrapolate, and an affine field is
then reproduced only where the point lies among its neighbours); skin
points with no grid node within ``radius`` (parts of the head that are not simulated) get
zero displacement, and point array ``SUPPORT`` (the sum of the weights) tells which.

Delegates to scipy: :meth:`scipy.spatial.cKDTree.sparse_distance_matrix` for the
neighbour pairs, :func:`numpy.bincount` for the weighted moments, one batched
:func:`numpy.linalg.solve` of 4x4 systems and a :class:`scipy.sparse.csr_matrix` operator
(:class:`SurfaceMapping`) that sweeps reuse for every field on the same mesh.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv
from scipy.spatial import cKDTree

from .. import arrays
from ..progress import Progress

log = logging.getLogger(__name__)

#: point array written by :func:`map_to_surface`: sum of the Gaussian weights (0 = no grid
#: node within the radius, displacement set to zero)
SUPPORT = arrays.MAPPING_SUPPORT


def map_to_surface(grid, skin, *, sigma=2.0, radius=None, warp=True, progress_bar=False):
    """Map the grid's point ``displacement`` onto a dense skin surface (paper 001).

    Parameters
    ----------
    grid : pyvista.DataSet
        Tetrahedral grid (any point set) with point array ``arrays.DISPLACEMENT``.
    skin : pyvista.DataSet
        Dense skin surface (e.g. :func:`pvcmf.filters.extract_skin` of the label image),
        in the grid's rest frame.
    sigma : float, default 2.0
        Gaussian width (mm); larger smooths more.
    radius : float, optional
        Neighbourhood radius (mm); default ``3 * sigma``.
    warp : bool, default True
        Move the skin points by the mapped displacement (the predicted dense skin).
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.DataSet
        Copy of ``skin`` with point arrays ``arrays.DISPLACEMENT`` (float64 (n, 3), mm)
        and ``SUPPORT``; points moved when ``warp``.

    Raises
    ------
    ValueError
        Missing ``displacement``, empty inputs, or ``sigma`` / ``radius`` not positive.

    Examples
    --------
    >>> import numpy as np, pyvista as pv, pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(11, 11, 11), origin=(-5, -5, -5)).cast_to_unstructured_grid()
    >>> grid[arrays.DISPLACEMENT] = 0.1 * grid.points          # a linear field
    >>> skin = pv.Sphere(radius=4.0)
    >>> out = grid.cmf.map_to_surface(skin, sigma=1.0)
    >>> bool(np.allclose(out[arrays.DISPLACEMENT], 0.1 * skin.points))
    True
    """
    if not isinstance(grid, pv.DataSet) or not isinstance(skin, pv.DataSet):
        raise TypeError(
            f"grid and skin must be pyvista datasets, got {type(grid).__name__} and "
            f"{type(skin).__name__}"
        )
    u = arrays.require_array(grid, arrays.DISPLACEMENT, "point", dtype="f", ncomp=3,
                             producer="pvcmf.mtm.solve")
    if grid.n_points == 0 or skin.n_points == 0:
        raise ValueError(
            f"grid and skin must have points, got {grid.n_points} and {skin.n_points}"
        )
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 mm, got {sigma}")
    radius = 3.0 * sigma if radius is None else float(radius)
    if not radius > 0:
        raise ValueError(f"radius must be > 0 mm, got {radius}")
    with Progress(total=2, desc="map_to_surface", enabled=progress_bar, logger=log) as bar:
        mapping = SurfaceMapping(grid.points, skin.points, sigma, radius)
        bar.step(f"weights of {skin.n_points} skin points")
        disp, support = mapping(u), mapping.support
        bar.step("displacement mapped")
    out = skin.copy()
    out.point_data[arrays.DISPLACEMENT] = disp
    out.point_data[SUPPORT] = support
    if warp:
        out.points = np.asarray(skin.points, float) + disp
    n_out = int((support == 0).sum())
    if n_out:
        log.info("map_to_surface: %d of %d skin points have no grid node within %.3g mm",
                 n_out, skin.n_points, radius)
    return out


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
        import scipy.sparse as sp

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
