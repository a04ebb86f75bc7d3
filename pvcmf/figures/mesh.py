"""Paper 000 Fig. 2c: the labelled volumetric mesh, cut open to show the muscle volumes.

The tetrahedra on one side of a cutting plane are kept whole (PyVista ``clip`` with
``crinkle=True``) and drawn with their edges, fat in yellow and each muscle in a shade of
red; the removed half is drawn as its translucent outer surface.

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
    cut = grid.clip(normal=normal, origin=origin, crinkle=True, invert=True)
    rest = grid.clip(normal=normal, origin=origin, crinkle=True, invert=False)
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
    if rest.n_cells:
        pl.add_mesh(rest.extract_surface(algorithm="dataset_surface"), color=FAT_COLOR, opacity=0.1)
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
    # muscle cells crossing the plane: the muscle patches of the cut face
    d = (np.asarray(cut.points) - origin) @ n
    conn = cut.cell_connectivity
    offsets = cut.cell_offsets
    lo = np.minimum.reduceat(d[conn], offsets[:-1])
    hi = np.maximum.reduceat(d[conn], offsets[:-1])
    on_face = (lo <= 0) & (hi >= 0) & (np.asarray(cut.cell_data["label"]) > 0)
    target = cut.extract_cells(np.nonzero(on_face)[0]) if on_face.any() else cut
    b = np.asarray(target.bounds).reshape(3, 2)
    center = b.mean(axis=1)
    center = center - np.dot(center - origin, n) * n  # on the cutting plane
    size = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    pl.camera_position = [tuple(center + 3.0 * size * view / np.linalg.norm(view)),
                          tuple(center), up]
    pl.enable_parallel_projection()
    pl.camera.parallel_scale = 0.45 * max(size, 1e-6)
    pl.reset_camera_clipping_range()
