"""Virtual post-operative truth: a richer finite-element model than the one being judged.

No public pair of pre/post-operative scans exists, so pvcmf makes the post-operative face
of its virtual patients with a model that is deliberately *not* the MTM:

* large deformation: compressible neo-Hookean,
  ``W = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2``, nearly incompressible at the
  tissue's Poisson ratios (``mu``, ``lambda`` per element from ``E_cross`` and ``nu``);
* fibre reinforcement: ``+ k/2 (I4 - 1)^2`` with ``I4 = a.C a`` along the element's fibre
  ``a`` and ``k = max(E_fiber - E_cross, 0)`` (zero for Table I, where muscle is softer
  along its fibres than across: then the muscle is isotropic in this model);
* quadratic (P2) elements on the tetrahedral mesh (and the study meshes several times
  finer than the MTM);
* boundary conditions from the plan (``apply_plan``): every fixed and joint node
  prescribed (its vertex dofs, as the MTM prescribes them; with P2 also the edge dofs of
  the boundary faces whose three nodes are all prescribed, by the linear interpolant of the
  data), sliding teeth contact as a penalty on the normal displacement over the sliding
  faces, tangential motion free; where the prescribed data *alone* would invert or crush an
  element (all four nodes prescribed, volume ratio below ``release_below``: a fixed node
  one element, 10-30 mm, from joint nodes the plan moves 9-12 mm), the odd node of that
  element is released (left free) and reported (:func:`_released_nodes`);
* load stepping: each load step starts from a linearised predictor (the tangent response
  to the step's boundary increment, from the last converged state: the first one is the
  linear-elastic solution), then Newton's method with a backtracking energy line search
  that rejects inverted elements; a step that fails is halved, and one that still does
  not converge raises.

Solved by NGSolve (``pip install pvcmf[reference]``), not by pvcmf's MTM code: the mesh
is handed to Netgen (``netgen.meshing.Mesh.AddPoints/AddElements``), the energy to an
NGSolve ``BilinearForm`` ``Variation`` (energy, residual and Hessian) with NGSolve's
sparse direct solvers inside a damped Newton loop.
:func:`truth_grid` builds the whole truth for a virtual patient (its true labels, a fine
conforming mesh, this model) and caches the solved grid on disk under a hash of the
solver's input grid, options and code (:func:`grid_hash`); :func:`postop_skin` moves the
dense skin with it (:func:`pvcmf.postop.postop_ct` warps the CT with it).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import socket
import time
from pathlib import Path

import numpy as np
import pyvista as pv

from . import arrays

log = logging.getLogger(__name__)

#: bumped when the model changes, so cached truths are recomputed
MODEL_VERSION = "2"  # 2: every fixed/joint vertex prescribed, crushing data released


def _ngsolve():
    try:
        import netgen.meshing as ngm
        import ngsolve as ngs
    except ImportError as err:  # pragma: no cover - depends on the optional extra
        raise ImportError(
            "pvcmf.reference needs NGSolve: pip install 'pvcmf[reference]' (or ngsolve)"
        ) from err
    return ngm, ngs


def _boundary_faces(grid):
    surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface").triangulate()
    pid = np.asarray(surf.point_data["vtkOriginalPointIds"], dtype=np.int64)
    return pid[surf.faces.reshape(-1, 4)[:, 1:]]


def _netgen_mesh(ngm, points, tets, faces, face_region):
    """Netgen mesh of the tetrahedra with boundary faces in regions 1 dirichlet,
    2 sliding, 3 free (all faces added at once, no Python loop over elements)."""
    mesh = ngm.Mesh(dim=3)
    mesh.AddPoints(np.ascontiguousarray(points, dtype=np.float64))
    names = ("dirichlet", "sliding", "free")
    for k, name in enumerate(names, start=1):
        mesh.Add(ngm.FaceDescriptor(surfnr=k, domin=1, bc=k))
        mesh.SetBCName(k - 1, name)
    mesh.AddElements(dim=3, index=1, data=np.ascontiguousarray(tets, dtype=np.int32), base=0)
    for k in (1, 2, 3):
        sel = faces[face_region == k]
        if len(sel):
            mesh.AddElements(dim=2, index=k, data=np.ascontiguousarray(sel, dtype=np.int32),
                             base=0)
    return mesh


def _released_nodes(points, tets, prescribed, g, ratio):
    """Prescribed nodes to release so that no element's prescribed data inverts or crushes it.

    An element whose four nodes are all prescribed is deformed by the data alone; where
    that maps it to less than ``ratio`` of its volume (signed: below 0 it is inverted), no
    solution of a large-deformation model exists (``ln J`` is undefined; P2 can only fold
    the element by its free edge dofs). Releases, element by element, the node whose
    prescribed displacement differs most from the mean of the other three (the fixed node
    among moved ones, or the moved one among fixed ones), and repeats until no such element
    is left (each round releases at least one node). Returns a boolean point mask."""
    def volumes(x):
        q = x[tets]
        return np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]),
                         q[:, 3] - q[:, 0])

    v0 = volumes(points)
    v0 = np.where(v0 == 0, np.finfo(float).tiny, v0)
    crushed = volumes(points + g) / v0 < ratio
    prescribed = prescribed.copy()
    released = np.zeros(len(points), dtype=bool)
    while True:  # a few rounds, each vectorised over the elements
        bad = tets[crushed & prescribed[tets].all(axis=1)]
        if not len(bad):
            return released
        d = g[bad]  # (k, 4, 3)
        dev = np.linalg.norm(d - (d.sum(axis=1, keepdims=True) - d) / 3, axis=2)
        odd = bad[np.arange(len(bad)), np.argmax(dev, axis=1)]
        released[odd] = True
        prescribed[odd] = False


class _Linear:
    """The Newton systems' linear solver, with wall-time bookkeeping.

    ``inverse`` names an NGSolve sparse direct solver ("sparsecholesky", "pardiso",
    "umfpack"). The factorisation is the expensive part (P2 in 3-D: its cost grows about
    as the square of the dofs), so with ``reuse`` a later system is solved by conjugate
    gradients preconditioned with the last factor (the Hessians of successive Newton
    iterates differ little), and refactored only when that needs more than ``max_cg``
    iterations."""

    def __init__(self, ngs, form, freedofs, inverse, reuse=True, max_cg=25, cg_tol=1e-8):
        self.ngs, self.form, self.freedofs, self.inverse = ngs, form, freedofs, inverse
        self.reuse, self.max_cg, self.cg_tol = reuse, max_cg, cg_tol
        self.times = {"energy": 0.0, "assemble": 0.0, "factor": 0.0, "solve": 0.0}
        self.factorizations = self.solves = self.cg_iterations = 0
        self.factor = None

    def timed(self, key, fn, *args):
        t = time.perf_counter()
        out = fn(*args)
        self.times[key] += time.perf_counter() - t
        return out

    def linearize(self, x):
        self.timed("assemble", self.form.AssembleLinearization, x)
        self.fresh = False

    def _factorize(self):
        self.factor = self.timed("factor", self.form.mat.Inverse, self.freedofs,
                                 self.inverse)
        self.factorizations += 1
        self.fresh = True

    def solve(self, rhs, out):
        """out = K^-1 rhs on the free dofs (zero on the others), K the last linearisation."""
        self.solves += 1
        if self.factor is not None and self.reuse and not self.fresh:
            from ngsolve.krylovspace import CGSolver

            t = time.perf_counter()
            cg = CGSolver(self.form.mat, self.factor, tol=self.cg_tol, maxiter=self.max_cg)
            out.data = cg * rhs
            self.times["solve"] += time.perf_counter() - t
            self.cg_iterations += cg.iterations
            if cg.iterations < self.max_cg and np.all(np.isfinite(out.FV().NumPy())):
                return
            log.debug("reference: CG with the old factor needed > %d iterations: refactor",
                      self.max_cg)
        if not self.fresh:
            self._factorize()
        t = time.perf_counter()
        out.data = self.factor * rhs
        self.times["solve"] += time.perf_counter() - t


def _predictor(ngs, form, x, step, linear):
    """Linearised load-step predictor: from the converged state ``x`` of the last load,
    move the Dirichlet dofs by ``step`` (a vector that is zero on the free dofs) and the
    free dofs by the tangent response ``-K^-1 (r(x) + K step)``. Returns False when the
    predicted state inverts an element (non-finite energy)."""
    res = x.CreateVector()
    du = x.CreateVector()
    linear.linearize(x)
    form.Apply(x, res)
    res.data += form.mat * step
    linear.solve(res, du)
    trial = x.CreateVector()
    trial.data = x + step - du
    if not np.isfinite(linear.timed("energy", form.Energy, trial)):
        return False
    x.data = trial
    return True


def _damped_newton(ngs, form, gfu, maxerr, maxit, linear):
    """Newton's method on the energy with a backtracking line search that also rejects
    non-finite energies (inverted elements: ln J undefined). Returns (status, iterations),
    status 0 when the energy-norm size of the update fell below ``maxerr``."""
    x = gfu.vec
    res = x.CreateVector()
    du = x.CreateVector()
    trial = x.CreateVector()
    for it in range(1, maxit + 1):  # Newton iterations, each one sparse factorisation
        energy = linear.timed("energy", form.Energy, x)
        form.Apply(x, res)
        linear.linearize(x)
        linear.solve(res, du)
        err = float(np.sqrt(abs(ngs.InnerProduct(du, res))))
        if not np.isfinite(err):
            return 1, it
        if err < maxerr:
            return 0, it
        alpha = 1.0
        # backtracking down to 2**-20: a smaller step makes no progress (seen at 2 mm: the
        # same |du| for 20+ iterations at steps of 7e-9, an element at the edge of
        # inversion blocking the direction), so the load step is halved at once instead
        for _ in range(21):
            trial.data = x - alpha * du
            new = linear.timed("energy", form.Energy, trial)
            if np.isfinite(new) and new <= energy + 1e-12 * abs(energy):
                break
            alpha /= 2
        else:
            return 1, it
        log.debug("reference: Newton %d, |du| %.3g (tol %.3g), step %.3g", it, err, maxerr,
                  alpha)
        x.data = trial
    return 1, maxit


def solve_reference(grid, *, order=2, steps=4, penalty=1e3, tol=1e-6, max_newton=30,
                    inverse="sparsecholesky", reuse_factor=False, threads=None,
                    predictor="tangent", release_below=0.2, progress_bar=False):
    """Large-deformation neo-Hookean solve of a planned tetrahedral grid with NGSolve.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with point arrays ``bc``, ``bc_displacement`` (and ``bc_normal``
        where there are sliding nodes) from ``apply_plan``, and cell arrays ``E_cross`` and
        ``nu`` (``E_fiber`` and ``fiber`` optional) from ``assign_materials``.
    order : int, default 2
        Polynomial order of the elements (2: quadratic).
    steps : int, default 4
        Load steps (the prescribed displacements are ramped linearly; a step whose Newton
        solve fails is halved, up to 6 times, and doubled back after each success).
    penalty : float, default 1e3
        Sliding-contact penalty, times the largest stiffness over the mean edge length.
    tol : float, default 1e-6
        Newton tolerance, relative: NGSolve's energy-norm size of the update must fall below
        ``tol * sqrt(W0)`` with ``W0 = max(E) * volume * (max |bc_displacement| / size)^2``
        the energy scale of the problem (an absolute tolerance is unreachable by round-off
        on a large, stiff mesh).
    max_newton : int, default 30
        Newton iterations per step.
    inverse : str, default 'sparsecholesky'
        NGSolve direct solver ("sparsecholesky", "pardiso", "umfpack"; measured on a 30k-tet
        patient, one P2 Hessian: 5.7 / 19 / 41 s CPU).
    reuse_factor : bool, default False
        Solve a Newton system by conjugate gradients preconditioned with the last
        factorisation, refactoring only when that takes more than 25 iterations (False:
        factorise every Newton iteration). Same converged answer; on the virtual patients
        the Hessian changes too much between iterates (CG rarely converges in 25), so it
        does not pay there.
    predictor : {'tangent', 'proportional'}, default 'tangent'
        Start of each load step: the linearised response to the step's boundary increment,
        or (the first version, kept for comparison) the last solution scaled with the
        boundary moved alone (it puts the whole step on the first layer of elements:
        measured on virtual patient 1, 3 mm, 4000 tetrahedra, see
        ``benchmarks/reference.py``).
    release_below : float or None, default 0.2
        Volume ratio in [0, 1): an element whose four nodes are all fixed/joint and whose
        prescribed displacements alone take it below this share of its volume (or invert
        it) has its odd node released (left free; :func:`_released_nodes`), because no
        large-deformation solution exists otherwise (0: release only where the data
        inverts an element; None: never). The released nodes are listed in the result's
        field array ``reference_released`` and logged as a warning.
    threads : bool, optional
        Assemble and factorise inside ``ngsolve.TaskManager()`` (all cores). Default: only
        when the machine is idle (1-minute load below half the cores): NGSolve's worker
        threads spin while they wait, which on a busy machine doubled the CPU time of a
        solve without making it faster.
    progress_bar : bool, default False
        Log each load step at INFO level.

    Returns
    -------
    pyvista.UnstructuredGrid
        Copy of ``grid`` with point array ``arrays.DISPLACEMENT`` (the P2 solution at the
        vertices, mm) and field arrays ``reference_solver`` (dofs, Newton iterations,
        factorisations, seconds), ``reference_released`` (ids of the fixed/joint points
        left free, see ``release_below``; usually empty) and ``reference_folded`` (ids of
        the cells that the vertex displacements, i.e. the linear interpolant used to warp
        the CT and the skin, invert; P2 elements can fold there by their edge dofs while
        the quadratic solution stays valid at the quadrature points).

    Raises
    ------
    ImportError
        NGSolve is not installed.
    ValueError
        Missing arrays, or a grid that is not all tetrahedra.
    RuntimeError
        Newton did not converge even after halving the load step 6 times.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf import arrays
    >>> from pvcmf.reference import solve_reference
    >>> g = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid().triangulate()
    >>> g[arrays.BC] = np.where(np.isin(g.points, [0, 2]).any(1), arrays.BC_JOINT, 0).astype(np.int8)
    >>> g[arrays.BC_DISPLACEMENT] = 0.1 * g.points
    >>> g.cell_data[arrays.E_CROSS] = np.full(g.n_cells, 0.003)
    >>> g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    >>> u = solve_reference(g)[arrays.DISPLACEMENT]         # doctest: +SKIP
    >>> bool(np.allclose(u, 0.1 * g.points))                # doctest: +SKIP
    True
    """
    ngm, ngs = _ngsolve()

    if release_below is not None and not (
            isinstance(release_below, (int, float)) and 0 <= release_below < 1):
        raise ValueError(
            f"release_below must be a volume ratio in [0, 1) or None, got {release_below!r}")
    if predictor not in ("tangent", "proportional"):
        raise ValueError(f"predictor must be 'tangent' or 'proportional', got {predictor!r}")
    if not isinstance(grid, pv.UnstructuredGrid):
        raise TypeError(f"grid must be a pyvista.UnstructuredGrid, got {type(grid).__name__}")
    cells = grid.cells_dict
    if set(cells) != {pv.CellType.TETRA} or len(cells[pv.CellType.TETRA]) != grid.n_cells:
        raise ValueError("grid must hold linear tetrahedra only")
    bc = arrays.require_array(grid, arrays.BC, "point", dtype="iu", ncomp=1, producer="apply_plan")
    g = arrays.require_array(grid, arrays.BC_DISPLACEMENT, "point", dtype="f", ncomp=3,
                             producer="apply_plan")
    e_cross = arrays.require_array(grid, arrays.E_CROSS, "cell", dtype="f", ncomp=1,
                                   producer="assign_materials")
    nu = arrays.require_array(grid, arrays.NU, "cell", dtype="f", ncomp=1,
                              producer="assign_materials")
    if not (np.all(e_cross > 0) and np.all((nu > -1) & (nu < 0.5))):
        raise ValueError("E_cross must be > 0 and nu in (-1, 0.5) in every cell")
    points = np.asarray(grid.points, dtype=np.float64)
    tets = np.asarray(cells[pv.CellType.TETRA], dtype=np.int64).copy()
    p = points[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]  # positive orientation for Netgen
    faces = _boundary_faces(grid)
    constrained = np.isin(bc, (arrays.BC_FIXED, arrays.BC_JOINT))
    g = np.asarray(g, dtype=np.float64)
    released = (np.zeros(len(points), dtype=bool) if release_below is None else
                _released_nodes(points, tets, constrained, g, float(release_below)))
    if released.any():
        log.warning("reference: %d prescribed nodes released (left free): their elements "
                    "would be inverted or crushed below %.2g of their volume by the prescribed "
                    "data alone (bc codes %s, |bc_displacement| %s mm, around %s mm)",
                    released.sum(), release_below, np.asarray(bc)[released].tolist(),
                    np.round(np.linalg.norm(g[released], axis=1), 1).tolist(),
                    np.round(points[released].mean(axis=0), 1).tolist())
    constrained &= ~released
    sliding = bc == arrays.BC_SLIDING
    region = np.full(len(faces), 3)
    region[(sliding[faces] | constrained[faces]).all(axis=1) & sliding[faces].any(axis=1)] = 2
    region[constrained[faces].all(axis=1)] = 1
    mesh = ngs.Mesh(_netgen_mesh(ngm, points, tets, faces, region))
    if mesh.nv != len(points) or mesh.ne != len(tets):
        raise RuntimeError("Netgen renumbered the mesh; cannot map the solution back")

    # piecewise-constant materials, in cell order
    l2 = ngs.L2(mesh, order=0)

    def cellwise(values):
        f = ngs.GridFunction(l2)
        f.vec.FV().NumPy()[:] = np.asarray(values, dtype=np.float64)
        return f

    e_cross = np.asarray(e_cross, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    mu = cellwise(e_cross / (2 * (1 + nu)))
    lam = cellwise(e_cross * nu / ((1 + nu) * (1 - 2 * nu)))
    k_fib = np.zeros(grid.n_cells)
    fib = np.zeros((grid.n_cells, 3))
    if arrays.E_FIBER in grid.cell_data and arrays.FIBER in grid.cell_data:
        k_fib = np.maximum(np.asarray(grid.cell_data[arrays.E_FIBER], float) - e_cross, 0.0)
        fib = np.asarray(grid.cell_data[arrays.FIBER], float)

    fes = ngs.H1(mesh, order=order, dim=3, dirichlet="dirichlet")
    u = fes.TrialFunction()
    F = ngs.Id(3) + ngs.Grad(u)
    C = F.trans * F
    J = ngs.Det(F)
    energy = mu / 2 * (ngs.Trace(C) - 3 - 2 * ngs.log(J)) + lam / 2 * ngs.log(J) ** 2
    if np.any(k_fib > 0):
        a = ngs.CoefficientFunction(tuple(cellwise(fib[:, i]) for i in range(3)))
        i4 = ngs.InnerProduct(a, C * a)
        energy = energy + cellwise(k_fib) / 2 * (i4 - 1) ** 2
    form = ngs.BilinearForm(fes, symmetric=True)
    form += ngs.Variation(energy.Compile() * ngs.dx)

    # prescribed data as P1 fields (vertex dofs = vertex numbers), ramped by `load`
    p1 = ngs.H1(mesh, order=1, dim=3)
    g_p1 = ngs.GridFunction(p1)
    g_p1.vec.FV().NumPy().reshape(-1, 3)[:] = np.asarray(g, dtype=np.float64)
    load = ngs.Parameter(0.0)
    if np.any(region == 2):
        n = arrays.require_array(grid, arrays.BC_NORMAL, "point", dtype="f", ncomp=3,
                                 producer="apply_plan")
        n_p1 = ngs.GridFunction(p1)
        n_p1.vec.FV().NumPy().reshape(-1, 3)[:] = np.asarray(n, dtype=np.float64)
        edge = np.linalg.norm(p[:, 1] - p[:, 0], axis=1).mean()
        kappa = penalty * float((e_cross / (2 * (1 + nu))).max() + (e_cross * nu / (
            (1 + nu) * (1 - 2 * nu))).max()) / edge
        gap = ngs.InnerProduct(u - load * g_p1, n_p1)
        form += ngs.Variation(kappa / 2 * gap**2 * ngs.ds(definedon=mesh.Boundaries("sliding")))

    gfu = ngs.GridFunction(fes)
    prescribed = ngs.GridFunction(fes)
    prescribed.Set(g_p1, definedon=mesh.Boundaries("dirichlet"))
    # dofs on the dirichlet faces, and the vertex dof of every prescribed node (NGSolve's
    # H1 numbers the vertex dofs first, in vertex order): the nodes the MTM prescribes
    free = np.array(fes.FreeDofs(), dtype=bool)
    free[: mesh.nv][constrained] = False
    freedofs = ngs.BitArray(free)
    fixed = ~free
    pres = prescribed.vec.FV().NumPy().reshape(-1, 3)
    pres[: mesh.nv][constrained] = g[constrained]
    values = gfu.vec.FV().NumPy()
    target = pres[fixed].copy()
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    volume = float(np.abs(vol).sum()) / 6.0
    g_max = float(np.abs(np.asarray(g, dtype=float)).max()) or 1.0
    e_max = float(max(e_cross.max(), k_fib.max()))
    maxerr = tol * np.sqrt(e_max * volume * (g_max / size) ** 2)
    # load stepping: linearised predictor, Newton corrector, halved steps where either fails
    linear = _Linear(ngs, form, freedofs, inverse, reuse=reuse_factor)
    step = gfu.vec.CreateVector()
    step_np = step.FV().NumPy().reshape(-1, 3)
    done, step_size, newton_its = 0.0, 1.0 / steps, 0
    start = time.perf_counter()
    if threads is None:
        threads = os.getloadavg()[0] < 0.5 * (os.cpu_count() or 1)
    with ngs.TaskManager() if threads else contextlib.nullcontext():
        while done < 1.0 - 1e-12:  # a few load steps, each a vectorised Newton solve
            t = min(done + step_size, 1.0)
            saved = values.copy()
            load.Set(t)
            step_np[:] = 0.0
            step_np[fixed] = (t - done) * target
            its = 0
            status = 1
            if predictor == "tangent":
                status = 0 if _predictor(ngs, form, gfu.vec, step, linear) else 1
            if status != 0:  # session 1's: the last solution scaled, the boundary moved
                # alone; also the fallback where the tangent predictor inverts an element
                # (close to a buckled state its linearisation overshoots)
                values[:] = saved * (t / done if done > 0 else 0.0)
                values.reshape(-1, 3)[fixed] = t * target
                status = 0 if np.isfinite(linear.timed("energy", form.Energy, gfu.vec)) else 1
            if status == 0:
                status, its = _damped_newton(ngs, form, gfu, maxerr, max_newton, linear)
                newton_its += its
            if status != 0 or not np.all(np.isfinite(values)):
                values[:] = saved
                if step_size < 1.0 / steps / 2**6:
                    raise RuntimeError(
                        f"reference model: Newton did not converge at load {t:.3g} even with "
                        f"steps of {step_size:.3g} ({its} iterations, tol={tol})"
                    )
                step_size /= 2
                log.info("reference: load step to %.3g failed (%s), halving the step", t,
                         "both predictors invert an element" if its == 0 else "Newton")
                continue
            done = t
            step_size = min(2 * step_size, 1.0 / steps)  # grow back after a success
            (log.info if progress_bar else log.debug)(
                "reference: load %.3g converged in %d Newton iterations", t, its)
    disp = gfu.vec.FV().NumPy().reshape(-1, 3)[: mesh.nv]
    log.info("reference: %d dofs solved in %.1f s: %d Newton iterations, %d linear solves "
             "with %d %s factorisations (%.1f s) and %d CG iterations (solves %.1f s), "
             "assembly %.1f s, energy %.1f s", 3 * fes.ndof, time.perf_counter() - start,
             newton_its, linear.solves, linear.factorizations, inverse,
             linear.times["factor"], linear.cg_iterations, linear.times["solve"],
             linear.times["assemble"], linear.times["energy"])
    out = grid.copy()
    out.point_data[arrays.DISPLACEMENT] = np.array(disp, dtype=np.float64)
    # solver statistics (benchmarks/reference.py): dofs, Newton its, factorisations, s
    out.field_data["reference_solver"] = np.array(
        [3 * fes.ndof, newton_its, linear.factorizations, time.perf_counter() - start])
    # prescribed (fixed/joint) nodes left free by ``release_below``
    out.field_data["reference_released"] = np.flatnonzero(released).astype(np.int64)
    # elements whose vertex displacements (the linear interpolant that postop_ct and
    # postop_skin warp with) invert them: P2 can fold an element by its edge dofs
    q = (points + disp)[tets]
    moved = np.einsum("ij,ij->i", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]),
                      q[:, 3] - q[:, 0])
    folded = np.flatnonzero(moved <= 0)
    if len(folded):
        log.warning("reference: %d elements are inverted by the solution's vertex values "
                    "(linear interpolant), around %s mm", len(folded),
                    np.round(points[tets[folded]].mean(axis=(0, 1)), 1).tolist())
    out.field_data["reference_folded"] = folded.astype(np.int64)
    return out


def _cache_dir(cache_dir):
    if cache_dir is not None:
        return Path(cache_dir)
    return Path(os.environ.get("PVCMF_CACHE_DIR", Path.home() / ".cache" / "pvcmf")) / "reference"


def _lock_is_stale(lock, stale_after):
    """A lock is stale when it is older than ``stale_after`` seconds, or when it was
    written on this host by a process that no longer exists."""
    try:
        age = time.time() - lock.stat().st_mtime
        owner = lock.read_text().split()
    except (FileNotFoundError, OSError):
        return False  # released meanwhile (or unreadable for a moment): not stale
    if age > stale_after:
        return True
    if len(owner) >= 2 and owner[1] == socket.gethostname():
        try:
            os.kill(int(owner[0]), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, ValueError):
            return False
    return False


def cached(path, compute, *, cache=True, stale_after=7200.0, poll=0.5):
    """Read ``path`` if it exists, else compute it once across processes and write it.

    The first caller takes an exclusive lock file ``<path>.lock`` (``os.open`` with
    ``O_CREAT | O_EXCL``, atomic on local and NFSv3+ file systems), computes, writes the
    result atomically (temporary file + ``os.replace``) and releases the lock. Any other
    caller asking for the same ``path`` meanwhile (another process, thread or dask worker)
    waits for the lock to go and then reads the result instead of recomputing. A lock left
    by a crashed caller is broken when its process no longer exists (same host) or when
    it is older than ``stale_after`` seconds; if the holder failed without writing, the
    next waiter computes.

    Parameters
    ----------
    path : path-like
        Cache file (any format ``pyvista.read`` / ``DataObject.save`` know, e.g. ``.vtp``).
    compute : callable
        ``compute() -> pyvista.DataSet``, called at most once per missing entry.
    cache : bool, default True
        False: just ``compute()``, no reading, writing or locking.
    stale_after : float, default 7200
        Seconds after which another process's lock is considered abandoned.
    poll : float, default 0.5
        Seconds between checks while waiting.

    Returns
    -------
    pyvista.DataSet

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import pyvista as pv
    >>> from pvcmf.reference import cached
    >>> path = Path(tempfile.mkdtemp()) / "sphere.vtp"
    >>> cached(path, pv.Sphere).n_points == cached(path, lambda: None).n_points
    True
    """
    if not cache:
        return compute()
    path = Path(path)
    lock = path.with_name(path.name + ".lock")
    path.parent.mkdir(parents=True, exist_ok=True)
    waited = False
    while True:
        if path.exists():
            log.info("reference: cached truth %s%s", path, " (computed by another caller)"
                     if waited else "")
            return pv.read(path)
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if _lock_is_stale(lock, stale_after):
                log.warning("reference: breaking the stale lock %s", lock)
                with contextlib.suppress(FileNotFoundError):
                    lock.unlink()
                continue
            if not waited:
                log.info("reference: %s is being computed by another caller; waiting", path)
            waited = True
            time.sleep(poll)
            continue
        try:
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()} {socket.gethostname()} {time.time():.0f}\n")
            if path.exists():  # written between our check and our lock
                return pv.read(path)
            out = compute()
            tmp = path.with_name(f"{path.stem}.{os.getpid()}.tmp{path.suffix}")
            out.save(tmp)
            os.replace(tmp, path)  # atomic: no half-written cache entry
            return out
        finally:
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()


#: the solver's code, hashed (docstrings and comments left out) into the truth's cache key
_SOLVER_CODE = ("_boundary_faces", "_netgen_mesh", "_released_nodes", "_Linear", "_predictor",
                "_damped_newton", "solve_reference")
_CODE_HASH = []


def solver_code_hash():
    """SHA-256 (16 hex digits) of the truth solver's code, without docstrings or comments.

    The syntax trees (:func:`ast.dump`, no line numbers) of the functions and classes named
    in ``_SOLVER_CODE``: editing how the truth is solved changes the cache key of every
    truth; editing a docstring, a comment or the layout does not.

    Examples
    --------
    >>> from pvcmf.reference import solver_code_hash
    >>> len(solver_code_hash())
    16
    """
    if not _CODE_HASH:
        import ast
        import inspect
        import sys

        module = sys.modules[__name__]
        h = hashlib.sha256()
        for name in _SOLVER_CODE:
            tree = ast.parse(inspect.getsource(getattr(module, name)))
            for node in ast.walk(tree):
                body = getattr(node, "body", None)
                if (isinstance(node, (ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
                        and body and isinstance(body[0], ast.Expr)
                        and isinstance(getattr(body[0], "value", None), ast.Constant)
                        and isinstance(body[0].value.value, str)):
                    node.body = body[1:] or [ast.Pass()]
            h.update(name.encode())
            h.update(ast.dump(tree).encode())
        _CODE_HASH.append(h.hexdigest()[:16])
    return _CODE_HASH[0]


def grid_hash(grid, params=""):
    """Cache key (32 hex digits) of a truth solve: the solver's input grid itself.

    Hashes :data:`MODEL_VERSION`, :func:`solver_code_hash`, ``params`` (the solver's
    options) and the planned grid the solver reads: points, cells, cell types and every
    point and cell array (name, dtype, shape, bytes; ``bc``, ``bc_displacement``,
    ``bc_normal``, ``E_cross``, ``nu``, ``E_fiber``, ``fiber``, labels). So the key follows
    the *result* of the mesher, the osteotomy, the materials and the plan, whatever code
    made them: a mesher change that changes the mesh recomputes the truth, a change that
    leaves the mesh bit-identical (refactoring, documentation) keeps it. Floating-point
    arrays (points included) are hashed quantised to multiples of ``2**-24`` of their
    largest magnitude (~12 nm for a 200 mm head): the mesher's output differs between
    processes by round-off (seen: 1e-14 mm in 3 of 14k coordinates, the solved truths
    identical), which must not change the key (a quantisation boundary falls between two
    such runs with a probability of about 1e-5).

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.reference import grid_hash
    >>> g = pv.ImageData(dimensions=(3, 3, 3)).cast_to_unstructured_grid()
    >>> grid_hash(g) == grid_hash(g.copy()) != grid_hash(g, "order=1")
    True
    """
    def canonical(value):  # floats quantised: see the docstring
        value = np.asarray(value)
        if value.dtype.kind == "f" and value.size:
            scale = float(np.abs(value).max()) * 2.0**-24 or 1.0
            value = np.round(value / scale).astype(np.int64)
        return np.ascontiguousarray(value)

    h = hashlib.sha256(f"{MODEL_VERSION}|{solver_code_hash()}|{params}".encode())
    for data in (grid.points, grid.cells, grid.celltypes):
        h.update(canonical(data).tobytes())
    for kind, store in (("point", grid.point_data), ("cell", grid.cell_data)):
        for name in sorted(store.keys()):
            value = canonical(store[name])
            h.update(f"{kind}|{name}|{value.dtype.str}|{value.shape}".encode())
            h.update(value.tobytes())
    return h.hexdigest()[:32]


def truth_grid(case, *, n_tets=16_000, order=2, steps=4, face_fraction=0.5, cache=True,
               cache_dir=None, progress_bar=False):
    """The solved truth of a virtual patient: its fine planned grid with the displacement.

    The patient's *true* labels (``case.truth``, not a segmentation) are cut by the plan,
    meshed finely with the muscles embedded (``tetrahedralize(conforming=True)`` of the
    anterior ``face_fraction`` of the head), given fibres and Table I materials,
    constrained by ``apply_plan`` (unmoved bone fixed) and solved by
    :func:`solve_reference`. The grid is rebuilt on every call (1-2 s at 2 mm / 16k: the
    mesher is deterministic) and the solution is read from the on-disk cache
    (``PVCMF_CACHE_DIR`` or ``~/.cache/pvcmf``, ``reference/truth_grid_<key>.vtu``) under
    :func:`grid_hash` of that grid, the solver options, :data:`MODEL_VERSION` and the
    solver's code: the key hashes what the solver computes from, not the code of the
    mesher, osteotomy or material filters that made its input (a change there that changes
    the grid changes the key; one that does not keeps the cached truth). Concurrent
    callers (processes, threads, dask workers) asking for the same truth compute it once:
    the others wait on a lock file and read the cache (:func:`cached`). Reading a cached
    truth does not need NGSolve.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient (``truth`` labels and ``plan``).
    n_tets : int, default 16000
        Tetrahedra of the fine mesh (P2 elements: ~75k dofs at 16k, several times the
        ~20k of the MTM's 30k P1 tetrahedra).
    order, steps :
        See :func:`solve_reference`.
    face_fraction : float, default 0.5
        Anterior share of the head that is meshed (as the pipeline).
    cache : bool, default True
        Read / write the on-disk cache.
    cache_dir : path, optional
        Cache folder.
    progress_bar : bool, default False
        Log the steps at INFO level.

    Returns
    -------
    pyvista.UnstructuredGrid
        Planned linear-tetrahedral grid (pre-operative frame) with the point array
        ``arrays.DISPLACEMENT`` (the P2 solution at its vertices, mm), the arrays of
        ``apply_plan`` / ``assign_materials`` and the field array ``reference_solver``.

    Examples
    --------
    >>> import pvcmf                                                  # doctest: +SKIP
    >>> grid = pvcmf.reference.truth_grid(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    return _solved_truth(case, n_tets, order, steps, face_fraction, cache, cache_dir,
                         progress_bar)[1]


def _solved_truth(case, n_tets, order, steps, face_fraction, cache, cache_dir, progress_bar):
    """(cut labels, solved grid) of the truth; the solve cached by :func:`grid_hash`."""
    labels, grid = _truth_grid(case, n_tets, face_fraction, progress_bar)
    key = grid_hash(grid, f"order={order}|steps={steps}")
    path = _cache_dir(cache_dir) / f"truth_grid_{key}.vtu"
    solved = cached(path, lambda: solve_reference(grid, order=order, steps=steps,
                                                  progress_bar=progress_bar), cache=cache)
    return labels, solved


def postop_skin(case, *, n_tets=16_000, order=2, steps=4, face_fraction=0.5, cache=True,
                cache_dir=None, progress_bar=False):
    """The virtual post-operative skin of a virtual patient (the truth of the study).

    The skin of the patient's cut true labels (``extract_skin``) moved by the solved
    truth grid of :func:`truth_grid` (same options; that grid is what is cached on disk,
    the skin is recomputed from it in about a second): linear interpolation inside the
    tetrahedra (VTK probe), the nearest mesh point outside.

    Parameters
    ----------
    case : pvcmf.datasets.Case
        Virtual patient (``truth`` labels and ``plan``).
    n_tets, order, steps, face_fraction, cache, cache_dir :
        See :func:`truth_grid`.
    progress_bar : bool, default False
        Log the steps at INFO level.

    Returns
    -------
    pyvista.PolyData
        Post-operative skin (patient frame) with point array ``arrays.DISPLACEMENT``.

    Examples
    --------
    >>> import pvcmf                                                  # doctest: +SKIP
    >>> truth = pvcmf.reference.postop_skin(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    from . import filters

    labels, solved = _solved_truth(case, n_tets, order, steps, face_fraction, cache,
                                   cache_dir, progress_bar)
    return _skin_of(filters.extract_skin(labels), solved)


def _truth_grid(case, n_tets, face_fraction, progress_bar):
    """The truth's planned grid: true labels cut by the plan, conforming mesh with the
    muscles, fibres, Table I materials, plan boundary conditions."""
    from . import filters
    from .pipeline import drop_floating_parts, face_box

    labels = filters.cut_bones(case.truth, case.plan)
    grid = filters.tetrahedralize(labels, n_tets=n_tets, conforming=True,
                                  roi=face_box(labels, face_fraction), progress_bar=progress_bar)
    if arrays.MUSCLE in grid.cell_data and np.any(grid.cell_data[arrays.MUSCLE]):
        grid = filters.fiber_directions(grid)
        # muscle tissue outside the twelve atlas muscles has no box: a vertical fibre
        # (immaterial for Table I, where this model's fibre term vanishes)
        fib = np.asarray(grid.cell_data[arrays.FIBER]).copy()
        fib[~np.any(fib, axis=1)] = (0.0, 0.0, 1.0)
        grid.cell_data[arrays.FIBER] = fib
    grid = filters.assign_materials(grid)
    grid = drop_floating_parts(filters.apply_plan(grid, case.plan, labels,
                                                  fix_unmoved_bone=True))
    return labels, grid


def _skin_of(skin, post):
    """``skin`` moved by the solved grid ``post``: probed inside, nearest node outside."""
    from scipy.spatial import cKDTree

    probe = skin.sample(post, progress_bar=False)
    disp = np.asarray(probe[arrays.DISPLACEMENT], dtype=np.float64)
    outside = ~np.asarray(probe["vtkValidPointMask"], dtype=bool)
    if outside.any():
        _, idx = cKDTree(post.points).query(skin.points[outside])
        disp[outside] = np.asarray(post[arrays.DISPLACEMENT])[idx]
    out = skin.copy()
    out.clear_data()
    out.points = np.asarray(skin.points, dtype=np.float64) + disp
    out.point_data[arrays.DISPLACEMENT] = disp
    return out
