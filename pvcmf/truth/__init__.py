"""Virtual post-operative truth: a richer finite-element model than the one being judged.

No public pair of pre/post-operative scans exists, so pvcmf makes the post-operative face
of its virtual patients with a model that is deliberately *not* the MTM:

* large deformation: compressible neo-Hookean,
  ``W = mu/2 (I1 - 3 - 2 ln J) + lambda/2 (ln J)^2``, nearly incompressible at the
  tissue's Poisson ratios (``mu``, ``lambda`` per element from ``E_cross`` and ``nu``);
* fibre reinforcement: ``+ k/2 (I4 - 1)^2`` with ``I4 = a.C a`` along the element's fibre
  ``a`` and ``k = max(E_fiber - E_cross, 0)`` (zero for Table I, where muscle is softer
  along its fibres than across: then the muscle is isotropic in this model);
* quadratic (P2) elements on a tetrahedral mesh several times finer than the MTM's;
* boundary conditions from the plan (``apply_plan``): every fixed and joint node
  prescribed, sliding teeth contact as a penalty on the normal displacement, tangential
  motion free; where the prescribed data *alone* would invert or crush an element, the
  odd node of that element is released (left free) and reported;
* load stepping: a linearised predictor per load step, then Newton's method with a
  backtracking energy line search that rejects inverted elements; a failing step is
  halved.

Modules:

* :mod:`pvcmf.truth.solver` - :func:`solve_reference` (NGSolve, ``pip install
  pvcmf[reference]``);
* :mod:`pvcmf.truth.linear` - its Newton systems' linear solves, and whether the cores
  are free for NGSolve's threads (:func:`~pvcmf.truth.linear.cores_free`);
* :mod:`pvcmf.truth.grid` - :func:`truth_grid` (the patient's true labels -> fine planned
  grid -> solve, cached on disk by :func:`grid_hash` through :mod:`pvcmf.cache`) and
  :func:`postop_skin`;
* :mod:`pvcmf.truth.postop` - :func:`postop_ct`, the virtual post-operative CT, and
  :func:`reference_grid`;
* :mod:`pvcmf.truth.anatomy` - the patient's true anatomy as level sets, and a mesh's
  accuracy against it (``interface_distance``, ``muscle_volume_errors``);
* :mod:`pvcmf.truth.independent` - ``independent_truth_grid``: a truth on its own mesh
  of the exact anatomy with its own boundary model (``study_predictor(truth=
  "independent")``; the study's default truth is still :func:`truth_grid`);
* :mod:`pvcmf.truth.conform` - ``conforming_mesh``: the independent truth's soft tissue
  meshed by gmsh on its exact surface (``independent_truth_grid(mesher="conforming")``);
* :mod:`pvcmf.truth.graded` - ``graded_mesh``: the same, its surface sampled finely in the
  ball of the moved bones and at the conforming spacing elsewhere
  (``independent_truth_grid(mesher="graded")``);
* :mod:`pvcmf.truth.exact` - the exact soft tissue's level sets, projection and muscle
  fractions, shared by the meshers and the refinement measure;
* :mod:`pvcmf.truth.refinement` - the independent truth's refinement measured on the
  exact skin (``exact_skin_samples``, ``skin_displacement``, ``refinement_change``).

The truth is built from the filters directly, never through the pipeline it judges.
"""

from .grid import MODEL_VERSION, cached, grid_hash, postop_skin, solver_code_hash, truth_grid
from .postop import AIR_HU, GAP_HU, postop_ct, random_pose, reference_grid
from .solver import solve_reference

__all__ = ["AIR_HU", "GAP_HU", "MODEL_VERSION", "cached", "grid_hash", "postop_ct",
           "postop_skin", "random_pose", "reference_grid", "solve_reference",
           "solver_code_hash", "truth_grid"]
