"""The first steps of :func:`pvcmf.pipeline.simulate`, from the file to the CT it labels.

"read" (:func:`pvcmf.io.read_ct`), "working grid" (a very fine scan averaged over blocks of
whole voxels, :func:`pvcmf.filters.working_grid`), the units and axes check
(:func:`pvcmf.filters.standardize`) and "shading" (a cone-beam scan's slow shading
divided out, :func:`pvcmf.filters.flatten_shading`). Each takes the pipeline's step runner
(``run``: times the step or records why it was skipped) and records what it found in the
run's :class:`~pvcmf.pipeline.Result`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import pyvista as pv

from . import arrays, filters
from .filters.resolution import BYTES_PER_VOXEL, describe_grid, working_factors
from .io import read_ct
from .io.orientation import standardize

log = logging.getLogger(__name__)

__all__ = ["SHADING", "check_shading", "read_step", "shading_step", "working_grid_step"]

#: what ``simulate(shading=...)`` takes: ``'auto'`` flattens a scan whose grey values were
#: rescaled to HU (a cone-beam scan's), ``'n4'`` any scan, ``'none'`` none
SHADING = ("auto", "n4", "none")


def check_shading(shading):
    """``shading`` if it is one of :data:`SHADING`, else a ValueError naming them."""
    if not isinstance(shading, str) or shading.lower() not in SHADING:
        raise ValueError(f"shading must be one of {SHADING}, got {shading!r}")
    return shading.lower()


def read_step(run, ct, units, orient, working_spacing, labels_given, shading="auto"):
    """Step "read": the CT from a file or folder (:func:`pvcmf.io.read_ct`); step "working
    grid" (:func:`working_grid_step`); then its units and axes checked on the image
    (:func:`pvcmf.filters.standardize`): always for a CT read from a path or given as
    read_ct returned it, for another CT in memory when ``units`` or ``orient`` is given;
    then step "shading" (:func:`shading_step`)."""
    if isinstance(ct, (str, Path)):
        ct = run.run("read", read_ct, ct)
        units, orient = units or "auto", orient or "auto"
    else:
        run.skip("read", "CT given in memory")
        if isinstance(ct, pv.ImageData) and arrays.SOURCE_PATH in ct.field_data:
            units, orient = units or "auto", orient or "auto"  # unchecked: as from a path
    ct = working_grid_step(run, ct, working_spacing, labels_given)
    if units is not None or orient is not None:
        ct, run.result.ct_report = standardize(ct, units=units or "auto",
                                               orient=orient or "auto")
    return shading_step(run, ct, shading, labels_given)


def working_grid_step(run, ct, working_spacing, labels_given):
    """Step "working grid": a scan finer than ``working_spacing`` asks averaged over blocks
    of whole voxels (:func:`pvcmf.filters.working_grid`), recorded in
    :attr:`Result.working_grid`; warned about where ``'auto'`` chose it."""
    if labels_given or working_spacing is None:
        run.skip("working grid", "labels given" if labels_given else "working_spacing=None")
        return ct
    if not isinstance(ct, pv.ImageData):  # (refused by the segmentation)
        run.skip("working grid", "no CT image")
        return ct
    factors = working_factors(ct.dimensions, ct.spacing, working_spacing)
    if factors == (1, 1, 1):
        run.skip("working grid", "the scan's own grid")
        return ct
    work = run.run("working grid", filters.working_grid, ct, working_spacing)
    run.result.working_grid, text = describe_grid(ct, work)
    (log.warning if working_spacing == "auto" else log.info)(
        "simulate: %s (working_spacing=%r; None, or --working-spacing none, keeps the scan's "
        "grid at about %.0f GB)", text, working_spacing, BYTES_PER_VOXEL * ct.n_points / 1e9)
    return work


def shading_step(run, ct, shading, labels_given=False):
    """Step "shading": :func:`pvcmf.filters.flatten_shading` for a scan whose grey values
    were rescaled to HU (``shading='auto'``: a cone-beam scanner's, whose reconstruction
    shades the field) or for any scan (``'n4'``); the field's spread goes to the run's
    ``ct_report["shading"]`` (``summary.json``)."""
    shading = check_shading(shading)
    units = (run.result.ct_report or {}).get("units", {}).get("units")
    why = ("labels given" if labels_given else "shading='none'" if shading == "none"
           else "no CT image" if not isinstance(ct, pv.ImageData)
           else "a CT scanner's HU (grey values not rescaled)"
           if shading == "auto" and units != "rescaled" else None)
    if why is not None:
        run.skip("shading", why)
        return ct
    out = run.run("shading", filters.flatten_shading, ct)
    low, high = (float(v) for v in out.field_data[arrays.SHADING])
    run.result.ct_report = dict(run.result.ct_report or {})
    run.result.ct_report["shading"] = {
        "method": "N4", "field_p5": round(low, 4), "field_p95": round(high, 4),
        "how": (f"a smooth field from {low:.3f} to {high:.3f} (5th to 95th percentile over "
                f"the tissue) divided out of the attenuation")}
    log.info("simulate: shading %s", run.result.ct_report["shading"]["how"])
    return out
