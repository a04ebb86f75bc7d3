"""Rasterising the atlas head: truth label images of the head through a point map.

:func:`rasterize` evaluates the head's signed distances on an image grid, through a map
from the grid's frame to the atlas frame (:class:`IdentityMap` for the atlas itself, a
patient warp for a virtual patient), coarse-to-fine so the costly evaluations stay near
the surfaces while every label is exact. Delegates to numpy and PyVista (``ImageData``).
"""

from __future__ import annotations

import functools

import numpy as np
import pyvista as pv

from .. import arrays
from .muscles import _muscle_models
from .shapes import F32
from .skull import (Z_LEFORT, braincase_sdf, cranium_vault_sdf, face_bone_sdf,
                    face_cavities_sdf, lower_teeth_sdf, mandible_sdf, spine_sdf, upper_teeth_sdf)
from .soft_tissue import (_bone_envelope, airway_sdf, eyes_sdf, neck_muscles_sdf, oral_air_sdf,
                          skin_sdf, temporalis_sdf, tongue_sdf)

#: allowed voxel sizes (mm)
SPACING_RANGE = (0.5, 4.0)


class IdentityMap:
    """The atlas's own frame as a point map (what :func:`rasterize` needs of a warp).

    The identity in every role: soft tissue, mid-face, mandible and cranium move nowhere.
    """

    def base_inverse(self, X):
        """Grid -> atlas coordinates before any segment displacement (tuple of float32)."""
        return tuple(np.asarray(x, dtype=F32) for x in X)

    def soft(self, S):
        return S

    face = mandible = soft

    def forward_kind(self, points, kind):
        """Atlas -> grid for points of one map kind: unchanged, as (n, 3) floats."""
        return np.atleast_2d(np.asarray(points, float)).copy()

    def forward(self, points):
        """Atlas -> grid for soft-tissue points: unchanged, as (n, 3) floats."""
        return self.forward_kind(points, "soft")


_FIELD_LO = np.array([-100.0, -130.0, -160.0])
_FIELD_STEP = 4.0


@functools.lru_cache(maxsize=1)
def _template_fields():
    """Skin and bony-envelope SDFs of the template on a 3 mm grid (bounds, radial map)."""
    ax = [_FIELD_LO[i] + _FIELD_STEP * np.arange(n) for i, n in enumerate((51, 71, 76))]
    X, Y, Z = np.meshgrid(*[a.astype(F32) for a in ax], indexing="ij")
    return skin_sdf((X, Y, Z)), _bone_envelope((X, Y, Z)), (X, Y, Z)


#: semi-axes (mm) of the inner ellipsoid (about CENTER) beyond which the radial soft-tissue
#: map stretches: inside the skull and the facial skeleton, so the map is smooth and the


class _Grid:
    def __init__(self, origin, spacing, dims):
        self.origin = np.asarray(origin, float)
        self.spacing = float(spacing)
        self.dims = tuple(int(d) for d in dims)  # (nx, ny, nz)

    def axes(self):
        return [(self.origin[i] + self.spacing * np.arange(self.dims[i])).astype(F32)
                for i in range(3)]

    def slices(self, lo, hi):
        """Index slices (z, y, x order) of the voxels inside the box [lo, hi]."""
        i0 = np.clip(np.floor((np.asarray(lo) - self.origin) / self.spacing), 0, self.dims)
        i1 = np.clip(np.ceil((np.asarray(hi) - self.origin) / self.spacing) + 1, 0, self.dims)
        i0, i1 = i0.astype(int), i1.astype(int)
        return (slice(i0[2], i1[2]), slice(i0[1], i1[1]), slice(i0[0], i1[0]))


def _box_lattice(lo, hi, n=5):
    t = np.linspace(0, 1, n)
    g = np.stack(np.meshgrid(t, t, t, indexing="ij"), -1).reshape(-1, 3)
    return np.asarray(lo) + g * (np.asarray(hi) - np.asarray(lo))


#: template bounding boxes (lo, hi) of the components, generous
_BOXES = {
    "cranium": ((-70, -102, -45), (70, 92, 120)),
    "face": ((-70, 15, -62), (70, 108, 55)),
    "upper_teeth": ((-38, 22, -66), (38, 97, -30)),
    "lower_teeth": ((-36, 28, -92), (36, 95, -60)),
    "mandible": ((-62, -8, -112), (62, 100, -15)),
    "spine": ((-12, -34, -142), (12, -10, -40)),
    "airway": ((-14, 10, -140), (14, 120, -15)),
    "oral_air": ((-17, 22, -56), (17, 82, -44)),
    "tongue": ((-23, 23, -77), (23, 87, -51)),
    "eyes": ((-47, 65, -2), (47, 93, 26)),
    "temporalis": ((-80, -35, -20), (80, 65, 70)),
    "neck": ((-45, -56, -140), (45, 36, -33)),
}


class _Rasterizer:
    """Evaluate the head's components on an image grid through a point map (``warp``).

    Each component is evaluated coarse-to-fine (factors 4, 2, 1 at 1 mm): a lattice point
    is evaluated only where the value of its parent block lies within a band of the zero
    level wider than the SDF can change across the block (the SDFs change by at most
    ``LIPSCHITZ`` mm per mm), so the sign, i.e. the label, is exact everywhere while the
    costly evaluations stay near the surfaces. The grid -> atlas map is evaluated
    exactly at every point that is evaluated (it is analytic and cheap).
    """

    LIPSCHITZ = 1.8

    def __init__(self, grid, warp):
        self.grid = grid
        self.warp = warp
        self.shape = grid.dims[::-1]
        self.axes = grid.axes()
        self.factor = 1
        while self.factor * 2 * grid.spacing <= 4.0 + 1e-9:
            self.factor *= 2
        self._subs = {}
        self._kinds = {"soft": warp.soft, "face": warp.face, "mandible": warp.mandible,
                       "cranium": lambda s: s}

    def sub(self, lo, hi, kind):
        """Slices of the patient grid covering template box [lo, hi] for a map kind."""
        if lo is None:
            return (slice(0, self.shape[0]), slice(0, self.shape[1]), slice(0, self.shape[2]))
        key = (tuple(np.ravel(lo)), tuple(np.ravel(hi)), kind)
        if key not in self._subs:
            X = self.warp.forward_kind(_box_lattice(lo, hi), kind)
            pad = 2.0 + self.grid.spacing
            self._subs[key] = self.grid.slices(X.min(0) - pad, X.max(0) + pad)
        return self._subs[key]

    def _points(self, iz, iy, ix, kind):
        X = (self.axes[0][ix], self.axes[1][iy], self.axes[2][iz])
        return self._kinds[kind](self.warp.base_inverse(X))

    def evaluate(self, fn, box, kind, lipschitz=None):
        """``fn`` on the sub-box of template box ``box``; returns (values, slices).

        ``fn`` may return several channels (an array of shape (k, ...)); a point is then
        refined where any channel is near its zero level.
        """
        lipschitz = self.LIPSCHITZ if lipschitz is None else lipschitz
        sl = self.sub(*(box if box is not None else (None, None)), kind)
        n = [s.stop - s.start for s in sl]
        if min(n) <= 0:
            return np.zeros((0, 0, 0), F32), sl
        start = [s.start for s in sl]
        c = self.factor
        while c > 1 and min(n) < 2 * c:
            c //= 2

        def lattice(f):
            return [np.minimum(np.arange(f // 2, m + f - 1, f)[: -(-m // f)], m - 1) for m in n]

        idx = lattice(c)
        iz, iy, ix = np.meshgrid(*idx, indexing="ij")
        values = np.asarray(fn(self._points(iz + start[0], iy + start[1], ix + start[2], kind)),
                            F32)
        multi = values.ndim == 4
        if not multi:
            values = values[None]
        while c > 1:
            band = lipschitz * (np.sqrt(3.0) * c / 2.0) * self.grid.spacing + 0.5
            c //= 2
            idx = lattice(c)
            up = values
            for axis in (1, 2, 3):
                up = np.repeat(up, 2, axis=axis)
            values = np.ascontiguousarray(up[:, :len(idx[0]), :len(idx[1]), :len(idx[2])])
            near = np.nonzero((np.abs(values) < band).any(axis=0))
            if len(near[0]):
                pts = self._points(idx[0][near[0]] + start[0], idx[1][near[1]] + start[1],
                                   idx[2][near[2]] + start[2], kind)
                fine = np.asarray(fn(pts), F32)
                values[(slice(None),) + near] = fine if multi else fine[None]
        return (values if multi else values[0]), sl


def rasterize(grid, warp, factor=None, progress_bar=False):
    """Truth labels and auxiliary fields of the template through ``warp`` on ``grid``.

    ``factor`` is the coarsest sampling step (voxels, a power of 2) of the coarse-to-fine
    evaluation; default: about 4 mm; 1 evaluates every voxel.

    Returns
    -------
    dict
        ``tissue``, ``muscle``, ``bone`` (uint8, shape (nz, ny, nx)), ``bone_depth``
        (float32 mm inside bone, for cortical/cancellous HU), ``eye`` (bool).
    """
    R = _Rasterizer(grid, warp)
    if factor is not None:
        R.factor = int(factor)
    shape = R.shape

    def masks(fn, name, kind, lipschitz=1.8):
        d, sl = R.evaluate(fn, _BOXES.get(name), kind, lipschitz)
        d = d if d.ndim == 4 else d[None]
        out = np.zeros((len(d),) + shape, bool)
        out[(slice(None),) + sl] = d < 0
        return out, d, sl

    inside = masks(skin_sdf, None, "soft", 2.6)[0][0]  # the thickness factor lives in the warp
    tissue = np.zeros(shape, np.uint8)
    bone = np.zeros(shape, np.uint8)
    muscle = np.zeros(shape, np.uint8)
    depth = np.zeros(shape, F32)
    tissue[inside] = arrays.FAT
    # generic muscle tissue: tongue, temporalis, neck
    for fn, name, lip in ((tongue_sdf, "tongue", 1.8), (temporalis_sdf, "temporalis", 1.8),
                          (neck_muscles_sdf, "neck", 2.2)):
        tissue[masks(fn, name, "soft", lip)[0][0] & inside] = arrays.MUSCLE_TISSUE

    def set_depth(d, sl):
        sub = depth[sl]
        m = d < 0
        sub[m] = np.maximum(sub[m], -d[m])

    # cranium (vault and braincase share one evaluation), spine
    m, d, sl = masks(lambda P: np.stack([cranium_vault_sdf(P), braincase_sdf(P)]), "cranium",
                     "cranium", 2.4)
    vault, brain = m
    bone[vault] = arrays.CRANIUM
    set_depth(d[0], sl)
    m, d, sl = masks(spine_sdf, "spine", "cranium")
    bone[m[0]] = arrays.CRANIUM
    set_depth(d[0], sl)
    # mid-face: bone, air cavities, oral air, upper teeth and the Le Fort I level at once
    m, d, sl = masks(lambda P: np.stack([face_bone_sdf(P), face_cavities_sdf(P),
                                         P[2] - Z_LEFORT]), "face", "face")
    face, air, low = m
    bone[face & ~low] = arrays.CRANIUM
    bone[face & low] = arrays.MAXILLA
    set_depth(d[0], sl)
    m, _, _ = masks(lambda P: np.stack([upper_teeth_sdf(P), oral_air_sdf(P)]), "upper_teeth",
                    "face")
    upper, oral = m
    air |= oral
    m, d, sl = masks(lambda P: np.stack([mandible_sdf(P), lower_teeth_sdf(P)]), "mandible",
                     "mandible")
    mand, lower = m
    bone[mand] = arrays.MANDIBLE
    set_depth(d[0], sl)
    tissue[bone > 0] = arrays.BONE_TISSUE
    teeth = upper | lower
    tissue[teeth] = arrays.TEETH
    bone[upper] = arrays.MAXILLA
    bone[lower] = arrays.MANDIBLE
    depth[teeth] = 0.0
    # air inside the head
    soft = (tissue == arrays.FAT) | (tissue == arrays.MUSCLE_TISSUE)
    air |= masks(airway_sdf, "airway", "soft")[0][0]
    eye = masks(eyes_sdf, "eyes", "soft")[0][0] & soft
    tissue[air & soft & ~eye] = arrays.AIR
    tissue[brain] = arrays.INTRACRANIAL
    bone[brain] = arrays.BONE_NONE
    depth[brain] = 0.0
    # the 12 facial muscles, only in soft tissue
    soft = ((tissue == arrays.FAT) | (tissue == arrays.MUSCLE_TISSUE)) & ~eye
    for name, model in _muscle_models().items():
        d, sl = R.evaluate(model, model.bounds, "soft", 1.8)
        if d.size == 0:
            continue
        m = (d < 0) & soft[sl]
        muscle[sl][m] = arrays.MUSCLE_IDS[name]
        tissue[sl][m] = arrays.MUSCLE_TISSUE
    return {arrays.TISSUE: tissue, arrays.MUSCLE: muscle, arrays.BONE: bone,
            arrays.BONE_DEPTH: depth, arrays.EYE: eye}


@functools.lru_cache(maxsize=1)
def _template_bounds():
    """Points inside the template skin (3 mm sampling), for bounding boxes."""
    skin_f, _, (X, Y, Z) = _template_fields()
    inside = skin_f < 0
    return np.stack([X[inside], Y[inside], Z[inside]], 1).astype(float)


def head_points(warp, n=20000):
    """Patient-frame sample of points inside the head (for bounding boxes)."""
    pts = _template_bounds()
    step = max(1, len(pts) // n)
    return warp.forward(pts[::step])


def check_spacing(spacing):
    """``spacing`` as a float of mm within :data:`SPACING_RANGE` (TypeError/ValueError else)."""
    if isinstance(spacing, bool) or not isinstance(spacing, (int, float, np.integer,
                                                              np.floating)):
        raise TypeError(f"spacing must be a number of mm, got {type(spacing).__name__}")
    spacing = float(spacing)
    lo, hi = SPACING_RANGE
    if not np.isfinite(spacing) or not lo <= spacing <= hi:
        raise ValueError(f"spacing must be between {lo} and {hi} mm, got {spacing}")
    return spacing


def head_grid(warp, spacing, pad_back=0.0):
    """Image grid holding the head through ``warp``, a margin and ``pad_back`` mm behind it."""
    pts = head_points(warp)
    margin = 3 * spacing + 3.0
    lo = pts.min(0) - margin
    hi = pts.max(0) + margin
    lo[1] -= pad_back
    lo = np.floor(lo / spacing) * spacing
    hi = np.ceil(hi / spacing) * spacing
    dims = np.round((hi - lo) / spacing).astype(int) + 1
    return _Grid(lo, spacing, dims)


def label_image(spacing=1.0):
    """The atlas head's truth labels (the same arrays as a virtual patient's ``Case.truth``).

    Parameters
    ----------
    spacing : float
        Voxel size in mm (0.5 .. 4).

    Returns
    -------
    pyvista.ImageData
        Point arrays ``tissue``, ``muscle``, ``bone`` (uint8), atlas frame.

    Examples
    --------
    >>> from pvcmf.atlas.raster import label_image
    >>> img = label_image(spacing=4.0)
    >>> sorted(img.point_data.keys())
    ['bone', 'muscle', 'tissue']
    """
    spacing = check_spacing(spacing)
    warp = IdentityMap()
    grid = head_grid(warp, spacing)
    labels = rasterize(grid, warp)
    img = pv.ImageData(dimensions=grid.dims, spacing=(spacing,) * 3, origin=grid.origin)
    for name in (arrays.TISSUE, arrays.MUSCLE, arrays.BONE):
        img.point_data[name] = labels[name].ravel()
    return img
