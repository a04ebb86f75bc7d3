"""``pvcmf sweep``: a parameter study on virtual patients from the command line.

:func:`add_sweep_parser` registers the sub-command on :mod:`argparse`; :func:`run_sweep`
runs it (:func:`pvcmf.study.engine.sweep`) and writes the table
(:func:`pvcmf.study.tables.save_table`). Everything that can be checked is checked before
any work: the grid, the patients, ``--workers`` and where the table goes
(:func:`pvcmf.study.tables.check_table_path`). Dask (``distributed``) is needed unless
``--scheduler synchronous``; without it the command says which extra to install.
"""

from __future__ import annotations

from pathlib import Path

from .engine import PATIENTS, sweep
from .evaluation import synthetic_evaluate
from .parameters import PARAMETERS, parse_grid
from .pipeline_evaluation import STUDY_SPACING, PipelineEvaluation
from .tables import check_table_path, save_table

__all__ = ["add_sweep_parser", "run_sweep"]

#: what ``pvcmf sweep`` says when Dask is missing
MISSING_DASK = ('pvcmf sweep needs Dask: pip install "pvcmf[sweep]" (or run with '
                "--scheduler synchronous)")


def add_sweep_parser(subparsers):
    """Register ``pvcmf sweep`` on an argparse sub-parser collection."""
    p = subparsers.add_parser(
        "sweep", help="run a parameter study (Dask) and write a table",
        description="Run a parameter sweep over virtual patients on Dask; write CSV/Parquet.",
    )
    p.add_argument("--patients", type=int, nargs="+", default=[1],
                   help="virtual patient numbers (%s)" % ", ".join(map(str, PATIENTS)))
    p.add_argument("--grid", nargs="+", required=True, metavar="NAME=VALUES",
                   help="e.g. nu=0:0.495:20 n_tets=10000,30000 maxilla_t_ap=0:8:17 (names: %s)"
                        % ", ".join(PARAMETERS))
    p.add_argument("--out", required=True, help="output table, .csv or .parquet")
    p.add_argument("--scheduler", default=None,
                   help="processes (default), threads, synchronous, or tcp://host:8786")
    p.add_argument("--cache-dir", default=None, help="result cache folder (rerun recomputes nothing)")
    p.add_argument("--workers", type=int, default=None,
                   help="local Dask processes (threads with --scheduler threads), >= 1; "
                        "default one per CPU")
    p.add_argument("--spacing", type=float, default=STUDY_SPACING,
                   help="default image resolution, mm (2: the study default, truths cached)")
    p.add_argument("--n-tets", type=int, default=30_000, help="default tetrahedra count")
    p.add_argument("--synthetic", action="store_true",
                   help="use the cheap synthetic evaluation instead of the pipeline (demo/test)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.add_argument("-v", "--verbose", action="count", default=0, help="log more (-v info, -vv debug)")
    p.set_defaults(func=run_sweep)
    return p


def run_sweep(args):
    """Run ``pvcmf sweep`` from parsed arguments; return (the written path, the table)."""
    if args.scheduler != "synchronous":
        try:
            import distributed  # noqa: F401
        except ImportError as err:
            raise SystemExit(f"{MISSING_DASK}; {err}") from None
    out = check_table_path(args.out, "--out")  # before any work: results are never lost
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be a positive integer (default: one per CPU), "
                         f"got {args.workers}")
    bad = [p for p in args.patients if p not in PATIENTS]
    if bad:
        raise ValueError(f"--patients must be virtual patient numbers {list(PATIENTS)}, "
                         f"got {bad}")
    grid = parse_grid(args.grid)
    evaluate = synthetic_evaluate if args.synthetic else PipelineEvaluation(
        spacing=args.spacing, n_tets=args.n_tets,
        cache_dir=None if args.cache_dir is None else Path(args.cache_dir) / "prepared")
    df = sweep(args.patients, grid, evaluate=evaluate, scheduler=args.scheduler,
               cache_dir=args.cache_dir, progress_bar=not args.no_progress, n_workers=args.workers)
    return save_table(df, out), df
