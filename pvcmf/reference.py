"""Old import path of the virtual post-operative truth: see :mod:`pvcmf.truth`."""

from .truth.grid import (  # noqa: F401
    MODEL_VERSION, _skin_of, _solved_truth, _truth_grid, cached, grid_hash, postop_skin,
    solver_code_hash, truth_grid,
)
from .truth.solver import _released_nodes, solve_reference  # noqa: F401
