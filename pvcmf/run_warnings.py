"""The warnings of one run, kept for its summary and its report.

:func:`capture_warnings` collects, while a run lasts, the message of every ``logging``
record at WARNING or above of the ``pvcmf`` loggers and of every Python warning
(:mod:`warnings`) shown in that time, in order and each once, without changing how either
is shown: the records still reach the handlers the application set up, and the Python
warnings still go to the ``warnings.showwarning`` in place under the filters in place.
:func:`pvcmf.pipeline.simulate` keeps them in ``Result.warnings``; ``summary.json``
(``"warnings"``) and ``report.html`` show them, so that a run read later from its files
says what it warned about (a face cut by the field of view, a muscle fit that fell back,
weakened mesh surfaces).

Delegates to :mod:`logging` (a handler on the ``pvcmf`` logger while the run lasts) and
:mod:`warnings` (``catch_warnings`` restores ``showwarning`` afterwards).
"""

from __future__ import annotations

import contextlib
import logging
import warnings

__all__ = ["capture_warnings"]


class _ListHandler(logging.Handler):
    """Appends each record's message to a list (once)."""

    def __init__(self, sink):
        super().__init__(logging.WARNING)
        self.sink = sink

    def emit(self, record):
        try:
            _add(self.sink, record.getMessage())
        except Exception:  # noqa: BLE001 - logging's own contract: report, never raise
            self.handleError(record)


def _add(sink, message):
    if message not in sink:
        sink.append(message)


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
    handler = _ListHandler(sink)
    target = logging.getLogger(logger)
    target.addHandler(handler)
    try:
        with warnings.catch_warnings():
            shown = warnings.showwarning

            def show(message, category, filename, lineno, file=None, line=None):
                _add(sink, f"{category.__name__}: {message}")
                shown(message, category, filename, lineno, file, line)

            warnings.showwarning = show
            yield sink
    finally:
        target.removeHandler(handler)
