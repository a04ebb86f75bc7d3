"""Benchmark: how far the independent truth's skin depends on its osteotomy blend width.

The truth ties the soft tissue to the bone surfaces and blends the segments' moves across
an osteotomy over a Gaussian width (``blend_mm`` of
:func:`pvcmf.truth.independent.independent_truth_grid`, default
:data:`pvcmf.truth.independent.BLEND_MM`): a modelling choice, not a measured property of
the tissue. For one virtual patient, the graded truth at each face size and each blend
width; per blend, the skin's change between successive face sizes (does a wider, gentler
blend make the truth converge?), and per face size, the skin's change from the first
blend to each other (how much of the truth is this choice?), both measured on the exact
skin as the refinement study measures them (:mod:`pvcmf.truth.refinement`). Run through
``benchmarks/study.py --blend-mm``; writes ``docs/benchmarks/truth_blend.md``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays
from pvcmf.truth.independent import independent_truth_grid
from pvcmf.truth.refinement import (exact_skin_normals, exact_skin_samples, refinement_change,
                                    skin_state)

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "truth_blend.md"
#: skin change (p90, mm) between the two finest truths below which a truth has converged
CONVERGED_MM = 0.1


def _stats(change):
    return {k: float(change[k]) for k in ("p50", "p90", "max")}


def blend_rows(patient, spacing, count, face_mm, blends, materials="field", cache=True,
               face_margin_mm=0.0):
    """The truths of ``patient`` at each face size (graded mesher, ``count`` tetrahedra
    outside the face, the face ball grown by ``face_margin_mm`` as the refinement grows
    it) and blend width; returns ``(refinement, cross)``: per blend and
    successive face sizes, the skin change between them (with each truth's size and its
    folded elements); per face size and blend after the first, the skin change from the
    first blend."""
    if len(blends) < 2 or len(face_mm) < 2:
        raise ValueError(f"need two blend widths and two face sizes, got blends {blends} "
                         f"and face sizes {face_mm}")
    case = pvcmf.datasets.phantom(patient, spacing=spacing)
    points = exact_skin_samples(case)
    normals = exact_skin_normals(case, points)
    states = {}  # one truth's mesh at a time: the finest ones are 100k+ P2 tetrahedra
    for b in blends:
        for f in face_mm:
            grid = independent_truth_grid(case, n_tets=count, mesher="graded",
                                          materials=materials, face_mm=f, blend_mm=b,
                                          face_margin_mm=face_margin_mm,
                                          reuse_factor=True, cache=cache)
            states[b, f] = {**skin_state(grid, points, normals), "tets": grid.n_cells,
                            "folded": len(grid.field_data[arrays.REFERENCE_FOLDED])}
            del grid
    refinement = []
    for b in blends:
        for f0, f1 in zip(face_mm[:-1], face_mm[1:]):
            coarse, fine = states[b, f0], states[b, f1]
            refinement.append({
                "patient": patient, "blend": b, "faces": (f0, f1),
                "tets": (coarse["tets"], fine["tets"]),
                "folded": (coarse["folded"], fine["folded"]),
                **_stats(refinement_change(coarse, fine, points))})
    cross = [{"patient": patient, "face": f, "blends": (blends[0], b),
              **_stats(refinement_change(states[blends[0], f], states[b, f], points))}
             for f in face_mm for b in blends[1:]]
    return refinement, cross


def verdict(refinement, cross):
    """What the rows say, in sentences made from their numbers."""
    finest = {}
    for r in refinement:  # the last pair of each blend is its two finest truths
        finest[r["blend"]] = r
    ref_blend = refinement[0]["blend"]
    parts = []
    for b, r in finest.items():
        state = "converged" if r["p90"] <= CONVERGED_MM else "not converged"
        parts.append(f"blend {b:g} mm: p90 {r['p90']:.3f} mm between face {r['faces'][0]:g} "
                     f"and {r['faces'][1]:g} mm ({state})")
    p90s = [r["p90"] for r in finest.values()]
    gain = max(p90s) - min(p90s)
    text = ["Refinement change between the two finest truths, by blend width: "
            + "; ".join(parts) + "."]
    if all(p > CONVERGED_MM for p in p90s):
        text.append(f"No blend width tried brings the truth under {CONVERGED_MM:g} mm "
                    f"(the p90s lie within {gain:.3f} mm of each other): the blend's "
                    "sharpness is not what keeps this patient's truth from converging.")
    elif any(p > CONVERGED_MM for p in p90s):
        ok = [b for b, r in finest.items() if r["p90"] <= CONVERGED_MM]
        text.append(f"The truth converges with blend width(s) {', '.join(f'{b:g}' for b in ok)}"
                    " mm only: its convergence depends on the blend's sharpness.")
    finest_face = cross[-1]["face"]
    spread = max(c["p90"] for c in cross if c["face"] == finest_face)
    disc = finest[ref_blend]["p90"]
    text.append(f"At face {finest_face:g} mm, changing the blend from {ref_blend:g} mm moves "
                f"the skin by up to p90 {spread:.3f} mm, "
                + ("more" if spread > disc else "less")
                + f" than refining the face at blend {ref_blend:g} mm ({disc:.3f} mm): "
                "the blend is a modelling uncertainty of the truth of that size, which a "
                "paired difference between two models judged by the same truth shares.")
    return " ".join(text)


def blend_page(refinement, cross, command, machine):
    """The markdown page of :func:`blend_rows`'s rows."""
    head = ["# The truth's osteotomy blend width", "",
            f"Command: `{command}`  ", f"Machine: {machine}", "",
            "The independent truth blends the bone segments' moves on the tied bone surface "
            "across an osteotomy over a Gaussian width (``blend_mm``; default "
            "``pvcmf.truth.independent.BLEND_MM``). Skin points, the change measure and the "
            "convergence threshold as in ``truth_refinement.md``. Folded: elements the "
            "solution's vertex displacements invert (``reference_folded``).", "",
            "## Refinement at each blend width", "",
            "| patient | blend mm | face mm | tetrahedra | folded | change p50 mm | p90 mm "
            "| max mm |", "|---|---|---|---|---|---|---|---|"]
    head += [f"| {r['patient']} | {r['blend']:g} | {r['faces'][0]:g} -> {r['faces'][1]:g} | "
             f"{r['tets'][0]} -> {r['tets'][1]} | {r['folded'][0]} -> {r['folded'][1]} | "
             f"{r['p50']:.3f} | {r['p90']:.3f} | {r['max']:.3f} |" for r in refinement]
    head += ["", "## The skin's change with the blend width, on the same mesh", "",
             "| patient | face mm | blend mm | change p50 mm | p90 mm | max mm |",
             "|---|---|---|---|---|---|"]
    head += [f"| {c['patient']} | {c['face']:g} | {c['blends'][0]:g} -> {c['blends'][1]:g} | "
             f"{c['p50']:.3f} | {c['p90']:.3f} | {c['max']:.3f} |" for c in cross]
    head += ["", verdict(refinement, cross), ""]
    return "\n".join(head)
