"""The directions a plan's moves are given in: the image's, the occlusal plane's, or the
Frankfort horizontal's.

A plan's translations and rotations are (horizontal, vertical, anterior-posterior) numbers.
With ``axes = "image"`` (the default) these are the image's own axes, which are the face's
only when the head lies level in the scanner. A head scanned chin down or rolled then
moves the maxilla "forward" partly downward, by the sine of the tilt (a quarter of the move
at 15 degrees), and a head turned about its vertical axis moves it partly sideways.
:func:`plan_axes` gives the 3x3 rotation whose columns are the plan's (x, y, z) directions
in the image, which :meth:`pvcmf.plan.Osteotomy.matrix` turns the moves with:

* ``"occlusal"``: the plane of the upper dental arch found in the image
  (:func:`~pvcmf.filters.bone_segments.occlusal_normal`, fixed to the skull: the lower jaw may
  hang open). Vertical is its normal, horizontal the normal of the head's mirror plane
  through it (the symmetry of the skull's hard tissue, :func:`~pvcmf.filters.mirror_plane`,
  so a head turned about its vertical axis is turned back too), anterior-posterior the
  third. Derived from the image alone; refused where the teeth found are a row rather than
  an arch (a row's plane may turn about it) or where the hard tissue has no mirror plane.
* ``"frankfort"``: the Frankfort horizontal, the plane through both porions (the tops of the
  ear canals) and the orbitales (the lowest points of the orbit rims; their midpoint).
  Horizontal runs from the right porion to the left one, vertical is the plane's normal.
  The landmarks are the label image's (``arrays.LANDMARK_NAMES`` / ``LANDMARK_POINTS``:
  those given to :func:`pvcmf.pipeline.simulate` or :func:`~pvcmf.filters.embed_muscles`,
  else the atlas fit's own, which can lie several millimetres off a real scan's ear canal).

A frame more than :data:`MAX_AXES_DEG` from the image's axes is refused: the landmarks are
swapped or in another frame, or the teeth found are no arch.

Delegates to :func:`numpy.linalg.norm` and :func:`numpy.cross`; the arch's plane to
:mod:`pvcmf.filters.jaw_pose`, the mirror plane to :mod:`pvcmf.filters.symmetry`.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np

from .. import arrays
from ..plan import AXES, Plan
from .bone_segments import occlusal_normal, occlusal_plane
from .jaw_pose import MIN_ARCH_SPAN_MM
from .symmetry import mirror_plane

log = logging.getLogger(__name__)

__all__ = ["FRANKFORT_LANDMARKS", "MAX_AXES_DEG", "check_plan_landmarks", "frankfort_axes",
           "mirror_normal", "occlusal_axes", "plan_axes", "with_plan_axes"]

#: landmarks the Frankfort horizontal goes through
FRANKFORT_LANDMARKS = ("porion_left", "porion_right", "orbitale_left", "orbitale_right")
#: largest angle (degrees) between a plan's axes and the image's: a head lies in a scanner
#: at most this far from its axes (as :data:`pvcmf.filters.jaw_pose.MAX_TILT_DEG`)
MAX_AXES_DEG = 45.0
#: nearest the landmarks may lie (mm): porions (adults: 100-150 mm apart) and the orbitales'
#: midpoint from the porions' (70-90 mm)
MIN_SPAN_MM = 20.0


def _angle(frame):
    """Angle (degrees) of the rotation ``frame``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(frame) - 1.0) / 2.0, -1.0, 1.0))))


def _checked(frame, what):
    angle = _angle(frame)
    if angle > MAX_AXES_DEG:
        raise ValueError(
            f"{what} turn {angle:.0f} degrees from the image's axes, more than a head lies "
            f"tilted in a scanner ({MAX_AXES_DEG:g}): the landmarks are swapped or in another "
            "frame, or the image is not in the patient frame (pvcmf.filters.standardize)")
    return frame


def occlusal_axes(labels):
    """The occlusal plane's axes in the image: columns (left, anterior, superior).

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with ``tissue`` (teeth and bones), or holding the arch and the head's
        left-right direction already (``arrays.ARCH_NORMAL``, ``ARCH_SPAN``,
        ``MIRROR_NORMAL``: :func:`with_plan_axes` stores them).

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        A rotation: vertical is the upper arch's normal, horizontal the normal of the head's
        mirror plane through it (:func:`mirror_normal`), anterior the third.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> labels = pv.ImageData(dimensions=(2, 2, 2))
    >>> a = np.radians(10.0)  # an arch descending 10 degrees anteriorly
    >>> labels.field_data[arrays.ARCH_NORMAL] = [0.0, np.sin(a), np.cos(a)]
    >>> labels.field_data[arrays.ARCH_SPAN] = [13.0]  # mm across the row: an arch
    >>> labels.field_data[arrays.MIRROR_NORMAL] = [1.0, 0.0, 0.0]  # the head lies straight
    >>> np.round(occlusal_axes(labels)[:, 1], 3).tolist()  # anterior points down 10 deg
    [0.0, 0.985, -0.174]
    """
    normal = occlusal_normal(labels)
    across = mirror_normal(labels, normal)
    x = across - (across @ normal) * normal
    if np.linalg.norm(x) < 0.5:
        raise ValueError(f"occlusal_axes: the arch's normal {np.round(normal, 3).tolist()} is "
                         "nearly the head's left-right direction: no occlusal plane")
    x /= np.linalg.norm(x)
    frame = np.column_stack([x, np.cross(normal, x), normal])
    return _checked(frame, "the occlusal plane's axes")


def mirror_normal(labels, normal):
    """The head's left-right direction: ``arrays.MIRROR_NORMAL`` where ``labels`` hold it,
    else the normal of the mirror plane of their hard tissue that contains ``normal``
    (:func:`~pvcmf.filters.symmetry.mirror_plane`)."""
    fd = labels.field_data
    if arrays.MIRROR_NORMAL in fd:
        across = np.asarray(fd[arrays.MIRROR_NORMAL], dtype=float).ravel()
        if across.shape != (3,) or not np.isfinite(across).all() or not across.any():
            raise ValueError(f"labels' field {arrays.MIRROR_NORMAL!r} must be 3 finite numbers, "
                             f"not all zero; got {across.tolist()}")
        across = across / np.linalg.norm(across)
        return across if across[0] >= 0 else -across
    return mirror_plane(labels, normal).direction


def _landmarks(labels):
    """The label image's landmarks as a dict, or None."""
    fd = labels.field_data
    if arrays.LANDMARK_NAMES not in fd or arrays.LANDMARK_POINTS not in fd:
        return None
    points = np.asarray(fd[arrays.LANDMARK_POINTS], dtype=float).reshape(-1, 3)
    return dict(zip((str(n) for n in fd[arrays.LANDMARK_NAMES]), points))


def frankfort_axes(landmarks):
    """The Frankfort horizontal's axes in the image: columns (left, anterior, superior).

    Parameters
    ----------
    landmarks : dict or pyvista.ImageData
        ``{name: (x, y, z)}`` (mm) with :data:`FRANKFORT_LANDMARKS`, or a label image
        holding them (``arrays.LANDMARK_NAMES`` / ``LANDMARK_POINTS``).

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        A rotation: horizontal from the right porion to the left, vertical the normal of
        the plane through both porions and the orbitales' midpoint.

    Raises
    ------
    ValueError
        A landmark missing or not finite, landmarks too close to span a plane
        (:data:`MIN_SPAN_MM`), or axes beyond :data:`MAX_AXES_DEG` from the image's.

    Examples
    --------
    >>> marks = {"porion_left": (60, 0, 0), "porion_right": (-60, 0, 0),
    ...          "orbitale_left": (30, 80, -8), "orbitale_right": (-30, 80, -8)}
    >>> import numpy as np
    >>> np.round(frankfort_axes(marks)[:, 1], 3).tolist()  # the orbitales lie 8 mm lower
    [0.0, 0.995, -0.1]
    """
    given = landmarks if isinstance(landmarks, dict) else _landmarks(landmarks)
    if given is None:
        raise ValueError(
            "plan axes 'frankfort' need the landmarks " + ", ".join(FRANKFORT_LANDMARKS)
            + ": the label image holds none (give landmarks= to simulate, or run "
            "embed_muscles first)")
    missing = [n for n in FRANKFORT_LANDMARKS if n not in given]
    if missing:
        raise ValueError(f"plan axes 'frankfort' need the landmarks {missing}; got "
                         f"{sorted(given)}")
    pl, pr, ol, orr = (np.asarray(given[n], dtype=float) for n in FRANKFORT_LANDMARKS)
    if not all(p.shape == (3,) and np.isfinite(p).all() for p in (pl, pr, ol, orr)):
        raise ValueError("the Frankfort landmarks must be 3 finite numbers each (mm), got "
                         + str({n: given[n] for n in FRANKFORT_LANDMARKS}))
    across, forward = pl - pr, (ol + orr) / 2.0 - (pl + pr) / 2.0
    if min(np.linalg.norm(across), np.linalg.norm(forward)) < MIN_SPAN_MM:
        raise ValueError(
            f"the Frankfort landmarks span no plane: porions {np.linalg.norm(across):.1f} mm "
            f"apart, orbitales {np.linalg.norm(forward):.1f} mm from them (at least "
            f"{MIN_SPAN_MM:g} mm each)")
    x = across / np.linalg.norm(across)
    z = np.cross(x, forward)
    z /= np.linalg.norm(z)
    frame = np.column_stack([x, np.cross(z, x), z])
    return _checked(frame, "the Frankfort horizontal's axes")


def plan_axes(labels, plan):
    """The 3x3 rotation whose columns are ``plan``'s (x, y, z) directions in the image.

    Parameters
    ----------
    labels : pyvista.ImageData
        The label image the plan moves (its teeth or arch normal for ``"occlusal"``, its
        landmarks for ``"frankfort"``).
    plan : pvcmf.Plan or str
        A plan, or one of :data:`pvcmf.plan.AXES`.

    Returns
    -------
    numpy.ndarray, shape (3, 3)
        The identity for ``"image"``.

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.plan import Osteotomy, Plan
    >>> plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 5.0)),))
    >>> plan_axes(pv.ImageData(dimensions=(2, 2, 2)), plan).tolist()  # the image's axes
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    axes = plan.axes if isinstance(plan, Plan) else plan
    if axes not in AXES:
        raise ValueError(f"axes must be one of {list(AXES)}, got {axes!r}")
    if axes == "image":
        return np.eye(3)
    frame = occlusal_axes(labels) if axes == "occlusal" else frankfort_axes(labels)
    log.debug("plan axes %r: %.1f degrees from the image's", axes, _angle(frame))
    return frame


def check_plan_landmarks(plan, landmarks, *, fit, labels=None):
    """Refuse, before any work, a Frankfort plan without its landmarks: ``landmarks``
    given (checked), held by the given ``labels``, or ``fit`` (the atlas fit of the muscle
    step will place them)."""
    if plan.axes != "frankfort":
        return
    if landmarks is not None:
        frankfort_axes(dict(landmarks))
    elif labels is not None and _landmarks(labels) is not None:
        frankfort_axes(labels)
    elif not fit:
        raise ValueError("plan axes 'frankfort' need the landmarks " + ", ".join(
            FRANKFORT_LANDMARKS) + ": give landmarks=, or keep muscles=True (the atlas fit "
            "then places them)")


def _with_landmarks(labels, landmarks):
    """A shallow copy of ``labels`` holding ``landmarks`` (over those it holds)."""
    merged = {**(_landmarks(labels) or {}), **dict(landmarks)}
    out = labels.copy(deep=False)
    names = sorted(merged)
    out.field_data[arrays.LANDMARK_NAMES] = np.array(names)
    out.field_data[arrays.LANDMARK_POINTS] = np.array(
        [np.asarray(merged[n], dtype=float) for n in names])
    return out


def _roll_against_teeth(labels, frame):
    """Degrees the Frankfort ``frame``'s horizontal rises out of the upper dental arch's
    plane towards the left, or None where the labels hold no arch."""
    try:
        normal = occlusal_normal(labels)
    except ValueError:
        return None
    return float(np.degrees(np.arcsin(np.clip(frame[:, 0] @ normal, -1.0, 1.0))))


def _turn_against_mirror(labels, frame):
    """Degrees the Frankfort ``frame``'s horizontal turns, about its vertical, from the
    normal of the skull's mirror plane, or None where the labels hold no mirror plane."""
    try:
        across = mirror_normal(labels, frame[:, 2])
    except ValueError:
        return None
    across = across - (across @ frame[:, 2]) * frame[:, 2]
    return -float(np.degrees(np.arctan2(across @ frame[:, 1], across @ frame[:, 0])))


def _with_arch(labels):
    """``labels``, or a shallow copy holding the arch and the head's left-right direction
    (``arrays.ARCH_NORMAL``, ``ARCH_SPAN``, ``MIRROR_NORMAL``), each measured where missing
    (once: every later step reads them)."""
    fd = labels.field_data
    if all(name in fd for name in (arrays.ARCH_NORMAL, arrays.ARCH_SPAN, arrays.MIRROR_NORMAL)):
        return labels
    normal, span = occlusal_plane(labels)
    out = labels.copy(deep=False)
    out.field_data[arrays.ARCH_NORMAL] = normal
    out.field_data[arrays.ARCH_SPAN] = np.array([span])
    if arrays.MIRROR_NORMAL not in fd and span >= MIN_ARCH_SPAN_MM:  # else refused anyway
        mirror = mirror_plane(labels, normal)
        out.field_data[arrays.MIRROR_NORMAL] = mirror.direction
        log.info("plan axes 'occlusal': the head turns %+.1f degrees about its vertical axis "
                 "from the image's (its mirror plane's overlap %.2f)", mirror.turn,
                 mirror.overlap)
    return out


def with_plan_axes(labels, plan, landmarks=None):
    """``labels`` with what ``plan``'s axes need, checked and logged before the mesh.

    A Frankfort plan's ``landmarks`` are stored in a shallow copy's field data (over those
    the labels hold), as are an occlusal plan's arch and the head's left-right direction
    where the labels do not hold them (``arrays.ARCH_NORMAL``, ``ARCH_SPAN``,
    ``MIRROR_NORMAL``: measured once, read by every later step);
    without landmarks those the labels hold (the atlas fit's, in
    :func:`pvcmf.pipeline.simulate`) are used, with a warning that says how far their
    horizontal rolls from the upper dental arch's plane and turns from the skull's mirror
    plane (faces are near symmetric: a few degrees point to a misplaced porion, or to a
    canted arch). Returns ``labels`` itself for a plan in the image's axes.
    """
    if plan.axes == "image":
        return labels
    if plan.axes == "frankfort" and landmarks is not None:
        labels = _with_landmarks(labels, landmarks)
    fd = labels.field_data
    if plan.axes == "occlusal":
        labels = _with_arch(labels)
    frame = plan_axes(labels, plan)
    if plan.axes == "frankfort" and landmarks is None:
        roll, turn = _roll_against_teeth(labels, frame), _turn_against_mirror(labels, frame)
        checks = ([] if roll is None else [f"rolls {roll:+.1f} degrees from the upper dental "
                                           "arch's plane"]) + \
            ([] if turn is None else [f"turns {turn:+.1f} degrees from the skull's mirror plane"])
        warnings.warn(
            "plan axes 'frankfort' from the porions and orbitales the label image holds, "
            "not from landmarks given: where the atlas fit placed them, a porion can lie "
            "several millimetres off a real scan's ear canal (a few degrees of roll)"
            + ("; this horizontal " + " and ".join(checks) if checks else "")
            + "; give the landmarks (landmarks=, --landmarks) for a precise frame",
            UserWarning, stacklevel=3)
    log.info("plan axes %r: %.1f degrees from the image's axes", plan.axes, _angle(frame))
    return labels
