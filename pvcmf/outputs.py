"""Outputs of a prediction: offscreen PNGs and the files of a :class:`pvcmf.pipeline.Result`.

:func:`write_outputs` writes the predicted skin (VTP), the deformed mesh (VTU), the PNGs
and a JSON summary, each atomically (temporary file in the same folder + ``os.replace``).
Rendering delegates to :mod:`pvcmf.figures.face_views` (PyVista off screen, matplotlib),
writing to VTK's XML writers and Pillow.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyvista as pv
from PIL import Image

from . import arrays
from ._atomic import atomic_path, write_text
from .figures import face_views
from .figures.osteotomy import osteotomy_panel

__all__ = ["render", "write_outputs"]


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
    _front_camera(p, face_views.to_display(surface).bounds, zoom=0.9)
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
    the visible face's 99th percentile). With a skeleton: ``osteotomy.png``.
    See :mod:`pvcmf.figures.face_views`.
    """
    images = {}
    views = tuple(face_views.VIEWS)
    pre, post = result.skin_pre, result.skin_post
    if pre is not None:
        images["face_pre.png"] = _shot(_row(pre, views, "pre-operative"))
    if pre is not None and post is not None:
        images["face_post.png"] = _shot(_row(post, views, "predicted"))
        for view in views:
            images[f"face_{view}.png"] = _shot(face_views.face_comparison(pre, post, (view,)))
        images["profile_overlay.png"] = face_views.chart_image(face_views.profile_overlay(pre, post))
        skin = pre.copy()
        skin.point_data[arrays.DISPLACEMENT] = np.asarray(post[arrays.DISPLACEMENT])
        shown = ("frontal", "profile")
        seen = face_views.visible_in_views(skin, shown)
        for component, name in (("ap", "displacement_ap.png"),
                                ("normal", "displacement_normal.png"),
                                ("magnitude", "displacement.png")):
            images[name] = _shot(face_views.displacement_views(skin, component, shown,
                                                               visible=seen))
    if result.skeleton is not None and result.labels is not None:
        images["osteotomy.png"] = _shot(osteotomy_panel(result.labels, result.plan, skin=pre,
                                                        skeleton=result.skeleton))
    return images


def _row(skin, views, label):
    """One skin in several views, side by side."""
    p = pv.Plotter(off_screen=True, shape=(1, len(views)), window_size=[400 * len(views), 480],
                   border=False)
    bounds = face_views.to_display(skin).bounds
    for col, view in enumerate(views):
        p.subplot(0, col)
        p.set_background("white", all_renderers=False)
        face_views.add_patient_mesh(p, skin, color=face_views.SKIN_COLOR, specular=0.2)
        face_views.set_view(p, bounds, view)
        p.add_text(f"{label}, {face_views.VIEW_TITLES[view]}", font_size=10, color="black")
    return p


def write_outputs(result, out, images=None):
    """Write a result's files into ``out``, each atomically.

    Files: ``predicted_skin.vtp`` (predicted skin with ``displacement``),
    ``deformed_mesh.vtu`` (the mesh at its predicted position, with ``displacement`` and
    the ``bc`` arrays), ``skin_pre.vtp``, the PNGs in ``images`` and ``summary.json``
    (seconds per step, skipped steps, the plan). Returns ``result.files``. The command line
    adds ``report.html`` (:func:`pvcmf.report.write_report`, a layer above the pipeline).
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
               "files": {k: Path(v).name for k, v in files.items()}}
    if result.ct_report:
        summary["ct"] = result.ct_report
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
