"""Data pvcmf runs on: virtual patients (embedded, the default) and real CT.

``phantom(patient=1, spacing=1.0)`` builds a deterministic virtual patient (module
``phantom``); ``headsq()`` loads VTK's real head CT (module ``realct``);
``cone_beam_field(ct, centre)`` turns a real CT into a cone-beam scanner's field around the
jaws (module ``cone_beam``). Real data is found
through the ``PVCMF_DATA_DIR`` environment variable (see :func:`data_path`).
"""

from __future__ import annotations

import importlib

from ._paths import data_path

_LAZY = {"phantom": "phantom", "Case": "phantom", "headsq": "realct",
         "cone_beam_field": "cone_beam"}

__all__ = ["data_path", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'pvcmf.datasets' has no attribute {name!r}")
