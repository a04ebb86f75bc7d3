"""The twelve facial muscles of the atlas (paper 000 Fig. 2a, both sides).

Each muscle is a strap swept through control points kept at given depths below the atlas
skin, or (masseter) a sweep along the ramus; its signed distance is contoured with
PyVista's ``ImageData.contour`` into a closed, outward-oriented surface.
"""

from __future__ import annotations

import functools

import numpy as np
import pyvista as pv

from .. import arrays
from .shapes import _spline, _Sweep, _tuple
from .soft_tissue import skin_sdf


def _skin_normal(points, h=0.5):
    points = np.asarray(points, float)
    offsets = np.vstack([np.eye(3), -np.eye(3)]) * h
    probe = (points[None, :, :] + offsets[:, None, :]).reshape(-1, 3)
    v = skin_sdf(_tuple(probe)).astype(float).reshape(6, len(points))
    g = (v[:3] - v[3:]).T / (2 * h)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def _under_skin(points, depth, iterations=12):
    """Move points along the skin normal until they lie ``depth`` mm below the skin."""
    p = np.asarray(points, float).copy()
    depth = np.broadcast_to(np.asarray(depth, float), (len(p),))
    for _ in range(iterations):
        n = _skin_normal(p)
        d = skin_sdf(_tuple(p)).astype(float)
        p -= ((d + depth) * 0.8)[:, None] * n
    return p


def _straps(specs):
    """Muscle straps through control points kept at given depths below the skin.

    ``specs`` is a list of (control points, depth(s), half widths, half thicknesses, n,
    closed); all points are projected in one batch.
    """
    def depths(spec, m):
        d = np.atleast_1d(np.asarray(spec[1], float))
        return np.interp(np.linspace(0, 1, m), np.linspace(0, 1, len(d)), d)

    controls = [np.asarray(sp[0], float) for sp in specs]
    flat = _under_skin(np.vstack(controls), np.concatenate(
        [depths(sp, len(c)) for sp, c in zip(specs, controls)]))
    splits = np.cumsum([len(c) for c in controls])[:-1]
    curves = [_spline(c, n=sp[4], closed=sp[5]) for c, sp in zip(np.split(flat, splits), specs)]
    flat = _under_skin(np.vstack(curves), np.concatenate(
        [depths(sp, len(c)) for sp, c in zip(specs, curves)]))
    normals = _skin_normal(flat)
    splits = np.cumsum([len(c) for c in curves])[:-1]
    return [_Sweep(c, n, np.atleast_1d(sp[2]), np.atleast_1d(sp[3]), closed=sp[5])
            for c, n, sp in zip(np.split(flat, splits), np.split(normals, splits), specs)]


def _ring(center, rx, rz, tilt_y, n=16):
    """Control points of an ellipse in a near-coronal plane."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([center[0] + rx * np.cos(t), center[1] + tilt_y * np.cos(t),
                            center[2] + rz * np.sin(t)])


def _masseter(sx):
    curve = np.array([[sx * 57.0, 34.0, -15.0], [sx * 57.5, 27.0, -40.0],
                      [sx * 56.0, 19.0, -66.0]])
    curve = _spline(curve, 60)
    normals = np.tile([sx * 1.0, 0.0, 0.0], (len(curve), 1))
    return _Sweep(curve, normals, [13.0, 15.0, 13.0], [3.5, 5.0, 3.5])


@functools.lru_cache(maxsize=1)
def _muscle_models():
    specs, names = [], []
    for side, sx in (("left", 1.0), ("right", -1.0)):
        names.append(f"orbicularis_oculi_{side}")
        specs.append((_ring((sx * 33.0, 100.0, 11.0), 21.0, 18.0, -sx * 4.0), 3.0, 6.5, 1.6,
                      160, True))
        names.append(f"levator_labii_superioris_alaeque_nasi_{side}")
        specs.append(([[sx * 11.0, 95.0, 10.0], [sx * 15.0, 92.0, -10.0],
                       [sx * 20.0, 95.0, -31.0], [sx * 18.0, 94.0, -45.0]],
                      [2.6, 3.5, 4.0, 4.5], [3.0, 4.0, 5.0], [1.3, 1.6, 1.8], 120, False))
        names.append(f"levator_labii_superioris_{side}")
        specs.append(([[sx * 30.0, 87.0, -4.0], [sx * 26.0, 88.0, -20.0],
                       [sx * 20.0, 93.0, -45.0]],
                      [3.5, 4.5, 4.5], [8.0, 6.5, 4.5], [1.5, 1.8, 1.8], 120, False))
        names.append(f"zygomaticus_minor_{side}")
        specs.append(([[sx * 42.0, 78.0, -8.0], [sx * 33.0, 84.0, -28.0],
                       [sx * 22.0, 92.0, -48.0]],
                      [4.0, 5.0, 4.5], [3.5, 3.5, 3.0], [1.6, 1.8, 1.6], 120, False))
        names.append(f"zygomaticus_major_{side}")
        specs.append(([[sx * 55.0, 72.0, -12.0], [sx * 44.0, 80.0, -38.0],
                       [sx * 29.0, 88.0, -59.0]],
                      [5.5, 6.5, 4.5], [5.0, 4.5, 4.0], [2.0, 2.5, 2.2], 120, False))
    models = dict(zip(names, _straps(specs)))
    for side, sx in (("left", 1.0), ("right", -1.0)):
        models[f"masseter_{side}"] = _masseter(sx)
    return {name: models[name] for name in arrays.MUSCLES}


def muscle_sdfs():
    """The 12 facial muscles as callables ``sdf(P) -> mm`` (negative inside).

    Returns
    -------
    dict
        name (``pvcmf.arrays.MUSCLES``) -> callable taking a tuple of three coordinate
        arrays (atlas frame) and returning a float32 array; each callable has a
        ``bounds`` attribute ``(lo, hi)``, the atlas box outside which it is positive.
    """
    return dict(_muscle_models())


def muscle_sdf(name, points):
    """Evaluate one atlas muscle's signed distance at ``points`` (n, 3), mm.

    Examples
    --------
    >>> from pvcmf.atlas.muscles import muscle_sdf
    >>> import numpy as np
    >>> float(muscle_sdf("masseter_left", np.array([[58.0, 26.0, -40.0]]))[0]) < 0
    True
    """
    if name not in arrays.MUSCLE_IDS:
        raise ValueError(f"name must be one of {list(arrays.MUSCLES)}, got {name!r}")
    return _muscle_models()[name](_tuple(np.atleast_2d(points)))


@functools.lru_cache(maxsize=1)
def _muscle_surfaces_cached(spacing):
    out = {}
    for name, model in _muscle_models().items():
        lo, hi = model.bounds
        lo = np.floor(lo - 2.0)
        dims = np.ceil((hi + 2.0 - lo) / spacing).astype(int) + 1
        img = pv.ImageData(dimensions=dims, spacing=(spacing,) * 3, origin=lo)
        pts = img.points
        img[arrays.SDF] = model(_tuple(pts))
        surf = img.contour([0.0], scalars=arrays.SDF, method="flying_edges")
        surf = surf.compute_normals(auto_orient_normals=True, consistent_normals=True,
                                    split_vertices=False, cell_normals=False)
        surf.point_data.clear()
        surf.field_data[arrays.MUSCLE_ID] = np.array([arrays.MUSCLE_IDS[name]])
        out[name] = surf
    return out


def muscle_surfaces(spacing=0.5):
    """The 12 atlas muscles as closed, outward-oriented triangle surfaces.

    Parameters
    ----------
    spacing : float
        Sampling step (mm) of the signed distance that is contoured.

    Returns
    -------
    dict
        name (``pvcmf.arrays.MUSCLES``) -> :class:`pyvista.PolyData` in the atlas frame.

    Examples
    --------
    >>> from pvcmf.atlas.muscles import muscle_surfaces
    >>> surf = muscle_surfaces()["zygomaticus_major_left"]
    >>> surf.n_open_edges
    0
    """
    spacing = float(spacing)
    if not 0.2 <= spacing <= 2.0:
        raise ValueError(f"spacing must be in [0.2, 2] mm, got {spacing}")
    return {k: v.copy() for k, v in _muscle_surfaces_cached(spacing).items()}
