"""Volume meshing of the region surfaces with gmsh, and the calibration of the count.

Every region's closed surface becomes a gmsh volume; HXT (Delaunay, algorithm 10) meshes
them keeping the input surface triangles, so the interfaces stay conforming, and its
optimiser improves the elements. Remaining flat slivers spanning four surface points are
dropped, the interior nodes of other slivers are relocated where that helps
(:func:`~pvcmf.filters.meshing.quality._relocate_sliver_nodes`), and what is left goes
through a gmsh optimiser only on request. gmsh keeps one global model and its options,
so one volume meshing runs at a time per process (:data:`_GMSH_LOCK`). What gmsh's
boundary recovery prints on the C streams goes to the debug log.

The working spacing for a requested number of tetrahedra comes from
``n = a V / s**3 + b A / s**2`` (V soft-tissue volume, A muscle surface area counted on
voxel faces; graded meshes scale the volume term by the share of elements the grading
keeps, :func:`~pvcmf.filters.meshing.grading.graded_share`).

Delegates to the gmsh Python API (imported when a mesh is made) and the graded sizes to
:mod:`pvcmf.filters.meshing.grading`.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import sys
import tempfile
import threading

import numpy as np

from . import grading as _grading
from .grid import _MUSCLE0, SurfaceError
from .quality import _relocate_sliver_nodes, tet_quality

log = logging.getLogger(__name__)

#: coefficients ``a`` and ``b`` of the count model (tetrahedra per working cell and per
#: muscle face); the spacing is refined from the counts obtained (secant in log-log)
#: when the count misses by more than ``_RETRY_TOLERANCE``
_TETS_PER_CELL = 5.7
_TETS_PER_FACE = 5.0
_RETRY_TOLERANCE = 0.18
#: mean surface edge / working spacing (graded meshes: the size at the surfaces is the
#: mean surface edge; the calibration works in working spacings)
_EDGE_PER_SPACING = 0.95
#: graded meshes: tetrahedra obtained per tetrahedra predicted by the count model
_GRADED_COUNT_BIAS = 0.82
_MAX_ATTEMPTS = 3
#: surface slivers below min(min_dihedral, this) degrees are dropped as flat caps
_FLAT_DIHEDRAL = 5.0
#: gmsh optimisers accepted by ``tetrahedralize(sliver_optimizer=...)``
_SLIVER_OPTIMIZERS = ("Netgen", "Relocate3D")


def _initial_spacing(fine, volume, n_tets, conforming, min_spacing, share=None):
    """Working spacing predicted for ``n_tets`` from the volume and the muscle surface area.

    The area counts the voxel faces with a muscle on one side (the cropped image of
    :func:`_crop_fine` holds them all; with its faces, :func:`_fine_faces`, they are
    counted there). ``share(s)``: graded meshes, the share of the uniform count of the
    volume term that the grading keeps at spacing ``s`` (``n = a V share(s) / s**3 +
    b A / s**2`` solved by bisection in log ``s``).
    """
    area = 0.0
    if conforming:
        code, sp = fine[0], np.asarray(fine[2], float)[::-1]  # array axes z, y, x
        if len(fine) > 5 and fine[4] is not None:
            muscle_face = fine[4] % 256 >= _MUSCLE0  # the higher code is a muscle
            axis = 2 - np.argmax(np.abs(fine[5][muscle_face]), axis=1)
            per_axis = np.bincount(axis, minlength=3)
        else:
            per_axis = []
            for ax in range(3):
                x = np.moveaxis(code, ax, 0)
                a, b = x[1:], x[:-1]
                per_axis.append(np.count_nonzero((a != b) & ((a >= _MUSCLE0) | (b >= _MUSCLE0))))
        for ax in range(3):
            area += int(per_axis[ax]) * np.prod(np.delete(sp, ax))
    # a V u^3 + b A u^2 = n with u = 1 / s: the positive real root
    roots = np.roots([_TETS_PER_CELL * volume, _TETS_PER_FACE * area, 0.0, -float(n_tets)])
    u = max(r.real for r in roots if abs(r.imag) < 1e-9 * max(1.0, abs(r)) and r.real > 0)
    if share is None:
        return max(min_spacing, 1.0 / u)

    def count(x):  # decreasing in x (the graded sizes grow with x at any distance)
        return _GRADED_COUNT_BIAS * (
            _TETS_PER_CELL * volume * share(x) / x**3 + _TETS_PER_FACE * area / x**2
        )

    lo, hi = 0.2 / u, 1.0 / u  # share <= 1: the graded spacing is below the uniform one
    for _ in range(30):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if count(mid) > n_tets else (lo, mid)
    return max(min_spacing, hi)


def _gmsh_tets(regions):
    """(nodes, tets, region per tet) of the current gmsh model."""
    import gmsh

    tags, coords, _ = gmsh.model.mesh.getNodes()
    lut = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    lut[tags.astype(np.int64)] = np.arange(len(tags))
    tets, comp = [], []
    for r in regions:
        _, nodes = gmsh.model.mesh.getElementsByType(4, int(r))
        cells = lut[nodes.astype(np.int64)].reshape(-1, 4)
        tets.append(cells)
        comp.append(np.full(len(cells), r, dtype=np.int64))
    return coords.reshape(-1, 3), np.concatenate(tets), np.concatenate(comp)


#: gmsh keeps one global state (model, options) and :func:`_c_output_to_log` swaps the
#: process's stdout/stderr descriptors: one volume meshing at a time per process. Without it,
#: four threads meshing the same shell (a Dask ``threads`` scheduler) gave a wrong mesh, two

#: gmsh keeps one global state (model, options) and :func:`_c_output_to_log` swaps the
#: process's stdout/stderr descriptors: one volume meshing at a time per process, other
#: threads wait their turn
_GMSH_LOCK = threading.Lock()


def _gmsh_mesh(*args, **kwargs):
    """:func:`_gmsh_mesh_locked` under :data:`_GMSH_LOCK` (threads wait their turn)."""
    with _GMSH_LOCK:
        return _gmsh_mesh_locked(*args, **kwargs)


@contextlib.contextmanager
def _c_output_to_log():
    """Send what compiled code prints on stdout/stderr meanwhile to ``log.debug``.

    gmsh's boundary recovery (TetGen inside HXT) prints "PLC Error: A segment and a facet
    intersect ..." with C ``printf`` whatever ``General.Terminal`` says, also when the
    next fallback meshes fine: that alarms users. File descriptors 1 and 2 go to a
    temporary file for the duration (the C buffers are flushed before they are given
    back); the text is logged at DEBUG level and yielded (a one-element list, filled on
    exit) so that a failure can quote it. Without ``os.dup`` support nothing is captured.
    The descriptors are the process's: what other threads print in that window (gmsh's
    volume step) goes to the debug log as well.
    """
    printed = []
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (AttributeError, ValueError, OSError):
            pass
    try:
        libc = ctypes.CDLL(None)
    except (OSError, TypeError):
        libc = None
    with tempfile.TemporaryFile() as tmp:
        saved = []
        try:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(tmp.fileno(), fd)
        except OSError:
            for fd, old in saved:
                os.dup2(old, fd)
                os.close(old)
            saved = []
        try:
            yield printed
        finally:
            if saved:
                if libc is not None:
                    libc.fflush(None)
                for fd, old in saved:
                    os.dup2(old, fd)
                    os.close(old)
                tmp.seek(0)
                text = tmp.read().decode(errors="replace")
                printed.append(text)
                if text.strip():
                    log.debug("tetrahedralize: gmsh printed: %s", text.strip())



def _gmsh_mesh_locked(points, tri, patch, patch_sides, threads, optimize, min_dihedral=None, accept=None,
                      optimizers=(), grading=None):
    """Volume mesh of every meshed region; returns (nodes, tets, comp id per tet).

    ``grading``: ``(InterfaceDistance, g)`` for graded sizes (a gmsh background field,
    :mod:`pvcmf.filters.meshing.grading`), None for sizes from the surfaces.
    """
    import gmsh

    own = not gmsh.isInitialized()
    if own:
        gmsh.initialize(interruptible=False)
    gmsh.model.add("pvcmf_tetrahedralize")
    graded_field = None
    try:
        regions = _build_model(points, tri, patch, patch_sides, threads, optimize)
        if grading is not None:
            edges = np.linalg.norm(points[tri[:, [1, 2, 0]]] - points[tri], axis=2)
            graded_field = _grading.add_background_field(grading[0], float(edges.mean()), grading[1])
        _generate()
        nodes, tets, comp = _gmsh_tets(regions)
        if min_dihedral is None or (accept is not None and not accept(len(tets))):
            return nodes, tets, comp
        return _remove_slivers(nodes, tets, comp, regions, len(points), min_dihedral, optimizers)
    except SurfaceError:
        raise
    except Exception as exc:  # gmsh raises a bare Exception with its last error
        raise SurfaceError(f"gmsh could not build the model: {exc}") from exc
    finally:
        if graded_field is not None:
            _grading.restore(*graded_field)
        gmsh.model.remove()
        if own:
            gmsh.finalize()


def _build_model(points, tri, patch, patch_sides, threads, optimize):
    """Options, surface patches and one volume per region of the current gmsh model.

    Returns the region ids (the gmsh volume tags).
    """
    import gmsh

    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", threads)
    gmsh.option.setNumber("Mesh.Algorithm3D", 10)  # HXT
    gmsh.option.setNumber("Mesh.Optimize", 1 if optimize else 0)
    gmsh.option.setNumber("Mesh.OptimizeNetgen", 0)
    order = np.argsort(patch, kind="stable")
    bounds = np.searchsorted(patch[order], np.arange(len(patch_sides) + 1))
    for p in range(len(patch_sides)):
        gmsh.model.addDiscreteEntity(2, p + 1)
        if p == 0:
            gmsh.model.mesh.addNodes(2, 1, np.arange(1, len(points) + 1), points.ravel())
        tris = tri[order[bounds[p] : bounds[p + 1]]]
        gmsh.model.mesh.addElementsByType(p + 1, 2, [], (tris + 1).ravel())
    gmsh.model.mesh.createTopology(False, True)
    regions = np.unique(patch_sides)
    regions = regions[regions >= 2]
    for r in regions:
        bounding = (np.flatnonzero((patch_sides == r).any(axis=1)) + 1).tolist()
        loop = gmsh.model.geo.addSurfaceLoop(bounding)
        gmsh.model.geo.addVolume([loop], int(r))
    gmsh.model.geo.synchronize()
    return regions


def _generate():
    """Mesh the volumes of the current gmsh model; raise SurfaceError with gmsh's message."""
    import gmsh

    failure = None
    with _c_output_to_log() as printed:
        try:
            gmsh.model.mesh.generate(3)
        except Exception as exc:  # gmsh raises a bare Exception with its last error
            failure = exc
    if failure is not None:
        first = printed[0].strip().splitlines()[:1] if printed and printed[0].strip() else []
        detail = f" ({first[0]})" if first else ""
        raise SurfaceError(f"gmsh could not mesh the surfaces: {failure}{detail}") from failure


def _drop_flat(nodes, tets, comp, n_surface, min_dihedral):
    """Drop the slivers spanning four surface points; returns (tets, comp, worst angle)."""
    import gmsh

    worst = tet_quality(nodes, tets)[0].min(axis=1)
    sliver = worst < min(min_dihedral, _FLAT_DIHEDRAL)
    node_tags = gmsh.model.mesh.getNodes()[0].astype(np.int64)
    on_surface = np.all(node_tags[tets] <= n_surface, axis=1)
    flat = sliver & on_surface
    if flat.any():
        # flat tetrahedra spanning four surface points (a crease where a region
        # pinches): dropping them changes the volume by ~0 and keeps conformity
        log.info("tetrahedralize: %d flat surface tetrahedra dropped", int(flat.sum()))
        return tets[~flat], comp[~flat], worst[~flat]
    return tets, comp, worst


def _remove_slivers(nodes, tets, comp, regions, n_surface, min_dihedral, optimizers):
    """Flat slivers dropped, sliver nodes relocated, then the requested gmsh optimisers.

    ``n_surface``: the number of surface nodes (gmsh tags ``1..n_surface``).
    """
    import gmsh

    tets, comp, worst = _drop_flat(nodes, tets, comp, n_surface, min_dihedral)
    if worst.min() < min_dihedral:
        node_tags = gmsh.model.mesh.getNodes()[0].astype(np.int64)
        nodes, worst = _relocate_sliver_nodes(nodes, tets, node_tags > n_surface, worst, min_dihedral)
    # a sliver the HXT optimiser left (usually where a region pinches): the chosen
    # gmsh optimiser on the regions holding one (Netgen: swaps + smoothing, several
    # times the meshing time)
    for method in optimizers:
        if worst.min() >= min_dihedral:
            break
        bad = np.unique(comp[worst < min_dihedral])
        log.info(
            "tetrahedralize: min dihedral %.2f deg, %s optimisation of %d region(s)",
            worst.min(), method, len(bad),
        )
        gmsh.model.mesh.optimize(method, dimTags=[(3, int(r)) for r in bad])
        before = nodes, tets, comp, worst
        nodes, tets, comp = _gmsh_tets(regions)
        tets, comp, worst = _drop_flat(nodes, tets, comp, n_surface, min_dihedral)
        if worst.min() <= before[3].min():  # the optimiser made it no better: keep
            log.info("tetrahedralize: %s optimisation did not raise the min dihedral", method)
            nodes, tets, comp, worst = before
    return nodes, tets, comp
