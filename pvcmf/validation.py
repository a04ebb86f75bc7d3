"""Error statistics of a predicted face, face regions, and the validation study loop.

Paper 000 (sec. V, Figs. 6-8) and paper 001 judge a prediction by the signed distances
between predicted and actual skin: median, percentiles (001: 50/90/95 %), the share of
points within 1 and 2 mm (000 Fig. 8), for the whole face and, here, per face region.

* :func:`error_statistics` -> tidy :class:`pandas.DataFrame`, one row per region;
* :func:`label_face_regions` -> point array ``arrays.REGION`` from landmarks or geometry;
* :func:`run_study` -> runs ``predict(patient, method)`` for every patient and method and
  collects the distance arrays and the statistics table;
* :func:`study_predictor` -> the ``predict`` of paper 000's study on the virtual patients
  (pvcmf's pipeline against the :mod:`pvcmf.reference` truth, scanned in another pose).

Delegates to numpy (percentiles) and pandas (the table); the study to pvcmf's pipeline,
:mod:`pvcmf.reference` (NGSolve) and the ``register`` / ``distance_to`` filters.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from . import arrays

log = logging.getLogger(__name__)

#: columns of the statistics table, in order
STAT_COLUMNS = (
    "n", "median", "mean_abs", "rms", "p50", "p90", "p95", "within_1mm", "within_2mm",
)


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
    >>> from pvcmf.validation import summary
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
    >>> from pvcmf.validation import error_statistics
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
    ``landmarks['pronasale']``); regions are boxes around it in (|x - x_tip|, z - z_tip)
    of an average adult face (nose -12..35 mm around the tip and 17 mm either side;
    upper lip -30..-12 mm, lower lip -45..-30, chin -75..-45, within 24-28 mm of the
    midline; cheeks 24-62 mm lateral, -45..20 mm; the patient's left cheek has x > x_tip),
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
    >>> from pvcmf.validation import label_face_regions
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
    dx = np.abs(p[:, 0] - tip[0])
    dz = p[:, 2] - tip[2]
    face = (p[:, 1] >= tip[1] - depth * scale) & _front_visible(p)
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
        inside = face & (dx >= x0) & (dx < x1) & (dz >= z0) & (dz < z1)
        if name == "cheek":
            left = p[:, 0] > tip[0]
            region[inside & left] = arrays.FACE_REGIONS["cheek_left"]
            region[inside & ~left] = arrays.FACE_REGIONS["cheek_right"]
        else:
            region[inside & (region == 0)] = arrays.FACE_REGIONS[name]
    out = skin.copy()
    out.point_data[arrays.REGION] = region
    return out


def run_study(predict, patients=(1, 2, 3, 4), methods=("proposed", "state_of_the_art"), *,
              regions=True):
    """Run the validation study: one prediction per patient and method, then statistics.

    Parameters
    ----------
    predict : callable
        ``predict(patient, method) -> skin`` returning the predicted skin with point array
        ``arrays.DISTANCE`` (signed error against that patient's actual skin).
    patients : sequence, default (1, 2, 3, 4)
        Patient ids (paper 000 Table II).
    methods : sequence of str, default ('proposed', 'state_of_the_art')
        Methods (paper 000: muscle-embedded mesh vs homogeneous mesh + sampling).
    regions : bool, default True
        Per-region rows in the table (see :func:`error_statistics`).

    Returns
    -------
    skins : dict
        ``skins[patient][method]`` -> the predicted skin (for Fig. 6).
    distances : dict
        ``distances[patient][method]`` -> 1-D signed distances (Figs. 7, 8).
    table : pandas.DataFrame
        :func:`error_statistics` rows with ``patient`` and ``method`` columns.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.validation import run_study
    >>> def predict(patient, method):
    ...     s = pv.Sphere()
    ...     s[arrays.DISTANCE] = np.full(s.n_points, 0.1 * patient)
    ...     return s
    >>> _, d, table = run_study(predict, patients=(1, 2), methods=("a",), regions=False)
    >>> table["median"].round(2).tolist()
    [0.1, 0.2]
    """
    import pandas as pd

    if not callable(predict):
        raise TypeError(f"predict must be callable(patient, method), got {type(predict).__name__}")
    skins, distances, tables = {}, {}, []
    for patient in patients:  # a handful of patients x methods: each runs a whole pipeline
        skins[patient], distances[patient] = {}, {}
        for method in methods:
            log.info("validation study: patient %s, method %s", patient, method)
            skin = predict(patient, method)
            d = _distances(skin)
            skins[patient][method] = skin
            distances[patient][method] = d
            tables.append(error_statistics(skin, regions=regions, patient=patient,
                                           method=method))
    return skins, distances, pd.concat(tables, ignore_index=True)


def study_predictor(*, spacing=2.0, n_tets=30_000, truth_tets=16_000, sigma=2.0,
                    truth_cache=True, cache_dir=None):
    """The ``predict(patient, method)`` of paper 000's study on the virtual patients.

    For virtual patient ``patient`` (``datasets.phantom(patient, spacing=spacing)``) and
    Table II's plan, ``method`` "proposed" simulates with the muscle-embedded conforming
    mesh, "state_of_the_art" with the homogeneous mesh and random-point sampling of the
    muscle share (``sample_muscle_fraction``); both MTM predictions are mapped to the dense
    pre-operative skin by paper 001's Gaussian mapping (width ``sigma``, at least half the
    median edge). The truth is :func:`pvcmf.reference.postop_skin` with ``n_tets =
    truth_tets``, moved to a random pose (seeded by the patient: up to 4 degrees and 5 mm)
    with 0.1 mm scanner noise and registered back by point-to-plane ICP on the face above
    the nose tip (forehead, orbits, nose bridge: unchanged by jaw surgery). The signed
    distance of the prediction to it is judged on the meshed anterior face only.

    Parameters
    ----------
    spacing : float, default 2.0
        Voxel size of the virtual patients (mm).
    n_tets : int, default 30000
        Tetrahedra of the MTM meshes.
    truth_tets : int, default 16000
        Tetrahedra of the truth mesh (``postop_skin(n_tets=...)``; P2 elements).
    sigma : float, default 2.0
        Smallest Gaussian width of the tetrahedra -> skin mapping (mm).
    truth_cache : bool, default True
        Use the truth's on-disk cache.
    cache_dir : path, optional
        Truth cache folder (default ``PVCMF_CACHE_DIR`` / ``~/.cache/pvcmf``).

    Returns
    -------
    callable
        ``predict(patient, method) -> PolyData`` with point arrays ``arrays.DISTANCE`` and
        ``arrays.REGION``, for :func:`run_study`.

    Examples
    --------
    >>> from pvcmf.validation import run_study, study_predictor
    >>> predict = study_predictor(spacing=3.0, n_tets=3000, truth_tets=6000)  # doctest: +SKIP
    >>> skins, distances, table = run_study(predict, patients=(1,))             # doctest: +SKIP
    """
    from scipy.spatial.transform import Rotation

    from . import filters, mtm, reference
    from .datasets import phantom
    from .pipeline import DEFAULT_FACE_FRACTION, face_box, simulate

    for name, value in (("spacing", spacing), ("sigma", sigma)):
        if not value > 0:
            raise ValueError(f"{name} must be > 0 mm, got {value!r}")
    for name, value in (("n_tets", n_tets), ("truth_tets", truth_tets)):
        if int(value) < 100:
            raise ValueError(f"{name} must be an integer >= 100, got {value!r}")
    cases = {}

    def case(patient):
        if patient not in cases:
            cases[patient] = phantom(patient=patient, spacing=spacing)
        return cases[patient]

    def truth_in_scanner(patient):
        c = case(patient)
        post = reference.postop_skin(c, n_tets=truth_tets, cache=truth_cache,
                                     cache_dir=cache_dir)
        rng = np.random.default_rng(patient)
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("xyz", rng.uniform(-4, 4, 3),
                                           degrees=True).as_matrix()
        pose[:3, 3] = rng.uniform(-5, 5, 3)
        scan = post.transform(pose, inplace=False)
        scan.points = scan.points + rng.normal(0, 0.1, scan.points.shape)  # scanner noise
        pre = filters.extract_skin(c.truth)
        tip = c.landmarks.get("pronasale", pre.points[np.argmax(pre.points[:, 1])])

        def region(p):  # the face above the nose tip, in front of the ears
            return (p[:, 2] > tip[2] + 15) & (p[:, 1] > tip[1] - 60)

        return scan.cmf.register(pre, region=region)

    def predict(patient, method):
        if method not in ("proposed", "state_of_the_art"):
            raise ValueError(
                f"method must be 'proposed' or 'state_of_the_art', got {method!r}")
        c = case(patient)
        conforming = method == "proposed"
        res = simulate(c.ct, c.plan, bones=c.truth, landmarks=c.landmarks, n_tets=n_tets,
                       mesh_options={"conforming": conforming}, figures=False)
        post = res.post
        if not conforming:  # state of the art: muscle share by random points, re-solved
            grid = filters.sample_muscle_fraction(res.mesh, res.labels)
            grid = filters.fiber_directions(grid)
            post = mtm.solve(filters.assign_materials(grid))
        skin = filters.extract_skin(res.labels)
        # the Gaussian must span the element size, or coarse meshes leave holes in the skin
        edges = post.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                            volume=False)
        width = max(sigma, 0.5 * float(np.median(edges["Length"])))
        pred = post.cmf.map_to_surface(skin, sigma=width)
        pred = label_face_regions(pred, landmarks=c.landmarks)
        out = pred.cmf.distance_to(truth_in_scanner(patient), max_distance=10.0)
        # only the face the model simulates (the meshed, anterior part) is judged
        y0 = face_box(res.labels, DEFAULT_FACE_FRACTION)[2]
        face = (out["mapping_support"] > 0) & (out.points[:, 1] >= y0)
        return out.extract_points(face, adjacent_cells=False).extract_surface(
            algorithm="dataset_surface")

    return predict
