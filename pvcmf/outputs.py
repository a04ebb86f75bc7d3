"""Outputs of a prediction: offscreen PNGs and the files of a :class:`pvcmf.pipeline.Result`.

:func:`write_outputs` writes the predicted skin (VTP), the deformed mesh (VTU), the PNGs
and a JSON summary, each atomically (temporary file in the same folder + ``os.replace``).
Rendering delegates to PyVista (off screen), writing to VTK's XML writers and Pillow.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyvista as pv
from PIL import Image

from . import arrays
from ._atomic import atomic_path, write_text
from .figures.osteotomy import osteotomy_panel

__all__ = ["render", "write_outputs"]


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


def render(result):
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
        skin[arrays.DISPLACEMENT_MAGNITUDE] = mag
        p = _plot_surface(skin, scalars=arrays.DISPLACEMENT_MAGNITUDE, cmap="viridis",
                          clim=(0.0, max(float(mag.max()), 1e-3)), title="displacement magnitude")
        images["displacement.png"] = p.screenshot(return_img=True)
        p.close()
    if result.skeleton is not None and result.labels is not None:
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
    (seconds per step, skipped steps, the plan, tissue and bone segment volumes in mL).
    Returns ``result.files``.
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
    for key in ("tissue_volumes", "segment_volumes"):  # mL per tissue / bone segment
        if getattr(result, key, None):
            summary[f"{key}_ml"] = getattr(result, key)
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
