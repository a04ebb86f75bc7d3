"""Colour ranges of the displacement maps, and the words that say where they end.

:func:`symmetric_limit` takes the half-width of a symmetric range from a percentile of the
values over the points a figure shows (so a few outliers, or points hidden inside the
mouth, do not set it); :func:`saturation_note` says when shown values lie beyond the
range, and gives the largest. :func:`pvcmf.figures.face_views.displacement_views` uses
both. Plain numpy.
"""

from __future__ import annotations

import numpy as np

__all__ = ["symmetric_limit", "saturation_note"]


def symmetric_limit(values, visible, percentile=99.0, floor=0.1):
    """Half-width of a symmetric colour range: ``percentile`` of ``|values[visible]|``.

    Examples
    --------
    >>> import numpy as np
    >>> v = np.r_[np.linspace(-2.0, 2.0, 101), 50.0]
    >>> symmetric_limit(v, np.r_[np.ones(101, bool), False])
    2.0
    """
    values = np.asarray(values, dtype=np.float64)
    visible = np.asarray(visible, dtype=bool)
    if visible.shape != values.shape:
        raise ValueError(f"visible must have the shape of values {values.shape}, "
                         f"got {visible.shape}")
    seen = np.abs(values[visible & np.isfinite(values)])
    if seen.size == 0:
        return float(floor)
    return max(float(np.percentile(seen, percentile)), float(floor))


def saturation_note(values, limit, visible=None, signed=True):
    """Words for the colour bar when some shown values lie beyond its range, else ``""``.

    The colours stop at ``limit`` (a percentile, so a few points saturate): the bar then
    says so and gives the largest value, over the ``visible`` points (all without it).

    Examples
    --------
    >>> import numpy as np
    >>> saturation_note(np.array([-0.5, 1.0, 2.7]), 2.2)
    'colours end at \u00b12.2 mm; largest 2.7 mm'
    >>> saturation_note(np.array([0.5, 1.0]), 2.2)
    ''
    """
    values = np.asarray(values, dtype=np.float64)
    shown = values if visible is None else values[np.asarray(visible, dtype=bool)]
    shown = np.abs(shown[np.isfinite(shown)])
    if shown.size == 0:
        return ""
    largest = float(shown.max())
    if f"{largest:.1f}" == f"{limit:.1f}" or largest <= limit:  # reads as the bar's end
        return ""
    sign = "\u00b1" if signed else ""
    return f"colours end at {sign}{limit:.1f} mm; largest {largest:.1f} mm"
