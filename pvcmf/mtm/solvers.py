"""Former home of the MTM solver; the names now live in :mod:`pvcmf.mtm.solver` and
:mod:`pvcmf.mtm.backends` and are re-exported here so that old imports keep working."""

from __future__ import annotations

from .backends.cg import AMG_OPTIONS as _AMG_OPTIONS  # noqa: F401
from .solver import (  # noqa: F401
    AUTO_DIRECT_MAX_POINTS,
    FIELD_BACKEND,
    FIELD_ERROR_ESTIMATE,
    FIELD_ITERATIONS,
    FIELD_LOST_DIGITS,
    FIELD_METHOD,
    FIELD_RESIDUAL,
    FIELD_TIME,
    METHODS,
    ORDERINGS,
    PRECISIONS,
    BackendUnavailableError,
    ConvergenceError,
    IllConditionedWarning,
    Solver,
    direct_backends,
    gpu_available,
    solve,
)
