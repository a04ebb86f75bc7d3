"""Error statistics of a predicted face, and face regions.

Paper 000 (sec. V, Figs. 6-8) and paper 001 judge a prediction by the signed distances
between predicted and actual skin: median, percentiles (001: 50/90/95 %), the share of
points within 1 and 2 mm (000 Fig. 8), for the whole face and, here, per face region.

* :func:`summary` -> the statistics of one set of distances;
* :func:`error_statistics` -> tidy :class:`pandas.DataFrame`, one row per region;
* :func:`label_face_regions` -> point array ``arrays.REGION`` from landmarks or geometry.

Delegates to numpy (percentiles) and pandas (the table).
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays

log = logging.getLogger("pvcmf.validation")

__all__ = ["STAT_COLUMNS", "error_statistics", "label_face_regions", "summary"]


#: columns of the statistics table, in order
STAT_COLUMNS = arrays.STAT_COLUMNS


def _distances(data):
    if isinstance(data, pv.DataSet):
        return np.asarray(
            arrays.require_array(data, arrays.DISTANCE, "point", dtype="f", ncomp=1,
                                 producer="distance_to"), dtype=float)
    d = np.asarray(data, dtype=float)
    if d.ndim != 1:
        raise ValueError(f"distances must be a 1-D array, got shape {d.shape}")
    return d


def summary(distances):
    """Statistics of one set of signed distances (mm).

    Parameters
    ----------
    distances : array_like or pyvista.DataSet
        Signed distances, or a dataset with point array ``arrays.DISTANCE``.

    Returns
    -------
    dict
        ``n``; ``median`` of the signed distance; ``mean_abs`` and ``rms``; ``p50``,
        ``p90``, ``p95`` percentiles of ``|d|`` (paper 001's accuracy measures);
        ``within_1mm`` and ``within_2mm`` in percent of points with ``|d| <= 1`` / ``2``
        (paper 000 Fig. 8). NaN entries of an empty set.

    Examples
    --------
    >>> from pvcmf.study.statistics import summary
    >>> s = summary([-1.0, 0.5, 3.0])
    >>> s["median"], round(s["within_1mm"], 1)
    (0.5, 66.7)
    """
    d = _distances(distances)
    d = d[np.isfinite(d)]
    if d.size == 0:
        return dict(zip(STAT_COLUMNS, [0] + [np.nan] * (len(STAT_COLUMNS) - 1)))
    a = np.abs(d)
    p50, p90, p95 = np.percentile(a, [50, 90, 95])
    return {
        "n": int(d.size),
        "median": float(np.median(d)),
        "mean_abs": float(a.mean()),
        "rms": float(np.sqrt(np.mean(d**2))),
        "p50": float(p50),
        "p90": float(p90),
        "p95": float(p95),
        "within_1mm": float(100.0 * np.mean(a <= 1.0)),
        "within_2mm": float(100.0 * np.mean(a <= 2.0)),
    }


def error_statistics(skin, *, regions=True, **labels):
    """Tidy table of the signed-error statistics, for the whole face and per region.

    Parameters
    ----------
    skin : pyvista.DataSet
        Predicted skin with point array ``arrays.DISTANCE`` (from ``distance_to``).
    regions : bool, default True
        Also one row per face region of ``arrays.FACE_REGIONS`` (except ``other``): the
        skin's ``arrays.REGION`` array, or :func:`label_face_regions` when it has none.
    **labels
        Extra columns with constant values (e.g. ``patient=1, method='proposed'``).

    Returns
    -------
    pandas.DataFrame
        One row per region (``region`` column: ``'face'`` then the region names), the
        columns of :data:`STAT_COLUMNS` and the ``labels``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.statistics import error_statistics
    >>> skin = pv.Sphere()
    >>> skin[arrays.DISTANCE] = np.full(skin.n_points, 0.5)
    >>> error_statistics(skin, regions=False, patient=1)[["region", "p90", "patient"]].values.tolist()
    [['face', 0.5, 1]]
    """
    import pandas as pd

    d = _distances(skin)
    rows = [{"region": "face", **summary(d)}]
    if regions:
        if not isinstance(skin, pv.DataSet):
            raise TypeError("regions=True needs a skin dataset, not a bare array")
        if arrays.REGION in skin.point_data:
            reg = arrays.require_array(skin, arrays.REGION, "point", dtype="iu", ncomp=1)
        else:
            reg = label_face_regions(skin)[arrays.REGION]
        for name, rid in arrays.FACE_REGIONS.items():
            if rid == 0:
                continue
            rows.append({"region": name, **summary(d[reg == rid])})
    table = pd.DataFrame(rows, columns=["region", *STAT_COLUMNS])
    for key, value in labels.items():
        table[key] = value
    return table


#: region boxes relative to the nose tip, in mm of an average adult face:
#: (|x| from the midline min, max; z below/above the tip min, max)
_REGION_BOXES = {
    "nose": (0.0, 17.0, -12.0, 35.0),
    "upper_lip": (0.0, 24.0, -30.0, -12.0),
    "lower_lip": (0.0, 24.0, -45.0, -30.0),
    "chin": (0.0, 28.0, -75.0, -45.0),
    "cheek": (24.0, 62.0, -45.0, 20.0),
}


#: landmarks on the face's midsagittal line: the median of their x is the midline
_MIDLINE_LANDMARKS = ("soft_tissue_nasion", "nasion", "subnasale", "labrale_superius",
                      "stomion", "labrale_inferius", "soft_tissue_B_point", "pogonion",
                      "soft_tissue_pogonion", "menton", "soft_tissue_menton")


def _midline(p, face, tip, landmarks, scale, row=2.0):
    """x (mm) of the face's midsagittal plane.

    The median x of the midline landmarks given; without them, the median over the
    ``row`` mm tall rows of the face (nose bridge to chin) of the midpoint between the
    face's leftmost and rightmost point: the middle of the face's width, which a nose tip
    bent to one side (a cadaver's, a broken nose) does not move. The nose tip's x when the
    face has no row of 20 points.
    """
    marks = [landmarks[k][0] for k in _MIDLINE_LANDMARKS if k in landmarks]
    if marks:
        return float(np.median(marks))
    dz = p[:, 2] - tip[2]
    keep = face & (dz >= _REGION_BOXES["chin"][2] * scale) & (dz < _REGION_BOXES["nose"][3] * scale)
    rows = np.floor(dz[keep] / row).astype(np.int64)
    if rows.size == 0:
        return float(tip[0])
    _, inv, counts = np.unique(rows, return_inverse=True, return_counts=True)
    lo = np.full(counts.size, np.inf)
    hi = np.full(counts.size, -np.inf)
    np.minimum.at(lo, inv, p[keep, 0])
    np.maximum.at(hi, inv, p[keep, 0])
    full = counts >= 20
    return float(np.median(0.5 * (lo + hi)[full])) if full.any() else float(tip[0])


def _front_visible(p, cell=2.0, slack=3.0):
    """Points within ``slack`` mm of the most anterior point of their 2 mm (x, z) column."""
    ij = np.floor((p[:, [0, 2]] - p[:, [0, 2]].min(axis=0)) / cell).astype(np.int64)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    _, inv = np.unique(key, return_inverse=True)
    front = np.full(inv.max() + 1, -np.inf)
    np.maximum.at(front, inv, p[:, 1])
    return p[:, 1] >= front[inv] - slack


def label_face_regions(skin, *, landmarks=None, scale=1.0, depth=45.0):
    """Label the face regions of a skin in the patient frame (x left, y anterior, z up).

    Geometric labeller: the nose tip (pronasale) is the most anterior point (or
    ``landmarks['pronasale']``); the midline is the median x of the midline landmarks
    given (``subnasale``, ``stomion``, ``pogonion``, ...) or else the middle of the face's
    width (the median, over 2 mm rows from the chin to the nose bridge, of the midpoint
    between the face's leftmost and rightmost point: a nose tip bent to one side does not
    move it). Regions are boxes in (``|x - x_mid|``, ``z - z_tip``) of an average adult face (nose
    -12..35 mm around the tip and 17 mm either side of the tip; upper lip -30..-12 mm,
    lower lip -45..-30, chin -75..-45, within 24-28 mm of the midline; cheeks 24-62 mm
    lateral, -45..20 mm; the patient's left cheek has x > x_mid),
    all times ``scale``, and only points within ``depth`` mm behind the tip that are
    seen from the front (within 3 mm of the most anterior point of their 2 mm (x, z)
    column: inner surfaces and the back of the head are left out). The lip / chin bands are moved to ``landmarks['stomion']`` and
    ``landmarks['subnasale']`` / ``['pogonion']`` when those are given. A coarse,
    documented partition for regional statistics, not an anatomical segmentation.

    Parameters
    ----------
    skin : pyvista.DataSet
        Skin surface in the patient frame.
    landmarks : dict, optional
        Name -> (x, y, z) in mm; ``pronasale``, ``subnasale``, ``stomion``, ``pogonion``
        are used when present.
    scale : float, default 1.0
        Face size relative to an average adult.
    depth : float, default 45.0
        Points further than this behind the nose tip (mm, along -y) are not face.

    Returns
    -------
    pyvista.DataSet
        Copy of ``skin`` with point array ``arrays.REGION`` (uint8, ids of
        ``arrays.FACE_REGIONS``).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.statistics import label_face_regions
    >>> head = pv.ParametricEllipsoid(70, 95, 110)
    >>> out = label_face_regions(head)
    >>> ids = set(np.unique(out[arrays.REGION]).tolist())
    >>> {arrays.FACE_REGIONS["nose"], arrays.FACE_REGIONS["chin"]} <= ids
    True
    """
    if not isinstance(skin, pv.DataSet) or skin.n_points == 0:
        raise ValueError("skin must be a non-empty pyvista dataset")
    landmarks = dict(landmarks or {})
    p = np.asarray(skin.points, dtype=float)
    tip = np.asarray(landmarks.get("pronasale", p[np.argmax(p[:, 1])]), dtype=float)
    dz = p[:, 2] - tip[2]
    face = (p[:, 1] >= tip[1] - depth * scale) & _front_visible(p)
    mid = _midline(p, face, tip, landmarks, scale)
    dx = np.abs(p[:, 0] - mid)
    bands = {k: [v[0] * scale, v[1] * scale, v[2] * scale, v[3] * scale]
             for k, v in _REGION_BOXES.items()}
    # landmark-driven band limits (relative to the tip)
    if "subnasale" in landmarks:
        z = landmarks["subnasale"][2] - tip[2]
        bands["nose"][2] = bands["upper_lip"][3] = z
    if "stomion" in landmarks:
        z = landmarks["stomion"][2] - tip[2]
        bands["upper_lip"][2] = bands["lower_lip"][3] = z
    if "pogonion" in landmarks:
        z = landmarks["pogonion"][2] - tip[2]
        bands["chin"][3] = bands["lower_lip"][2] = min(bands["lower_lip"][2], z + 10 * scale)
        bands["chin"][2] = z - 20 * scale
    region = np.zeros(len(p), dtype=np.uint8)
    for name, (x0, x1, z0, z1) in bands.items():  # five regions, not a loop over points
        across = np.abs(p[:, 0] - tip[0]) if name == "nose" else dx
        inside = face & (across >= x0) & (across < x1) & (dz >= z0) & (dz < z1)
        if name == "cheek":
            left = p[:, 0] > mid
            region[inside & left] = arrays.FACE_REGIONS["cheek_left"]
            region[inside & ~left] = arrays.FACE_REGIONS["cheek_right"]
        else:
            region[inside & (region == 0)] = arrays.FACE_REGIONS[name]
    out = skin.copy()
    out.point_data[arrays.REGION] = region
    return out
