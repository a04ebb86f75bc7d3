"""Whether the scan holds each planned bone segment whole.

A scan of the face alone (a cone-beam field, a CT cut at the lips) can end inside a jaw:
the segment found there is the part in the scan, and a plan that moves it moves that
part only, while the skin on the image's end is the scan's edge, not the patient's.
:func:`segment_coverage` finds, per segment, the image ends its voxels reach (numpy counts
over the end planes) and how many of its voxels lie on a cut of the scan the
segmentation found (:func:`pvcmf.filters.field_of_view.on_scan_cuts`: flat cuts and the
round field of view). :func:`check_coverage` (a step of :func:`pvcmf.pipeline.simulate`,
after :func:`pvcmf.filters.cut_bones`) warns with :func:`coverage_message` and adds an
inferior end that cuts a segment to the labels' cuts (:func:`with_inferior_cut`): the
segmentation never reports that end itself, since the neck always leaves the scan
there, but a jaw reaching it means the face is cut there too. Delegates to numpy. Index
axis 2 is the axial axis and the patient frame (x left, y anterior, z superior) is
assumed for the side names, as in :mod:`pvcmf.filters.field_of_view`.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays
from ..arrays import voxel_points
from .field_of_view import cuts_array, on_scan_cuts

log = logging.getLogger(__name__)

__all__ = ["check_coverage", "coverage_message", "segment_coverage", "with_inferior_cut"]

#: the image ends, as (axis, sign of the outward normal): their names
SIDES = {(0, -1): "right (-x)", (0, 1): "left (+x)", (1, -1): "posterior (-y)",
         (1, 1): "anterior (+y)", (2, -1): "inferior (-z)", (2, 1): "superior (+z)"}


def segment_coverage(labels, segment_ids):
    """Where the scan cuts each bone segment ``segment_ids`` of ``labels``' ``bone`` array.

    Returns
    -------
    dict
        Per segment id present: ``{"ends": [(axis, sign, voxels, mm^2), ...],
        "on_cuts": voxels, "voxels": voxels}``: the image ends its voxels reach (with how
        many voxels and how much area of the end plane they cover) and how many of its
        voxels lie on a cut the segmentation found (``arrays.SCAN_CUTS``,
        ``arrays.SCAN_FOV``). A segment the scan holds whole has no ends and no voxels
        on cuts.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.segment_coverage import segment_coverage
    >>> img = pv.ImageData(dimensions=(6, 6, 6))
    >>> bone = np.zeros((6, 6, 6), np.uint8)
    >>> bone[2:4, 2:4, 0:3] = arrays.MANDIBLE   # down to the image's inferior end
    >>> img[arrays.BONE] = bone.ravel(order="F")
    >>> segment_coverage(img, [arrays.MANDIBLE, arrays.MAXILLA])
    {3: {'ends': [(2, -1, 4, 4.0)], 'on_cuts': 0, 'voxels': 12}}
    """
    if not isinstance(labels, pv.ImageData):
        raise TypeError(f"labels must be a pyvista.ImageData, got {type(labels).__name__}")
    bone = np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu", ncomp=1,
                                           producer="segment"))
    dims = tuple(int(d) for d in labels.dimensions)
    spacing = np.asarray(labels.spacing, dtype=float)
    vol = bone.reshape(dims, order="F")
    wanted = np.asarray(list(dict.fromkeys(int(s) for s in segment_ids)), dtype=np.int64)
    ids = np.flatnonzero(np.isin(bone, wanted))
    which = bone[ids]
    on = on_scan_cuts(voxel_points(labels, ids), labels)  # once for every segment
    out = {}
    for sid in wanted.tolist():
        mine = which == sid
        if not mine.any():
            continue
        ends = []
        for (axis, sign) in SIDES:
            index = 0 if sign < 0 else dims[axis] - 1
            plane = (slice(None),) * axis + (index,)  # a view (np.take would copy)
            n = int(np.count_nonzero(vol[plane] == sid))
            if n:
                area = n * float(np.prod(np.delete(spacing, axis)))
                ends.append((axis, sign, n, area))
        out[sid] = {"ends": ends, "on_cuts": int(np.count_nonzero(on[mine])),
                    "voxels": int(np.count_nonzero(mine))}
    return out


def coverage_message(name, coverage, labels):
    """The warning for segment ``name`` with :func:`segment_coverage` entry ``coverage``,
    or None where the scan holds it whole."""
    parts = []
    origin, spacing = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    dims = np.asarray(labels.dimensions)
    for axis, sign, _, area in coverage["ends"]:
        at = origin[axis] + spacing[axis] * (0 if sign < 0 else dims[axis] - 1)
        parts.append(f"the image's {SIDES[(axis, sign)]} end at {'xyz'[axis]} = {at:.0f} mm "
                     f"({area:.0f} mm^2 of it)")
    if coverage["on_cuts"]:
        share = 100.0 * coverage["on_cuts"] / coverage["voxels"]
        parts.append(f"the scan's cut ({share:.1f} % of its voxels)")
    if not parts:
        return None
    return (f"the scan does not hold the whole {name}: it reaches {' and '.join(parts)}; the "
            "plan moves only the part in the scan, and the face over the rest is not "
            "predicted")


def with_inferior_cut(labels):
    """A copy of ``labels`` whose scan cuts (``arrays.SCAN_CUTS``) hold the image's
    inferior end as a flat cut by the image's end, over the extent of the head in that
    plane (the non-air voxels of ``arrays.TISSUE``, else the bone's): the skin there is
    the scan's edge (:func:`~pvcmf.filters.field_of_view.on_scan_cuts` marks it). Unchanged
    (a copy) where the cuts already hold that end or the plane holds no head."""
    out = labels.copy()
    dims = tuple(int(d) for d in labels.dimensions)
    name = arrays.TISSUE if arrays.TISSUE in labels.point_data else arrays.BONE
    values = np.asarray(labels.point_data[name]).reshape(dims, order="F")[:, :, 0]
    head = values != (arrays.AIR if name == arrays.TISSUE else 0)
    rows = np.zeros((0, 8))
    if arrays.SCAN_CUTS in labels.field_data:
        rows = np.asarray(labels.field_data[arrays.SCAN_CUTS], dtype=np.float64).reshape(-1, 8)
    if not head.any() or np.any((rows[:, 0] == 2) & (rows[:, 1] < 0)):
        return out
    origin, spacing = np.asarray(labels.origin, float), np.asarray(labels.spacing, float)
    i, j = np.nonzero(head)
    cut = {"axis": 2, "sign": -1, "at": float(origin[2]),
           "lo": (float(origin[0] + spacing[0] * i.min()), float(origin[1] + spacing[1] * j.min())),
           "hi": (float(origin[0] + spacing[0] * i.max()), float(origin[1] + spacing[1] * j.max())),
           "edge": False}
    out.field_data[arrays.SCAN_CUTS] = np.concatenate([rows.reshape(-1), cuts_array([cut])])
    return out


def check_coverage(labels, plan):
    """Warn (``logging``) for each segment ``plan`` moves that the scan does not hold whole
    (:func:`segment_coverage`, :func:`coverage_message`).

    Returns
    -------
    pyvista.ImageData
        A copy of ``labels``; where a segment reaches the image's inferior end, with that
        end among the scan's cuts (:func:`with_inferior_cut`), so that the skin on it is
        marked as the scan's edge.
    """
    coverage = segment_coverage(labels, [o.segment_id for o in plan.osteotomies])
    inferior = False
    for o in plan.osteotomies:
        entry = coverage.get(o.segment_id)
        message = None if entry is None else coverage_message(o.segment, entry, labels)
        if message is not None:
            log.warning("bone segments: %s", message)
            inferior |= any((axis, sign) == (2, -1) for axis, sign, _, _ in entry["ends"])
    return with_inferior_cut(labels) if inferior else labels.copy()
