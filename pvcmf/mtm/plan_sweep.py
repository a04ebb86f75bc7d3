"""Plan sweeps: plans that vary one segment's motion over given values.

The plans a :class:`pvcmf.mtm.response.PlanResponse` predicts in one batched product
(also importable from :mod:`pvcmf.mtm.response`). Delegates to numpy and :mod:`pvcmf.plan`.
"""

from __future__ import annotations

import numpy as np

from ..plan import Osteotomy, Plan

__all__ = ["plan_grid"]


def plan_grid(segment, *, translations=None, rotations=None, base=None):
    """Plans that vary one segment's motion over given values (a plan sweep).

    Parameters
    ----------
    segment : str
        The moved segment (e.g. ``"maxilla"``).
    translations, rotations : array_like, shape (m, 3), optional
        Per plan: translation (mm) and rotation (degrees) in the plan's (horizontal,
        vertical, anterior-posterior) convention; a missing one is zero (or ``base``'s).
    base : pvcmf.Plan, optional
        The other segments' motions, kept in every plan; its ``segment`` entry (if any)
        gives the cut planes and pivot.

    Returns
    -------
    list of pvcmf.Plan

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.mtm.response import plan_grid
    >>> plans = plan_grid("maxilla", translations=[[0, 0, a] for a in np.arange(0, 9, 2.0)])
    >>> len(plans), plans[-1].osteotomies[0].translation
    (5, (0.0, 0.0, 8.0))
    """
    if translations is None and rotations is None:
        raise ValueError("plan_grid needs translations= or rotations=")
    t = None if translations is None else np.asarray(translations, dtype=float)
    r = None if rotations is None else np.asarray(rotations, dtype=float)
    for name, v in (("translations", t), ("rotations", r)):
        if v is not None and (v.ndim != 2 or v.shape[1] != 3):
            raise ValueError(f"{name} must have shape (m, 3), got {v.shape}")
    m = len(t) if t is not None else len(r)
    if t is not None and r is not None and len(r) != m:
        raise ValueError(f"translations and rotations must have the same length, got {m} and {len(r)}")
    others = tuple(o for o in base.osteotomies if o.segment != segment) if base is not None else ()
    mine = [o for o in base.osteotomies if o.segment == segment] if base is not None else []
    ref = mine[0] if mine else Osteotomy(segment)
    plans = []
    for i in range(m):
        tr = tuple(t[i].tolist()) if t is not None else tuple(ref.translation)
        ro = tuple(r[i].tolist()) if r is not None else tuple(ref.rotation)
        o = Osteotomy(segment, translation=tr, rotation=ro, pivot=ref.pivot, cut=ref.cut)
        plans.append(Plan(others + (o,), name=base.name if base is not None else "",
                          axes=base.axes if base is not None else "image"))
    return plans
