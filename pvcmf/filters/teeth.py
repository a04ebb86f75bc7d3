"""Which tooth-dense bone is teeth: the dentition, not the otic capsules of the skull base.

Dentine and enamel are as dense as the otic capsule of the petrous bone (around the inner
ear). :func:`teeth_of_the_dentition` keeps as teeth the tooth-dense components that are
neither near the intracranial volume (the capsule lies a few mm from the brain, the teeth
far from it) nor apart from the dentition: the components linked by gaps under
``DENTITION_LINK_MM`` form groups, and only the group with the most tooth voxels is kept.
The second rule holds where the scan has no intracranial volume (a face-only scan: a
cone-beam field around the jaws reaching the ears). The others are bone.

Delegates to :mod:`scipy.ndimage` (labelling, distance transforms) on a coarse copy.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import ndimage

from .morphology import _box, _down, _sq_edt

log = logging.getLogger(__name__)

__all__ = ["teeth_of_the_dentition"]

#: dense bone within this distance (mm) of the intracranial volume is not teeth: the otic
#: capsule of the petrous bone is as dense as dentine, ~5-10 mm from the brain; the
#: teeth are > 25 mm from it (the maxillary sinus and the orbits lie between)
TEETH_BRAIN_MM = 15.0
#: teeth farther than this (mm) from every other tooth of the dentition are not teeth: a gap
#: of two or three missing teeth, or the molars of an open mouth, stay below it; the otic
#: capsules lie several centimetres behind and above the last molars
DENTITION_LINK_MM = 35.0


def teeth_of_the_dentition(teeth, intracranial, spacing, factor):
    """``teeth`` without the tooth-dense bone of the skull base (see module): a new mask.

    ``teeth``, ``intracranial``: boolean masks on one grid of voxel size ``spacing`` (mm);
    ``factor``: the block size (voxels per axis) of the coarse copy the distances use.
    """
    teeth = _teeth_off_the_brain(teeth, intracranial, spacing, factor)
    return _one_dentition(teeth, spacing, factor)


def _one_dentition(teeth, spacing, factor, link=DENTITION_LINK_MM):
    """The group of ``teeth`` components linked by gaps under ``link`` mm (single linkage:
    the components of the coarse teeth grown by half the gap) that holds the most tooth
    voxels; the rest is dropped."""
    if not teeth.any():
        return teeth
    f = [int(v) for v in factor]
    cspace = np.asarray(spacing, dtype=float) * f
    tbox = _box(teeth, 0)
    sub = teeth[tbox]
    coarse = _down(sub, f, "any")
    pad = np.ceil(0.5 * link / cspace).astype(int) + 1
    grown = np.sqrt(_sq_edt(~np.pad(coarse, [(int(p), int(p)) for p in pad]), cspace))
    groups, n = ndimage.label(grown <= 0.5 * link, structure=np.ones((3, 3, 3), dtype=bool))
    if n <= 1:
        return teeth
    idx = np.nonzero(sub)
    of = groups[tuple(i // k + int(p) for i, k, p in zip(idx, f, pad))]
    count = np.bincount(of, minlength=n + 1)
    count[0] = 0
    keep = int(np.argmax(count))
    log.debug("segment: %d tooth-dense group(s) apart from the dentition are not teeth "
              "(%d voxels)", n - 1, int(count.sum() - count[keep]))
    out = teeth.copy()
    mask = np.zeros_like(sub)
    mask[idx] = of == keep
    out[tbox] = mask
    return out


def _teeth_off_the_brain(teeth, intracranial, spacing, factor, reach=TEETH_BRAIN_MM):
    """Teeth without the tooth-dense bone of the skull base: components of ``teeth`` that
    come within ``reach`` mm of the intracranial volume (distance on the coarse grid) are
    bone."""
    if not teeth.any() or not intracranial.any():
        return teeth
    # only the teeth's box matters: the coarse distance map of it, ``reach`` wider
    cspace = spacing * factor
    f = [int(v) for v in factor]
    grow = np.ceil(reach / cspace).astype(int) + 1
    tbox = _box(teeth, 0)
    start = [max(b.start // k - g, 0) * k for b, k, g in zip(tbox, f, grow)]  # block-aligned
    wide = tuple(slice(a, min(b.stop + (g + 1) * k, n))
                 for a, b, k, g, n in zip(start, tbox, f, grow, teeth.shape))
    ic = _down(intracranial[wide], f, "any")
    if not ic.any():
        return teeth
    dist = np.sqrt(_sq_edt(~ic, cspace))
    sub = teeth[tbox]
    comp, n = ndimage.label(sub, structure=np.ones((3, 3, 3), dtype=bool))
    idx = np.nonzero(sub)
    coarse_idx = tuple((i + b.start - a) // k for i, b, a, k in zip(idx, tbox, start, f))
    near = np.full(n + 1, np.inf)
    np.minimum.at(near, comp[idx], dist[coarse_idx])
    drop = near < reach
    if drop[1:].any():
        log.debug("segment: %d dense bone component(s) within %.0f mm of the brain are not "
                  "teeth", int(drop[1:].sum()), reach)
    out = teeth.copy()
    out[tbox] &= ~drop[comp]
    return out
