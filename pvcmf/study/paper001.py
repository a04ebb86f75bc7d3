"""Paper 001's models in the validation study: the homogeneous and the inhomogeneous MTM.

Paper 001 meshes the facial soft tissue without muscles and compares

* the homogeneous model (sec. 2.1): one isotropic material of Poisson ratio
  :data:`PAPER_NU` (0.46, its optimum); Young's modulus cancels, every load being a
  prescribed displacement;
* the inhomogeneous model (sec. 2.2): each tetrahedron mixes fat and muscle by its share
  of the per-slice Gaussian-mixture classification of the CT
  (:func:`pvcmf.filters.classify_tissue`, the share sampled by random points,
  :func:`pvcmf.filters.sample_muscle_fraction`), ``nu_fat`` 0.485, ``nu_muscle`` 0.43 and
  ``E_muscle / E_fat`` 1 (the ratio of its optimum; results independent of it), the
  ``'paper001_inhomogeneous'`` table of :data:`pvcmf.mtm.TABLES`;
* the homogeneous model at other Poisson ratios (its sweep, :func:`nu_method`), re-solved
  on the same mesh;
* the homogeneous model on a finer mesh (``"homogeneous_fine"``), for the claim that a
  mesh of a given size is enough;
* ``"homogeneous_auto"`` and ``"inhomogeneous_auto"``: the two models from the CT and the
  plan alone (automatic bone segments, no true labels), as a real pipeline has them; the
  other names get the true bone labels (oracle inputs).

Method names of :func:`pvcmf.study.validation.study_predictor`. One pipeline run
(segmentation, classification, mesh, boundary conditions; :func:`pvcmf.pipeline.simulate`)
serves every model of a patient at one mesh size; each model is one MTM solve on it.
Delegates to :mod:`pvcmf.pipeline`, :mod:`pvcmf.filters` and :mod:`pvcmf.mtm`.
"""

from __future__ import annotations

import re

import numpy as np

from .. import arrays, filters, mtm
from ..pipeline import simulate

__all__ = ["FINE_METHOD", "NU_GRID", "PAPER001_AUTO_METHODS", "PAPER001_METHODS", "PAPER_NU",
           "is_paper001_method", "method_nu", "nu_method", "paper001_pipeline",
           "paper001_solve"]

#: paper 001's optimal Poisson ratio of the homogeneous model (sec. 3.1: 0.45 <= nu <= 0.46)
PAPER_NU = 0.46
#: the Poisson ratios of the cohort's sweep of the homogeneous model (paper 001 sweeps
#: 0-0.495; denser near its optimum)
NU_GRID = (0.30, 0.40, 0.45, 0.46, 0.47, 0.49)
#: the homogeneous model on the finer mesh (``fine_tets`` of ``study_predictor``)
FINE_METHOD = "homogeneous_fine"
#: the fixed methods of paper 001 (the sweep adds :func:`nu_method` names)
PAPER001_METHODS = ("homogeneous", "inhomogeneous", FINE_METHOD)
#: the homogeneous and inhomogeneous models from the CT and the plan alone
PAPER001_AUTO_METHODS = ("homogeneous_auto", "inhomogeneous_auto")
_NU_NAME = re.compile(r"^homogeneous_nu(0\.\d{1,4})$")


def nu_method(nu):
    """Method name of the homogeneous model at Poisson ratio ``nu``.

    Examples
    --------
    >>> from pvcmf.study.paper001 import method_nu, nu_method
    >>> nu_method(0.46), nu_method(0.3), method_nu(nu_method(0.3))
    ('homogeneous', 'homogeneous_nu0.300', 0.3)
    """
    nu = float(nu)
    if not 0.0 <= nu < 0.5:
        raise ValueError(f"nu must be in [0, 0.5), got {nu!r}")
    return "homogeneous" if abs(nu - PAPER_NU) < 5e-5 else f"homogeneous_nu{nu:.3f}"


def method_nu(method):
    """Poisson ratio of a homogeneous method (``"homogeneous"``: :data:`PAPER_NU`), else
    None."""
    if method in ("homogeneous", FINE_METHOD):
        return PAPER_NU
    m = _NU_NAME.match(str(method))
    return float(m.group(1)) if m else None


def is_paper001_method(method):
    """Whether ``method`` is one of paper 001's models (:data:`PAPER001_METHODS` or a
    :func:`nu_method` name, or one of :data:`PAPER001_AUTO_METHODS`)."""
    return (method in PAPER001_METHODS or method in PAPER001_AUTO_METHODS
            or method_nu(method) is not None)


def paper001_pipeline(case, n_tets, oracle=True):
    """Paper 001's pre-operative model of a patient, unsolved: segmentation with the true
    bone labels and landmarks (``oracle=False``: the bone segments found from the CT, as
    :func:`pvcmf.pipeline.simulate` finds them for a real scan), fat/muscle
    classification, no atlas muscles, a mesh that ignores the tissue classes, the plan's
    boundary conditions.

    Returns
    -------
    pvcmf.pipeline.Result
        ``mesh`` (with boundary conditions) and ``labels`` (classified tissue).
    """
    res = simulate(case.ct, case.plan, bones=case.truth if oracle else None,
                   landmarks=case.landmarks if oracle else None,
                   n_tets=n_tets, mesh_options={"conforming": False}, figures=False,
                   muscles=False, classify=True, solve=False)
    if res.mesh is None:
        raise RuntimeError(f"the pipeline made no mesh for patient "
                           f"{getattr(case, 'patient', '?')}; skipped steps: {res.skipped}")
    return res


def _isotropic(grid, e, nu):
    g = grid.copy()
    n = g.n_cells
    g.cell_data[arrays.E_FIBER] = np.broadcast_to(np.asarray(e, float), (n,)).copy()
    g.cell_data[arrays.E_CROSS] = g.cell_data[arrays.E_FIBER].copy()
    g.cell_data[arrays.NU] = np.broadcast_to(np.asarray(nu, float), (n,)).copy()
    g.cell_data[arrays.FIBER] = np.zeros((n, 3))
    return g


def paper001_solve(res, method):
    """Solve one of paper 001's models on a pipeline result of :func:`paper001_pipeline`.

    Parameters
    ----------
    res : pvcmf.pipeline.Result
        The patient's unsolved model.
    method : str
        ``"inhomogeneous"``, a homogeneous method (:func:`method_nu`), or one of
        :data:`PAPER001_AUTO_METHODS` (the same model; the inputs differ upstream).

    Returns
    -------
    pyvista.UnstructuredGrid
        The solved mesh (``arrays.DISPLACEMENT``).
    """
    if method in PAPER001_AUTO_METHODS:
        method = method[: -len("_auto")]
    if method == "inhomogeneous":
        g = filters.sample_muscle_fraction(res.mesh, res.labels)
        f = np.clip(np.asarray(g.cell_data[arrays.MUSCLE_FRACTION], float), 0.0, 1.0)
        table = mtm.TABLES["paper001_inhomogeneous"]
        nu = (1 - f) * table["fat"]["nu"] + f * table["muscle"]["nu"]
        e = (1 - f) * table["fat"]["E_cross"] + f * table["muscle"]["E_cross"]
        return mtm.solve(_isotropic(g, e, nu))
    nu = method_nu(method)
    if nu is None:
        raise ValueError(f"method must be one of paper 001's models, got {method!r}")
    return mtm.solve(_isotropic(res.mesh, 1.0, nu))
