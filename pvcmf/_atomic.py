"""Atomic file writing: write next to the target, then ``os.replace`` it into place.

An interrupted write (exception, Ctrl-C, crash) leaves either the previous file or no
file at all, never a half-written one. Delegates to :func:`tempfile.mkstemp` and
:func:`os.replace` (atomic on POSIX and Windows when both paths share a folder).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path in ``path``'s folder; move it onto ``path`` on success.

    The temporary file keeps ``path``'s suffix so that writers choosing a format by
    extension (VTK, matplotlib) still work. On any exception the temporary file is
    removed and ``path`` is left untouched.

    Examples
    --------
    >>> import pyvista as pv, tempfile, os
    >>> from pvcmf._atomic import atomic_path
    >>> out = os.path.join(tempfile.mkdtemp(), "sphere.vtp")
    >>> with atomic_path(out) as tmp:
    ...     pv.Sphere().save(tmp)
    >>> os.path.exists(out)
    True
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def write_text(path, text):
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return Path(path)


@contextlib.contextmanager
def atomic_dir(path):
    """Yield a temporary folder next to ``path``; move it onto ``path`` on success.

    Whatever the caller writes into the folder appears at ``path`` all at once (a folder
    already there is replaced). On any exception the temporary folder is removed and
    ``path`` is left untouched.

    Examples
    --------
    >>> import tempfile, os
    >>> from pathlib import Path
    >>> from pvcmf._atomic import atomic_dir
    >>> out = Path(tempfile.mkdtemp()) / "entry"
    >>> with atomic_dir(out) as tmp:
    ...     _ = (Path(tmp) / "a.txt").write_text("a")
    >>> sorted(os.listdir(out))
    ['a.txt']
    """
    import shutil

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            shutil.rmtree(path, ignore_errors=True)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
