"""The one on-disk cache of pvcmf: keys, a cross-process lock, atomic entries.

Used by the virtual post-operative truths (:mod:`pvcmf.truth`) and the parameter sweeps
(:mod:`pvcmf.study`):

* :func:`code_hash` - the one code-hashing rule: the syntax trees (:func:`ast.dump`, no
  line numbers, docstrings dropped) of functions, classes, modules or source files, so
  editing what code computes changes a key and editing a docstring, a comment or the
  layout does not;
* :func:`make_key` - SHA-256 of JSON-serialised key parts;
* :func:`file_lock` - an exclusive lock file (``os.open`` with ``O_CREAT | O_EXCL``,
  atomic on local and NFSv3+ file systems) shared by processes, threads and Dask
  processes, broken when its holder died (same host) or when it is older than
  ``stale_after`` seconds;
* :func:`cached` - read an entry, or compute it once across processes and write it
  atomically (:mod:`pvcmf._atomic`: a file or a whole folder);
* :func:`load_entry`, :func:`store_entry` - the reading and the locked atomic writing of
  :func:`cached`, for results computed elsewhere (e.g. on Dask).

The cache root is ``PVCMF_CACHE_DIR``, else ``~/.cache/pvcmf`` (:func:`cache_root`).
"""

from __future__ import annotations

import ast
import contextlib
import hashlib
import inspect
import json
import logging
import os
import socket
import textwrap
import time
from pathlib import Path

from ._atomic import atomic_dir, atomic_path

log = logging.getLogger(__name__)

__all__ = ["cache_root", "cached", "code_hash", "file_lock", "load_entry", "make_key",
           "store_entry"]


def cache_root(sub=None, cache_dir=None):
    """The cache folder: ``cache_dir`` if given, else ``PVCMF_CACHE_DIR`` (default
    ``~/.cache/pvcmf``) with the sub-folder ``sub``.

    Examples
    --------
    >>> from pvcmf.cache import cache_root
    >>> cache_root("x", cache_dir="my_cache").as_posix()
    'my_cache'
    """
    if cache_dir is not None:
        return Path(cache_dir)
    root = Path(os.environ.get("PVCMF_CACHE_DIR", Path.home() / ".cache" / "pvcmf"))
    return root / sub if sub else root


def _strip_docstrings(tree):
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.FunctionDef, ast.ClassDef, ast.AsyncFunctionDef))
                and body and isinstance(body[0], ast.Expr)
                and isinstance(getattr(body[0], "value", None), ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree


def _sources(target):
    """(name, source text) pairs of a function, class, module, file or folder."""
    if isinstance(target, (str, os.PathLike)):
        path = Path(target)
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        return [(f.as_posix(), f.read_text(encoding="utf-8")) for f in files]
    name = f"{getattr(target, '__module__', '')}.{getattr(target, '__qualname__', '')}"
    if inspect.ismodule(target):
        name = target.__name__
    return [(name, textwrap.dedent(inspect.getsource(target)))]


def code_hash(*targets, root=None):
    """SHA-256 (16 hex digits) of code, without docstrings or comments.

    Parameters
    ----------
    *targets : function, class, module or path
        What to hash; a path is a source file or a folder (its ``*.py`` files, sorted).
    root : path, optional
        Folder the names of hashed files are taken relative to (so the key does not
        depend on where the package is installed).

    Raises
    ------
    OSError, TypeError
        The source of an object cannot be found (builtins, lambdas typed at a prompt).

    Examples
    --------
    >>> from pvcmf.cache import code_hash
    >>> def f(x):
    ...     "doc"
    ...     return x + 1
    >>> def g(x):
    ...     return x + 1  # a comment
    >>> len(code_hash(f)), code_hash(f) == code_hash(g)
    (16, False)
    """
    h = hashlib.sha256()
    for target in targets:
        for name, text in _sources(target):
            if isinstance(target, (str, os.PathLike)):  # files: by their relative path
                name = Path(name).relative_to(root).as_posix() if root else Path(name).name
            else:  # objects: by their own name
                name = name.rsplit(".", 1)[-1]
            tree = _strip_docstrings(ast.parse(text))
            h.update(name.encode())
            h.update(ast.dump(tree).encode())
    return h.hexdigest()[:16]


def make_key(*parts, length=64):
    """SHA-256 hex digest (``length`` digits) of JSON-serialised ``parts`` (sorted keys).

    Examples
    --------
    >>> from pvcmf.cache import make_key
    >>> make_key({"b": 1, "a": 2}) == make_key({"a": 2, "b": 1})
    True
    """
    payload = json.dumps(parts if len(parts) != 1 else parts[0], sort_keys=True, default=repr)
    return hashlib.sha256(payload.encode()).hexdigest()[:length]


def _lock_is_stale(lock, stale_after):
    """A lock is stale when it is older than ``stale_after`` seconds, or when it was
    written on this host by a process that no longer exists."""
    try:
        age = time.time() - lock.stat().st_mtime
        owner = lock.read_text().split()
    except (FileNotFoundError, OSError):
        return False  # released meanwhile (or unreadable for a moment): not stale
    if age > stale_after:
        return True
    if len(owner) >= 2 and owner[1] == socket.gethostname():
        try:
            os.kill(int(owner[0]), 0)
        except ProcessLookupError:
            return True
        except (PermissionError, ValueError):
            return False
    return False


@contextlib.contextmanager
def file_lock(lock, *, stale_after=7200.0, poll=0.5, ready=None):
    """Hold the exclusive lock file ``lock`` (waiting for it), or skip once ``ready()``.

    Yields True when the lock is held, False when ``ready()`` became true while waiting
    (someone else produced the result: nothing to do). The lock file records
    ``pid host time``; a stale lock (see :func:`cached`) is broken.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from pvcmf.cache import file_lock
    >>> lock = Path(tempfile.mkdtemp()) / "x.lock"
    >>> with file_lock(lock) as held:
    ...     held, lock.exists()
    (True, True)
    >>> lock.exists()
    False
    """
    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    waited = False
    while True:
        if ready is not None and ready():
            yield False
            return
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            if _lock_is_stale(lock, stale_after):
                log.warning("cache: breaking the stale lock %s", lock)
                with contextlib.suppress(FileNotFoundError):
                    lock.unlink()
                continue
            if not waited:
                log.info("cache: %s is held by another caller; waiting", lock)
            waited = True
            time.sleep(poll)
            continue
        break
    try:
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()} {socket.gethostname()} {time.time():.0f}\n")
        yield True
    finally:
        with contextlib.suppress(FileNotFoundError):
            lock.unlink()


def _read_dataset(path):
    import pyvista as pv

    return pv.read(path)


def _save_dataset(obj, path):
    obj.save(path)


def cached(path, compute, *, cache=True, read=None, write=None, folder=False,
           stale_after=7200.0, poll=0.5):
    """Read ``path`` if it exists, else compute it once across processes and write it.

    The first caller takes the lock file ``<path>.lock`` (:func:`file_lock`), computes,
    writes the result atomically (:func:`pvcmf._atomic.atomic_path`, or
    :func:`pvcmf._atomic.atomic_dir` for a ``folder`` entry) and releases the lock. Any
    other caller asking for the same ``path`` meanwhile (another process, thread or Dask
    process) waits for the lock to go and then reads the result instead of recomputing. A
    lock left by a crashed caller is broken when its process no longer exists (same host)
    or when it is older than ``stale_after`` seconds; if the holder failed without
    writing, the next waiter computes. An entry that cannot be read is recomputed.

    Parameters
    ----------
    path : path-like
        Cache entry: a file (default format: any that ``pyvista.read`` and
        ``DataObject.save`` know, e.g. ``.vtp``) or, with ``folder=True``, a folder.
    compute : callable
        ``compute() -> object``, called at most once per missing entry.
    cache : bool, default True
        False: just ``compute()``, no reading, writing or locking.
    read, write : callable, optional
        ``read(path) -> object`` and ``write(object, path)`` (default: pyvista's). With
        ``folder=True``, ``write`` fills the (temporary) folder it is given.
    folder : bool, default False
        The entry is a folder.
    stale_after : float, default 7200
        Seconds after which another process's lock is considered abandoned.
    poll : float, default 0.5
        Seconds between checks while waiting.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import pyvista as pv
    >>> from pvcmf.cache import cached
    >>> path = Path(tempfile.mkdtemp()) / "sphere.vtp"
    >>> cached(path, pv.Sphere).n_points == cached(path, lambda: None).n_points
    True
    """
    if not cache:
        return compute()
    read = read or _read_dataset
    write = write or _save_dataset
    path = Path(path)
    out = load_entry(path, read)
    if out is not None:
        log.info("cache: read %s", path)
        return out
    with file_lock(_lock_path(path), stale_after=stale_after, poll=poll,
                   ready=path.exists) as held:
        if not held or path.exists():  # written by another caller meanwhile
            out = load_entry(path, read)
            if out is not None:
                log.info("cache: read %s (computed by another caller)", path)
                return out
        out = compute()
        _write_entry(path, out, write, folder)
        return out


def _lock_path(path):
    return path.with_name(path.name + ".lock")


def _write_entry(path, obj, write, folder):
    with (atomic_dir if folder else atomic_path)(path) as tmp:
        write(obj, tmp)


def load_entry(path, read=None):
    """The cache entry at ``path`` read by ``read`` (default pyvista's), or None when it is
    missing or cannot be read (a corrupt entry is logged and never trusted).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from pvcmf.cache import load_entry
    >>> load_entry(Path(tempfile.mkdtemp()) / "missing.vtp") is None
    True
    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        return (read or _read_dataset)(path)
    except Exception as err:  # a corrupt entry is recomputed, never trusted
        log.warning("cache: ignoring unreadable entry %s (%s)", path, err)
        return None


def store_entry(path, obj, write=None, *, folder=False, stale_after=7200.0, poll=0.5):
    """Write ``obj`` to the cache entry ``path`` atomically, holding the entry's lock.

    The writing half of :func:`cached` for a result computed elsewhere (a Dask task): the
    lock file ``<path>.lock`` (:func:`file_lock`) keeps two writers of one entry apart, and
    :func:`pvcmf._atomic.atomic_path` (``atomic_dir`` for a ``folder``) makes the entry
    appear whole or not at all. Returns ``path``.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> from pvcmf.cache import load_entry, store_entry
    >>> path = Path(tempfile.mkdtemp()) / "a.txt"
    >>> _ = store_entry(path, "text", lambda obj, tmp: Path(tmp).write_text(obj))
    >>> load_entry(path, lambda p: Path(p).read_text())
    'text'
    """
    path = Path(path)
    with file_lock(_lock_path(path), stale_after=stale_after, poll=poll):
        _write_entry(path, obj, write or _save_dataset, folder)
    return path
