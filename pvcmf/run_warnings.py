"""The warnings of one run, kept for its summary and its report.

:func:`capture_warnings` collects, while a run lasts, the message of every ``logging``
record at WARNING or above of the ``pvcmf`` loggers and of every Python warning
(:mod:`warnings`) shown in that time by the thread that runs it, in order and each once,
without changing how either is shown: the records still reach the handlers the
application set up, and the Python warnings still go to the ``warnings.showwarning`` in
place under the filters in place. Runs in other threads (a sweep on a thread scheduler)
keep their own warnings. :func:`pvcmf.pipeline.simulate` keeps them in
``Result.warnings``; ``summary.json`` (``"warnings"``) and ``report.html`` show them, so
that a run read later from its files says what it warned about (a face cut by the field
of view, a muscle fit that fell back, weakened mesh surfaces).

Delegates to :mod:`logging` (a handler on the ``pvcmf`` logger, filtered to the thread,
while the run lasts) and :mod:`warnings` (one ``showwarning`` hook shared by the runs in
progress, removed when the last one ends).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import warnings

__all__ = ["capture_warnings"]

_LOCK = threading.Lock()
#: thread id -> the sinks of the runs in progress in that thread (nested runs: all)
_SINKS = {}
#: ``warnings.showwarning`` before the hook, while any run is in progress
_SHOWN = []
_DEFAULT = warnings.showwarning


class _ListHandler(logging.Handler):
    """Appends the message of each record of one thread to a list (once)."""

    def __init__(self, sink, thread):
        super().__init__(logging.WARNING)
        self.sink, self.thread = sink, thread

    def emit(self, record):
        if record.thread != self.thread:
            return
        try:
            _add(self.sink, record.getMessage())
        except Exception:  # noqa: BLE001 - logging's own contract: report, never raise
            self.handleError(record)


def _add(sink, message):
    if message not in sink:
        sink.append(message)


def _show(message, category, filename, lineno, file=None, line=None):
    """The hook: note the warning for the runs of this thread, then show it as before."""
    for sink in _SINKS.get(threading.get_ident(), ()):
        _add(sink, f"{category.__name__}: {message}")
    shown = _SHOWN[0] if _SHOWN else _DEFAULT  # (the last run ended meanwhile)
    shown(message, category, filename, lineno, file, line)


def _start(sink, thread):
    with _LOCK:
        if not _SINKS:
            _SHOWN[:] = [warnings.showwarning]
            warnings.showwarning = _show
        _SINKS.setdefault(thread, []).append(sink)


def _stop(sink, thread):
    with _LOCK:
        mine = _SINKS[thread]
        del mine[max(i for i, s in enumerate(mine) if s is sink)]
        if not mine:
            del _SINKS[thread]
        if not _SINKS:
            if warnings.showwarning is _show:  # else someone replaced it after us: keep theirs
                warnings.showwarning = _SHOWN[0]
            _SHOWN.clear()
@contextlib.contextmanager
def capture_warnings(sink, logger="pvcmf"):
    """Collect the warnings of the ``logger`` loggers and Python's into ``sink``.

    Parameters
    ----------
    sink : list
        Receives each warning's message (str), in order, each once; Python warnings as
        ``"<Category>: <message>"``.
    logger : str, default "pvcmf"
        The logger whose records (and its children's) are collected.

    Yields
    ------
    list
        ``sink``.

    Examples
    --------
    >>> import logging, warnings
    >>> from pvcmf.run_warnings import capture_warnings
    >>> found = []
    >>> with capture_warnings(found), warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     logging.getLogger("pvcmf.example").warning("the face is cut at y = %d mm", 80)
    >>> found
    ['the face is cut at y = 80 mm']
    """
    if not isinstance(sink, list):
        raise TypeError(f"sink must be a list, got {type(sink).__name__}")
    thread = threading.get_ident()
    handler = _ListHandler(sink, thread)
    target = logging.getLogger(logger)
    target.addHandler(handler)
    _start(sink, thread)
    try:
        yield sink
    finally:
        _stop(sink, thread)
        target.removeHandler(handler)
