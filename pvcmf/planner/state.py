"""The planner's slider values and the :class:`pvcmf.Plan` they stand for.

Each movable segment (``maxilla``, ``mandible``) has six sliders, in the plan's own terms
(:mod:`pvcmf.plan`): translation (horizontal, vertical, anterior-posterior) in mm, +
meaning patient-left, superior, anterior, and rotation in degrees about the same three
axes (pitch, yaw, roll). A slider is named ``<segment>_<t|r>_<h|v|ap>``, e.g.
``maxilla_t_ap`` is the maxilla's anterior-posterior translation.

:class:`PlanSliders` converts between a flat ``{name: value}`` dictionary (what the web
page holds) and a :class:`pvcmf.Plan`; cut planes, pivots and the name of a starting plan
are kept, so a plan read, moved and saved keeps everything the sliders do not show.
Pure Python on top of :mod:`pvcmf.plan`; no web framework is imported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..plan import MAX_ROTATION_DEG, MOVABLE_SEGMENTS, Osteotomy, Plan

__all__ = ["AXES", "KINDS", "PlanSliders", "TRANSLATION_RANGE_MM", "ROTATION_RANGE_DEG",
           "SLIDER_STEP", "slider_key"]

#: plan axes in plan order: (key suffix, label)
AXES = (("h", "horizontal (+ left)"), ("v", "vertical (+ up)"),
        ("ap", "anterior-posterior (+ forward)"))
#: slider kinds: (key part, label, unit, attribute of Osteotomy)
KINDS = (("t", "translation", "mm", "translation"), ("r", "rotation", "deg", "rotation"))
#: slider range of a translation, +- mm
TRANSLATION_RANGE_MM = 15.0
#: slider range of a rotation, +- degrees (within :data:`pvcmf.plan.MAX_ROTATION_DEG`)
ROTATION_RANGE_DEG = min(15.0, MAX_ROTATION_DEG)
#: slider step (mm or degrees)
SLIDER_STEP = 0.5


def slider_key(segment, kind, axis):
    """Name of one slider, e.g. ``slider_key("maxilla", "t", "ap") == "maxilla_t_ap"``."""
    if segment not in MOVABLE_SEGMENTS:
        raise ValueError(f"segment must be one of {list(MOVABLE_SEGMENTS)}, got {segment!r}")
    if kind not in {k for k, *_ in KINDS}:
        raise ValueError(f"kind must be 't' or 'r', got {kind!r}")
    if axis not in {a for a, _ in AXES}:
        raise ValueError(f"axis must be one of {[a for a, _ in AXES]}, got {axis!r}")
    return f"{segment}_{kind}_{axis}"


@dataclass(frozen=True)
class PlanSliders:
    """The sliders of the movable segments and their conversion to and from a plan.

    Parameters
    ----------
    segments : tuple of str
        Segments with sliders (default: every movable segment).
    template : pvcmf.Plan, optional
        Starting plan: its segments are always in the plan made from the sliders, with
        their cut planes and pivots; its name is kept.

    Examples
    --------
    >>> from pvcmf.plan import Plan, Osteotomy
    >>> sliders = PlanSliders()
    >>> values = sliders.zero_values()
    >>> values["maxilla_t_ap"] = 4.0
    >>> plan = sliders.to_plan(values)
    >>> plan.osteotomies[0].segment, plan.osteotomies[0].translation
    ('maxilla', (0.0, 0.0, 4.0))
    >>> sliders.from_plan(plan)["maxilla_t_ap"]
    4.0
    """

    segments: tuple = MOVABLE_SEGMENTS
    template: Plan | None = None
    keys: tuple = field(init=False)

    def __post_init__(self):
        segments = tuple(self.segments)
        bad = [s for s in segments if s not in MOVABLE_SEGMENTS]
        if bad or not segments:
            raise ValueError(f"segments must be a non-empty subset of {list(MOVABLE_SEGMENTS)}, "
                             f"got {list(segments)}")
        if self.template is not None and not isinstance(self.template, Plan):
            raise TypeError(f"template must be a pvcmf.Plan or None, got "
                            f"{type(self.template).__name__}")
        if self.template is not None:
            missing = [s for s in self.template.segments if s not in segments]
            if missing:
                raise ValueError(f"template moves {missing}, which have no sliders "
                                 f"(segments {list(segments)})")
        object.__setattr__(self, "segments", segments)
        object.__setattr__(self, "keys", tuple(
            slider_key(s, k, a) for s in segments for k, *_ in KINDS for a, _ in AXES))

    def zero_values(self):
        """Every slider at 0."""
        return {key: 0.0 for key in self.keys}

    def from_plan(self, plan):
        """Slider values of ``plan`` (segments it does not move are at 0)."""
        values = self.zero_values()
        for o in plan.osteotomies:
            if o.segment not in self.segments:
                raise ValueError(f"plan moves {o.segment!r}, which has no sliders "
                                 f"(segments {list(self.segments)})")
            for kind, _, _, attr in KINDS:
                for (axis, _), v in zip(AXES, getattr(o, attr)):
                    values[slider_key(o.segment, kind, axis)] = float(v)
        return values

    def to_plan(self, values, name=None):
        """The plan the sliders say.

        A segment is in the plan when the template has it or a slider of it is not 0;
        when none is, every segment is listed with a zero move (a plan file needs one
        osteotomy at least).

        Parameters
        ----------
        values : dict
            Slider name -> value; missing names count as 0, unknown names raise.
        name : str, optional
            Plan name (default: the template's).

        Raises
        ------
        ValueError
            Unknown slider names or values a plan rejects (e.g. a rotation over
            :data:`pvcmf.plan.MAX_ROTATION_DEG`).
        """
        unknown = sorted(set(values) - set(self.keys))
        if unknown:
            raise ValueError(f"values has unknown slider(s) {unknown}; known: {list(self.keys)}")
        full = {**self.zero_values(), **{k: float(v) for k, v in values.items()}}
        base = {o.segment: o for o in (self.template.osteotomies if self.template else ())}
        moved = [s for s in self.segments
                 if s in base or any(full[k] != 0.0 for k in self.keys if k.startswith(s + "_"))]
        osteotomies = []
        for segment in moved or self.segments:
            move = {attr: tuple(full[slider_key(segment, kind, a)] for a, _ in AXES)
                    for kind, _, _, attr in KINDS}
            old = base.get(segment)
            osteotomies.append(Osteotomy(segment, pivot=old.pivot if old else None,
                                         cut=old.cut if old else (), **move))
        if name is None:
            name = self.template.name if self.template is not None else ""
        axes = self.template.axes if self.template is not None else "image"
        return Plan(tuple(osteotomies), name=name, axes=axes)

    def ranges(self, key):
        """``(min, max, step)`` of slider ``key``."""
        if key not in self.keys:
            raise ValueError(f"key must be one of {list(self.keys)}, got {key!r}")
        span = TRANSLATION_RANGE_MM if key.split("_")[1] == "t" else ROTATION_RANGE_DEG
        return -span, span, SLIDER_STEP
