"""``pvcmf validate``: judge a predicted skin against a post-operative skin or CT.

The path of paper 000 (sec. V) for one case, from files:

1. the post-operative skin: a surface file (VTP, STL, PLY, OBJ, VTK), or a CT (file,
   DICOM folder or ImageData) through :func:`pvcmf.study.from_ct.skin_from_ct`;
2. rigid point-to-plane ICP of that skin onto the pre-operative skin (or, without one,
   the predicted skin, which surgery on the jaws leaves unchanged there) on the region
   surgery does not change (:func:`pvcmf.study.from_ct.upper_face_region`: forehead,
   orbits, nose bridge; or a box) with :func:`pvcmf.filters.register`;
3. exact signed distances of the prediction to it (:func:`pvcmf.filters.distance_to`,
   + anterior), face regions (:func:`pvcmf.study.statistics.label_face_regions`) and
   their statistics (:func:`pvcmf.study.statistics.error_statistics`);
4. ``regions.csv`` and ``summary.json`` (:func:`write_validation`); the command adds
   paper 000 Figs. 6-8 for this case and ``report.html`` (:mod:`pvcmf.report`).

The options of step 2 are those of :func:`pvcmf.study.from_ct.validate_from_ct`, so a
prediction judged here against the study's post-operative CT, with the study's
pre-operative skin and landmarks, gets the study's numbers.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyvista as pv

from .. import arrays, filters
from .._atomic import atomic_path, write_text
from ..figures.skin_marks import judged_points
from ..filters.registration import ICP_ITERATIONS, registration_result
from ..io import read_ct, read_surface
from ..io.surfaces import SURFACE_FORMATS
from ..progress import Progress
from .from_ct import skin_from_ct, upper_face_region
from .statistics import error_statistics, label_face_regions

log = logging.getLogger("pvcmf.validate")

__all__ = ["Validation", "load_post", "validate", "write_validation"]

@dataclass
class Validation:
    """What :func:`validate` produced."""

    skin: pv.PolyData  #: prediction with ``distance`` and ``region``
    postop: pv.PolyData  #: registered post-operative skin
    table: object  #: pandas.DataFrame of error_statistics
    registration: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)
    pre: pv.PolyData | None = None


def _as_surface(data, name):
    if isinstance(data, (str, Path)):
        data = read_surface(data)
    if not isinstance(data, pv.DataSet) or data.n_points == 0:
        raise ValueError(f"{name} must be a non-empty surface, got {type(data).__name__}")
    return data if isinstance(data, pv.PolyData) else data.extract_surface(
        algorithm="dataset_surface")


def load_post(post, *, progress_bar=False):
    """The post-operative skin of a surface file/dataset, or of a CT (file, folder, image).

    A folder, an ImageData or a CT file (``.nii``, ``.nii.gz``, ``.nrrd``, ``.mha``,
    ``.mhd``, ``.vti``) is segmented into a skin (:func:`skin_from_ct`); a surface file is
    read (:func:`pvcmf.io.read_surface`). Returns ``(skin, kind)``, kind ``'ct'`` or
    ``'surface'``.
    """
    if isinstance(post, pv.ImageData):
        return skin_from_ct(post, name="post"), "ct"
    if isinstance(post, (str, Path)):
        path = Path(post)
        if not path.exists():
            raise FileNotFoundError(f"post: no such file or folder: {path}")
        if path.is_dir() or path.suffix.lower() not in SURFACE_FORMATS or \
                path.suffix.lower() == ".vti":
            return skin_from_ct(read_ct(path), name=str(path)), "ct"
    return _as_surface(post, "post"), "surface"


def _region(region, landmarks):
    if region is None or (isinstance(region, str) and region in ("upper", "upper_face")):
        return upper_face_region(landmarks)
    if isinstance(region, str):
        try:
            region = [float(v) for v in region.split(",")]
        except ValueError:
            raise ValueError(f"region must be 'upper' or six numbers xmin,xmax,ymin,ymax,"
                             f"zmin,zmax (mm), got {region!r}") from None
    if not callable(region) and np.asarray(region).shape != (6,) and \
            np.asarray(region).dtype != bool:
        raise ValueError(f"region must be 'upper', a callable, a mask or six bounds, "
                         f"got {region!r}")
    return region


def _judged_only(skin, pred):
    """``skin`` with the distances the statistics do not judge set to NaN
    (:func:`pvcmf.figures.skin_marks.judged_points` of ``pred``).

    A whole-head prediction carries ``arrays.SKIN_MODELLED``: the back of the head and the
    neck keep zero displacement because the model does not reach them, so their distances
    say nothing about the model and would dilute the statistics. Skin on a cut of the
    pre-operative scan (``arrays.SKIN_CUT``) is the scan's edge, not the patient's skin:
    its distance to the post-operative skin says nothing about the model either.
    """
    judged_mask = judged_points(pred)
    if judged_mask.all() or not judged_mask.any():
        return skin
    judged = skin.copy()
    d = np.array(skin.point_data[arrays.DISTANCE], dtype=float)
    d[~judged_mask] = np.nan
    judged.point_data[arrays.DISTANCE] = d
    return judged


def validate(pred, post, *, pre=None, region=None, landmarks=None, max_distance=10.0,
             icp_options=None, progress_bar=False):
    """Judge a predicted skin against a post-operative skin or CT (paper 000, sec. V).

    Parameters
    ----------
    pred : pyvista.PolyData or path
        Predicted skin in the pre-operative patient frame (``predicted_skin.vtp``).
    post : pyvista.DataSet, ImageData or path
        Post-operative skin (surface) or CT (image, file or DICOM folder), in any pose.
    pre : pyvista.PolyData or path, optional
        Pre-operative skin, the ICP target (default: ``pred``).
    region : None, 'upper', six bounds, mask or callable, optional
        ICP region on the target (:func:`pvcmf.filters.register`); default
        :func:`upper_face_region` of ``landmarks``.
    landmarks : dict, optional
        Patient landmarks (mm): nasion for the region, nose/lip/chin for the face regions.
    max_distance : float, default 10.0
        Median |distance| (mm) above which the surfaces are said not to overlap (error).
    icp_options : dict, optional
        Keyword arguments of ``register`` (default ``tol=5e-3, closest='auto'``, as
        :func:`pvcmf.study.from_ct.validate_from_ct`).
    progress_bar : bool, default False
        Show the steps.

    Returns
    -------
    Validation
        The judged prediction (``distance``, ``region``), the registered post-operative
        skin, the statistics table, the ICP result and seconds per step.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.study.validate import validate
    >>> head = pv.ParametricEllipsoid(70, 95, 110, u_res=60, v_res=40).clean()
    >>> post = head.translate((0.0, 0.0, 2.0))   # a scan 2 mm higher: ICP undoes it
    >>> v = validate(head, post, region=[-100, 100, -200, 200, 30, 200])
    >>> bool(v.table.loc[0, "p95"] < 0.05)
    True
    """
    timings = {}
    start = time.perf_counter()
    with Progress(total=3, desc="validate", enabled=progress_bar, logger=log) as bar:
        pred = _as_surface(pred, "pred")
        post_skin, kind = load_post(post)
        target = pred if pre is None else _as_surface(pre, "pre")
        timings["read" if kind == "surface" else "read + skin of the CT"] = \
            time.perf_counter() - start
        bar.step("read")
        t = time.perf_counter()
        icp = {"tol": 5e-3, "closest": "auto", **(icp_options or {})}
        registered = filters.register(post_skin, target, region=_region(region, landmarks),
                                      **icp)
        matrix, rms, converged = registration_result(registered)
        timings["registration"] = time.perf_counter() - t
        bar.step("registered")
        t = time.perf_counter()
        postop = pv.PolyData(registered.points, faces=registered.faces)
        skin = filters.distance_to(pred, postop, max_distance=max_distance)
        skin = label_face_regions(skin, landmarks=landmarks)
        table = error_statistics(_judged_only(skin, pred), regions=True)
        timings["distances"] = time.perf_counter() - t
        bar.step("distances")
    reg = {"rms_mm": float(rms), "converged": bool(converged),
           "iterations": int(np.asarray(registered.field_data[ICP_ITERATIONS]).ravel()[0])
           if ICP_ITERATIONS in registered.field_data else None,
           "matrix": np.asarray(matrix).round(6).tolist(), "post": kind}
    log.info("validate: ICP RMS %.3f mm; p90 %.2f mm", rms, table.loc[0, "p90"])
    return Validation(skin=skin, postop=postop, table=table, registration=reg,
                      timings=timings, pre=None if pre is None else target)


def write_validation(validation, out, *, inputs=None, extra_files=None):
    """Write a :class:`Validation` into ``out``; returns name -> path.

    Files: ``validated_skin.vtp`` (prediction with ``distance`` and ``region``),
    ``postop_skin.vtp`` (registered), ``skin_pre.vtp`` (when a pre-operative skin was
    given), ``regions.csv`` and ``summary.json`` (inputs, registration, region rows,
    seconds, and the names of ``extra_files``). ``pvcmf validate`` adds Figs. 6-8
    (:func:`pvcmf.report.validation_figures`) and ``report.html``
    (:func:`pvcmf.report.write_report`). Each file is written atomically.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    v, files = validation, validation.files
    t = time.perf_counter()
    for name, data in (("validated_skin", v.skin), ("postop_skin", v.postop),
                       ("skin_pre", v.pre)):
        if data is not None:
            with atomic_path(out / f"{name}.vtp") as tmp:
                data.save(tmp)
            files[name] = out / f"{name}.vtp"
    files["regions"] = write_text(out / "regions.csv", v.table.to_csv(index=False))
    files.update(extra_files or {})
    v.timings["write"] = time.perf_counter() - t
    rows = json.loads(v.table.to_json(orient="records"))
    summary = {"inputs": {k: str(val) for k, val in (inputs or {}).items()},
               "registration": v.registration, "regions": rows, "seconds": v.timings,
               "files": {k: Path(p).name for k, p in files.items()}}
    files["summary"] = write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return files
