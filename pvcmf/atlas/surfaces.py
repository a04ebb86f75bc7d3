"""Patient surfaces for atlas registration: skin and skull of a label image, closest points.

Surfaces are contoured with PyVista's ``ImageData.contour`` (flying edges) from the tissue
labels; closest-point queries use :class:`scipy.spatial.cKDTree`; the similarity steps are
Umeyama's least-squares fit and a linearised point-to-plane step.
"""

from __future__ import annotations

import numpy as np
import pyvista as pv
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from .. import arrays

#: spacing (mm) at which surfaces are extracted for automatic fitting
FIT_SPACING = 2.0


# --------------------------------------------------------------------------- surfaces
def label_surfaces(labels, *, spacing=FIT_SPACING):
    """Skin and skull surfaces of a tissue label image (for registration).

    The skin is the outer boundary of the head (everything that is not air, with the
    cavities enclosed in it filled); the skull is the boundary of bone and teeth. Images
    finer than ``spacing`` are subsampled first; the masks are contoured at 0.5
    (``ImageData.contour``, flying edges; ``scipy.ndimage.binary_fill_holes``).

    Parameters
    ----------
    labels : pyvista.ImageData
        Image with point array ``tissue``.
    spacing : float
        Approximate spacing (mm) to contour at.

    Returns
    -------
    skin, skull : pyvista.PolyData

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.atlas import label_surfaces
    >>> img = pv.ImageData(dimensions=(30, 30, 30), origin=(-29, -29, -29), spacing=(2, 2, 2))
    >>> r = np.linalg.norm(img.points, axis=1)
    >>> img[arrays.TISSUE] = np.select([r < 10, r < 20], [arrays.BONE_TISSUE, arrays.FAT], 0).astype(np.uint8)
    >>> skin, skull = label_surfaces(img)
    >>> bool(19 < np.linalg.norm(skin.points, axis=1).mean() < 21)
    True
    """
    tissue = arrays.require_array(labels, arrays.TISSUE, "point", dtype="iu", ncomp=1)
    dims = np.asarray(labels.dimensions)
    rate = np.maximum(1, np.floor(spacing / np.asarray(labels.spacing) + 1e-9)).astype(int)
    vol = np.asarray(tissue).reshape(dims, order="F")[:: rate[0], :: rate[1], :: rate[2]]
    direction = np.asarray(labels.direction_matrix, dtype=float)
    origin = np.asarray(labels.origin) + direction @ (
        np.asarray(labels.offset) * np.asarray(labels.spacing)
    )
    img = pv.ImageData(
        dimensions=vol.shape,
        spacing=np.asarray(labels.spacing) * rate,
        origin=origin,
        direction_matrix=direction,
    )
    head = ndimage.binary_fill_holes(vol != arrays.AIR)
    bone = np.isin(vol, arrays.HARD_LABELS)
    out = []
    for mask in (head, bone):
        img.point_data[arrays.MASK] = mask.ravel(order="F").astype(np.float32)
        out.append(img.contour([0.5], scalars=arrays.MASK, method="flying_edges").clean())
    return out[0], out[1]


def _downsample(points, cell):
    """One point per ``cell``-mm voxel (the first), vectorised."""
    pts = np.asarray(points, dtype=float)
    if len(pts) == 0:
        return pts
    return pts[_subsample_index(pts, cell)]


def _unique_rows(points, classes, tol):
    """Drop every point closer than ``tol`` to an earlier one (with its class)."""
    drop = {j for i, j in cKDTree(points).query_pairs(tol)} if len(points) else set()
    keep = np.setdiff1d(np.arange(len(points)), np.fromiter(drop, int, len(drop)))
    return points[keep], classes[keep]


def _umeyama(src, dst, weights=None):
    """Least-squares similarity (s, R, t) with dst ~ s R src + t (Umeyama 1991)."""
    w = np.ones(len(src)) if weights is None else weights
    w = w / w.sum()
    ms, md = w @ src, w @ dst
    a, b = src - ms, dst - md
    cov = (b * w[:, None]).T @ a
    u, d, vt = np.linalg.svd(cov)
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2, 2] = -1
    rot = u @ sign @ vt
    var = (w * (a**2).sum(axis=1)).sum()
    scale = np.trace(np.diag(d) @ sign) / var
    return scale, rot, md - scale * rot @ ms


def _correspond(moving, trees, classes, trim):
    """Closest patient points (per class) of moving points; mask of the pairs kept."""
    target = np.empty_like(moving)
    dist = np.empty(len(moving))
    for c, tree in enumerate(trees):
        sel = classes == c
        if sel.any():
            dist[sel], i = tree.query(moving[sel])
            target[sel] = tree.data[i]
    keep = dist <= np.quantile(dist, trim)
    return target, dist, keep


def _plane_step(p, q, n):
    """One linearised point-to-plane similarity step about the centroid of ``p``.

    Minimises sum(((1+d)(R p - c) + c + t - q) . n)^2 over a small rotation, scale
    change d and translation t; returns (scale, R, t) in the form p -> scale R p + t."""
    c = p.mean(axis=0)
    pc = p - c
    a = np.column_stack([np.cross(pc, n), n, (pc * n).sum(1)])
    b = ((q - p) * n).sum(1)
    x = np.linalg.lstsq(a, b, rcond=None)[0]
    w, t, d = x[:3], x[3:6], x[6]
    rot = Rotation.from_rotvec(w).as_matrix()
    scale = 1.0 + d
    # p -> scale (R (p - c)) + c + t  ==  scale R p + (c + t - scale R c)
    return scale, rot, c + t - scale * rot @ c


def _subsample_index(points, cell):
    key = np.floor(np.asarray(points) / cell).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def _symmetric_goal(current, classes, trees, patient, trim=0.95):
    """Target of each moving point: mean of its closest patient point and of the patient
    points (``patient``, per class, a sparse sample) that have it as their closest
    (same class); NaN where it has neither."""
    target, dist, keep = _correspond(current, trees, classes, trim)
    acc = np.zeros_like(current)
    cnt = np.zeros(len(current))
    for c in range(len(trees)):
        idx_c = np.flatnonzero(classes == c)
        if len(idx_c) == 0:
            continue
        d, j = cKDTree(current[idx_c]).query(patient[c])
        ok = d <= np.quantile(d, trim)
        owner = idx_c[j[ok]]
        cnt += np.bincount(owner, minlength=len(current))
        for k in range(3):
            acc[:, k] += np.bincount(owner, weights=patient[c][ok, k], minlength=len(current))
    goal = np.full_like(current, np.nan)
    has = cnt > 0
    rev = np.zeros_like(current)
    rev[has] = acc[has] / cnt[has, None]
    both = has & keep
    goal[both] = 0.5 * (target[both] + rev[both])
    goal[keep & ~has] = target[keep & ~has]
    goal[has & ~keep] = rev[has & ~keep]
    return goal


class _PatientSurfaces:
    """Skin and skull of a label image, with closest-point queries (for registration)."""

    def __init__(self, labels, spacing):
        skin, skull = label_surfaces(labels, spacing=spacing)
        if skin.n_points == 0 or skull.n_points == 0:
            raise ValueError(
                f"labels: atlas registration needs skin and bone in the image, found "
                f"{skin.n_points} skin and {skull.n_points} bone surface points"
            )
        b = np.asarray(labels.bounds, dtype=float).reshape(3, 2)
        pad = 2.0 * np.asarray(labels.spacing, dtype=float)
        self.lo, self.hi = b[:, 0] + pad, b[:, 1] - pad
        self.points, self.normals, self.trees, self.sparse = [], [], [], []
        for surf in (skin, skull):
            smooth = surf.smooth_taubin(n_iter=20, pass_band=0.1)
            nrm = smooth.compute_normals(cell_normals=False, split_vertices=False)
            self.points.append(np.asarray(surf.points))
            self.normals.append(np.asarray(nrm.point_data[arrays.NORMALS]))
            self.trees.append(cKDTree(self.points[-1]))
            self.sparse.append(_downsample(self.points[-1], 1.5 * spacing))

    def inside(self, pts):
        """Which points lie inside the patient image (less a 2-voxel border)."""
        return ((pts >= self.lo) & (pts <= self.hi)).all(axis=1)

    def closest(self, pts, classes):
        """Closest patient points of ``pts`` on the surface of each one's class."""
        q = np.empty_like(pts)
        n = np.empty_like(pts)
        d = np.empty(len(pts))
        for c, tree in enumerate(self.trees):
            sel = classes == c
            if sel.any():
                d[sel], i = tree.query(pts[sel])
                q[sel] = self.points[c][i]
                n[sel] = self.normals[c][i]
        return q, n, d

    def rms(self, pts, classes, max_distance=np.inf):
        """RMS point-to-plane distance (mm) of the points within ``max_distance``."""
        q, n, d = self.closest(pts, classes)
        r = ((q - pts) * n).sum(1)[d <= max_distance]
        return float(np.sqrt((r**2).mean())) if len(r) else np.nan
