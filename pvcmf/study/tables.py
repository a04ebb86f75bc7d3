"""Sweep tables on disk: CSV or Parquet, chosen by the file's suffix, written atomically.

Delegates to :meth:`pandas.DataFrame.to_csv` / :meth:`~pandas.DataFrame.to_parquet`
(``pyarrow``) and :func:`pvcmf._atomic.atomic_path`; :func:`check_table_path` refuses a
path that could not be written (:func:`pvcmf.outputs.check_output_file`) before a sweep
computes anything.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pandas as pd

from .._atomic import atomic_path
from ..outputs import check_output_file

log = logging.getLogger(__name__)

__all__ = ["TABLE_SUFFIXES", "check_table_path", "load_table", "save_table"]

#: file extensions of a sweep table
TABLE_SUFFIXES = (".csv", ".parquet")
#: what writing Parquet without pyarrow says
NO_PYARROW = "writing Parquet needs pyarrow: pip install pyarrow (or use .csv)"


def _has_pyarrow():
    try:
        import pyarrow  # noqa: F401
    except ImportError:
        return False
    return True


def check_table_path(path, name="path"):
    """Check where a sweep table will go, before the sweep runs; returns it absolute.

    Refused with a ``ValueError`` naming ``name``: an empty path, a folder, a path under
    a file, a folder that cannot be written (:func:`pvcmf.outputs.check_output_file`),
    an extension other than ``.csv``/``.parquet``, and ``.parquet`` without ``pyarrow``.

    Examples
    --------
    >>> from pvcmf.study.tables import check_table_path
    >>> check_table_path("table.xlsx", "--out")
    Traceback (most recent call last):
    ...
    ValueError: --out='table.xlsx' must end in one of ['.csv', '.parquet'], got '.xlsx'
    """
    out = check_output_file(path, name, suffixes=TABLE_SUFFIXES)
    if out.suffix.lower() == ".parquet" and not _has_pyarrow():
        raise ValueError(f"{name}={str(path)!r}: {NO_PYARROW}")
    return out


def save_table(df, path):
    """Write a sweep table to ``.csv`` or ``.parquet`` (chosen by suffix), atomically.

    Array columns (``keep_arrays=True``) are dropped from CSV, with a warning; Parquet
    keeps them as lists and needs ``pyarrow`` (``pip install pyarrow``).

    Parameters
    ----------
    df : pandas.DataFrame
        Table from :func:`sweep`.
    path : str or Path
        Target file, ``*.csv`` or ``*.parquet``.

    Returns
    -------
    pathlib.Path
        The written path.

    Examples
    --------
    >>> import pvcmf, tempfile, pathlib
    >>> from pvcmf.study.evaluation import synthetic_evaluate
    >>> from pvcmf.study.tables import save_table, load_table
    >>> df = pvcmf.sweep(1, {"nu": [0.46]}, evaluate=synthetic_evaluate, scheduler="synchronous")
    >>> out = save_table(df, pathlib.Path(tempfile.mkdtemp()) / "t.csv")
    >>> float(load_table(out)["nu"].iloc[0])
    0.46
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".csv", ".parquet"):
        raise ValueError(f"path must end in .csv or .parquet, got {path.name!r}")
    array_cols = [c for c in df.columns if df[c].map(lambda v: isinstance(v, np.ndarray)).any()]
    out = df.copy()
    if suffix == ".csv":
        if array_cols:
            log.warning("save_table: dropping array columns %s from CSV (use .parquet)", array_cols)
            out = out.drop(columns=array_cols)
    else:
        try:
            import pyarrow  # noqa: F401
        except ImportError as err:
            raise ImportError(NO_PYARROW) from err
        for c in array_cols:
            out[c] = out[c].map(lambda v: v.ravel().tolist() if isinstance(v, np.ndarray) else v)
    out.attrs = {}
    with atomic_path(path) as tmp:
        if suffix == ".csv":
            out.to_csv(tmp, index=False)
        else:
            out.to_parquet(tmp, index=False)
    return path


def load_table(path):
    """Read a table written by :func:`save_table` (CSV or Parquet)."""
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        return pd.read_parquet(path)
    if path.suffix.lower() == ".csv":
        return pd.read_csv(path)
    raise ValueError(f"path must end in .csv or .parquet, got {path.name!r}")
