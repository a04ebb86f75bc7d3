"""The validation study: predictions of every patient and method, judged and tabulated.

* :func:`run_study` -> runs ``predict(patient, method)`` for every patient and method and
  collects the distance arrays and the statistics table
  (:func:`pvcmf.study.statistics.error_statistics`);
* :func:`study_predictor` -> the ``predict`` of paper 000's study on the virtual patients:
  pvcmf's pipeline against the :mod:`pvcmf.truth` truth, through a virtual
  post-operative CT (:func:`pvcmf.truth.postop_ct`) judged as a real scan
  (:mod:`pvcmf.study.from_ct`).
"""

from __future__ import annotations

import functools
import logging

import numpy as np
from scipy.spatial import cKDTree

from .. import arrays, filters, mtm
from ..datasets import phantom
from ..filters.osteotomy import cut_bones
from ..pipeline import DEFAULT_FACE_FRACTION, face_box, simulate
from ..truth.graded import check_face_size
from ..truth.grid import _skin_of, truth_grid
from ..truth.independent import independent_truth_grid
from ..truth.postop import postop_ct
from .from_ct import judge_skin, register_postop_skin, skin_from_ct
from .paper001 import (FINE_METHOD, PAPER001_AUTO_METHODS, is_paper001_method, paper001_pipeline,
                       paper001_solve)
from .predictions import cached_judged, cached_prediction
from .statistics import _distances, error_statistics

log = logging.getLogger("pvcmf.validation")

__all__ = ["AUTO_METHODS", "CONTROL_METHODS", "JUDGE_LIMIT", "STUDY_METHODS", "TRUTH_REACH",
           "run_study", "study_predictor"]


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
    >>> from pvcmf.study.validation import run_study
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
#: deliberately degraded controls of :func:`study_predictor` (the inference must rank them
#: worse): "no_muscles" is "proposed" without the muscles: no atlas muscles and no fat/muscle
#: classification (every method of the study runs without it), so all soft tissue is fat;
#: "wrong_nu" is "proposed" with every Poisson ratio set to 0.3 (Table I: 0.43-0.46)
CONTROL_METHODS = ("no_muscles", "wrong_nu")
#: the two models with what a real pipeline has (no oracle inputs): the CT and the plan
#: alone (automatic segmentation, bone segments and atlas fit, no true bone labels or
#: landmarks); the second row next to the oracle-input row of :data:`STUDY_METHODS`
AUTO_METHODS = ("proposed_auto", "state_of_the_art_auto")
#: how far (mm) outside its grid the study's truth reaches (``postop_ct``'s ``extrapolate``:
#: tissue there moves with the nearest truth node); skin beyond it is not judged
TRUTH_REACH = 10.0
#: how far (mm) the post-operative CT's registered skin may lie from the truth's own skin
#: (the pre-operative skin moved by the truth) for a point to be judged. Beyond it the CT
#: does not show the skin where the truth puts it (e.g. an internal air passage that one CT
#: connects to the outside air and the other does not: its wall is skin in one scan only),
#: so no method can be judged there; such points are excluded from every method, counted
#: in the judged skin's field data ``arrays.STUDY_EXCLUDED`` and logged
JUDGE_LIMIT = 3.0


def study_predictor(*, spacing=2.0, n_tets=30_000, truth_tets=16_000, sigma=2.0,
                    truth_cache=True, cache_dir=None, truth=None, noise_hu=18.0,
                    ct_spacing=None, cases=None, prediction_cache=False, fine_tets=None,
                    truth_mesher="lattice", truth_face_mm=None, truth_materials="cells",
                    truth_face_margin_mm=0.0):
    """The ``predict(patient, method)`` of paper 000's study on the virtual patients.

    The study runs the path of a real post-operative scan. For virtual patient ``patient``
    (``datasets.phantom(patient, spacing=spacing)``) and Table II's plan:

    1. the truth: the solved fine grid of :func:`pvcmf.truth.truth_grid` (NGSolve's
       large-deformation model, ``truth_tets`` P2 tetrahedra, cached on disk), or
       ``truth(case)``;
    2. the virtual post-operative CT: the pre-operative CT warped by it and by the plan's
       bone moves, with ``noise_hu`` of Gaussian noise and a random pose seeded by the
       patient number (:func:`pvcmf.truth.postop_ct`: up to 5 degrees, 10 mm);
    3. :func:`pvcmf.study.from_ct.validate_from_ct`: segment that CT -> skin (refined onto its
       -500 HU edge) -> point-to-plane ICP onto the pre-operative CT's skin on the upper
       face (forehead, orbits, nose bridge) -> exact signed distance of the prediction to
       the registered post-operative skin -> face regions (the CT is segmented and
       registered once per patient: :func:`pvcmf.study.from_ct.register_postop_skin`).

    Every method runs paper 000's model: ``simulate(..., classify=False)``, the atlas
    muscles in fat without paper 001's fat/muscle classification.
    ``method`` "proposed" simulates with the muscle-embedded conforming mesh,
    "state_of_the_art" with the homogeneous mesh and random-point sampling of the muscle
    share (``sample_muscle_fraction``); both MTM predictions are mapped by paper 001's
    Gaussian mapping (width ``sigma``, at least half the median edge) to the dense skin of
    the pre-operative CT, extracted as the post-operative one is
    (:func:`pvcmf.study.from_ct.skin_from_ct`: segment, skin, refined onto the -500 HU edge), and
    judged on the meshed anterior face (``mapping_support > 0``, in front of the face
    box) where the truth is defined (inside its grid or within :data:`TRUTH_REACH` mm of
    a node; further out ``postop_ct`` fades the displacement away, so neither model can
    be judged there) and where the post-operative CT shows the skin within
    :data:`JUDGE_LIMIT` mm of where the truth puts it (elsewhere the scan cannot judge any
    method: the points are left out of every method and logged). "truth" judges that same skin moved by the truth grid (its displacement probed
    inside the grid, the nearest node's outside) on the anterior face through the same
    path: what the CT path itself adds (warping, noise, voxels, segmentation, ICP), the
    floor against which the differences between the methods are to be read. The controls
    of :data:`CONTROL_METHODS` ("no_muscles", "wrong_nu") are "proposed" made deliberately
    worse, to test that the study's inference (:mod:`pvcmf.study.inference`) can tell
    methods apart. The methods of :data:`AUTO_METHODS` ("proposed_auto",
    "state_of_the_art_auto") predict from the CT and the plan alone, as a real pipeline
    would (automatic segmentation, bone segments and atlas fit); the others get the true
    bone labels and landmarks. Paper 001's models (:mod:`pvcmf.study.paper001`:
    "homogeneous", "inhomogeneous", the homogeneous model at another Poisson ratio,
    :func:`~pvcmf.study.paper001.nu_method`, and "homogeneous_fine", on a mesh of
    ``fine_tets``) share one pipeline run per mesh size and patient, true bone labels and
    landmarks given. Every judged skin carries the point array
    ``arrays.SKIN_POINT_ID`` (the index of its points in the pre-operative skin), which
    pairs the points of two methods.

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
    truth : callable or 'independent', optional
        ``truth(case) -> pyvista.UnstructuredGrid`` with ``arrays.DISPLACEMENT`` in the
        pre-operative frame, instead of the reference model (e.g. a synthetic truth in
        tests, where NGSolve is not installed); ``'independent'``:
        :func:`pvcmf.truth.independent.independent_truth_grid` (own mesher, exact anatomy,
        own boundary model; ``truth_tets`` tetrahedra; ``truth_mesher``,
        ``truth_face_mm``, ``truth_materials``). Default: the reference model of
        :func:`pvcmf.truth.truth_grid`.
    truth_mesher : {'lattice', 'conforming', 'graded'}, default 'lattice'
        With ``truth='independent'``: its mesher (``independent_truth_grid(mesher=...)``).
        ``'conforming'`` and ``'graded'`` solve with ``reuse_factor=True``, as the
        refinement study (``benchmarks/truth_refinement.py``) does, so that the truth is
        the one whose convergence it measures.
    truth_face_mm : float or dict, optional
        With ``truth_mesher='graded'`` (and only then; required there): the size (mm) of
        the surface sampling in the face (``independent_truth_grid(face_mm=...)``), or a
        size per moved segment (``{"maxilla": 3.2, "mandible": 4.0}``: each patient's
        truth takes the smallest of the segments its plan moves);
        ``truth_tets`` sets the conforming spacing elsewhere.
    truth_materials : {'cells', 'field'}, default 'cells'
        With ``truth='independent'``: its materials (``independent_truth_grid(materials=...)``).
    truth_face_margin_mm : float, default 0.0
        With ``truth_mesher='graded'``: the fine ball also holds the soft tissue within this
        distance (mm) of the moved bones (``independent_truth_grid(face_margin_mm=...)``).
    noise_hu : float, default 18.0
        Noise of the post-operative CT (HU).
    ct_spacing : float, optional
        Voxel size of the post-operative CT (default: the pre-operative one).
    cases : mapping, optional
        ``patient -> pvcmf.datasets.Case`` (e.g. :func:`pvcmf.study.cohort.cohort`'s
        patients by number) instead of ``datasets.phantom(patient, spacing=spacing)``.
    prediction_cache : bool, default False
        Read / write each model's prediction (the MTM pipeline and the mapping onto the
        pre-operative skin) in the on-disk cache (``cache_dir``'s ``predictions`` folder,
        :mod:`pvcmf.study.predictions`: keyed by the patient, the plan, the method, the
        sizes and the code that computes it), so a second run of a study runs no
        pipeline. With the truth named (``None`` or ``'independent'``), also each judged
        skin (:func:`pvcmf.study.predictions.cached_judged`: keyed by the patient, the
        method, the sizes, the truth's options, the noise and the code of the prediction,
        the truth and the judging), so a second run neither builds the truth's mesh nor
        makes, segments and registers the post-operative CT; with a ``truth`` callable
        the judging always runs.
    fine_tets : int, optional
        Tetrahedra of the "homogeneous_fine" method (default ``2 * n_tets``).

    Returns
    -------
    callable
        ``predict(patient, method) -> PolyData`` with point arrays ``arrays.DISTANCE`` and
        ``arrays.REGION``, the ICP result and ``arrays.STUDY_EXCLUDED`` (face points not
        judged: the post-operative CT shows no skin within :data:`JUDGE_LIMIT` mm of the
        truth's) in its field data, for :func:`run_study`.

    Examples
    --------
    >>> from pvcmf.study.validation import run_study, study_predictor
    >>> predict = study_predictor(spacing=3.0, n_tets=3000, truth_tets=6000)  # doctest: +SKIP
    >>> skins, distances, table = run_study(predict, patients=(1,))             # doctest: +SKIP
    """
    for name, value in (("spacing", spacing), ("sigma", sigma)):
        if not value > 0:
            raise ValueError(f"{name} must be > 0 mm, got {value!r}")
    fine_tets = 2 * int(n_tets) if fine_tets is None else fine_tets
    for name, value in (("n_tets", n_tets), ("truth_tets", truth_tets),
                        ("fine_tets", fine_tets)):
        if int(value) < 100:
            raise ValueError(f"{name} must be an integer >= 100, got {value!r}")
    independent = _independent_options(truth, truth_mesher, truth_face_mm, truth_materials,
                                       truth_face_margin_mm)
    # a named truth is known by its options and code, so its judged skins can be cached
    named = {"truth": truth or "reference", "truth_tets": int(truth_tets),
             "noise_hu": float(noise_hu), "ct_spacing": ct_spacing,
             "reach": TRUTH_REACH, "judge_limit": JUDGE_LIMIT} if truth in (
                 None, "independent") else None
    if truth == "independent":
        named.update({f"truth_{k}": v for k, v in independent.items()})
        truth = functools.partial(independent_truth_grid, n_tets=truth_tets,
                                  cache=truth_cache, cache_dir=cache_dir, **independent)
    if truth is not None and not callable(truth):
        raise TypeError(f"truth must be callable(case) -> grid or 'independent', got "
                        f"{type(truth).__name__}")
    if not noise_hu >= 0:
        raise ValueError(f"noise_hu must be >= 0, got {noise_hu!r}")
    if truth is None:
        truth = functools.partial(_reference_truth, truth_tets=truth_tets, cache=truth_cache,
                                  cache_dir=cache_dir)
    built, scans, models = dict(cases or {}), {}, {}

    def case(patient):
        if patient not in built:
            built[patient] = phantom(patient=patient, spacing=spacing)
        return built[patient]

    def predict(patient, method):
        paper001 = is_paper001_method(method)
        if method not in STUDY_METHODS + CONTROL_METHODS + AUTO_METHODS and not paper001:
            raise ValueError(f"method must be 'proposed', 'state_of_the_art' or 'truth' "
                             f"(or one of {CONTROL_METHODS + AUTO_METHODS} or paper 001's "
                             f"models), got {method!r}")
        c = case(patient)
        size = int(fine_tets) if method == FINE_METHOD else int(n_tets)
        options = {"n_tets": size, "sigma": float(sigma)}

        def judge():
            if patient not in scans:
                scans[patient] = _scan(c, patient, truth, noise_hu, ct_spacing)
            grid, registered, pre_skin, judged = scans[patient]

            def compute():
                if not paper001:
                    return _prediction(c, method, grid, pre_skin, n_tets, sigma)
                auto = method in PAPER001_AUTO_METHODS  # from the CT and the plan alone
                key = (patient, size, auto)
                if key not in models:  # one pipeline per patient, size and inputs
                    for other in [k for k in models if k[0] != patient]:
                        del models[other]
                    models[key] = paper001_pipeline(c, size, oracle=not auto)
                res = models[key]
                return _face_y0(res.labels), _map(paper001_solve(res, method), pre_skin, sigma)

            y0, pred = cached_prediction(
                compute, c, method, options, cache=prediction_cache and method != "truth",
                cache_dir=cache_dir, n_points=pre_skin.n_points)
            return _judge(c, registered, pred, y0, judged)

        if prediction_cache and named is not None:
            return cached_judged(judge, c, method, {**options, **named}, cache_dir=cache_dir)
        return judge()

    return predict


def _independent_options(truth, mesher, face_mm, materials, margin=0.0):
    """The options of ``independent_truth_grid`` for the study's independent truth
    (validated; those of the refinement study for the conforming and graded meshers)."""
    if mesher not in ("lattice", "conforming", "graded"):
        raise ValueError(f"truth_mesher must be 'lattice', 'conforming' or 'graded', got "
                         f"{mesher!r}")
    if materials not in ("cells", "field"):
        raise ValueError(f"truth_materials must be 'cells' or 'field', got {materials!r}")
    if mesher == "graded":
        try:
            face_mm = check_face_size(face_mm)
        except ValueError:
            raise ValueError(f"truth_face_mm must be a size > 0 mm, or a mapping of the "
                             f"moved segments to sizes, with truth_mesher 'graded', got "
                             f"{face_mm!r}") from None
    if mesher != "graded" and face_mm is not None:
        raise ValueError(f"truth_face_mm applies to truth_mesher 'graded' only (None with "
                         f"truth_mesher {mesher!r}), got {face_mm!r}")
    if not (isinstance(margin, (int, float, np.number)) and not isinstance(margin, bool)
            and np.isfinite(margin) and margin >= 0):
        raise ValueError(f"truth_face_margin_mm must be a distance >= 0 mm, got {margin!r}")
    if margin and mesher != "graded":
        raise ValueError(f"truth_face_margin_mm applies to truth_mesher 'graded' only (0 with "
                         f"truth_mesher {mesher!r}), got {margin!r}")
    if truth != "independent" and (mesher, materials) != ("lattice", "cells"):
        raise ValueError(f"truth_mesher and truth_materials apply to truth 'independent' "
                         f"only (defaults 'lattice', 'cells' otherwise), got {mesher!r}, "
                         f"{materials!r} with truth {truth!r}")
    options = {"mesher": mesher, "materials": materials}
    if mesher != "lattice":
        options["reuse_factor"] = True
    if mesher == "graded":
        options["face_mm"] = face_mm
        if margin:  # (absent at 0: the judged skins cached before the option keep their keys)
            options["face_margin_mm"] = float(margin)
    return options


def _reference_truth(case, *, truth_tets, cache, cache_dir):
    return truth_grid(case, n_tets=truth_tets, cache=cache, cache_dir=cache_dir)


def _scan(case, patient, truth, noise_hu, ct_spacing):
    """The truth grid, the registered skin of the posed noisy post-operative CT, the
    pre-operative skin and the masks (covered, apart) of :func:`_judgeable`."""
    grid = truth(case)
    ct, _ = postop_ct(case, grid, noise_hu=noise_hu, pose="random", seed=patient,
                      spacing=ct_spacing, extrapolate=TRUTH_REACH, extension="nearest")
    pre_skin = skin_from_ct(case.ct, name="pre-operative CT")
    registered = register_postop_skin(case, ct, pre_skin=pre_skin, landmarks=case.landmarks)
    return grid, registered, pre_skin, _judgeable(case, patient, grid, registered, pre_skin)


def _judgeable(case, patient, grid, registered, pre_skin):
    """Masks of the pre-operative skin points the truth covers and of those of them that
    cannot be judged (logged when there are some).

    The truth is defined inside its grid and, by postop_ct's extrapolation of the nearest
    node (as the truth's own skin, pvcmf.truth.grid's _skin_of, moves), up to TRUTH_REACH
    mm outside it; of that skin, only the points where the post-operative CT shows the skin
    where the truth puts it (within JUDGE_LIMIT mm) are judged."""
    covered = np.asarray(pre_skin.sample(grid, progress_bar=False)[
        arrays.VALID_POINT_MASK], dtype=bool)
    near, _ = cKDTree(grid.points).query(pre_skin.points[~covered])
    covered[~covered] = near <= TRUTH_REACH
    own = judge_skin(_skin_of(pre_skin, grid), registered, landmarks=case.landmarks)
    apart = covered & ~(np.abs(np.asarray(own[arrays.DISTANCE])) <= JUDGE_LIMIT)
    if apart.any():
        log.warning("patient %s: %d of %d skin points the truth covers (%.1f %%) are not "
                    "judged: the post-operative CT shows no skin within %.1f mm of where the "
                    "truth puts it (largest gap %.1f mm; e.g. an air passage whose wall is "
                    "skin in one CT only)", patient, int(apart.sum()), int(covered.sum()),
                    100.0 * apart.sum() / max(int(covered.sum()), 1), JUDGE_LIMIT,
                    float(np.nanmax(np.abs(own[arrays.DISTANCE][apart]))))
    return covered, apart


def _prediction(case, method, grid, pre_skin, n_tets, sigma):
    """(front of the face box, predicted skin on the points of ``pre_skin``) of one
    method; the face box is that of the method's own cut labels."""
    if method == "truth":  # the truth's own skin through the CT path: its floor
        pred = _skin_of(pre_skin, grid)
        pred.point_data[arrays.MAPPING_SUPPORT] = np.ones(pred.n_points)
        return _face_y0(cut_bones(case.truth, case.plan)), pred
    oracle = method not in AUTO_METHODS  # true bone labels and landmarks given
    conforming = method not in ("state_of_the_art", "state_of_the_art_auto")
    # paper 000's models: the atlas muscles in fat, no fat/muscle classification (paper 001's
    # step, on by default in simulate). Off for every method, so the "no_muscles" control
    # loses all its muscle: with classification on, the classifier would find that muscle
    # again and the control would no longer be degraded.
    res = simulate(case.ct, case.plan, bones=case.truth if oracle else None,
                   landmarks=case.landmarks if oracle else None, n_tets=n_tets,
                   mesh_options={"conforming": conforming}, figures=False,
                   muscles=method != "no_muscles", classify=False)
    post = res.post
    if method == "wrong_nu":  # control: the proposed mesh with a wrong Poisson ratio
        g = res.mesh.copy()
        g.cell_data[arrays.NU] = np.full(g.n_cells, 0.3)
        post = mtm.solve(g)
    if not conforming:  # state of the art: muscle share by random points, re-solved
        g = filters.sample_muscle_fraction(res.mesh, res.labels)
        g = filters.fiber_directions(g)
        post = mtm.solve(filters.assign_materials(g))
    return _face_y0(res.labels), _map(post, pre_skin, sigma)


def _map(post, pre_skin, sigma):
    """A solved mesh's displacement on the pre-operative CT's skin (the skin the truth is
    measured on), by a Gaussian at least half the median edge wide (narrower ones leave
    holes on coarse meshes)."""
    edges = post.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                        volume=False)
    width = max(sigma, 0.5 * float(np.median(edges["Length"])))
    return post.cmf.map_to_surface(pre_skin, method="gaussian", sigma=width)


def _face_y0(labels):
    """Front of the face box of cut labels (mm): only the skin in front of it is judged."""
    return float(face_box(labels, DEFAULT_FACE_FRACTION)[2])


def _judge(case, registered, pred, y0, masks):
    """Distances of ``pred`` to the registered post-operative skin, on the judged anterior
    face only (the meshed part, in front of ``y0``, where the truth is judgeable)."""
    out = judge_skin(pred, registered, landmarks=case.landmarks)
    # (every prediction is a copy of pre_skin, point for point: its ids pair the methods)
    out.point_data[arrays.SKIN_POINT_ID] = np.arange(out.n_points, dtype=np.int64)
    covered, apart = masks
    front = (out[arrays.MAPPING_SUPPORT] > 0) & (out.points[:, 1] >= y0) & covered
    face = front & ~apart
    judged = out.extract_points(face, adjacent_cells=False).extract_surface(
        algorithm="dataset_surface")
    for key in out.field_data.keys():  # the ICP result
        judged.field_data[key] = out.field_data[key]
    judged.field_data[arrays.STUDY_EXCLUDED] = np.array([int((front & apart).sum())])
    return judged
