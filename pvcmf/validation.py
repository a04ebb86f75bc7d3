"""Old import path of the error statistics, face regions and validation study: see
:mod:`pvcmf.study.statistics` and :mod:`pvcmf.study.validation`."""

from .study.statistics import STAT_COLUMNS, error_statistics, label_face_regions, summary  # noqa: F401
from .study.validation import STUDY_METHODS, TRUTH_REACH, run_study, study_predictor  # noqa: F401
