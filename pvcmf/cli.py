"""The ``pvcmf`` command line.

``pvcmf demo --out DIR [--patient N]``
    Runs the whole prediction on a virtual patient (:func:`pvcmf.datasets.phantom`) with
    its Table II plan and writes the predicted skin, the deformed mesh, PNGs and a summary
    of seconds per step into ``DIR``. Steps not installed yet are skipped with a note.
``pvcmf simulate --ct PATH --plan PLAN.toml --out DIR``
    The same on a CT file/folder (DICOM, NIfTI, NRRD, MHA/MHD, VTI) and a plan file;
    ``--ct headsq`` takes VTK's real head CT (:func:`pvcmf.datasets.headsq`), for which
    ``examples/headsq_plan.toml`` is written.
``pvcmf plan --ct SCAN [--plan start.toml] [--port N]``
    Interactive planner in the web browser (:mod:`pvcmf.planner`, needs the ``planner``
    extra): sliders move the jaws, the predicted face updates live, *Save plan* writes a
    plan file for ``pvcmf simulate``.
``pvcmf validate --pred predicted_skin.vtp --post SKIN_OR_CT --out DIR``
    Judges a prediction against a post-operative skin (VTP/STL/PLY/OBJ) or CT:
    point-to-plane ICP on the upper face, signed distances, paper 000 Figs. 6-8, the
    region table (:mod:`pvcmf.study.validate`).

``demo``, ``simulate`` and ``validate`` also write ``report.html``, one offline page with
the 3D view, figures, plan, region table, versions and timings (:mod:`pvcmf.report`;
``--no-report`` to skip); ``--skin-format stl|obj|ply`` adds the predicted skin for
planning software (:func:`pvcmf.io.write_surface`).

Every command checks its ``--out`` path before any work. A run is built in a hidden
sibling of ``--out`` and renamed onto it at the end, under a lock: an interrupted run
(Ctrl-C, SIGTERM, a crash) leaves ``--out`` as it was, and a killed one leaves a hidden
sibling that the next run into that folder removes. Delegates to :mod:`argparse` and
:func:`pvcmf.pipeline.simulate`. This is the only module of pvcmf that prints.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pyvista as pv

from . import arrays, datasets
from ._version import __version__
from .datasets import headsq
from . import report
from .io import (check_export, export, read_ct, read_landmarks, read_plan_file,
                 write_surface)
from .arguments import add_ct_checks
from .figures.offscreen import prefer_egl
from .io.surfaces import SURFACE_FORMATS
from .outputs import check_output_dir, check_output_file
from .pipeline import STEPS, flip_axes, simulate
from .planner import add_plan_parser, run_plan
from .study.validate import validate, write_validation
from .sweeps import add_sweep_parser, run_sweep

log = logging.getLogger(__name__)

#: defaults of ``pvcmf demo``: coarse enough to finish in well under 2 minutes on 2 cores
DEMO_SPACING = 2.0
DEMO_N_TETS = 25_000


#: the exit statuses, as every command's --help states them
EXIT_STATUS = ("Exit status: 0 done, 2 bad input (the message names the option), 1 a step "
               "failed, 130 interrupted.")


def _positive_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _positive_float(text):
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _working_spacing(text):
    """``--working-spacing``: 'auto', 'none' or a voxel size in mm (> 0)."""
    if text.strip().lower() in ("auto", "none"):
        return None if text.strip().lower() == "none" else "auto"
    try:
        return _positive_float(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto', 'none' or a voxel size in mm > 0, got {text!r}") from None


def _flip(text):
    """``--flip``: distinct letters of 'xyz' (may be empty)."""
    axes = text.strip().lower()
    if set(axes) - set("xyz") or len(set(axes)) != len(axes):
        raise argparse.ArgumentTypeError(
            f"expected distinct letters of 'xyz' (e.g. 'yz'), got {text!r}")
    return axes


def _export_path(text):
    """``--export``: a path whose extension a writer knows (:func:`pvcmf.io.check_export`)."""
    try:
        return check_export(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).removeprefix("export: ")) from None


def _region(text):
    """``--region``: 'upper' or six numbers xmin,xmax,ymin,ymax,zmin,zmax (mm), each min
    below its max; returned as given (:func:`pvcmf.study.validate.validate` parses it)."""
    if text.strip() in ("upper", "upper_face"):
        return text.strip()
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not np.all(np.isfinite(values)) or \
            not all(lo < hi for lo, hi in zip(values[::2], values[1::2])):
        raise argparse.ArgumentTypeError(
            "expected 'upper' or six numbers xmin,xmax,ymin,ymax,zmin,zmax in mm, each min "
            f"below its max, got {text!r}")
    return text


def _out_path(text):
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a folder path, got {text!r}")
    return Path(text)


def _common(parser):
    parser.add_argument("--out", required=True, type=_out_path,
                        help="output folder (created if missing)")
    parser.add_argument("--n-tets", type=_positive_int, default=DEMO_N_TETS,
                        help=f"requested number of tetrahedra (default {DEMO_N_TETS})")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--no-figures", action="store_true", help="do not render PNGs")
    parser.add_argument("--no-classify", dest="classify", action="store_false", default=True,
                        help="no fat/muscle classification of the soft tissue from the CT "
                             "values (paper 001; on by default: the muscle the atlas does not "
                             "name, e.g. tongue, temporalis, lips, neck, becomes muscle tissue): "
                             "soft tissue outside the atlas muscles is fat, as in paper 000")
    parser.add_argument("--classify", dest="classify", action="store_true",
                        help="classify fat/muscle (the default; accepted so that command "
                             "lines naming it keep working)")
    parser.add_argument("--fit-skin", action="store_true",
                        help="push the mesh's skin nodes out around the dense skin before "
                             "solving (pvcmf.filters.meshing.fit_to_skin; off by default)")
    parser.add_argument("--no-muscles", action="store_true",
                        help="homogeneous soft tissue: skip the muscle atlas (faster)")
    parser.add_argument("--no-predict", action="store_true",
                        help="only segment, cut the bones and draw the plan (no mesh/solve)")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more (-v info, -vv debug)")
    parser.add_argument("--no-report", action="store_true",
                        help="do not write report.html (pvcmf.report)")
    parser.add_argument("--skin-format", action="append", choices=("stl", "obj", "ply"),
                        default=[], help="also write the predicted skin as "
                        "predicted_skin.stl/.obj/.ply for planning software (repeatable)")


def _add_validate_parser(sub):
    val = sub.add_parser("validate", help="judge a predicted skin against a post-operative "
                                          "skin or CT (ICP, signed distances, Figs. 6-8)",
                         description="Register a post-operative skin or CT onto the prediction "
                         "(ICP on the face that surgery leaves unchanged) and map the signed "
                         "error: validated_skin.vtp, regions.csv, Figs. 6-8, report.html. "
                         + EXIT_STATUS)
    val.add_argument("--pred", required=True, type=Path,
                     help="predicted skin (predicted_skin.vtp of pvcmf simulate, or STL/PLY/OBJ)")
    val.add_argument("--post", required=True, type=Path,
                     help="post-operative skin (.vtp/.stl/.ply/.obj/.vtk) or CT (DICOM folder, "
                          ".nii(.gz), .nrrd, .mha/.mhd, .vti), in any pose")
    val.add_argument("--out", required=True, type=Path, help="output folder")
    val.add_argument("--pre", type=Path, default=None,
                     help="pre-operative skin, the ICP target (default: skin_pre.vtp next to "
                          "--pred if there, else the prediction itself)")
    val.add_argument("--region", type=_region, default="upper",
                     help="ICP region surgery leaves unchanged: 'upper' (forehead, orbits, nose "
                          "bridge; default) or xmin,xmax,ymin,ymax,zmin,zmax in mm")
    val.add_argument("--landmarks", type=Path, default=None,
                     help="Slicer markups (.mrk.json/.fcsv): nasion for the region, nose/lips/"
                          "chin for the face regions")
    val.add_argument("--max-distance", type=_positive_float, default=10.0,
                     help="median distance (mm) above which the skins are said not to overlap")
    val.add_argument("--no-figures", action="store_true", help="do not draw Figs. 6-8")
    val.add_argument("--no-report", action="store_true", help="do not write report.html")
    val.add_argument("--no-progress", action="store_true", help="no progress bar")
    val.add_argument("-v", "--verbose", action="count", default=0,
                     help="log more (-v info, -vv debug)")


def build_parser():
    """The argument parser of the ``pvcmf`` command."""
    parser = argparse.ArgumentParser(
        prog="pvcmf",
        description="Predict the face after cranio-maxillofacial surgery (PyVista + MTM).")
    parser.add_argument("--version", action="version", version=f"pvcmf {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="predict a virtual patient's face after its Table II plan",
                          description="Predict a virtual patient's face after its Table II plan "
                          "and write the skins, the solved mesh, the figures, summary.json and "
                          "report.html into --out. " + EXIT_STATUS)
    _common(demo)
    demo.add_argument("--patient", type=int, choices=(1, 2, 3, 4), default=1,
                      help="virtual patient 1-4 (default 1)")
    demo.add_argument("--spacing", type=_positive_float, default=DEMO_SPACING,
                      help=f"voxel size of the virtual CT in mm (default {DEMO_SPACING})")

    sim = sub.add_parser("simulate", help="predict the face from a CT and a plan file",
                         description="Predict the face from a head CT and a plan file and "
                         "write the skins, the solved mesh, the figures, summary.json and "
                         "report.html into --out (replaced as a whole when the run completes). "
                         + EXIT_STATUS)
    _common(sim)
    sim.add_argument("--ct", required=True, type=Path,
                     help="CT file or DICOM folder (read by pvcmf.read_ct), or 'headsq' for "
                          "VTK's real head CT (pvcmf.datasets.headsq, in the patient frame)")
    sim.add_argument("--series", default=None,
                     help="for a DICOM folder holding several series: the number, UID or part "
                          "of the description of the one to read (default: the CT series with "
                          "the most slices; the log lists the others)")
    sim.add_argument("--plan", required=True, type=Path,
                     help="plan file (.toml or .json); an osteotomy may give a 4x4 'matrix' or "
                          "a 'transform' file (ITK/Slicer .tfm/.h5) instead of translation/"
                          "rotation (pvcmf.io.read_plan_file)")
    sim.add_argument("--landmarks", type=Path, default=None,
                     help="Slicer markups (.mrk.json or .fcsv) with the muscle atlas's "
                          "landmarks (pvcmf.io.read_landmarks); automatic without")
    sim.add_argument("--export", type=_export_path, default=None,
                     help="also write the solved model for another tool: .inp (CalculiX/"
                          "Abaqus), .feb (FEBio) or a meshio format (.vtu, .msh, ...)")
    sim.add_argument("--offset", type=float, default=None,
                     help="HU = scale * value + offset (for scanner units; default 0, "
                          "headsq: its loader's default)")
    sim.add_argument("--scale", type=float, default=None, help="see --offset (default 1)")
    add_ct_checks(sim, "; --offset/--scale imply 'hu'")
    sim.add_argument("--flip", type=_flip, default="",
                     help="mirror the CT along these axes to reach the patient frame (x left, "
                          "y anterior, z superior), e.g. 'yz' for VTK's headsq")
    sim.add_argument("--working-spacing", type=_working_spacing, default="auto",
                     help="'auto' (a scan of more than 134 million voxels, e.g. a cone-beam CT "
                          "at 0.2 mm, is averaged over blocks of whole voxels until it fits; "
                          "default), a voxel size in mm to work at, or 'none' (the scan's grid "
                          "whatever its size: about 50 bytes of memory per voxel)")
    _add_validate_parser(sub)
    add_sweep_parser(sub)  # `pvcmf sweep`: parameter studies on Dask (pvcmf/sweeps.py)
    add_plan_parser(sub)  # `pvcmf plan`: interactive planner (pvcmf/planner)
    return parser


def _setup_logging(verbose):
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)


def _demo(args):
    start = time.perf_counter()
    case = datasets.phantom(patient=args.patient, spacing=args.spacing)
    seconds = time.perf_counter() - start
    print(f"virtual patient {args.patient} at {args.spacing:g} mm ({seconds:.1f} s): "
          f"{case.plan.name or 'plan'}: "
          + "; ".join(f"{o.segment} T{o.translation} R{o.rotation}"
                      for o in case.plan.osteotomies))
    result = simulate(case.ct, case.plan, args.out, bones=case.truth,
                      landmarks=getattr(case, "landmarks", None), n_tets=args.n_tets,
                      predict=not args.no_predict, muscles=not args.no_muscles,
                      classify=args.classify, fit_skin=args.fit_skin,
                      figures=not args.no_figures, progress_bar=not args.no_progress)
    result.timings = {"phantom": seconds, **result.timings}
    return _finish(result, args)


def _finish(result, args):
    """Skin exports (``--skin-format``) and ``report.html`` (unless ``--no-report``)."""
    for fmt in args.skin_format:
        if result.skin_post is not None:
            result.files[f"skin_{fmt}"] = write_surface(result.skin_post,
                                                        args.out / f"predicted_skin.{fmt}")
    if not args.no_report and args.out.is_dir():
        start = time.perf_counter()
        result.files["report"] = report.write_report(args.out, result=result)
        result.timings["report"] = time.perf_counter() - start
    return result


def _simulate(args):
    args.offset_given, args.scale_given = args.offset is not None, args.scale is not None
    args.offset = 0.0 if args.offset is None else args.offset
    args.scale = 1.0 if args.scale is None else args.scale
    if args.export is not None and args.no_predict:
        raise ValueError(f"--export={str(args.export)!r} writes the solved model, which "
                         "--no-predict does not make: drop one of them")
    plan = read_plan_file(args.plan)  # fail on a bad plan before reading the CT
    landmarks = read_landmarks(args.landmarks) if args.landmarks else None
    start = time.perf_counter()
    if str(args.ct) == "headsq" and not args.ct.exists():
        ct = headsq(offset=args.offset if args.offset_given else None,
                    scale=args.scale if args.scale_given else None)
    else:
        ct = read_ct(args.ct, offset=args.offset, scale=args.scale, series=args.series)
    if args.flip:
        ct = flip_axes(ct, args.flip)
    seconds = time.perf_counter() - start
    units = args.units
    if units == "auto" and (args.offset_given or args.scale_given or str(args.ct) == "headsq"):
        units = "hu"  # already mapped to HU by the given offset/scale or by headsq()
    result = simulate(ct, plan, args.out, landmarks=landmarks, n_tets=args.n_tets,
                      predict=not args.no_predict, muscles=not args.no_muscles,
                      classify=args.classify, fit_skin=args.fit_skin,
                      figures=not args.no_figures, progress_bar=not args.no_progress,
                      units=units, orient=args.orient, working_spacing=args.working_spacing,
                      shading=args.shading)
    result.timings = {"read": seconds, **result.timings}
    if args.export is not None and result.post is not None:  # --export: the solved model
        result.files["export"] = export(result.post, args.export)
    return _finish(result, args)


def _case_name(pred):
    """The case's name in the figures: the run folder's name for a ``pvcmf simulate``
    output (``RUN/predicted_skin.vtp``), else the file's stem."""
    pred = Path(pred).absolute()
    if pred.name == "predicted_skin.vtp" and pred.parent.name:
        return pred.parent.name
    return pred.stem


def _check_validate_inputs(args):
    """``--pred``, ``--post`` and ``--pre`` exist and ``--pred``/``--pre`` are surfaces,
    before any work; the message names the option."""
    for name in ("pred", "post", "pre"):
        path = getattr(args, name)
        if path is not None and not path.exists():
            raise FileNotFoundError(f"--{name}={str(path)!r} does not exist")
    for name in ("pred", "pre"):
        path = getattr(args, name)
        if path is not None and (path.is_dir() or path.suffix.lower() not in SURFACE_FORMATS):
            raise ValueError(f"--{name}={str(path)!r} must be a skin surface file ending in "
                             f"one of {', '.join(SURFACE_FORMATS)}")


def _validate(args):
    _check_validate_inputs(args)
    pre = args.pre
    if pre is None and (args.pred.parent / "skin_pre.vtp").exists():
        pre = args.pred.parent / "skin_pre.vtp"
    landmarks = read_landmarks(args.landmarks) if args.landmarks else None
    v = validate(args.pred, args.post, pre=pre, region=args.region, landmarks=landmarks,
                 max_distance=args.max_distance, progress_bar=not args.no_progress)
    inputs = {"pred": args.pred, "post": args.post, "pre": pre or "(the prediction)",
              "region": args.region, "landmarks": args.landmarks or "(none)"}
    args.out.mkdir(parents=True, exist_ok=True)
    figures = {} if args.no_figures else report.validation_figures(v.skin, args.out,
                                                                   case=_case_name(args.pred))
    write_validation(v, args.out, inputs=inputs, extra_files=figures)
    if not args.no_report:
        v.files["report"] = report.write_report(args.out, title=f"Validation: {args.pred}")
    return v


#: columns of regions.csv that ``validate`` prints, and their printed names: the signed
#: median and the percentiles of the unsigned distance
VALIDATION_COLUMNS = {"region": "region", "n": "points", "median": "signed median",
                      "p50": "|d| p50", "p90": "|d| p90", "p95": "|d| p95",
                      "within_1mm": "% within 1 mm", "within_2mm": "% within 2 mm"}


def _report_validation(v):
    table = v.table[list(VALIDATION_COLUMNS)].rename(columns=VALIDATION_COLUMNS)
    print(table.to_string(index=False, float_format=lambda x: f"{x:.2f}"))
    print("(distances in mm, + where the prediction lies outside the actual skin; the "
          "percentiles are of |distance|)")
    reg = v.registration
    print(f"\nICP on the unchanged region: RMS {reg['rms_mm']:.3f} mm, "
          f"{'converged' if reg['converged'] else 'NOT converged'}")
    print("\nwrote:")
    for path in v.files.values():
        print(f"  {path}")


def _report(result):
    width = max(len(s) for s in (*STEPS, "phantom"))
    print("\nseconds per step")
    for step, seconds in result.timings.items():
        print(f"  {step:<{width}}  {seconds:7.2f}")
    print(f"  {'total':<{width}}  {sum(result.timings.values()):7.2f}")
    for step, why in result.skipped.items():
        if "given" not in why and "no output" not in why:
            print(f"  skipped {step}: {why}")
    if result.post is not None:
        u = np.linalg.norm(np.asarray(result.post[arrays.DISPLACEMENT]), axis=1)
        print(f"\nprediction: {result.post.n_cells} tetrahedra, max displacement {u.max():.2f} mm")
        fd = result.post.field_data
        if arrays.MTM_INVERTED in fd.keys():
            print(f"solution check: {int(fd[arrays.MTM_INVERTED][0])} inverted tetrahedra, largest "
                  f"free displacement {float(fd[arrays.MTM_FREE_RATIO][0]):.2f} x the largest "
                  "prescribed move")
    else:
        print("\nno prediction (meshing / materials / solver not available): "
              "segmentation and figures only")
    if result.warnings:
        print(f"\n{len(result.warnings)} warning(s), also in summary.json and report.html:")
        for message in result.warnings:
            print(f"  {message}")
    print("\nwrote:")
    for path in result.files.values():
        print(f"  {path}")


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that it cleans up like Ctrl-C."""


def _terminate(signum, frame):
    raise Terminated()


def _check_out(args):
    """Check ``--out`` before any work (a folder; a .csv/.parquet file for ``sweep``)."""
    if getattr(args, "out", None) is None:
        return
    if getattr(args, "export", None) is not None:
        args.export = check_output_file(args.export, "--export")
    if args.command == "sweep":
        check_output_file(args.out, "--out", suffixes=(".csv", ".parquet"))
    else:  # validate writes beside what is there; demo and simulate replace the folder
        args.out = check_output_dir(args.out, "--out", replaces=args.command != "validate")


def main(argv=None):
    """Entry point of the ``pvcmf`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _setup_logging(args.verbose)
    pv.OFF_SCREEN = True
    prefer_egl()
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        if args.command == "plan":  # serves until stopped; nothing to report
            return run_plan(args)
        _check_out(args)
        result = {"demo": _demo, "simulate": _simulate, "sweep": _sweep,
                  "validate": _validate}[args.command](args)
    except KeyboardInterrupt as err:
        print("interrupted: the output folder was left as it was", file=sys.stderr)
        return 143 if isinstance(err, Terminated) else 130
    except (ValueError, TypeError, FileNotFoundError) as err:  # bad input
        if args.verbose >= 2:
            raise
        print(f"pvcmf {args.command}: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:  # a step failed: say which, keep the traceback for -vv
        if args.verbose >= 2:
            raise
        print(f"pvcmf {args.command}: failed: {type(err).__name__}: {err}\n"
              f"(run with -vv for the traceback; the output folder was left as it was)",
              file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGTERM, previous)
    {"sweep": _report_sweep, "validate": _report_validation}.get(args.command, _report)(result)
    return 0


def _sweep(args):
    return run_sweep(args)


def _report_sweep(result):
    path, df = result
    cols = [c for c in ("case", *df.attrs.get("grid", {}), "p50", "p90", "p95", "within_2mm", "error")
            if c in df]
    print(df[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print(f"\n{len(df)} rows ({df.attrs['n_computed']} computed, {df.attrs['n_cached']} from the "
          f"cache, {df.attrs['n_failed']} failed) in {df.attrs['wall_time']:.1f} s")
    print(f"wrote {path}")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
