"""Which skin points the face figures draw apart, and in what colour.

Two kinds of skin are not what they seem and are drawn in their own colour over the skin
colour: the predicted skin the model does not reach (``arrays.SKIN_MODELLED`` is 0: the
back of the head, the neck; its move is an extension fading to none), in the colour the
caller gives (:data:`pvcmf.figures.face_views.UNMODELLED_COLOR`), and the skin on a plane
where the scan cut the head (``arrays.SKIN_CUT``: a face cut by the field of view, a
vertex cut by the scan's end; the scan's edge, not the patient's skin), in
:data:`CUT_COLOR`, on the pre-operative and the predicted skin alike
(:func:`pvcmf.figures.face_views.face_comparison` draws them;
:func:`pvcmf.figures.profiles.profile_overlay` lays a band of that colour under a
silhouette where it runs over the cut); the colour maps draw it in
:data:`MAP_CUT_COLOR` instead. Statistics of a prediction count
:func:`judged_points` only: the modelled skin off the scan's cuts.
"""

from __future__ import annotations

import numpy as np

from .. import arrays
from ..filters.field_of_view import cut_points

__all__ = ["CUT_COLOR", "MAP_CUT_COLOR", "MAP_CUT_WORDS", "cut_points", "judged_points",
           "modelled_points"]

#: colour of the skin on a cut of the scan (``arrays.SKIN_CUT``) in the face figures
CUT_COLOR = "lightsteelblue"
#: its colour in the colour maps (displacement, error): a neutral dark grey, which none of
#: their colour maps holds (their light blues would pass for :data:`CUT_COLOR`)
MAP_CUT_COLOR = "#4d4d4d"
#: what a map's caption says of that colour
MAP_CUT_WORDS = "dark grey: the scan's edge"


def modelled_points(skin):
    """The points of ``skin`` the model predicts: its ``arrays.SKIN_MODELLED`` array, all
    points without it. The rest of a head's skin (the back of the head, the neck) keeps
    zero displacement and sets no colour range.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> skin = pv.PolyData(np.zeros((3, 3)))
    >>> modelled_points(skin).tolist()
    [True, True, True]
    >>> skin.point_data[arrays.SKIN_MODELLED] = np.array([1, 0, 1], np.uint8)
    >>> modelled_points(skin).tolist()
    [True, False, True]
    """
    if arrays.SKIN_MODELLED in skin.point_data:
        return np.asarray(skin.point_data[arrays.SKIN_MODELLED]).astype(bool)
    return np.ones(skin.n_points, dtype=bool)


def judged_points(skin):
    """The points of ``skin`` whose prediction statistics may judge: modelled
    (:func:`modelled_points`; every point where none is) and not on a cut of the scan
    (:func:`cut_points`).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> skin = pv.PolyData(np.zeros((3, 3)))
    >>> skin.point_data[arrays.SKIN_MODELLED] = np.array([1, 0, 1], np.uint8)
    >>> skin.point_data[arrays.SKIN_CUT] = np.array([0, 0, 1], np.uint8)
    >>> judged_points(skin).tolist()
    [True, False, False]
    """
    modelled = modelled_points(skin)
    if not modelled.any():
        modelled = np.ones(skin.n_points, dtype=bool)
    return modelled & ~cut_points(skin)
