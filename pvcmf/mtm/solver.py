"""The MTM solver: eliminate the constraints, assemble, factorise or precondition, solve.

The rest position of the free vertices makes every elastic force ``K_jj u_j + sum K_jk u_k``
zero (paper 001 eq. 2). After eliminating the constraints (:mod:`pvcmf.mtm.constraints`) this
is one sparse symmetric positive definite system ``K_ff y = -K_fp y_p``.

Methods (``method=``)
---------------------
``direct``
    A sparse factorisation by the ``backend`` the caller names (:mod:`pvcmf.mtm.backends`):
    ``'pardiso'`` (MKL PARDISO, ``pip install pypardiso``), ``'cholmod'`` (scikit-sparse),
    ``'superlu'``/``'splu'`` (scipy), or ``'auto'`` (default): the first installed of
    PARDISO, CHOLMOD, SuperLU. The backend, the ``precision`` (``'mixed'``: a
    single-precision PARDISO factor refined in double, the default with PARDISO;
    ``'double'``, the default with the others) and the ``threads`` (default one) are fixed
    for the solver's life. One refinement step estimates the forward error
    (:class:`IllConditionedWarning` when many digits are lost).
``cg``
    Conjugate gradient preconditioned by algebraic multigrid (pyamg) or block Jacobi.
``relaxation``
    The paper's local iteration, as a multicolour block Gauss-Seidel.
``gpu``
    Jacobi-preconditioned conjugate gradient through CuPy on a CUDA device.
``auto``
    ``direct`` up to :data:`AUTO_DIRECT_MAX_POINTS` points, ``cg`` above (memory).

:class:`Solver` keeps everything that does not depend on the material (geometry, sparsity
pattern, elimination maps, the symbolic analysis), so new materials cost a numeric
refactorisation and a new bone move only a solve. Delegates to :mod:`pvcmf.mtm.backends`.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp

from .. import arrays
from ._common import (  # the field-data names written by solve live with solution_grid
    FIELD_BACKEND, FIELD_ERROR_ESTIMATE, FIELD_ITERATIONS, FIELD_LOST_DIGITS, FIELD_METHOD,
    FIELD_RESIDUAL, FIELD_TIME, BackendUnavailableError, ConvergenceError,
    IllConditionedWarning, SymmetricFromTriangle, blas_threads as _blas_threads, norm,
    solution_grid,
)
from .assembly import _LINEAR_CELLS, Assembler, _merge_pairs, grid_materials, tetrahedra
from .backends import direct_backends, gpu_available, resolve
from .backends.cg import CG
from .backends.cholmod import ORDERINGS, node_order
from .backends.direct import Direct
from .backends.gpu import GPU
from .backends.pardiso import node_order as pardiso_node_order
from .backends.relaxation import Relaxation
from .constraints import Constraints, SolutionWarning, solution_checks
from .materials import check_positive_definite, elastic_coefficients

log = logging.getLogger(__name__)

__all__ = [
    "Solver", "solve", "SolutionWarning", "ConvergenceError", "IllConditionedWarning",
    "BackendUnavailableError",
    "direct_backends", "gpu_available", "METHODS", "ORDERINGS", "PRECISIONS",
    "AUTO_DIRECT_MAX_POINTS", "FIELD_METHOD", "FIELD_BACKEND", "FIELD_RESIDUAL",
    "FIELD_ITERATIONS", "FIELD_TIME", "FIELD_ERROR_ESTIMATE", "FIELD_LOST_DIGITS",
]

METHODS = ("direct", "cg", "relaxation", "gpu", "auto")
#: numeric factor precisions of :class:`Solver` (``'auto'``: ``'mixed'`` with the PARDISO
#: backend, ``'double'`` with the others; ``'mixed'`` needs the PARDISO backend)
PRECISIONS = ("auto", "double", "mixed")
#: ``method="auto"`` uses ``direct`` up to this many points, else ``cg`` (the memory of a
#: sparse factor of a 3D mesh grows faster than linearly)
AUTO_DIRECT_MAX_POINTS = 100_000

_METHOD_CLASSES = {"direct": Direct, "cg": CG, "relaxation": Relaxation, "gpu": GPU}


def _check_options(grid, method, tol, backend, precision, ordering, preconditioner, threads):
    """Validated ``(method, tol, backend, precision)``; errors name the parameter."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if method == "auto":
        method = "direct" if grid.n_points <= AUTO_DIRECT_MAX_POINTS else "cg"
    tol = float(tol)
    if not 0 < tol < 1:
        raise ValueError(f"tol must be in (0, 1), got {tol}")
    if method == "gpu" and not gpu_available():
        raise RuntimeError("method='gpu' needs CuPy and a CUDA device, and none was found; "
                           "use method='direct' or 'cg'")
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if method == "direct":
        backend = resolve(backend)
    elif backend not in (None, "auto"):
        raise ValueError(f"backend applies to method='direct' only, got method={method!r}")
    else:
        backend = None
    if precision == "auto":
        precision = "mixed" if backend == "pardiso" else "double"
    if precision == "mixed" and backend != "pardiso":
        raise ValueError(
            f"precision='mixed' needs method='direct' with backend='pardiso' (a single-"
            f"precision factor), got method={method!r}, backend={backend!r}")
    if ordering not in ORDERINGS:
        raise ValueError(f"ordering must be one of {ORDERINGS}, got {ordering!r}")
    if preconditioner not in (None, "amg", "jacobi"):
        raise ValueError(f"preconditioner must be 'amg' or 'jacobi', got {preconditioner!r}")
    if threads is not None and (int(threads) != threads or threads < 1):
        raise ValueError(f"threads must be None or a positive integer, got {threads!r}")
    return method, tol, backend, precision


class Solver:
    """Reusable MTM solver for one mesh and one set of boundary-condition types.

    Keeps the geometry, the block sparsity pattern, the elimination maps and the symbolic
    analysis (``direct``); :meth:`update_materials` re-assembles and refactors numerically
    only, and :meth:`solve` accepts new prescribed displacements without any
    refactorisation. The backend, precision and threads chosen here never change.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with materials (cell ``E_fiber``, ``nu``, optional ``E_cross``,
        ``fiber``) and boundary conditions (point ``bc``, ``bc_displacement``, ``bc_normal``).
    method : {'direct', 'cg', 'relaxation', 'gpu', 'auto'}
        ``auto``: ``direct`` up to :data:`AUTO_DIRECT_MAX_POINTS` points, else ``cg``.
    tol : float
        Relative residual ``||K_ff y - b|| / ||b||`` to reach (iterative methods) or to check
        (``direct``, which raises :class:`ConvergenceError` above it after refinement).
    backend : {'auto', 'pardiso', 'cholmod', 'superlu', 'splu'}, optional
        Direct backend. ``'auto'`` (or None): the first installed of PARDISO (pypardiso),
        CHOLMOD (scikit-sparse), SuperLU (scipy); see :func:`direct_backends`. A backend that
        is not installed raises :class:`BackendUnavailableError` naming it.
    precision : {'auto', 'mixed', 'double'}
        Numeric factor. ``'mixed'`` (PARDISO only): a single-precision factor (about half
        the work of a double one) refined in double by conjugate gradient to a relative
        residual of about 1e-14, the accuracy of a double factor; when the refinement
        stalls or the single-precision error is too large to estimate the lost digits from,
        the solver factors in double from then on and ``info['precision']`` says
        ``'double (mixed stalled)'``. ``'double'``: a double factor. ``'auto'`` (default):
        ``'mixed'`` with the PARDISO backend, ``'double'`` with the others.
    threads : int or None
        Threads of the factorisation and solves (PARDISO: MKL threads of every phase; other
        methods: a BLAS limit through threadpoolctl). Default 1: where other jobs share the
        cores, a thread waiting for its core stalls every synchronisation of a parallel
        factorisation, which costs more than a free core left unused
        (``docs/benchmarks/mtm.md``). On a machine of your own pass the number of free
        cores, or None for the libraries' defaults (MKL: one thread per core).
    maxiter : int, optional
        Iteration cap (default 2000 for cg, 5000 for gpu, 20000 sweeps for relaxation).
    preconditioner : {'amg', 'jacobi'}, optional
        For ``cg``; default AMG when pyamg imports.
    omega : float
        Over-relaxation factor of ``relaxation`` (1 = Gauss-Seidel).
    warn_lost_digits : float
        ``direct`` warns (:class:`IllConditionedWarning`) when the estimated number of lost
        significant digits reaches this.
    progress_bar : bool
        Show progress of the iterative methods (:class:`pvcmf.progress.Progress`).
    ordering : {'auto', 'amd', 'metis', 'nesdis'}
        Node-graph ordering of the unknowns for CHOLMOD and PARDISO when scikit-sparse is
        installed (``'auto'``: AMD below 30k nodes with unknowns, METIS above). Without it,
        ``'auto'`` and ``'metis'`` number PARDISO's unknowns by the METIS order of the node
        graph from a PARDISO analysis of that graph (``'pardiso-metis'``), and the other
        orderings leave PARDISO to run METIS on the dof graph. :attr:`node_ordering` is the
        node-graph ordering used (None: none).
    E_fiber, E_cross, nu, fiber : optional
        Override the grid's materials (scalars or per-cell arrays).

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(5, 5, 5)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.46)
    >>> z = grid.points[:, 2]
    >>> grid.point_data[arrays.BC] = np.where((z == 0) | (z == 4), arrays.BC_JOINT,
    ...                                       arrays.BC_FREE).astype(np.int8)
    >>> d = np.zeros((grid.n_points, 3)); d[z == 4, 2] = -0.4
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = d
    >>> solver = pvcmf.mtm.Solver(grid)
    >>> u = solver.solve()
    >>> solver.update_materials(nu=0.3)      # numeric refactorisation only
    >>> u2 = solver.solve()
    >>> bool(np.allclose(u[z == 4], d[z == 4]))
    True
    """

    def __init__(self, grid, method="direct", *, tol=1e-10, backend="auto", precision="auto",
                 threads=1, maxiter=None, preconditioner=None, omega=1.0,
                 warn_lost_digits=8.0, progress_bar=False, ordering="auto", E_fiber=None,
                 E_cross=None, nu=None, fiber=None):
        method, tol, backend, precision = _check_options(
            grid, method, tol, backend, precision, ordering, preconditioner, threads)
        self.method, self.tol, self.backend_name = method, tol, backend
        self.precision, self.ordering = precision, ordering
        self.threads = None if threads is None else int(threads)
        self.maxiter = maxiter
        self.preconditioner = preconditioner
        self.omega = float(omega)
        self.warn_lost_digits = float(warn_lost_digits)
        self.progress_bar = progress_bar
        self.grid = grid
        t0 = time.perf_counter()
        self.points, cells = tetrahedra(grid)
        self._cells = cells
        self.assembler = asm = Assembler(self.points, cells)
        self.constraints = cons = Constraints(grid, used=asm.used)
        cons.check_rigid_modes(self.points, asm.indptr, asm.indices)
        if np.any(~asm.used):
            log.warning("%d point(s) belong to no tetrahedron; they keep their prescribed "
                        "displacement (0 if free)", int(np.sum(~asm.used)))
        self.materials = grid_materials(grid, E_fiber=E_fiber, E_cross=E_cross, nu=nu, fiber=fiber)
        self._groups = None
        self._vals = None
        self._build_maps()
        self.timings = {"setup": time.perf_counter() - t0}
        self._method = _METHOD_CLASSES[method](self)
        self._assemble_and_factor()

    @property
    def _triangular(self):
        """Whether only the triangle of ``K_ff`` is kept (CHOLMOD, PARDISO)."""
        return self.method == "direct" and self.backend_name in ("cholmod", "pardiso")

    @property
    def _backend(self):
        """The direct factorisation in use (None for the iterative methods)."""
        return getattr(self._method, "factor", None)

    # ------------------------------------------------------------------ structure
    def _build_maps(self):
        """Where each entry of ``K_ff``, ``K_fp`` (and the factored triangle) sits in the blocks.

        The unknowns are numbered node by node in elimination order (with scikit-sparse:
        the node-graph ordering of :func:`~pvcmf.mtm.backends.cholmod.node_order`; without
        it, for PARDISO, the METIS order of the node graph from
        :func:`~pvcmf.mtm.backends.pardiso.node_order`; otherwise the natural order). The block pattern is permuted to that node
        order once (a sort of the blocks, 9x fewer than the entries); every dof row then lists
        its blocks' entries already sorted, so the dof-level maps are built with no sort.
        """
        asm, cons = self.assembler, self.constraints
        n = asm.n_points
        free = cons.free.reshape(n, 3)
        self._natural_order, self.node_ordering = False, None
        nodes = None
        if self._triangular:  # CHOLMOD, PARDISO
            found = node_order(asm.indptr, asm.indices, cons.free, self.ordering)
            if found is None and self.backend_name == "pardiso" and self.ordering in ("auto", "metis"):
                found = pardiso_node_order(asm.indptr, asm.indices, cons.free, self.threads or 1)
            if found is not None:  # the unknowns numbered in elimination order
                nodes, self.node_ordering = found
                self._natural_order = True
        if nodes is None:
            rank = np.arange(n)
            node_of = rank
            bptr, bpos = asm.indptr.astype(np.int64), np.arange(asm.nnzb)
        else:
            rest = np.ones(n, dtype=bool)
            rest[nodes] = False
            node_of = np.concatenate([nodes, np.flatnonzero(rest)])
            rank = np.empty(n, dtype=np.int64)
            rank[node_of] = np.arange(n)
            bptr, _, bpos = _merge_pairs(rank[asm.rows], rank[asm.indices], n)
            order = np.empty_like(bpos)
            order[bpos] = np.arange(bpos.size)
            bpos = order  # the blocks sorted by (rank of row, rank of column)
        dof_of = (3 * node_of[:, None] + np.arange(3)).ravel()  # dofs in rank order
        fr = free.ravel()[dof_of]
        self.F = dof_of[fr]
        self.P = dof_of[~fr]
        pos = np.full(3 * n, -1, dtype=np.int64)  # position in F (>= 0) or in P (< 0: -1 - k)
        pos[self.F] = np.arange(self.F.size)
        pos[self.P] = -1 - np.arange(self.P.size)
        # the entries of dof row (rank r, i): block k of block row r, then j = 0..2
        seg = np.repeat(np.diff(bptr), 3)[fr]  # blocks per row of an unknown, in rank order
        starts = np.repeat(bptr[:-1], 3)[fr]
        first = np.cumsum(seg) - seg
        blk = bpos[np.repeat(starts - first, seg) + np.arange(seg.sum())]  # (row, block) pairs
        comp = np.repeat(np.tile(np.arange(3), n)[fr], seg)
        itype = np.int32 if 9 * asm.nnzb < 2**31 else np.int64
        j = np.arange(3, dtype=itype)
        where = ((9 * blk.astype(itype) + 3 * comp.astype(itype))[:, None] + j).ravel()
        col = pos.astype(np.int32)[(3 * asm.indices[blk].astype(itype))[:, None] + j].ravel()
        nrow = self.F.size
        row_end = np.cumsum(3 * seg)

        def parts(mask, cols):
            ptr = np.zeros(nrow + 1, dtype=np.int32)
            if nrow:
                ptr[1:] = np.cumsum(mask, dtype=np.int32)[row_end - 1]
            return ptr, cols[mask], where[mask]

        isf = col >= 0
        self._fp = parts(~isf, -1 - col)
        if self._triangular:
            # the upper triangle in CSR is also the lower triangle in CSC (K is symmetric):
            # PARDISO reads the former, CHOLMOD the latter, neither needs a conversion
            row = np.repeat(np.arange(nrow, dtype=np.int32), 3 * seg)
            self._ffu = parts(col >= row, col)  # prescribed columns (< 0) drop out too
        else:
            self._ff = parts(isf, col)
        log.debug("MTM system: %d unknowns of %d dofs", nrow, 3 * n)

    # ------------------------------------------------------------------ materials
    def update_materials(self, *, E_fiber=None, E_cross=None, nu=None, fiber=None,
                         refactor=True):
        """Re-assemble with new materials and refactor numerically (symbolic analysis kept).

        Each argument is a scalar or a per-cell array; omitted ones keep their value. The
        backend, precision, ordering and threads stay as they are.

        ``refactor=False`` (``direct`` only) keeps the previous numeric factorisation when a
        bound on the condition number (from the old and new materials only) predicts that
        conjugate gradient preconditioned by it converges in at most 30 iterations; the next
        :meth:`solve` then iterates, and refactors when it does not reach ``tol`` in that
        many. The answer meets ``tol`` either way.
        """
        ef, ec, nu_, a = self.materials
        m = self.assembler.n_cells

        def pick(new, old):
            if new is None:
                return old
            v = np.asarray(new, dtype=float)
            if v.ndim == 0:
                return np.full(m, float(v))
            if v.shape != (m,):
                raise ValueError(f"material arrays must be scalars or have shape ({m},), got {v.shape}")
            return v.copy()

        ef2 = pick(E_fiber, ef)
        ec2 = ef2 if (E_cross is None and E_fiber is not None and np.array_equal(ec, ef)) \
            else pick(E_cross, ec)
        nu2 = pick(nu, nu_)
        if fiber is not None:
            a = np.broadcast_to(np.asarray(fiber, dtype=float), (m, 3)).copy()
            nrm = np.linalg.norm(a, axis=1)
            a[nrm > 0] /= nrm[nrm > 0, None]
        missing = (ef2 != ec2) & ~(np.linalg.norm(a, axis=1) > 0)
        if np.any(missing):
            raise ValueError(
                f"fiber must be a nonzero vector where E_fiber != E_cross; {int(missing.sum())} "
                f"cell(s) have none, e.g. cell {int(np.flatnonzero(missing)[0])}"
            )
        check_positive_definite(ef2, ec2, nu2)
        self.materials = (ef2, ec2, nu2, a)
        self._assemble_and_factor(refactor=refactor or self.method != "direct")

    def _assemble_and_factor(self, refactor=True):
        asm, cons = self.assembler, self.constraints
        t0 = time.perf_counter()
        vals = self._group_values() if self._vals is not None else None
        if vals is None:
            ef, ec, nu, a = self.materials
            # the first assembly scatters directly; re-assemblies use the linear map
            assemble = asm.linear_upper_blocks if self._vals is not None else asm.upper_blocks
            data = asm.full_blocks(assemble(ef, ec, nu, a))
            cons.rotate_blocks(data, asm.rows, asm.indices)
            self._data = data
            flat = data.reshape(-1)
            tri = self._triangular
            vals = {"fp": flat[self._fp[2]], "ff": flat[(self._ffu if tri else self._ff)[2]]}
        self._vals = vals
        self._set_matrices(vals)
        t1 = time.perf_counter()
        self.timings["assembly"] = t1 - t0
        if self.F.size:
            with _blas_threads(self.threads):
                self._method.setup(refactor=refactor)
        self.timings["factor"] = time.perf_counter() - t1
        log.debug("assembly %.3f s, factor/setup %.3f s", t1 - t0, self.timings["factor"])

    def _set_matrices(self, vals):
        nf, npres = self.F.size, self.P.size
        self.K_fp = sp.csr_matrix((vals["fp"], *self._fp[1::-1]), shape=(nf, npres))
        if self._triangular:
            indptr, indices, _ = self._ffu
            # CSR of the upper triangle == CSC of the lower one (K is symmetric)
            self.K_ff = SymmetricFromTriangle(vals["ff"], indices, indptr, nf)
        else:
            self.K_ff = sp.csr_matrix((vals["ff"], *self._ff[1::-1]), shape=(nf, nf))

    def _direct_matrix(self):
        """The matrix the direct backend reads, without a format conversion."""
        if self.backend_name == "pardiso":
            return self.K_ff.upper
        if self.backend_name == "cholmod":
            return self.K_ff.lower
        indptr, indices, _ = self._ff  # K_ff's CSR arrays read as CSC (K_ff is symmetric)
        return sp.csc_matrix((self._vals["ff"], indices, indptr), shape=self.K_ff.shape)

    #: :meth:`update_materials` combines cached per-material matrices when the cells carry at
    #: most this many distinct materials (tables: fat and muscle), else it re-assembles
    max_material_groups = 8

    def _group_values(self):
        """``K_ff`` triangle and ``K_fp`` values for piecewise-constant materials, or None.

        The blocks are linear in each cell's coefficients ``(lambda, mu_T, alpha,
        mu_L - mu_T, beta)``, so with the cells grouped by material (``g``) the values the
        backend reads are ``sum_g sum_c coef_gc B_gc``: the ``B_gc`` (assembled, rotated at
        sliding nodes and gathered into the eliminated system once per grouping, fibres and
        constraints) turn a sweep's re-assembly into one small dense product instead of a
        sparse product, a symmetric copy, rotations and gathers. Only for the direct CHOLMOD / PARDISO
        backends (which read the triangle) up to ``_LINEAR_CELLS`` cells; None (re-assemble)
        otherwise or when the materials have more than :attr:`max_material_groups` values.
        """
        asm = self.assembler
        if not self._triangular or asm.n_cells > _LINEAR_CELLS or not self.F.size:
            return None
        ef, ec, nu, a = self.materials
        ani = np.flatnonzero(ef != ec)
        g = getattr(self, "_groups", None)
        if g is not None:
            label, rep = g["label"], g["rep"]
            if not (np.array_equal(ani, g["ani"]) and np.array_equal(a[ani], g["fiber"])
                    and all(np.array_equal(x, x[rep][label]) for x in (ef, ec, nu))):
                g = None
        if g is None:
            table = np.stack([ef, ec, nu], axis=1)
            # per-cell materials (e.g. mixed by muscle fraction) show in a sample of the cells
            # at once: skip the full np.unique for them
            sample = table[:: max(1, len(table) // 256)]
            if len(np.unique(sample, axis=0)) > self.max_material_groups:
                self._groups = None
                return None
            mats, rep, label = np.unique(table, axis=0, return_index=True, return_inverse=True)
            if len(mats) > self.max_material_groups:
                self._groups = None
                return None
            g = self._groups = self._group_basis(label.ravel(), rep, ani, a[ani])
        lam, muT, alpha, muL, beta = elastic_coefficients(ef[g["rep"]], ec[g["rep"]],
                                                          nu[g["rep"]])
        coef = np.stack([lam, muT, alpha, muL - muT, beta])[g["kind"], g["group"]]
        # einsum, not BLAS: no BLAS thread pool is woken next to the factorisation's threads
        vals = np.einsum("vk,k->v", g["basis"], coef)
        ntri = self._ffu[2].size
        return {"ff": vals[:ntri], "fp": vals[ntri:]}

    def _group_basis(self, label, rep, ani, fiber):
        t = time.perf_counter()
        asm, cons = self.assembler, self.constraints
        U, group, kind = asm.group_upper_blocks(label, len(rep), ani, fiber)
        K = len(group)
        blocks = np.ascontiguousarray(U.transpose(2, 1, 0)).reshape(asm.n_upper, 3, 3, K)
        full = np.empty((asm.nnzb, 3, 3, K))
        full[asm._upper_pos] = blocks
        full[asm._lower_pos] = np.swapaxes(blocks[asm._off], 1, 2)
        for k in range(K):
            cons.rotate_blocks(full[..., k], asm.rows, asm.indices)
        flat = full.reshape(-1, K)
        basis = np.concatenate([flat[self._ffu[2]], flat[self._fp[2]]])  # (values, K)
        log.debug("material-group basis: %d groups, %d matrices, %.3f s", len(rep), len(group),
                  time.perf_counter() - t)
        return {"label": label, "rep": rep, "ani": ani, "fiber": np.array(fiber),
                "group": np.array(group), "kind": np.array(kind), "basis": basis}

    # ------------------------------------------------------------------ solve
    def solve(self, bc_displacement=None, *, x0=None, checks=True):
        """Solve for the displacement of every point, shape ``(n, 3)``.

        Parameters
        ----------
        bc_displacement : (n, 3) array, optional
            New prescribed displacements (same ``bc`` codes and normals); no refactorisation.
        x0 : (n, 3) array, optional
            Initial guess for ``cg``, ``gpu`` and ``relaxation`` (warm start).
        checks : bool, default True
            False skips :func:`~pvcmf.mtm.constraints.solution_checks` (NaN in :attr:`info`).

        Returns
        -------
        numpy.ndarray (n, 3)
            Also sets :attr:`info` (method, backend, residual, iterations, times, error
            estimate; ``direct``: precision and threads).
        """
        cons = self.constraints
        if bc_displacement is not None:
            cons.set_displacement(bc_displacement)
        t0 = time.perf_counter()
        yp = cons.prescribed[self.P]
        b = -(self.K_fp @ yp)
        nb = norm(b)
        info = {"method": self.method, "backend": self.backend_name or "", "iterations": 0,
                "error_estimate": np.nan, "lost_digits": np.nan}
        if self.method == "direct":
            info.update(precision=self.precision, threads=self.threads)
        if self.F.size == 0 or nb == 0:
            y = np.zeros(self.F.size)
            info["residual"] = 0.0
        else:
            y0 = None
            if x0 is not None:
                x0 = np.asarray(x0, dtype=float)
                if x0.shape != (cons.n_points, 3):
                    raise ValueError(f"x0 must have shape ({cons.n_points}, 3), got {x0.shape}")
                y0 = cons.to_local(x0)[self.F]
            with _blas_threads(self.threads):
                y = self._method.solve(b, nb, y0, info)
        if not np.all(np.isfinite(y)):
            raise ConvergenceError(f"method={self.method!r} produced non-finite values")
        full = cons.prescribed.copy()
        full[self.F] = y
        u = cons.to_global(full)
        info["inverted"], info["free_ratio"] = (np.nan, np.nan) if not checks else solution_checks(
            self.points, self._cells, u, cons.bc, cons.to_global(cons.prescribed))
        self.timings["solve"] = time.perf_counter() - t0
        times = {f"{k}_time": self.timings[k] for k in ("assembly", "factor", "solve")}
        info.update(times, time=sum(times.values()))
        self.info = info
        return u

    def _residual(self, y, b, nb):
        return float(norm(b - self.K_ff @ y) / nb)

    def _moduli(self):
        """Per-cell moduli ``(mu_T, mu_L, lambda + 2 mu_T / 3)`` of the current materials."""
        lam, muT, _, muL, _ = elastic_coefficients(*self.materials[:3])
        return np.stack([muT, muL, lam + 2.0 * muT / 3.0])

    # ------------------------------------------------------------------ output
    def to_grid(self, u, grid=None):
        """Copy of ``grid`` (default the solver's) with point ``displacement`` and field data."""
        return solution_grid(self.grid if grid is None else grid, u, getattr(self, "info", {}))


def solve(grid, method="direct", tol=1e-10, progress_bar=False, **kwargs):
    """Rest position of the MTM under the grid's boundary conditions.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Linear tetrahedra with cell materials (``E_fiber``, ``nu``, optional ``E_cross``,
        ``fiber``; see :func:`pvcmf.filters.assign_materials`) and point ``bc``,
        ``bc_displacement``, ``bc_normal`` (see :func:`pvcmf.filters.apply_plan`).
    method : {'direct', 'cg', 'relaxation', 'gpu', 'auto'}
        See :class:`Solver`; ``auto`` picks ``cg`` above :data:`AUTO_DIRECT_MAX_POINTS`
        points, where a direct factorisation no longer fits a few GB.
    tol : float
        Relative residual tolerance.
    progress_bar : bool
        Show progress for iterative methods.
    **kwargs
        Passed to :class:`Solver` (``backend``, ``precision``, ``threads``, ``ordering``, ``maxiter``,
        ``preconditioner``, ``omega``, ``warn_lost_digits``, material overrides) except
        ``x0`` (warm start, (n, 3)).

    Returns
    -------
    pyvista.UnstructuredGrid
        A copy with point array ``displacement`` (n, 3) and field data ``mtm_method``,
        ``mtm_backend``, ``mtm_residual``, ``mtm_iterations``, ``mtm_time``,
        ``mtm_error_estimate``, ``mtm_lost_digits``, ``mtm_inverted_cells`` (tetrahedra the
        displacement inverts) and ``mtm_free_over_prescribed`` (largest free displacement
        over the largest prescribed one); a :class:`SolutionWarning` says when either is
        suspect (:func:`pvcmf.mtm.constraints.solution_checks`). No array shares memory
        with ``grid``.

    Raises
    ------
    ValueError
        Missing or invalid arrays, indefinite materials, or a part of the mesh with rigid
        motions left (:class:`pvcmf.mtm.RigidModeError`).
    ConvergenceError
        The method did not reach ``tol``.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> import pvcmf
    >>> from pvcmf import arrays
    >>> grid = pv.ImageData(dimensions=(4, 4, 4)).triangulate()
    >>> grid.cell_data[arrays.E_FIBER] = np.ones(grid.n_cells)
    >>> grid.cell_data[arrays.NU] = np.full(grid.n_cells, 0.3)
    >>> boundary = np.any((grid.points == 0) | (grid.points == 3), axis=1)
    >>> grid.point_data[arrays.BC] = np.where(boundary, arrays.BC_JOINT,
    ...                                       arrays.BC_FREE).astype(np.int8)
    >>> grid.point_data[arrays.BC_DISPLACEMENT] = 0.01 * grid.points   # a linear field
    >>> post = grid.cmf.solve()
    >>> bool(np.allclose(post[arrays.DISPLACEMENT], 0.01 * grid.points))
    True
    """
    x0 = kwargs.pop("x0", None)
    if not hasattr(grid, "point_data") or arrays.BC not in grid.point_data.keys():
        name = type(grid).__name__
        raise ValueError(
            f"solve needs point array {arrays.BC!r} (boundary conditions; it is produced by "
            f"apply_plan); the {name} has point arrays "
            f"{sorted(grid.point_data.keys()) if hasattr(grid, 'point_data') else []}"
        )
    solver = Solver(grid, method=method, tol=tol, progress_bar=progress_bar, **kwargs)
    u = solver.solve(x0=x0)
    log.info("MTM %s: residual %.1e, %d iterations, %.3f s", method, solver.info["residual"],
             solver.info["iterations"], solver.info["time"])
    return solver.to_grid(u)
