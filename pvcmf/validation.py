"""Error statistics of a predicted face, face regions, and the validation study loop.

Paper 000 (sec. V, Figs. 6-8) and paper 001 judge a prediction by the signed distances
between predicted and actual skin: median, percentiles (001: 50/90/95 %), the share of
points within 1 and 2 mm (000 Fig. 8), for the whole face and, here, per face region.

* :func:`error_statistics` -> tidy :class:`pandas.DataFrame`, one row per region;
* :func:`label_face_regions` -> point array ``arrays.REGION`` from landmarks or geometry;
* :func:`run_study` -> runs ``predict(patient, method)`` for every patient and method and
  collects the distance arrays and the statistics table;
* :func:`study_predictor` -> the ``predict`` of paper 000's study on the virtual patients
  (pvcmf's pipeline against the :mod:`pvcmf.reference` truth, through a virtual
  post-operative CT: :mod:`pvcmf.postop`).

Delegates to numpy (percentiles) and pandas (the table); the study to pvcmf's pipeline,
:mod:`pvcmf.reference` (NGSolve) and :mod:`pvcmf.postop` (post-operative CT, segment,
skin, ``register``, ``distance_to``).
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


#: methods of :func:`study_predictor`: the two models of paper 000 and the truth itself
STUDY_METHODS = ("proposed", "state_of_the_art", "truth")
#: how far (mm) outside its grid the study's truth reaches (``postop_ct``'s ``extrapolate``:
#: tissue there moves with the nearest truth node); skin beyond it is not judged
TRUTH_REACH = 10.0


def study_predictor(*, spacing=2.0, n_tets=30_000, truth_tets=16_000, sigma=2.0,
                    truth_cache=True, cache_dir=None, truth=None, noise_hu=18.0,
                    ct_spacing=None):
    """The ``predict(patient, method)`` of paper 000's study on the virtual patients.

    The study runs the path of a real post-operative scan. For virtual patient ``patient``
    (``datasets.phantom(patient, spacing=spacing)``) and Table II's plan:

    1. the truth: the solved fine grid of :func:`pvcmf.reference.truth_grid` (NGSolve's
       large-deformation model, ``truth_tets`` P2 tetrahedra, cached on disk), or
       ``truth(case)``;
    2. the virtual post-operative CT: the pre-operative CT warped by it and by the plan's
       bone moves, with ``noise_hu`` of Gaussian noise and a random pose seeded by the
       patient number (:func:`pvcmf.postop.postop_ct`: up to 5 degrees, 10 mm);
    3. :func:`pvcmf.postop.validate_from_ct`: segment that CT -> skin (refined onto its
       -500 HU edge) -> point-to-plane ICP onto the pre-operative CT's skin on the upper
       face (forehead, orbits, nose bridge) -> exact signed distance of the prediction to
       the registered post-operative skin -> face regions.

    ``method`` "proposed" simulates with the muscle-embedded conforming mesh,
    "state_of_the_art" with the homogeneous mesh and random-point sampling of the muscle
    share (``sample_muscle_fraction``); both MTM predictions are mapped by paper 001's
    Gaussian mapping (width ``sigma``, at least half the median edge) to the dense skin of
    the pre-operative CT, extracted as the post-operative one is
    (:func:`pvcmf.postop.skin_from_ct`: segment, skin, refined onto the -500 HU edge), and
    judged on the meshed anterior face (``mapping_support > 0``, in front of the face
    box) where the truth is defined (inside its grid or within :data:`TRUTH_REACH` mm of
    a node; further out ``postop_ct`` fades the displacement away, so neither model can
    be judged there). "truth" judges that same skin moved by the truth grid (its displacement probed
    inside the grid, the nearest node's outside) on the anterior face through the same
    path: what the CT path itself adds (warping, noise, voxels, segmentation, ICP), the
    floor against which the differences between the methods are to be read.

    Parameters
    ----------
    spacing : float, default 2.0
        Voxel size of the virtual patients (mm).
    n_tets : int, default 30000
        Tetrahedra of the MTM meshes.
    truth_tets : int, default 16000
        Tetrahedra of the truth mesh (``truth_grid(n_tets=...)``; P2 elements).
    sigma : float, default 2.0
        Smallest Gaussian width of the tetrahedra -> skin mapping (mm).
    truth_cache : bool, default True
        Use the truth's on-disk cache.
    cache_dir : path, optional
        Truth cache folder (default ``PVCMF_CACHE_DIR`` / ``~/.cache/pvcmf``).
    truth : callable, optional
        ``truth(case) -> pyvista.UnstructuredGrid`` with ``arrays.DISPLACEMENT`` in the
        pre-operative frame, instead of the reference model (e.g. a synthetic truth in
        tests, where NGSolve is not installed).
    noise_hu : float, default 18.0
        Noise of the post-operative CT (HU).
    ct_spacing : float, optional
        Voxel size of the post-operative CT (default: the pre-operative one).

    Returns
    -------
    callable
        ``predict(patient, method) -> PolyData`` with point arrays ``arrays.DISTANCE`` and
        ``arrays.REGION`` and the ICP result in its field data, for :func:`run_study`.

    Examples
    --------
    >>> from pvcmf.validation import run_study, study_predictor
    >>> predict = study_predictor(spacing=3.0, n_tets=3000, truth_tets=6000)  # doctest: +SKIP
    >>> skins, distances, table = run_study(predict, patients=(1,))             # doctest: +SKIP
    """
    from scipy.spatial import cKDTree

    from . import filters, mtm, reference
    from .datasets import phantom
    from .filters.osteotomy import cut_bones
    from .pipeline import DEFAULT_FACE_FRACTION, face_box, simulate
    from .postop import postop_ct, skin_from_ct, validate_from_ct

    for name, value in (("spacing", spacing), ("sigma", sigma)):
        if not value > 0:
            raise ValueError(f"{name} must be > 0 mm, got {value!r}")
    for name, value in (("n_tets", n_tets), ("truth_tets", truth_tets)):
        if int(value) < 100:
            raise ValueError(f"{name} must be an integer >= 100, got {value!r}")
    if truth is not None and not callable(truth):
        raise TypeError(f"truth must be callable(case) -> grid, got {type(truth).__name__}")
    if not noise_hu >= 0:
        raise ValueError(f"noise_hu must be >= 0, got {noise_hu!r}")
    cases, scans = {}, {}

    def case(patient):
        if patient not in cases:
            cases[patient] = phantom(patient=patient, spacing=spacing)
        return cases[patient]

    def scan(patient):
        """The truth grid, the posed noisy post-operative CT and the pre-operative skin."""
        if patient not in scans:
            c = case(patient)
            if truth is None:
                grid = reference.truth_grid(c, n_tets=truth_tets, cache=truth_cache,
                                            cache_dir=cache_dir)
            else:
                grid = truth(c)
            ct, _ = postop_ct(c, grid, noise_hu=noise_hu, pose="random", seed=patient,
                              spacing=ct_spacing, extrapolate=TRUTH_REACH)
            pre_skin = skin_from_ct(c.ct, name="pre-operative CT")
            # the truth is defined inside its grid and, by postop_ct's full extrapolation,
            # up to TRUTH_REACH mm outside it: only that skin is judged
            covered = np.asarray(pre_skin.sample(grid, progress_bar=False)[
                "vtkValidPointMask"], dtype=bool)
            near, _ = cKDTree(grid.points).query(pre_skin.points[~covered])
            covered[~covered] = near <= TRUTH_REACH
            scans[patient] = grid, ct, pre_skin, covered
        return scans[patient]

    def predict(patient, method):
        if method not in STUDY_METHODS:
            raise ValueError(f"method must be 'proposed', 'state_of_the_art' or 'truth', "
                             f"got {method!r}")
        c = case(patient)
        grid, ct, pre_skin, covered = scan(patient)
        if method == "truth":  # the truth's own skin through the CT path: its floor
            labels = cut_bones(c.truth, c.plan)
            pred = reference._skin_of(pre_skin, grid)
            pred.point_data["mapping_support"] = np.ones(pred.n_points)
        else:
            conforming = method == "proposed"
            res = simulate(c.ct, c.plan, bones=c.truth, landmarks=c.landmarks, n_tets=n_tets,
                           mesh_options={"conforming": conforming}, figures=False)
            post = res.post
            if not conforming:  # state of the art: muscle share by random points, re-solved
                g = filters.sample_muscle_fraction(res.mesh, res.labels)
                g = filters.fiber_directions(g)
                post = mtm.solve(filters.assign_materials(g))
            labels = res.labels
            skin = pre_skin  # the skin of the pre-operative CT, as the truth is measured
            # the Gaussian must span the element size, or coarse meshes leave holes
            edges = post.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                                volume=False)
            width = max(sigma, 0.5 * float(np.median(edges["Length"])))
            pred = post.cmf.map_to_surface(skin, sigma=width)
        out, _ = validate_from_ct(c, ct, pred, pre_skin=pre_skin, landmarks=c.landmarks,
                                  regions=False)
        # only the face the model simulates (the meshed, anterior part) is judged
        y0 = face_box(labels, DEFAULT_FACE_FRACTION)[2]
        # (every prediction is a copy of pre_skin, point for point)
        face = (out["mapping_support"] > 0) & covered & (out.points[:, 1] >= y0)
        judged = out.extract_points(face, adjacent_cells=False).extract_surface(
            algorithm="dataset_surface")
        for key in out.field_data.keys():  # the ICP result
            judged.field_data[key] = out.field_data[key]
        return judged

    return predict
