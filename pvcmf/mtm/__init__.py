"""The Mass Tensor Model (MTM): materials, tensors, constraints and solvers.

Paper 001 (eqs. 1-4) writes the elastic force at vertex ``j`` as
``K_jj u_j + sum_k K_jk u_k``; the rest position of the free vertices makes every such force
zero. pvcmf stores the tensors ``K_jj`` / ``K_jk`` as the 3x3 blocks of one
:class:`scipy.sparse.bsr_matrix` (:func:`stiffness`), eliminates fixed, joint and sliding
boundary conditions (:mod:`~pvcmf.mtm.constraints`) and solves with a sparse factorisation
(PARDISO, CHOLMOD or SuperLU, :mod:`~pvcmf.mtm.backends`), an AMG-preconditioned CG, the
paper's relaxation or a CuPy CG (:func:`solve`, :class:`Solver` in :mod:`~pvcmf.mtm.solver`).
Materials follow paper 000 Table I (transversely isotropic muscle) or paper 001
(:data:`TABLES`, :mod:`~pvcmf.mtm.materials`). Delegates to numpy, scipy.sparse,
scikit-sparse/pypardiso, pyamg and CuPy.

Examples
--------
>>> import pvcmf
>>> sorted(pvcmf.mtm.TABLES)
['paper000', 'paper001_homogeneous', 'paper001_inhomogeneous']
"""

from __future__ import annotations

from .assembly import Assembler, InvertedTetrahedraWarning, grid_materials, stiffness, tetrahedra
from .constraints import Constraints, RigidModeError, sliding_frames
from .materials import (
    TABLES,
    VOIGT_PAIRS,
    check_positive_definite,
    constitutive_matrix,
    elastic_coefficients,
    material_table,
    positive_definite_mask,
)
from .solver import (
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

__all__ = [
    "AUTO_DIRECT_MAX_POINTS", "Assembler", "BackendUnavailableError", "PRECISIONS", "Constraints", "InvertedTetrahedraWarning", "ConvergenceError", "IllConditionedWarning", "METHODS", "ORDERINGS",
    "RigidModeError", "Solver", "TABLES", "VOIGT_PAIRS", "check_positive_definite",
    "constitutive_matrix", "direct_backends", "elastic_coefficients", "gpu_available",
    "grid_materials", "material_table", "positive_definite_mask", "sliding_frames", "solve",
    "stiffness", "tetrahedra", "FIELD_BACKEND", "FIELD_ERROR_ESTIMATE", "FIELD_ITERATIONS",
    "FIELD_LOST_DIGITS", "FIELD_METHOD", "FIELD_RESIDUAL", "FIELD_TIME",
]
