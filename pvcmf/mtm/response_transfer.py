"""The skin transfer of the plan response, built on both cores beside the factorisation.

The transfer's rows before its smoothing steps are built in ranges of skin points
(:mod:`pvcmf.filters.transfer_parts`: row ``i`` depends on point ``i`` alone, so the
ranges stacked equal :class:`pvcmf.filters.surface_mapping.Transfer`'s rows bit for bit).
A partner starts on the ranges from the front while the calling thread runs the
boundary conditions, the factorisation and the solves; the calling thread then takes the
ranges left from the back, so both cores finish together (ranges handed out one at a
time through counters in shared memory). The calling thread joins the ranges and makes
the smoothing steps (their neighbour search on every core) while a second thread
multiplies the joined rows by the nodal response (``right``); the plan response folds
that product in (:class:`pvcmf.mtm.response_operator.SkinOperator`: the smoothing
steps on its dense rows, on every core, the partner being done).

The partner is a second thread by default (:data:`BUILD_IN`): its larger numpy and
scipy operations release Python's global interpreter lock, and sharing the process's
memory spares the copy of its rows (tens of megabytes for a 100k-point skin) that a
child process pickles to its parent; on two cores it builds the operator in less time
than a forked child (``benchmarks/plan_response.py`` times both in one run). On Linux
the partner can instead be a forked child process (``"process"``, or ``"auto"``: a
child where the calling process runs a single Python thread and the cores are not
contended, :func:`cpu_pressure`), which shares only the range counters with the parent
after the fork: it first writes its mesh index
(:class:`~pvcmf.filters.transfer_locate.MeshIndex`, pickled; the parent reads it in
milliseconds instead of making its own, and the child makes it while the parent runs
the boundary conditions), then each range's rows to an anonymous temporary file
(pickle) as soon as it has built it, which the parent reads once the child has exited;
where the fork fails, a second thread. If the child dies, the caller builds the ranges
it had taken and not written. Either way the result is the same transfer.

Delegates to :func:`os.fork`, :mod:`mmap`, :mod:`multiprocessing` (a lock), :mod:`pickle`,
:mod:`tempfile`, :mod:`concurrent.futures` and :mod:`pvcmf.filters.transfer_parts`.
"""

from __future__ import annotations

import logging
import mmap
import multiprocessing
import os
import pickle
import signal
import sys
import tempfile
import threading
import time

import numpy as np
import pyvista as pv

from ..filters.transfer_locate import tetra
from ..filters.transfer_parts import CHUNK, join_rows, prepared_index, ranges, transfer_rows

log = logging.getLogger(__name__)

__all__ = ["transfer_in_background"]

#: where the partner builds its ranges of the transfer: ``"thread"`` (a second thread),
#: ``"process"`` (a forked process where possible) or ``"auto"`` (a forked process where
#: possible and the cores are not contended, see :func:`cpu_pressure`)
BUILD_IN = "thread"
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


class _Claims:
    """Ranges of skin points shared by two builders: the partner takes them from the front,
    the caller from the back, one at a time, until they meet (counters in shared memory,
    so a forked child and its parent see the same ones)."""

    def __init__(self, n, lock):
        self._buf = mmap.mmap(-1, 24)  # anonymous and shared: survives the fork
        self._c = np.frombuffer(self._buf, dtype=np.int64)
        self._c[:] = (0, n - 1, 0)  # front, back, the partner's mesh index is written
        self._lock = lock

    @property
    def index_written(self):
        return bool(self._c[2])

    def mark_index_written(self):
        self._c[2] = 1

    def front(self):
        with self._lock:
            i = int(self._c[0])
            if i > self._c[1]:
                return None
            self._c[0] = i + 1
            return i

    def back(self):
        with self._lock:
            j = int(self._c[1])
            if j < self._c[0]:
                return None
            self._c[1] = j - 1
            return j

    def stop(self):
        """No range is handed out any more (the partner ends after its current one)."""
        with self._lock:
            self._c[0] = self._c[1] + 1


class _Builder:
    """The transfer's rows of ranges of the skin points (:func:`transfer_rows`) against
    one :class:`MeshIndex`, made on first use."""

    def __init__(self, grid, x):
        self.grid, self.x = grid, x
        self.ranges = ranges(len(x), CHUNK)
        self._index = None
        self._index_lock = threading.Lock()
        self.fetch = None  # returns the partner's index where it has one to give

    def index(self):
        with self._index_lock:
            if self._index is None and self.fetch is not None:
                self._index = self.fetch()
            if self._index is None:
                self._index = prepared_index(self.grid)
            return self._index

    def run(self, claim, clock=time.thread_time, keep=None):
        """``({range: Rows}, seconds, CPU seconds)`` of the ranges ``claim()`` hands out
        (``keep(i, rows)``: called with each range as it is built, instead of returning
        it)."""
        t, c = time.perf_counter(), clock()
        done = {}
        while (i := claim()) is not None:
            a, b = self.ranges[i]
            rows = transfer_rows(self.index(), self.x[a:b])
            if keep is None:
                done[i] = rows
            else:
                keep(i, rows)
        return done, time.perf_counter() - t, clock() - c


class _Thread:
    """The partner on a second thread (a future's ``result``)."""

    where = "second thread"

    def __init__(self, builder, claims):
        from concurrent.futures import ThreadPoolExecutor

        self.builder = builder
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="pvcmf-transfer")
        self._future = self._pool.submit(builder.run, claims.front)

    def result(self):
        try:
            return self._future.result()
        finally:  # the thread has ended when this returns (a later build may fork)
            self._pool.shutdown(wait=True)

    def cancel(self):
        self._future.cancel()
        self._pool.shutdown(wait=False)

    def close(self):
        pass


class _Process:
    """The partner in a forked child process, which writes its mesh index (for the parent's
    ranges) to an anonymous temporary file, then each range's rows to another as soon as
    it has built it (so that only the last one is left to write once the ranges are
    taken), then its timings, and exits (a pipe would make the child wait for the parent
    to read); :meth:`result` waits for it and reads them, :meth:`cancel` kills it (the
    parent failed before reading)."""

    where = "second process"

    def __init__(self, builder, claims):
        self._file, self._index_file = tempfile.TemporaryFile(), tempfile.TemporaryFile()
        self._claims = claims
        try:
            pid = os.fork()
        except OSError:
            self._file.close()
            self._index_file.close()
            raise
        if pid == 0:  # the child: build, write, exit without returning to the caller
            status = 1
            try:
                with os.fdopen(os.dup(self._file.fileno()), "wb") as fh:
                    def keep(i, rows):
                        pickle.dump(("range", i, rows), fh, protocol=pickle.HIGHEST_PROTOCOL)

                    try:
                        t, c = time.perf_counter(), time.process_time()
                        self._share_index(builder.index())
                        builder.run(claims.front, time.process_time, keep=keep)
                        answer = ("ok", time.perf_counter() - t, time.process_time() - c)
                    except BaseException as exc:  # noqa: BLE001 - sent to the parent
                        answer = ("error", exc)
                    pickle.dump(answer, fh, protocol=pickle.HIGHEST_PROTOCOL)
                status = 0
            finally:
                os._exit(status)
        self.pid = pid
        builder.fetch = self._fetch_index

    def _share_index(self, index):
        """Write the mesh index for the parent (it reads it instead of making its own)."""
        with os.fdopen(os.dup(self._index_file.fileno()), "wb") as fh:
            pickle.dump(index, fh, protocol=pickle.HIGHEST_PROTOCOL)
        self._claims.mark_index_written()

    def _fetch_index(self):
        """The child's mesh index, or None where it has not written it (yet)."""
        if not self._claims.index_written or self._index_file.closed:
            return None
        try:
            self._index_file.seek(0)
            return pickle.load(self._index_file)
        except (EOFError, pickle.UnpicklingError, OSError):  # pragma: no cover - torn
            return None

    def result(self):
        """``({range: Rows}, seconds, CPU seconds)`` of the child; where it died, the
        ranges it wrote (the caller builds the others it had taken)."""
        os.waitpid(self.pid, 0)
        done, last = {}, None
        try:
            self._file.seek(0)
            while last is None:
                record = pickle.load(self._file)
                if record[0] == "range":
                    done[record[1]] = record[2]
                else:
                    last = record
        except Exception as exc:  # noqa: BLE001 - the child died: its other ranges here
            log.warning("plan_response: the transfer process ended without an answer "
                        "(%s: %s); building the rest of its part of the transfer here",
                        type(exc).__name__, exc)
            last = ("ok", 0.0, 0.0)
        finally:
            self._file.close()
        if last[0] == "error":
            raise last[1]
        return done, last[1], last[2]

    def cancel(self):
        if self._file.closed:
            return
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:  # pragma: no cover - already gone
            pass
        os.waitpid(self.pid, 0)
        self.close()

    def close(self):
        self._file.close()
        self._index_file.close()


class _Pending:
    """The transfer being built by a partner (:class:`_Process` or :class:`_Thread`) and,
    once the caller asks for it, by the caller too."""

    def __init__(self, builder, claims, partner):
        self.builder, self.claims, self.partner = builder, claims, partner
        self.where = partner.where
        self.ranges = None

    def result(self, right=None):
        """``(transfer, timings)``: the joined transfer (:class:`Joined`) after the caller
        has built the ranges the partner had not taken, and the seconds of each part
        (:attr:`ranges` then says how many ranges each built); ``right``: a list of dense
        arrays whose products with the transfer before its steps are made beside the join
        (``transfer.product``, :func:`~pvcmf.filters.transfer_parts.join_rows`)."""
        builder = self.builder
        try:
            mine, wall, cpu = builder.run(self.claims.back)
        except BaseException:
            self.cancel()
            raise
        try:
            theirs, their_wall, their_cpu = self.partner.result()
            t, c = time.perf_counter(), time.thread_time()
            joined = self._join({**theirs, **mine}, right)
        finally:
            self.partner.close()
        where = self.where
        self.ranges = {where: len(theirs), "calling thread": len(builder.ranges) - len(theirs)}
        timings = {
            f"transfer rows ({where})": their_wall,
            f"transfer rows, CPU time ({where})": their_cpu,
            "transfer rows (calling thread)": wall,
            "transfer rows, CPU time (calling thread)": cpu,
            "transfer join": time.perf_counter() - t,
            "transfer join, CPU time (calling thread)": time.thread_time() - c,
        }
        return joined, timings

    def _join(self, rows, right=None):
        """The ranges joined (those a dead partner had taken built here first)."""
        builder = self.builder
        for i in range(len(builder.ranges)):
            if i not in rows:  # the partner died: its ranges here
                rows[i] = transfer_rows(builder.index(), builder.x[slice(*builder.ranges[i])])
        return join_rows(builder.index(), builder.x, [rows[i] for i in range(len(builder.ranges))],
                         threads=_cores(), right=right)

    def cancel(self):
        self.claims.stop()
        self.partner.cancel()


def _cores():
    """Cores this process may run on (at least 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def transfer_in_background(mesh, skin):
    """Start the skin transfer of ``skin`` on ``mesh`` beside the caller's work (a forked
    process or a second thread, see the module docs); it works on its own copies of the
    mesh's points and tetrahedra and of the skin points (no VTK object is shared). Returns
    an object whose ``result()`` builds the ranges left (on the calling thread) and
    returns ``(transfer, timings)`` (``transfer`` a
    :class:`~pvcmf.filters.transfer_parts.Joined`: ``W0``, ``steps``, ``inside``,
    ``modelled``), whose ``cancel()`` stops the partner and whose ``where`` names where
    it runs."""
    points, tets = tetra(mesh)
    grid = pv.UnstructuredGrid({pv.CellType.TETRA: tets.copy()}, points.copy())
    x = np.array(skin.points, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or not len(x):
        raise ValueError(f"skin points must have shape (n, 3) with n > 0, got {x.shape}")
    if BUILD_IN not in ("auto", "process", "thread"):
        raise ValueError(f"BUILD_IN must be 'auto', 'process' or 'thread', got {BUILD_IN!r}")
    builder = _Builder(grid, x)
    contended = BUILD_IN == "auto" and (cpu_pressure() or 0.0) >= CPU_PRESSURE_LIMIT
    if (BUILD_IN != "thread" and not contended and sys.platform.startswith("linux")
            and hasattr(os, "fork") and threading.active_count() == 1):
        claims = _Claims(len(builder.ranges), multiprocessing.get_context("fork").Lock())
        try:
            return _Pending(builder, claims, _Process(builder, claims))
        except OSError as exc:  # no fork (limits, memory): a thread instead
            log.info("plan_response: transfer on a thread (fork failed: %s)", exc)
    claims = _Claims(len(builder.ranges), threading.Lock())
    return _Pending(builder, claims, _Thread(builder, claims))
