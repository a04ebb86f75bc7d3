"""Where real data lives: ``$PVCMF_DATA_DIR`` (tests default it to ``../shared/data``)."""

from __future__ import annotations

import os
from pathlib import Path

ENV = "PVCMF_DATA_DIR"


def data_path(*parts, required=True):
    """Return ``$PVCMF_DATA_DIR/<parts>``.

    Parameters
    ----------
    *parts : str
        Path components below the data folder, e.g. ``("headsq", "quarter.nhdr")``.
    required : bool
        Raise ``FileNotFoundError`` if the path does not exist.

    Returns
    -------
    pathlib.Path or None
        ``None`` when the variable is unset and ``required`` is False.
    """
    root = os.environ.get(ENV)
    if not root:
        if required:
            raise FileNotFoundError(f"set {ENV} to the folder holding pvcmf's real data")
        return None
    path = Path(root).joinpath(*parts)
    if required and not path.exists():
        raise FileNotFoundError(f"{path} not found (from {ENV}={root!r})")
    return path
