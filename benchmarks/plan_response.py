"""Speed of the plan response operator against the full solve, in one run.

Not run by CI. ``python benchmarks/plan_response.py --write docs/benchmarks/plan_response.md``
builds a mesh of virtual patient 1 at 2 mm (muscles embedded, as ``pvcmf demo``) of about
``--n-tets`` tetrahedra (default 30k),
a dense skin of about ``--skin-points`` points (the image skin, subdivided and decimated),
and measures, for a two-segment template (maxilla and mandible):

* ``full``: one plan by ``apply_plan`` + :func:`pvcmf.mtm.solve` + the skin transfer (a kept
  transfer operator; its build is timed on its own);
* ``build``: :func:`pvcmf.mtm.response.plan_response` (boundary conditions, one
  factorisation, twelve solves per segment, the transfer's rows built in ranges of skin
  points by a partner beside them (a second thread, as ``plan_response`` does by
  default, or as ``--build-in`` says) and by the calling thread after its solves, joined (the
  smoothing steps, with the unsmoothed transfer times the nodal response made beside them
  on a second thread) and folded in: the smoothing steps on those dense rows), and its
  ratio to a factorisation plus the same solves timed on
  their own in the same run (nothing else running in the process; the build's double
  factor, with and without the per-solve solution checks, which the build skips), in
  wall-clock and CPU time (the process's and its child's), medians of ``--repeat`` rounds
  that time the five in turn (the fourth: the build with the other partner, a forked
  process for a thread and a thread otherwise; the fifth: the build without a dense
  skin, the operator of the mesh's own nodes);
* ``predict``: one plan's dense-skin displacement (new array, or written into a kept one),
  its breakdown (parameters; the product on one BLAS thread: nodal displacement of the
  nodes the few-weight rows use, dense rows, one CSR product into the output; the new
  surface), its CPU time (the calling thread's, insensitive to other processes taking
  the core), the product on two BLAS threads, the same plans through a dense operator
  over every skin point (one vector-matrix product over ``(12 k, 3 n_skin)``) and the
  ratio, the predicted surface (a new PolyData, or a kept one updated in place) and the
  mesh's surface nodes (medians over ``--plans`` random plans);
* ``statistics``: max / mean / RMS of the skin displacement of ``--batch`` random plans;
* errors: the operator against the full solve (with the operator's double factor, and
  with :func:`~pvcmf.mtm.solve`'s default: a single-precision PARDISO factor refined in
  double to ``tol``, whose own error then shows), the float32 rounding bound that decides
  ``dtype='auto'``, and the float32 skin operator against the same product in float64.

Every time is a median; ratios are taken within the run.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout
from pvcmf import arrays, datasets  # noqa: E402
from pvcmf.filters import apply_plan  # noqa: E402
from pvcmf.filters.surface_mapping import Transfer  # noqa: E402
from pvcmf.mtm import solve  # noqa: E402
from pvcmf.mtm.response import plan_response  # noqa: E402
from pvcmf.pipeline import simulate  # noqa: E402
from pvcmf.plan import Osteotomy, Plan  # noqa: E402

SEGMENTS = ("maxilla", "mandible")


def random_plans(n, seed=0):
    """``n`` random two-segment plans: translations within 6 mm, rotations within 6 deg."""
    rng = np.random.default_rng(seed)
    return [Plan(tuple(Osteotomy(s, translation=tuple(rng.uniform(-6, 6, 3)),
                                 rotation=tuple(rng.uniform(-6, 6, 3))) for s in SEGMENTS))
            for _ in range(n)]


def dense_skin(skin, n_points):
    """The skin with about ``n_points`` points (linear subdivision, then decimation)."""
    dense = skin
    while dense.n_points < n_points:
        dense = dense.subdivide(1, subfilter="linear")
    if dense.n_points > 1.05 * n_points:
        dense = dense.decimate(1.0 - n_points / dense.n_points)
    return dense.clean()


def median_time(fn, repeat):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def per_plan_ms(fn, plans, clock=time.perf_counter):
    """Median milliseconds of ``fn(plan)`` over ``plans`` (``clock``: wall or thread CPU)."""
    times = []
    for plan in plans:
        t = clock()
        fn(plan)
        times.append(clock() - t)
    return 1e3 * statistics.median(times)


def machine():
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, numpy {np.__version__}, {platform.system()}")


def cpu_now():
    """CPU seconds of this process and its waited-for children."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def reference_solves(mesh, labels, template, checks=True):
    """Seconds (wall, process CPU) of one factorisation plus the operator's 12 k solves, on
    their own, with the solver options of :func:`plan_response` (a double factor);
    ``checks=False``: without the per-solve solution checks (as the build solves)."""
    import warnings

    from pvcmf.mtm import Solver
    from pvcmf.mtm.constraints import SolutionWarning

    probe = Plan(tuple(Osteotomy(o.segment, translation=tuple(np.eye(3)[i]))
                       for i, o in enumerate(template.osteotomies)))
    ref = apply_plan(mesh, probe, labels)
    rhs = np.asarray(ref[arrays.BC_DISPLACEMENT], dtype=float)
    t, c = time.perf_counter(), cpu_now()
    solver = Solver(ref, precision="double")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SolutionWarning)
        for _ in range(12 * len(template.osteotomies)):
            solver.solve(rhs, checks=checks)
    return time.perf_counter() - t, cpu_now() - c


def build_rows(mesh, labels, skin, template, rows, repeat, build_in="thread"):
    """Time the operator's build against a factorisation plus its solves (medians of
    ``repeat`` rounds, each timing the four in turn; ``build_in``: where the build's
    partner runs, :data:`pvcmf.mtm.response_transfer.BUILD_IN`)."""
    from pvcmf.mtm import response_transfer

    other = "process" if build_in == "thread" else "thread"  # the other partner, compared
    keys = ("ref", "ref_cpu", "bare", "bare_cpu", "build", "build_cpu", "other", "other_cpu",
            "nodes", "nodes_cpu")
    times = {key: [] for key in keys}
    parts = []  # the build's own timings, per round
    op = None
    for _ in range(repeat):
        for key, value in zip(("ref", "ref_cpu"), reference_solves(mesh, labels, template)):
            times[key].append(value)
        for key, value in zip(("bare", "bare_cpu"),
                              reference_solves(mesh, labels, template, checks=False)):
            times[key].append(value)
        for key, where in (("other", other), ("build", build_in)):
            response_transfer.BUILD_IN = where
            op = None  # free the previous operator first
            t, c = time.perf_counter(), cpu_now()
            op = plan_response(mesh, labels, skin=skin, plan=template)
            times[key].append(time.perf_counter() - t)
            times[f"{key}_cpu"].append(cpu_now() - c)
            if key == "build":
                parts.append({**op.timings, **{f"ranges {k}": v for k, v in
                                               (op.transfer_ranges or {}).items()}})
        response_transfer.BUILD_IN = build_in
        t, c = time.perf_counter(), cpu_now()  # the operator alone: the mesh's own nodes
        plan_response(mesh, labels, plan=template)
        times["nodes"].append(time.perf_counter() - t)
        times["nodes_cpu"].append(cpu_now() - c)
    med = {key: statistics.median(v) for key, v in times.items()}
    rows["build (s)"] = med["build"]
    for key in parts[-1]:  # medians over the rounds, like the rest
        value = statistics.median(p.get(key, np.nan) for p in parts)
        if key.startswith("ranges "):
            rows[f"build: transfer ranges ({key[7:]})"] = value
        else:
            rows[f"build: {key} (s)"] = value
    rows["factorisation + solves on their own (s)"] = med["ref"]
    rows["build / (factorisation + solves)"] = med["build"] / med["ref"]
    rows["build without a dense skin (the mesh's nodes) (s)"] = med["nodes"]
    rows["build without a dense skin / (factorisation + solves)"] = med["nodes"] / med["ref"]
    rows["build without a dense skin, CPU time (s)"] = med["nodes_cpu"]
    rows["build, CPU time of the process and its child (s)"] = med["build_cpu"]
    rows["factorisation + solves on their own, CPU time (s)"] = med["ref_cpu"]
    rows["build / (factorisation + solves), CPU time"] = med["build_cpu"] / med["ref_cpu"]
    rows["factorisation + solves without solution checks, CPU time (s)"] = med["bare_cpu"]
    rows["build / (factorisation + solves without checks), CPU time"] = (med["build_cpu"]
                                                                         / med["bare_cpu"])
    named = {"process": "in a forked process", "thread": "on a second thread",
             "auto": "as 'auto' chooses"}[other]
    rows[f"build, transfer {named} instead (s)"] = med["other"]
    rows[f"build, transfer {named} / as built"] = med["other"] / med["build"]
    rows[f"build, transfer {named}, CPU time (s)"] = med["other_cpu"]
    skin_op = op.skin_operator
    rows["skin operator dtype ('auto')"] = str(skin_op.dtype)
    rows["float32 rounding bound, plans to 30 deg / 20 mm (mm)"] = op.float32_error
    rows["skin points the transfer reaches"] = len(op.reached)
    rows["skin points from the nodal response (few transfer weights)"] = len(skin_op.sparse_rows)
    rows["mesh nodes those points use"] = len(skin_op.used)
    rows["skin points with dense rows (many transfer weights)"] = len(skin_op.dense_rows)
    rows["bytes one plan reads (MB)"] = skin_op.nbytes / 1e6
    rows["bytes of a dense operator over every skin point (MB)"] = (
        8 * skin_op.K * 3 * skin_op.n / 1e6)
    return op


def predict_rows(op, skin, plans, rows):
    """Per-plan prediction times and their breakdown."""
    from pvcmf.mtm.response import _one_thread

    op32 = op.astype(np.float32)
    n = skin.n_points
    buf = np.zeros((n, 3))
    rows["predict, dense skin, per plan (ms)"] = per_plan_ms(op.predict_displacement, plans)
    rows["predict, dense skin, CPU time per plan (ms)"] = per_plan_ms(
        op.predict_displacement, plans, clock=time.thread_time)
    rows["predict breakdown: parameters (ms)"] = per_plan_ms(op.parameters, plans)
    params = {id(p): op.parameters(p) for p in plans}
    skin_op = op.skin_operator
    out = np.empty(3 * n)
    rows["predict breakdown: product into the output, one BLAS thread (ms)"] = per_plan_ms(
        lambda p: skin_op.apply(params[id(p)], out, threads=1), plans)
    rows["predict breakdown: product, CPU time (ms)"] = per_plan_ms(
        lambda p: skin_op.apply(params[id(p)], out, threads=1), plans, clock=time.thread_time)
    rows["product, two BLAS threads (ms)"] = per_plan_ms(
        lambda p: skin_op.apply(params[id(p)], out, threads=2), plans)
    n_u3 = skin_op.Ru.shape[0]
    x = np.empty(n_u3 + skin_op.D.shape[1])
    with _one_thread(1):
        rows["product breakdown: nodal displacement, CPU time (ms)"] = per_plan_ms(
            lambda p: np.dot(skin_op.Ru, params[id(p)], out=x[:n_u3]), plans,
            clock=time.thread_time)
        rows["product breakdown: dense rows, CPU time (ms)"] = per_plan_ms(
            lambda p: np.dot(params[id(p)], skin_op.D, out=x[n_u3:]), plans,
            clock=time.thread_time)
    full = np.ascontiguousarray(skin_op.rows(np.arange(n)).reshape(skin_op.K, -1))
    dest = np.empty(3 * n)

    def dense(p):  # a dense operator over every skin point: parameters, one product
        a = op.parameters(p)
        with _one_thread(1):
            np.dot(a, full, out=dest)

    ratio = []
    for p in plans:  # interleaved, so both see the same machine
        times = []
        for fn in (lambda q: op.predict_displacement(q, out=buf), dense):
            t = time.thread_time()
            fn(p)
            times.append(time.thread_time() - t)
        ratio.append(times[0] / times[1])
    rows["dense operator over every skin point, into a kept array, per plan (ms)"] = (
        per_plan_ms(dense, plans))
    rows["predict into a kept array / dense operator, CPU time (median ratio)"] = (
        statistics.median(ratio))
    full = None  # free it before the statistics
    rows["predict, dense skin, float32, per plan (ms)"] = per_plan_ms(op32.predict_displacement, plans)
    rows["predict, dense skin, into a kept array, per plan (ms)"] = per_plan_ms(
        lambda p: op.predict_displacement(p, out=buf), plans)
    rows["predict, new PolyData, per plan (ms)"] = per_plan_ms(op.predict, plans)
    surf = op.predict(plans[0])
    rows["predict, kept PolyData updated in place, per plan (ms)"] = per_plan_ms(
        lambda p: op.predict(p, out=surf), plans)
    rows["predict, kept PolyData updated in place, CPU time per plan (ms)"] = per_plan_ms(
        lambda p: op.predict(p, out=surf), plans, clock=time.thread_time)
    rows["predict, new PolyData, CPU time per plan (ms)"] = per_plan_ms(
        op.predict, plans, clock=time.thread_time)
    rows["predict breakdown: the new surface, CPU time (ms)"] = (
        rows["predict, new PolyData, CPU time per plan (ms)"]
        - rows["predict, dense skin, CPU time per plan (ms)"])
    rows["predict, surface nodes, per plan (ms)"] = per_plan_ms(op.predict_nodes, plans)
    return op32


def run(args):
    case = datasets.phantom(patient=1, spacing=2.0)
    res = simulate(case.ct, case.plan, bones=case.truth, landmarks=getattr(case, "landmarks", None),
                   solve=False, figures=False, n_tets=args.n_tets)
    mesh, labels = res.mesh, res.labels
    skin = dense_skin(res.skin_pre, args.skin_points)
    template = Plan(tuple(Osteotomy(s) for s in SEGMENTS))
    plans = random_plans(max(args.plans, 3))
    rows = {"tetrahedra": mesh.n_cells, "mesh points": mesh.n_points, "skin points": skin.n_points}

    t = time.perf_counter()
    transfer = Transfer(mesh, skin)
    transfer.W  # the smoothed sparse operator, as map_to_surface applies it
    rows["transfer build, smoothed sparse operator (s)"] = time.perf_counter() - t
    rows["modelled skin points"] = int(transfer.modelled.sum())

    def full(plan, **options):
        grid = apply_plan(mesh, plan, labels)
        u = np.asarray(solve(grid, **options)[arrays.DISPLACEMENT], dtype=float)
        return transfer(u)

    rows["full solve per plan (s)"] = median_time(lambda: full(plans[0]), args.repeat)
    op = build_rows(mesh, labels, skin, template, rows, args.repeat, args.build_in)
    op32 = predict_rows(op, skin, plans[:args.plans], rows)
    rows["full / predict (dense skin)"] = (rows["full solve per plan (s)"]
                                           / (1e-3 * rows["predict, dense skin, per plan (ms)"]))
    err, err_default, err32 = 0.0, 0.0, 0.0
    for plan in plans[:3]:
        fast = op.predict_displacement(plan)
        err = max(err, float(np.abs(fast - full(plan, precision="double")).max()))
        err_default = max(err_default, float(np.abs(fast - full(plan)).max()))
        err32 = max(err32, float(np.abs(fast - transfer(op.predict_mesh(plan))).max()))
    rows["max |operator - full solve| (mm)"] = err
    rows["max |operator - full solve, default mixed-precision factor| (mm)"] = err_default
    rows["max |operator - float64 product| (mm)"] = err32
    rows["max |float32 - float64 operator|, these plans (mm)"] = max(
        float(np.abs(op32.predict_displacement(p) - op.predict_displacement(p)).max())
        for p in plans[:3])
    batch = random_plans(args.batch, seed=1)
    for name, o in (("", op), (", float32", op32)):
        t = time.perf_counter()
        o.statistics(batch)
        rows[f"statistics of {args.batch} plans{name} (s)"] = time.perf_counter() - t
    return rows


def table(rows):
    lines = ["| quantity | value |", "|---|---|"]
    for key, value in rows.items():
        text = f"{value:.4g}" if isinstance(value, float) else str(value)
        lines.append(f"| {key} | {text} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skin-points", type=int, default=100_000)
    p.add_argument("--n-tets", type=int, default=30_000,
                   help="tetrahedra the mesh is asked for (simulate's n_tets)")
    p.add_argument("--plans", type=int, default=50, help="plans timed one by one")
    p.add_argument("--batch", type=int, default=1000, help="plans of the statistics batch")
    p.add_argument("--repeat", type=int, default=3,
                   help="repeats of the full solve and of the build with its reference")
    p.add_argument("--build-in", choices=("auto", "process", "thread"), default="thread",
                   help="where the build's transfer partner runs (default: a second thread, "
                        "as plan_response; the other of thread and process is timed beside "
                        "it)")
    p.add_argument("--write", metavar="MD", help="write the table as a MyST page")
    args = p.parse_args(argv)
    rows = run(args)
    text = table(rows)
    print(text)
    if args.write:
        command = "python benchmarks/plan_response.py " + " ".join(argv or sys.argv[1:])
        page = ("# Plan response operator\n\n"
                "The predicted skin of a plan as a few products over a stored operator "
                "(:func:`pvcmf.mtm.response.plan_response`: skin points with few transfer "
                "weights from the nodal displacement, the others from dense rows) "
                "against apply_plan + solve + "
                "transfer, on a mesh of virtual patient 1 (2 mm, muscles) of about 30k "
                "tetrahedra (`--n-tets`), in one run. "
                "Times are medians of wall-clock time unless marked CPU time (the calling "
                "thread's own time, which other processes sharing the cores do not inflate). "
                "The build's ratio divides by a factorisation plus the same solves timed on "
                "their own (the build's double factor; with the solution checks that "
                "`Solver.solve` runs by default, and without them as the build solves), "
                "medians of rounds that time them in turn with the build and the build "
                "without a dense skin (the operator of the mesh's own nodes: boundary "
                "conditions, factorisation and solves; the dense skin adds its transfer); "
                "the skin transfer's rows are built in ranges of skin points on both "
                "cores: a partner starts on them beside the factorisation and solves, the "
                "calling thread takes the ranges left after its solves (the timings name "
                "the partner: a second thread, plan_response's default, or a forked "
                "process; `--build-in` chooses, and the other is timed beside it), then "
                "joins them (`transfer join`: the "
                "smoothing steps, and beside them on a second thread the unsmoothed "
                "transfer times the nodal response) and folds them in on both cores "
                "(`build: fold`: the steps on those dense rows); the build's CPU time "
                "is the process's (all its threads) and its child's. "
                "The transfer's smoothing steps outside the mesh act on the folded dense "
                "rows, not on the sparse transfer; the transfer build on its own makes "
                "the smoothed sparse operator that map_to_surface applies. "
                "The float32 rounding bound is what ``dtype='auto'`` compares with 1e-6 mm.\n\n"
                f"Command: `{command}`\n\nMachine: {machine()}\n\n{text}\n")
        with open(args.write, "w", encoding="utf-8") as fh:
            fh.write(page)


if __name__ == "__main__":
    main()
