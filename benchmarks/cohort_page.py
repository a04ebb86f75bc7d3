"""The cohort study's page (``docs/benchmarks/cohort.md``), written by ``benchmarks/study.py``.

Turns the study's results (per-patient errors, the claims' tests, the Poisson-ratio sweep,
the mesh-size comparison, the per-region errors and the cost of the cold and warm runs) into
markdown: the verdicts, the mesh-size section (:func:`mesh_note`), the tables and the cost
paragraph. Pure formatting: it runs nothing and reads only what it is given.
"""

from __future__ import annotations

import datetime
import os
import platform
import sys

import pvcmf
from pvcmf.study.claims import CLINICAL_TOLERANCE_MM, MESH_TOLERANCE_MM, NU_LOSS_TOLERANCE_MM
from pvcmf.study.inference import MIN_REGION_POINTS
from pvcmf.study.paper001 import FINE_METHOD, PAPER001_AUTO_METHODS, PAPER_NU
from pvcmf.truth.graded import face_size_text
from truth_refinement import PAGE, _truth_name, truth_note

#: oracle inputs (true bone labels and landmarks) and CT-only (automatic segmentation,
#: bone segments and atlas fit): both models of paper 000 in both modes
COHORT_METHODS = ("proposed", "state_of_the_art", "proposed_auto", "state_of_the_art_auto")
#: the models of both papers whose errors the cohort page tabulates per face region
REGION_METHODS = ("proposed", "state_of_the_art", "homogeneous", "inhomogeneous")


def _markdown(df):
    """A pandas table as a markdown table (no ``tabulate`` needed)."""
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    rule = "|" + "---|" * len(df.columns)
    rows = ["| " + " | ".join(str(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *rows])


def _verdict_lines(claims):
    """One line per claim: claim, n, difference, its interval, p, verdict."""
    out = []
    for r in claims.itertuples(index=False):
        if r.verdict == "not tested":
            out.append(f"- {r.claim}: n = {r.n} patients, not tested (fewer than 2 "
                       f"patients with {MIN_REGION_POINTS} judged points there)")
            continue
        out.append(f"- {r.claim}: n = {r.n}, difference {r.difference:+.3f} (95 % CI "
                   f"{r.ci_low:+.3f} to {r.ci_high:+.3f}), p = {r.p_value:.3g}, "
                   f"{r.verdict}; {'holds' if r.holds else 'does not hold'}")
    return out


def _region_pivot(regions):
    wide = regions.pivot_table(index=["patient", "region"], columns="method",
                               values=["p50", "p90"], sort=False)
    wide.columns = [f"{m} {q}" for q, m in wide.columns]
    order = [f"{m} {q}" for m in REGION_METHODS for q in ("p50", "p90")]
    return wide[[c for c in order if c in wide.columns]].reset_index()


def _nu_pivot(nu_table):
    wide = nu_table.pivot(index="patient", columns="nu", values="p90")
    best = nu_table[nu_table["optimum"]].set_index("patient")["nu"]
    wide.columns = [f"nu {c:g}" for c in wide.columns]
    wide = wide.round(3)
    wide["optimum"] = best
    return wide.reset_index()


def _mesh_rows(paper001):
    """The four rows of ``pvcmf.study.claims.mesh_size_claims`` in a paper 001 table:
    paired error, |change| below the clinical tolerance, |change| below paper 001's,
    skin difference."""
    rows = paper001[paper001["claim"].str.contains("tetrahedra", regex=False)]
    if len(rows) != 4:
        raise ValueError(f"expected the 4 rows of mesh_size_claims, found {len(rows)}")
    return list(rows.itertuples(index=False))


def mesh_note(mesh, paper001, n_tets, fine_tets, truth_tets, truth_face_mm=None,
              truth_face_margin_mm=0.0):
    """The cohort page's section on paper 001's mesh-size claim: what the claim says,
    the equivalence of the two meshes' skins (independent of the truth), the paired error
    (against the truth), and the verdict, read from ``mesh`` (``mesh_size_table``) and the
    rows of ``paper001``. ``truth_face_mm``: the face size of a graded truth
    (``truth_tets`` then sets its size elsewhere only), ``truth_face_margin_mm`` its
    margin around the moved bones."""
    paired, clinical, paper, skin = _mesh_rows(paper001)
    tol = CLINICAL_TOLERANCE_MM

    def hl(row, offset):  # one-sample Hodges-Lehmann estimate and interval, in mm
        return (f"{offset + row.difference:.3f} mm (95 % CI {offset + row.ci_low:.3f}-"
                f"{offset + row.ci_high:.3f} mm), p = {row.p_value:.3g}")

    sp90, change = mesh["skin_p90"], mesh["change"].abs()
    shown = "shown below" if skin.holds else "not shown below"

    def above(values, bound):  # the patients whose own value exceeds the bound
        out = mesh.loc[values > bound, "patient"].tolist()
        return (f"{len(out)} of {len(mesh)} patients above {bound:g} mm"
                + (": patient " + ", ".join(f"{p} ({v:.3f} mm)" for p, v in
                                             zip(out, values[values > bound]))
                   if 0 < len(out) <= 3 else ""))
    coarser = ("coarser than either model mesh" if truth_tets < n_tets else
               "finer than the coarser model mesh" if truth_tets > n_tets else
               "as fine as the coarser model mesh")
    truth = (f"The truth of this run has {truth_tets} tetrahedra, {coarser}."
             if truth_face_mm is None else
             f"The truth of this run is graded: {face_size_text(truth_face_mm)} in the face"
             + (f" and within {truth_face_margin_mm:g} mm of the moved bones"
                if truth_face_margin_mm else "") + ", the "
             f"conforming spacing of {truth_tets} tetrahedra elsewhere (more tetrahedra "
             "than that in all).")
    return [
        f"Paper 001 (sec. 3.2): about 30 000 tetrahedra are enough, a much denser mesh "
        f"changing the p90 error by less than {MESH_TOLERANCE_MM:g} mm. Tested here with "
        f"the homogeneous model (nu {PAPER_NU:g}, oracle inputs) on {n_tets} and "
        f"{fine_tets} tetrahedra (``homogeneous`` and ``{FINE_METHOD}``; paper 001's dense "
        "mesh has 200 000), per patient (``pvcmf.study.claims.mesh_size_table``, "
        "``mesh_size_claims``):", "",
        f"- Equivalence of the predictions, independent of the truth: the p90 of the "
        f"distance between the two predicted skins is median {sp90.median():.3f} mm "
        f"(patients {sp90.min():.3f}-{sp90.max():.3f} mm; the farthest single point "
        f"{mesh['skin_max'].max():.2f} mm apart); Hodges-Lehmann estimate {hl(skin, tol)}; "
        f"{shown} the {tol:g} mm clinical tolerance; {above(sp90, tol)}. The test is on "
        "the location of the per-patient values, not on every patient.",
        f"- Paired error against the truth: p90 |error| median {paired.median_a:.3f} mm "
        f"({n_tets}) and {paired.median_b:.3f} mm ({fine_tets}), difference "
        f"{paired.difference:+.3f} mm (95 % CI {paired.ci_low:+.3f} to "
        f"{paired.ci_high:+.3f}), p = {paired.p_value:.3g}, {paired.verdict}; the "
        f"per-patient change |p90 {n_tets} - p90 {fine_tets}| is median "
        f"{change.median():.3f} mm (largest {change.max():.3f} mm), Hodges-Lehmann "
        f"{hl(clinical, tol)}: "
        f"{'shown' if clinical.holds else 'not shown'} below {tol:g} mm, "
        f"{'shown' if paper.holds else 'not shown'} below paper 001's "
        f"{MESH_TOLERANCE_MM:g} mm; {above(change, MESH_TOLERANCE_MM)}.", "",
        f"Verdict: {n_tets} tetrahedra {'are' if skin.holds else 'are not shown to be'} "
        f"enough at the clinical tolerance (their predicted skin within {tol:g} mm of "
        f"{fine_tets} tetrahedra's: {'holds' if skin.holds else 'does not hold'}; "
        f"{above(sp90, tol)}); "
        f"paper 001's own criterion (p90 error within {MESH_TOLERANCE_MM:g} mm) "
        f"{'holds' if paper.holds else 'does not hold'}.", "",
        f"{truth} The skin difference between the two model meshes does not depend on "
        "the truth. The error comparison does: both meshes are judged against this one "
        "truth, so a paired error difference smaller than the truth's own "
        "discretisation error is not resolved by it, and a finer model mesh need not err "
        "less against a coarser truth.", "",
        _markdown(mesh.round(3)), ""]


def _intro(args, res, command, status):
    """The page's title, run and models paragraphs and the truth's note."""
    from pvcmf.study.validation import JUDGE_LIMIT

    options = (args.truth_mesher, args.truth_face_mm, args.truth_materials,  # the truth's
               args.truth_face_margin_mm)
    fine_tets, n_pat = res["fine_tets"], res["n_patients"]
    return [
        "# Cohort study: paper 000's and paper 001's claims on seeded virtual patients", "",
        f"Command: `{command}`  ",
        f"Date: {datetime.date.today().isoformat()}; machine: {platform.machine()}, "
        f"{os.cpu_count()} cores (shared with other jobs), Python "
        f"{sys.version.split()[0]}, pvcmf {pvcmf.__version__}. Run: {status}.", "",
        f"{n_pat} patients of ``pvcmf.study.cohort.cohort({args.cohort}, "
        f"seed={args.seed})`` at {args.spacing} mm, MTM meshes of {args.n_tets} "
        f"tetrahedra (the finer mesh: {fine_tets}), truth: "
        f"{_truth_name(args.truth, args.truth_tets, *options)}. "
        "Paper 000's models: "
        "``proposed`` (muscle-embedded conforming mesh) / ``state_of_the_art`` (the same "
        "mesh without muscle surfaces, the muscles sampled onto it by random points) with "
        "oracle inputs (true bone labels and landmarks) and ``proposed_auto`` / "
        "``state_of_the_art_auto`` from the CT and the plan alone (automatic "
        "segmentation, bone segments, atlas fit). Paper 001's models "
        "(``pvcmf.study.paper001``, no atlas muscles, a mesh that ignores "
        f"the tissue classes): ``homogeneous`` (one isotropic material, nu {PAPER_NU:g}), "
        "``inhomogeneous`` (each tetrahedron mixes fat and muscle by its share of the "
        "per-slice Gaussian-mixture classification, nu_fat 0.485, nu_muscle 0.43, "
        f"E_muscle / E_fat 1), ``homogeneous_nu<nu>`` (the sweep) and ``{FINE_METHOD}`` "
        f"(the homogeneous model on {fine_tets} tetrahedra), all with oracle inputs (true "
        "bone labels), and ``homogeneous_auto`` / ``inhomogeneous_auto``, the two models "
        "from the CT and the plan alone (automatic bone segments). |error| in mm on the judged "
        "anterior face (signed error statistics of "
        "``pvcmf.study.statistics.error_statistics``; n: judged skin points; excluded: "
        "skin points of the judged face left out of every method because the "
        f"post-operative CT shows no skin within ``JUDGE_LIMIT`` ({JUDGE_LIMIT:g} mm) of "
        "where the truth puts it, ``pvcmf.study.validation.study_predictor``).", "",
        truth_note(args.truth, args.truth_tets, PAGE, *options), "",
    ]


def _verdicts(args, res):
    """The verdicts of both papers' claims, the Poisson-ratio optimum and the tolerances."""
    claims, paper001, spread = res["claims"], res["paper001"], res["spread"]
    few, fine_tets = res["n_patients"] < 6, res["fine_tets"]
    return [
        "## Verdicts", "",
        "Each claim tested over the patients: Wilcoxon signed-rank test of the per-patient "
        "statistic, Hodges-Lehmann difference (a - b, mm; for a tolerance: value - "
        "tolerance; for the Poisson ratio: optimum - paper's) with its 95 % bootstrap "
        "interval (``pvcmf.study.inference.claims_table``, "
        "``pvcmf.study.claims.paper001_claims``). "
        + ("With fewer than 6 patients no two-sided p-value can fall below 0.05: this run "
           "shows the path end to end, not a verdict." if few else
           "A verdict other than \"no difference\" needs p < 0.05; \"no difference\" is "
           "not equivalence: read the interval as the largest difference the run leaves "
           "possible. A claim that a quantity stays below a tolerance holds only when the "
           "test puts it below with p < 0.05."), "",
        *_verdict_lines(claims), *_verdict_lines(paper001), "",
        f"Optimal Poisson ratio of the homogeneous model (the p90's minimum over nu "
        f"{', '.join(f'{g:g}' for g in spread['grid'])}), over {spread['n']} patients: "
        f"median {spread['median']:g}, interquartile range {spread['q25']:g}-"
        f"{spread['q75']:g}, 95 % bootstrap interval of the median {spread['ci_low']:g}-"
        f"{spread['ci_high']:g}; paper 001's {PAPER_NU:g} "
        f"{'lies' if spread['paper_in_ci'] else 'does not lie'} in it. "
        f"{spread['at_grid_end']} of {spread['n']} optima lie at an end of the sweep "
        "(there the sweep bounds the optimum, it does not find it).", "",
        f"Tolerances: {NU_LOSS_TOLERANCE_MM:g} mm (paper 001: the p90 at nu 0.46 within "
        f"0.1 mm of each patient's best), {MESH_TOLERANCE_MM:g} mm (paper 001: the p90 of "
        f"30 000 tetrahedra within 0.05 mm of a very dense mesh), "
        f"{CLINICAL_TOLERANCE_MM:g} mm (the skin difference between two meshes: a quarter "
        "of the 2 mm within which paper 000 counts a prediction accurate). The mesh claims "
        f"are tested at {args.n_tets} against {fine_tets} tetrahedra (paper 001: 30 000 "
        "against 200 000; section \"Mesh size\" below).", "",
    ]


def _cost(res):
    """The cost section: seconds per patient, cold and warm, against the targets."""
    cost, n_pat, claims_s = res["cost"], res["n_patients"], res["claims_seconds"]
    cold = cost[cost.run == "cold"].seconds
    warm = cost[cost.run == "warm"].seconds
    per_cold, per_warm = float(cold.mean()), float(warm.mean())
    # the claims over every patient of the run, timed on the cold run's skins (the warm
    # ones are the same, bit for bit); scaled to 16 patients when the run has fewer
    warm16 = 16 * per_warm + claims_s * max(16 / n_pat, 1.0)
    return [
        "## Cost", "",
        "Wall seconds per patient (the patient built, its truth, post-operative CT, "
        "registration and every method judged); cold: empty caches (a new cache folder: "
        "every patient is built, every truth solved, every pipeline run and every "
        "prediction judged), warm: the same patients again in the same process with "
        "fresh predictors, reading each patient (``virtual_patient(cache=True)``) and "
        "each method's judged skin (``pvcmf.study.predictions.cached_judged``) from the "
        "on-disk cache and computing the statistics again. p90_change_mm: the largest "
        "change of a method's p90 error from the cold run to the warm one; identical: "
        "every judged skin of the patient (points, every point and field array) and its "
        "statistics equal bit for bit in both runs.",
        "", _markdown(cost.round(1)), "",
        f"Mean per patient ({len(cold)} cold, {len(warm)} warm): cold {per_cold:.0f} s"
        + (f", warm {per_warm:.1f} s" if len(warm) else "") + ". "
        + f"The claims, per-region table and Poisson-ratio sweep over the {n_pat} "
        f"patients: {claims_s:.1f} s"
        + (f"; over the {res['warm_claims_patients']} warm patients "
           f"{res['warm_claims_seconds']:.1f} s"
           + (", the same tables as the cold run's" if res.get("warm_claims_identical")
              else "") if len(warm) else "") + ". "
        + f"Measured in this run: cold {(cold.sum() + claims_s) / 60:.1f} min for its "
        f"{len(cold)} patients with the claims"
        + (f", warm {(warm.sum() + res['warm_claims_seconds']) / 60:.2f} min for "
           f"{len(warm)} patients with their claims" if len(warm) else "") + ". "
        + "Projected for 16 patients at these sizes on this machine: cold "
        f"{16 * per_cold / 60:.0f} min (target 90 min: "
        f"{'met' if 16 * per_cold <= 5400 else 'not met'}), warm "
        + (f"{warm16 / 60:.1f} min with the claims" + (
            "" if n_pat >= 16 else f" (their seconds scaled by 16 / {n_pat})")
           + " (target 5 min: "
           f"{'met' if warm16 <= 300 else 'not met'})" if len(warm) else
           "not measured in this run") + ". A warm run runs no truth "
        "mesh or solve, no post-operative CT, segmentation or registration and no MTM "
        "pipeline: what is left is reading the patients and the judged skins, the "
        "statistics and the claims (a run in a new process also hashes the code that keys "
        "the cache once, ``pvcmf.study.predictions.judged_code_hash``: seconds, in the "
        "first warm patient's time when the cold run did not hash it).", ""
    ]


def cohort_page(args, res, command, status="complete"):
    """The cohort page (markdown) of :func:`study.cohort_study`'s result ``res``."""
    table, claims, paper001 = res["table"], res["claims"], res["paper001"]
    fine_tets = res["fine_tets"]
    keep = [c for c in ("patient", "method", "n", "excluded", "median", "p90", "p95",
                        "within_1mm", "within_2mm") if c in table.columns]
    main_methods = (COHORT_METHODS + ("homogeneous", "inhomogeneous") + PAPER001_AUTO_METHODS
                    + (FINE_METHOD,))
    errors = table[table["method"].isin(main_methods)]
    lines = [*_intro(args, res, command, status), *_verdicts(args, res),
        "## Mesh size", "",
        *mesh_note(res["mesh"], paper001, args.n_tets, fine_tets, args.truth_tets,
                   args.truth_face_mm if args.truth_mesher == "graded" else None,
                   args.truth_face_margin_mm),
        "## Errors per patient and method", "",
        _markdown(errors[keep].round(3)), "",
        "## Paper 000's claims, paired over the patients", "",
        _markdown(claims.round(4)), "",
        "## Paper 001's claims, paired over the patients", "",
        _markdown(paper001.round(4)), "",
        "p90 |error| (mm) of the homogeneous model per Poisson ratio, and each patient's "
        "optimum (``pvcmf.study.claims.nu_optimum``):", "",
        _markdown(_nu_pivot(res["nu"])), "",
        "## Errors per face region", "",
        f"p50 and p90 of |error| (mm) per patient and face region (regions of "
        f"``pvcmf.study.statistics.label_face_regions``: lips = upper and lower lip, cheeks "
        f"= both cheeks; NaN: fewer than {MIN_REGION_POINTS} judged points; "
        "``pvcmf.study.claims.region_table``). The per-region claims of paper 000 are in "
        "its table above.", "",
        _markdown(_region_pivot(res["regions"]).round(3)), "",
        *_cost(res)]
    return "\n".join(lines)
