"""The large-deformation neo-Hookean solve of the virtual post-operative truth (NGSolve).

Model (see :mod:`pvcmf.truth`): compressible neo-Hookean
``W = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2`` with fibre reinforcement
``k/2 (I4 - 1)^2``, quadratic elements, the plan's fixed and joint nodes prescribed,
sliding contact as a penalty, load stepping with a linearised predictor and a damped
Newton corrector. Delegates to NGSolve (``pip install pvcmf[reference]``): the mesh goes
to Netgen (``netgen.meshing.Mesh.AddPoints/AddElements``), the energy to an NGSolve
``BilinearForm`` ``Variation`` (energy, residual and Hessian), the linear systems to
NGSolve's sparse direct solvers.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time

import numpy as np
import pyvista as pv

from .. import arrays
from ..mtm.backends.pardiso import available as pardiso_available
from ..progress import Progress
from .linear import _Linear, cores_free

log = logging.getLogger("pvcmf.reference")

__all__ = ["cores_free", "solve_reference"]


def _ngsolve():
    try:
        import netgen.meshing as ngm
        import ngsolve as ngs
    except ImportError as err:  # pragma: no cover - depends on the optional extra
        raise ImportError(
            "pvcmf.truth needs NGSolve: pip install 'pvcmf[reference]' (or ngsolve)"
        ) from err
    return ngm, ngs


def _boundary_faces(grid):
    surf = grid.extract_surface(pass_pointid=True, algorithm="dataset_surface").triangulate()
    pid = np.asarray(surf.point_data[arrays.ORIGINAL_POINT_IDS], dtype=np.int64)
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
        # backtracking down to 2**-20: below that an element at the edge of inversion
        # blocks the direction, so the load step is halved instead
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
                    inverse=None, reuse_factor=False, threads=None,
                    predictor="tangent", release_below=0.2, law="neo-hookean",
                    materials=None, progress_bar=False):
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
    inverse : str, optional
        NGSolve direct solver ("sparsecholesky", "pardiso", "umfpack"; their timings are in
        the reference benchmark page), or "mkl": MKL PARDISO through
        :class:`pvcmf.mtm.backends.pardiso.Pardiso` (needs pypardiso; the METIS analysis
        once, a numeric factorisation per Newton system, on the cores of ``threads``).
        Default: "mkl" where pypardiso imports, else "sparsecholesky" (the same solution
        to round-off; their costs on a cohort truth: ``benchmarks/truth_solver.py``).
    reuse_factor : bool, default False
        Solve a Newton system by conjugate gradients preconditioned with the last
        factorisation, refactoring only when that takes more than 25 iterations (False:
        factorise every Newton iteration). Same converged answer; it pays only where the
        Hessian changes little between Newton iterates.
    predictor : {'tangent', 'proportional'}, default 'tangent'
        Start of each load step: the linearised response to the step's boundary increment,
        or the last solution scaled with the boundary moved alone (which puts the whole
        step on the first layer of elements; compared in ``benchmarks/reference.py``).
    release_below : float or None, default 0.2
        Volume ratio in [0, 1): an element whose four nodes are all fixed/joint and whose
        prescribed displacements alone take it below this share of its volume (or invert
        it) has its odd node released (left free; :func:`_released_nodes`), because no
        large-deformation solution exists otherwise (0: release only where the data
        inverts an element; None: never). The released nodes are listed in the result's
        field array ``arrays.REFERENCE_RELEASED`` and logged as a warning.
    law : {'neo-hookean', 'linear'}, default 'neo-hookean'
        Strain energy. ``'neo-hookean'``: the truth's model (module docstring).
        ``'linear'``: small-strain linear elasticity
        ``mu eps:eps + lambda/2 tr(eps)^2`` with ``eps = sym(grad u)`` (fibre term
        ``k/2 (2 a.eps a)^2``), the linearisation of the same energy at the undeformed state:
        a control that the tests of the large-deformation behaviour must reject (it is
        not rotation invariant).
    materials : dict, optional
        Isotropic materials as fields of the position, evaluated at the quadrature points
        (``ngsolve.VoxelCoefficient``, trilinear) instead of the cell arrays ``E_cross``
        and ``nu``: ``origin`` and ``end`` (the box's corners, mm) and ``e_cross`` and
        ``nu``, arrays of shape (nz, ny, nx) of samples over that box (x fastest). A
        material that is the same function on every mesh (the cell arrays still set the
        fibre term and the tolerance's scale).
    threads : bool, optional
        Assemble and factorise inside ``ngsolve.TaskManager()`` (all cores; on two cores
        about 1.7 times faster than one). Default: unless the cores are contended
        (:func:`cores_free`), since NGSolve's threads spin while they wait, which costs
        CPU time on a busy machine without a speed-up.
    progress_bar : bool, default False
        Show the load steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        Copy of ``grid`` with point array ``arrays.DISPLACEMENT`` (the P2 solution at the
        vertices, mm) and field arrays ``arrays.REFERENCE_SOLVER`` (dofs, Newton iterations,
        factorisations, seconds), ``arrays.REFERENCE_RELEASED`` (ids of the fixed/joint points
        left free, see ``release_below``; usually empty) and ``arrays.REFERENCE_FOLDED`` (ids of
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
    >>> from pvcmf.truth import solve_reference
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
    inp = _inputs(grid, release_below, predictor)
    if law not in _LAWS:
        raise ValueError(f"law must be one of {_LAWS}, got {law!r}")
    released = _release(inp, release_below)
    if inverse is None:
        inverse = "mkl" if pardiso_available() else "sparsecholesky"
    model = _model(ngm, ngs, inp, order, penalty, law, materials)
    start = time.perf_counter()
    if threads is None:
        threads = cores_free()
    linear = _Linear(ngs, model["form"], model["freedofs"], inverse, reuse=reuse_factor,
                     threads=(os.cpu_count() or 1) if threads else 1)
    with ngs.TaskManager() if threads else contextlib.nullcontext():
        newton_its = _load_steps(ngs, model, linear, steps=steps, tol=tol,
                                 max_newton=max_newton, predictor=predictor,
                                 progress_bar=progress_bar)
    disp = _by_point(model["gfu"].vec.FV().NumPy())[: model["mesh"].nv]
    log.info("reference: %d dofs solved in %.1f s: %d Newton iterations, %d linear solves "
             "with %d %s factorisations (%.1f s) and %d CG iterations (solves %.1f s), "
             "assembly %.1f s, energy %.1f s", len(model["gfu"].vec.FV()),
             time.perf_counter() - start, newton_its, linear.solves, linear.factorizations,
             inverse, linear.times["factor"], linear.cg_iterations, linear.times["solve"],
             linear.times["assemble"], linear.times["energy"])
    stats = [len(model["gfu"].vec.FV()), newton_its, linear.factorizations,
             time.perf_counter() - start]
    out = _result(grid, inp, disp, released, stats)
    if order > 1:
        edges, mid = _midpoint_values(model, inp)
        out.field_data[arrays.REFERENCE_EDGES] = edges
        out.field_data[arrays.REFERENCE_MIDPOINT_DISPLACEMENT] = mid
    return out


#: strain energies of :func:`solve_reference` (``law``)
_LAWS = ("neo-hookean", "linear")


def _by_point(values):
    """A (dofs, 3) view of the flat values of a ``VectorH1`` vector: one scalar space after
    another, each with the vertex dofs first, in vertex order."""
    return values.reshape(3, -1).T


#: polynomial order per element of a ``materials`` field (:func:`_material_fields`)
MATERIAL_ORDER = 2


def _inputs(grid, release_below, predictor):
    """Check the options and the grid; its points, positively oriented tets and arrays."""
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
    e_cross = np.asarray(e_cross, dtype=np.float64)
    k_fib = np.zeros(grid.n_cells)
    fib = np.zeros((grid.n_cells, 3))
    if arrays.E_FIBER in grid.cell_data and arrays.FIBER in grid.cell_data:
        k_fib = np.maximum(np.asarray(grid.cell_data[arrays.E_FIBER], float) - e_cross, 0.0)
        fib = np.asarray(grid.cell_data[arrays.FIBER], float)
    return {"grid": grid, "bc": np.asarray(bc), "g": np.asarray(g, dtype=np.float64),
            "e_cross": e_cross, "nu": np.asarray(nu, dtype=np.float64), "points": points,
            "tets": tets, "p": p, "vol": vol, "k_fib": k_fib, "fib": fib,
            "faces": _boundary_faces(grid),
            "constrained": np.isin(bc, (arrays.BC_FIXED, arrays.BC_JOINT))}


def _release(inp, release_below):
    """Release the prescribed nodes whose data alone crushes an element (in ``inp``)."""
    points, g, bc = inp["points"], inp["g"], inp["bc"]
    released = (np.zeros(len(points), dtype=bool) if release_below is None else
                _released_nodes(points, inp["tets"], inp["constrained"], g,
                                float(release_below)))
    if released.any():
        log.warning("reference: %d prescribed nodes released (left free): their elements "
                    "would be inverted or crushed below %.2g of their volume by the prescribed "
                    "data alone (bc codes %s, |bc_displacement| %s mm, around %s mm)",
                    released.sum(), release_below, bc[released].tolist(),
                    np.round(np.linalg.norm(g[released], axis=1), 1).tolist(),
                    np.round(points[released].mean(axis=0), 1).tolist())
    inp["constrained"] = inp["constrained"] & ~released
    return released


def _model(ngm, ngs, inp, order, penalty, law="neo-hookean", materials=None):
    """The NGSolve mesh, space, energy form and prescribed data of the truth.

    The space is ``VectorH1`` (one scalar H1 space per component): its Hessian is a scalar
    sparse matrix, which MKL PARDISO reads, and which NGSolve's sparse Cholesky factorises
    in about half the time of the same Hessian in ``H1(dim=3)``'s 3x3 blocks."""
    points, tets, faces, constrained = inp["points"], inp["tets"], inp["faces"], inp["constrained"]
    sliding = inp["bc"] == arrays.BC_SLIDING
    region = np.full(len(faces), 3)
    region[(sliding[faces] | constrained[faces]).all(axis=1) & sliding[faces].any(axis=1)] = 2
    region[constrained[faces].all(axis=1)] = 1
    mesh = ngs.Mesh(_netgen_mesh(ngm, points, tets, faces, region))
    if mesh.nv != len(points) or mesh.ne != len(tets):
        raise RuntimeError("Netgen renumbered the mesh; cannot map the solution back")
    l2 = ngs.L2(mesh, order=0)  # piecewise-constant materials, in cell order

    def cellwise(values):
        f = ngs.GridFunction(l2)
        f.vec.FV().NumPy()[:] = np.asarray(values, dtype=np.float64)
        return f

    e_cross, nu, k_fib, fib = inp["e_cross"], inp["nu"], inp["k_fib"], inp["fib"]
    if materials is None:
        mu = cellwise(e_cross / (2 * (1 + nu)))
        lam = cellwise(e_cross * nu / ((1 + nu) * (1 - 2 * nu)))
    else:  # fields of the position, projected onto quadratic polynomials per element
        e_f, nu_f = _material_fields(ngs, mesh, materials)
        mu = e_f / (2 * (1 + nu_f))
        lam = e_f * nu_f / ((1 + nu_f) * (1 - 2 * nu_f))
    fes = ngs.VectorH1(mesh, order=order, dirichlet="dirichlet")
    u = fes.TrialFunction()
    if law == "linear":  # small strain: the control the large-deformation tests reject
        eps = ngs.Sym(ngs.Grad(u))
        energy = mu * ngs.InnerProduct(eps, eps) + lam / 2 * ngs.Trace(eps) ** 2
        stretch = 2 * eps  # linearisation of C - I
    else:
        F = ngs.Id(3) + ngs.Grad(u)
        C = F.trans * F
        J = ngs.Det(F)
        energy = mu / 2 * (ngs.Trace(C) - 3 - 2 * ngs.log(J)) + lam / 2 * ngs.log(J) ** 2
        stretch = C - ngs.Id(3)
    if np.any(k_fib > 0):
        a = ngs.CoefficientFunction(tuple(cellwise(fib[:, i]) for i in range(3)))
        i4m1 = ngs.InnerProduct(a, stretch * a)  # I4 - 1
        energy = energy + cellwise(k_fib) / 2 * i4m1 ** 2
    form = ngs.BilinearForm(fes, symmetric=True)
    form += ngs.Variation(energy.Compile() * ngs.dx)
    # prescribed data as P1 fields (vertex dofs = vertex numbers), ramped by `load`
    p1 = ngs.H1(mesh, order=1, dim=3)
    g_p1 = ngs.GridFunction(p1)
    g_p1.vec.FV().NumPy().reshape(-1, 3)[:] = inp["g"]
    load = ngs.Parameter(0.0)
    if np.any(region == 2):
        n = arrays.require_array(inp["grid"], arrays.BC_NORMAL, "point", dtype="f", ncomp=3,
                                 producer="apply_plan")
        n_p1 = ngs.GridFunction(p1)
        n_p1.vec.FV().NumPy().reshape(-1, 3)[:] = np.asarray(n, dtype=np.float64)
        p = inp["p"]
        edge = np.linalg.norm(p[:, 1] - p[:, 0], axis=1).mean()
        kappa = penalty * float((e_cross / (2 * (1 + nu))).max() + (e_cross * nu / (
            (1 + nu) * (1 - 2 * nu))).max()) / edge
        gap = ngs.InnerProduct(u - load * g_p1, n_p1)
        form += ngs.Variation(kappa / 2 * gap**2 * ngs.ds(definedon=mesh.Boundaries("sliding")))
    gfu = ngs.GridFunction(fes)
    model = {"mesh": mesh, "fes": fes, "form": form, "gfu": gfu, "load": load}
    model.update(_prescribed(ngs, mesh, fes, g_p1, inp))
    return model


def _material_fields(ngs, mesh, materials, order=MATERIAL_ORDER):
    """``E_cross`` and ``nu`` of a ``materials`` field on ``mesh``: the trilinear
    interpolant of the samples (``ngsolve.VoxelCoefficient``), L2-projected onto
    polynomials of ``order`` on each element and clipped to the samples' range (the
    projection is used, not the voxel coefficient itself, whose linearisation in NGSolve's
    symbolic energy differs from its residual)."""
    out = []
    box = tuple(map(float, materials["origin"])), tuple(map(float, materials["end"]))
    space = ngs.L2(mesh, order=order)
    for name in ("e_cross", "nu"):
        v = np.ascontiguousarray(materials[name], dtype=np.float64)
        if v.ndim != 3:
            raise ValueError(f"materials {name} must be a 3-d array (nz, ny, nx), got shape "
                             f"{v.shape}")
        lo, hi = float(v.min()), float(v.max())
        if not (lo > 0 if name == "e_cross" else (lo > -1 and hi < 0.5)):
            raise ValueError("materials e_cross must be > 0 and nu in (-1, 0.5) everywhere, "
                             f"got {name} in [{lo}, {hi}]")
        f = ngs.GridFunction(space)
        f.Set(ngs.VoxelCoefficient(*box, v, linear=True))
        out.append(ngs.IfPos(f - hi, hi, ngs.IfPos(f - lo, f, lo)))
    return out


def _prescribed(ngs, mesh, fes, g_p1, inp):
    """Free dofs, prescribed-dof mask and target values, and the Newton tolerance scale.

    The dofs on the dirichlet faces, and the vertex dof of every prescribed node
    (NGSolve's H1 numbers the vertex dofs first, in vertex order): the nodes the MTM
    prescribes."""
    constrained, g, points = inp["constrained"], inp["g"], inp["points"]
    prescribed = ngs.GridFunction(fes)
    prescribed.Set(g_p1, definedon=mesh.Boundaries("dirichlet"))
    free = np.array(fes.FreeDofs(), dtype=bool)
    _by_point(free)[: mesh.nv][constrained] = False
    fixed = ~free
    pres = prescribed.vec.FV().NumPy()
    _by_point(pres)[: mesh.nv][constrained] = g[constrained]
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) or 1.0
    volume = float(np.abs(inp["vol"]).sum()) / 6.0
    g_max = float(np.abs(g).max()) or 1.0
    e_max = float(max(inp["e_cross"].max(), inp["k_fib"].max()))
    return {"freedofs": ngs.BitArray(free), "fixed": fixed, "target": pres[fixed].copy(),
            "scale": np.sqrt(e_max * volume * (g_max / size) ** 2)}


def _load_steps(ngs, model, linear, *, steps, tol, max_newton, predictor, progress_bar):
    """Ramp the prescribed data to 1 in load steps (halved where one fails); Newton its."""
    form, gfu, fixed, target = model["form"], model["gfu"], model["fixed"], model["target"]
    maxerr = tol * model["scale"]
    values = gfu.vec.FV().NumPy()
    step = gfu.vec.CreateVector()
    step_np = step.FV().NumPy()
    done, step_size, newton_its = 0.0, 1.0 / steps, 0
    with Progress(total=None, desc="reference load steps", enabled=progress_bar,
                  logger=log) as bar:
        while done < 1.0 - 1e-12:  # a few load steps, each a vectorised Newton solve
            t = min(done + step_size, 1.0)
            saved = values.copy()
            model["load"].Set(t)
            step_np[:] = 0.0
            step_np[fixed] = (t - done) * target
            its = 0
            status = 1
            if predictor == "tangent":
                status = 0 if _predictor(ngs, form, gfu.vec, step, linear) else 1
            if status != 0:  # the proportional predictor: the last solution scaled, the
                # boundary moved alone; also the fallback where the tangent predictor
                # inverts an element (close to a buckled state its linearisation overshoots)
                values[:] = saved * (t / done if done > 0 else 0.0)
                values[fixed] = t * target
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
            bar.step(f"load {t:.3g} converged in {its} Newton iterations")
    return newton_its


def _midpoint_values(model, inp):
    """The edges of the mesh (sorted point-id pairs, (m, 2)) and the solution at their
    midpoints (m, 3): with the vertex values, the whole quadratic field (P2)."""
    tets = inp["tets"]
    pairs = tets[:, [0, 0, 0, 1, 1, 2, 1, 2, 3, 2, 3, 3]].reshape(-1, 2, 6)
    edges = np.unique(np.sort(pairs.transpose(0, 2, 1).reshape(-1, 2), axis=1), axis=0)
    mid = inp["points"][edges].mean(axis=1)
    mesh = model["mesh"]
    values = np.asarray(model["gfu"](mesh(mid[:, 0], mid[:, 1], mid[:, 2])), dtype=np.float64)
    return edges.astype(np.int64), values.reshape(-1, 3)


def _result(grid, inp, disp, released, stats):
    """Copy of ``grid`` with the displacement and the solver's field arrays."""
    points, tets = inp["points"], inp["tets"]
    out = grid.copy()
    out.point_data[arrays.DISPLACEMENT] = np.array(disp, dtype=np.float64)
    out.field_data[arrays.REFERENCE_SOLVER] = np.array(stats)
    out.field_data[arrays.REFERENCE_RELEASED] = np.flatnonzero(released).astype(np.int64)
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
    out.field_data[arrays.REFERENCE_FOLDED] = folded.astype(np.int64)
    return out
