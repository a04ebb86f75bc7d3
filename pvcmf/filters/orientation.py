"""Units and orientation of a head CT, checked on the image (the filter face of
:mod:`pvcmf.io.orientation`, where the code lives so that readers and datasets can use it),
and the check that the image shows a head at all (:func:`check_head`, which
:func:`standardize` and :func:`pvcmf.filters.segment` run)."""

from ..io.head_check import check_head
from ..io.orientation import check_units, orient_head, reorient, standardize

__all__ = ["check_head", "check_units", "orient_head", "reorient", "standardize"]
