"""A seeded cohort of virtual patients, varied in face, soft tissue, skeletal class and plan.

The four virtual patients of :func:`pvcmf.datasets.phantom` (paper 000's Table II) are too
few for a paired test over patients (a two-sided Wilcoxon signed-rank p-value needs at
least 6 pairs to fall below 0.05). :func:`cohort_parameters` draws any number of patients
from one seed:

* face shape: the warp's affine scale (0.93-1.07 per axis) and the amplitude (1-2.5 mm)
  and seed of its smooth non-linear part;
* soft-tissue thickness: factor 0.8-1.2 on the layer outside the bony envelope;
* skeletal class: in turn maxillary protrusion / retrusion and mandibular retrusion /
  protrusion (classes II and III), 3-6 mm;
* plan: the osteotomy that corrects the jaw displacement (its anterior translation),
  with a vertical move of up to 1.5 mm and up to 2 degrees of pitch about the segment's
  centroid.

:func:`virtual_patient` builds one patient as :func:`pvcmf.datasets.phantom` builds patients
1-4 (the same rasterizer and CT synthesis), numbered from 101, optionally read from and
written to the on-disk cache (:mod:`pvcmf.cache`). Delegates to :mod:`pvcmf.datasets` and
numpy.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from ..cache import cache_root, cached, make_key
from ..datasets import phantom as _phantom
from ..datasets import template
from ..plan import Osteotomy, Plan
from .predictions import _image_digest, judged_code_hash

log = logging.getLogger("pvcmf.validation")

__all__ = ["cohort", "cohort_parameters", "virtual_patient"]

#: skeletal classes drawn in turn: (segment, sign of the jaw's anterior displacement)
CLASSES = (("maxilla", 1.0), ("maxilla", -1.0), ("mandible", -1.0), ("mandible", 1.0))


def cohort_parameters(n=16, seed=0):
    """Parameters and plans of ``n`` virtual patients drawn from ``seed``.

    Parameters
    ----------
    n : int, default 16
        Number of patients.
    seed : int, default 0
        Seed of the draw.

    Returns
    -------
    list of (pvcmf.datasets.template.PatientParameters, pvcmf.plan.Plan)
        One pair per patient; each plan corrects its patient's jaw displacement.

    Examples
    --------
    >>> from pvcmf.study.cohort import cohort_parameters
    >>> draw = cohort_parameters(8, seed=1)
    >>> len(draw), draw[0] == cohort_parameters(8, seed=1)[0]
    (8, True)
    >>> p, plan = draw[0]
    >>> round(-plan.osteotomies[0].translation[2], 6) == round(p.maxilla + p.mandible, 6)
    True
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    rng = np.random.default_rng(seed)
    out = []
    for i in range(int(n)):  # a handful of patients, a few random numbers each
        segment, sign = CLASSES[i % len(CLASSES)]
        shift = sign * float(rng.uniform(3.0, 6.0))
        params = template.PatientParameters(
            scale=tuple(float(v) for v in rng.uniform(0.93, 1.07, 3).round(4)),
            thickness=round(float(rng.uniform(0.8, 1.2)), 4),
            maxilla=shift if segment == "maxilla" else 0.0,
            mandible=shift if segment == "mandible" else 0.0,
            wave=round(float(rng.uniform(1.0, 2.5)), 3), seed=int(rng.integers(2000, 10**6)))
        plan = Plan((Osteotomy(segment, (0.0, float(rng.uniform(-1.5, 1.5)), -shift),
                               (float(rng.uniform(-2.0, 2.0)), 0.0, 0.0)),),
                    name=f"cohort patient {101 + i}")
        out.append((params, plan))
    return out


def virtual_patient(params, plan, *, spacing=2.0, number=101, cache=False, cache_dir=None):
    """One virtual patient of the given parameters and plan (see :func:`cohort_parameters`).

    Parameters
    ----------
    params : pvcmf.datasets.template.PatientParameters
        Face shape, soft-tissue thickness and jaw displacement.
    plan : pvcmf.plan.Plan
        The patient's plan.
    spacing : float, default 2.0
        Voxel size (mm).
    number : int, default 101
        The patient's number (``Case.patient``).
    cache : bool, default False
        Read / write the patient in the on-disk cache (``cache_dir``'s ``cases`` folder:
        its CT, label image and landmarks), keyed by ``params``, ``plan``, ``spacing``,
        ``number`` and the code that builds it
        (:func:`pvcmf.study.predictions.judged_code_hash`).
    cache_dir : path, optional
        Cache root (default ``PVCMF_CACHE_DIR`` / ``~/.cache/pvcmf``).

    Returns
    -------
    pvcmf.datasets.Case
        As :func:`pvcmf.datasets.phantom` returns, with ``parameters`` set (the true
        anatomy of :mod:`pvcmf.truth.anatomy` follows them).
    """
    spacing = _phantom._check_spacing(spacing)
    if not cache:
        return _build(params, plan, spacing, number)
    key = make_key({"parameters": repr(params), "plan": repr(plan), "spacing": spacing,
                    "number": int(number), "code": judged_code_hash()})
    root = cache_root("cases") if cache_dir is None else Path(cache_dir) / "cases"
    t0 = time.perf_counter()
    case = cached(root / key, lambda: _build(params, plan, spacing, number), folder=True,
                  read=lambda folder: _read_case(folder, params, plan), write=_write_case)
    if not getattr(case, "build_seconds", 0.0):
        case.build_seconds = time.perf_counter() - t0
    return case


def _write_case(case, folder):
    folder = Path(folder)
    case.ct.save(folder / "ct.vti")
    case.truth.save(folder / "truth.vti")
    meta = {"name": case.name, "patient": int(case.patient), "spacing": float(case.spacing),
            "landmarks": {k: np.asarray(v, float).tolist() for k, v in case.landmarks.items()},
            "ct": _image_digest(case.ct), "truth": _image_digest(case.truth)}
    (folder / "meta.json").write_text(json.dumps(meta))


def _read_case(folder, params, plan):
    """A cached patient, checked against its record (image digests): a truncated or
    foreign entry raises and is rebuilt."""
    import pyvista as pv

    folder = Path(folder)
    meta = json.loads((folder / "meta.json").read_text())
    ct, truth = pv.read(folder / "ct.vti"), pv.read(folder / "truth.vti")
    if _image_digest(ct) != meta["ct"] or _image_digest(truth) != meta["truth"]:
        raise ValueError(f"cached patient {folder} does not match its record")
    landmarks = {k: np.asarray(v, float) for k, v in meta["landmarks"].items()}
    return _phantom.Case(name=meta["name"], patient=meta["patient"], spacing=meta["spacing"],
                         ct=ct, truth=truth, landmarks=landmarks, plan=plan, parameters=params)


def _build(params, plan, spacing, number):
    t0 = time.perf_counter()
    warp = template.PatientWarp(params)
    grid = _phantom._grid_for(warp, spacing)
    labels = _phantom.rasterize(grid, warp)
    hu = _phantom._synthesize_ct(labels, grid, params.seed)
    ct = _phantom._image(grid, {_phantom.arrays.CT: hu})
    keys = (_phantom.arrays.TISSUE, _phantom.arrays.MUSCLE, _phantom.arrays.BONE)
    truth = _phantom._image(grid, {k: labels[k] for k in keys})
    case = _phantom.Case(name=f"cohort patient {number}", patient=int(number),
                         spacing=spacing, ct=ct, truth=truth,
                         landmarks=_phantom._patient_landmarks(warp), plan=plan,
                         parameters=params)
    case.build_seconds = time.perf_counter() - t0
    log.info("cohort patient %d built in %.1f s", number, case.build_seconds)
    return case


def cohort(n=16, seed=0, *, spacing=2.0):
    """The cohort's patients, built one at a time (a generator: each takes seconds).

    Examples
    --------
    >>> from pvcmf.study.cohort import cohort
    >>> case = next(cohort(2, seed=0, spacing=4.0))
    >>> case.patient, case.plan.name
    (101, 'cohort patient 101')
    """
    for i, (params, plan) in enumerate(cohort_parameters(n, seed)):
        yield virtual_patient(params, plan, spacing=spacing, number=101 + i)
