"""Paper 000 Figs. 6-8 for one validated case, as PNGs in its folder.

Delegates to :mod:`pvcmf.figures.validation` (PyVista off screen, matplotlib).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from .. import arrays
from .._atomic import atomic_path
from ..figures.skin_marks import judged_points
from ..figures.validation import fig6_error_maps, fig7_boxplots, fig8_cumulative

__all__ = ["validation_figures", "judged_distances"]

#: the method name of a single prediction in Figs. 6-8
METHOD = "prediction"


def _png(figure_or_plotter, path):
    with atomic_path(path) as tmp:
        if isinstance(figure_or_plotter, pv.Plotter):
            figure_or_plotter.screenshot(tmp)
            figure_or_plotter.close()
        else:
            figure_or_plotter.savefig(tmp, dpi=120, bbox_inches="tight")
    return Path(path)


def judged_distances(skin):
    """The signed distances of ``skin`` the statistics judge: those of the skin the model
    predicts (``arrays.SKIN_MODELLED`` above 0, all points without the array; the back of
    the head keeps zero displacement and would inflate the shares near zero error), off a
    cut of the scan (``arrays.SKIN_CUT``: :func:`~pvcmf.figures.skin_marks.judged_points`),
    finite.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> skin = pv.PolyData(np.zeros((3, 3)))
    >>> skin.point_data[arrays.DISTANCE] = [1.0, 0.0, np.nan]
    >>> skin.point_data[arrays.SKIN_MODELLED] = np.array([1, 0, 1], np.uint8)
    >>> judged_distances(skin).tolist()
    [1.0]
    """
    d = np.asarray(arrays.require_array(skin, arrays.DISTANCE, "point", producer="distance_to"),
                   dtype=float).reshape(-1)[judged_points(skin)]
    return d[np.isfinite(d)]


def validation_figures(skin, out, *, case="case"):
    """Write ``fig6_error_map.png``, ``fig7_boxplot.png`` and ``fig8_cumulative.png``.

    Figs. 7 and 8 count the skin the model predicts only (:func:`judged_distances`), as
    ``regions.csv`` does; Fig. 6 colours the whole skin (a cut of the scan in its own
    colour).

    Parameters
    ----------
    skin : pyvista.PolyData
        Judged prediction with point array ``arrays.DISTANCE``.
    out : str or pathlib.Path
        Folder.
    case : str
        Name of the case in the figures.

    Returns
    -------
    dict
        ``fig6``, ``fig7``, ``fig8`` -> written paths.
    """
    out = Path(out)
    d = judged_distances(skin)
    return {"fig6": _png(fig6_error_maps({case: {METHOD: skin}}), out / "fig6_error_map.png"),
            "fig7": _png(fig7_boxplots({case: {METHOD: d}}), out / "fig7_boxplot.png"),
            "fig8": _png(fig8_cumulative({case: {METHOD: d}}), out / "fig8_cumulative.png")}
