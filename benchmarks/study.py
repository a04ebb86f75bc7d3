"""Benchmark: the independent truth's convergence and cost, and the study's paired inference.

Not run by CI. Heavy (NGSolve P2 solves of minutes each): run on a quiet machine.

1. ``--refinement``: per virtual patient, :func:`pvcmf.truth.independent.independent_truth_grid`
   at the requested ``--counts`` (P2), each solve's cost (dofs, Newton iterations,
   factorisations, seconds); the exact skin moved by each truth
   (:mod:`pvcmf.truth.refinement`), and the p50 / p90 / max of its change between
   successive counts. Converged when the p90 between the two finest is <= 0.1 mm.
   With ``--mesher graded`` the sequence is the face sizes ``--face-mm`` (coarse to
   fine), the finest count setting the size elsewhere; ``--face-margin-mm M`` grows the
   fine ball to hold the soft tissue within M mm of the moved bones
   (:func:`pvcmf.truth.graded.face_ball`). ``--patients``: the phantoms 1-4 of
   :func:`pvcmf.datasets.phantom`, and from 101 on the cohort's patients (seed 0, as the
   cohort study builds them: ``truth_refinement.refinement_case``).
2. ``--compare``: the study (``study_predictor(truth=...)``) of "proposed",
   "state_of_the_art" and the controls, and :func:`pvcmf.study.inference.compare_methods`
   per patient and over the patients.
3. ``--cohort N``: N seeded patients of :func:`pvcmf.study.cohort.cohort` through both
   models with oracle inputs and CT-only (automatic segmentation, bone segments, atlas
   fit), paper 000's claims tested over the patients, overall and per face region
   (:func:`pvcmf.study.inference.claims_table`), paper 001's models (homogeneous,
   inhomogeneous, a Poisson-ratio sweep, a finer mesh) and claims
   (:func:`pvcmf.study.claims.paper001_claims`; the mesh-size claim, ``--n-tets``
   against ``--fine-tets``, in its own section with the per-patient distance between the
   two meshes' skins, :func:`mesh_note`), cost per patient cold and warm (warm:
   the patients and the judged skins read from the cache, checked bit for bit against
   the cold run, and the claims computed again): writes ``docs/benchmarks/cohort.md``.
   Its sentence on the truth's convergence is read from the table of
   ``truth_refinement.md`` (``truth_refinement.truth_note``). ``--truth-mesher``,
   ``--truth-face-mm``, ``--truth-materials``, ``--truth-face-margin-mm``: the independent
   truth's options (``graded``, a face size or one per moved segment
   (``maxilla=3.2,mandible=4.0``: each patient's truth at the size where the refinement
   converged for the segment its plan moves), ``field``, a margin: the truth of the
   refinement study, solved as it solves it).
4. ``--blend-mm B B ...``: the first of ``--patients`` at the face sizes ``--face-mm``
   (graded, the last of ``--counts`` elsewhere) and each blend width of the truth's
   osteotomy blend (:mod:`truth_blend`): the refinement change per blend and the skin's
   change between blends; writes ``docs/benchmarks/truth_blend.md``.

Writes markdown tables to ``docs/benchmarks/truth_refinement.md`` (1, 2; ``--page`` another
file) with the command and machine.

Run::

    python benchmarks/study.py --refinement --patients 1 --counts 8000 16000 32000
    python benchmarks/study.py --refinement --patients 1 2 3 4 --spacing 3 \
        --counts 4000 8000 16000 --order-check --fine 40000
    python benchmarks/study.py --refinement --mesher graded --materials field \
        --patients 1 2 3 4 --spacing 3 --counts 30000 --face-mm 4.0 3.2 2.56 --until-converged
    python benchmarks/study.py --refinement --mesher graded --materials field \
        --patients 1 2 3 4 --spacing 3 --counts 30000 --face-mm 4.0 3.2 2.56 \
        --face-margin-mm 30 --until-converged
    python benchmarks/study.py --refinement --mesher graded --materials field \
        --patients 1 2 3 4 102 103 --spacing 3 --counts 30000 --face-mm 4.0 3.2 2.56 \
        --face-margin-mm 30 --until-converged
    python benchmarks/study.py --compare --truth independent --patients 1 2 3 4
    python benchmarks/study.py --cohort 2 --spacing 3 --n-tets 8000 --truth-tets 4000
    python benchmarks/study.py --cohort 16 --spacing 3 --n-tets 30000 --truth-tets 2000 \
        --fine-tets 60000
    python benchmarks/study.py --cohort 16 --spacing 3 --n-tets 30000 --truth-tets 30000 \
        --truth-mesher graded --truth-face-mm maxilla=3.2,mandible=4.0 \
        --truth-face-margin-mm 30 --truth-materials field --fine-tets 60000
    python benchmarks/study.py --blend-mm 4 8 2 --patients 1 --spacing 3 --counts 30000 \
        --face-mm 4.0 3.2 --materials field
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
import platform
import sys
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays
from pvcmf.study.cohort import cohort_parameters, virtual_patient
from pvcmf.study.claims import mesh_size_table, paper001_claims, region_table
from pvcmf.study.inference import PAPER_CLAIMS, REGION_GROUPS, claims_table, compare_methods
from pvcmf.study.paper001 import FINE_METHOD, NU_GRID, PAPER001_AUTO_METHODS, nu_method
from pvcmf.study.validation import run_study, study_predictor
from pvcmf.truth.graded import check_face_size

sys.path.insert(0, str(Path(__file__).resolve().parent))
from truth_refinement import (  # noqa: E402 (the refinement study: benchmarks/truth_refinement.py)
    PAGE, fine_truth_cost, order_check, refinement, truth_note,
)
import truth_blend  # noqa: E402 (the truth's blend width: benchmarks/truth_blend.py)
from cohort_page import (  # noqa: E402 (the cohort's page: benchmarks/cohort_page.py)
    COHORT_METHODS, REGION_METHODS, _markdown, cohort_page, mesh_note,
)


def compare(patients, truth, spacing, n_tets, truth_tets, **truth_options):
    predict = study_predictor(spacing=spacing, n_tets=n_tets, truth_tets=truth_tets,
                              truth=None if truth == "reference" else truth, **truth_options)
    methods = ("proposed", "state_of_the_art", "no_muscles", "wrong_nu")
    skins, _, _ = run_study(predict, patients=patients, methods=methods)
    out = ["## Paired inference", ""]
    for other in methods[1:]:
        table = compare_methods(skins, "proposed", other)
        out.append(f"proposed vs {other}:\n")
        out.append(_markdown(table.round(3)))
        out.append("")
    return "\n".join(out)


COHORT_PAGE = PAGE.parent / "cohort.md"


def _claims(skins):
    """Paper 000's claims with oracle inputs, CT-only, and per face region (p90, oracle)."""
    claims = list(PAPER_CLAIMS)
    claims += [(f"{c} [CT-only]", f"{a}_auto", f"{b}_auto", st) for c, a, b, st in PAPER_CLAIMS]
    claims += [(f"{PAPER_CLAIMS[1][0].replace(' (p90)', '')} on the {region} (p90)",
                "proposed", "state_of_the_art", "p90", region) for region in REGION_GROUPS]
    return _columns(claims_table(skins, claims))


def _columns(table):
    cols = ["claim", "statistic", "n", "median_a", "median_b", "difference", "ci_low",
            "ci_high", "p_value",
            "effect_size", "verdict", "holds"]
    return table[[c for c in cols if c in table.columns]]



def _cohort_results(skins, tables, timing, n_tets, fine_tets):
    import pandas as pd

    t = time.perf_counter()
    paper001, nu_table, spread = paper001_claims(skins, sizes=(n_tets, fine_tets))
    claims, regions = _claims(skins), region_table(skins, REGION_METHODS)
    return {"table": pd.concat(tables, ignore_index=True), "claims": claims,
            "paper001": _columns(paper001), "nu": nu_table, "spread": spread,
            "regions": regions, "mesh": mesh_size_table(skins), "cost": pd.DataFrame(timing),
            "claims_seconds": time.perf_counter() - t,
            "fine_tets": fine_tets, "n_patients": len(skins)}


def _same_skins(cold, warm):
    """Whether two runs' judged skins of one patient are bit-identical: the same methods,
    points, and every point and field array."""
    if list(cold) != list(warm):
        return False
    for method, a in cold.items():
        b = warm[method]
        if not np.array_equal(np.asarray(a.points), np.asarray(b.points)):
            return False
        for store_a, store_b in ((a.point_data, b.point_data), (a.field_data, b.field_data)):
            if sorted(store_a.keys()) != sorted(store_b.keys()):
                return False
            if not all(np.array_equal(np.asarray(store_a[k]), np.asarray(store_b[k]),
                                      equal_nan=np.asarray(store_a[k]).dtype.kind == "f")
                       for k in store_a.keys()):
                return False
    return True


def cohort_study(n, seed, spacing, n_tets, truth_tets, truth, cache_dir=None, fine_tets=None,
                 nus=NU_GRID, checkpoint=None, every=4, warm=None, truth_mesher="lattice",
                 truth_face_mm=None, truth_materials="cells", truth_face_margin_mm=0.0):
    """Run ``n`` seeded cohort patients through both input modes, twice (cold, warm).

    Both runs use one cache folder (``cache_dir``, default a new temporary one, so the cold
    run starts from empty caches): the cold run builds the patients, solves the truths,
    runs every pipeline and judges every prediction, the warm run (fresh predictors) reads
    the patients and the judged skins from the cache and computes the statistics and, over
    the patients it repeats, the claims again; each warm patient's judged skins are
    compared bit for bit with the cold ones (``identical``).
    ``checkpoint(results, status)`` is called with the results so far after every
    ``every`` cold patients and after the cold run, so a run stopped early leaves a
    labelled page. ``warm``: how many patients the warm run repeats (default all).
    ``truth_mesher``, ``truth_face_mm``, ``truth_materials``, ``truth_face_margin_mm``:
    the independent truth's options (``study_predictor``)."""
    tmp = None if cache_dir else tempfile.TemporaryDirectory(prefix="pvcmf_cohort_")
    cache_dir = cache_dir or tmp.name
    draw = cohort_parameters(n, seed)
    fine_tets = fine_tets or 2 * n_tets
    methods = COHORT_METHODS + ("homogeneous", "inhomogeneous") + PAPER001_AUTO_METHODS + tuple(
        nu_method(nu) for nu in nus if nu_method(nu) != "homogeneous") + (FINE_METHOD,)
    timing, skins, tables, warm_skins, warm_tables = [], {}, [], {}, []
    for run in ("cold", "warm"):
        for i, (params, plan) in enumerate(draw):  # a few patients, a handful of pipelines
            if run == "warm" and warm is not None and i >= warm:
                break
            t = time.perf_counter()
            case = virtual_patient(params, plan, spacing=spacing, number=101 + i, cache=True,
                                   cache_dir=cache_dir)
            p = case.patient
            predict = study_predictor(spacing=spacing, n_tets=n_tets, truth_tets=truth_tets,
                                      truth=None if truth == "reference" else truth,
                                      cases={p: case}, cache_dir=cache_dir,
                                      prediction_cache=True, fine_tets=fine_tets,
                                      truth_mesher=truth_mesher, truth_face_mm=truth_face_mm,
                                      truth_materials=truth_materials,
                                      truth_face_margin_mm=truth_face_margin_mm)
            s, _, tab = run_study(predict, patients=(p,), methods=methods, regions=False)
            timing.append({"run": run, "patient": p, "seconds": time.perf_counter() - t,
                           "p90_change_mm": np.nan, "identical": None})
            tab["excluded"] = [int(s[p][m].field_data[arrays.STUDY_EXCLUDED][0])
                               for m in tab["method"]]
            if run == "cold":
                skins.update(s)
                tables.append(tab)
            else:  # the warm run reads what the cold one computed: the same numbers
                warm_skins.update(s)
                warm_tables.append(tab)
                cold = tables[i].set_index("method")["p90"].loc[list(tab["method"])]
                timing[-1]["p90_change_mm"] = float(np.abs(cold.to_numpy() - tab["p90"]).max())
                timing[-1]["identical"] = (_same_skins(skins[p], s[p])
                                           and tables[i].equals(tab))
            print(timing[-1], flush=True)
            done = i + 1
            if (checkpoint is not None and run == "cold" and done >= 2
                    and (done % every == 0 or done == len(draw))):
                checkpoint(_cohort_results(skins, tables, timing, n_tets, fine_tets),
                           f"partial: {done} of {len(draw)} patients, cold run only "
                           "(the warm run not yet made)")
    if tmp is not None:
        tmp.cleanup()
    out = _cohort_results(skins, tables, timing, n_tets, fine_tets)
    if warm_skins:  # the claims over the warm patients, timed: part of a warm run's cost
        again = _cohort_results(warm_skins, warm_tables, timing, n_tets, fine_tets)
        out["warm_claims_seconds"] = again["claims_seconds"]
        out["warm_claims_patients"] = len(warm_skins)
        if len(warm_skins) == len(skins):
            out["warm_claims_identical"] = all(
                out[k].equals(again[k])
                for k in ("claims", "paper001", "nu", "regions", "mesh"))
    return out


def _face_size(text):
    """``--truth-face-mm``: a size (``4.0``) or sizes per segment
    (``maxilla=3.2,mandible=4.0``), checked by :func:`pvcmf.truth.graded.check_face_size`."""
    try:
        if "=" not in text:
            return check_face_size(float(text))
        pairs = [item.split("=") for item in text.split(",")]
        return check_face_size({k.strip(): float(v) for k, v in pairs})
    except ValueError as exc:
        raise argparse.ArgumentTypeError(
            f"a size in mm (4.0) or sizes per segment (maxilla=3.2,mandible=4.0), got "
            f"{text!r} ({exc})") from None


def _truth_options(args):
    """The independent truth's options of the command line (``study_predictor``'s names)."""
    return {"truth_mesher": args.truth_mesher, "truth_face_mm": args.truth_face_mm,
            "truth_materials": args.truth_materials,
            "truth_face_margin_mm": args.truth_face_margin_mm}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--refinement", action="store_true")
    ap.add_argument("--compare", action="store_true")
    ap.add_argument("--cohort", type=int, default=0, metavar="N",
                    help="run N seeded cohort patients in both input modes, write cohort.md")
    ap.add_argument("--seed", type=int, default=0, help="cohort seed")
    ap.add_argument("--cache-dir", default=None,
                    help="cohort: cache folder of truths and predictions (default: a new "
                         "temporary one, so the cold run is cold)")
    ap.add_argument("--fine-tets", type=int, default=0, metavar="N",
                    help="cohort: tetrahedra of the finer mesh of paper 001's mesh-size "
                         "claim (default: twice --n-tets)")
    ap.add_argument("--warm", type=int, default=None, metavar="N",
                    help="cohort: the warm run repeats the first N patients (default all)")
    ap.add_argument("--nu-grid", type=float, nargs="+", default=list(NU_GRID),
                    help="cohort: Poisson ratios of the homogeneous model's sweep")
    ap.add_argument("--truth", default="independent", choices=["independent", "reference"])
    ap.add_argument("--patients", type=int, nargs="+", default=[1],
                    help="refinement: phantoms 1-4 and, from 101 on, the cohort's patients "
                         "(seed 0)")
    ap.add_argument("--counts", type=int, nargs="+", default=[8000, 16000, 32000])
    ap.add_argument("--spacing", type=float, default=2.0)
    ap.add_argument("--order-check", action="store_true",
                    help="with --refinement: P3 against P2 on the finest mesh of the first "
                         "patient (small-strain control law)")
    ap.add_argument("--fine", type=int, default=0, metavar="N",
                    help="with --refinement: also solve one truth of N tetrahedra for the "
                         "first patient, its cost and its change from the finest count")
    ap.add_argument("--fine-patients", type=int, nargs="+", default=None,
                    help="with --fine: the patients of the finer truth (default: the first)")
    ap.add_argument("--mesher", default="lattice", choices=["lattice", "conforming", "graded"],
                    help="with --refinement: the independent truth's mesher")
    ap.add_argument("--face-mm", type=float, nargs="+", default=None,
                    help="with --refinement --mesher graded: the face sizes (mm) of the "
                         "sequence, coarse to fine (the finest --counts sets the size "
                         "elsewhere)")
    ap.add_argument("--face-margin-mm", type=float, default=0.0, metavar="MM",
                    help="with --refinement --mesher graded: the fine ball also holds the "
                         "soft tissue within MM of the moved bones")
    ap.add_argument("--until-converged", action="store_true",
                    help="refinement: stop a patient's sequence once its skin changes by "
                         "p90 <= 0.1 mm from the level before")
    ap.add_argument("--blend-mm", type=float, nargs="+", default=None, metavar="MM",
                    help="the truth's osteotomy blend widths to compare (the first is the "
                         "reference; needs two --face-mm): writes truth_blend.md")
    ap.add_argument("--materials", default="cells", choices=["cells", "field"],
                    help="with --refinement: the independent truth's materials (per "
                         "tetrahedron, or a field of the position)")
    ap.add_argument("--page", type=Path, default=PAGE,
                    help="with --refinement or --compare: the page to write (default "
                         "docs/benchmarks/truth_refinement.md, which the cohort page reads)")
    ap.add_argument("--no-cache", action="store_true",
                    help="solve every truth again (default: reuse the on-disk cache)")
    ap.add_argument("--n-tets", type=int, default=30_000)
    ap.add_argument("--truth-tets", type=int, default=30_000)
    ap.add_argument("--truth-mesher", default="lattice",
                    choices=["lattice", "conforming", "graded"],
                    help="cohort, --compare: the independent truth's mesher (graded and "
                         "conforming solve as the refinement study does)")
    ap.add_argument("--truth-face-mm", type=_face_size, default=None, metavar="MM",
                    help="cohort, --compare, with --truth-mesher graded: the face size (mm), "
                         "or one per moved segment (maxilla=3.2,mandible=4.0: each "
                         "patient's truth takes the smallest of the segments its plan "
                         "moves); --truth-tets sets the size elsewhere")
    ap.add_argument("--truth-face-margin-mm", type=float, default=0.0, metavar="MM",
                    help="cohort, --compare, with --truth-mesher graded: the fine ball also "
                         "holds the soft tissue within MM of the moved bones")
    ap.add_argument("--truth-materials", default="cells", choices=["cells", "field"],
                    help="cohort, --compare: the independent truth's materials")
    ap.add_argument("-v", "--verbose", action="store_true", help="log the steps")
    args = ap.parse_args(argv)
    if args.verbose:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    title = ("Validation study: the truth's convergence and the paired inference"
             if args.compare or args.cohort or not args.refinement else
             "The independent truth's convergence: patients "
             + ", ".join(str(p) for p in args.patients))
    parts = [f"# {title}", "",
             f"Command: `python benchmarks/study.py {' '.join(sys.argv[1:] if argv is None else argv)}`  ",
             f"Machine: {platform.machine()}, Python {sys.version.split()[0]}, "
             f"pvcmf {pvcmf.__version__}.", ""]
    if args.blend_mm:
        command = "python benchmarks/study.py " + " ".join(sys.argv[1:] if argv is None else argv)
        rows = truth_blend.blend_rows(args.patients[0], args.spacing, args.counts[-1],
                                      args.face_mm or [], args.blend_mm,
                                      materials=args.materials, cache=not args.no_cache,
                                      face_margin_mm=args.face_margin_mm)
        truth_blend.PAGE.write_text(truth_blend.blend_page(
            *rows, command, f"{platform.machine()}, Python {sys.version.split()[0]}, "
            f"pvcmf {pvcmf.__version__}"))
        print(truth_blend.PAGE.read_text())
        if not (args.refinement or args.compare or args.cohort):
            return
    if args.refinement:
        parts.append(refinement(args.patients, args.counts, args.spacing,
                                cache=not args.no_cache, mesher=args.mesher,
                                materials=args.materials, face_mm=args.face_mm,
                                until=0.1 if args.until_converged else None,
                                face_margin_mm=args.face_margin_mm))
        if args.order_check:
            parts[-1] += order_check(args.patients[0], args.counts[-1], args.spacing,
                                     args.mesher)
        for patient in (args.fine_patients or args.patients[:1]) if args.fine else ():
            parts[-1] += fine_truth_cost(patient, args.counts, args.fine,
                                         args.spacing, cache=not args.no_cache,
                                         mesher=args.mesher, materials=args.materials)
    if args.compare:
        parts.append(compare(args.patients, args.truth, args.spacing, args.n_tets,
                             args.truth_tets, **_truth_options(args)))
    if args.cohort:
        command = "python benchmarks/study.py " + " ".join(sys.argv[1:] if argv is None else argv)

        def write(res, status="complete"):
            for name in ("table", "claims", "paper001", "nu", "regions", "mesh", "cost"):
                res[name].to_csv(Path(tempfile.gettempdir()) / f"pvcmf_cohort_{name}.csv",
                                 index=False)
            COHORT_PAGE.write_text(cohort_page(args, res, command, status))

        res = cohort_study(args.cohort, args.seed, args.spacing, args.n_tets,
                           args.truth_tets, args.truth, args.cache_dir,
                           fine_tets=args.fine_tets, nus=tuple(args.nu_grid), checkpoint=write,
                           warm=args.warm, **_truth_options(args))
        write(res)
        print(COHORT_PAGE.read_text())
        if not (args.refinement or args.compare):
            return
    args.page.write_text("\n".join(parts) + "\n")
    print("\n".join(parts))


if __name__ == "__main__":
    main()
