"""Judge a predicted skin against a post-operative CT, as for a real scan.

The path of a real post-operative scan (paper 000 sec. V): segment
(:func:`pvcmf.filters.segment`) -> skin (:func:`pvcmf.filters.extract_skin`, refined
onto the CT's air/skin edge by :func:`refine_skin`) -> point-to-plane ICP on the
unchanged upper face (:func:`upper_face_region`, :func:`pvcmf.filters.register`) ->
signed distances (:func:`pvcmf.filters.distance_to`) -> statistics
(:func:`pvcmf.study.statistics.error_statistics`). Profiles are sampled with
:func:`scipy.ndimage.map_coordinates`.
"""

from __future__ import annotations

import logging

import numpy as np
import pyvista as pv

from .. import arrays, filters
from ..filters.registration import ICP_MATRIX, registration_result
from ..progress import Progress
from ..truth.postop import AIR_HU, _check_case, _sample
from .statistics import error_statistics, label_face_regions

log = logging.getLogger("pvcmf.postop")

__all__ = ["judge_skin", "refine_skin", "register_postop_skin", "skin_from_ct",
           "upper_face_region", "validate_from_ct"]


def upper_face_region(landmarks=None, *, below_nasion=15.0):
    """Region of the pre-operative skin that jaw surgery does not change, for ICP.

    The anterior skin above ``below_nasion`` mm under the soft-tissue nasion: forehead,
    orbits and nose bridge (paper 000 registers on the unchanged region). Without
    landmarks, the anterior skin above 62 % of the skin's height.

    Parameters
    ----------
    landmarks : dict, optional
        Patient landmarks (``soft_tissue_nasion`` or ``nasion``, mm).
    below_nasion : float, default 15.0
        How far below the nasion the region reaches (mm).

    Returns
    -------
    callable
        ``f(points) -> bool mask`` for :func:`pvcmf.filters.register`'s ``region``.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.study.from_ct import upper_face_region
    >>> f = upper_face_region({"nasion": (0.0, 80.0, 30.0)})
    >>> f(np.array([[0.0, 90.0, 40.0], [0.0, 90.0, -20.0]])).tolist()
    [True, False]
    """
    lm = dict(landmarks or {})
    nasion = lm.get("soft_tissue_nasion", lm.get("nasion"))

    def region(points):
        p = np.asarray(points, dtype=float)
        if nasion is not None:
            z0 = float(nasion[2]) - below_nasion
        else:
            z0 = p[:, 2].min() + 0.62 * np.ptp(p[:, 2])
        return (p[:, 2] >= z0) & (p[:, 1] >= np.median(p[:, 1]))

    return region


def refine_skin(skin, ct, *, level=-500.0, reach=1.5, step=0.125):
    """Move each skin point along its normal onto the CT's ``level`` iso-surface.

    A skin contoured from a label image sits on the voxel staircase (smoothed); the CT's
    air/skin edge locates it to a fraction of a voxel. Each point's CT profile along its
    normal, over ``[-reach, reach]`` voxels, is sampled trilinearly
    (:func:`scipy.ndimage.map_coordinates`, all points at once) and the point moves to the
    crossing of ``level`` (from inside above to outside below) nearest to it, by linear
    interpolation between samples; a point whose profile has no crossing stays put.

    Parameters
    ----------
    skin : pyvista.PolyData
        Skin with outward point normals (``'Normals'``, as :func:`pvcmf.filters.extract_skin`
        gives; computed otherwise).
    ct : pyvista.ImageData
        CT with point array ``arrays.CT`` (HU) the skin was extracted from.
    level : float, default -500.0
        HU of the air/skin edge (half way between air and soft tissue).
    reach : float, default 1.5
        Search distance along the normal, in voxels.
    step : float, default 0.125
        Sampling step along the normal, in voxels.

    Returns
    -------
    pyvista.PolyData
        Copy of ``skin`` with moved points (normals kept).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.study.from_ct import refine_skin
    >>> img = pv.ImageData(dimensions=(40, 40, 40), origin=(-20, -20, -20))
    >>> r = np.linalg.norm(img.points, axis=1)
    >>> img[arrays.CT] = np.clip((12.3 - r) * 500 - 500, -1000, 0).astype(np.float32)
    >>> out = refine_skin(pv.Sphere(radius=12.0), img)
    >>> bool(abs(np.linalg.norm(out.points, axis=1).mean() - 12.3) < 0.03)
    True
    """
    hu = np.asarray(arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1,
                                         producer="read_ct / postop_ct"), dtype=np.float64)
    out = skin.copy()
    if arrays.NORMALS in skin.point_data:
        normals = np.asarray(skin.point_data[arrays.NORMALS], dtype=float)
    else:
        normals = np.asarray(skin.compute_normals(cell_normals=False,
                                                  split_vertices=False)[arrays.NORMALS], float)
    normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    h = float(np.min(ct.spacing))
    t = np.arange(-reach, reach + step / 2, step) * h  # (m,) offsets along the normal, mm
    p = np.asarray(skin.points, dtype=float)
    samples = p[:, None, :] + t[None, :, None] * normals[:, None, :]
    prof = _sample(ct, hu, samples.reshape(-1, 3), 1, AIR_HU).reshape(len(p), len(t)) - level
    # crossings inside -> outside: prof[k] >= 0 > prof[k + 1]
    cross = (prof[:, :-1] >= 0) & (prof[:, 1:] < 0)
    mid = (t[:-1] + t[1:]) / 2
    cost = np.where(cross, np.abs(mid)[None, :], np.inf)
    k = np.argmin(cost, axis=1)
    has = np.isfinite(cost[np.arange(len(p)), k])
    a, b = prof[np.arange(len(p)), k], prof[np.arange(len(p)), k + 1]
    frac = np.where(has, a / np.where(a - b != 0, a - b, 1.0), 0.0)
    shift = np.where(has, t[k] + frac * step * h, 0.0)
    out.points = p + shift[:, None] * normals
    log.debug("refine_skin: %d of %d points moved, median |shift| %.3f mm", int(has.sum()),
              len(p), float(np.median(np.abs(shift[has]))) if has.any() else 0.0)
    return out


def skin_from_ct(ct, *, refine=True, segment_options=None, skin_options=None, name="ct"):
    """Skin surface of a CT as for a real scan: segment -> extract_skin -> refine.

    Parameters
    ----------
    ct : pyvista.ImageData
        CT with point array ``arrays.CT`` (HU).
    refine : bool, default True
        Move the points onto the CT's air/skin edge (:func:`refine_skin`).
    segment_options, skin_options : dict, optional
        Keyword arguments of :func:`pvcmf.filters.segment` and
        :func:`pvcmf.filters.extract_skin`.
    name : str, default 'ct'
        Name of the CT in error messages.

    Returns
    -------
    pyvista.PolyData
        Outward skin with point normals.

    Examples
    --------
    >>> import pvcmf
    >>> from pvcmf.study.from_ct import skin_from_ct
    >>> skin_from_ct(pvcmf.datasets.phantom(1, spacing=4.0).ct).n_points > 1000
    True
    """
    if not isinstance(ct, pv.ImageData):
        raise TypeError(f"{name} must be a pyvista.ImageData CT, got {type(ct).__name__}")
    arrays.require_array(ct, arrays.CT, "point", dtype="f", ncomp=1, producer="read_ct / postop_ct")
    labels = filters.segment(ct, **(segment_options or {}))
    skin = filters.extract_skin(labels, **(skin_options or {}))
    if skin.n_points == 0:
        raise ValueError(f"{name} has no skin: segmentation found no head (all air?)")
    return refine_skin(skin, ct) if refine else skin


def validate_from_ct(pre_case, postop_ct, predicted_skin, *, region=None, pre_skin=None,
                     landmarks=None, max_distance=10.0, segment_options=None,
                     skin_options=None, icp_options=None, regions=True, refine=True,
                     progress_bar=False):
    """Judge a predicted skin against a post-operative CT, as for a real scan.

    segment (:func:`pvcmf.filters.segment`) -> skin (:func:`pvcmf.filters.extract_skin`)
    of the post-operative CT -> rigid point-to-plane ICP of that skin onto the
    pre-operative skin on ``region`` (:func:`pvcmf.filters.register`) -> signed distance
    of the prediction to it (:func:`pvcmf.filters.distance_to`, + anterior) -> statistics
    (:func:`pvcmf.validation.error_statistics`, face regions from the landmarks).

    Parameters
    ----------
    pre_case : pvcmf.datasets.Case
        Pre-operative patient (``ct``, ``landmarks``): its CT gives the pre-operative skin
        (unless ``pre_skin`` is given), i.e. the frame of the prediction.
    postop_ct : pyvista.ImageData
        Post-operative CT with point array ``arrays.CT`` (e.g. :func:`postop_ct`), in any pose.
    predicted_skin : pyvista.DataSet
        Predicted post-operative skin in the pre-operative patient frame.
    region : None, mask, bounds or callable, optional
        ICP region on the pre-operative skin (see :func:`pvcmf.filters.register`);
        default :func:`upper_face_region` of the landmarks.
    pre_skin : pyvista.PolyData, optional
        Pre-operative skin (default: :func:`skin_from_ct` of ``pre_case.ct``).
    landmarks : dict, optional
        Default ``pre_case.landmarks``.
    max_distance : float, default 10.0
        Median |distance| (mm) above which the surfaces are said not to overlap (error).
    segment_options, skin_options, icp_options : dict, optional
        Keyword arguments of ``segment``, ``extract_skin`` and ``register``. ICP's
        ``tol`` defaults to 5 um here (on skins of 2-3 mm voxels the last updates cycle
        around the optimum by a few um) and ``closest`` to ``'auto'`` (closest points on
        the triangles at the end when libigl is installed: coarse skins).
    regions : bool, default True
        Per-region rows in the table.
    refine : bool, default True
        Put the skins on the CTs' air/skin edge (:func:`refine_skin`): sub-voxel skins,
        so that ICP and the distances are not limited by the voxel staircase.
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    tuple
        ``(surface, table)``: copy of ``predicted_skin`` with point arrays
        ``arrays.DISTANCE`` and ``arrays.REGION`` and the ICP result in its field data
        (:func:`pvcmf.filters.registration.registration_result` reads it: the matrix maps
        the post-operative CT's frame onto the pre-operative one), and the
        :class:`pandas.DataFrame` of :func:`pvcmf.validation.error_statistics`.

    Raises
    ------
    TypeError
        If a CT is not an ImageData or the prediction is not a dataset.
    ValueError
        If a skin is empty or the surfaces do not overlap.
    pvcmf.filters.registration.RegistrationError
        If ICP does not converge.

    Examples
    --------
    >>> import pvcmf                                                   # doctest: +SKIP
    >>> from pvcmf.study.from_ct import postop_ct, validate_from_ct           # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=3.0)                  # doctest: +SKIP
    >>> ct, pose = postop_ct(case, pose="random")                      # doctest: +SKIP
    >>> skin = case.ct.cmf.segment().cmf.skin()                # doctest: +SKIP
    >>> surface, table = validate_from_ct(case, ct, skin)              # doctest: +SKIP
    """
    _check_case(pre_case, "pre_case")
    if not isinstance(predicted_skin, pv.DataSet):
        raise TypeError(f"predicted_skin must be a pyvista dataset, got "
                        f"{type(predicted_skin).__name__}")
    if predicted_skin.n_points == 0:
        raise ValueError("predicted_skin must have points, got an empty dataset")
    with Progress(total=4, desc="validate_from_ct", enabled=progress_bar, logger=log) as bar:
        registered = register_postop_skin(
            pre_case, postop_ct, region=region, pre_skin=pre_skin, landmarks=landmarks,
            segment_options=segment_options, skin_options=skin_options,
            icp_options=icp_options, refine=refine)
        bar.step("skins, registered")
        landmarks = getattr(pre_case, "landmarks", None) if landmarks is None else landmarks
        out = judge_skin(predicted_skin, registered, landmarks=landmarks,
                         max_distance=max_distance)
        bar.step("distances")
        table = error_statistics(out, regions=regions)
        bar.step("statistics")
    return out, table


def register_postop_skin(pre_case, postop_ct, *, region=None, pre_skin=None, landmarks=None,
                         segment_options=None, skin_options=None, icp_options=None,
                         refine=True):
    """The post-operative CT's skin, registered onto the pre-operative skin (ICP).

    The first half of :func:`validate_from_ct` (same parameters): segment -> skin ->
    point-to-plane ICP on ``region``. It does not depend on the prediction, so several
    predictions of one patient are judged against one registration (:func:`judge_skin`).

    Returns
    -------
    pyvista.PolyData
        The registered post-operative skin (triangles), the ICP result in its field
        data.
    """
    _check_case(pre_case, "pre_case")
    opts = dict(refine=refine, segment_options=segment_options, skin_options=skin_options)
    post_skin = skin_from_ct(postop_ct, name="postop_ct", **opts)
    if pre_skin is None:
        pre_skin = skin_from_ct(pre_case.ct, name="pre_case.ct", **opts)
    landmarks = getattr(pre_case, "landmarks", None) if landmarks is None else landmarks
    if region is None:
        region = upper_face_region(landmarks)
    icp = {"tol": 5e-3, "closest": "auto", **(icp_options or {})}
    registered = filters.register(post_skin, pre_skin, region=region, **icp)
    matrix, rms, converged = registration_result(registered)
    log.info("validate_from_ct: ICP RMS %.3f mm, converged %s", rms, converged)
    target = pv.PolyData(registered.points, faces=registered.faces)
    for key in registered.field_data.keys():
        target.field_data[key] = registered.field_data[key]
    if ICP_MATRIX not in target.field_data.keys():
        raise RuntimeError("register() returned no ICP matrix")
    return target


def judge_skin(predicted_skin, registered, *, landmarks=None, max_distance=10.0):
    """Signed distances of a prediction to a registered post-operative skin, face regions.

    The second half of :func:`validate_from_ct`: ``registered`` comes from
    :func:`register_postop_skin`, ``landmarks`` (the pre-operative patient's) label the
    face regions; returns the copy of ``predicted_skin`` with point arrays
    ``arrays.DISTANCE`` and ``arrays.REGION`` and the ICP result in its field data.
    """
    if not isinstance(predicted_skin, pv.DataSet):
        raise TypeError(f"predicted_skin must be a pyvista dataset, got "
                        f"{type(predicted_skin).__name__}")
    if predicted_skin.n_points == 0:
        raise ValueError("predicted_skin must have points, got an empty dataset")
    out = filters.distance_to(predicted_skin, registered, max_distance=max_distance)
    out = label_face_regions(out, landmarks=landmarks)
    for key in registered.field_data.keys():
        out.field_data[key] = registered.field_data[key]
    return out
