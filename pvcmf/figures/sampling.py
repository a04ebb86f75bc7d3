"""Paper 000 Fig. 1: the state of the art's random-point sampling of a tetrahedron's muscle share.

One tetrahedron crossed by a muscle (a cylinder, drawn translucent red); random points drawn
uniformly inside the tetrahedron (the same flat-Dirichlet barycentric sampling as
:func:`pvcmf.filters.sample_muscle_fraction`) are black outside the muscle and red inside;
the title compares the sampled share with the exact one (volume of a finely tetrahedralised
copy of the tetrahedron clipped at the cylinder, VTK ``clip_scalar``).

Delegates to PyVista (rendering, clipping) and numpy (sampling).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

#: the tetrahedron of the figure (mm)
TET = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [3.0, 9.0, 0.0], [4.0, 3.5, 9.0]])
#: the muscle: a cylinder (centre, direction, radius in mm)
MUSCLE = (np.array([5.5, 4.0, 2.0]), np.array([0.0, 0.3, 1.0]), 2.6)


def _muscle_distance(points):
    """Signed distance (mm) to the muscle cylinder's surface, negative inside."""
    centre, direction, radius = MUSCLE
    d = direction / np.linalg.norm(direction)
    rel = points - centre
    return np.linalg.norm(rel - np.outer(rel @ d, d), axis=1) - radius


def exact_share(level=40):
    """Muscle share of :data:`TET`: volume inside the cylinder over the tetrahedron's volume.

    The tetrahedron is filled with a regular barycentric lattice of ``level`` divisions,
    tetrahedralised (VTK Delaunay) and clipped at the zero level of the distance to the
    cylinder (``clip_scalar``); the error falls as ``1 / level**2``.

    Examples
    --------
    >>> from pvcmf.figures.sampling import exact_share
    >>> round(exact_share(), 2)
    0.52
    """
    i, j, k = np.meshgrid(*(np.arange(level + 1),) * 3, indexing="ij")
    keep = i + j + k <= level
    lam = np.stack([i[keep], j[keep], k[keep]], axis=1) / level
    bary = np.column_stack([1.0 - lam.sum(axis=1), lam])
    fine = pv.PolyData(bary @ TET).delaunay_3d()
    fine.point_data["f"] = _muscle_distance(fine.points)
    part = fine.clip_scalar(scalars="f", value=0.0, invert=True)
    return float(part.volume / fine.volume)


def sampling_figure(n_points=150, seed=0, window_size=(800, 640)):
    """Render paper 000 Fig. 1: random points inside a tetrahedron, in and out of a muscle.

    Parameters
    ----------
    n_points : int
        Random points drawn inside the tetrahedron.
    seed : int
        Seed of ``numpy.random.default_rng``.
    window_size : (int, int)

    Returns
    -------
    pyvista.Plotter
        Off screen; call ``screenshot``.

    Examples
    --------
    >>> from pvcmf.figures.sampling import sampling_figure
    >>> pl = sampling_figure(n_points=50)
    >>> pl.close()
    """
    rng = np.random.default_rng(seed)
    lam = rng.exponential(size=(n_points, 4))
    lam /= lam.sum(axis=1, keepdims=True)
    points = lam @ TET
    inside = _muscle_distance(points) <= 0
    share = inside.mean()
    exact = exact_share()

    tet = pv.UnstructuredGrid({pv.CellType.TETRA: np.array([[0, 1, 2, 3]])}, TET)
    centre, direction, radius = MUSCLE
    cylinder = pv.Cylinder(
        center=centre, direction=direction, radius=radius, height=22.0, resolution=60, capping=False
    )
    pl = pv.Plotter(off_screen=True, window_size=list(window_size))
    pl.set_background("white")
    pl.add_mesh(tet.extract_surface(algorithm="dataset_surface"), color="#f2d16b", opacity=0.25)
    pl.add_mesh(tet.extract_all_edges(), color="black", line_width=3)
    pl.add_mesh(cylinder.clip_box(tet.bounds, invert=False), color="#c0392b", opacity=0.35)
    if (~inside).any():
        pl.add_points(points[~inside], color="black", point_size=9, render_points_as_spheres=True)
    if inside.any():
        pl.add_points(points[inside], color="#e3170a", point_size=11, render_points_as_spheres=True)
    pl.add_text(
        f"muscle share: sampled {share:.2f} ({n_points} points), exact {exact:.2f}",
        position="upper_edge",
        font_size=12,
        color="black",
    )
    pl.camera_position = [(24.0, -22.0, 16.0), (4.5, 3.5, 3.0), (0.0, 0.0, 1.0)]
    return pl
