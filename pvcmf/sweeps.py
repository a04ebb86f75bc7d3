"""Parameter sweeps over cases and model parameters, run on Dask, cached on disk.

The import path of :mod:`pvcmf.study`'s sweep modules, by responsibility:

* :mod:`pvcmf.study.parameters` - :data:`PARAMETERS`, :func:`validate_grid`,
  :func:`parse_grid`;
* :mod:`pvcmf.study.evaluation` - :class:`Evaluation`, :class:`FunctionEvaluation`,
  :func:`error_statistics`, :func:`synthetic_evaluate`, cache identities;
* :mod:`pvcmf.study.pipeline_evaluation` - :class:`PipelineEvaluation` (the pipeline),
  :func:`study_truth`;
* :mod:`pvcmf.study.engine` - :func:`sweep`;
* :mod:`pvcmf.study.tables` - :func:`save_table`, :func:`load_table`;
* :mod:`pvcmf.study.cli` - ``pvcmf sweep`` (:func:`add_sweep_parser`, :func:`run_sweep`).
"""

from __future__ import annotations

from .study.cli import add_sweep_parser, run_sweep
from .study.engine import _make_client, _run_group, resolve_evaluation, sweep  # noqa: F401
from .study.engine import resolve_evaluation as _resolve_evaluation  # noqa: F401
from .study.evaluation import (  # noqa: F401
    _SOURCE_HASHES, RESULT_SOURCES, Evaluation, FunctionEvaluation, case_identity, code_version,
    error_statistics, point_key, source_hash, synthetic_evaluate, synthetic_skin,
)
from .study.evaluation import case_identity as _case_identity  # noqa: F401
from .study.evaluation import point_key as _point_key  # noqa: F401
from .study.parameters import METRICS, PARAMETERS, TIMES, parse_grid, validate_grid
from .study.pipeline_evaluation import (  # noqa: F401
    STUDY_SPACING, TRUTH_MARGIN, PipelineEvaluation, _face_only, _postop_skin, _skin_mapping,
    _TruthSurface, study_truth,
)
from .study.tables import load_table, save_table

__all__ = [
    "PARAMETERS",
    "METRICS",
    "TIMES",
    "RESULT_SOURCES",
    "STUDY_SPACING",
    "TRUTH_MARGIN",
    "Evaluation",
    "FunctionEvaluation",
    "PipelineEvaluation",
    "sweep",
    "validate_grid",
    "study_truth",
    "code_version",
    "source_hash",
    "case_identity",
    "point_key",
    "resolve_evaluation",
    "error_statistics",
    "synthetic_evaluate",
    "synthetic_skin",
    "save_table",
    "load_table",
    "parse_grid",
    "add_sweep_parser",
    "run_sweep",
]
