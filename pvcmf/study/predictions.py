"""On-disk cache of the study's predictions (one per patient, method, sizes and options).

A prediction of :func:`pvcmf.study.validation.study_predictor` (an MTM pipeline, the
mapping onto the pre-operative skin) costs seconds to minutes and does not depend on the
truth, so a second run of a study reads it instead of running the pipeline again. An entry
is a folder (``predictions/<key>/``: ``skin.vtp`` and ``meta.json``) written atomically
by :func:`pvcmf.cache.cached`; its key (:func:`prediction_key`) hashes

* the patient: its number, generation parameters, voxel size, plan and landmarks, and
  the bytes of its CT and label images (a case built by other means gets its own key);
* the method and the options (MTM tetrahedra, Gaussian width);
* :func:`prediction_code_hash`: the code that computes a prediction (the whole package
  but the truth, the figures, the reports and the sweeps), so editing that code
  recomputes the entry, and the versions of numpy, scipy and VTK.

An entry that cannot be read, or whose skin does not match its record (points, arrays),
is recomputed, never trusted. Delegates to :mod:`pvcmf.cache`.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
from pathlib import Path

import numpy as np

from .. import arrays
from ..cache import cache_root, cached, code_hash, make_key

log = logging.getLogger("pvcmf.validation")

__all__ = ["cached_judged", "cached_prediction", "judged_code_hash", "prediction_code_hash",
           "prediction_key"]

_PACKAGE = Path(__file__).resolve().parents[1]
#: folders of the package whose code never runs in a prediction
_NOT_PREDICTION = ("truth", "figures", "report", "study")
#: modules of those folders (and top-level modules) that do run in one
_PREDICTION_EXTRA = ("truth/postop.py", "study/validation.py", "study/from_ct.py",
                     "study/predictions.py", "study/paper001.py")
#: top-level modules above the pipeline
_ABOVE = ("cli.py", "accessor.py", "validation.py")
#: code a judged skin runs beyond its prediction: the truth (mesh, solve, post-operative
#: CT), the face regions and the cohort's patients
_JUDGED_EXTRA = ("truth", "study/statistics.py", "study/cohort.py")
#: libraries whose version is part of a judged skin's key (besides numpy, scipy and VTK):
#: the truth's solver, the segmentation's distance maps, the meshers, pyvista's filters
_JUDGED_LIBRARIES = ("ngsolve", "SimpleITK", "gmsh", "pyvista")


@functools.lru_cache(maxsize=None)
def prediction_code_hash(package=None):
    """:func:`pvcmf.cache.code_hash` of the code that computes a study's prediction.

    Every ``*.py`` file of the package except the truth, figures, reports, sweeps and the
    command line (the study's prediction path, :mod:`pvcmf.truth.postop`'s sampling of
    the CT included), with the versions of numpy, scipy and VTK.

    Examples
    --------
    >>> from pvcmf.study.predictions import prediction_code_hash
    >>> len(prediction_code_hash())
    16
    """
    import scipy
    import vtk

    root = Path(package) if package else _PACKAGE
    files = [f for f in sorted(root.rglob("*.py"))
             if f.relative_to(root).parts[0] not in _NOT_PREDICTION + _ABOVE]
    files += [root / f for f in _PREDICTION_EXTRA if (root / f).exists()]
    versions = f"numpy {np.__version__} scipy {scipy.__version__} vtk {vtk.vtkVersion.GetVTKVersion()}"
    return make_key(code_hash(*files, root=root), versions, length=16)


@functools.lru_cache(maxsize=None)
def judged_code_hash(package=None):
    """:func:`pvcmf.cache.code_hash` of the code that computes a judged skin of the study.

    :func:`prediction_code_hash` and the truth (its mesher, solver and post-operative
    CT: the whole ``truth`` folder), the face regions (``study/statistics.py``) and the
    cohort's patients (``study/cohort.py``), with the versions of NGSolve, SimpleITK,
    gmsh and pyvista (those installed). Keys the cached judged skins and cohort patients
    (:func:`cached_judged`, :func:`pvcmf.study.cohort.virtual_patient`).

    Examples
    --------
    >>> from pvcmf.study.predictions import judged_code_hash, prediction_code_hash
    >>> len(judged_code_hash()), judged_code_hash() != prediction_code_hash()
    (16, True)
    """
    from importlib import metadata

    root = Path(package) if package else _PACKAGE
    versions = {}
    for name in _JUDGED_LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    extra = [root / f for f in _JUDGED_EXTRA if (root / f).exists()]
    return make_key(prediction_code_hash(package), code_hash(*extra, root=root), versions,
                    length=16)


def _image_digest(image):
    """SHA-256 of an image's geometry and point arrays (None for no image)."""
    if image is None:
        return None
    h = hashlib.sha256(repr((tuple(image.dimensions), tuple(image.origin),
                             tuple(image.spacing))).encode())
    for name in sorted(image.point_data.keys()):
        value = np.ascontiguousarray(image.point_data[name])
        h.update(f"{name}|{value.dtype.str}|{value.shape}".encode())
        h.update(value.tobytes())
    return h.hexdigest()


def prediction_key(case, method, options, *, code=None):
    """Cache key (64 hex digits) of one prediction of ``case`` by ``method``.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        The patient (number, ``parameters``, ``spacing``, ``plan``, ``landmarks``, ``ct``,
        ``truth``).
    method : str
        The study's method.
    options : dict
        The prediction's options (MTM tetrahedra, Gaussian width, ...), JSON-serialisable.
    code : str, optional
        Code hash (default :func:`prediction_code_hash`).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> from pvcmf.study.predictions import prediction_key
    >>> case = SimpleNamespace(patient=101, parameters=None, spacing=3.0, plan="p",
    ...                        landmarks={}, ct=None, truth=None)
    >>> k = prediction_key(case, "proposed", {"n_tets": 5000}, code="c")
    >>> k == prediction_key(case, "proposed", {"n_tets": 6000}, code="c")
    False
    """
    landmarks = {k: np.asarray(v, dtype=float).round(9).tolist()
                 for k, v in sorted((getattr(case, "landmarks", None) or {}).items())}
    patient = {"patient": getattr(case, "patient", None),
               "parameters": repr(getattr(case, "parameters", None)),
               "spacing": getattr(case, "spacing", None),
               "plan": repr(getattr(case, "plan", None)), "landmarks": landmarks,
               "ct": _image_digest(getattr(case, "ct", None)),
               "labels": _image_digest(getattr(case, "truth", None))}
    return make_key({"patient": patient, "method": method, "options": options,
                     "code": prediction_code_hash() if code is None else code})


def _write(result, folder):
    y0, skin = result
    folder = Path(folder)
    skin.save(folder / "skin.vtp")
    meta = {"face_y0": float(y0), "n_points": int(skin.n_points),
            "arrays": sorted(skin.point_data.keys())}
    (folder / "meta.json").write_text(json.dumps(meta))


def _read(folder):
    """The entry, checked against its record: a truncated or foreign entry raises."""
    import pyvista as pv

    folder = Path(folder)
    meta = json.loads((folder / "meta.json").read_text())
    skin = pv.read(folder / "skin.vtp")
    if skin.n_points != meta["n_points"] or skin.n_points == 0:
        raise ValueError(f"skin has {skin.n_points} points, its record says {meta['n_points']}")
    if sorted(skin.point_data.keys()) != meta["arrays"]:
        raise ValueError(f"skin arrays {sorted(skin.point_data.keys())} differ from the record")
    if not np.isfinite(np.asarray(skin.points)).all():
        raise ValueError("skin has non-finite points")
    return float(meta["face_y0"]), skin


def cached_prediction(compute, case, method, options, *, cache=True, cache_dir=None,
                      n_points=None):
    """``compute() -> (face_y0, skin)``, read from the cache when the entry exists.

    Parameters
    ----------
    compute : callable
        Computes the prediction: the front of the face box (``face_y0``, mm) and the
        predicted skin.
    case, method, options :
        The key's parts (:func:`prediction_key`).
    cache : bool, default True
        False: just ``compute()``.
    cache_dir : path, optional
        Cache root (default ``PVCMF_CACHE_DIR`` / ``~/.cache/pvcmf``); entries go to its
        ``predictions`` folder.
    n_points : int, optional
        Points the skin must have (the pre-operative skin's); an entry of another size is
        recomputed.

    Returns
    -------
    tuple
        ``(face_y0, skin)``.
    """
    if not cache:
        return compute()
    key = prediction_key(case, method, options)
    root = cache_root("predictions") if cache_dir is None else Path(cache_dir) / "predictions"
    path = root / key

    def read(folder):
        out = _read(folder)
        if n_points is not None and out[1].n_points != n_points:
            raise ValueError(f"skin has {out[1].n_points} points, the pre-operative skin "
                             f"{n_points}")
        return out

    def checked():
        y0, skin = compute()
        if not np.isfinite(y0) or skin.n_points == 0:
            raise ValueError(f"prediction of {method!r} is empty or has no face box")
        return float(y0), skin

    y0, skin = cached(path, checked, read=read, write=_write, folder=True)
    if arrays.MAPPING_SUPPORT not in skin.point_data:
        raise ValueError(f"prediction of {method!r} has no {arrays.MAPPING_SUPPORT!r} array")
    return y0, skin


#: point arrays every judged skin carries (:func:`pvcmf.study.validation.study_predictor`)
_JUDGED_ARRAYS = (arrays.DISTANCE, arrays.REGION, arrays.SKIN_POINT_ID, arrays.MAPPING_SUPPORT)


def _read_judged(path):
    """A judged skin, checked: a truncated or foreign entry raises (and is recomputed)."""
    import pyvista as pv

    skin = pv.read(path)
    missing = [a for a in _JUDGED_ARRAYS if a not in skin.point_data]
    if skin.n_points == 0 or missing:
        raise ValueError(f"judged skin has {skin.n_points} points, lacks arrays {missing}")
    if arrays.STUDY_EXCLUDED not in skin.field_data.keys():
        raise ValueError(f"judged skin has no {arrays.STUDY_EXCLUDED!r} field")
    return skin


def cached_judged(compute, case, method, options, *, cache_dir=None):
    """``compute() -> judged skin``, read from the cache when the entry exists.

    The judged skin of one method (the prediction's distances to the registered
    post-operative CT's skin on the judged face) depends on the patient, the method,
    the prediction's and the truth's options and the code of both
    (:func:`judged_code_hash`): its key is :func:`prediction_key` of those, so a study
    run again reads it without building the truth's mesh, the post-operative CT, its
    segmentation and registration, or the distances.

    Parameters
    ----------
    compute : callable
        Computes the judged skin (``pyvista.PolyData``).
    case, method, options :
        The key's parts (:func:`prediction_key`); ``options`` must name everything the
        judging depends on besides the code (sizes, Gaussian width, truth, noise, ...).
    cache_dir : path, optional
        Cache root (default ``PVCMF_CACHE_DIR`` / ``~/.cache/pvcmf``); entries go to its
        ``judged`` folder.

    Returns
    -------
    pyvista.PolyData
        The judged skin.
    """
    key = prediction_key(case, method, options, code=judged_code_hash())
    root = cache_root("judged") if cache_dir is None else Path(cache_dir) / "judged"
    return cached(root / f"{key}.vtp", compute, read=_read_judged)
