"""Backends of the MTM solver: direct factorisations and the solution methods.

Direct factorisations (``Solver(method='direct', backend=...)``), one module each:

``pardiso``
    MKL PARDISO through pypardiso's MKL runtime (:mod:`.pardiso`; ``pip install pvcmf[fast]``).
``cholmod``
    CHOLMOD supernodal Cholesky through scikit-sparse (:mod:`.cholmod`; needs a system
    SuiteSparse).
``superlu``
    scipy's SuperLU (:mod:`.superlu`; always available, alias ``'splu'``).

``backend='auto'`` takes the first *installed* one of :data:`PREFERENCE` (PARDISO, CHOLMOD,
SuperLU): the choice depends on the installed packages only, and a :class:`~pvcmf.mtm.Solver`
keeps its backend for its whole life. Methods: :mod:`.direct` (factorise, solve, refine),
:mod:`.cg` (AMG- or Jacobi-preconditioned conjugate gradient), :mod:`.relaxation` (the
paper's local iteration) and :mod:`.gpu` (CuPy conjugate gradient).
"""

from __future__ import annotations

from .._common import BackendUnavailableError
from . import cholmod, pardiso
from .cholmod import Cholmod
from .pardiso import Pardiso
from .superlu import SuperLU

#: direct backends in the order ``backend='auto'`` tries them (the first installed one wins)
PREFERENCE = ("pardiso", "cholmod", "superlu")
#: other accepted spellings of backend names
ALIASES = {"splu": "superlu"}
_CLASSES = {"pardiso": Pardiso, "cholmod": Cholmod, "superlu": SuperLU}
_INSTALL = {"pardiso": "pip install pypardiso (or pvcmf[fast])",
            "cholmod": "pip install scikit-sparse (needs SuiteSparse installed on the system)"}


def direct_backends():
    """Names of the installed direct backends, in ``backend='auto'`` order (``'superlu'`` last).

    Examples
    --------
    >>> from pvcmf.mtm import direct_backends
    >>> direct_backends()[-1]
    'superlu'
    """
    found = {"pardiso": pardiso.available(), "cholmod": cholmod.available(), "superlu": True}
    return [name for name in PREFERENCE if found[name]]


def resolve(backend):
    """The direct backend's canonical name for ``backend`` (``'auto'``, None: the first installed).

    Raises
    ------
    BackendUnavailableError
        ``backend`` is unknown or not installed here; the message names it and says how to
        install it.

    Examples
    --------
    >>> from pvcmf.mtm.backends import resolve
    >>> resolve("splu")
    'superlu'
    """
    installed = direct_backends()
    if backend is None or backend == "auto":
        return installed[0]
    name = ALIASES.get(backend, backend)
    if name not in _CLASSES:
        raise BackendUnavailableError(
            f"backend must be 'auto' or one of {list(PREFERENCE) + sorted(ALIASES)}, "
            f"got {backend!r}")
    if name not in installed:
        raise BackendUnavailableError(
            f"backend {backend!r} is not installed here ({_INSTALL[name]}); installed: "
            f"{installed}")
    return name


def factorisation(name):
    """The class of the direct backend ``name`` (a canonical name from :func:`resolve`)."""
    return _CLASSES[name]


def gpu_available():
    """True when CuPy imports and sees a CUDA device."""
    try:
        import cupy

        return cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # ImportError, CUDARuntimeError, ...
        return False


__all__ = ["ALIASES", "PREFERENCE", "BackendUnavailableError", "Cholmod", "Pardiso", "SuperLU",
           "direct_backends", "factorisation", "gpu_available", "resolve"]
