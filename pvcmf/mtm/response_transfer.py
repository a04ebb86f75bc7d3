"""The skin transfer of the plan response, built alongside the factorisation and solves.

:class:`pvcmf.filters.surface_mapping.Transfer` runs many small numpy operations that hold
Python's global interpreter lock; on a second thread they stall the factorisation and solves
of the calling thread (and those stall it). On Linux, when the calling process runs a single
Python thread and the cores are not contended (:func:`cpu_pressure`), the transfer is
therefore built in a forked child process, which shares nothing with the parent after the
fork and writes the transfer before its smoothing steps (``W0``), the steps as sparse
matrices, ``inside`` and ``modelled`` (:class:`Parts`) to an anonymous temporary file
(pickle) that the parent reads once the child has exited (the steps are applied to the
folded dense rows, :class:`pvcmf.mtm.response_operator.SkinOperator`); elsewhere, or when the fork fails, on a
second thread. Either way the result is the same :class:`Transfer` computation on the same
inputs.

Delegates to :func:`os.fork`, :mod:`pickle`, :mod:`tempfile`, :mod:`concurrent.futures` and
:class:`pvcmf.filters.surface_mapping.Transfer`.
"""

from __future__ import annotations

import logging
import os
import pickle
import signal
import sys
import tempfile
import threading
import time

import numpy as np
import pyvista as pv

from ..filters.surface_mapping import Transfer
from ..filters.transfer_locate import tetra

log = logging.getLogger(__name__)

__all__ = ["transfer_in_background"]

#: where the transfer is built: ``"auto"`` (a forked process where possible and the cores
#: are not contended, see :func:`cpu_pressure`), ``"process"`` (where possible) or
#: ``"thread"``
BUILD_IN = "auto"
#: ``"auto"`` takes a thread when runnable tasks waited for a core this share (percent) of
#: the last ten seconds or more: the child then gains no core of its own and only adds
#: the fork's copy-on-write work
CPU_PRESSURE_LIMIT = 20.0


def cpu_pressure():
    """Share (percent) of the last ten seconds in which some runnable task waited for a
    core (Linux pressure stall information, ``/proc/pressure/cpu``), or None where the
    kernel does not provide it.

    Examples
    --------
    >>> p = cpu_pressure()
    >>> p is None or 0.0 <= p <= 100.0
    True
    """
    try:
        with open("/proc/pressure/cpu", encoding="ascii") as fh:
            first = fh.readline().split()
        return float(dict(f.split("=") for f in first[1:])["avg10"])
    except (OSError, ValueError, KeyError, IndexError):
        return None


class Parts:
    """What the plan response needs of a :class:`Transfer`: ``W0`` (the transfer before
    its smoothing steps), ``steps`` (:class:`~pvcmf.filters.transfer_smoothing.Steps` or
    None), ``inside`` and ``modelled``; ``W`` (the smoothed transfer) is made on first use,
    as :attr:`Transfer.W`."""

    def __init__(self, transfer):
        self.W0, self.steps = transfer.W0, transfer.steps
        self.inside, self.modelled = transfer.inside, transfer.modelled
        self._W = None

    @property
    def W(self):
        if self._W is None:
            self._W = self.W0 if self.steps is None else self.steps.apply(self.W0)
        return self._W


def _build(grid, x, clock=time.thread_time):
    """``(transfer parts, seconds, CPU seconds)`` of :class:`Transfer` on ``grid``, ``x``
    (:class:`Parts`: the smoothing steps are not applied to the sparse transfer)."""
    t, c = time.perf_counter(), clock()
    parts = Parts(Transfer(grid, x))
    return parts, time.perf_counter() - t, clock() - c


class _Thread:
    """The transfer built on a second thread (a future's ``result``)."""

    where = "second thread"

    def __init__(self, grid, x):
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pvcmf-transfer")
        self._future = pool.submit(_build, grid, x)
        pool.shutdown(wait=False)

    def result(self):
        return self._future.result()

    def cancel(self):
        self._future.cancel()


class _Process:
    """The transfer built in a forked child process, which writes its answer to an
    anonymous temporary file and exits (a pipe would make the child wait for the parent to
    read); :meth:`result` waits for it and reads the answer, :meth:`cancel` kills it (the
    parent failed before reading)."""

    where = "second process"

    def __init__(self, grid, x):
        self._file = tempfile.TemporaryFile()
        self._inputs = (grid, x)
        try:
            pid = os.fork()
        except OSError:
            self._file.close()
            raise
        if pid == 0:  # the child: build, write, exit without returning to the caller
            status = 1
            try:
                try:
                    answer = ("ok", _build(grid, x, time.process_time))
                except BaseException as exc:  # noqa: BLE001 - sent to the parent
                    answer = ("error", exc)
                with os.fdopen(os.dup(self._file.fileno()), "wb") as fh:
                    pickle.dump(answer, fh, protocol=pickle.HIGHEST_PROTOCOL)
                status = 0
            finally:
                os._exit(status)
        self.pid = pid

    def result(self):
        os.waitpid(self.pid, 0)
        try:
            self._file.seek(0)
            kind, value = pickle.load(self._file)
        except (EOFError, pickle.UnpicklingError) as exc:  # the child died: build here
            log.warning("plan_response: the transfer process ended without an answer "
                        "(%s); building the transfer here", exc)
            kind, value = "ok", _build(*self._inputs)
        finally:
            self._file.close()
        if kind == "error":
            raise value
        return value

    def cancel(self):
        if self._file.closed:
            return
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:  # pragma: no cover - already gone
            pass
        os.waitpid(self.pid, 0)
        self._file.close()


def transfer_in_background(mesh, skin):
    """Start :class:`Transfer` of ``skin`` on ``mesh`` beside the caller's work (a forked
    process or a second thread, see the module docs); it works on its own copies of the
    mesh's points and tetrahedra and of the skin points (no VTK object is shared). Returns
    an object whose ``result()`` is ``(transfer, seconds, CPU seconds)`` (``transfer`` a
    :class:`Parts`), whose ``cancel()`` stops it and whose
    ``where`` names where it runs."""
    points, tets = tetra(mesh)
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets.copy()}, points.copy())
    x = np.array(skin.points, dtype=float)
    if BUILD_IN not in ("auto", "process", "thread"):
        raise ValueError(f"BUILD_IN must be 'auto', 'process' or 'thread', got {BUILD_IN!r}")
    contended = BUILD_IN == "auto" and (cpu_pressure() or 0.0) >= CPU_PRESSURE_LIMIT
    if (BUILD_IN != "thread" and not contended and sys.platform.startswith("linux")
            and hasattr(os, "fork") and threading.active_count() == 1):
        try:
            return _Process(grid, x)
        except OSError as exc:  # no fork (limits, memory): a thread instead
            log.info("plan_response: transfer on a thread (fork failed: %s)", exc)
    return _Thread(grid, x)
