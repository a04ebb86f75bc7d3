"""Atomic file writing: write next to the target, then ``os.replace`` it into place.

An interrupted write (exception, Ctrl-C, crash) leaves either the previous file or no
file at all, never a half-written one. The temporary files and folders are hidden
siblings named ``.<name>.<random>.part<suffix>``, so that a later writer can remove
those a killed process left behind (:func:`remove_temporaries`). Files and folders get the
permissions the process's umask allows (``mkstemp``'s 0600 is widened to them).
Delegates to :func:`tempfile.mkstemp` and :func:`os.replace` (atomic on POSIX and
Windows when both paths share a folder).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path

#: signals held back while a temporary is created, so that one arriving then is raised
#: only once the temporary is known to its cleanup
_HELD = {getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name)}


def umask():
    """The process's file-creation mask (read without changing it where the OS allows)."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def _signals_held():
    """Hold Ctrl-C and SIGTERM back (main thread) until the block ends.

    A signal between ``mkstemp``/``mkdtemp`` creating a temporary and the ``try`` that
    removes it would leave the temporary behind. During the block the Python handlers of
    SIGINT and SIGTERM only record the signal; afterwards the previous handlers are put
    back and a recorded signal is handed to its handler (``KeyboardInterrupt`` for
    Ctrl-C), inside that ``try``. Handlers, unlike a thread's signal mask, run in the main
    thread whichever thread the signal reached.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {}
    for sig in _HELD:
        handler = signal.getsignal(sig)
        if handler is None:  # installed outside Python: left alone
            continue
        previous[sig] = signal.signal(sig, lambda signum, frame: caught.append(signum))
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(caught):
            handler = previous[sig]
            if callable(handler):
                handler(sig, None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), sig)  # the default action, now that it is back


def remove_temporaries(path):
    """Remove the temporary siblings of ``path`` (files and folders) a dead writer left.

    Call it only while no other writer of ``path`` can be running (e.g. under a lock).
    Returns the removed paths.
    """
    path = Path(path)
    removed = []
    if not path.parent.is_dir():
        return removed
    for entry in path.parent.iterdir():
        if entry.name.startswith(f".{path.name}.") and ".part" in entry.name:
            if entry.is_dir() and not entry.is_symlink():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    entry.unlink()
            removed.append(entry)
    return removed


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
    tmp = None
    try:
        with _signals_held():
            fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{path.suffix}",
                                       dir=path.parent)
            os.close(fd)
        os.chmod(tmp, 0o666 & ~umask())
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
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

    Whatever the caller writes into the folder appears at ``path`` all at once: a folder
    already there is first renamed aside (``.<name>.<random>.old.part``), the new one
    renamed onto ``path``, then the old one removed, so ``path`` holds either the old or
    the new folder, never a mix. On any exception the temporary folder is removed and
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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = old = None
    try:
        with _signals_held():
            tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part",
                                        dir=path.parent))
        os.chmod(tmp, 0o777 & ~umask())
        yield tmp
        with _signals_held():  # the swap: old aside, new in place
            if path.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old.part",
                                            dir=path.parent))
                os.replace(path, old / "previous")
            os.replace(tmp, path)
    except BaseException:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        if old is not None and (old / "previous").exists() and not path.exists():
            os.replace(old / "previous", path)  # put the previous folder back
        raise
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
