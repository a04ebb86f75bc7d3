"""What a run warned about is kept: in ``Result.warnings``, ``summary.json`` and the report."""

import json
import logging
import warnings

import pytest

from pvcmf.run_warnings import capture_warnings


def test_log_records_and_python_warnings_are_collected_once_each_and_still_shown(caplog):
    found = []
    with pytest.warns(UserWarning, match="surfaces weakened"), caplog.at_level(logging.WARNING):
        with capture_warnings(found):
            logging.getLogger("pvcmf.filters.x").warning("face cut at y = %d mm", 80)
            logging.getLogger("pvcmf.filters.x").warning("face cut at y = %d mm", 80)
            logging.getLogger("pvcmf.filters.x").info("not a warning")
            logging.getLogger("other").warning("not pvcmf's")
            warnings.warn("surfaces weakened", UserWarning)
    assert found == ["face cut at y = 80 mm", "UserWarning: surfaces weakened"]
    assert "face cut at y = 80 mm" in caplog.text  # the application's handlers saw it too


def test_capture_ends_with_the_run():
    found, target = [], logging.getLogger("pvcmf")
    before, shown = list(target.handlers), warnings.showwarning
    with pytest.raises(RuntimeError), capture_warnings(found):
        raise RuntimeError("a step failed")
    assert target.handlers == before and warnings.showwarning is shown
    logging.getLogger("pvcmf.late").warning("after the run")
    assert found == []


def test_runs_in_other_threads_keep_their_own_warnings():
    """Two runs at once (a sweep on threads): each keeps what its own thread warned about,
    and the hook goes when the last one ends."""
    import threading

    shown = warnings.showwarning
    started, finish, sinks = threading.Barrier(2), threading.Barrier(2), {}

    def run(name):
        with capture_warnings(sinks.setdefault(name, [])):
            started.wait()
            logging.getLogger("pvcmf.run").warning("log of %s", name)
            warnings.warn(f"warning of {name}", UserWarning)
            finish.wait()

    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        threads = [threading.Thread(target=run, args=(n,)) for n in ("a", "b")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert sinks["a"] == ["log of a", "UserWarning: warning of a"]
    assert sinks["b"] == ["log of b", "UserWarning: warning of b"]
    assert sorted(str(w.message) for w in seen) == ["warning of a", "warning of b"]  # shown
    assert warnings.showwarning is shown


def test_sink_must_be_a_list():
    with pytest.raises(TypeError, match="sink must be a list, got tuple"):
        with capture_warnings(()):
            pass


def test_the_command_line_recaps_the_warnings_at_the_end(capsys):
    from pvcmf import cli
    from pvcmf.pipeline import Result
    from pvcmf.plan import Osteotomy, Plan

    res = Result(plan=Plan((Osteotomy("maxilla"),)), warnings=["the head is cut flat"])
    cli._report(res)
    out = capsys.readouterr().out
    assert "1 warning(s), also in summary.json and report.html:\n  the head is cut flat" in out
    cli._report(Result(plan=res.plan))
    assert "warning" not in capsys.readouterr().out
