"""End-to-end prediction: CT + surgical plan -> predicted post-operative face.

:func:`simulate` chains the pipeline steps of :mod:`pvcmf.filters` and :mod:`pvcmf.mtm`
(segmentation, muscles, meshing, materials, plan -> boundary conditions, MTM solve,
skin), times every step, and, given an output folder, writes the predicted skin (VTP),
the deformed mesh (VTU) and offscreen PNGs, each atomically (temporary file in the same
folder + ``os.replace``: an interrupted run leaves no half-written file).

Steps are looked up lazily by their registry names; steps the caller turns off (muscles,
prediction) or that decline on purpose (a failed muscle fit leaves homogeneous tissue) are
recorded in :attr:`Result.skipped`; any other failure raises. Rendering delegates to PyVista
(off screen), writing to VTK's XML writers.
"""

from __future__ import annotations

import json
import logging
import numbers
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyvista as pv

from . import arrays
from ._atomic import atomic_path, write_text
from .plan import Plan, read_plan

log = logging.getLogger(__name__)

__all__ = ["Result", "simulate", "STEPS", "write_outputs"]

#: the steps of :func:`simulate`, in order, as named in the timing summary
STEPS = ("read", "segment", "bone segments", "muscles", "mesh", "fibres", "materials",
         "boundary conditions", "solve", "skin", "skeleton", "figures", "write")

#: default number of tetrahedra: coarse enough for a < 2 min demo on 2 cores
DEFAULT_N_TETS = 25_000
#: boundary-condition options of the pipeline (see :func:`pvcmf.filters.apply_plan`)
DEFAULT_BC_OPTIONS = {"fix_unmoved_bone": True}
#: default anterior share of the head that is meshed (the face model of paper 000)
DEFAULT_FACE_FRACTION = 0.5


class StepUnavailable(RuntimeError):
    """A step declined and the pipeline goes on without it (recorded in ``Result.skipped``).

    Raised on purpose only, e.g. when the muscle fit fails and the soft tissue stays
    homogeneous; a bug or a missing dependency in a step is raised, not skipped.
    """


@dataclass
class Result:
    """What :func:`simulate` produced, with the time spent per step.

    Attributes
    ----------
    labels : pyvista.ImageData
        Tissue / muscle / bone labels (``bone`` holds the planned segments).
    mesh : pyvista.UnstructuredGrid or None
        Pre-operative tetrahedral mesh with materials and ``bc`` arrays.
    post : pyvista.UnstructuredGrid or None
        ``mesh`` with the point array ``displacement`` (rest positions, not warped).
    skin_pre, skin_post : pyvista.PolyData or None
        Pre-operative and predicted skin (``skin_post`` carries ``displacement``).
    skeleton : pyvista.MultiBlock or None
        Post-operative bone segment surfaces (:func:`pvcmf.filters.move_bones`).
    timings : dict
        Step name -> seconds.
    skipped : dict
        Step name -> why it did not run.
    files : dict
        Output name -> written path.
    ct_report : dict
        Units and orientation found in the CT (:func:`pvcmf.filters.standardize`); empty
        when the CT was not checked.
    """

    plan: Plan
    labels: pv.ImageData | None = None
    mesh: pv.UnstructuredGrid | None = None
    post: pv.UnstructuredGrid | None = None
    skin_pre: pv.PolyData | None = None
    skin_post: pv.PolyData | None = None
    skeleton: pv.MultiBlock | None = None
    timings: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)
    files: dict = field(default_factory=dict)
    ct_report: dict = field(default_factory=dict)

    @property
    def complete(self):
        """True when the prediction ran (mesh, boundary conditions and solve)."""
        return self.post is not None

    def summary(self):
        """A small text table of seconds per step (and the skipped steps)."""
        width = max(len(s) for s in STEPS)
        lines = [f"{'step':<{width}}  seconds"]
        for step in STEPS:
            if step in self.timings:
                lines.append(f"{step:<{width}}  {self.timings[step]:7.2f}")
            elif step in self.skipped:
                lines.append(f"{step:<{width}}  skipped: {self.skipped[step]}")
        lines.append(f"{'total':<{width}}  {sum(self.timings.values()):7.2f}")
        if self.post is not None:
            u = np.linalg.norm(np.asarray(self.post[arrays.DISPLACEMENT]), axis=1)
            lines.append(f"max displacement {u.max():.2f} mm, mesh {self.post.n_cells} tetrahedra, "
                         f"{self.post.n_points} points")
        return "\n".join(lines)


# --------------------------------------------------------------------------- step look-up
def _filter(name):
    """The registered filter ``name`` of :mod:`pvcmf.filters`."""
    from . import filters

    return getattr(filters, name)


def _solver():
    from . import mtm

    return mtm.solve


class _Progress:
    """tqdm over the steps when available and wanted, else nothing (logging only)."""

    def __init__(self, enabled, total):
        self.bar = None
        if enabled:
            try:
                from tqdm.auto import tqdm

                self.bar = tqdm(total=total, unit="step", file=sys.stderr,
                                bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}]")
            except ImportError:
                self.bar = _SimpleBar(total)

    def step(self, name):
        if self.bar is not None:
            self.bar.set_description(name)

    def update(self):
        if self.bar is not None:
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()


class _SimpleBar:
    """Fallback text progress bar on stderr."""

    def __init__(self, total):
        self.total, self.n, self.desc = total, 0, ""

    def set_description(self, desc):
        self.desc = desc
        self._draw()

    def update(self, k):
        self.n += k
        self._draw()

    def _draw(self):
        done = int(30 * self.n / max(self.total, 1))
        sys.stderr.write(f"\r{self.desc:<20} [{'#' * done}{'.' * (30 - done)}] "
                         f"{self.n}/{self.total}")
        sys.stderr.flush()

    def close(self):
        sys.stderr.write("\n")


class _Runner:
    def __init__(self, result, progress):
        self.result, self.progress = result, progress

    def run(self, step, func, *args, **kwargs):
        """Run ``func`` as ``step``; a step that declines (:class:`StepUnavailable`, e.g. a
        failed muscle fit falling back to homogeneous tissue) is recorded as skipped."""
        self.progress.step(step)
        start = time.perf_counter()
        try:
            value = func(*args, **kwargs)
        except StepUnavailable as err:
            self.result.skipped[step] = str(err)
            log.warning("step %r skipped: %s", step, err)
            value = None
        else:
            self.result.timings[step] = time.perf_counter() - start
            log.info("step %r took %.2f s", step, self.result.timings[step])
        self.progress.update()
        return value

    def skip(self, step, why):
        self.result.skipped[step] = why
        log.info("step %r skipped: %s", step, why)
        self.progress.update()


# --------------------------------------------------------------------------- steps
def _transfer_bone_segments(labels, bones):
    """Give every segmented bone voxel the segment id of the nearest ``bones`` voxel."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    ref = np.asarray(arrays.require_array(bones, arrays.BONE, "point", dtype="iu"))
    ours = np.asarray(labels[arrays.BONE]) if arrays.BONE in labels.point_data else None
    tissue = np.asarray(labels[arrays.TISSUE])
    hard = np.isin(tissue, arrays.HARD_LABELS) | ((ours > 0) if ours is not None else False)
    same = (tuple(bones.dimensions) == tuple(labels.dimensions)
            and np.allclose(bones.origin, labels.origin)
            and np.allclose(bones.spacing, labels.spacing))
    new = np.zeros(labels.n_points, dtype=np.uint8)
    if same:
        vol = ref.reshape(tuple(bones.dimensions), order="F")
        _, idx = ndimage.distance_transform_edt(vol == 0, sampling=bones.spacing,
                                                return_indices=True)
        nearest = vol[tuple(idx)].ravel(order="F")
        new[hard] = nearest[hard]
    else:
        ref_pts = np.asarray(bones.points)[ref > 0]
        _, near = cKDTree(ref_pts).query(np.asarray(labels.points)[hard])
        new[hard] = ref[ref > 0][near]
    out = labels.copy()
    out[arrays.BONE] = new
    return out


def _segment(ct, options):
    seg = _filter("segment")
    return seg(ct, **options)


def _muscles(labels, landmarks):
    """Embed the muscles; a failing fit falls back to homogeneous tissue with a warning."""
    embed = _filter("embed_muscles")
    try:
        return embed(labels, landmarks=landmarks) if landmarks is not None else embed(labels)
    except (ValueError, RuntimeError) as err:
        raise StepUnavailable(f"embed_muscles failed, soft tissue left homogeneous: "
                              f"{type(err).__name__}: {str(err)[:300]}") from None


def face_box(labels, face_fraction):
    """Box (xmin, xmax, ymin, ymax, zmin, zmax) of the head's anterior ``face_fraction``.

    The model is the face in front of a coronal plane, as in paper 000 where the most
    posterior plane of the soft-tissue model is fixed (Fig. 4c).
    """
    if not (isinstance(face_fraction, numbers.Real) and 0 < face_fraction <= 1):
        raise ValueError(f"face_fraction must be a number in (0, 1], got {face_fraction!r}")
    head = np.asarray(labels[arrays.TISSUE]) != arrays.AIR
    if not head.any():
        raise ValueError("labels has no tissue: the 'tissue' array is all air")
    direction = getattr(labels, "direction_matrix", None)
    if direction is None or np.allclose(direction, np.eye(3)):
        # index bounds of the head from the mask's projections (no (n, 3) point array:
        # a 1 mm head image has ~30M voxels)
        mask = head.reshape(labels.dimensions[::-1])  # (z, y, x)
        lo_idx, hi_idx = [], []
        for axis in (2, 1, 0):  # x, y, z
            other = tuple(a for a in range(3) if a != axis)
            hit = np.flatnonzero(mask.any(axis=other))
            lo_idx.append(hit[0])
            hi_idx.append(hit[-1])
        origin, spacing = np.asarray(labels.origin), np.asarray(labels.spacing)
        lo, hi = origin + spacing * lo_idx, origin + spacing * hi_idx
    else:
        pts = np.asarray(labels.points)[head]
        lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = np.asarray(labels.spacing)
    y0 = hi[1] - face_fraction * (hi[1] - lo[1])
    return (lo[0] - pad[0], hi[0] + pad[0], y0, hi[1] + pad[1], lo[2] - pad[2], hi[2] + pad[2])


def _mesh(labels, n_tets, options, progress_bar, face_fraction):
    tet = _filter("tetrahedralize")
    options = dict(options)
    if face_fraction is not None and "roi" not in options:
        options["roi"] = face_box(labels, face_fraction)
    return tet(labels, n_tets=n_tets, progress_bar=progress_bar, **options)


def _fibres(grid):
    if arrays.MUSCLE not in grid.cell_data or not np.any(grid.cell_data[arrays.MUSCLE]):
        return grid
    return _filter("fiber_directions")(grid)


def _materials(grid, options):
    return _filter("assign_materials")(grid, **options)


def drop_floating_parts(grid, min_constrained=3, collinear_tol=0.05):
    """Remove connected parts of a mesh that the boundary conditions do not hold.

    A part with fewer than ``min_constrained`` fixed/joint/sliding nodes, or with all of
    them (nearly) on one line, would keep rigid motions the solver cannot remove (small
    islands a mesher leaves behind, e.g. tissue in a nostril, or slivers cut off on the
    fixed posterior plane); the MTM's answer does not depend on them elsewhere, so they go.

    Parameters
    ----------
    grid : pyvista.UnstructuredGrid
        Mesh with the point array ``bc``.
    min_constrained : int, default 3
    collinear_tol : float, default 0.05
        A part whose constrained nodes lie within this fraction of their extent of one
        line (second singular value of their centred coordinates below ``collinear_tol``
        times the first) is not held: it could rotate about that line.

    Returns
    -------
    pyvista.UnstructuredGrid
        The mesh itself when every part is held, else a new mesh without the others.
    """
    bc = np.asarray(arrays.require_array(grid, arrays.BC, "point", producer="apply_plan"))
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # parts = connected components of the cells' node graph (scipy; the MTM checks the
    # same graph). VTK's connectivity filter reorders points, so it is not used here.
    conn_ids = np.asarray(grid.cell_connectivity, dtype=np.int64)
    offsets = np.asarray(grid.cell_offsets, dtype=np.int64)
    sizes_ = np.diff(offsets)
    first = np.repeat(conn_ids[offsets[:-1]], sizes_)
    n = grid.n_points
    graph = coo_matrix((np.ones(first.size, dtype=np.int8), (first, conn_ids)), shape=(n, n))
    _, region = connected_components(graph, directed=False)
    used = np.zeros(n, dtype=bool)
    used[conn_ids] = True
    cell_region = region[conn_ids[offsets[:-1]]]
    n_regions = int(region.max()) + 1
    constrained = used & (bc != arrays.BC_FREE)
    counts = np.bincount(region[constrained], minlength=n_regions)
    held = counts >= min_constrained
    held &= np.bincount(cell_region, minlength=n_regions) > 0  # unused points are no part
    # constrained nodes (nearly) on one line leave the rotation about it free (slivers cut
    # off on the fixed posterior plane): such a part is not held either
    pts = np.asarray(grid.points, float)
    for part in np.flatnonzero(held):  # a loop over the few parts, not over points
        c = pts[(region == part) & constrained]
        sv = np.linalg.svd(c - c.mean(axis=0), compute_uv=False)
        held[part] = sv[1] > collinear_tol * sv[0]
    keep_cells = held[cell_region]
    if keep_cells.all():
        return grid
    dropped = np.unique(cell_region[~keep_cells])
    n_dropped = int(np.isin(region[used], dropped).sum())
    log.warning("dropping %d mesh part(s) held by fewer than %d non-collinear constrained "
                "nodes (%d points in all)", len(dropped), min_constrained, n_dropped)
    out = grid.extract_cells(np.flatnonzero(keep_cells))
    for name in ("vtkOriginalPointIds", "vtkOriginalCellIds"):
        for data in (out.point_data, out.cell_data):
            if name in data:
                data.remove(name)
    return out


def _apply_plan(grid, plan, labels, options):
    return drop_floating_parts(_filter("apply_plan")(grid, plan, labels, **options))


def _skin(labels, post):
    """Pre-operative skin and, with a solved mesh, the predicted skin.

    The skin comes from :func:`pvcmf.filters.extract_skin` of the label image. The mesh displacement is carried onto it by
    the finite-element interpolation inside the tetrahedra (VTK's probe filter,
    :meth:`pyvista.DataSet.sample`); skin points just outside the mesh (the label skin and
    the smoothed mesh surface differ by up to a voxel) take the nearest mesh point's
    displacement, so skin behind the meshed face takes that of the fixed plane: zero.
    """
    from scipy.spatial import cKDTree

    pre = _filter("extract_skin")(labels).copy()
    pre.clear_data()
    if post is None:
        return pre, None
    probe = pre.sample(post)
    disp = np.asarray(probe[arrays.DISPLACEMENT], dtype=np.float64).copy()
    outside = np.asarray(probe["vtkValidPointMask"]) == 0
    if outside.any():
        near = cKDTree(np.asarray(post.points)).query(np.asarray(pre.points)[outside])[1]
        disp[outside] = np.asarray(post[arrays.DISPLACEMENT])[near]
    log.info("skin: %d points, %d interpolated in tetrahedra, %d from the nearest mesh point",
             pre.n_points, int((~outside).sum()), int(outside.sum()))
    pre.point_data[arrays.DISPLACEMENT] = disp
    moved = pre.copy()
    moved.points = np.asarray(pre.points) + disp
    return pre, moved


def flip_axes(image, axes):
    """Mirror an image along some of its axes, in place of a reorientation.

    Flipping two axes is a 180 degree rotation (patient left/right kept): use it to bring
    a scan whose superior is -z and anterior -y (VTK's headsq) into pvcmf's patient frame
    (x left, y anterior, z superior). Every point array is flipped; bounds are unchanged.

    Parameters
    ----------
    image : pyvista.ImageData
    axes : str or sequence of str
        Subset of ``"xyz"``, e.g. ``"yz"``.

    Returns
    -------
    pyvista.ImageData
        A new image.

    Examples
    --------
    >>> import numpy as np, pyvista as pv
    >>> from pvcmf.pipeline import flip_axes
    >>> img = pv.ImageData(dimensions=(2, 3, 4))
    >>> img["z"] = img.points[:, 2].copy()
    >>> flip_axes(img, "z")["z"][:3].tolist()
    [3.0, 3.0, 3.0]
    """
    axes = "".join(axes)
    if not isinstance(image, pv.ImageData):
        raise TypeError(f"image must be a pyvista.ImageData, got {type(image).__name__}")
    bad = set(axes) - set("xyz")
    if bad or len(set(axes)) != len(axes):
        raise ValueError(f"axes must be distinct letters of 'xyz', got {axes!r}")
    out = image.copy()
    dims = tuple(image.dimensions)
    for name in image.point_data.keys():
        data = np.asarray(image.point_data[name])
        vol = data.reshape(dims + data.shape[1:], order="F")
        for axis in axes:
            vol = np.flip(vol, "xyz".index(axis))
        out.point_data[name] = vol.reshape(data.shape, order="F").copy()
    return out


# --------------------------------------------------------------------------- main entry
def simulate(ct, plan, out=None, *, labels=None, bones=None, landmarks=None,
             n_tets=DEFAULT_N_TETS, segment_options=None, mesh_options=None,
             material_options=None, bc_options=None, solve_options=None, muscles=True,
             face_fraction=DEFAULT_FACE_FRACTION, predict=True, solve=True, figures=True,
             progress_bar=False, units=None, orient=None):
    """Predict the post-operative face from a CT and a surgical plan.

    Parameters
    ----------
    ct : pyvista.ImageData or str or pathlib.Path
        CT with point array ``ct`` in HU (or a file/folder :func:`pvcmf.read_ct` reads).
    plan : pvcmf.Plan or str or pathlib.Path
        The surgical plan, or a TOML/JSON plan file.
    out : str or pathlib.Path, optional
        Folder for the outputs (see :func:`write_outputs`); nothing is written if None.
    labels : pyvista.ImageData, optional
        Precomputed ``tissue``/``bone`` labels: skips segmentation.
    bones : pyvista.ImageData, optional
        A label image whose ``bone`` array names the segments (e.g. a virtual patient's
        ``truth``): each segmented bone voxel takes the id of its nearest ``bones`` voxel.
        Without it the plan's cut planes (or the segmentation's own ids) define segments.
    landmarks : dict, optional
        Patient landmarks for the muscle atlas (``embed_muscles``); automatic without.
    n_tets : int, default 25000
        Requested number of tetrahedra (the speed/accuracy knob).
    segment_options, mesh_options, material_options, bc_options, solve_options : dict
        Keyword arguments passed to ``segment``, ``tetrahedralize``, ``assign_materials``,
        ``apply_plan`` and ``mtm.solve``. ``bc_options`` defaults to
        :data:`DEFAULT_BC_OPTIONS`: the paper's conditions plus soft tissue on unmoved bone
        fixed (without it, the tissue over the skull, free in the paper, follows a moved
        jaw as a whole, e.g. the forehead moves 5 mm with a Le Fort I; pass
        ``bc_options={"fix_unmoved_bone": False}`` for the paper's exact setting).
    face_fraction : float or None, default 0.5
        Mesh only the anterior fraction of the head (a region of interest in front of a
        coronal plane, whose nodes are the fixed posterior plane of paper 000); None
        meshes the whole head.
    predict : bool, default True
        Run the prediction (mesh, materials, boundary conditions, solve); ``False`` only
        segments, cuts and draws the plan.
    solve : bool, default True
        ``False`` stops after the boundary conditions: :attr:`Result.mesh` and
        :attr:`Result.skin_pre` are made, but no solve, no predicted skin, no skeleton and
        no outputs. This is what a parameter sweep needs once per mesh
        (:class:`pvcmf.sweeps.PipelineEvaluation` then solves per parameter set).
    muscles : bool, default True
        Embed the facial muscles (``embed_muscles``); without, the soft tissue is
        homogeneous. A muscle fit that fails (e.g. bad landmarks) is logged as a warning,
        recorded in :attr:`Result.skipped`, and the prediction goes on without muscles.
    figures : bool, default True
        Render the PNGs when ``out`` is given.
    progress_bar : bool, default False
        Show a progress bar over the steps on stderr.
    units, orient : str, optional
        Units and axes check of :func:`pvcmf.filters.standardize` (``'auto'``, ``'hu'`` or
        an offset; ``'auto'``, ``'none'`` or a code such as ``'LPI'``). Default: ``'auto'``
        for a CT read from a path, no check for a CT given in memory. What was found goes
        to :attr:`Result.ct_report` and ``summary.json`` (``"ct"``).

    Returns
    -------
    Result
        Datasets, seconds per step (:meth:`Result.summary`), skipped steps, written files.

    Raises
    ------
    TypeError, ValueError
        For a bad ``ct``/``plan``/option, before anything is written.

    Examples
    --------
    >>> import pvcmf                                        # doctest: +SKIP
    >>> case = pvcmf.datasets.phantom(1, spacing=2.0)       # doctest: +SKIP
    >>> res = pvcmf.pipeline.simulate(case.ct, case.plan, bones=case.truth)  # doctest: +SKIP
    >>> print(res.summary())                                # doctest: +SKIP
    """
    if isinstance(plan, (str, Path)):
        plan = read_plan(plan)
    if not isinstance(plan, Plan):
        raise TypeError(f"plan must be a pvcmf.Plan or a plan file path, got {type(plan).__name__}")
    if isinstance(n_tets, bool) or not isinstance(n_tets, (int, np.integer)) or n_tets <= 0:
        raise ValueError(f"n_tets must be a positive integer, got {n_tets!r}")
    opts = {}
    for name, value in (("segment_options", segment_options), ("mesh_options", mesh_options),
                        ("material_options", material_options), ("bc_options", bc_options),
                        ("solve_options", solve_options)):
        if value is not None and not isinstance(value, dict):
            raise TypeError(f"{name} must be a dict or None, got {type(value).__name__}")
        opts[name] = dict(value or {})
    if bc_options is None:
        opts["bc_options"] = dict(DEFAULT_BC_OPTIONS)
    if face_fraction is not None and not (0 < float(face_fraction) <= 1):
        raise ValueError(f"face_fraction must be in (0, 1] or None, got {face_fraction!r}")
    if bones is not None and not isinstance(bones, pv.ImageData):
        raise TypeError(f"bones must be a pyvista.ImageData or None, got {type(bones).__name__}")

    result = Result(plan=plan)
    progress = _Progress(progress_bar, len(STEPS))
    run = _Runner(result, progress)
    try:
        if isinstance(ct, (str, Path)):
            from .io import read_ct

            ct = run.run("read", read_ct, ct)
            units, orient = units or "auto", orient or "auto"
        else:
            run.skip("read", "CT given in memory")
        if units is not None or orient is not None:  # units / axes checked on the image
            from .filters.orientation import standardize

            ct, result.ct_report = standardize(ct, units=units or "auto",
                                               orient=orient or "auto")
        if labels is None:
            if not isinstance(ct, pv.ImageData):
                raise TypeError(f"ct must be a pyvista.ImageData or a path, got {type(ct).__name__}")
            arrays.require_array(ct, arrays.CT, "point", dtype="f", producer="pvcmf.read_ct")
            labels = run.run("segment", _segment, ct, opts["segment_options"])
        else:
            run.skip("segment", "labels given")
        if bones is not None:
            labels = run.run("bone segments", _transfer_bone_segments, labels, bones)
        else:
            run.skip("bone segments", "segments from the plan's cut planes / the labels")
        from .filters.osteotomy import cut_bones

        labels = cut_bones(labels, plan)
        if muscles and predict:
            with_muscles = run.run("muscles", _muscles, labels, landmarks)
            if with_muscles is not None:
                labels = with_muscles
        else:
            run.skip("muscles", "muscles=False" if predict else "predict=False")
        result.labels = labels

        if predict:
            grid = run.run("mesh", _mesh, labels, n_tets, opts["mesh_options"], progress_bar,
                           face_fraction)
        else:
            grid = None
            run.skip("mesh", "predict=False")
        if grid is not None:
            grid = run.run("fibres", _fibres, grid) or grid
            with_materials = run.run("materials", _materials, grid, opts["material_options"])
            if with_materials is None:
                grid = None  # no materials: the MTM cannot run
        else:
            for step in ("fibres", "materials"):
                run.skip(step, "no mesh")
        if grid is not None:
            grid = run.run("boundary conditions", _apply_plan, with_materials, plan, labels,
                           opts["bc_options"])
            result.mesh = grid
            if solve:
                result.post = run.run("solve", lambda g: _solver()(g, **opts["solve_options"]),
                                      grid)
            else:
                run.skip("solve", "solve=False")
        else:
            for step in ("boundary conditions", "solve"):
                run.skip(step, "no mesh with materials")

        skins = run.run("skin", _skin, labels, result.post)
        if skins is not None:
            result.skin_pre, result.skin_post = skins
        if not solve:
            for step in ("skeleton", "figures", "write"):
                run.skip(step, "solve=False")
            return result
        from .filters.osteotomy import move_bones

        result.skeleton = run.run("skeleton", move_bones, labels, plan)
        if out is not None:
            start = time.perf_counter()
            progress.step("figures")
            pngs = _render(result, Path(out)) if figures else {}
            result.timings["figures"] = time.perf_counter() - start
            progress.update()
            run.run("write", write_outputs, result, out, pngs)
        else:
            run.skip("figures", "no output folder")
            run.skip("write", "no output folder")
    finally:
        progress.close()
    log.info("simulate finished:\n%s", result.summary())
    return result


# --------------------------------------------------------------------------- outputs
def _front_camera(plotter, bounds, zoom=1.0):
    """Look at the face from the front (patient frame: anterior +y, superior +z)."""
    b = np.asarray(bounds).reshape(3, 2)
    center = b.mean(axis=1)
    size = float(np.linalg.norm(b[:, 1] - b[:, 0]))
    plotter.camera_position = [tuple(center + [0.0, 2.5 * size, 0.0]), tuple(center),
                               (0.0, 0.0, 1.0)]
    plotter.camera.zoom(zoom)


def _plot_surface(surface, scalars=None, cmap=None, clim=None, title=None, color="peachpuff",
                  window_size=(600, 700), scalar_bar_title=None):
    p = pv.Plotter(off_screen=True, window_size=list(window_size))
    p.set_background("white")
    kwargs = dict(smooth_shading=True, specular=0.2)
    if scalars is not None:
        p.add_mesh(surface, scalars=scalars, cmap=cmap, clim=clim,
                   scalar_bar_args={"title": scalar_bar_title or scalars, "color": "black",
                                    "vertical": True, "position_x": 0.82},
                   **kwargs)
    else:
        p.add_mesh(surface, color=color, **kwargs)
    if title:
        p.add_text(title, font_size=11, color="black")
    _front_camera(p, surface.bounds, zoom=1.6)
    return p


def _render(result, out):
    """Render the output PNGs into memory; returns name -> image array."""
    images = {}
    if result.skin_pre is not None:
        p = _plot_surface(result.skin_pre, title="pre-operative face")
        images["face_pre.png"] = p.screenshot(return_img=True)
        p.close()
    if result.skin_post is not None:
        p = _plot_surface(result.skin_post, title="predicted post-operative face")
        images["face_post.png"] = p.screenshot(return_img=True)
        p.close()
        mag = np.linalg.norm(result.skin_post[arrays.DISPLACEMENT], axis=1)
        skin = result.skin_pre.copy()
        skin["|displacement| (mm)"] = mag
        p = _plot_surface(skin, scalars="|displacement| (mm)", cmap="viridis",
                          clim=(0.0, max(float(mag.max()), 1e-3)), title="displacement magnitude")
        images["displacement.png"] = p.screenshot(return_img=True)
        p.close()
    if result.skeleton is not None and result.labels is not None:
        from .figures.osteotomy import osteotomy_panel

        p = osteotomy_panel(result.labels, result.plan, skin=result.skin_pre,
                            skeleton=result.skeleton)
        images["osteotomy.png"] = p.screenshot(return_img=True)
        p.close()
    return images


def write_outputs(result, out, images=None):
    """Write a result's files into ``out``, each atomically.

    Files: ``predicted_skin.vtp`` (predicted skin with ``displacement``),
    ``deformed_mesh.vtu`` (the mesh at its predicted position, with ``displacement`` and
    the ``bc`` arrays), ``skin_pre.vtp``, the PNGs in ``images`` and ``summary.json``
    (seconds per step, skipped steps, the plan). Returns ``result.files``.
    """
    from PIL import Image

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = result.files
    if result.skin_post is not None:
        files["predicted_skin"] = _save(result.skin_post, out / "predicted_skin.vtp")
    if result.skin_pre is not None:
        files["skin_pre"] = _save(result.skin_pre, out / "skin_pre.vtp")
    if result.post is not None:
        deformed = result.post.copy()
        deformed.points = np.asarray(deformed.points) + np.asarray(deformed[arrays.DISPLACEMENT])
        files["deformed_mesh"] = _save(deformed, out / "deformed_mesh.vtu")
    for name, img in (images or {}).items():
        with atomic_path(out / name) as tmp:
            Image.fromarray(np.asarray(img)).save(tmp, format="PNG")
        files[Path(name).stem] = out / name
    summary = {"plan": result.plan.to_dict(), "seconds": result.timings,
               "skipped": result.skipped, "complete": result.complete,
               **({"ct": result.ct_report} if result.ct_report else {}),
               "files": {k: Path(v).name for k, v in files.items()}}
    if result.post is not None:
        u = np.linalg.norm(np.asarray(result.post[arrays.DISPLACEMENT]), axis=1)
        summary.update(n_tets=int(result.post.n_cells), n_points=int(result.post.n_points),
                       max_displacement_mm=float(u.max()))
    files["summary"] = write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return files


def _save(dataset, path):
    with atomic_path(path) as tmp:
        dataset.save(tmp)
    return Path(path)
