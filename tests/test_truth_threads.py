"""The truth solver's default use of NGSolve's threads: on free cores, off on contended ones."""

from __future__ import annotations

import pytest

from pvcmf.truth import linear as solver


@pytest.mark.parametrize("pressure, free", [(0.0, True), (5.0, True), (20.0, False),
                                            (80.0, False)])
def test_threads_follow_the_cpu_pressure(monkeypatch, pressure, free):
    monkeypatch.setattr(solver, "cpu_pressure", lambda: pressure)
    # the load average counts this process too: it must not decide where pressure is known
    monkeypatch.setattr(solver.os, "getloadavg", lambda: (50.0, 50.0, 50.0))
    assert solver.cores_free() is free


@pytest.mark.parametrize("load, free", [(0.0, True), (1.0, True), (1.99, True), (2.0, False),
                                        (3.5, False)])
def test_without_pressure_information_the_load_counts_this_process(monkeypatch, load, free):
    """One busy process (this one) on two cores leaves a core for the second thread."""
    monkeypatch.setattr(solver, "cpu_pressure", lambda: None)
    monkeypatch.setattr(solver.os, "getloadavg", lambda: (load, load, load))
    monkeypatch.setattr(solver.os, "cpu_count", lambda: 2)
    assert solver.cores_free() is free

