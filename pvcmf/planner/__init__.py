"""Interactive surgical planner: move the jaws with sliders, see the predicted face live.

``pvcmf plan --ct SCAN [--plan start.toml] [--port N]`` prepares the model once (labels,
mesh, materials, skin, skeleton and the plan-response operator; :func:`prepare_model`)
and serves a local web page (trame) with per-segment translation and rotation sliders in
the plan's (horizontal, vertical, anterior-posterior) terms, the skeleton and the
predicted face with its signed displacement map in 3D, the profile before and after,
and a button that saves the plan as TOML for ``pvcmf simulate``.

Modules: :mod:`~pvcmf.planner.state` (sliders <-> :class:`pvcmf.Plan`),
:mod:`~pvcmf.planner.model` (preparation and the prediction adapter),
:mod:`~pvcmf.planner.views` (3D scene, profile chart) and :mod:`~pvcmf.planner.app`
(the trame page and the command; trame is imported only there, lazily).
"""

from .app import Planner, add_plan_parser, build_app, run_plan, serve
from .model import PlannerModel, make_predictor, prepare_model
from .state import PlanSliders, slider_key
from .views import Scene, profile_png, signed_displacement

__all__ = ["PlanSliders", "Planner", "PlannerModel", "Scene", "add_plan_parser", "build_app",
           "make_predictor", "prepare_model", "profile_png", "run_plan", "serve",
           "signed_displacement", "slider_key"]
