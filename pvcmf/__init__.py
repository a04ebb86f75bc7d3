"""pvcmf: predict the face after cranio-maxillofacial surgery with PyVista and a Mass Tensor Model.

Importing pvcmf registers the ``cmf`` accessor on every PyVista dataset (see
:mod:`pvcmf.accessor`). Heavier submodules (datasets, mtm, atlas, ...) load on first use.
"""

from __future__ import annotations

import importlib
import logging

from . import arrays, filters
from .accessor import CMFAccessor
from ._version import __version__
from .plan import Osteotomy, Plan

logging.getLogger(__name__).addHandler(logging.NullHandler())

_LAZY_MODULES = ("datasets", "mtm", "atlas", "io", "figures", "reference", "validation", "cli",
                 "postop")
_LAZY_ATTRS = {
    "read_ct": "io",
    "sweep": "sweeps",
}

__all__ = ["arrays", "filters", "CMFAccessor", "Osteotomy", "Plan", "__version__",
           *_LAZY_MODULES, *_LAZY_ATTRS]


def __getattr__(name):
    if name in _LAZY_MODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _LAZY_ATTRS:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY_ATTRS[name]}"), name)
    raise AttributeError(f"module 'pvcmf' has no attribute {name!r}")
