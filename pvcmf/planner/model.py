"""The planner's model: prepared once, then a plan -> predicted face in one call.

:func:`prepare_model` runs the expensive steps once (read, segment, bone segments, muscles,
mesh, materials, the skin and the skeleton at rest, and the plan-response operator) with a
progress display; :meth:`PlannerModel.predict` then turns a :class:`pvcmf.Plan` into the
predicted skin (point array ``displacement``, mm) and :meth:`PlannerModel.skeleton` the
moved bone segments.

The prediction goes through one adapter, :func:`make_predictor`: when
:mod:`pvcmf.mtm.response` is importable it uses its precomputed plan-response operator
(``plan_response(mesh, labels, skin=...)`` whose ``predict(plan)`` evaluates a plan in
milliseconds); otherwise it runs the full pipeline per plan (boundary conditions
:func:`pvcmf.filters.apply_plan`, the MTM solve :func:`pvcmf.mtm.solve`, and
:func:`pvcmf.filters.map_to_surface` onto the dense skin). The label and mesh steps are
those of :func:`pvcmf.pipeline.simulate`; rigid segment moves are
:meth:`pvcmf.Osteotomy.matrix` about the segments' voxel centroids (as
:func:`pvcmf.filters.osteotomy.segment_transforms`, with the centroids computed once).
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pyvista as pv

from .. import arrays, filters, mtm
from ..filters.face_axes import plan_axes
from ..filters.osteotomy import move_bones, voxel_points
from ..pipeline import DEFAULT_BC_OPTIONS, DEFAULT_FACE_FRACTION, simulate
from ..plan import MOVABLE_SEGMENTS, Osteotomy, Plan
from ..progress import Progress

log = logging.getLogger(__name__)

__all__ = ["PlannerModel", "make_predictor", "prepare_model", "PREPARE_STEPS"]

#: the steps of :func:`prepare_model`, in order
PREPARE_STEPS = ("labels", "muscles", "mesh", "skeleton", "response")


def make_predictor(mesh, labels, skin, bc_options=None):
    """A function ``plan -> displacement (n_skin, 3)`` on the dense ``skin``'s points.

    Uses :func:`pvcmf.mtm.response.plan_response` when that module is importable (one
    factorisation, then milliseconds per plan), else the full pipeline per plan.

    Parameters
    ----------
    mesh : pyvista.UnstructuredGrid
        Tetrahedral soft tissue with materials (boundary condition arrays are replaced).
    labels : pyvista.ImageData
        The label image the mesh was made from (``bone`` holds the segments).
    skin : pyvista.PolyData
        Dense rest skin the displacement is wanted on.
    bc_options : dict, optional
        Options of :func:`pvcmf.filters.apply_plan` (default
        :data:`pvcmf.pipeline.DEFAULT_BC_OPTIONS`). One operator serves every plan, so its
        boundary types may not depend on the plan: ``release_margin="auto"`` (twice the
        plan's largest move) becomes no release; give a number (mm) to release a margin.

    Returns
    -------
    callable, str
        The predictor and its kind: ``"response"`` or ``"solve"``.
    """
    bc_options = dict(DEFAULT_BC_OPTIONS if bc_options is None else bc_options)
    if bc_options.get("release_margin") == "auto":
        bc_options["release_margin"] = None
    try:
        response = importlib.import_module("pvcmf.mtm.response")
    except ImportError:
        response = None
    if response is not None and hasattr(response, "plan_response"):
        operator = response.plan_response(mesh, labels, skin=skin, bc_options=bc_options)

        def predict(plan):
            return np.asarray(operator.predict(plan)[arrays.DISPLACEMENT], dtype=np.float64)

        return predict, "response"

    def predict(plan):
        grid = filters.apply_plan(mesh, plan, labels, **bc_options)
        post = mtm.solve(grid)
        mapped = filters.map_to_surface(post, skin, warp=False)
        return np.asarray(mapped[arrays.DISPLACEMENT], dtype=np.float64)

    return predict, "solve"


@dataclass
class PlannerModel:
    """Everything the planner needs, prepared once by :func:`prepare_model`.

    Attributes
    ----------
    labels : pyvista.ImageData
        Labels with the bone segments.
    mesh : pyvista.UnstructuredGrid
        Tetrahedral soft tissue with materials.
    skin : pyvista.PolyData
        Dense rest skin with point normals (``Normals``).
    bones : pyvista.MultiBlock
        Bone segment surfaces at rest (``cranium``, ``maxilla``, ``mandible`` as present).
    segments : tuple of str
        Movable segments present in ``labels``.
    plan : pvcmf.Plan or None
        Starting plan.
    kind : str
        ``"response"`` (precomputed operator) or ``"solve"`` (full pipeline per plan).
    timings : dict
        Step name -> seconds of the preparation.
    """

    labels: pv.ImageData
    mesh: pv.UnstructuredGrid
    skin: pv.PolyData
    bones: pv.MultiBlock
    segments: tuple
    plan: Plan | None = None
    kind: str = "solve"
    timings: dict = field(default_factory=dict)
    _predict: object = field(default=None, repr=False)
    _centroids: dict | None = field(default=None, repr=False)
    _axes: dict = field(default_factory=dict, repr=False)

    def displacement(self, plan):
        """Skin displacement (n, 3) in mm for ``plan``; zero for a plan that moves nothing."""
        if not isinstance(plan, Plan):
            raise TypeError(f"plan must be a pvcmf.Plan, got {type(plan).__name__}")
        if all(not any(o.translation) and not any(o.rotation) for o in plan.osteotomies):
            return np.zeros((self.skin.n_points, 3))
        start = time.perf_counter()
        disp = self._predict(plan)
        log.info("plan predicted in %.3f s (%s)", time.perf_counter() - start, self.kind)
        return disp

    def predict(self, plan):
        """The predicted skin: a copy of :attr:`skin` moved, with ``displacement`` (mm)."""
        disp = self.displacement(plan)
        out = self.skin.copy()
        out.points = np.asarray(self.skin.points) + disp
        out.point_data[arrays.DISPLACEMENT] = disp
        return out

    def plan_axes(self, plan):
        """``plan``'s directions in the image (:func:`pvcmf.filters.plan_axes`), measured
        once per kind of axes."""
        if plan.axes not in self._axes:
            self._axes[plan.axes] = plan_axes(self.labels, plan)
        return self._axes[plan.axes]

    def skeleton(self, plan):
        """The bone segment surfaces moved by ``plan`` (rest segments copied)."""
        if self._centroids is None:  # pivots by default: the segments' voxel centroids
            bone = np.asarray(self.labels[arrays.BONE])
            self._centroids = {s: voxel_points(self.labels, np.flatnonzero(
                bone == arrays.BONE_LABELS[s])).mean(axis=0) for s in self.segments}
        axes = self.plan_axes(plan)
        matrices = {o.segment_id: o.matrix(self._centroids.get(o.segment), axes=axes)
                    for o in plan.osteotomies}
        out = pv.MultiBlock()
        for name in self.bones.keys():
            block = self.bones[name].copy()
            matrix = matrices.get(arrays.BONE_LABELS[name])
            if matrix is not None:
                pts = np.asarray(block.points)
                block.points = pts @ matrix[:3, :3].T + matrix[:3, 3]
            out[name] = block
        return out


def _zero_plan(segments):
    return Plan(tuple(Osteotomy(s) for s in segments), name="")


def prepare_model(ct, plan=None, *, bones=None, labels=None, landmarks=None, n_tets=5000,
                  muscles=True, face_fraction=DEFAULT_FACE_FRACTION, bc_options=None,
                  units=None, orient=None, shading="auto", progress_bar=False):
    """Prepare the planner's model once: labels, mesh, skin, skeleton and predictor.

    Parameters
    ----------
    ct : pyvista.ImageData or str or pathlib.Path
        The CT (see :func:`pvcmf.pipeline.simulate`).
    plan : pvcmf.Plan, optional
        Starting plan; its cut planes define the segments. Without, the label image must
        already hold the maxilla and/or mandible (a virtual patient with ``bones``).
    bones, labels, landmarks, face_fraction, bc_options, units, orient, shading
        As in :func:`pvcmf.pipeline.simulate` (``units``, ``orient``: the check of a CT
        given in memory; ``pvcmf plan`` passes ``'auto'`` for a CT it reads).
    n_tets : int, default 5000
        Requested number of tetrahedra (small: the full-pipeline fallback solves per plan).
    muscles : bool, default True
        Embed the muscle atlas.
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    PlannerModel

    Raises
    ------
    ValueError
        When no movable segment can be found in the labels.
    """
    if plan is not None and not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan or None, got {type(plan).__name__}")
    first = plan if plan is not None else _zero_plan(MOVABLE_SEGMENTS)
    timings = {}
    with Progress(total=len(PREPARE_STEPS), desc="planner", enabled=progress_bar) as bar:
        start = time.perf_counter()
        # the labels alone: the plan's axes (a Frankfort plan's landmarks) come later
        res = simulate(ct, dataclasses.replace(first, axes="image"), labels=labels,
                       bones=bones, predict=False, solve=False, muscles=False,
                       face_fraction=face_fraction, units=units, orient=orient,
                       shading=shading)
        lab, skin = res.labels, res.skin_pre
        present = set(np.unique(np.asarray(lab[arrays.BONE])).tolist())
        segments = tuple(s for s in MOVABLE_SEGMENTS if arrays.BONE_LABELS[s] in present)
        if not segments:
            raise ValueError("the labels hold no maxilla or mandible: give a starting plan "
                             "(--plan) whose osteotomies have cut planes")
        if plan is None:
            first = _zero_plan(segments)
        timings["labels"] = time.perf_counter() - start
        bar.step("labels")
        start = time.perf_counter()
        if muscles:
            try:
                lab = filters.embed_muscles(lab, **({"landmarks": landmarks} if landmarks else {}))
            except (ValueError, RuntimeError) as err:
                log.warning("muscle fit failed, soft tissue left homogeneous: %s", err)
        timings["muscles"] = time.perf_counter() - start
        bar.step("muscles")
        start = time.perf_counter()
        res = simulate(None, first, labels=lab, landmarks=landmarks, predict=True,
                       solve=False, muscles=False, n_tets=n_tets, face_fraction=face_fraction, bc_options=bc_options,
                       progress_bar=False)
        if res.mesh is None:
            raise RuntimeError(f"meshing gave no model: {res.skipped}")
        lab = res.labels  # (with the landmarks a Frankfort plan was given)
        timings["mesh"] = time.perf_counter() - start
        bar.step(f"mesh: {res.mesh.n_cells} tetrahedra")
        start = time.perf_counter()
        rest = move_bones(lab, _zero_plan(segments))  # labels are cut already
        skeleton = pv.MultiBlock({name: rest[name] for name in rest.keys()})
        skin = skin.compute_normals(cell_normals=False, auto_orient_normals=True)
        timings["skeleton"] = time.perf_counter() - start
        bar.step("skeleton")
        start = time.perf_counter()
        predict, kind = make_predictor(res.mesh, lab, skin, bc_options)
        timings["response"] = time.perf_counter() - start
        bar.step(f"response ({kind})")
    log.info("planner model: %s", ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()))
    return PlannerModel(labels=lab, mesh=res.mesh, skin=skin, bones=skeleton,
                        segments=segments, plan=plan, kind=kind, timings=timings,
                        _predict=predict)
