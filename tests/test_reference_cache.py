"""The on-disk cache of the virtual post-operative truth (``pvcmf.reference.cached``):
concurrent callers compute one truth once, stale locks are broken, failures leave no entry.
Runs without NGSolve (the computation here is a stand-in)."""

from __future__ import annotations

import multiprocessing
import os
import threading
import time

import numpy as np
import pytest
import pyvista as pv

from pvcmf import arrays
from pvcmf.reference import cached, grid_hash, solver_code_hash


def slow_sphere(counter, delay=1.0):
    """A stand-in truth that takes ``delay`` seconds and records each computation."""
    with open(counter, "a") as f:
        f.write(f"{os.getpid()}\n")
    time.sleep(delay)
    return pv.Sphere(theta_resolution=12, phi_resolution=12)


def _worker(path, counter, queue):
    out = cached(path, lambda: slow_sphere(counter), poll=0.05)
    queue.put(out.n_points)


def computations(counter):
    return len(counter.read_text().split()) if counter.exists() else 0


def test_two_processes_compute_once(tmp_path):
    path, counter = tmp_path / "truth.vtp", tmp_path / "count.txt"
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(path, counter, queue)) for _ in range(2)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=60)
    assert [p.exitcode for p in procs] == [0, 0]
    sizes = [queue.get(timeout=5) for _ in procs]
    assert computations(counter) == 1  # the second process waited and read the cache
    assert sizes == [pv.Sphere(theta_resolution=12, phi_resolution=12).n_points] * 2
    assert not (tmp_path / "truth.vtp.lock").exists()
    assert sorted(q.name for q in tmp_path.iterdir()) == ["count.txt", "truth.vtp"]


def test_threads_compute_once(tmp_path):
    path, counter = tmp_path / "truth.vtp", tmp_path / "count.txt"
    results = []

    def run():
        results.append(cached(path, lambda: slow_sphere(counter, 0.5), poll=0.05))

    threads = [threading.Thread(target=run) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=30)
    assert computations(counter) == 1
    assert len(results) == 4
    for r in results[1:]:
        np.testing.assert_allclose(r.points, results[0].points, atol=1e-6)


def test_stale_lock_of_a_dead_process_is_broken(tmp_path):
    path, counter = tmp_path / "truth.vtp", tmp_path / "count.txt"
    ctx = multiprocessing.get_context("fork")
    dead = ctx.Process(target=lambda: None)
    dead.start()
    dead.join()
    lock = tmp_path / "truth.vtp.lock"
    import socket

    lock.write_text(f"{dead.pid} {socket.gethostname()} {time.time():.0f}\n")
    start = time.perf_counter()
    cached(path, lambda: slow_sphere(counter, 0.0), poll=0.05)
    assert time.perf_counter() - start < 5
    assert computations(counter) == 1 and path.exists() and not lock.exists()


def test_old_lock_is_broken_and_a_live_one_is_waited_for(tmp_path):
    path, counter = tmp_path / "truth.vtp", tmp_path / "count.txt"
    lock = tmp_path / "truth.vtp.lock"
    lock.write_text("1 another-host 0\n")  # another host's lock: only its age tells
    old = time.time() - 100
    os.utime(lock, (old, old))
    cached(path, lambda: slow_sphere(counter, 0.0), stale_after=50, poll=0.05)
    assert computations(counter) == 1 and not lock.exists()

    # a fresh lock of a live process: the caller waits until the holder writes the entry
    path.unlink()
    lock.write_text(f"{os.getpid()} another-host {time.time():.0f}\n")

    def holder():
        time.sleep(0.5)
        pv.Sphere().save(tmp_path / "tmp.vtp")
        os.replace(tmp_path / "tmp.vtp", path)  # as cached() writes: atomically
        lock.unlink()

    t = threading.Thread(target=holder)
    t.start()
    out = cached(path, lambda: slow_sphere(counter, 0.0), poll=0.05)
    t.join()
    assert computations(counter) == 1  # read, not recomputed
    assert out.n_points == pv.Sphere().n_points


def test_failed_computation_leaves_no_entry_and_no_lock(tmp_path):
    path = tmp_path / "truth.vtp"

    def fail():
        raise RuntimeError("Newton did not converge")

    with pytest.raises(RuntimeError, match="Newton"):
        cached(path, fail)
    assert list(tmp_path.iterdir()) == []
    calls = []
    cached(path, lambda: calls.append(1) or pv.Sphere(), cache=False)
    cached(path, lambda: calls.append(1) or pv.Sphere(), cache=False)
    assert calls == [1, 1] and list(tmp_path.iterdir()) == []


def test_grid_hash_follows_the_solver_input():
    """The truth's cache key is the solver's input grid (whatever code made it), its
    options and the solver's code: equal grids share it, any change of an array, a point
    or an option changes it."""
    g = pv.ImageData(dimensions=(4, 4, 4)).cast_to_unstructured_grid().triangulate()
    g.point_data[arrays.BC_DISPLACEMENT] = np.zeros((g.n_points, 3))
    g.cell_data[arrays.NU] = np.full(g.n_cells, 0.46)
    key = grid_hash(g, "order=2")
    assert len(key) == 32 and grid_hash(g.copy(), "order=2") == key
    moved = g.copy()
    moved.point_data[arrays.BC_DISPLACEMENT][3, 1] = 1e-12
    softer = g.copy()
    softer.cell_data[arrays.NU][0] = 0.45
    shifted = g.copy()
    shifted.points = shifted.points + (0.0, 0.0, 1e-5)  # 10 nm: above the quantum
    extra = g.copy()
    extra.cell_data["x"] = np.zeros(g.n_cells)
    keys = {key, grid_hash(g, "order=1"), grid_hash(moved, "order=2"),
            grid_hash(softer, "order=2"), grid_hash(shifted, "order=2"),
            grid_hash(extra, "order=2")}
    assert len(keys) == 6
    # round-off of the mesher between processes (1e-14 mm) keeps the key
    jitter = g.copy()
    jitter.points = jitter.points + 1e-14 * (np.arange(g.n_points) % 3 == 0)[:, None]
    assert grid_hash(jitter, "order=2") == key
    assert len(solver_code_hash()) == 16
