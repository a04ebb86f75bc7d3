"""End-to-end prediction: CT + surgical plan -> predicted post-operative face.

:func:`simulate` chains the pipeline steps of :mod:`pvcmf.filters` and :mod:`pvcmf.mtm`
(a working grid for very fine scans, segmentation, fat/muscle classification, muscles,
meshing, materials, plan -> boundary conditions, MTM solve, skin), times every step, and,
given an output folder, writes the predicted skin (VTP), the deformed mesh (VTU) and
offscreen PNGs, each atomically (temporary file in the same folder + ``os.replace``: an
interrupted run leaves no half-written file).

Each stage (:data:`STEPS`) is a named function calling the filter of that name in
:mod:`pvcmf.filters`; steps the caller turns off (muscles, prediction) or that decline on
purpose (a failed muscle fit leaves homogeneous tissue) are recorded in
:attr:`Result.skipped`; any other failure raises. Progress goes through
:class:`pvcmf.progress.Progress`; outputs are written by :mod:`pvcmf.outputs`.
"""

from __future__ import annotations

import json
import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyvista as pv

from . import arrays, filters, mtm
from ._atomic import write_text
from .filters.bone_segments import segment_volumes, transfer_segments
from .filters.face_axes import check_plan_landmarks, with_plan_axes
from .filters.jaw_pose import check_pose
from .filters.symmetry import check_turn
from .filters.meshing.skin_fit import on_hard_tissue
from .filters.osteotomy import cut_bones, move_bones
from .filters.resolution import working_factors
from .filters.segment_coverage import check_coverage
from .filters.segmentation import tissue_volumes
from .filters.skin import NECK_BELOW_BOX, head_skin  # noqa: F401 (public here too)
from .filters.skin_prediction import (FAR_REDUCTION, TRANSFER_REACH,  # noqa: F401 (public)
                                      SKIN_SUMMARY, near_box, predict_skin)
from .filters.surface_mapping import mesh_band
from .io.ct import flip_axes  # noqa: F401 (public here too)
from .outputs import check_output_dir, render, run_lock, write_outputs, write_run
from .filters.model_region import drop_floating_parts, face_box  # noqa: F401 (public here too)
from .plan import Plan, read_plan
from .progress import Progress
from .run_warnings import capture_warnings
from .scan_steps import check_shading, read_step

log = logging.getLogger(__name__)

__all__ = ["Result", "simulate", "head_skin", "STEPS", "write_outputs"]

#: the steps of :func:`simulate`, in order, as named in the timing summary
STEPS = ("read", "working grid", "shading", "segment", "classify", "bone segments", "muscles", "mesh",
         "skin fit", "fibres", "materials", "boundary conditions", "solve", "skin", "skeleton", "figures", "write")

#: default number of tetrahedra: coarse enough for a < 2 min demo on 2 cores
DEFAULT_N_TETS = 25_000
#: boundary-condition options (:func:`pvcmf.filters.apply_plan`; fixed nodes near a moving one free)
DEFAULT_BC_OPTIONS = {"fix_unmoved_bone": True, "release_margin": "auto"}
#: default anterior share of the head that is meshed (the face model of paper 000)
DEFAULT_FACE_FRACTION = 0.5

class StepUnavailable(RuntimeError):
    """A step declined and the pipeline goes on without it (recorded in ``Result.skipped``).

    Raised on purpose only, e.g. when the muscle fit fails and the soft tissue stays
    homogeneous; a bug or a missing dependency in a step is raised, not skipped.
    """


@dataclass
class Result:
    """What :func:`simulate` produced, with the time spent per step.

    Attributes
    ----------
    labels : pyvista.ImageData
        Tissue / muscle / bone labels (``bone`` holds the planned segments).
    mesh : pyvista.UnstructuredGrid or None
        Pre-operative tetrahedral mesh with materials and ``bc`` arrays.
    post : pyvista.UnstructuredGrid or None
        ``mesh`` with the point array ``displacement`` (rest positions, not warped).
    skin_pre, skin_post : pyvista.PolyData or None
        Pre-operative and predicted skin (``skin_post`` carries ``displacement``).
    skeleton : pyvista.MultiBlock or None
        Post-operative bone segment surfaces (:func:`pvcmf.filters.move_bones`).
    timings : dict
        Step name -> seconds.
    tissue_volumes : dict
        Tissue name -> volume (mL) of the final labels
        (:func:`pvcmf.filters.segmentation.tissue_volumes`).
    segment_volumes : dict
        Bone segment name -> volume (mL) (:func:`pvcmf.filters.bone_segments.segment_volumes`).
    ct_report : dict
        Units and orientation found in the CT (:func:`pvcmf.filters.standardize`); empty
        when the CT was not checked.
    working_grid : dict
        The blocks of scan voxels averaged into the voxels segmented
        (:func:`pvcmf.filters.working_grid`): ``factors``, ``scan_spacing_mm``,
        ``spacing_mm``, ``scan_voxels``, ``voxels``; empty on the scan's own grid.
    skipped : dict
        Step name -> why it did not run.
    skin_fit : dict
        ``arrays.SKIN_FIT_FIELDS`` -> value: what :func:`pvcmf.filters.meshing.fit_to_skin`
        did to the mesh; empty when it was not fitted.
    warnings : list of str
        What the run warned about (:func:`pvcmf.run_warnings.capture_warnings`), in order.
    files : dict
        Output name -> written path.
    """

    plan: Plan
    labels: pv.ImageData | None = None
    mesh: pv.UnstructuredGrid | None = None
    post: pv.UnstructuredGrid | None = None
    skin_pre: pv.PolyData | None = None
    skin_post: pv.PolyData | None = None
    skeleton: pv.MultiBlock | None = None
    timings: dict = field(default_factory=dict)
    tissue_volumes: dict = field(default_factory=dict)
    segment_volumes: dict = field(default_factory=dict)
    ct_report: dict = field(default_factory=dict)
    working_grid: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    skin_fit: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    files: dict = field(default_factory=dict)

    @property
    def complete(self):
        """True when the prediction ran (mesh, boundary conditions and solve)."""
        return self.post is not None

    def summary(self):
        """A small text table of seconds per step (and the skipped steps)."""
        width = max(len(s) for s in STEPS)
        lines = [f"{'step':<{width}}  seconds"]
        for step in STEPS:
            if step in self.timings:
                lines.append(f"{step:<{width}}  {self.timings[step]:7.2f}")
            elif step in self.skipped:
                lines.append(f"{step:<{width}}  skipped: {self.skipped[step]}")
        lines.append(f"{'total':<{width}}  {sum(self.timings.values()):7.2f}")
        if self.post is not None:
            u = np.linalg.norm(np.asarray(self.post[arrays.DISPLACEMENT]), axis=1)
            lines.append(f"max displacement {u.max():.2f} mm, mesh {self.post.n_cells} tetrahedra, "
                         f"{self.post.n_points} points")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


# --------------------------------------------------------------------------- step runner
class _Runner:
    """Runs the named steps of :func:`simulate`: times them, records skips, shows progress."""

    def __init__(self, result, progress):
        self.result, self.progress = result, progress

    def run(self, step, func, *args, **kwargs):
        """Run ``func`` as ``step``; a step that declines (:class:`StepUnavailable`, e.g. a
        failed muscle fit falling back to homogeneous tissue) is recorded as skipped."""
        start = time.perf_counter()
        try:
            value = func(*args, **kwargs)
        except StepUnavailable as err:
            self.result.skipped[step] = str(err)
            log.warning("step %r skipped: %s", step, err)
            value = None
        else:
            self.result.timings[step] = time.perf_counter() - start
            log.info("step %r took %.2f s", step, self.result.timings[step])
        self.progress.step(step)
        return value

    def skip(self, step, why):
        self.result.skipped[step] = why
        log.info("step %r skipped: %s", step, why)
        self.progress.step(f"{step} (skipped)")


# --------------------------------------------------------------------------- steps
def _segment(ct, options):
    return filters.segment(ct, **options)


def _classify(labels):
    """Step "classify": fat / muscle by per-slice Gaussian mixtures (paper 001); the muscle
    tissue the atlas does not name (tongue, temporalis, neck) comes from here."""
    out = filters.classify_tissue(labels)
    if arrays.MUSCLE not in out.point_data.keys():  # generic muscle: no atlas id
        out.point_data[arrays.MUSCLE] = np.full(out.n_points, arrays.MUSCLE_NONE, np.uint8)
    return out


def _muscles(labels, landmarks):
    """Embed the muscles; a failing fit falls back to homogeneous tissue with a warning."""
    embed = filters.embed_muscles
    try:
        return embed(labels, landmarks=landmarks) if landmarks is not None else embed(labels)
    except (ValueError, RuntimeError) as err:
        raise StepUnavailable(f"embed_muscles failed, soft tissue left homogeneous: "
                              f"{type(err).__name__}: {str(err)[:300]}") from None


def _model_box(labels, options, face_fraction):
    """The model's box: a box ``roi`` of the mesh options, else :func:`face_box`; None for
    the whole head or another kind of ``roi``."""
    roi = options.get("roi")
    if roi is None:
        return None if face_fraction is None else face_box(labels, face_fraction)
    arr = None if callable(roi) else np.asarray(roi)
    ok = arr is not None and arr.shape == (6,) and arr.dtype.kind in "iuf"
    return tuple(float(v) for v in arr) if ok else None


def _mesh(labels, n_tets, options, progress_bar, box):
    options = dict(options) if box is None else {"roi": box, **options}
    handler = signal.getsignal(signal.SIGTERM)
    try:
        return filters.tetrahedralize(labels, n_tets=n_tets, progress_bar=progress_bar, **options)
    finally:  # gmsh's initialisation resets SIGTERM to the default: restore the caller's
        if handler is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, handler)


def _fit_skin(grid, labels, box, options):
    """Step "skin fit": the mesh fitted to the dense skin within the transfer's reach of the
    box (not to bare bone); returns the fitted mesh and the head's skin (:func:`head_skin`)."""
    skin = head_skin(labels, box)
    near = near_box(skin.points, box, 2 * mesh_band(grid))  # all the transfer reaches
    cloud = skin.extract_points(near & ~on_hard_tissue(skin.points, labels), adjacent_cells=False)
    return filters.fit_to_skin(grid, cloud, labels=labels, box=box, **options), skin


def _fibres(grid):
    if arrays.MUSCLE not in grid.cell_data or not np.any(grid.cell_data[arrays.MUSCLE]):
        if np.any(np.asarray(grid.cell_data.get(arrays.TISSUE, [])) == arrays.MUSCLE_TISSUE):
            grid = grid.copy()  # generic muscle only (no atlas id): no fibre, isotropic
            grid.cell_data[arrays.FIBER] = np.zeros((grid.n_cells, 3))
        return grid
    return filters.fiber_directions(grid)


def _materials(grid, options):
    return filters.assign_materials(grid, **options)


def _apply_plan(grid, plan, labels, options):
    return drop_floating_parts(filters.apply_plan(grid, plan, labels, **options))


def _skin(labels, post, pre=None, box=None):
    """Step "skin": :func:`pvcmf.filters.skin_prediction.predict_skin`."""
    return predict_skin(labels, post, pre, box)


_SKIN_SUMMARY = SKIN_SUMMARY + (arrays.SKIN_CUT_POINTS,)


def _write_outputs(result, out, images=None):
    """:func:`write_outputs`, plus in ``summary.json`` ``"classified"`` (fat / muscle), the
    skin fit (``arrays.SKIN_FIT_FIELDS``) and the transfer's crumple metric."""
    files = write_outputs(result, out, images)
    if "summary" not in files:
        return files
    path = Path(files["summary"])
    summary = json.loads(path.read_text(encoding="utf-8"))
    summary["classified"] = "classify" in result.timings
    for name, value in result.skin_fit.items():
        summary[name] = value
    skin = result.skin_post
    if skin is not None and arrays.CRUMPLE_VIOLATIONS in skin.field_data:
        for name in _SKIN_SUMMARY:
            if name in skin.field_data:
                summary[name] = skin.field_data[name][0].item()
    write_text(path, json.dumps(summary, indent=2) + "\n")
    return files


# --------------------------------------------------------------------------- main entry
def simulate(ct, plan, out=None, *, labels=None, bones=None, landmarks=None,
             n_tets=DEFAULT_N_TETS, segment_options=None, mesh_options=None,
             material_options=None, bc_options=None, solve_options=None, classify=True,
             muscles=True,
             face_fraction=DEFAULT_FACE_FRACTION, predict=True, solve=True, figures=True,
             fit_skin=False, progress_bar=False, units=None, orient=None,
             working_spacing="auto", shading="auto"):
    """Predict the post-operative face from a CT and a surgical plan.

    Parameters
    ----------
    ct : pyvista.ImageData or str or pathlib.Path
        CT with point array ``ct`` in HU (or a file/folder :func:`pvcmf.read_ct` reads).
    plan : pvcmf.Plan or str or pathlib.Path
        The surgical plan, or a TOML/JSON plan file.
    out : str or pathlib.Path, optional
        Folder for the outputs (see :func:`write_outputs`); nothing is written if None.
        Checked first (:func:`pvcmf.outputs.check_output_dir`); the run is built in a
        hidden sibling folder and renamed onto ``out`` at the end, under a lock
        (:func:`pvcmf.outputs.run_lock`): ``out`` holds one complete run or is unchanged.
    labels : pyvista.ImageData, optional
        Precomputed ``tissue``/``bone`` labels: skips segmentation.
    bones : pyvista.ImageData, optional
        A label image whose ``bone`` array names the segments (e.g. a virtual patient's
        ``truth``): each segmented bone voxel takes the id of its nearest ``bones`` voxel.
        Without it the plan's cut planes (or the segmentation's own ids) define segments.
    landmarks : dict, optional
        Patient landmarks for the muscle atlas (``embed_muscles``); automatic without.
    n_tets : int, default 25000
        Requested number of tetrahedra (the speed/accuracy knob).
    segment_options, mesh_options, material_options, bc_options, solve_options : dict
        Keyword arguments passed to ``segment``, ``tetrahedralize``, ``assign_materials``,
        ``apply_plan`` and ``mtm.solve``. ``bc_options`` defaults to
        :data:`DEFAULT_BC_OPTIONS`: the paper's conditions plus soft tissue on unmoved bone
        fixed (without it, the tissue over the skull, free in the paper, follows a moved
        jaw as a whole, e.g. the forehead moves 5 mm with a Le Fort I; pass
        ``bc_options={"fix_unmoved_bone": False}`` for the paper's exact setting).
    face_fraction : float or None, default 0.5
        Mesh only the anterior fraction of the head (a region of interest in front of a
        coronal plane, whose nodes are the fixed posterior plane of paper 000); None
        meshes the whole head.
    predict : bool, default True
        Run the prediction (mesh, materials, boundary conditions, solve); ``False`` only
        segments, cuts and draws the plan.
    solve : bool, default True
        ``False`` stops after the boundary conditions: :attr:`Result.mesh` and
        :attr:`Result.skin_pre` are made, but no solve, no predicted skin, no skeleton and
        no outputs. This is what a parameter sweep needs once per mesh
        (:class:`pvcmf.sweeps.PipelineEvaluation` then solves per parameter set).
    classify : bool, default True
        Label the segmented soft tissue fat or muscle from the CT values
        (:func:`pvcmf.filters.classify_tissue`, paper 001): the muscle the atlas does not
        name (tongue, temporalis, lips, neck) becomes (isotropic) muscle tissue. ``False``:
        soft tissue that no atlas muscle covers is fat (paper 000's model; the
        virtual-patient study, :func:`pvcmf.study.validation.study_predictor`, judges that
        model and passes ``classify=False``). ``--no-classify`` on the command line. Whether
        it ran is in :attr:`Result.timings` / :attr:`Result.skipped` (step ``"classify"``)
        and in ``summary.json`` (``"classified"``). Not run when ``labels`` are given.
    muscles : bool, default True
        Embed the facial muscles (``embed_muscles``); without, the soft tissue is
        homogeneous. A muscle fit that fails (e.g. bad landmarks) is logged as a warning,
        recorded in :attr:`Result.skipped`, and the prediction goes on without muscles.
    figures : bool, default True
        Render the PNGs when ``out`` is given.
    fit_skin : bool or dict, default False
        Step "skin fit", after meshing: the dense skin of the model's box is extracted and
        the mesh's skin nodes pushed out until the mesh holds it
        (:func:`pvcmf.filters.meshing.fit_to_skin`, options in a dict). Off by default: where
        the mesh lacks tissue (cracks) it sharpens the gaps, and a thin part it pushes
        moves more. What it did: :attr:`Result.skin_fit` and ``summary.json``.
    progress_bar : bool, default False
        Show a progress bar over the steps (:class:`pvcmf.progress.Progress`).
    units, orient : str, optional
        Units and axes check of :func:`pvcmf.filters.standardize` (``'auto'``, ``'hu'``,
        ``'rescale'`` for a cone-beam CT's grey values, or an offset; ``'auto'``, ``'none'``
        or a code such as ``'LPI'``). Default: ``'auto'`` for a CT read from a path or
        given as :func:`pvcmf.read_ct` returned it (field ``source_path``), no check for
        another CT given in memory (a virtual patient, a CT ``standardize`` returned).
        What was found goes to :attr:`Result.ct_report` and ``summary.json`` (``"ct"``).
    working_spacing : 'auto', float or None, default 'auto'
        Step "working grid" (:func:`pvcmf.filters.working_grid`, before the units check and
        the segmentation): ``'auto'`` keeps the scan's grid up to
        :data:`pvcmf.filters.resolution.MAX_VOXELS` voxels and averages a finer scan (a
        cone-beam CT at 0.2 mm) over blocks of whole voxels until it fits, with a warning;
        a number asks for working voxels of about that size (mm); None keeps the scan's
        grid whatever its size (about 50 bytes of memory per voxel). What was done:
        :attr:`Result.working_grid` and ``summary.json`` (``"working_grid"``). Not used
        when ``labels`` are given.
    shading : {'auto', 'n4', 'none'}, default 'auto'
        Step "shading" (:func:`pvcmf.filters.flatten_shading`, after the units check): the
        slow shading of a cone-beam scan's field divided out, for a scan whose grey values
        were rescaled to HU (``'auto'``), any scan (``'n4'``) or none. What was done:
        :attr:`Result.ct_report` and ``summary.json`` (``"ct"``, ``"shading"``).

    Returns
    -------
    Result
        Datasets, seconds per step (:meth:`Result.summary`), skipped steps, written files.

    Raises
    ------
    TypeError, ValueError
        For a bad ``ct``/``plan``/option, before anything is written.

    Examples
    --------
    >>> import pvcmf                                        # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)       # doctest: +SKIP
    >>> res = pvcmf.pipeline.simulate(case.ct, case.plan, bones=case.truth)  # doctest: +SKIP
    >>> print(res.summary())                                # doctest: +SKIP
    """
    plan, opts = _check_inputs(plan, n_tets, face_fraction, bones, segment_options=segment_options,
                               mesh_options=mesh_options, material_options=material_options,
                               bc_options=bc_options, solve_options=solve_options)
    working_factors((1, 1, 1), (1.0, 1.0, 1.0), working_spacing)  # refused before any work
    shading = check_shading(shading)
    check_plan_landmarks(plan, landmarks, fit=muscles and predict, labels=labels)
    if not isinstance(fit_skin, (bool, dict)):  # options of fit_to_skin, or whether to fit
        raise TypeError(f"fit_skin must be a bool or a dict, got {type(fit_skin).__name__}")
    opts["fit_options"] = dict(fit_skin) if isinstance(fit_skin, dict) else ({} if fit_skin else None)
    out = None if out is None else check_output_dir(out)  # before any work
    result = Result(plan=plan)
    with run_lock(out), capture_warnings(result.warnings), \
            Progress(total=len(STEPS), desc="simulate", enabled=progress_bar) as bar:
        run = _Runner(result, bar)
        ct = read_step(run, ct, units, orient, working_spacing, labels is not None, shading)
        labels = _label_steps(run, ct, labels, bones, plan, opts, classify)
        if muscles and predict:
            with_muscles = run.run("muscles", _muscles, labels, landmarks)
            labels = labels if with_muscles is None else with_muscles
        else:
            run.skip("muscles", "muscles=False" if predict else "predict=False")
        labels = with_plan_axes(labels, plan, landmarks)
        result.labels = labels
        result.tissue_volumes = tissue_volumes(labels)
        if arrays.BONE in labels.point_data:
            result.segment_volumes = segment_volumes(labels)
        box = _model_box(labels, opts["mesh_options"], face_fraction)
        _model_steps(run, labels, plan, opts, n_tets=n_tets, box=box, predict=predict,
                     solve=solve, progress_bar=progress_bar)
        _output_steps(run, out, solve=solve, figures=figures, box=box)
    log.info("simulate finished:\n%s", result.summary())
    return result


def _check_inputs(plan, n_tets, face_fraction, bones, **options):
    """The plan (read from a file if need be) and every step's options, checked."""
    if isinstance(plan, (str, Path)):
        plan = read_plan(plan)
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan or a plan file path, got {type(plan).__name__}")
    if isinstance(n_tets, bool) or not isinstance(n_tets, (int, np.integer)) or n_tets <= 0:
        raise ValueError(f"n_tets must be a positive integer, got {n_tets!r}")
    opts = {}
    for name, value in options.items():
        if value is not None and not isinstance(value, dict):
            raise TypeError(f"{name} must be a dict or None, got {type(value).__name__}")
        opts[name] = dict(value or {})
    if options["bc_options"] is None:
        opts["bc_options"] = dict(DEFAULT_BC_OPTIONS)
    if face_fraction is not None and not (0 < float(face_fraction) <= 1):
        raise ValueError(f"face_fraction must be in (0, 1] or None, got {face_fraction!r}")
    if bones is not None and not isinstance(bones, pv.ImageData):
        raise TypeError(f"bones must be a pyvista.ImageData or None, got {type(bones).__name__}")
    return plan, opts


def _label_steps(run, ct, labels, bones, plan, opts, classify=True):
    """Steps "segment", "classify" and "bone segments", then the plan's cuts, a warning for
    each planned segment the scan does not hold whole (:func:`check_coverage`) and one for a
    head the scan holds tilted or turned (:func:`check_pose`, :func:`check_turn`): the label
    image."""
    if labels is None:
        if not isinstance(ct, pv.ImageData):
            raise TypeError(f"ct must be a pyvista.ImageData or a path, got {type(ct).__name__}")
        arrays.require_array(ct, arrays.CT, "point", dtype="f", producer="pvcmf.read_ct")
        seg = opts["segment_options"]  # a head already checked by standardize: not again
        seg = {"check": False, **seg} if run.result.ct_report else seg
        labels = run.run("segment", _segment, ct, seg)
        if classify:
            labels = run.run("classify", _classify, labels)
        else:
            run.skip("classify", "classify=False")
    else:
        run.skip("segment", "labels given")
        run.skip("classify", "labels given")
    if bones is not None:
        labels = run.run("bone segments", transfer_segments, labels, bones)
    else:
        run.skip("bone segments", _segment_sources(labels, plan))
    labels = check_coverage(cut_bones(labels, plan), plan)
    check_pose(labels, plan.axes)
    check_turn(labels, plan.axes)
    return labels


def _segment_sources(labels, plan):
    """Where :func:`cut_bones` takes each planned segment from, without a bone-segment
    image: the plan's cut planes, the labels, or the anatomy (``find_jaws``)."""
    bone = np.asarray(labels[arrays.BONE]) if arrays.BONE in labels.point_data else None
    parts = []
    for o in plan.osteotomies:
        if o.cut:
            parts.append(f"{o.segment} from the plan's cut planes")
        elif bone is not None and np.any(bone == o.segment_id):
            parts.append(f"{o.segment} from the labels")
        else:
            parts.append(f"{o.segment} from the anatomy (find_jaws)")
    return "no bone-segment image: " + (", ".join(parts) or "the plan moves no bone segment")


def _model_steps(run, labels, plan, opts, *, n_tets, box, predict, solve, progress_bar):
    """Steps "mesh", "skin fit", "fibres", "materials", "boundary conditions" and "solve"."""
    result = run.result
    grid = None
    if predict:
        grid = run.run("mesh", _mesh, labels, n_tets, opts["mesh_options"], progress_bar, box)
    else:
        run.skip("mesh", "predict=False")
    if grid is None:
        for step in ("skin fit", "fibres", "materials", "boundary conditions", "solve"):
            run.skip(step, "no mesh" if step in ("skin fit", "fibres", "materials")
                     else "no mesh with materials")
        return
    if opts["fit_options"] is None:
        run.skip("skin fit", "fit_skin=False")
    else:  # the dense skin is extracted here, the mesh fitted to it
        grid, result.skin_pre = run.run("skin fit", _fit_skin, grid, labels, box,
                                        opts["fit_options"])
        result.skin_fit = {k: grid.field_data[k][0].item() for k in arrays.SKIN_FIT_FIELDS}
    grid = run.run("fibres", _fibres, grid) or grid
    grid = run.run("materials", _materials, grid, opts["material_options"])
    if grid is None:  # no materials: the MTM cannot run
        for step in ("boundary conditions", "solve"):
            run.skip(step, "no mesh with materials")
        return
    result.mesh = run.run("boundary conditions", _apply_plan, grid, plan, labels,
                          opts["bc_options"])
    if solve:
        result.post = run.run("solve", _solve, result.mesh, opts["solve_options"])
    else:
        run.skip("solve", "solve=False")


def _solve(grid, options):
    """Step "solve": the MTM (:func:`pvcmf.mtm.solve`)."""
    return mtm.solve(grid, **options)


def _output_steps(run, out, *, solve, figures, box=None):
    """Steps "skin" (map to skin), "skeleton", "figures" and "write"."""
    result = run.result
    skins = run.run("skin", _skin, result.labels, result.post, result.skin_pre, box)
    if skins is not None:
        result.skin_pre, result.skin_post = skins
    if not solve:
        for step in ("skeleton", "figures", "write"):
            run.skip(step, "solve=False")
        return
    result.skeleton = run.run("skeleton", move_bones, result.labels, result.plan)
    if out is None:
        run.skip("figures", "no output folder")
        run.skip("write", "no output folder")
        return
    start = time.perf_counter()
    pngs = render(result) if figures else {}
    result.timings["figures"] = time.perf_counter() - start
    run.progress.step("figures")
    run.run("write", write_run, result, out, pngs, writer=_write_outputs)
