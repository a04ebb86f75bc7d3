"""A plan on a head scanned chin down and turned: the image's axes or the face's
=============================================================================

A head often lies tilted in the scanner (chin down to keep the eyes out of the beam) and
turned a little about its vertical axis. A plan's numbers are in the image's axes by
default, so "6 mm forward" then moves the mandible along the scanner's axis: in the face's
terms, forward, partly up and partly sideways. With ``axes = "occlusal"`` the plan moves
along the plane of the upper dental arch found in the image, across the skull's mirror
plane (:func:`pvcmf.filters.plan_axes`, :func:`pvcmf.filters.mirror_plane`), which turn
with the head.

Virtual patient 1 is scanned upright, and turned 15 degrees chin down and 10 degrees about
its vertical axis (its CT and its bone segments, about the image's centre). The same plan, the mandible 6 mm forward, is predicted
on both (:func:`pvcmf.planner.prepare_model`, one plan-response operator each). The
predicted midsagittal profiles of the turned head are turned back for the figure, so all
three panels show the face upright: in the image's axes the chin goes up as well as
forward and to the side; in the occlusal axes the turned head gets the upright head's move.
"""

import dataclasses
import os
from pathlib import Path

import numpy as np
import pyvista as pv
from matplotlib.figure import Figure
from scipy import ndimage

import pvcmf
from pvcmf import arrays
from pvcmf.figures.profiles import anterior_profile, midline_x
from pvcmf.plan import Osteotomy, Plan
from pvcmf.planner import prepare_model

pv.OFF_SCREEN = True
OUT = Path(os.environ.get("PVCMF_GALLERY_OUT") or Path(__file__).resolve().parent / "_out")
OUT.mkdir(parents=True, exist_ok=True)
TILT = -15.0  # degrees about the left-right axis: chin down
YAW = 10.0  # degrees about the vertical axis

case = pvcmf.datasets.phantom(patient=1, spacing=3.0)
a = np.radians(TILT)
b = np.radians(YAW)
TURN = (np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
        @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]))
CENTRE = np.asarray(case.ct.center)


def turned(image, names, order, fill):
    """``image``'s arrays turned by TURN about CENTRE, on a grid 30 mm larger each way."""
    pad = int(np.ceil(30.0 / image.spacing[0]))
    out = pv.ImageData(dimensions=np.asarray(image.dimensions) + 2 * pad,
                       spacing=image.spacing,
                       origin=np.asarray(image.origin) - pad * np.asarray(image.spacing))
    points = np.asarray(out.points)
    back = (points - CENTRE) @ TURN + CENTRE  # where each new voxel was before the turn
    index = ((back - np.asarray(image.origin)) / np.asarray(image.spacing)).T
    for name in names:
        volume = np.asarray(image[name]).reshape(image.dimensions, order="F")
        values = ndimage.map_coordinates(volume, index, order=order, cval=fill)
        out[name] = values.astype(volume.dtype)
    return out


ct = turned(case.ct, [arrays.CT], order=1, fill=-1000.0)
truth = turned(case.truth, [arrays.TISSUE, arrays.BONE], order=0, fill=0)
models = {"upright": prepare_model(case.ct, bones=case.truth, n_tets=4000, muscles=False),
          "turned": prepare_model(ct, bones=truth, n_tets=4000, muscles=False)}
plan = Plan((Osteotomy("mandible", translation=(0.0, 0.0, 6.0)),), name="mandible 6 mm forward",
            axes="occlusal")


def upright(surface, name):
    """``surface`` turned back into the upright head's frame (for the turned head)."""
    if name == "upright":
        return surface
    out = surface.copy()
    out.points = (np.asarray(surface.points) - CENTRE) @ TURN + CENTRE
    return out


panels = [("upright", "occlusal"), ("turned", "image"), ("turned", "occlusal")]
fig = Figure(figsize=(10, 5.2))
x = midline_x(models["upright"].skin)
for i, (name, axes) in enumerate(panels):
    model = models[name]
    this = dataclasses.replace(plan, axes=axes)
    pre, post = upright(model.skin, name), upright(model.predict(this), name)
    rest = upright(model.bones["mandible"], name)
    moved = upright(model.skeleton(this)["mandible"], name)
    shift = (np.asarray(moved.points) - np.asarray(rest.points)).mean(axis=0)
    ax = fig.add_subplot(1, 3, i + 1)
    for surface, colour, label in ((pre, "0.5", "pre-operative"), (post, "tab:red", "predicted")):
        line = anterior_profile(surface, x)
        ax.plot(line[:, 0], line[:, 1], color=colour, label=label)
    ax.set_aspect("equal")
    ax.set_xlim(20, 140)
    ax.set_ylim(-130, -15)
    ax.set_title(f"{name}, {axes} axes\nmandible {shift[1]:+.1f} mm forward, "
                 f"{shift[2]:+.1f} up, {shift[0]:+.1f} left", fontsize=9)
    ax.set_xlabel("anterior (y, mm)")
    if i == 0:
        ax.set_ylabel("superior (z, mm)")
        ax.legend(loc="lower left", fontsize=8)
fig.suptitle("The same plan (mandible 6 mm forward) on an upright scan and one turned chin "
             "down and sideways, shown upright")
fig.tight_layout()
fig.savefig(OUT / "plan_axes.png", dpi=90)
