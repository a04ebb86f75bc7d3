"""Plan response operator: the predicted skin of any surgical plan as one small product.

A plan enters the linear MTM only through prescribed displacements: a joint node ``x`` of a
segment moved by the rigid map ``M`` is displaced by ``(M[:3, :3] - I) x + M[:3, 3]``, and a
sliding node's prescribed normal part is the normal component of the same vector. Both are
linear in the twelve numbers ``A = (M - I)[:3, :]`` of every moved segment, so the nodal
displacement is ``u = R a`` with ``a`` the stacked ``A``'s, and the skin displacement is
``T R a`` with ``T`` the mesh -> skin transfer (:func:`pvcmf.filters.surface_mapping.
transfer_operator`). :func:`plan_response` builds ``R`` with one factorisation
(:class:`pvcmf.mtm.Solver`) and twelve solves per segment, for boundary conditions whose
*types* match those of the plans it will see (same moved segments, same cut planes);
:class:`PlanResponse` folds ``T`` in and predicts a plan by one dense matrix product. A plan
whose boundary-condition types differ (another set of moved segments when unmoved bone is
free, other cut planes) is predicted by a full ``apply_plan`` + solve, with a warning.

Coordinates are centred on each segment's pivot centroid, so the columns have the size of
the face and ``float32`` storage keeps the product within about a micrometre.
Delegates to :func:`pvcmf.filters.apply_plan`, :class:`pvcmf.mtm.Solver` and numpy.
"""

from __future__ import annotations

import logging
import warnings

import numpy as np
import pyvista as pv

from .. import arrays
from ..filters.boundary_conditions import apply_plan
from ..filters.osteotomy import cut_bones
from ..filters.surface_mapping import transfer_operator
from ..plan import MOVABLE_SEGMENTS, Osteotomy, Plan
from ..progress import Progress
from .solver import Solver

log = logging.getLogger(__name__)

__all__ = ["PlanResponse", "plan_response", "PlanResponseWarning"]


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
        Segments and cut planes of the plans to come (its motions are ignored). Default:
        every movable segment the ``bone`` label holds, without cut planes.
    dtype : {'auto', 'float32', 'float64'}
        Storage of the skin operator; ``'auto'`` keeps float32 when its rounding stays
        below 1e-6 mm for rotations up to 30 degrees and 20 mm translations.
    bc_options : dict, optional
        Keyword arguments of :func:`pvcmf.filters.apply_plan` (e.g. ``fix_unmoved_bone``).
    solver_options : dict, optional
        Keyword arguments of :class:`pvcmf.mtm.Solver`.
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
    return PlanResponse(mesh, labels, skin=skin, plan=_template(labels, plan), dtype=dtype,
                        bc_options=dict(bc_options or {}), solver_options=dict(solver_options or {}),
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
    surface_ids : ndarray
        The mesh's boundary nodes (:meth:`predict_nodes`).
    timings : dict
        Seconds of ``bc`` (apply_plan), ``factor``, ``solves``, ``transfer``.
    """

    def __init__(self, mesh, labels, *, skin, plan, dtype, bc_options, solver_options,
                 progress_bar):
        import time

        from ..filters.boundary_conditions import boundary_points

        self.mesh, self.labels, self.skin, self.template = mesh, labels, skin, plan
        self.bc_options, self.solver_options = bc_options, solver_options
        self.timings = {}
        with Progress(total=4, desc="plan_response", enabled=progress_bar, logger=log) as bar:
            t = time.perf_counter()
            cut = cut_bones(labels, plan)
            self.centroids = {s: np.asarray(m, float) for s, m in self._pivots(cut, plan).items()}
            probe = Plan(tuple(Osteotomy(o.segment, translation=tuple(np.eye(3)[i]), cut=o.cut)
                               for i, o in enumerate(plan.osteotomies)))
            self._probe = probe
            ref = apply_plan(mesh, probe, labels, **bc_options)
            self.segments = tuple(o.segment_id for o in plan.osteotomies)
            self.timings["bc"] = time.perf_counter() - t
            bar.step("boundary conditions")
            t = time.perf_counter()
            solver = Solver(ref, **solver_options)
            self.timings["factor"] = time.perf_counter() - t
            bar.step("factorised")
            t = time.perf_counter()
            self.nodal = self._solve_basis(ref, solver)
            self.timings["solves"] = time.perf_counter() - t
            bar.step(f"{self.nodal.shape[2]} solves")
            t = time.perf_counter()
            self.surface_ids = boundary_points(mesh)
            self.skin_response = None
            if skin is not None:
                T = transfer_operator(mesh, skin)
                R = np.stack([np.asarray(T @ self.nodal[c]) for c in range(3)])
                self.skin_response = R.astype(self._dtype(R, dtype))
            self._surface = np.ascontiguousarray(self.nodal[:, self.surface_ids])
            self.timings["transfer"] = time.perf_counter() - t
            bar.step("transfer folded in")
        self._bc_types = np.asarray(ref[arrays.BC]).copy()

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
        for s, sid in enumerate(self.segments):
            shift = self._probe.osteotomies[s].matrix()[:3, 3]
            mine = carried & np.isclose(disp, shift).all(axis=1)  # the probe's shift
            x = pts[mine] - self.centroids[sid]
            basis = np.column_stack([x, np.ones(len(x))])  # (m, 4)
            for i in range(3):
                for j in range(4):
                    d = np.zeros((n, 3))
                    d[mine, i] = basis[:, j]
                    out[:, :, 12 * s + 4 * i + j] = solver.solve(d).T
        return out

    def _dtype(self, R, dtype):
        if dtype != "auto":
            return np.dtype(dtype)
        # |a| <= 0.5 for the rotation part (30 deg), 20 mm for the centroid shift
        scale = np.tile(np.r_[0.5, 0.5, 0.5, 20.0], 3 * len(self.segments))
        err = np.finfo(np.float32).eps * (np.abs(R) @ scale).max() * 2
        return np.dtype(np.float32 if err <= 1e-6 else np.float64)

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
        for o in plan.osteotomies:
            s = self.segments.index(o.segment_id)
            c = self.centroids[o.segment_id]
            M = o.matrix(c)
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
    def predict_displacement(self, plan):
        """Skin displacement ``(n_skin, 3)`` of ``plan``."""
        if self.skin_response is None:
            raise ValueError("plan_response was built without skin=: no skin to predict")
        a = self.parameters(plan)
        if a is None:
            u = self._full(plan, self.skin)
            T = transfer_operator(self.mesh, self.skin)
            return np.asarray(T @ u)
        R = self.skin_response
        a = a.astype(R.dtype)
        return np.stack([R[0] @ a, R[1] @ a, R[2] @ a], axis=1).astype(float)

    def predict(self, plan):
        """The predicted skin: a copy of ``skin`` moved by the plan, with point array
        ``displacement`` (mm)."""
        u = self.predict_displacement(plan)
        out = self.skin.copy()
        out.point_data[arrays.DISPLACEMENT] = u
        out.points = np.asarray(self.skin.points, dtype=float) + u
        return out

    def predict_nodes(self, plan):
        """Displacement ``(len(surface_ids), 3)`` of the mesh's surface nodes."""
        a = self.parameters(plan)
        if a is None:
            return self._full(plan, None)[self.surface_ids]
        S = self._surface
        return np.stack([S[0] @ a, S[1] @ a, S[2] @ a], axis=1)

    def predict_mesh(self, plan):
        """Displacement ``(n_points, 3)`` of every mesh node."""
        a = self.parameters(plan)
        if a is None:
            return self._full(plan, None)
        return np.stack([self.nodal[c] @ a for c in range(3)], axis=1)

    def statistics(self, plans, chunk=64):
        """Per plan: max, mean and RMS of the skin's ``|displacement|`` (n_plans, 3), in
        chunks of matrix products (plans needing a full solve are solved one by one)."""
        R = self.skin_response
        if R is None:
            raise ValueError("plan_response was built without skin=: no skin statistics")
        params = [self.parameters(p) for p in plans]
        out = np.zeros((len(plans), 3))
        fast = [i for i, a in enumerate(params) if a is not None]
        for start in range(0, len(fast), chunk):
            idx = fast[start:start + chunk]
            A = np.stack([params[i] for i in idx], axis=1).astype(R.dtype)
            sq = sum((R[c] @ A) ** 2 for c in range(3))
            mag = np.sqrt(sq)
            out[idx] = np.column_stack([mag.max(axis=0), mag.mean(axis=0),
                                        np.sqrt(sq.mean(axis=0))])
        for i, a in enumerate(params):
            if a is None:
                mag = np.linalg.norm(self.predict_displacement(plans[i]), axis=1)
                out[i] = mag.max(), mag.mean(), np.sqrt((mag ** 2).mean())
        return out
