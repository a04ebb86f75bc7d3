"""The planner's web page: trame server, sliders, live 3D view, profile and saving.

:func:`build_app` lays out one page on a trame server (Vuetify 3 widgets): a drawer with
six sliders per segment (translation mm and rotation degrees about the plan's horizontal,
vertical and anterior-posterior axes, :mod:`pvcmf.planner.state`), the plan as TOML, a
file name and a *Save plan* button (:func:`pvcmf.plan.write_plan`, which ``pvcmf
simulate --plan`` reads back); the main area shows the 3D scene (rendered on the server by
VTK offscreen and streamed as images, :class:`trame_vtk.widgets.vtk.VtkRemoteView`) and
the profile before/after (:func:`pvcmf.planner.views.profile_png`). Every slider change
predicts the face for the new plan (:class:`pvcmf.planner.model.PlannerModel`) and
redraws.

:func:`serve` starts the server on the loopback interface; :func:`add_plan_parser` and
:func:`run_plan` are ``pvcmf plan``. trame is imported lazily (the ``planner`` extra:
``pip install "pvcmf[planner]"``).
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from .. import datasets
from ..arguments import add_ct_checks
from ..figures.plan_frame import turned_into
from ..figures.profiles import midline_x
from ..figures.skin_marks import MAP_CUT_WORDS
from ..plan import AXES as PLAN_AXES
from ..plan import Plan, read_plan, write_plan
from .model import prepare_model
from .state import AXES, KINDS, PlanSliders, slider_key
from .views import Scene, data_url, profile_png

log = logging.getLogger(__name__)

__all__ = ["Planner", "add_plan_parser", "build_app", "run_plan", "serve"]

_TRAME_HINT = 'the planner needs trame: pip install "pvcmf[planner]" (trame, trame-vtk, trame-vuetify)'


def _import_trame():
    try:
        from trame.app import get_server
        from trame.ui.vuetify3 import SinglePageWithDrawerLayout
        from trame.widgets import html, vuetify3
        from trame_vtk.widgets import vtk as vtk_widgets
    except ImportError as err:
        raise ImportError(f"{_TRAME_HINT} ({err})") from None
    return get_server, SinglePageWithDrawerLayout, html, vuetify3, vtk_widgets


class Planner:
    """The planner's logic behind the page: sliders -> plan -> scene, profile, file.

    Parameters
    ----------
    model : pvcmf.planner.PlannerModel
        The prepared model.
    save_path : str or pathlib.Path
        Where *Save plan* writes (TOML or JSON by suffix).
    """

    def __init__(self, model, save_path="plan.toml"):
        self.model = model
        self.sliders = PlanSliders(model.segments, model.plan)
        self.save_path = Path(save_path)
        self.scene = Scene(model)
        self._turned = {}  # per kind of face axes: the profile's rest skin, frame, midline
        self.values = (self.sliders.from_plan(model.plan) if model.plan is not None
                       else self.sliders.zero_values())
        self.plan = self.sliders.to_plan(self.values)

    def set_values(self, values):
        """Update to new slider values; return ``(status text, profile data URL)``."""
        self.values = {k: float(values.get(k, 0.0)) for k in self.sliders.keys}
        self.plan = self.sliders.to_plan(self.values)
        start = time.perf_counter()
        signed = self.scene.update(self.plan)
        seconds = time.perf_counter() - start
        skin = signed[~self.scene.on_cut] if not self.scene.on_cut.all() else signed
        edge = f"; {MAP_CUT_WORDS}" if self.scene.on_cut.any() else ""
        status = (f"signed displacement {skin.min():+.1f} .. {skin.max():+.1f} mm{edge} "
                  f"({self.model.kind}, {1000 * seconds:.0f} ms)")
        return status, data_url(profile_png(*self.profile_surfaces()))

    def profile_surfaces(self):
        """``(rest skin, predicted skin, x)`` of the profile: for a plan in the face's axes
        both turned into them (:func:`~pvcmf.figures.plan_frame.turned_into`) and cut at
        their midline, so a head scanned turned shows its midsagittal profile."""
        pre, post = self.model.skin, self.scene.predicted
        if self.plan.axes == "image":
            return pre, post, self.scene.midline
        if self.plan.axes not in self._turned:  # the rest skin turned, and its midline, once
            frame, centre = self.model.plan_axes(self.plan), np.asarray(pre.center)
            rest = turned_into(pre, frame, centre)
            self._turned[self.plan.axes] = (rest, frame, centre, midline_x(rest))
        rest, frame, centre, midline = self._turned[self.plan.axes]
        return rest, turned_into(post, frame, centre), midline

    def set_axes(self, axes):
        """Move the sliders in ``axes`` (:data:`pvcmf.plan.AXES`), keeping their values;
        return ``(status text, profile data URL)``.

        Raises
        ------
        ValueError
            Unknown axes, or axes the model's labels cannot give (no teeth for
            ``"occlusal"``, no landmarks for ``"frankfort"``); the plan is left as it was.
        """
        if axes not in PLAN_AXES:
            raise ValueError(f"axes must be one of {list(PLAN_AXES)}, got {axes!r}")
        template = self.model.plan if self.model.plan is not None else Plan(())
        sliders = PlanSliders(self.model.segments, dataclasses.replace(template, axes=axes))
        self.model.plan_axes(sliders.to_plan(self.values))  # refused before use
        self.sliders = sliders
        return self.set_values(self.values)

    def plan_toml(self):
        """The current plan as the TOML text :func:`pvcmf.plan.write_plan` writes."""
        with tempfile.TemporaryDirectory() as folder:
            return write_plan(self.plan, Path(folder) / "plan.toml").read_text(encoding="utf-8")

    def save(self, path=None):
        """Write the current plan; return the path."""
        return write_plan(self.plan, Path(path) if path else self.save_path)


def build_app(planner, server=None):
    """Lay out the page for ``planner`` on a trame server (a new one by default)."""
    get_server, Layout, html, v3, vtk_widgets = _import_trame()
    server = server or get_server("pvcmf-planner", client_type="vue3")
    state, ctrl = server.state, server.controller
    window = planner.scene.plotter.ren_win
    if window.GetInteractor() is None:  # camera interaction from the page needs one
        from vtkmodules.vtkRenderingCore import vtkRenderWindowInteractor
        from vtkmodules.vtkInteractionStyle import vtkInteractorStyleTrackballCamera
        iren = vtkRenderWindowInteractor()
        iren.SetRenderWindow(window)
        iren.SetInteractorStyle(vtkInteractorStyleTrackballCamera())
    keys = planner.sliders.keys
    for key, value in planner.values.items():
        state[key] = value
    state.plan_axes = planner.plan.axes
    state.save_path = str(planner.save_path)
    state.saved = ""
    state.status, state.profile_src = planner.set_values(planner.values)
    state.plan_toml = planner.plan_toml()
    state.prepare = ", ".join(f"{k} {v:.1f} s" for k, v in planner.model.timings.items())

    @state.change(*keys)
    def _on_slider(**changed):
        try:
            state.status, state.profile_src = planner.set_values({k: state[k] for k in keys})
            state.plan_toml = planner.plan_toml()
        except (ValueError, RuntimeError) as err:
            state.status = f"cannot predict this plan: {err}"
        ctrl.view_update()

    def _save():
        try:
            path = planner.save(state.save_path)
        except (OSError, ValueError) as err:
            state.saved = f"not saved: {err}"
        else:
            state.saved = f"saved {path}"
            log.info("plan saved to %s", path)

    @state.change("plan_axes")
    def _on_axes(**_):
        axes = state.plan_axes
        if axes == planner.plan.axes:
            return
        try:
            state.status, state.profile_src = planner.set_axes(axes)
            state.plan_toml = planner.plan_toml()
        except (ValueError, RuntimeError) as err:
            state.status = f"cannot move in the {axes} axes: {err}"
            state.plan_axes = planner.plan.axes
        ctrl.view_update()

    ctrl.save_plan = _save
    with Layout(server) as layout:
        layout.title.set_text("pvcmf planner")
        with layout.drawer as drawer:
            drawer.width = 380
            _slider_panel(planner, v3, html)
            with html.Div(classes="pa-2"):
                v3.VTextField(v_model=("save_path",), label="save as (.toml / .json)",
                              density="compact", hide_details=True, id="save-path")
                v3.VBtn("Save plan", click=ctrl.save_plan, color="primary", classes="mt-2",
                        id="save-button", block=True)
                html.Div("{{ saved }}", id="saved", classes="text-caption mt-1")
                html.Pre("{{ plan_toml }}", id="plan-toml",
                         style="font-size: 11px; white-space: pre-wrap")
        with layout.content:
            with v3.VContainer(fluid=True, classes="pa-0 fill-height"):
                with html.Div(style="display: flex; width: 100%; height: 100%"):
                    with html.Div(style="flex: 1 1 auto; height: 100%", id="view3d"):
                        view = vtk_widgets.VtkRemoteView(window, ref="view", still_quality=90,
                                                         interactive_ratio=1)
                        ctrl.view_update = view.update
                    with html.Div(style="flex: 0 0 380px; padding: 8px"):
                        html.Div("profile (midsagittal)", classes="text-subtitle-2")
                        html.Img(src=("profile_src",), id="profile", style="width: 100%")
                        html.Div("{{ status }}", id="status", classes="text-caption")
                        html.Div("prepared once: {{ prepare }}", classes="text-caption")
    return server


def _slider_panel(planner, v3, html):
    """The axes the sliders move in (the image's or the face's), then six sliders per
    segment, grouped by segment and kind."""
    html.Div("axes", classes="text-caption px-2 pt-2")
    with v3.VBtnToggle(v_model=("plan_axes",), mandatory=True, density="compact",
                       classes="px-2", id="plan-axes"):
        for axes in PLAN_AXES:
            v3.VBtn(axes, value=axes, id=f"axes-{axes}", size="small")
    for segment in planner.sliders.segments:
        html.Div(segment, classes="text-subtitle-1 px-2 pt-2")
        for kind, label, unit, _ in KINDS:
            html.Div(f"{label} ({unit})", classes="text-caption px-2")
            for axis, axis_label in AXES:
                key = slider_key(segment, kind, axis)
                low, high, step = planner.sliders.ranges(key)
                with html.Div(id=f"slider-{key}", classes="px-2"):
                    v3.VSlider(v_model=(key,), min=low, max=high, step=step,
                               label=axis_label.split(" ")[0], thumb_label=True,
                               density="compact", hide_details=True)


def serve(model, *, port=0, save_path="plan.toml", open_browser=False):
    """Serve the planner for ``model`` on 127.0.0.1 (blocks until stopped)."""
    server = build_app(Planner(model, save_path))
    server.start(port=port, host="127.0.0.1", open_browser=open_browser)


# --------------------------------------------------------------------------- `pvcmf plan`
#: ``pvcmf plan --help``: what the command does and its exit statuses
PLAN_DESCRIPTION = (
    "Prepare the model of a head CT once (segmentation, mesh, plan-response operator), then "
    "serve a planner page on 127.0.0.1: sliders move the maxilla and the mandible, the "
    "predicted face and its profile update live, and 'Save plan' writes a plan file for "
    "pvcmf simulate --plan. Needs the planner extra (pip install \"pvcmf[planner]\"). "
    "Exit status: 0 the server stopped, 2 bad input (the message names the option), "
    "1 a step failed (trame missing included), 130 interrupted.")


def add_plan_parser(sub):
    """Add ``pvcmf plan`` to the ``pvcmf`` subcommands."""
    p = sub.add_parser("plan", help="interactive surgical planner in the web browser",
                       description=PLAN_DESCRIPTION)
    p.add_argument("--ct", required=True,
                   help="CT file or DICOM folder, 'headsq' (VTK's head CT) or 'phantom[:N]' "
                        "(virtual patient N, 1-4)")
    p.add_argument("--series", default=None,
                   help="for a DICOM folder with several series: the one to read (see simulate)")
    p.add_argument("--plan", type=Path, default=None,
                   help="starting plan (.toml/.json); its cut planes define the segments")
    p.add_argument("--axes", choices=PLAN_AXES, default=None,
                   help="directions the sliders move in: the image's, the occlusal plane's or "
                        "the Frankfort horizontal's (default: the starting plan's, else image)")
    p.add_argument("--port", type=int, default=8080, help="port on 127.0.0.1 (default 8080)")
    p.add_argument("--save", type=Path, default=Path("plan.toml"),
                   help="file the Save button writes (default plan.toml)")
    p.add_argument("--n-tets", type=int, default=5000,
                   help="requested number of tetrahedra (default 5000)")
    p.add_argument("--spacing", type=float, default=3.0,
                   help="voxel size (mm) of a virtual patient (default 3)")
    p.add_argument("--flip", default="", help="mirror the CT along these axes (see simulate)")
    add_ct_checks(p, "; for a CT file or folder (headsq is in HU already)")
    p.add_argument("--no-muscles", action="store_true", help="homogeneous soft tissue")
    p.add_argument("--browser", action="store_true", help="open the page in a browser")
    p.add_argument("-v", "--verbose", action="count", default=0, help="log more")
    return p


def _load_ct(args):
    """``(ct, bones, landmarks, start plan, checks)`` for the ``--ct`` argument;
    ``checks``: the units and axes check :func:`prepare_model` runs on the CT (as
    ``pvcmf simulate``: ``--units``, ``--orient`` and ``--shading`` on a scan read from a path; headsq is
    in HU already; a virtual patient is exact and is not checked)."""
    text = str(args.ct)
    if text.startswith("phantom") and not Path(text).exists():
        patient = int(text.split(":")[1]) if ":" in text else 1
        case = datasets.phantom(patient=patient, spacing=args.spacing)
        return case.ct, case.truth, case.landmarks, case.plan, {}
    if text == "headsq" and not Path(text).exists():
        ct, checks = datasets.headsq(), {"units": "hu", "orient": args.orient,
                                         "shading": args.shading}
    else:
        from ..io import read_ct
        ct, checks = read_ct(text, series=args.series), {
            "units": args.units, "orient": args.orient, "shading": args.shading}
    if args.flip:
        from ..pipeline import flip_axes
        ct = flip_axes(ct, args.flip)
    return ct, None, None, None, checks


def _start_plan(plan, axes):
    """The starting plan in ``axes`` (``--axes``): a plan that moves nothing where none was
    given; refused where it contradicts the plan's own axes (its numbers mean those)."""
    if axes is None:
        return plan
    if plan is None:
        return Plan((), axes=axes)
    if plan.axes != axes:
        raise ValueError(f"--axes {axes} contradicts the starting plan's axes = "
                         f"{plan.axes!r}: its numbers are given in those")
    return plan


def run_plan(args):
    """``pvcmf plan``: prepare the model (with a progress bar), then serve the page."""
    plan = read_plan(args.plan) if args.plan is not None else None
    ct, bones, landmarks, case_plan, checks = _load_ct(args)
    plan = _start_plan(plan if plan is not None else case_plan, args.axes)
    model = prepare_model(ct, plan, bones=bones,
                          landmarks=landmarks, n_tets=args.n_tets, muscles=not args.no_muscles,
                          progress_bar=True, **checks)
    log.warning("planner ready (%s): http://127.0.0.1:%d/ (Ctrl+C stops it)", model.kind,
                args.port)
    serve(model, port=args.port, save_path=args.save, open_browser=args.browser)
    return 0
