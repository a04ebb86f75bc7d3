"""The filter :func:`tetrahedralize`: label image -> labelled tetrahedral mesh.

Runs the steps of the package in turn (inputs and region of interest, working grid,
surfaces, volume), calibrates the working spacing until the count is near the request,
falls back to other grids and weaker smoothing when gmsh rejects the surfaces, and writes
the mesh in a canonical order (gmsh numbers nodes differently from run to run) with the
region labels and the quality and timings as field data.
"""

from __future__ import annotations

import logging
import numbers
import time
import warnings

import numpy as np
import pyvista as pv

from ... import arrays
from ...progress import Progress
from . import volume
from .grading import GRID_STEP, InterfaceDistance, check_grading, graded_share
from .grid import (
    _AIR, _FAT, _MUSCLE0, SurfaceError, _check_muscles, _code_name, _codes, _components,
    _crop_fine, _drop_fragments, _image_pieces, _repair_topology, _working_grid,
)
from .inputs import _check_image, _check_n_tets, _roi_crop, _roi_mask
from .quality import (
    GRADING, MIN_DIHEDRAL, MIN_RADIUS_RATIO, N_TETS_REQUESTED, P1_DIHEDRAL, P1_RADIUS_RATIO,
    SMOOTHING_SCALE, SURFACE_SPACING, TIME_SURFACE, TIME_TOTAL, TIME_VOLUME, tet_quality,
)
from .subvoxel import MuscleIndicators
from .surfaces import (
    _FINE_TARGETS, _TARGET_REACH, _check_surfaces, _fine_faces, _split_patches, _surfaces,
)
from .volume import (
    _EDGE_PER_SPACING, _MAX_ATTEMPTS, _RETRY_TOLERANCE, _SLIVER_OPTIMIZERS, _initial_spacing,
)

log = logging.getLogger(__name__)

#: (spacing factor, smoothing factor, target-reach factor) tried in turn when gmsh rejects
#: the surfaces: the last ones are the plain, unsmoothed SurfaceNets surfaces
_FALLBACKS = (
    (1.0, 1.0, 1.0), (0.97, 1.0, 1.0), (0.94, 1.0, 1.0), (0.97, 0.5, 0.5), (0.93, 0.0, 0.0),
    (0.86, 0.0, 0.0), (0.75, 0.0, 0.0),
)


def tetrahedralize(
    labels,
    *,
    n_tets=30_000,
    conforming=True,
    roi=None,
    smoothing_scale=0.1,
    spacing=None,
    optimize=True,
    min_dihedral=5.0,
    sliver_optimizer=None,
    threads=1,
    grading=None,
    subvoxel=False,
    progress_bar=False,
):
    """Labelled tetrahedral mesh of the facial soft tissue of a label image.

    Parameters
    ----------
    labels : pyvista.ImageData
        Label image with integer point arrays ``arrays.TISSUE`` and (for
        ``conforming=True`` when muscles are present) ``arrays.MUSCLE``. The soft tissue
        ``arrays.SOFT_LABELS`` (fat and muscle) is meshed; air, bone, teeth and the
        intracranial space are not.
    n_tets : int, default 30_000
        Requested number of tetrahedra, the speed/accuracy knob. The working spacing is
        calibrated from the soft-tissue volume and refined (re-meshing up to twice) until
        the count lies within +-18 % of the request (the goal is +-20 %).
    conforming : bool, default True
        ``True``: fat and every muscle are separate regions whose interfaces are element
        faces. ``False``: one homogeneous soft-tissue mesh, muscles ignored (every cell
        gets ``TISSUE = FAT`` and ``MUSCLE = 0``), the paper's baseline.
    roi : optional
        Region of interest, applied before meshing (only the soft tissue inside it is
        meshed):

        * ``(xmin, xmax, ymin, ymax, zmin, zmax)``: a box in mm;
        * ``(bone_id, distance)``: the tissue within ``distance`` mm of the bone segment
          ``bone_id`` of point array ``arrays.BONE`` (for example the moved mandible);
        * a boolean array of length ``labels.n_points``;
        * a callable ``f(points) -> bool array`` evaluated on the image points.
    smoothing_scale : float, default 0.1
        Smoothing strength of the surfaces after they are placed on the image interfaces
        (every vertex stays within ``smoothing_scale * s * sqrt(3) / 2`` of that place);
        0 switches smoothing off. Stronger smoothing pulls the placed vertices off the
        image interfaces; none leaves the staircase of the working grid in the element
        shapes. The placed surfaces can self-intersect; when gmsh rejects them the
        surfaces are rebuilt on slightly finer grids, then the smoothing and the
        placement reach are halved, then both switched off (plain SurfaceNets surfaces of
        the working grid), with a warning when the surfaces were weakened.
    spacing : float, optional
        Working-grid spacing in mm (surface triangle size). Overrides the calibration
        from ``n_tets`` (the count is then not controlled).
    optimize : bool, default True
        Run gmsh's tetrahedral optimisation (``Mesh.Optimize``).
    min_dihedral : float or None, default 5.0
        Slivers below this dihedral angle (degrees) that HXT's optimiser leaves (where a
        region pinches): those (below 5 deg at most) that span four surface points are
        dropped (flat caps on a crease of the surface, volume ~0; the mesh stays
        conforming); the interior nodes of the others are moved towards their
        neighbours or away from the opposite face where that raises the worst angle
        of their tetrahedra; what remains stays (the field data reports the minimum)
        unless ``sliver_optimizer`` is set. None skips the check.
    sliver_optimizer : {None, "Netgen", "Relocate3D"}, default None
        gmsh optimiser run on the regions that still hold a sliver below
        ``min_dihedral``. Netgen's removes most of them but takes several times the
        meshing time.
    threads : int, default 1
        Threads for gmsh's HXT mesher. HXT's threads spin while they wait, so more
        threads cost more CPU time where the cores are shared.
    grading : None, 0 or float in (1, 8], default None
        Size grading of the volume mesh (:mod:`pvcmf.filters.meshing.grading`). None or
        0: the sizes come from the surfaces (uniform meshes, the default). ``g > 1``: the
        element size is the mean surface edge ``s`` within ``0.5 s`` of a region
        interface (skin, muscles, bone, roi cut) and grows linearly to ``g s`` at
        ``2 g s`` away; the count calibration accounts for it, so the tetrahedra saved
        deep in the fat go to finer surfaces. The thin facial tissue (6-12 mm) leaves
        little to grade; thicker tissue gains more. Measured effects:
        ``docs/benchmarks/meshing.md``.
    subvoxel : bool, default False
        Sub-voxel muscle interfaces (``conforming=True``): after the placement and the
        smoothing, the vertices of the sheets between a named muscle and other soft
        tissue are moved onto the half level of the muscle's label indicator smoothed by
        a Gaussian of half a voxel (:mod:`pvcmf.filters.meshing.subvoxel`); those on
        the junction with the skin, the bone or the region's cut move within that
        surface. The label image is the only input. ``False``: the surfaces follow the
        local average of the voxel staircase. Measured effects:
        ``docs/benchmarks/meshing_accuracy.md``.
    progress_bar : bool, default False
        Show the steps (:class:`pvcmf.progress.Progress`: a tqdm bar, or INFO log lines
        without tqdm).

    Returns
    -------
    pyvista.UnstructuredGrid
        Linear tetrahedra (``VTK_TETRA``) with uint8 cell arrays ``arrays.TISSUE`` (FAT
        or MUSCLE_TISSUE) and ``arrays.MUSCLE`` (0 or the muscle id), and field data
        :data:`QUALITY_FIELDS` (min and 1st-percentile dihedral angle in degrees, min and
        1st-percentile radius ratio ``3 r_in / R_circ``, the requested count, working
        spacing, smoothing used, timings in s and the ``grading`` (1.0 for uniform
        meshes).

    Raises
    ------
    TypeError
        ``labels`` is not an ImageData, ``n_tets`` is not an integer or ``grading`` is
        not a number.
    ValueError
        Missing or non-integer label arrays, no soft tissue, ``n_tets`` out of range,
        a malformed ``roi``, ``grading`` not None, 0 or in (1, 8].
    SurfaceError
        The surfaces stay invalid for gmsh even without smoothing.

    Warns
    -----
    UserWarning
        A muscle with fewer than 8 voxels (merged into the fat), or a fallback to weaker
        smoothing.

    Notes
    -----
    The working grid is isotropic, so the surfaces are as fine at the skin as at the bone
    and, by default, so is the volume. Triangles of the working spacing cannot follow
    the nose, lips and eyelids to below a voxel, so some element centroids fall in a
    voxel of another tissue and the volume of thin facial muscles is off although every
    muscle is present: request more tetrahedra or a smaller region of interest where
    accuracy matters (``benchmarks/meshing.py --table``).

    Examples
    --------
    >>> from pvcmf import arrays
    >>> from pvcmf.filters.meshing import shell_labels, tetrahedralize
    >>> grid = tetrahedralize(shell_labels(spacing=2.0), n_tets=5_000)
    >>> 4_000 <= grid.n_cells <= 6_000
    True
    >>> sorted(set(grid.cell_data[arrays.TISSUE].tolist()))
    [1, 2]
    """
    t_start = time.perf_counter()
    tissue, muscle = _check_image(labels, conforming)
    _check_n_tets(n_tets)
    if not isinstance(smoothing_scale, numbers.Real) or smoothing_scale < 0:
        raise ValueError(f"smoothing_scale must be a number >= 0, got {smoothing_scale!r}")
    if sliver_optimizer is not None and sliver_optimizer not in _SLIVER_OPTIMIZERS:
        raise ValueError(
            f"sliver_optimizer must be None or one of {_SLIVER_OPTIMIZERS}, got {sliver_optimizer!r}"
        )
    if not isinstance(subvoxel, (bool, np.bool_)):
        raise TypeError(f"subvoxel must be True or False, got {type(subvoxel).__name__} {subvoxel!r}")
    optimizers = () if sliver_optimizer is None else (sliver_optimizer,)
    growth = check_grading(grading)
    if spacing is not None and (not isinstance(spacing, numbers.Real) or spacing <= 0):
        raise ValueError(f"spacing must be a positive number of mm, got {spacing!r}")
    with Progress(desc="tetrahedralize", enabled=progress_bar, logger=log) as bar:
        fine, pieces, volume_mm3, n_soft = _fine_image(labels, tissue, muscle, roi, conforming)
        min_spacing = float(min(labels.spacing))
        s, graded = _start_spacing(fine, volume_mm3, n_tets, conforming, min_spacing, spacing, growth)
        bar.step(f"{n_soft} soft voxels, {volume_mm3:.0f} mm^3, start spacing {s:.2f} mm")
        fallbacks = _fallbacks(float(smoothing_scale), spacing is not None)
        result, failures, t_surface, t_volume = _mesh_calibrated(
            fine, s, spacing, n_tets, fallbacks, min_spacing, pieces,
            dict(threads=threads, optimize=optimize, min_dihedral=min_dihedral if optimize else None,
                 optimizers=optimizers, grading=graded,
                 indicators=MuscleIndicators(fine) if conforming and subvoxel else None),
            bar,
        )
        nodes, tets, comp_code, cell_comp, smoothing, s, reach = result
        _report_fallbacks(failures, fallbacks[0], smoothing, reach, s, len(tets), n_tets)
        nodes, tets, cell_comp = _canonical(nodes, tets, cell_comp)
        codes = comp_code[cell_comp]
        if conforming:
            _warn_lost_muscles(fine[0], codes, s)
        grid = _output_grid(nodes, tets, codes)
        fd = grid.field_data
        fd[N_TETS_REQUESTED] = [int(n_tets)]
        fd[SURFACE_SPACING] = [float(s)]
        fd[SMOOTHING_SCALE] = [float(smoothing)]
        fd[TIME_SURFACE] = [t_surface]
        fd[TIME_VOLUME] = [t_volume]
        fd[GRADING] = [1.0 if growth is None else growth]
        fd[TIME_TOTAL] = [time.perf_counter() - t_start]
        bar.step(
            f"{grid.n_cells} tets, min dihedral {fd[MIN_DIHEDRAL][0]:.1f} deg "
            f"(1st pct {fd[P1_DIHEDRAL][0]:.1f}), {fd[TIME_TOTAL][0]:.2f} s"
        )
    return grid


def _fine_image(labels, tissue, muscle, roi, conforming):
    """The region codes of the image, cropped to the soft tissue, with their interfaces.

    Returns ``fine`` (code, origin, spacing, face midpoints, face code pairs, face
    normals), the number of pieces of every muscle, the soft-tissue volume (mm^3) and its
    number of voxels.
    """
    shape_zyx = tuple(labels.dimensions[::-1])
    # a box roi crops the image first (one voxel beyond the box), so that the whole-image
    # passes below run on the box only; the result is the same as on the whole image
    crop = _roi_crop(labels, roi)
    tissue = np.asarray(tissue).reshape(shape_zyx)
    muscle = None if muscle is None else np.asarray(muscle).reshape(shape_zyx)
    offset = np.zeros(3, np.int64)  # crop start, image axes x, y, z
    if crop is not None:
        tissue = tissue[crop]
        muscle = None if muscle is None else muscle[crop]
        offset = np.array([crop[2].start, crop[1].start, crop[0].start], np.int64)
    code = _codes(tissue, muscle, conforming)
    mask = _roi_mask(labels, roi, shape_zyx, crop)
    if mask is not None:
        code = np.where(mask | (code < _FAT), code, _AIR).astype(np.uint8)
    voxel_volume = float(np.prod(labels.spacing))
    n_soft = int(np.count_nonzero(code >= _FAT))
    if n_soft == 0:
        where = " inside the roi" if roi is not None else ""
        raise ValueError(
            f"labels: no soft tissue{where} (point array {arrays.TISSUE!r} has no "
            f"{arrays.FAT} (fat) or {arrays.MUSCLE_TISSUE} (muscle) labels)"
        )
    if conforming:
        _check_muscles(code, voxel_volume, stacklevel=4)
    fine = _crop_fine(code, labels, offset)
    fine = fine + (_fine_faces(fine) if _FINE_TARGETS else (None, None, None))
    pieces = _image_pieces(fine[0]) if conforming else {}
    return fine, pieces, n_soft * voxel_volume, n_soft


def _start_spacing(fine, volume_mm3, n_tets, conforming, min_spacing, spacing, growth):
    """First working spacing and the grading ``(InterfaceDistance, g)`` (None: uniform)."""
    if spacing is None:
        s = _initial_spacing(fine, volume_mm3, n_tets, conforming, min_spacing)
    else:
        s = float(spacing)
    if growth is None:
        return s, None
    # distance of the image voxels to the region interfaces, once (the surfaces are
    # snapped onto these interfaces), on a grid of a fraction of the uniform spacing
    t0 = time.perf_counter()
    distance = InterfaceDistance(fine[0], fine[1], fine[2], GRID_STEP * s, _FAT)
    if spacing is None:
        s = _initial_spacing(
            fine, volume_mm3, n_tets, conforming, min_spacing,
            share=lambda x: graded_share(distance.inside, _EDGE_PER_SPACING * x, growth),
        )
    log.info(
        "tetrahedralize: grading %g, interface distance on a %s voxel grid in %.2f s, "
        "start spacing %.2f mm", growth, "x".join(map(str, distance.distance.shape[::-1])),
        time.perf_counter() - t0, s,
    )
    return s, (distance, growth)


def _fallbacks(smoothing, fixed_spacing):
    """(spacing factor, smoothing, reach) tried in turn when gmsh rejects the surfaces.

    Weaker smoothing avoids self-intersections; slightly finer grids avoid the pinches
    that coarse grids make in thin tissue.
    """
    if not fixed_spacing:
        return [(f, smoothing * k, _TARGET_REACH * r) for f, k, r in _FALLBACKS]
    return [(1.0, smoothing, _TARGET_REACH), (1.0, smoothing / 2, _TARGET_REACH / 2), (1.0, 0.0, 0.0)]


def _mesh_calibrated(fine, s, spacing, n_tets, fallbacks, min_spacing, pieces, gmsh_options, bar):
    """Mesh until the count is within tolerance (or the attempts are spent).

    Returns the result ``(nodes, tets, comp_code, cell_comp, smoothing, spacing, reach)``,
    the messages of the rejected surfaces and the surface and volume times (s).
    """
    t_surface = t_volume = 0.0
    result, failures, step, n_calibrations, history = None, [], 0, 0, []

    def accept(n_cells):  # the sliver pass runs only on the mesh that will be returned
        last = n_calibrations >= _MAX_ATTEMPTS - 1
        return spacing is not None or last or abs(n_cells / n_tets - 1.0) <= _RETRY_TOLERANCE

    while step < len(fallbacks):
        factor, smooth, reach = fallbacks[step]
        s_try = max(min_spacing, s * factor)
        t0 = time.perf_counter()
        try:
            out = _mesh_once(fine, s_try, smooth, reach, pieces, accept, **gmsh_options)
        except SurfaceError as exc:
            failures.append(str(exc))
            t_volume += time.perf_counter() - t0
            step += 1
            continue
        nodes, tets, comp_code, cell_comp, dt_s, dt_v = out
        result = (nodes, tets, comp_code, cell_comp, smooth, s_try, reach)
        t_surface += dt_s
        t_volume += dt_v
        ratio = len(tets) / n_tets
        log.info(
            "tetrahedralize: spacing %.3f mm -> %d tets (%.2f x requested) in %.2f s",
            s_try, len(tets), ratio, dt_s + dt_v,
        )
        bar.step(f"spacing {s_try:.3f} mm: {len(tets)} tets")
        if spacing is not None or abs(ratio - 1.0) <= _RETRY_TOLERANCE:
            break
        if n_calibrations >= _MAX_ATTEMPTS - 1:
            break
        n_calibrations += 1
        history.append((s_try, len(tets)))
        new_s = _next_spacing(history, s_try, ratio, min_spacing)
        if new_s == s_try:
            break
        s, step = new_s, 0
    if result is None:
        raise SurfaceError("no valid surfaces for gmsh: " + "; ".join(failures))
    return result, failures, t_surface, t_volume


def _next_spacing(history, s_try, ratio, min_spacing):
    """Spacing for the next attempt: a secant step in log-log on the counts obtained."""
    slope = 3.0
    if len(history) >= 2:
        (s0, n0), (s1, n1) = history[-2:]
        if s0 != s1 and n0 != n1:
            slope = float(np.clip(-np.log(n1 / n0) / np.log(s1 / s0), 2.0, 4.0))
    return max(min_spacing, s_try * ratio ** (1.0 / slope))


def _report_fallbacks(failures, first, smoothing, reach, s, n_cells, n_tets):
    """Log a change of grid only; warn when the surfaces were weakened."""
    if failures and smoothing == first[1] and reach == first[2]:
        # only the working grid moved (a slightly finer spacing): same surfaces, no warning
        log.info(
            "tetrahedralize: gmsh rejected %d surface(s) (%s); meshed on a %.3g mm grid",
            len(failures), failures[0], s,
        )
    elif failures:
        warnings.warn(
            f"gmsh rejected {len(failures)} surface(s) ({failures[0]}); meshed at "
            f"spacing {s:.3g} mm, smoothing_scale {smoothing:g}, vertices moved at most "
            f"{reach:g} spacing towards the image interfaces: {n_cells} tetrahedra "
            f"for {n_tets} requested",
            stacklevel=3,
        )


def _canonical(nodes, tets, cell_comp):
    """Unused nodes dropped, nodes sorted by position, cells by their sorted nodes.

    gmsh numbers the nodes differently from run to run; the order here does not depend on
    it. Every cell starts at its smallest node (an even permutation, orientation kept)
    and is then oriented to a positive volume.
    """
    used = np.unique(tets)
    nodes = nodes[used]
    tets = np.searchsorted(used, tets)
    order = np.lexsort(np.round(nodes, 6).T)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    nodes, tets = nodes[order], rank[tets]
    key = np.sort(tets, axis=1)
    cell_order = np.lexsort(key.T[::-1])
    tets, cell_comp = tets[cell_order], cell_comp[cell_order]
    start = np.argmin(tets, axis=1)  # rotate to the smallest node, keeping orientation
    even = [[0, 1, 2, 3], [1, 2, 0, 3], [2, 0, 1, 3], [3, 1, 0, 2]]
    tets = np.take_along_axis(tets, np.asarray(even)[start], axis=1)
    vol = np.einsum(
        "ij,ij->i",
        np.cross(nodes[tets[:, 1]] - nodes[tets[:, 0]], nodes[tets[:, 2]] - nodes[tets[:, 0]]),
        nodes[tets[:, 3]] - nodes[tets[:, 0]],
    )
    neg = vol < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return nodes, tets, cell_comp


def _warn_lost_muscles(code, cell_codes, s):
    """Warn about the muscles of the image that no cell carries."""
    wanted = set(np.unique(code[code > _MUSCLE0]).tolist())
    lost = sorted(wanted - set(np.unique(cell_codes).tolist()))
    if lost:
        warnings.warn(
            f"muscle(s) {', '.join(_code_name(c) for c in lost)} are thinner than the "
            f"{s:.3g} mm working spacing and are not in the mesh; request more "
            "tetrahedra (or a region of interest) to keep them",
            stacklevel=3,
        )


def _output_grid(nodes, tets, codes):
    """The tetrahedral grid with its tissue and muscle labels and its quality field data."""
    dihedral, volumes, rr = tet_quality(nodes, tets)
    if np.any(volumes <= 0):
        raise RuntimeError(
            f"gmsh returned {int(np.sum(volumes <= 0))} zero-volume tetrahedra"
        )
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets}, nodes)
    grid.cell_data[arrays.TISSUE] = np.where(codes == _FAT, arrays.FAT, arrays.MUSCLE_TISSUE).astype(
        np.uint8
    )
    grid.cell_data[arrays.MUSCLE] = np.where(codes >= _MUSCLE0, codes - _MUSCLE0, 0).astype(np.uint8)
    min_dih = dihedral.min(axis=1)
    fd = grid.field_data
    fd[MIN_DIHEDRAL] = [float(min_dih.min())]
    fd[P1_DIHEDRAL] = [float(np.percentile(min_dih, 1))]
    fd[MIN_RADIUS_RATIO] = [float(rr.min())]
    fd[P1_RADIUS_RATIO] = [float(np.percentile(rr, 1))]
    return grid


def _mesh_once(fine, s, smoothing, reach, pieces, accept, *, threads, optimize, min_dihedral,
               optimizers=(), grading=None, indicators=None):
    """One surface + volume meshing pass at spacing ``s``; raises SurfaceError."""
    t0 = time.perf_counter()
    sub, origin = _working_grid(fine, s)
    n_fix = _repair_topology(sub)
    n_drop = _drop_fragments(sub, pieces)
    if n_drop:
        n_fix += _repair_topology(sub)
        log.info("tetrahedralize: %d muscle voxel(s) of coarse-grid fragments given to the fat", n_drop)
    if n_fix:
        log.info("tetrahedralize: %d voxel(s) relabelled to keep the surfaces manifold", n_fix)
    comp, comp_code = _components(sub)
    if len(comp_code) <= 2:
        raise ValueError(
            f"labels: the soft tissue vanishes on a {s:.3g} mm working grid; "
            "request more tetrahedra or a smaller spacing"
        )
    points, tri, sides = _surfaces(comp, origin, s, smoothing, comp_code, fine, reach, indicators)
    try:
        _check_surfaces(tri, sides, comp_code)
    except SurfaceError as exc:
        raise SurfaceError(f"spacing {s:.3g} mm, smoothing_scale {smoothing:g}: {exc}") from exc
    patch, patch_sides = _split_patches(tri, sides, len(points))
    t1 = time.perf_counter()
    try:
        nodes, tets, cell_comp = volume._gmsh_mesh(
            points, tri, patch, patch_sides, threads, optimize, min_dihedral, accept, optimizers,
            grading,
        )
    except SurfaceError as exc:
        raise SurfaceError(f"spacing {s:.3g} mm, smoothing_scale {smoothing:g}: {exc}") from exc
    return nodes, tets, comp_code, cell_comp, t1 - t0, time.perf_counter() - t1
