"""Is the CT a head? A check of :func:`pvcmf.io.orientation.standardize` from measured
anatomy: a cranial cavity or teeth, with the air enclosed by the body named (the lungs of a
chest CT). Delegates to :mod:`scipy.ndimage` (labelling)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

__all__ = ["arch_trend", "check_head"]

#: tooth-dense range as multiples of the air -> soft tissue step above soft tissue (enamel
#: and dentine from about 2000 HU; metal from about 3000 HU), as in pvcmf.filters.segment
TEETH_STEPS = (1.88, 2.85)
#: longest piece (mm) of tooth-dense bone taken as teeth: a whole dental arch (an adult
#: arch is 50-60 mm wide and deep)
ARCH_MM = 70.0
#: least tooth volume (mL) that tells a head: one incisor crown (about 0.1 mL)
MIN_TEETH_ML = 0.1
#: share of the body's volume of enclosed air above which it is named lungs (a head's
#: sinuses and airway are a few per cent of it; the lungs a fifth to a half of a chest)
LUNG_SHARE = 0.1
#: least tooth-dense blocks whose layout is read as a dental arch (a few teeth at 3 mm)
MIN_ARCH_BLOCKS = 10


def _teeth_blocks(dense, ds):
    """The tooth-dense blocks in components no longer than a dental arch (``ARCH_MM``): the
    crowns and roots of the teeth, or the petrous bone; the cortex of a long bone as dense
    runs longer."""
    lab, n = ndi.label(dense, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return np.zeros(dense.shape, dtype=bool)
    keep = np.zeros(n + 1, dtype=bool)
    for i, sl in enumerate(ndi.find_objects(lab), start=1):  # one entry per component
        keep[i] = max((s.stop - s.start) * d for s, d in zip(sl, ds)) <= ARCH_MM
    keep[0] = False
    return keep[lab]


def _teeth_ml(dense, ds):
    """Volume (mL) of :func:`_teeth_blocks`."""
    return float(np.count_nonzero(_teeth_blocks(dense, ds))) * float(np.prod(ds)) / 1e3


def arch_trend(teeth, ds, lr, midline):
    """How the teeth lie along each image axis: the correlation between a tooth block's
    distance from the mid-sagittal plane and its coordinate along the axis (0 for the
    left-right axis ``lr`` itself), or None with fewer than ``MIN_ARCH_BLOCKS`` blocks.

    A dental arch is a U open toward the back of the head: the farther a tooth lies from
    the midline (molars), the farther back it lies. Along the anterior axis the correlation
    is strongly negative; it holds for a face-only scan (a cone-beam field around the jaws)
    whose skull base and spine make the bone share grow backward.

    ``teeth``: mask of tooth-dense blocks (:func:`_teeth_blocks`) of size ``ds`` (mm);
    ``midline``: the mid-sagittal plane's index along ``lr``.

    Examples
    --------
    >>> import numpy as np
    >>> teeth = np.zeros((20, 20, 3), dtype=bool)
    >>> for x in range(2, 18):  # an arch in x-y, its front toward +y
    ...     teeth[x, 16 - (x - 10) ** 2 // 5, 1] = True
    >>> [round(c, 2) for c in arch_trend(teeth, (3, 3, 3), 0, 10.0)]
    [0.0, -0.96, 0.0]
    """
    idx = np.nonzero(teeth)
    if len(idx[0]) < MIN_ARCH_BLOCKS:
        return None
    side = np.abs(idx[lr] - midline) * ds[lr]
    out = []
    for a in range(3):
        x = idx[a] * ds[a]
        ok = a != lr and np.ptp(side) > 0 and np.ptp(x) > 0
        out.append(float(np.corrcoef(side, x)[0, 1]) if ok else 0.0)
    return out


def check_head(cues):
    """Refuse a CT that shows no head: neither a cranial cavity nor teeth.

    Parameters
    ----------
    cues : dict
        The anatomical measurements of the image (``report["orientation"]["cues"]`` of
        :func:`standardize`): ``cavity_ml`` (soft tissue enclosed by bone, at least 5 % of
        the body and 50 mm across in every direction), ``teeth_ml`` (tooth-dense bone in
        pieces no longer than a dental arch), ``inner_air_ml`` (air enclosed by the body:
        sinuses and airway in a head, the lungs in a chest), ``body_ml``.

    Raises
    ------
    ValueError
        Naming the measurements, when there is neither a cranial cavity nor a tooth.

    Examples
    --------
    >>> from pvcmf.io.orientation import check_head
    >>> check_head({"cavity_ml": 1400, "teeth_ml": 0.0, "inner_air_ml": 60, "body_ml": 5000})
    >>> check_head({"cavity_ml": 0, "teeth_ml": 0.0, "inner_air_ml": 2500, "body_ml": 9000})
    Traceback (most recent call last):
    ...
    ValueError: not a head CT: no cranial cavity (no soft tissue enclosed by bone over 5 % of the body and 50 mm across) and no teeth (0.0 mL of tooth-dense bone); 2500 mL of air inside the body (28 % of it: lungs, a chest CT?). pvcmf models the face over the jaws: give a CT of the head with the jaws
    """
    cavity, teeth = cues.get("cavity_ml", 0), cues.get("teeth_ml", 0.0)
    if cavity > 0 or teeth >= MIN_TEETH_ML:
        return
    air, body = cues.get("inner_air_ml", 0), max(cues.get("body_ml", 0), 1)
    lungs = ": lungs, a chest CT?" if air >= LUNG_SHARE * body else ""
    raise ValueError(
        "not a head CT: no cranial cavity (no soft tissue enclosed by bone over 5 % of the "
        f"body and 50 mm across) and no teeth ({teeth:.1f} mL of tooth-dense bone); "
        f"{air:.0f} mL of air inside the body ({100 * air / body:.0f} % of it{lungs}). pvcmf "
        "models the face over the jaws: give a CT of the head with the jaws")
