"""The virtual patient's truth: its fine planned grid, solved and cached, and its skin.

:func:`truth_grid` builds the truth's model from the patient's *true* labels with the
filters (:func:`pvcmf.filters.cut_bones`, ``tetrahedralize(conforming=True)``,
``fiber_directions``, ``assign_materials``, ``apply_plan``; the meshed region and the
dropped floating parts by :mod:`pvcmf.filters.model_region`), never through the pipeline
it judges, solves it with :func:`pvcmf.truth.solver.solve_reference` and caches the
solution on disk (:func:`pvcmf.cache.cached`) under :func:`grid_hash`;
:func:`postop_skin` moves the patient's skin with it.
"""

from __future__ import annotations

import hashlib
import logging

import numpy as np

from .. import arrays, filters
from ..cache import cache_root, code_hash
from ..cache import cached  # the one cache: truths are pyvista files, its default I/O
from ..filters.model_region import drop_floating_parts, face_box
from . import solver
from .solver import solve_reference

log = logging.getLogger("pvcmf.reference")

__all__ = ["MODEL_VERSION", "cached", "grid_hash", "postop_skin", "solver_code_hash",
           "truth_grid"]

#: bumped when the model changes, so cached truths are recomputed
MODEL_VERSION = "2"


#: the solver's code, hashed (docstrings and comments left out) into the truth's cache key
_SOLVER_CODE = ("_boundary_faces", "_netgen_mesh", "_released_nodes", "_Linear", "_predictor",
                "_damped_newton", "solve_reference", "_inputs", "_release", "_model",
                "_prescribed", "_load_steps", "_result", "_midpoint_values", "_material_fields",
                "_by_point")
_CODE_HASH = []


def solver_code_hash():
    """SHA-256 (16 hex digits) of the truth solver's code, without docstrings or comments.

    :func:`pvcmf.cache.code_hash` of the functions and classes of
    :mod:`pvcmf.truth.solver` named in ``_SOLVER_CODE``: editing how the truth is solved changes the cache key of every
    truth; editing a docstring, a comment or the layout does not.

    Examples
    --------
    >>> from pvcmf.truth import solver_code_hash
    >>> len(solver_code_hash())
    16
    """
    if not _CODE_HASH:
        _CODE_HASH.append(code_hash(*(getattr(solver, name) for name in _SOLVER_CODE)))
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
    processes by round-off (about 1e-14 mm), which must not change the key (a quantisation boundary falls between two
    such runs with a probability of about 1e-5).

    Examples
    --------
    >>> import pyvista as pv
    >>> from pvcmf.truth import grid_hash
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
    :func:`solve_reference`. The grid is rebuilt on every call (the mesher is
    deterministic) and the solution is read from the on-disk cache
    (``PVCMF_CACHE_DIR`` or ``~/.cache/pvcmf``, ``reference/truth_grid_<key>.vtu``) under
    :func:`grid_hash` of that grid, the solver options, :data:`MODEL_VERSION` and the
    solver's code: the key hashes what the solver computes from, not the code of the
    mesher, osteotomy or material filters that made its input (a change there that changes
    the grid changes the key; one that does not keeps the cached truth). Concurrent
    callers (processes, threads, dask workers) asking for the same truth compute it once:
    the others wait on a lock file and read the cache (:func:`pvcmf.cache.cached`). Reading a cached
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
        Show the meshing and solver steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.UnstructuredGrid
        Planned linear-tetrahedral grid (pre-operative frame) with the point array
        ``arrays.DISPLACEMENT`` (the P2 solution at its vertices, mm), the arrays of
        ``apply_plan`` / ``assign_materials`` and the field array ``arrays.REFERENCE_SOLVER``.

    Examples
    --------
    >>> import pvcmf                                                  # doctest: +SKIP
    >>> grid = pvcmf.truth.truth_grid(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    return _solved_truth(case, n_tets, order, steps, face_fraction, cache, cache_dir,
                         progress_bar)[1]


def _solved_truth(case, n_tets, order, steps, face_fraction, cache, cache_dir, progress_bar):
    """(cut labels, solved grid) of the truth; the solve cached by :func:`grid_hash`."""
    labels, grid = _truth_grid(case, n_tets, face_fraction, progress_bar)
    key = grid_hash(grid, f"order={order}|steps={steps}")
    path = cache_root("reference", cache_dir) / f"truth_grid_{key}.vtu"
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
        Show the meshing and solver steps (:class:`pvcmf.progress.Progress`).

    Returns
    -------
    pyvista.PolyData
        Post-operative skin (patient frame) with point array ``arrays.DISPLACEMENT``.

    Examples
    --------
    >>> import pvcmf                                                  # doctest: +SKIP
    >>> truth = pvcmf.truth.postop_skin(pvcmf.datasets.phantom(1, spacing=2.0))  # doctest: +SKIP
    """
    labels, solved = _solved_truth(case, n_tets, order, steps, face_fraction, cache,
                                   cache_dir, progress_bar)
    return _skin_of(filters.extract_skin(labels), solved)


def _truth_grid(case, n_tets, face_fraction, progress_bar):
    """The truth's planned grid: true labels cut by the plan, conforming mesh with the
    muscles, fibres, Table I materials, plan boundary conditions."""
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
    outside = ~np.asarray(probe[arrays.VALID_POINT_MASK], dtype=bool)
    if outside.any():
        _, idx = cKDTree(post.points).query(skin.points[outside])
        disp[outside] = np.asarray(post[arrays.DISPLACEMENT])[idx]
    out = skin.copy()
    out.clear_data()
    out.points = np.asarray(skin.points, dtype=np.float64) + disp
    out.point_data[arrays.DISPLACEMENT] = disp
    return out
