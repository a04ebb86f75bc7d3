"""Benchmark: the independent truth's refinement study (``study.py --refinement``).

Per virtual patient, :func:`pvcmf.truth.independent.independent_truth_grid` at the
requested counts (P2; ``mesher="graded"``: at the finest count, refined in the face to
each of the face sizes), each solve's cost (dofs, Newton iterations, factorisations,
seconds); the exact skin moved by each truth (:mod:`pvcmf.truth.refinement`), and the
p50 / p90 / max of its change between successive counts. Converged when the p90 between
the two finest is <= 0.1 mm. :func:`refinement_rows` reads the table back and
:func:`truth_note` says on the cohort page what it measured of the cohort's truth.
Run through ``benchmarks/study.py --refinement``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

import pvcmf
from pvcmf import arrays, filters
from pvcmf.plan import TABLE_II
from pvcmf.study.cohort import cohort_parameters, virtual_patient
from pvcmf.truth.graded import face_size, face_size_text
from pvcmf.truth.independent import independent_truth_grid
from pvcmf.truth.refinement import (exact_skin_normals, exact_skin_samples,
                                    refinement_change)

PAGE = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "truth_refinement.md"
#: the seed of the cohort whose patients (numbered from :data:`FIRST_COHORT` on) a
#: refinement also takes: those of ``pvcmf.study.cohort.cohort(n, seed=0)``
COHORT_SEED = 0
FIRST_COHORT = 101


def _draw(patient):
    """Parameters and plan of cohort patient ``patient`` (the draw of a cohort is the same
    for its first patients whatever its size)."""
    i = int(patient) - FIRST_COHORT
    return cohort_parameters(i + 1, COHORT_SEED)[i]


def refinement_case(patient, spacing):
    """Patient ``patient`` of a refinement: a phantom of ``pvcmf.datasets.phantom`` (1-4)
    or, from :data:`FIRST_COHORT` on, that patient of the cohort (seed
    :data:`COHORT_SEED`), as the cohort study builds it."""
    if int(patient) >= FIRST_COHORT:
        params, plan = _draw(patient)
        return virtual_patient(params, plan, spacing=spacing, number=int(patient), cache=True)
    return pvcmf.datasets.phantom(patient, spacing=spacing)


def patient_plan(patient):
    """The plan of refinement patient ``patient`` (``TABLE_II`` or the cohort's draw)."""
    return _draw(patient)[1] if int(patient) >= FIRST_COHORT else TABLE_II[int(patient)]


def patients_text(patients):
    """Refinement patients in words: the phantoms and the cohort's patients."""
    ph = [str(p) for p in patients if int(p) < FIRST_COHORT]
    co = [str(p) for p in patients if int(p) >= FIRST_COHORT]
    parts = ([f"patients {', '.join(ph)} of ``pvcmf.datasets.phantom``"] if ph else []) + (
        [f"patients {', '.join(co)} of the cohort (seed {COHORT_SEED})"] if co else [])
    return " and ".join(parts)


def _row(p, grid):
    """A truth's mesh and solve cost, as a table row."""
    dofs, newton, factors, seconds = grid.field_data[arrays.REFERENCE_SOLVER]
    edges = grid.extract_all_edges().compute_cell_sizes(length=True, area=False,
                                                        volume=False)["Length"]
    return {"patient": p, "tets": grid.n_cells, "h": float(np.median(edges)),
            "dofs": int(dofs), "newton": int(newton), "factorisations": int(factors),
            "seconds": float(seconds), "share": np.nan, "p50": np.nan, "p90": np.nan,
            "max": np.nan, "released": len(grid.field_data[arrays.REFERENCE_RELEASED])}


def fine_truth_cost(patient, counts, fine, spacing, cache=True, mesher="lattice",
                    materials="cells"):
    """One finer truth of ``patient`` (``fine`` tetrahedra asked): its cost and the change
    of its skin from the finest truth of the table (``counts[-1]``)."""
    case = refinement_case(patient, spacing)
    points = exact_skin_samples(case)
    coarse = independent_truth_grid(case, n_tets=counts[-1], cache=cache, mesher=mesher,
                                    materials=materials, reuse_factor=True)
    grid = independent_truth_grid(case, n_tets=fine, cache=cache, mesher=mesher,
                                  materials=materials, reuse_factor=True)
    r = _row(patient, grid)
    change = refinement_change(coarse, grid, points)
    print(r, {k: change[k] for k in ("p50", "p90", "max", "compared")}, flush=True)
    trend = ""
    if len(counts) > 1:  # p90 ~ edge^k from the last two changes, projected to 0.1 mm
        prev = independent_truth_grid(case, n_tets=counts[-2], cache=cache, mesher=mesher,
                                      materials=materials, reuse_factor=True)
        a, b, c = _row(patient, prev), _row(patient, coarse), r
        first = refinement_change(prev, coarse, points)["p90"]
        k = np.log(first / change["p90"]) / np.log(b["h"] / c["h"])
        t = np.log(c["tets"] / b["tets"]) / np.log(b["h"] / c["h"])
        cost = np.log(c["seconds"] / b["seconds"]) / np.log(c["tets"] / b["tets"])
        if k > 0:
            h = c["h"] * (0.1 / change["p90"]) ** (1 / k)
            tets = c["tets"] * (c["h"] / h) ** t
            trend = (f" Trend: p90 {first:.3f} mm ({a['h']:.1f} -> {b['h']:.1f} mm edges), "
                     f"{change['p90']:.3f} mm ({b['h']:.1f} -> {c['h']:.1f} mm): p90 ~ "
                     f"edge^{k:.2f}; 0.1 mm projected at an edge of {h:.1f} mm, about "
                     f"{tets:.0f} tetrahedra, solve about {c['seconds'] * (tets / c['tets']) ** cost / 60:.0f} "
                     "min on this machine (extrapolated, not measured).")
        else:
            trend = (f" Trend: p90 {first:.3f} mm ({a['h']:.1f} -> {b['h']:.1f} mm edges), "
                     f"{change['p90']:.3f} mm ({b['h']:.1f} -> {c['h']:.1f} mm): not shrinking, "
                     "no projection.")
    return (f"\n\nA finer truth, patient {patient} (``--fine {fine}``): {r['tets']} tetrahedra "
            f"(edge {r['h']:.1f} mm), {r['dofs']} dofs, {r['newton']} Newton iterations, "
            f"{r['factorisations']} factorisations, solve {r['seconds']:.0f} s (measured); "
            f"skin change from the {counts[-1]} truth above over {100 * change['compared']:.0f} "
            f"% of the skin: p50 {change['p50']:.3f} mm, p90 {change['p90']:.3f} mm, "
            f"max {change['max']:.3f} mm." + trend)


def order_check(patient, count, spacing, mesher="lattice"):
    """The P2 discretisation error on one mesh of the truth: the small-strain control law
    solved with P2 and with P3 elements on the same mesh (so the same geometry, materials
    and boundary data), compared on the exact skin."""
    from pvcmf.truth.conform import conforming_mesh
    from pvcmf.truth.independent import _boundary_conditions, soft_tissue_mesh
    from pvcmf.truth.solver import solve_reference

    case = refinement_case(patient, spacing)
    points = exact_skin_samples(case)
    mesh = conforming_mesh if mesher == "conforming" else soft_tissue_mesh
    grid = _boundary_conditions(case, mesh(case, n_tets=count))
    grid = filters.assign_materials(grid, default_fiber=(0.0, 0.0, 1.0))
    p2, p3 = (solve_reference(grid, order=k, law="linear", steps=1) for k in (2, 3))
    change = refinement_change(p2, p3, points)
    print("order check", {k: change[k] for k in ("p50", "p90", "max", "compared")}, flush=True)
    return (f"\n\nDiscretisation error of P2 on one mesh (``--order-check``): patient "
            f"{patient}, the {count} mesh ({grid.n_cells} tetrahedra), the small-strain control "
            f"law solved with P2 and with P3 elements on that same mesh (same geometry, "
            f"materials and boundary data): skin difference p50 {change['p50']:.3f} mm, p90 "
            f"{change['p90']:.3f} mm, max {change['max']:.3f} mm. The part of the change "
            "between two meshes above this is the problem itself resolved differently by "
            "the two meshes (the thin tissue, the muscle sheets, the surfaces).")


_LATTICE = ("Mesher ``lattice``: lattice edges across a gap thinner than the lattice are "
            "not meshed, boundary nodes are snapped onto the exact surfaces (flattened caps "
            "dropped). Edge mm: the median edge of the mesh (its spacing times about 1.4, "
            "the face diagonals included).")
_CONFORMING = ("Mesher ``conforming`` (``pvcmf.truth.conform.conforming_mesh``): the exact "
               "soft-tissue surface sampled on a grid (spacing from the count), "
               "triangulated (flying edges) and filled with tetrahedra by gmsh, its "
               "boundary nodes projected onto the exact surfaces where that flattens no "
               "element; the same meshed volume at every size. Solves use "
               "``reuse_factor=True`` (conjugate gradients preconditioned by the last "
               "factorisation). Edge mm: the median edge of the mesh.")


_GRADED = ("Mesher ``graded`` (``pvcmf.truth.graded.graded_mesh``): as ``conforming``, "
           "the surface sampled on a grid regular in a radially mapped space, so that it "
           "is ``face mm`` fine within the ball of the moved bone segments (centre: their "
           "centroid, radius: their farthest voxel from it; the lips, chin, cheeks and, for a "
           "moved maxilla, the nose), the size growing by ``GRADING`` mm per mm beyond it "
           "up to the conforming spacing of the count (``--counts``, the finest) "
           "elsewhere, so the thin tissue over the skull vault is meshed at least as finely "
           "as by the conforming mesh of that count; the tetrahedra grow from the surface "
           "inwards. The sequence refines the face only, by a fixed factor per step; the "
           "problem (exact geometry, boundary data, material field) is the same on every "
           "mesh.")


_CELLS = "each tetrahedron mixes fat and muscle by its sampled muscle fraction."
_FIELD = ("materials ``field`` (``pvcmf.truth.independent.material_field``): fat and muscle "
          "mixed by the exact muscle indicator sampled every ``MATERIAL_MM`` mm (on the "
          "whole multiples of the step in the patient frame: the same points for every "
          "mesh) and "
          "smoothed over ``MATERIAL_SIGMA_MM`` mm, a field of the position projected onto "
          "quadratic polynomials on each element at the solve, so every mesh integrates "
          "the same material.")


def _levels(counts, mesher, face_mm):
    """The meshes of one patient's sequence: (n_tets, face mm or None) coarse to fine
    (``graded``: the finest count outside the face, each face size inside it)."""
    if mesher == "graded":
        if not face_mm:
            raise ValueError("mesher 'graded' needs face sizes (--face-mm)")
        return [(counts[-1], f) for f in face_mm]
    return [(n, None) for n in counts]


_MARGIN = (" With ``--face-margin-mm {0:g}`` the ball also holds every soft-tissue voxel "
           "within {0:g} mm of a moved bone voxel (its radius: the farthest such voxel from "
           "the centre; ``face_ball``): around a compact moved segment (a maxilla) the "
           "tissue the move carries, the upper cheeks, reaches beyond the ball of the bone "
           "itself.")


def refinement(patients, counts, spacing, cache=True, mesher="lattice", materials="cells",
               face_mm=None, until=None, face_margin_mm=0.0):
    """The refinement sequence of each patient (``_levels``), coarse to fine; with
    ``until`` (mm), a patient's sequence stops at the first level whose skin change p90
    from the one before is at most ``until`` (its finer levels are not solved)."""
    rows = []
    levels = _levels(counts, mesher, face_mm)
    for p in patients:
        case = refinement_case(p, spacing)
        points = exact_skin_samples(case)
        normals = exact_skin_normals(case, points)
        prev = None
        for n, face in levels:
            grid = independent_truth_grid(case, n_tets=n, cache=cache, mesher=mesher,
                                          materials=materials, reuse_factor=True,
                                          **({"face_mm": face, "face_margin_mm": face_margin_mm}
                                             if face else {}))
            row = _row(p, grid)
            row["face"] = face
            if prev is not None:
                change = refinement_change(prev, grid, points, normals=normals)
                row.update({k: v for k, v in change.items() if k in ("p50", "p90", "max")})
                row["share"] = change["compared"]
                nearest = refinement_change(prev, grid, points)  # any closest triangle
                row["p90_nearest"], row["max_nearest"] = nearest["p90"], nearest["max"]
                last = change["change"]
            prev = grid
            rows.append(row)
            print(row, flush=True)
            if until is not None and row.get("p90", np.inf) <= until:
                break
        if len(levels) > 1:
            change_picture(points, last, PAGE.parent / f"truth_refinement_{p}.png")
            rows[-1]["bands"] = _by_distance(case, points, last)
    head = ("| patient | tetrahedra | face mm | edge mm | dofs | Newton | factorisations "
            "| solve s | released | skin compared | change p50 mm | p90 mm | max mm "
            "| p90 mm, any closest triangle |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    body = [f"| {r['patient']} | {r['tets']} | {r['face'] or '-'} | {r['h']:.1f} | "
            f"{r['dofs']} | {r['newton']} | {r['factorisations']} | {r['seconds']:.0f} | "
            f"{r['released']} | {100 * r['share']:.0f} % | {r['p50']:.3f} | {r['p90']:.3f} | "
            f"{r['max']:.3f} | {r.get('p90_nearest', np.nan):.3f} |" for r in rows]
    text = ("Skin points: the exact skin of the meshed face "
            "(``pvcmf.truth.refinement.exact_skin_samples``: the voxel skin projected onto "
            "the zero set of the patient's level sets, kept where that boundary is the "
            "skin); each truth's displacement there is that of its closest boundary point "
            "(``skin_displacement``) on the boundary triangles facing the same way as "
            "the exact skin there (outward normals less than 90 degrees apart, "
            "``exact_skin_normals``: across a gap narrower than a coarse mesh's elements, "
            "the lips, the closest boundary point of the upper lip can lie on the lower "
            "lip); the last column gives the p90 with the closest point on any triangle, "
            "as before. The change is taken from the next coarser truth over "
            "the points both meshes reach within a quarter of the coarser median edge "
            "(``refinement_change``). Converged: p90 <= 0.1 mm between the two finest. "
            "Solve s: the NGSolve solve (load steps, Newton, factorisations) on this "
            "machine, read from the truth's ``reference_solver`` record (cached truths keep "
            "the cost of the run that made them). The pictures colour the exact skin by "
            "the change between the two finest truths of each patient (0-0.5 mm) "
            "(``truth_refinement_<patient>.png``).\n\n"
            "Model (``pvcmf.truth.independent``), defined on the exact anatomy so that it "
            "is the same problem on every mesh: every node on a bone surface is tied, its "
            "data the segments' rigid moves blended by smooth weights of the position "
            "(``BLEND_MM``); the posterior plane is held except within ``CLEARANCE_MM`` of "
            "a moved bone; the tongue is not meshed (free, as the oral air); "
            + (_FIELD if materials == "field" else _CELLS) + " "
            + {"conforming": _CONFORMING, "graded": _CONFORMING + " " + _GRADED
               + (_MARGIN.format(face_margin_mm) if face_margin_mm else "")}.get(
                mesher, _LATTICE) + "\n\n")
    fits = []
    for p in patients:  # cost ~ tets^k from this patient's solves, projected to 30k and 60k
        r = [x for x in rows if x["patient"] == p]
        if len(r) > 1:
            k, c = np.polyfit(np.log([x["tets"] for x in r]), np.log([x["seconds"] for x in r]), 1)
            fits.append(f"patient {p}: solve s ~ tetrahedra^{k:.2f}; projected "
                        f"{np.exp(c) * 30_000 ** k / 60:.0f} min at 30k and "
                        f"{np.exp(c) * 60_000 ** k / 60:.0f} min at 60k tetrahedra "
                        "(extrapolated from the rows above, not measured; from wall seconds "
                        "on a 2-core machine, whose timing noise the exponent carries)")
    tail = "\n\nCost scaling:\n\n" + "\n".join(f"- {f}" for f in fits) if fits else ""
    tail += _verdict(rows, patients) if len(levels) > 1 else ""
    if len(levels) > 1:
        tail += "\n\n" + "\n\n".join(
            f"![skin change between the two finest truths, patient {p}]"
            f"(truth_refinement_{p}.png)" for p in patients)
    return ("## Refinement of the independent truth\n\n" + text + head + "\n"
            + "\n".join(body) + tail)


#: distances (mm) from the moved bone over which the finest change is summarised
BANDS = (0.0, 10.0, 20.0, 30.0, 50.0, np.inf)


def _by_distance(case, points, change):
    """p90 of the change (mm) and the number of skin points per band of distance from the
    plan's moved bone segments (:data:`BANDS`)."""
    from scipy.spatial import cKDTree

    from pvcmf.filters.osteotomy import cut_bones, segment_transforms, voxel_points

    labels = cut_bones(case.truth, case.plan)
    moved = [s for s, m in segment_transforms(labels, case.plan).items()
             if not np.allclose(m, np.eye(4))]
    bone = np.asarray(labels[arrays.BONE])
    d = cKDTree(voxel_points(labels, np.flatnonzero(np.isin(bone, moved)))).query(points)[0]
    out = []
    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        m = np.isfinite(change) & (d >= lo) & (d < hi)
        out.append((lo, hi, int(m.sum()), float(np.percentile(change[m], 90)) if m.any()
                    else np.nan))
    return out


def _verdict(rows, patients):
    """Per patient, the change between its two finest truths against the 0.1 mm goal."""
    lines = []
    for p in patients:
        r = [x for x in rows if x["patient"] == p]
        a, b = r[-2], r[-1]
        size = (f"face {a['face']} -> {b['face']} mm" if b.get("face") else
                f"{a['tets']} -> {b['tets']} tetrahedra")
        ok = b["p90"] <= 0.1
        bands = "; ".join(f"{lo:.0f}-{hi:.0f} mm: {q:.3f} ({n})" if np.isfinite(hi) else
                          f"beyond {lo:.0f} mm: {q:.3f} ({n})" for lo, hi, n, q in b["bands"])
        lines.append(f"- patient {p} ({size}; {a['tets']} -> {b['tets']} tetrahedra): "
                     f"p90 {b['p90']:.3f} mm, "
                     + ("converged (p90 <= 0.1 mm)" if ok else "not converged (p90 > 0.1 mm)")
                     + f". p90 mm (skin points) by distance of the skin from the moved bone: "
                     + bands)
    return "\n\nBetween the two finest truths:\n\n" + "\n".join(lines)


def change_picture(points, change, path):
    """The exact skin points coloured by their change between the two finest truths
    (grey: not reached by both meshes), front and side, offscreen."""
    import pyvista as pv

    from pvcmf.figures.face_views import saturation_note
    from pvcmf.figures.offscreen import prefer_egl

    prefer_egl()
    ok = np.isfinite(change)
    note = saturation_note(change, 0.5, ok, signed=False)
    pl = pv.Plotter(shape=(1, 2), off_screen=True, window_size=(1200, 600))
    for i, (view, up) in enumerate((((0, 1, 0), (0, 0, 1)), ((-1, 0.2, 0), (0, 0, 1)))):
        pl.subplot(0, i)
        if (~ok).any():
            pl.add_points(pv.PolyData(points[~ok]), color="lightgrey", point_size=4)
        pl.add_points(pv.PolyData(points[ok]), scalars=change[ok], clim=[0, 0.5],
                      cmap="viridis", point_size=5,
                      scalar_bar_args={"title": "skin change mm", "vertical": True,
                                       "position_x": 0.76, "position_y": 0.15,
                                       "height": 0.7, "width": 0.08})
        if note and i == 0:
            pl.add_text(note, position="upper_left", font_size=10, color="black")
        pl.view_vector(view, viewup=up)
    pl.screenshot(str(path))
    pl.close()


def refinement_rows(page=PAGE):
    """The refinement table of ``truth_refinement.md`` (written by :func:`refinement`):
    its mesher, materials, face margin (``--face-margin-mm`` of its command, 0 without)
    and finest count (``--counts`` of its command; None when the
    page does not give it) and, per patient, the tetrahedra and face sizes (mm; None
    without a ``face mm`` column) of its two finest truths and the skin change between
    them (p50, p90 mm), a finer truth's paragraph ("A finer truth, patient ...") taking
    over from the table's rows (``patients``); ``steps``: per patient, every change
    between consecutive rows of its table, coarsest first. None when the page or its
    table is missing."""
    if not Path(page).exists():
        return None
    text = Path(page).read_text()
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines)  # with or without a face mm column
                  if line.startswith("| patient | tetrahedra |") and "| edge mm |" in line),
                 None)
    if start is None:
        return None
    cols = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = []
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        rows.append(dict(zip(cols, (c.strip() for c in line.strip("|").split("|")))))
    finest, steps = {}, {}
    for prev, row in zip(rows, rows[1:]):  # consecutive rows of one patient: a change
        if prev["patient"] == row["patient"] and row["p90 mm"] != "nan":
            finest[row["patient"]] = {"coarse": int(prev["tetrahedra"]),
                                      "fine": int(row["tetrahedra"]),
                                      "coarse_face": _face(prev), "fine_face": _face(row),
                                      "p50": float(row["change p50 mm"]),
                                      "p90": float(row["p90 mm"])}
            steps.setdefault(row["patient"], []).append(finest[row["patient"]])
    last = {r["patient"]: int(r["tetrahedra"]) for r in rows}
    for pat, tets, p50, p90 in re.findall(  # a finer truth's paragraph supersedes the table
            r"A finer truth, patient (\d+) \(.*?\): (\d+) tetrahedra .*?skin change from the "
            r"\d+ truth above [^:]*: p50 ([\d.]+) mm, p90 ([\d.]+) mm", text):
        if pat in last:
            finest[pat] = {"coarse": last[pat], "fine": int(tets), "coarse_face": None,
                           "fine_face": None, "p50": float(p50), "p90": float(p90)}
    if not finest:
        return None
    mesher = ("graded" if "Mesher ``graded``" in text else
              "conforming" if "Mesher ``conforming``" in text else "lattice")
    materials = "field" if "materials ``field``" in text else "cells"
    command = re.search(r"Command: `[^`]*--counts((?: \d+)+)", text)
    count = int(command.group(1).split()[-1]) if command else None
    margin = re.search(r"Command: `[^`]*--face-margin-mm ([\d.]+)", text)
    return {"mesher": mesher, "materials": materials, "count": count, "patients": finest,
            "steps": steps, "margin": float(margin.group(1)) if margin else 0.0}


def _face(row):
    """A table row's face size (mm), None without one."""
    value = row.get("face mm", "-")
    return None if value in ("-", "", "None") else float(value)


def _span(values, fmt):
    lo, hi = min(values), max(values)
    return f"{lo:{fmt}}" if lo == hi else f"{lo:{fmt}}-{hi:{fmt}}"


def _truth_name(truth, truth_tets, mesher, face_mm, materials, margin=0.0):
    """The truth of a run, in words."""
    if truth != "independent":
        return f"the {truth} truth of {truth_tets} tetrahedra"
    if mesher != "graded":
        return (f"the {truth} truth (mesher ``{mesher}`` of {truth_tets} tetrahedra, "
                f"materials ``{materials}``)")
    within = ""
    if margin:
        within = ("," if isinstance(face_mm, dict) else "") + \
            f" within {margin:g} mm of the moved bones"
    face = (f", face {face_size_text(face_mm)}{within} (the conforming spacing of "
            f"{truth_tets} tetrahedra elsewhere)")
    return f"the {truth} truth (mesher ``{mesher}``{face}, materials ``{materials}``)"


def _truth_mismatch(ref, truth_tets, mesher, face_mm, materials, margin=0.0):
    """How the refinement page's truths differ from this run's (phrases; none: the same
    options, this run's truth one of the two finest of each patient)."""
    pats = ref["patients"].values()
    other = []
    if ref["mesher"] != mesher:
        other.append(f"measured with mesher ``{ref['mesher']}``, not this run's")
    if ref.get("materials", "cells") != materials:
        other.append(f"with materials ``{ref.get('materials', 'cells')}``, not this run's")
    if mesher != "graded":
        if truth_tets < min(r["coarse"] for r in pats):
            other.append(f"on meshes finer than this run's {truth_tets} tetrahedra")
        return other
    if ref.get("count") != truth_tets:
        other.append(f"with the conforming spacing of {ref.get('count')} tetrahedra outside "
                     f"the face, not this run's {truth_tets}")
    if not np.isclose(ref.get("margin", 0.0), margin):
        other.append(f"with a face margin of {ref.get('margin', 0.0):g} mm, not this run's "
                     f"{margin:g} mm")
    faces = {(r.get("coarse_face"), r.get("fine_face")) for r in pats}
    if any(a is None or b is None for a, b in faces):
        other.append("without face sizes")
    return other


def _patient_face(face_mm, patient):
    """This run's face size (mm) for refinement patient ``patient`` (of
    :func:`refinement_case`, plan :func:`patient_plan`): ``face_mm``, or its size for the
    segment that patient's plan moves."""
    return face_size(face_mm, patient_plan(patient) if isinstance(face_mm, dict) else None)


def _face_relation(pats, face_mm_of):
    """Where this run's face size lies against each patient's two finest truths: a phrase
    naming the patients of each relation (the coarser / finer of the two, coarser than
    both, finer than both, between them)."""
    groups = {}
    for p, r in pats.items():
        face_mm = _patient_face(face_mm_of, p)
        a, b = float(r["coarse_face"]), float(r["fine_face"])
        rel = ("the coarser of the two finest" if np.isclose(face_mm, a) else
               "the finer of the two finest" if np.isclose(face_mm, b) else
               "coarser than the two finest" if face_mm > a else
               "finer than the two finest" if face_mm < b else
               "between the two finest")
        groups.setdefault(rel, []).append(p)
    return "; ".join(f"{rel} for patient(s) {', '.join(ps)}" for rel, ps in groups.items())


def _then(phrase):
    """``"; phrase"``, or nothing for an empty one."""
    return f"; {phrase}" if phrase else ""


def _run_level(steps, face_mm_of):
    """How far a truth of face ``face_mm_of`` (a size, or sizes per moved segment) is from
    the next finer truth of each patient of the refinement (``steps``:
    :func:`refinement_rows`'s): ``(phrase, within)``, ``within`` True when every patient's refinement measured that change and it is at most 0.1 mm
    p90, or this face size is the patient's finest."""
    near, far, finest, unmeasured = {}, {}, [], []
    text = face_size_text(face_mm_of)
    for p, rows in steps.items():
        face_mm = _patient_face(face_mm_of, p)
        step = next((r for r in rows if r["coarse_face"] is not None
                     and np.isclose(face_mm, r["coarse_face"])), None)
        if step is not None:
            (near if step["p90"] <= 0.1 else far)[p] = step["p90"]
        elif rows and rows[-1]["fine_face"] is not None and (
                face_mm < rows[-1]["fine_face"] or np.isclose(face_mm, rows[-1]["fine_face"])):
            finest.append(p)
        else:
            unmeasured.append(p)
    parts = [f"by p90 {_span(list(g.values()), '.2f')} mm for patient(s) {', '.join(g)} "
             f"({why})" for g, why in ((near, "within 0.1 mm"),
                                       (far, "more: there this run's truth is coarser than "
                                             "the converged one")) if g]
    phrases = [f"a truth of this run's face {text} changes the skin from the next "
               "finer one " + ", and ".join(parts)] if parts else []
    if finest:
        phrases.append(f"this run's face {text} is as fine as the finest truth or "
                       f"finer for patient(s) {', '.join(finest)}")
    if unmeasured:
        phrases.append(f"the change from a truth of face {text} is not measured for "
                       f"patient(s) {', '.join(unmeasured)}")
    phrase = "; ".join(phrases)
    return phrase, not far and not unmeasured


def truth_note(truth, truth_tets, page=PAGE, mesher="lattice", face_mm=None,
               materials="cells", face_margin_mm=0.0):
    """What the refinement page measured of the truth, read from its table: the sentence
    of the cohort page on how far the truth has converged. ``mesher``, ``face_mm``,
    ``materials``, ``face_margin_mm``: the independent truth's options
    (``study_predictor``'s ``truth_mesher``, ``truth_face_mm``, ``truth_materials``,
    ``truth_face_margin_mm``); the refinement is this truth's only when the page used the
    same ones (and, for ``graded``, the same count
    outside the face and this run's face size as one of its two finest)."""
    this = _truth_name(truth, truth_tets, mesher, face_mm, materials, face_margin_mm)
    ref = refinement_rows(page) if truth == "independent" else None
    caveat = ("the errors below bound how far the models and this truth agree, not how "
              "accurate either is; a paired difference between two models is measured "
              "against the same truth and is the better-founded number.")
    if ref is None:
        return (f"The truth of this run is {this}; ``truth_refinement.md`` holds no "
                "refinement of it, so how far it has converged is not measured: " + caveat)
    pats = ref["patients"]
    p90 = [r["p90"] for r in pats.values()]
    coarse = [r["coarse"] for r in pats.values()]
    fine = [r["fine"] for r in pats.values()]
    other = _truth_mismatch(ref, truth_tets, mesher, face_mm, materials, face_margin_mm)
    faces = ""
    if mesher == "graded" and not other:
        faces = (f"; face {_span([float(r['coarse_face']) for r in pats.values()], 'g')} "
                 f"and {_span([float(r['fine_face']) for r in pats.values()], 'g')} mm; "
                 f"this run's face {face_size_text(face_mm)} is "
                 + _face_relation(pats, face_mm))
    done = [p for p, r in pats.items() if r["p90"] <= 0.1]
    it = "that truth" if other else "it"  # a refinement of another truth than this run's
    level, level_ok = ("", True) if faces == "" else _run_level(ref.get("steps", {}), face_mm)
    if len(done) == len(pats) and not level_ok:
        verdict = (f"{it} has converged there (p90 <= 0.1 mm) at its finest truths"
                   f"{_then(level)}, so " + caveat)
    elif len(done) == len(pats):
        verdict = f"{it} has converged there (p90 <= 0.1 mm)" + (
            "; this run's truth is not that one, so how far it has converged is not "
            "measured: " + caveat if other else f"{_then(level)}.")
    elif not done:
        verdict = f"{it} has not converged there (p90 above 0.1 mm){_then(level)}, so " + caveat
    else:
        verdict = (f"{it} has converged there (p90 <= 0.1 mm) for patient(s) "
                   f"{', '.join(done)}, not for patient(s) "
                   f"{', '.join(p for p in pats if p not in done)} (p90 above 0.1 mm)"
                   f"{_then(level)}, so " + caveat)
    return (f"The truth of this run is {this}. "
            + ("Its refinement" if not other else "A refinement of the independent truth")
            + f" (``truth_refinement.md``, {patients_text(pats)}"
            + ("" if any(int(p) >= FIRST_COHORT for p in pats)
               else ", not this run's patients")
            + (f"; {', and '.join(other)}" if other else "") + "): between the two finest "
            f"truths of each patient ({_span(coarse, 'd')} and {_span(fine, 'd')} "
            f"tetrahedra{faces}) the skin changes by p90 {_span(p90, '.2f')} mm, median "
            f"{_span([r['p50'] for r in pats.values()], '.3f')} mm; " + verdict)
