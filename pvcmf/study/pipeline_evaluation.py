"""The pvcmf pipeline as a sweep evaluation (:class:`PipelineEvaluation`).

Per task (a case and its mesh-level parameters) :meth:`PipelineEvaluation.prepare` runs
:func:`pvcmf.pipeline.simulate` without solving (virtual patient -> segmentation ->
muscles -> labelled mesh -> materials -> plan -> boundary conditions, pre-operative skin)
and keeps what does not depend on the material; per parameter set
:meth:`PipelineEvaluation.evaluate` sets the materials, refactorises a
:class:`pvcmf.mtm.Solver` numerically, solves, maps the displacement onto the skin
(the pipeline's :class:`pvcmf.filters.surface_mapping.Transfer` by default, paper 001's
Gaussian :class:`pvcmf.filters.surface_mapping.SurfaceMapping` with ``mapping="gaussian"``)
and measures the signed distance
to the post-operative truth (VTK's ``vtkImplicitPolyDataDistance`` on the truth cropped
to the face, :class:`_TruthSurface`). Plan parameters
(:data:`pvcmf.study.parameters.PLAN_PARAMETERS`, e.g. ``maxilla_t_ap``) are predicted by
one plan-response operator per case, material and solver
(:func:`pvcmf.mtm.response.plan_response`: one factorisation and twelve solves per moved
segment, then one matrix product per plan). Prepared cases are kept on disk with
:func:`pvcmf.cache.cached` (one folder per case and mesh-level parameters).
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import inspect
import json
import logging
import numbers
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pyvista as pv
import vtk
from scipy.spatial import cKDTree
from vtk.util.numpy_support import numpy_to_vtk, vtk_to_numpy

from .. import arrays, atlas, filters, mtm
from ..cache import cached, code_hash
from ..datasets import phantom
from ..filters import distance_to
from ..filters.surface_mapping import SurfaceMapping, Transfer, map_to_surface
from ..mtm.response import plan_response
from ..pipeline import DEFAULT_BC_OPTIONS, simulate
from ..plan import MOVABLE_SEGMENTS, Osteotomy, Plan, read_plan, write_plan
from ..truth.grid import postop_skin
from .evaluation import (Evaluation, FunctionEvaluation, case_identity, code_version,
                         error_statistics, point_key, source_hash)
from .parameters import PLAN_PARAMETERS, _positive, _positive_int, _solver_method, plan_values
from .statistics import label_face_regions

log = logging.getLogger(__name__)

__all__ = ["MAPPINGS", "PipelineEvaluation", "STUDY_SPACING", "TRUTH_MARGIN", "study_truth"]

#: image spacing (mm) of the study's virtual patients, at which the truths are cached
STUDY_SPACING = 2.0
#: the truth is cropped to the points within this distance (mm) of the pre-operative face:
#: far more than any predicted displacement (< 20 mm) plus any error, so every predicted
#: point's closest truth point is kept
TRUTH_MARGIN = 40.0
#: skin mappings of :class:`PipelineEvaluation` (``map_to_surface``'s methods)
MAPPINGS = ("interpolate", "gaussian")
#: files of a prepared case on disk (state key -> file name)
PREPARED_FILES = {"grid": "grid.vtu", "skin": "skin.vtp", "postop": "postop.vtp",
                  "labels": "labels.vti"}
#: files a prepared case cannot do without (the label image and the plan serve plan sweeps)
REQUIRED_PREPARED = ("grid", "skin", "postop")


class PipelineEvaluation(Evaluation):
    """The pvcmf pipeline as a sweep evaluation (the default of :func:`pvcmf.study.engine.sweep`).

    ``prepare(case, spacing=, n_tets=, roi=, conforming=)`` builds the virtual patient
    (``case`` is a patient number for :func:`pvcmf.datasets.phantom`, a mapping of its
    arguments, or a ``Case``) and runs :func:`pvcmf.pipeline.simulate` once *without
    solving* (``solve=False``: segmentation, muscles, labelled mesh, materials, plan ->
    boundary conditions, pre-operative skin), then keeps what does not depend on the
    material: the face skin, the post-operative truth cropped to the face and oriented
    (:class:`_TruthSurface`), and, built on first use, the skin mapping operator
    (:class:`pvcmf.filters.surface_mapping.Transfer`, once per mesh, or
    :class:`pvcmf.filters.surface_mapping.SurfaceMapping` per ``sigma``) and a :class:`pvcmf.mtm.Solver` (geometry,
    block pattern, elimination maps, symbolic factorisation; per ``method``/``tol``).
    ``evaluate(state, nu=..., ...)`` then only sets the materials of the parameter set
    (:meth:`materials`), refactorises numerically, solves, applies the mapping operator
    and measures the signed distance to the truth (:func:`pvcmf.filters.distance.signed_distance`).

    Plan parameters (``maxilla_t_ap=4.0``, ...: :data:`pvcmf.study.parameters.PLAN_PARAMETERS`)
    replace those components of the case's own plan (the others keep its values; a
    segment the case's plan does not move joins it with a zero move). Their points are
    predicted by one :func:`pvcmf.mtm.response.plan_response` operator per case,
    material, solver and set of moved segments (kept in ``state["responses"]``): the
    same answer as ``apply_plan`` + solve + skin transfer per plan, with the boundary
    conditions of :meth:`plan_bc_options` (the pipeline's, with the release margin fixed
    at the one of the case's own plan, so that every plan has the same boundary types).

    Parameters
    ----------
    spacing : float
        Default image resolution (mm) when the grid does not sweep ``spacing``; default
        2 mm, the study default at which :func:`pvcmf.truth.grid.postop_skin` caches the
        truths.
    n_tets : int
        Default tetrahedra count when the grid does not sweep ``n_tets``.
    method : str
        Default MTM solver (``"direct"``; the grid may sweep ``method`` and ``tol``).
    keep_distance : bool
        Return the per-point ``distance`` map and the skin (``skin_points``,
        ``skin_faces``) with every row (for Fig. 5).
    truth : callable, optional
        ``truth(case) -> pyvista.PolyData``: the case's post-operative skin in the
        pre-operative frame. Default: the case's ``postop_skin`` attribute, else the
        virtual post-operative truth of :mod:`pvcmf.truth`. Must be picklable (a
        module-level function, e.g. :func:`study_truth`) to run in Dask processes.
    region : {'face', 'skin'}
        Where errors are measured: ``'face'`` (default) the skin points of the face
        regions of :func:`pvcmf.study.statistics.label_face_regions` (nose, lips, chin,
        cheeks: what the surgery changes and the paper measures; the back of the head
        would dilute the percentiles with zeros), ``'skin'`` the whole skin.
    cache_dir : str or Path, optional
        Keep each prepared case (mesh with boundary conditions, skin, post-operative
        skin; VTK XML files) under a hash of (case, mesh-level parameters, options, code
        version; :func:`pvcmf.cache.cached`), so later sweeps on the same meshes (Figs. 2,
        4, 5) skip the phantom, segmentation, muscles and meshing.
    mesh_threads : int, default 1
        gmsh threads per task. A local sweep runs one single-threaded Dask process per
        core, so more threads only oversubscribe the machine.
    mapping : {'interpolate', 'gaussian'}, default 'interpolate'
        How the mesh displacement reaches the skin: ``'interpolate'`` the operator of
        :func:`pvcmf.pipeline.simulate` and ``map_to_surface``
        (:func:`pvcmf.filters.surface_mapping.transfer_operator`: finite-element
        interpolation inside the mesh, an exact-for-affine extension outside);
        ``'gaussian'`` paper 001's Gaussian moving least squares
        (:class:`pvcmf.filters.surface_mapping.SurfaceMapping`, width ``sigma`` per
        parameter set: what reproduces the paper's figures).
    """

    version = "4"

    def __init__(self, spacing=2.0, n_tets=30_000, method="direct", keep_distance=False,
                 truth=None, region="face", cache_dir=None, mesh_threads=1,
                 mapping="interpolate"):
        if mapping not in MAPPINGS:
            raise ValueError(f"mapping must be one of {MAPPINGS}, got {mapping!r}")
        self.mapping = mapping
        self.cache_dir = None if cache_dir is None else str(cache_dir)
        if region not in ("face", "skin"):
            raise ValueError(f"region must be 'face' or 'skin', got {region!r}")
        self.region = region
        self.spacing = _positive("spacing", spacing)
        self.n_tets = _positive_int("n_tets", n_tets)
        self.method = _solver_method("method", method)
        self.keep_distance = bool(keep_distance)
        if truth is not None and not callable(truth):
            raise TypeError(f"truth must be callable(case) -> PolyData or None, got {type(truth).__name__}")
        self.truth = truth
        if isinstance(mesh_threads, bool) or not isinstance(mesh_threads, numbers.Integral) \
                or mesh_threads < 1:
            raise ValueError(f"mesh_threads must be an integer >= 1, got {mesh_threads!r}")
        self.mesh_threads = int(mesh_threads)

    def identity(self):
        truth = None if self.truth is None else FunctionEvaluation(self.truth).identity()
        own = code_hash(type(self), _TruthSurface, _skin_mapping, _face_only, _postop_skin,
                        error_statistics)
        return {**super().identity(), "spacing": self.spacing, "n_tets": self.n_tets,
                "method": self.method, "keep_distance": self.keep_distance, "truth": truth,
                "region": self.region, "mesh_threads": self.mesh_threads,
                "mapping": self.mapping,
                "code": source_hash(), "own": own}

    def prepare(self, case, *, spacing=None, n_tets=None, roi=None, conforming=True, n_points=None):
        group = {"spacing": self.spacing if spacing is None else spacing,
                 "n_tets": self.n_tets if n_tets is None else n_tets,
                 "roi": roi, "conforming": conforming, "n_points": n_points}
        if self.cache_dir is None:
            return self._finish(self._timed_prepare(case, group))
        _, ident = case_identity(case)
        what = {k: v for k, v in self.identity().items()
                if k not in ("method", "keep_distance", "mapping")}
        folder = Path(self.cache_dir) / point_key(ident, group, what, code_version())
        state = cached(folder, lambda: self._timed_prepare(case, group), read=_read_prepared,
                       write=_write_prepared, folder=True)
        return self._finish(state)

    def _timed_prepare(self, case, group):
        _warm_up()  # once per process, outside the timed preparation
        t0, c0 = time.perf_counter(), time.process_time()
        state = self._prepare(case, **group)
        state["prepare_times"] = {"t_prepare": time.perf_counter() - t0,
                                  "cpu_prepare": time.process_time() - c0}
        return state

    @staticmethod
    def _finish(state):
        """Add the material-independent operators to a prepared (or loaded) state."""
        t0 = time.perf_counter()
        truth = _TruthSurface(state["postop"], np.asarray(state["skin"].points, float))
        log.info("truth cropped to the face: %d of %d points (%.2f s)", truth.surface.n_points,
                 state["postop"].n_points, time.perf_counter() - t0)
        return {"solvers": {}, "responses": {}, **state, "truth": truth, "mappings": {}}

    def _prepare(self, case, *, spacing, n_tets, roi, conforming, n_points):
        if isinstance(case, numbers.Integral):
            case = phantom(patient=int(case), spacing=spacing)
        elif isinstance(case, Mapping):
            case = phantom(**{"spacing": spacing, **case})
        postop = _postop_skin(case) if self.truth is None else self.truth(case)
        mesh_options = {"threads": self.mesh_threads}
        if roi is not None:  # the soft tissue within `roi` mm of the (first) moved segment
            mesh_options["roi"] = (case.plan.osteotomies[0].segment_id, roi)
        if not conforming:
            mesh_options["conforming"] = False
        # no solve, no predicted skin, no skeleton: evaluate() solves per parameter set
        result = simulate(case.ct, case.plan, bones=getattr(case, "truth", None),
                          landmarks=getattr(case, "landmarks", None), n_tets=n_tets,
                          mesh_options=mesh_options, figures=False, solve=False)
        if result.mesh is None or result.skin_pre is None:
            raise RuntimeError(f"the pipeline did not produce a mesh and skin for {case.name!r}; "
                               f"skipped steps: {result.skipped}")
        grid = result.mesh
        if not conforming and n_points:
            grid = grid.cmf.sample_muscle_fraction(result.labels, n_points=n_points)
        skin = result.skin_pre
        if self.region == "face":
            skin = _face_only(skin, getattr(case, "landmarks", None))
        return {"grid": grid, "skin": skin, "postop": postop, "labels": result.labels,
                "plan": case.plan}

    @staticmethod
    def materials(grid, *, nu=None, nu_fat=None, nu_muscle=None, E_ratio=None, E_fat=None,
                  E_muscle=None):
        """Per-cell material overrides of one parameter set (paper 001 sec. 2.1 / 2.2).

        ``nu``: homogeneous isotropic material (E = ``E_fat`` or 1; the displacement-driven
        MTM does not depend on E). Any of ``nu_fat``, ``nu_muscle``, ``E_ratio``, ``E_fat``,
        ``E_muscle``: isotropic fat and muscle (defaults nu_fat 0.485, nu_muscle 0.43,
        E_muscle = E_ratio * E_fat), mixed per cell by ``muscle_fraction`` when the grid
        has it (the baselines) or by the cell's ``tissue`` label. None of them: the grid's
        own materials (``{}``).
        """
        if nu is not None:
            e = 1.0 if E_fat is None else E_fat
            return {"E_fiber": e, "E_cross": e, "nu": nu}
        if all(v is None for v in (nu_fat, nu_muscle, E_ratio, E_fat, E_muscle)):
            return {}
        if arrays.MUSCLE_FRACTION in grid.cell_data.keys():
            f = np.clip(np.asarray(grid.cell_data[arrays.MUSCLE_FRACTION], float), 0.0, 1.0)
        else:
            tissue = arrays.require_array(grid, arrays.TISSUE, "cell", producer="tetrahedralize")
            f = (np.asarray(tissue) == arrays.MUSCLE_TISSUE).astype(float)
        e_fat = 1.0 if E_fat is None else E_fat
        e_muscle = E_muscle if E_muscle is not None else e_fat * (1.0 if E_ratio is None else E_ratio)
        e = (1 - f) * e_fat + f * e_muscle
        nu_cells = (1 - f) * (0.485 if nu_fat is None else nu_fat) + f * (0.43 if nu_muscle is None else nu_muscle)
        return {"E_fiber": e, "E_cross": e, "nu": nu_cells}

    def evaluate(self, state, *, nu=None, nu_fat=None, nu_muscle=None, E_ratio=None, E_fat=None,
                 E_muscle=None, tol=None, method=None, sigma=None, **plan):
        unknown = sorted(set(plan) - set(PLAN_PARAMETERS))
        if unknown:
            raise TypeError(f"evaluate got unknown parameter(s) {unknown}")
        if "truth" not in state:  # a state built by hand: add the reusable operators
            state.update(self._finish(state))
        grid = state["grid"]
        method = self.method if method is None else method
        materials = {"nu": nu, "nu_fat": nu_fat, "nu_muscle": nu_muscle, "E_ratio": E_ratio,
                     "E_fat": E_fat, "E_muscle": E_muscle}
        material = self.materials(grid, **materials)
        if sigma is not None and self.mapping != "gaussian":
            raise ValueError(f"sigma applies to mapping='gaussian' only, got sigma={sigma!r} "
                             f"with mapping={self.mapping!r}")
        mapping = state["mappings"].get((self.mapping, sigma))
        if mapping is None:  # independent of the material: once per mesh (and sigma)
            mapping = state["mappings"][(self.mapping, sigma)] = _skin_mapping(
                grid, state["skin"].points, sigma, self.mapping)
        if plan:
            t0 = time.perf_counter()
            disp = self._plan_displacement(state, plan, material, method, tol,
                                           tuple(materials.values()), mapping)
            t_solve, residual = time.perf_counter() - t0, np.nan
        else:
            solver = state["solvers"].get((method, tol))
            if solver is None:  # first parameter set of this method: structure + symbolic analysis
                options = {} if tol is None else {"tol": tol}
                solver = state["solvers"][(method, tol)] = mtm.Solver(grid, method, **options,
                                                                      **material)
            elif material:  # no symbolic analysis; direct: the previous factor preconditions CG
                # (to the same tolerance; it refactors when that needs > 20 iterations)
                solver.update_materials(**material, refactor=False)
            disp = np.asarray(mapping(solver.solve()), float)
            t_solve = float(solver.info.get("time", np.nan))
            residual = float(solver.info.get("residual", np.nan))
        pred = np.asarray(state["skin"].points, float) + disp
        d = state["truth"].distance(pred)
        out = error_statistics(d)
        out.update({arrays.SWEEP_N_CELLS: int(grid.n_cells), "t_solve": t_solve,
                    "residual": residual})
        if self.keep_distance:
            skin = state["skin"]
            out.update({arrays.SWEEP_DISTANCE: d, arrays.DISPLACEMENT: disp,
                        arrays.SWEEP_SKIN_POINTS: np.asarray(skin.points, float),
                        arrays.SWEEP_SKIN_FACES: np.asarray(skin.faces)})
        return out

    @staticmethod
    def plan_bc_options(state):
        """Boundary-condition options of plan-parameter points
        (:func:`pvcmf.filters.apply_plan`): the pipeline's
        (:data:`pvcmf.pipeline.DEFAULT_BC_OPTIONS`) with ``release_margin`` fixed at twice
        the largest move the prepared grid's boundary conditions prescribe (what ``'auto'``
        gave the case's own plan), so every plan of a sweep has the same boundary types."""
        options = dict(DEFAULT_BC_OPTIONS)
        grid = state["grid"]
        if arrays.BC in grid.point_data.keys() and arrays.BC_DISPLACEMENT in grid.point_data.keys():
            code = np.asarray(grid.point_data[arrays.BC])
            disp = np.asarray(grid.point_data[arrays.BC_DISPLACEMENT], float)
            moving = (code == arrays.BC_JOINT) | (code == arrays.BC_SLIDING)
            options["release_margin"] = 2.0 * float(
                np.linalg.norm(disp[moving], axis=1).max(initial=0.0))
        else:
            options["release_margin"] = None
        return options

    @staticmethod
    def plan_of(state, plan):
        """The plan of a point: the case's plan (``state["plan"]``) with the components
        named by the plan parameters ``plan`` replaced; every swept segment is in it."""
        base = state.get("plan")
        if base is None or state.get("labels") is None:
            raise ValueError("plan parameters need the case's plan and label image in the "
                             "prepared state (keys 'plan' and 'labels'), got "
                             f"{sorted(k for k in ('plan', 'labels') if state.get(k) is not None)}")
        values = plan_values(plan)
        have = {o.segment: o for o in base.osteotomies}
        osteotomies = []
        for segment in MOVABLE_SEGMENTS:
            if segment not in have and segment not in values:
                continue
            o = have.get(segment) or Osteotomy(segment)
            move = {}
            for attr, given in values.get(segment, {}).items():
                vec = list(getattr(o, attr))
                for axis, v in given.items():
                    vec[axis] = v
                move[attr] = tuple(vec)
            osteotomies.append(dataclasses.replace(o, **move))
        return Plan(tuple(osteotomies), name=base.name, axes=base.axes)

    def _plan_displacement(self, state, plan, material, method, tol, material_key, mapping):
        """Skin displacement of a plan point, from the case's plan-response operator
        (built on the first point of each material, solver and set of moved segments)."""
        target = self.plan_of(state, plan)
        key = (method, tol, material_key, target.segments)
        resp = state["responses"].get(key)
        if resp is None:
            log.info("plan response of %s (%s)", list(target.segments), method)
            options = {"method": method, **({} if tol is None else {"tol": tol}), **material}
            interpolate = self.mapping == "interpolate"
            resp = state["responses"][key] = plan_response(
                state["grid"], state["labels"], skin=state["skin"] if interpolate else None,
                plan=target, dtype="float64", bc_options=self.plan_bc_options(state),
                solver_options=options)
        if resp.skin_operator is not None:
            return resp.predict_displacement(target)
        return np.asarray(mapping(resp.predict_mesh(target)), float)


_WARM = []


def _warm_up():
    """Import the pipeline's modules (and load the muscle atlas) once per process, so the
    first task of a Dask process does not report the imports as its preparation time."""
    if _WARM:
        return
    for name in filters.__all__ if hasattr(filters, "__all__") else ():
        with contextlib.suppress(Exception):
            getattr(filters, name)
    for module in ("pyamg", "gmsh"):
        with contextlib.suppress(Exception):
            importlib.import_module(module)
    with contextlib.suppress(Exception):
        atlas.default()
    _WARM.append(True)


def study_truth(case, *, spacing=None, n_tets=None):
    """The post-operative truth of the study for any image spacing of a virtual patient.

    :func:`pvcmf.truth.grid.postop_skin` of ``phantom(case.patient, spacing=spacing)``
    (default :data:`STUDY_SPACING`, whose truths are cached; ``n_tets``: the truth's mesh
    size, default that of ``postop_skin``), whatever ``case.spacing`` is: a sweep over the
    image resolution must judge every resolution against the same truth. A module-level
    function, so it travels to Dask processes (``PipelineEvaluation(truth=study_truth)``, or
    ``functools.partial(study_truth, spacing=2.0, n_tets=16000)``).
    """
    spacing = STUDY_SPACING if spacing is None else float(spacing)
    options = {} if n_tets is None else {"n_tets": int(n_tets)}
    if float(case.spacing) == spacing:
        return postop_skin(case, **options)
    return postop_skin(phantom(patient=case.patient, spacing=spacing), **options)



class _TruthSurface:
    """The truth, oriented outward once and cropped to the face, for repeated distances.

    The exact point-to-triangle distance of :func:`pvcmf.filters.distance_to`, for every
    query point whose closest truth point lies within ``margin`` of ``near``, but with the
    orientation, the crop and VTK's cell locator (``vtkImplicitPolyDataDistance``, sign
    from the closest cell's normal) built once per truth instead of once per call. A
    closed truth is oriented by its signed volume before cropping; an open one (or one
    with inconsistent winding) is left to :func:`pvcmf.filters.distance_to` on each call.
    """

    def __init__(self, surface, near, margin=TRUTH_MARGIN):
        self.closed = surface.n_open_edges == 0 if isinstance(surface, pv.PolyData) else False
        self._full = surface
        self._implicit = None
        self.surface = surface
        if not self.closed:  # a crop of an open surface cannot be oriented reliably
            return
        surf = surface.triangulate() if not surface.is_all_triangles else surface
        tris = np.asarray(surf.faces).reshape(-1, 4)[:, 1:].astype(np.int64)
        pts = np.asarray(surf.points, float)
        directed = np.sort(np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
                           @ np.array([len(pts), 1]))
        if (directed[1:] == directed[:-1]).any():  # inconsistent winding: leave it to distance_to
            self.closed = False
            return
        a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
        if np.einsum("ij,ij->", a - pts.mean(axis=0), np.cross(b - a, c - a)) < 0:
            tris = tris[:, ::-1]  # outward: positive signed volume
        dist, _ = cKDTree(np.asarray(near, float)).query(pts, distance_upper_bound=margin)
        kept = tris[np.isfinite(dist)[tris].all(axis=1)]
        used = np.unique(kept)
        new_id = np.full(len(pts), -1)
        new_id[used] = np.arange(used.size)
        self.surface = pv.PolyData(pts[used], np.c_[np.full(len(kept), 3), new_id[kept]].ravel())

    def distance(self, points):
        """Signed distances (mm) of ``(n, 3)`` points, positive outside (anterior)."""
        points = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
        if not self.closed:  # cannot orient a crop of an open surface reliably
            return np.asarray(distance_to(pv.PolyData(points), self._full).point_data[arrays.DISTANCE])
        if self._implicit is None:  # VTK's cell locator, built once per truth
            self._implicit = vtk.vtkImplicitPolyDataDistance()
            self._implicit.SetInput(self.surface)
        out = vtk.vtkDoubleArray()
        self._implicit.FunctionValue(numpy_to_vtk(points, deep=True), out)
        return vtk_to_numpy(out).astype(np.float64, copy=True)


def _skin_mapping(grid, skin_points, sigma=None, mapping="interpolate"):
    """:func:`pvcmf.filters.map_to_surface` as its precomputed sparse operator, built once
    per mesh (the weights do not depend on the material): ``'interpolate'``
    :class:`pvcmf.filters.surface_mapping.Transfer` of the tetrahedral ``grid`` (the
    pipeline's defaults); ``'gaussian'``
    :class:`pvcmf.filters.surface_mapping.SurfaceMapping` of ``grid``'s points (a dataset
    or an ``(n, 3)`` array) per ``sigma``."""
    if mapping not in MAPPINGS:
        raise ValueError(f"mapping must be one of {MAPPINGS}, got {mapping!r}")
    if mapping == "interpolate":
        return Transfer(grid, skin_points)
    grid_points = np.asarray(grid.points if isinstance(grid, pv.DataSet) else grid, float)
    if sigma is None:
        sigma = inspect.signature(map_to_surface).parameters["sigma"].default
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0 mm, got {sigma}")
    return SurfaceMapping(grid_points, skin_points, sigma, 3.0 * sigma)


def _face_only(skin, landmarks):
    """The face regions of a skin (:func:`pvcmf.study.statistics.label_face_regions`)."""
    labelled = label_face_regions(skin, landmarks=landmarks)
    face = np.asarray(labelled.point_data[arrays.REGION]) > 0
    if not face.any():
        raise ValueError("no skin point lies in a face region; use region='skin'")
    if not labelled.is_all_triangles:
        labelled = labelled.triangulate()
    tri = np.asarray(labelled.faces).reshape(-1, 4)[:, 1:]
    new_id = np.cumsum(face) - 1
    kept = new_id[tri[face[tri].all(axis=1)]]
    out = pv.PolyData(np.asarray(labelled.points)[face],
                      np.c_[np.full(len(kept), 3), kept].ravel() if len(kept) else None)
    for name in labelled.point_data.keys():
        out.point_data[name] = np.asarray(labelled.point_data[name])[face]
    return out


def _postop_skin(case):
    skin = getattr(case, "postop_skin", None)
    if skin is not None:
        return skin
    return postop_skin(case)


def _write_prepared(state, folder):
    """Fill ``folder`` with a prepared case (VTK XML files, preparation times as JSON)."""
    folder = Path(folder)
    for key, name in PREPARED_FILES.items():
        if state.get(key) is not None:  # labels: only when the state has them
            state[key].save(folder / name)
    if state.get("plan") is not None:
        write_plan(state["plan"], folder / "plan.json")
    (folder / "times.json").write_text(json.dumps(state["prepare_times"]))


def _read_prepared(folder):
    """A prepared case written by :func:`_write_prepared` (raises when incomplete)."""
    folder = Path(folder)
    state = {key: pv.read(folder / name) for key, name in PREPARED_FILES.items()
             if key in REQUIRED_PREPARED or (folder / name).exists()}
    if (folder / "plan.json").exists():
        state["plan"] = read_plan(folder / "plan.json")
    state["prepare_times"] = json.loads((folder / "times.json").read_text())
    return state
