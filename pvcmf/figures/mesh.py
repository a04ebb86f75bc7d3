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
        A point of the plane (default: the mesh centre).
    window_size : (int, int)
    camera : optional
        PyVista camera position; by default the view looks at the cut face.

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
    origin = np.asarray(grid.center if origin is None else origin, float)
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
        # look at the cut face, slightly from the front (-y is posterior)
        n = normal / np.linalg.norm(normal)
        view = n + np.array([0.0, 0.35, 0.0]) if abs(n[1]) < 0.9 else n + np.array([0.0, 0.0, 0.35])
        up = (0.0, 1.0, 0.0) if abs(n[2]) > 0.9 else (0.0, 0.0, 1.0)
        pl.camera_position = [tuple(origin + 1.4 * grid.length * view), tuple(origin), up]
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
