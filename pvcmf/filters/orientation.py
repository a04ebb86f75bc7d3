"""Units and orientation of a head CT, checked on the image (the filter face of
:mod:`pvcmf.io.orientation`, where the code lives so that readers and datasets can use it)."""

from ..io.orientation import check_units, orient_head, reorient, standardize

__all__ = ["check_units", "orient_head", "reorient", "standardize"]
