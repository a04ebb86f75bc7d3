"""Plan response operator: the predicted skin of any surgical plan as a few small products.

A plan enters the linear MTM only through prescribed displacements: a joint node ``x`` of a
segment moved by the rigid map ``M`` is displaced by ``(M[:3, :3] - I) x + M[:3, 3]``, and a
sliding node's prescribed normal part is the normal component of the same vector. Both are
linear in the twelve numbers ``A = (M - I)[:3, :]`` of every moved segment, so the nodal
displacement is ``u = R a`` with ``a`` the stacked ``A``'s, and the skin displacement is
``T R a`` with ``T`` the mesh -> skin transfer (:func:`pvcmf.filters.surface_mapping.
transfer_operator`). :func:`plan_response` builds ``R`` with one factorisation
(:class:`pvcmf.mtm.Solver`) and twelve solves per segment, for boundary conditions whose
*types* match those of the plans it will see (same moved segments, same cut planes);
:class:`PlanResponse` folds ``T`` in (:class:`pvcmf.mtm.response_operator.SkinOperator`:
skin points with few transfer weights, inside the mesh, are evaluated from the nodal
displacement of the nodes they use; the others from dense rows of ``T R``) and predicts a
plan by two small dense products and one sparse product that writes the output. A plan
whose boundary-condition types differ (another set of moved segments when unmoved bone is
free, other cut planes) is predicted by a full ``apply_plan`` + solve, with a warning.

Coordinates are centred on each segment's pivot centroid. Skin points the transfer does
not reach (beyond twice its band) stay at rest; many plans are blocked products reduced to
statistics block by block. A predicted surface has its own points and data arrays and
shares only the cell connectivity of the operator's own copy of the skin (pyvista never
writes into it in place), so results cannot change each other or the input skin.

``float32`` storage halves the memory the products read; ``dtype='auto'`` takes it when
the rounding bound of the float32 products (:meth:`SkinOperator.float32_error`, from
:func:`float32_bound`), over plans with rotation entries up to :data:`FLOAT32_ROTATION` and
centroid shifts up to :data:`FLOAT32_SHIFT` mm, is within :data:`FLOAT32_TOLERANCE`. On a
face the bound is far above 1e-6 mm and float64 is kept (docs/benchmarks/plan_response.md
gives a 30k mesh's). The skin transfer is built on both cores: a partner (a second
thread, or a forked process) starts on its rows beside the factorisation and solves, and
the calling thread takes the rows left after them (:mod:`pvcmf.mtm.response_transfer`); the basis
solves skip the solution checks (unit fields, not motions). Delegates to
:func:`pvcmf.filters.apply_plan`, :class:`pvcmf.mtm.Solver`, numpy (BLAS), scipy.sparse
and threadpoolctl (one BLAS thread for the products).
"""

from __future__ import annotations

import logging
import time
import warnings

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.boundary_conditions import apply_plan
from ..filters.face_axes import plan_axes
from ..filters.field_of_view import cut_points
from ..filters.osteotomy import cut_bones
from ..filters.surface_mapping import transfer_operator
from ..plan import MOVABLE_SEGMENTS, Osteotomy, Plan
from ..progress import Progress
from .constraints import SolutionWarning
from .plan_sweep import plan_grid  # noqa: F401  (re-exported: pvcmf.mtm.response.plan_grid)
from .response_operator import FLOAT32_ROTATION, FLOAT32_SHIFT, float32_bound  # noqa: F401
from .response_operator import SkinOperator
from .response_operator import one_thread as _one_thread
from .response_transfer import _cores, transfer_in_background
from .solver import Solver

log = logging.getLogger(__name__)

__all__ = ["PlanResponse", "plan_response", "plan_grid", "PlanResponseWarning", "float32_bound"]


#: largest float32 rounding bound (mm) of the skin operator's product that keeps float32
FLOAT32_TOLERANCE = 1e-6


def _segmented(labels, plan):
    """``labels`` whose ``bone`` array holds every segment of ``plan``: the image itself when
    the plan has no cut planes and labels all its segments (:func:`cut_bones` would return
    a copy with the same ``bone``), else :func:`cut_bones`'s result."""
    if (isinstance(labels, pv.ImageData) and arrays.BONE in labels.point_data
            and not any(o.cut for o in plan.osteotomies)):
        bone = np.asarray(labels.point_data[arrays.BONE])
        if all(np.any(bone == o.segment_id) for o in plan.osteotomies):
            return labels
    return cut_bones(labels, plan)


class PlanResponseWarning(UserWarning):
    """A plan needs boundary conditions the operator cannot express: full solve used."""


def _template(labels, plan):
    """The plan that fixes the operator's boundary-condition types: ``plan``'s segments and
    cut planes, or every movable segment labelled in ``labels``."""
    if plan is not None:
        if not isinstance(plan, Plan):
            raise TypeError(f"plan must be a pvcmf.Plan or None, got {type(plan).__name__}")
        return plan
    bone = np.asarray(arrays.require_array(labels, arrays.BONE, "point", dtype="iu",
                                           producer="segment"))
    present = [s for s in MOVABLE_SEGMENTS if arrays.BONE_LABELS[s] in bone]
    if not present:
        raise ValueError(f"labels have no movable segment ({list(MOVABLE_SEGMENTS)}) in "
                         f"{arrays.BONE!r}; pass plan= with cut planes")
    return Plan(tuple(Osteotomy(s) for s in present))


def plan_response(mesh, labels, *, skin=None, plan=None, dtype="auto", bc_options=None,
                  solver_options=None, progress_bar=False):
    """Build the plan -> displacement operator of a mesh (see the module docs).

    Parameters
    ----------
    mesh : pyvista.UnstructuredGrid
        Tetrahedral soft-tissue mesh with materials (``assign_materials``).
    labels : pyvista.ImageData
        The label image ``apply_plan`` reads (``bone``, ``tissue``).
    skin : pyvista.DataSet, optional
        Dense skin (e.g. ``labels.cmf.skin()``): :meth:`PlanResponse.predict` maps onto it.
    plan : pvcmf.Plan, optional
        Segments and cut planes of the plans to come (its motions are ignored, except to fix
        ``release_margin="auto"``). Default:
        every movable segment the ``bone`` label holds, without cut planes.
    dtype : {'auto', 'float32', 'float64'}
        Storage of the skin operator; ``'auto'`` keeps float32 when the rounding bound of
        its product (:attr:`PlanResponse.float32_error`) is within
        :data:`FLOAT32_TOLERANCE` (1e-6 mm) for every plan with rotations up to 30 degrees
        and centroid shifts up to 20 mm.
    bc_options : dict, optional
        Keyword arguments of :func:`pvcmf.filters.apply_plan` (e.g. ``fix_unmoved_bone``).
        ``release_margin='auto'`` (twice a plan's largest move) is fixed once, from
        ``plan``'s motions (:attr:`PlanResponse.release_margin`), so that one operator has
        one set of boundary types; a ``plan`` that moves nothing is then refused.
    solver_options : dict, optional
        Keyword arguments of :class:`pvcmf.mtm.Solver` (``precision='double'`` unless given:
        its solves need no refinement).
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    PlanResponse
    """
    if not isinstance(mesh, pv.UnstructuredGrid):
        raise TypeError(f"mesh must be a pyvista.UnstructuredGrid, got {type(mesh).__name__}")
    if dtype not in ("auto", "float32", "float64"):
        raise ValueError(f"dtype must be 'auto', 'float32' or 'float64', got {dtype!r}")
    solver_options = {"precision": "double", **(solver_options or {})}
    return PlanResponse(mesh, labels, skin=skin, plan=_template(labels, plan), dtype=dtype,
                        bc_options=dict(bc_options or {}), solver_options=solver_options,
                        progress_bar=progress_bar)


class PlanResponse:
    """Linear map from a plan to the nodal and skin displacements (:func:`plan_response`).

    Attributes
    ----------
    segments : tuple of int
        Segment ids, in the order of the parameter vector (twelve numbers each).
    nodal : ndarray, shape (3, n_points, 12 * n_segments)
        Nodal response per component.
    skin_response : ndarray or None, shape (3, n_skin, 12 * n_segments)
        The skin operator per component as one dense array, made from the stored parts
        on first access and kept, read-only.
    skin_operator : pvcmf.mtm.response_operator.SkinOperator or None
        The stored skin operator (sparse rows on the nodal response, dense rows).
    reached : ndarray of int or None
        Skin points with a non-empty transfer row (the others never move).
    surface_ids : ndarray
        The mesh's boundary nodes (:meth:`predict_nodes`).
    modelled : ndarray of bool or None
        Skin points the mesh models (within the transfer's band, :data:`arrays.SKIN_MODELLED`).
    float32_error : float or None
        ``dtype='auto'``: rounding bound (mm) of the float32 skin products against the
        float64 ones, ``(K + 2) u |row| s`` over the dense rows and ``(K + 2) u |T_row| |R| s``
        over the points evaluated from the nodal response, ``s`` the plan range
        (:data:`FLOAT32_ROTATION`, :data:`FLOAT32_SHIFT`); float32 is kept when it is at
        most :data:`FLOAT32_TOLERANCE`.
    release_margin : float or None
        The release margin (mm) of the operator's boundary conditions
        (``bc_options['release_margin']``, ``'auto'`` resolved from the build plan).
    timings : dict
        Seconds of ``bc`` (apply_plan), ``factor``, ``solves``, ``transfer`` (after the
        solves: the skin transfer's ranges left to the calling thread, waiting for the
        partner, joining, folding), ``fold`` (of those, the skin operator's parts: the
        smoothing steps on the dense rows of the transfer before them times the nodal
        response, on every core, and the rows laid out parameter-major), the transfer's
        ``rows`` built by the partner (``(second process)`` or ``(second thread)``,
        beside the others) and by the calling thread, with their CPU times, its ``join``
        (the smoothing steps, with the product of the transfer before them and the nodal
        response made beside them on a second thread), and the CPU time of the calling
        thread (``main thread CPU``; ``main thread CPU, bc + factor + solves`` up to the
        solves).
    transfer_ranges : dict or None
        Ranges of skin points whose transfer rows the partner (``'second process'`` or
        ``'second thread'``) and the ``'calling thread'`` built.
    """

    def __init__(self, mesh, labels, *, skin, plan, dtype, bc_options, solver_options,
                 progress_bar):

        from ..filters.boundary_conditions import boundary_points

        self.mesh, self.labels, self.skin, self.template = mesh, labels, skin, plan
        self.bc_options, self.solver_options = bc_options, solver_options
        self.timings = {}
        self.threads = solver_options.get("threads", 1)  # BLAS threads of the products
        self.float32_error = None
        self._axes = {}
        cpu0 = time.thread_time()
        with Progress(total=4, desc="plan_response", enabled=progress_bar, logger=log) as bar:
            pending = None if skin is None else transfer_in_background(mesh, skin)
            try:
                ref = self._factor_and_solve(bar)
                self.timings["main thread CPU, bc + factor + solves"] = time.thread_time() - cpu0
            except BaseException:
                if pending is not None:
                    pending.cancel()
                raise
            t = time.perf_counter()
            self.surface_ids = boundary_points(mesh)
            self._skin, self._skin_dense, self.reached, self.modelled = None, None, None, None
            self.transfer_ranges = None
            if pending is not None:
                point_major = np.ascontiguousarray(self.nodal.transpose(1, 0, 2))
                transfer, timings = pending.result(  # W0 R_c made beside the join
                    right=[self.nodal[c] for c in range(3)])
                self.timings.update(timings)
                self.transfer_ranges = pending.ranges
                self.modelled = transfer.modelled
                fold = time.perf_counter()
                self._skin = SkinOperator(transfer.W0, point_major, steps=transfer.steps,
                                          threads=_cores(), product=transfer.product)
                self.timings["fold"] = time.perf_counter() - fold
                self.reached = self._skin.reached
                store = self._dtype(dtype)
                if store != self._skin.dtype:
                    self._skin = self._skin.astype(store)
            K = self.nodal.shape[2]  # point-major rows: a plan's product is (n_surface, 3)
            self._surface = np.ascontiguousarray(
                self.nodal[:, self.surface_ids].transpose(1, 0, 2)).reshape(-1, K)
            self.timings["transfer"] = time.perf_counter() - t
            self.timings["main thread CPU"] = time.thread_time() - cpu0
            bar.step("transfer folded in")
        self._bc_types = np.asarray(ref[arrays.BC]).copy()

    def _factor_and_solve(self, bar):
        """Boundary conditions of the probe plan, one factorisation and the basis solves
        (:attr:`nodal`); returns the probe's grid."""
        plan, labels = self.template, self.labels
        t = time.perf_counter()
        cut = _segmented(labels, plan)
        self.centroids = {s: np.asarray(m, float) for s, m in self._pivots(cut, plan).items()}
        self._probe = Plan(tuple(Osteotomy(o.segment, translation=tuple(np.eye(3)[i]), cut=o.cut)
                                 for i, o in enumerate(plan.osteotomies)))
        self.bc_options = self._fixed_release(plan)
        ref = apply_plan(self.mesh, self._probe, labels, **self.bc_options)
        self.segments = tuple(o.segment_id for o in plan.osteotomies)
        self.timings["bc"] = time.perf_counter() - t
        bar.step("boundary conditions")
        t = time.perf_counter()
        solver = Solver(ref, **self.solver_options)
        self.timings["factor"] = time.perf_counter() - t
        bar.step("factorised")
        t = time.perf_counter()
        self.nodal = self._solve_basis(ref, solver)
        self.timings["solves"] = time.perf_counter() - t
        bar.step(f"{self.nodal.shape[2]} solves")
        return ref

    def _fixed_release(self, plan):
        """``bc_options`` with ``release_margin='auto'`` made a number: twice the largest
        move ``plan`` prescribes (what ``'auto'`` gives that plan), so that every plan the
        operator evaluates has the same boundary types; refused for a plan without motion."""
        opts = dict(self.bc_options)
        margin = opts.get("release_margin")
        if not (isinstance(margin, str) and margin == "auto"):
            self.release_margin = margin
            return opts
        if all(np.allclose(o.matrix(), np.eye(4)) for o in plan.osteotomies):
            raise ValueError(
                "bc_options release_margin='auto' (twice the plan's largest move) needs "
                "plan= with its motions: one operator has one set of boundary types; got a "
                "plan that moves nothing. Pass plan= or a release_margin in mm")
        grid = apply_plan(self.mesh, plan, self.labels, **{**opts, "release_margin": None})
        code = np.asarray(grid[arrays.BC])
        disp = np.asarray(grid[arrays.BC_DISPLACEMENT], dtype=float)
        moving = (code == arrays.BC_JOINT) | (code == arrays.BC_SLIDING)
        opts["release_margin"] = self.release_margin = 2.0 * float(
            np.linalg.norm(disp[moving], axis=1).max(initial=0.0))
        log.info("plan_response: release_margin='auto' fixed at %.3g mm from the plan given",
                 self.release_margin)
        return opts

    @property
    def skin_response(self):
        if self._skin is None:
            return None
        if self._skin_dense is None:  # made on first use, kept read-only
            dense = self._skin.rows(np.arange(self._skin.n))  # (K, n_skin, 3)
            self._skin_dense = np.ascontiguousarray(np.transpose(dense, (2, 1, 0)))
            self._skin_dense.flags.writeable = False
        return self._skin_dense

    @property
    def skin_operator(self):
        return self._skin

    def astype(self, dtype):
        """A shallow copy whose skin operator is stored as ``dtype`` (e.g. ``float32``)."""
        import copy

        other = copy.copy(self)
        if self._skin is not None:
            other._skin = self._skin.astype(dtype)
            other._skin_dense = None
        return other

    @staticmethod
    def _pivots(cut, plan):
        bone = np.asarray(cut[arrays.BONE])
        return {o.segment_id: arrays.voxel_points(cut, np.flatnonzero(bone == o.segment_id)).mean(axis=0)
                for o in plan.osteotomies}

    def _solve_basis(self, ref, solver):
        """Nodal response (3, n, 12 k): one solve per entry of every segment's ``M - I``,
        in coordinates centred on the segment's pivot centroid."""
        pts = np.asarray(ref.points, dtype=float)
        code = np.asarray(ref[arrays.BC])
        disp = np.asarray(ref[arrays.BC_DISPLACEMENT], dtype=float)
        carried = (code == arrays.BC_JOINT) | (code == arrays.BC_SLIDING)
        n, k = len(pts), len(self.segments)
        out = np.zeros((3, n, 12 * k))
        with warnings.catch_warnings():  # unit basis fields, not motions: no solution checks
            warnings.simplefilter("ignore", SolutionWarning)
            self._basis_solves(pts, carried, disp, solver, out)
        return out

    def _basis_solves(self, pts, carried, disp, solver, out):
        n = len(pts)
        for s, sid in enumerate(self.segments):
            shift = self._probe.osteotomies[s].matrix()[:3, 3]
            mine = carried & np.isclose(disp, shift).all(axis=1)  # the probe's shift
            x = pts[mine] - self.centroids[sid]
            basis = np.column_stack([x, np.ones(len(x))])  # (m, 4)
            for i in range(3):
                for j in range(4):
                    d = np.zeros((n, 3))
                    d[mine, i] = basis[:, j]
                    out[:, :, 12 * s + 4 * i + j] = solver.solve(d, checks=False).T

    def _dtype(self, dtype):
        if dtype != "auto":
            return np.dtype(dtype)
        self.float32_error = self._skin.float32_error(len(self.segments))
        return np.dtype(np.float32 if self.float32_error <= FLOAT32_TOLERANCE else np.float64)

    # ------------------------------------------------------------------ parameters
    def parameters(self, plan):
        """The parameter vector ``a`` (12 per segment) of ``plan``, or None when the plan
        needs other boundary-condition types (a full solve)."""
        if not isinstance(plan, Plan):
            raise TypeError(f"plan must be a pvcmf.Plan, got {type(plan).__name__}")
        cuts = {o.segment_id: o.cut for o in self.template.osteotomies}
        moved = {o.segment_id for o in plan.osteotomies}
        subset_ok = (self.bc_options.get("fix_unmoved_bone", False)
                     and self.bc_options.get("joint", True)
                     and not any(cuts.values()))
        if not moved <= set(cuts) or (moved != set(cuts) and not subset_ok):
            return None
        if any(o.cut != cuts[o.segment_id] for o in plan.osteotomies):
            return None
        a = np.zeros(12 * len(self.segments))
        if plan.axes not in self._axes:  # the plan's directions in the image, once per kind
            self._axes[plan.axes] = plan_axes(self.labels, plan)
        for o in plan.osteotomies:
            s = self.segments.index(o.segment_id)
            c = self.centroids[o.segment_id]
            M = o.matrix(c, axes=self._axes[plan.axes])
            A = M[:3, :] - np.eye(4)[:3, :]
            A[:, 3] = A[:, :3] @ c + A[:, 3]  # centred: x = (x - c) + c
            a[12 * s:12 * s + 12] = A.ravel()
        return a

    def _full(self, plan, skin):
        warnings.warn("plan_response: the plan needs boundary conditions the operator "
                      "cannot express (other moved segments or cut planes); full solve",
                      PlanResponseWarning, stacklevel=3)
        from . import solver as _solver

        grid = apply_plan(self.mesh, plan, self.labels, **self.bc_options)
        return np.asarray(_solver.solve(grid, **self.solver_options)[arrays.DISPLACEMENT])

    # ------------------------------------------------------------------ predictions
    def predict_displacement(self, plan, out=None):
        """Skin displacement ``(n_skin, 3)`` (mm) of ``plan``.

        ``out``: a C-contiguous float64 ``(n_skin, 3)`` array written in place (and
        returned), e.g. to predict many plans without allocating."""
        if self._skin is None:
            raise ValueError("plan_response was built without skin=: no skin to predict")
        n = len(self.modelled)
        zeroed = out is None
        if zeroed:
            out = np.zeros((n, 3))  # fresh pages are zero already: no fill
        elif (not isinstance(out, np.ndarray) or out.shape != (n, 3) or out.dtype != np.float64
                or not out.flags.c_contiguous):
            raise ValueError(f"out must be a C-contiguous float64 array of shape ({n}, 3), "
                             f"got {getattr(out, 'dtype', type(out).__name__)} "
                             f"{getattr(out, 'shape', '')}")
        dest = np.asarray(out).reshape(-1)  # plain flat view: no VTK bookkeeping per write
        a = self.parameters(plan)
        if a is None:
            u = self._full(plan, self.skin)
            dest[:] = (transfer_operator(self.mesh, self.skin) @ u).ravel()
            return out
        self._skin.apply(a, dest, self.threads, zeroed=zeroed)
        return out

    def predict(self, plan, out=None):
        """The predicted skin: a copy of ``skin`` moved by the plan, with point array
        ``displacement`` (mm).

        ``out``: a surface returned by an earlier ``predict`` of this operator, updated
        in place (points and ``displacement``) and returned instead of a new copy.

        A new surface has its own points and data arrays and shares only the cell
        connectivity of the operator's own copy of ``skin`` (not the input): pyvista never
        writes into a connectivity array in place, so one result cannot change another;
        editing cells through VTK's low-level calls (``ReplaceCellAtId``) would."""
        if out is None:
            return self._new_surface(self.predict_displacement(plan))
        if not isinstance(out, pv.DataSet) or out.n_points != self.skin.n_points:
            raise ValueError(f"out must be a surface of {self.skin.n_points} points returned by "
                             f"predict, got {type(out).__name__}")
        disp = out.point_data.get(arrays.DISPLACEMENT)
        if disp is None or disp.dtype != np.float64 or not disp.flags.c_contiguous:
            out.point_data[arrays.DISPLACEMENT] = np.zeros((out.n_points, 3))
            disp = out.point_data[arrays.DISPLACEMENT]
        self.predict_displacement(plan, out=disp)
        pts = out.points
        if pts.dtype != np.float64:
            out.points = np.asarray(pts, dtype=float)
            pts = out.points
        np.add(self._skin_points, np.asarray(disp), out=np.asarray(pts))
        out.GetPoints().Modified()
        out.GetPointData().GetArray(arrays.DISPLACEMENT).Modified()
        out.Modified()
        return out

    def _new_surface(self, u):
        """The skin moved by ``u``: own points, own copies of the skin's data arrays,
        connectivity shared with the operator's copy of the skin."""
        tpl = getattr(self, "_template_surface", None)
        if tpl is None:
            tpl = self._template_surface = self.skin.copy(deep=True)
        if not hasattr(tpl, "SetPoints"):  # implicit points (image data): a full copy
            result = tpl.copy(deep=True)
            result.point_data[arrays.DISPLACEMENT] = u
            return result
        result = type(tpl)()
        result.ShallowCopy(tpl)
        for own, src in ((result.GetPointData(), tpl.GetPointData()),
                         (result.GetCellData(), tpl.GetCellData()),
                         (result.GetFieldData(), tpl.GetFieldData())):
            if src.GetNumberOfArrays():
                own.DeepCopy(src)
        result.SetPoints(pv.vtk_points(self._skin_points + u, deep=False))
        result.point_data[arrays.DISPLACEMENT] = u
        return result

    @property
    def _skin_points(self):
        if getattr(self, "_x0", None) is None:
            self._x0 = np.asarray(self.skin.points, dtype=float).copy()
        return self._x0

    def predict_nodes(self, plan):
        """Displacement ``(len(surface_ids), 3)`` of the mesh's surface nodes."""
        a = self.parameters(plan)
        if a is None:
            return self._full(plan, None)[self.surface_ids]
        return (self._surface @ a).reshape(-1, 3)

    def predict_mesh(self, plan):
        """Displacement ``(n_points, 3)`` of every mesh node."""
        a = self.parameters(plan)
        if a is None:
            return self._full(plan, None)
        return np.stack([self.nodal[c] @ a for c in range(3)], axis=1)

    def statistics(self, plans, chunk=256, modelled=True):
        """Per plan: max, mean and RMS of the skin's ``|displacement|`` (n_plans, 3), in
        chunks of ``chunk`` plans, each a product over blocks of skin points reduced block by
        block (plans needing a full solve are solved one by one).

        ``modelled=True`` takes the statistics over the modelled skin only (points within
        the transfer's band of the mesh, :data:`pvcmf.arrays.SKIN_MODELLED`) off the scan's
        cuts (the skin's ``arrays.SKIN_CUT`` where it has one: the scan's edge, not the
        patient's skin); otherwise over every skin point (the unreached ones count as
        zero)."""
        if self._skin is None:
            raise ValueError("plan_response was built without skin=: no skin statistics")
        judged = self.modelled & ~cut_points(self.skin)
        count = max(int(judged.sum()), 1) if modelled else len(self.modelled)
        select = judged if modelled else None
        params = [self.parameters(p) for p in plans]
        out = np.zeros((len(plans), 3))
        fast = [i for i, a in enumerate(params) if a is not None]
        for start in range(0, len(fast), chunk):
            idx = fast[start:start + chunk]
            A = np.stack([params[i] for i in idx], axis=1)
            peak, total, total_sq = (np.zeros(len(idx)) for _ in range(3))
            with _one_thread(self.threads):
                for ids, U in self._skin.blocks(A):  # U: (points, 3, plans)
                    sq = np.einsum("ncp,ncp->np", U, U)
                    if select is not None:
                        sq[~select[ids]] = 0.0  # not counted: adds nothing, max >= 0
                    mag = np.sqrt(sq)
                    np.maximum(peak, mag.max(axis=0, initial=0.0), out=peak)
                    total += mag.sum(axis=0)
                    total_sq += sq.sum(axis=0)
            out[idx] = np.column_stack([peak, total / count, np.sqrt(total_sq / count)])
        for i, a in enumerate(params):
            if a is None:
                u = self.predict_displacement(plans[i])
                mag = np.linalg.norm(u[judged] if modelled else u, axis=1)
                if mag.size:
                    out[i] = mag.max(), mag.mean(), np.sqrt((mag ** 2).mean())
        return out

    def displacements(self, plans, points=None, chunk=256):
        """Skin displacement of many plans at once: ``(n_plans, n_points, 3)`` (mm).

        One batched matrix product per ``chunk`` plans (plans needing a full solve are
        solved one by one, with a :class:`PlanResponseWarning`).

        Parameters
        ----------
        plans : sequence of pvcmf.Plan
        points : array_like of int, optional
            Skin point ids (default: every skin point).
        chunk : int, default 256
            Plans per matrix product.
        """
        if self._skin is None:
            raise ValueError("plan_response was built without skin=: no skin to predict")
        n = len(self.modelled)
        ids = np.arange(n) if points is None else np.asarray(points, dtype=np.int64)
        if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= n)):
            raise ValueError(f"points must be skin point ids in [0, {n}), got {points!r}")
        K = self._skin.K
        R = self._skin.rows(ids).reshape(K, -1)  # (K, 3 ids)
        params = [self.parameters(p) for p in plans]
        out = np.zeros((len(plans), ids.size, 3))
        fast = [i for i, a in enumerate(params) if a is not None]
        for start in range(0, len(fast), chunk):
            idx = fast[start:start + chunk]
            A = np.stack([params[i] for i in idx], axis=0).astype(R.dtype)
            with _one_thread(self.threads):
                out[idx] = (A @ R).reshape(len(idx), ids.size, 3)
        for i, a in enumerate(params):
            if a is None:
                out[i] = self.predict_displacement(plans[i])[ids]
        return out
