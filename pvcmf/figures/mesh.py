"""Paper 000 Fig. 2c: the labelled volumetric mesh, cut open to show the muscle volumes.

The tetrahedra crossing a cutting plane (the cut section, one element thick) are drawn
whole with their edges, fat in yellow and each muscle in a shade of red, seen from the
removed side; the mesh below the plane is drawn as its translucent outer surface. The
default camera frames the muscle elements of the section.

Delegates to PyVista (clipping, rendering).
"""

from __future__ import annotations

import numpy as np
import pyvista as pv

from .. import arrays

FAT_COLOR = "#f2d16b"
MUSCLE_COLORS = ("#8e1b12", "#b52a1c", "#d1402b", "#e35d44", "#a3271d", "#c23a2a")


def mesh_figure(grid, *, normal=(1.0, 0.0, 0.0), origin=None, window_size=(900, 700), camera=None):
    """Render the labelled tetrahedral mesh with a cut section (paper 000 Fig. 2c).

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Output of :func:`pvcmf.filters.tetrahedralize` (cell arrays ``arrays.TISSUE`` and
        ``arrays.MUSCLE``).
    normal : 3 floats
        Normal of the cutting plane; the tetrahedra on its negative side are drawn.
    origin : 3 floats, optional
        A point of the plane (default: the centre of the muscle cells).
    window_size : (int, int)
    camera : optional
        PyVista camera position; by default the view looks at the cut face from slightly
        anterior, framing the cut muscles (or the whole cut when it holds none).

    Returns
    -------
    pyvista.Plotter
        Off screen; call ``screenshot``.

    Examples
    --------
    >>> from pvcmf.filters import tetrahedralize
    >>> from pvcmf.filters.meshing import shell_labels
    >>> from pvcmf.figures.mesh import mesh_figure
    >>> pl = mesh_figure(tetrahedralize(shell_labels(spacing=3.0), spacing=8.0))
    >>> pl.close()
    """
    arrays.require_array(grid, arrays.MUSCLE, "cell", dtype="u", producer="tetrahedralize")
    normal = np.asarray(normal, float)
    if origin is None:
        muscles = grid.extract_cells(np.asarray(grid.cell_data[arrays.MUSCLE]) > 0)
        origin = (muscles if muscles.n_cells else grid).center
    origin = np.asarray(origin, float)
    n = normal / np.linalg.norm(normal)
    crossing = _crossing_cells(grid, origin, n)
    cut = grid.extract_cells(np.nonzero(crossing)[0])
    below = grid.clip(normal=normal, origin=origin, crinkle=True, invert=True)
    muscle = np.asarray(cut.cell_data[arrays.MUSCLE]).astype(int)
    cut.cell_data["label"] = muscle
    colors = [FAT_COLOR] + [MUSCLE_COLORS[i % len(MUSCLE_COLORS)] for i in range(len(arrays.MUSCLES))]

    pl = pv.Plotter(off_screen=True, window_size=list(window_size))
    pl.set_background("white")
    pl.add_mesh(
        cut,
        scalars="label",
        cmap=colors,
        clim=[-0.5, len(arrays.MUSCLES) + 0.5],
        n_colors=len(colors),
        show_edges=True,
        edge_color="#555555",
        line_width=0.5,
        show_scalar_bar=False,
    )
    if below.n_cells:
        pl.add_mesh(below.extract_surface(algorithm="dataset_surface"), color=FAT_COLOR,
                    opacity=0.12)
    if camera is None:
        _look_at_cut(pl, cut, normal, origin)
    else:
        pl.camera_position = camera
    n_muscles = len(set(np.unique(grid.cell_data[arrays.MUSCLE]).tolist()) - {0})
    pl.add_text(
        f"{grid.n_cells} tetrahedra, {n_muscles} muscles (red) in fat (yellow)",
        position="upper_edge",
        font_size=11,
        color="black",
    )
    return pl


def _look_at_cut(pl, cut, normal, origin):
    """Camera on the cut face, tilted anteriorly, framing the muscles lying on it."""
    n = normal / np.linalg.norm(normal)
    tilt = np.array([0.0, 0.35, 0.0]) if abs(n[1]) < 0.9 else np.array([0.0, 0.0, 0.35])
    view = n + tilt
    up = (0.0, 1.0, 0.0) if abs(n[2]) > 0.9 else (0.0, 0.0, 1.0)
    muscle = np.asarray(cut.cell_data["label"]) > 0
    target = cut.extract_cells(np.nonzero(muscle)[0]) if muscle.any() else cut
    b = np.asarray(target.bounds).reshape(3, 2)
    center = b.mean(axis=1)
    center = center - np.dot(center - origin, n) * n  # on the cutting plane
    size = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    pl.camera_position = [tuple(center + 3.0 * size * view / np.linalg.norm(view)),
                          tuple(center), up]
    pl.enable_parallel_projection()
    pl.camera.parallel_scale = 0.45 * max(size, 1e-6)
    pl.reset_camera_clipping_range()


def _crossing_cells(grid, origin, n):
    """Cells with points on both sides of the plane (or on it): the cut section."""
    d = (np.asarray(grid.points) - origin) @ n
    conn = np.asarray(grid.cell_connectivity)
    starts = np.asarray(grid.cell_offsets)[:-1]
    lo = np.minimum.reduceat(d[conn], starts)
    hi = np.maximum.reduceat(d[conn], starts)
    return (lo <= 0) & (hi >= 0)
