"""Outputs of a prediction: offscreen PNGs and the files of a :class:`pvcmf.pipeline.Result`.

:func:`write_outputs` writes the predicted skin (VTP), the deformed mesh (VTU), the PNGs
and a JSON summary, each atomically (temporary file in the same folder + ``os.replace``).
Rendering delegates to :mod:`pvcmf.figures.face_views` (PyVista off screen, matplotlib),
writing to VTK's XML writers and Pillow. :func:`write_run` writes them into a hidden
sibling folder and renames it onto the output folder: a folder holds one complete run,
never files of two. :func:`check_output_dir` refuses a bad output path before any work,
:func:`run_lock` serialises runs into one folder (:func:`pvcmf.cache.file_lock`) and
removes what a killed run left beside it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import pyvista as pv
from PIL import Image

from . import arrays
from ._atomic import _signals_held, atomic_dir, atomic_path, remove_temporaries, write_text
from .cache import file_lock
from .figures import face_views
from .figures.osteotomy import osteotomy_panel
from .figures.plan_frame import figure_frame, turned_into

log = logging.getLogger(__name__)

__all__ = ["render", "write_outputs", "write_run", "check_output_dir", "check_output_file",
           "run_lock", "RUN_MARKER"]

#: the file that marks a folder as a pvcmf run (a folder without it is never replaced)
RUN_MARKER = "summary.json"


def _check_path(out, name):
    """``out`` as an absolute path; refuse empty paths and paths under a file."""
    if out is None or not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"{name} must be a path (str or pathlib.Path), got {type(out).__name__}")
    if not str(os.fspath(out)).strip():
        raise ValueError(f"{name} must name a folder or file, got an empty path {out!r}")
    path = Path(os.path.abspath(Path(out).expanduser()))
    ancestor = path.parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"{name}={str(out)!r} lies under {ancestor}, which is a file, "
                         "not a folder")
    with _signals_held():  # a Ctrl-C between making and removing it would leave the probe
        try:  # a probe file: permissions, read-only or special file systems all show here
            fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=ancestor)
        except OSError as err:
            raise ValueError(f"{name}={str(out)!r}: cannot write in {ancestor} "
                             f"({err.strerror or err})") from None
        os.close(fd)
        os.remove(probe)
    return path


def check_output_dir(out, name="out", *, replaces=True):
    """Check an output folder before any work; returns it as an absolute path.

    Refused (``ValueError`` naming ``name``): an empty path, an existing file, a path
    under a file, a parent folder that is not writable, and, for a run that replaces
    the folder (``replaces=True``), the current folder and an existing non-empty folder
    that holds no earlier run (no :data:`RUN_MARKER`): a run replaces the whole folder
    and must never delete files it did not write.

    Examples
    --------
    >>> from pvcmf.outputs import check_output_dir
    >>> check_output_dir("")
    Traceback (most recent call last):
    ...
    ValueError: out must name a folder or file, got an empty path ''
    """
    path = _check_path(out, name)
    if path.exists() and not path.is_dir():
        raise ValueError(f"{name}={str(out)!r} is a file, expected a folder")
    if path.parent == path:
        raise ValueError(f"{name}={str(out)!r} is the file system root, expected a folder")
    if not replaces:
        return path
    cwd = Path.cwd()
    if path == cwd or path in cwd.parents:
        raise ValueError(f"{name}={str(out)!r} is (or holds) the current folder {cwd}; a run "
                         "replaces its output folder as a whole: name a new folder")
    if path.is_dir():
        entries = [e for e in os.listdir(path) if not e.startswith(".")]
        if entries and not (path / RUN_MARKER).is_file():
            raise ValueError(
                f"{name}={str(out)!r} is a folder with {len(entries)} "
                f"{'entry' if len(entries) == 1 else 'entries'} but no "
                f"{RUN_MARKER}: it holds no earlier pvcmf run, and a run replaces the whole "
                "folder; choose a new or empty folder"
            )
        if not os.access(path.parent, os.W_OK | os.X_OK):
            raise ValueError(f"{name}={str(out)!r}: its parent folder {path.parent} is not "
                             "writable (the run is built beside it and renamed into place)")
    return path


def check_output_file(out, name="out", suffixes=None):
    """Check an output file path before any work; returns it as an absolute path.

    Refused: an empty path, an existing folder, a path under a file, a folder that is
    not writable, and (with ``suffixes``) another extension.
    """
    path = _check_path(out, name)
    if path.is_dir():
        raise ValueError(f"{name}={str(out)!r} is a folder, expected a file path")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ValueError(f"{name}={str(out)!r} must end in one of {list(suffixes)}, "
                         f"got {path.suffix!r}")
    return path


@contextlib.contextmanager
def run_lock(out):
    """Hold the lock of output folder ``out`` (waiting for a run writing there).

    The lock is the hidden sibling file ``.<name>.lock`` (:func:`pvcmf.cache.file_lock`;
    a lock whose process died is broken). Once held, the temporary siblings a killed run
    left are removed. ``out=None`` does nothing.
    """
    if out is None:
        yield
        return
    out = Path(out)
    lock = out.parent / f".{out.name}.lock"
    if lock.exists():
        log.warning("another pvcmf run is writing to %s; waiting for it", out)
    with file_lock(lock, stale_after=float("inf")):
        for stale in remove_temporaries(out):
            log.warning("removed %s, left by an interrupted run", stale)
        yield


def write_run(result, out, images=None, writer=None):
    """Write a result's files into a temporary sibling of ``out``, then swap it in.

    ``out`` then holds this run's files only (an earlier run there is replaced as a
    whole); an interruption leaves ``out`` as it was. ``writer(result, folder, images)``
    writes the files (default :func:`write_outputs`). Returns ``result.files``.
    """
    out = Path(out)
    with atomic_dir(out) as tmp:
        files = (writer or write_outputs)(result, tmp, images)
    result.files = {key: out / Path(path).name for key, path in files.items()}
    return result.files


def _front_camera(plotter, bounds, zoom=1.0):
    """Look at the face from the front (display frame of :mod:`pvcmf.figures.face_views`)."""
    face_views.set_view(plotter, bounds, "frontal", zoom=zoom)


def _plot_surface(surface, scalars=None, cmap=None, clim=None, title=None, color="peachpuff",
                  window_size=(600, 700), scalar_bar_title=None):
    """One frontal view of ``surface`` (patient frame), photographic convention."""
    p = pv.Plotter(off_screen=True, window_size=list(window_size))
    p.set_background("white")
    kwargs = dict(specular=0.2)
    if scalars is not None:
        face_views.add_patient_mesh(
            p, surface, scalars=scalars, cmap=cmap, clim=clim,
            scalar_bar_args={"title": scalar_bar_title or scalars, "color": "black",
                             "vertical": False, "position_x": 0.15, "position_y": 0.03,
                             "width": 0.7, "title_font_size": 14, "label_font_size": 12},
            **kwargs)
    else:
        face_views.add_patient_mesh(p, surface, color=color, **kwargs)
    if title:
        p.add_text(title, font_size=11, color="black")
    _front_camera(p, face_views.display_bounds(surface), zoom=0.9)
    return p


def _shot(plotter):
    img = plotter.screenshot(return_img=True)
    plotter.close()
    return img


def render(result):
    """Render the output PNGs into memory; returns name -> image array.

    With a pre-operative skin: ``face_pre.png`` (frontal, three-quarter, profile). With a
    prediction also ``face_post.png``, the pre/post comparisons ``face_frontal.png``,
    ``face_three_quarter.png``, ``face_profile.png``, the midsagittal silhouettes
    ``profile_overlay.png``, the signed displacement maps ``displacement_ap.png`` and
    ``displacement_normal.png`` and the magnitude ``displacement.png`` (colour ranges from
    the visible modelled face's 99th percentile). With a skeleton: ``osteotomy.png``.
    See :mod:`pvcmf.figures.face_views`. A plan in the face's axes shows the surfaces turned
    into them (:mod:`pvcmf.figures.plan_frame`), and the face rows say so.
    """
    images = {}
    views = tuple(face_views.VIEWS)
    pre, post, skeleton, axes = _in_plan_frame(result)
    if pre is not None:
        images["face_pre.png"] = _shot(_row(pre, views, "pre-operative" + axes))
    if pre is not None and post is not None:
        images["face_post.png"] = _shot(_row(post, views, "predicted" + axes))
        for view in views:
            images[f"face_{view}.png"] = _shot(face_views.face_comparison(pre, post, (view,)))
        images["profile_overlay.png"] = face_views.chart_image(face_views.profile_overlay(pre, post))
        skin = pre.copy()
        skin.point_data[arrays.DISPLACEMENT] = np.asarray(post[arrays.DISPLACEMENT])
        shown = ("frontal", "profile")
        # colour ranges: the modelled face in view (not the unmoved back of the head)
        seen = face_views.visible_in_views(skin, shown) & face_views.modelled_points(pre)
        for component, name in (("ap", "displacement_ap.png"),
                                ("normal", "displacement_normal.png"),
                                ("magnitude", "displacement.png")):
            images[name] = _shot(face_views.displacement_views(skin, component, shown,
                                                               visible=seen))
    if skeleton is not None and result.labels is not None:
        images["osteotomy.png"] = _shot(osteotomy_panel(result.labels, result.plan, skin=pre,
                                                        skeleton=skeleton))
    return images


def _in_plan_frame(result):
    """The pre-operative and predicted skins and the skeleton, turned into the plan's axes
    where it gives its moves in the face's (:mod:`pvcmf.figures.plan_frame`), and the note
    the face rows' titles then carry."""
    pre, post, skeleton = result.skin_pre, result.skin_post, result.skeleton
    plan = getattr(result, "plan", None)  # (a result-like object may carry no plan)
    frame = None if pre is None else figure_frame(getattr(result, "labels", None), plan)
    if frame is None:
        return pre, post, skeleton, ""
    centre = np.asarray(pre.center)
    turned = [None if m is None else turned_into(m, frame, centre) for m in (pre, post, skeleton)]
    return (*turned, f", {plan.axes} axes")


def _row(skin, views, label):
    """One skin in several views, side by side."""
    p = pv.Plotter(off_screen=True, shape=(1, len(views)), window_size=[400 * len(views), 480],
                   border=False)
    bounds, points = face_views.frame_skins(skin)  # as face_comparison frames them
    for col, view in enumerate(views):
        p.subplot(0, col)
        p.set_background("white", all_renderers=False)
        face_views.add_skin(p, skin, face_views.SKIN_COLOR)  # the scan's cuts apart
        face_views.set_view(p, bounds, view, points=points)
        p.add_text(f"{label}, {face_views.VIEW_TITLES[view]}", font_size=10, color="black")
    return p


def write_outputs(result, out, images=None):
    """Write a result's files into ``out``, each atomically.

    Files: ``predicted_skin.vtp`` (predicted skin with ``displacement``),
    ``deformed_mesh.vtu`` (the mesh at its predicted position, with ``displacement`` and
    the ``bc`` arrays), ``skin_pre.vtp``, the PNGs in ``images`` and ``summary.json``
    (seconds per step, skipped steps, what the run warned about, the plan, tissue and
    bone segment volumes in mL).
    Returns ``result.files``. The command line adds ``report.html``
    (:func:`pvcmf.report.write_report`, a layer above the pipeline).
    """
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
               "warnings": list(getattr(result, "warnings", [])),
               "files": {k: Path(v).name for k, v in files.items()}}
    if result.ct_report:
        summary["ct"] = result.ct_report
    if getattr(result, "working_grid", None):
        summary["working_grid"] = result.working_grid
    for key in ("tissue_volumes", "segment_volumes"):  # mL per tissue / bone segment
        if getattr(result, key, None):
            summary[f"{key}_ml"] = getattr(result, key)
    if result.post is not None:
        u = np.linalg.norm(np.asarray(result.post[arrays.DISPLACEMENT]), axis=1)
        summary.update(n_tets=int(result.post.n_cells), n_points=int(result.post.n_points),
                       max_displacement_mm=float(u.max()))
        fd = result.post.field_data
        if arrays.MTM_INVERTED in fd.keys():  # the solver's flags (pvcmf.mtm.solution_checks)
            ratio = float(fd[arrays.MTM_FREE_RATIO][0])
            summary.update(inverted_cells=int(fd[arrays.MTM_INVERTED][0]),
                           free_over_prescribed=ratio if np.isfinite(ratio) else None)
    files["summary"] = write_text(out / "summary.json", json.dumps(summary, indent=2) + "\n")
    return files


def _save(dataset, path):
    """Write ``dataset`` atomically with VTK's XML writer, without string field data (which
    meshio and other readers refuse), so that every file of a run reads back in meshio, and
    without VTK's internal point and cell arrays (names starting ``vtk``: extraction ids,
    probe masks), which index meshes the run does not write."""
    strings = [k for k in dataset.field_data.keys()
               if np.asarray(dataset.field_data[k]).dtype.kind in "USO"]
    internal = [(data, k) for data in ("point_data", "cell_data")
                for k in getattr(dataset, data).keys() if k.startswith("vtk")]
    if strings or internal:
        dataset = dataset.copy(deep=False)
        for key in strings:
            dataset.field_data.remove(key)
        for data, key in internal:
            getattr(dataset, data).remove(key)
        log.debug("%s: string field data %s and VTK arrays %s not written", Path(path).name,
                  strings, [k for _, k in internal])
    with atomic_path(path) as tmp:
        dataset.save(tmp)
    return Path(path)
