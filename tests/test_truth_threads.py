"""The truth solver's default use of NGSolve's threads: on free cores, off where other
processes keep them busy (the load this process makes itself does not count)."""

from __future__ import annotations

import pytest

from pvcmf.truth import linear


@pytest.mark.parametrize("busy, free", [(0.0, True), (0.3, True), (0.5, False), (1.7, False)])
def test_threads_follow_the_other_processes_load(monkeypatch, busy, free):
    monkeypatch.setattr(linear, "others_busy", lambda: busy)
    # the load average counts this process too: it must not decide where the cores are read
    monkeypatch.setattr(linear.os, "getloadavg", lambda: (50.0, 50.0, 50.0))
    assert linear.cores_free() is free


@pytest.mark.parametrize("load, free", [(0.0, True), (1.0, True), (1.99, True), (2.0, False),
                                        (3.5, False)])
def test_without_cpu_accounting_the_load_counts_this_process(monkeypatch, load, free):
    """One busy process (this one) on two cores leaves a core for the second thread."""
    monkeypatch.setattr(linear, "others_busy", lambda: None)
    monkeypatch.setattr(linear.os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(linear.os, "cpu_count", lambda: 2)
    assert linear.cores_free() is free


def test_own_cpu_time_is_not_counted_as_others(monkeypatch):
    """Of the machine's busy time, this process's own (its threads) is taken off."""
    readings = iter([(100.0, 10.0), (101.0, 10.6)])  # (machine busy s, own s) 0.5 s apart
    monkeypatch.setattr(linear, "_snapshot", lambda: next(readings))
    monkeypatch.setattr(linear.time, "sleep", lambda s: None)
    assert linear.others_busy(0.5) == pytest.approx(0.8)  # 2 cores busy, 1.2 of them ours


def test_unreadable_cpu_accounting_gives_none(monkeypatch):
    def unreadable():
        raise OSError("no /proc/stat")

    monkeypatch.setattr(linear, "_snapshot", unreadable)
    assert linear.others_busy(0.01) is None


def test_the_machine_reading_is_consistent():
    """On Linux, a reading is two non-decreasing totals (machine, this process)."""
    try:
        a = linear._snapshot()
    except OSError:
        pytest.skip("no /proc/stat on this platform")
    sum(i * i for i in range(200_000))
    b = linear._snapshot()
    assert b[0] >= a[0] and b[1] > a[1]
