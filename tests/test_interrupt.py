"""Interrupting ``pvcmf simulate`` leaves the output folder as it was or holding one run.

Each case runs ``python -m pvcmf.cli simulate`` on a coarse virtual patient in a
subprocess, waits for the log line of a step, sends SIGINT, SIGTERM or SIGKILL, and
checks the folder: it holds exactly the earlier run's files (unchanged bytes) or one
complete new run, never a mix, and no hidden sibling survives a rerun.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from pvcmf import datasets

ROOT = Path(__file__).resolve().parents[1]

PLAN = """name = "tiny mandible advancement"

[[osteotomy]]
segment = "mandible"
translation = [0.0, 0.0, 4.0]

[[osteotomy.cut]]
point = [0.0, 0.0, -62.0]
normal = [0.0, 0.0, -1.0]
"""

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_case(tmp_path_factory):
    """A 4 mm virtual CT and a plan with a cut plane, as files."""
    folder = tmp_path_factory.mktemp("tiny")
    case = datasets.phantom(patient=1, spacing=4.0)
    ct = folder / "ct.vti"
    case.ct.save(ct)
    plan = folder / "plan.toml"
    plan.write_text(PLAN)
    return ct, plan


@pytest.fixture(scope="module")
def earlier_run(tiny_case, tmp_path_factory):
    """A complete run of the tiny case, copied into each test's output folder."""
    out = tmp_path_factory.mktemp("earlier") / "out"
    _run(*tiny_case, out)
    return out


def _command(ct, plan, out):
    return [sys.executable, "-m", "pvcmf.cli", "simulate", "--ct", str(ct), "--plan", str(plan),
            "--out", str(out), "--no-muscles", "--no-figures", "--no-progress",
            "--n-tets", "2000", "-v"]


def _env():
    env = dict(os.environ, PYVISTA_OFF_SCREEN="true")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return env


def _run(ct, plan, out):
    proc = subprocess.run(_command(ct, plan, out), env=_env(), cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def _interrupt(ct, plan, out, sig, after_step):
    """Start a run, send ``sig`` once step ``after_step`` has logged; return its exit code."""
    proc = subprocess.Popen(_command(ct, plan, out), env=_env(), cwd=ROOT,
                            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
    sent = False
    for line in proc.stderr:
        if f"step {after_step!r} took" in line:
            proc.send_signal(sig)
            sent = True
            break
    proc.stderr.read()
    code = proc.wait(timeout=300)
    assert sent, f"the run ended before step {after_step!r}"
    return code


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(Path(folder).iterdir())}


def _siblings(out):
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith(f".{out.name}."))


def _assert_one_run(out, before):
    """``out`` holds exactly ``before`` (nothing new) or one complete run."""
    now = _snapshot(out)
    if now == before:
        return "unchanged"
    summary = json.loads(now["summary.json"])
    assert summary["complete"]
    # the CLI adds report.html to the swapped-in folder (same process, same run)
    extra = set(now) - {*summary["files"].values(), "summary.json"} - {"report.html"}
    assert not extra, f"files of another run: {extra}"
    assert set(summary["files"].values()) <= set(now), "files missing"
    assert not [n for n in now if n.startswith(".")], "hidden temporary file inside the run"
    return "new run"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL],
                         ids=["SIGINT", "SIGTERM", "SIGKILL"])
@pytest.mark.parametrize("after_step", ["segment", "skeleton"])
def test_interrupted_simulate_leaves_one_run(tiny_case, earlier_run, tmp_path, sig, after_step):
    ct, plan = tiny_case
    out = tmp_path / "out"
    shutil.copytree(earlier_run, out)
    before = _snapshot(out)
    code = _interrupt(ct, plan, out, sig, after_step)
    state = _assert_one_run(out, before)
    if sig == signal.SIGKILL:
        assert code == -signal.SIGKILL
    elif state == "unchanged":
        assert code == (130 if sig == signal.SIGINT else 143)
        assert _siblings(out) == [], "cleanup left hidden siblings"
    # a rerun succeeds, removes what a killed run left, and leaves one complete run
    _run(ct, plan, out)
    assert _assert_one_run(out, {}) == "new run"
    assert _siblings(out) == []


def test_killed_run_leftovers_are_removed_by_the_next_run(tiny_case, tmp_path):
    """Hidden ``.part`` siblings and a dead process's lock do not outlive the next run."""
    ct, plan = tiny_case
    out = tmp_path / "out"
    (tmp_path / ".out.abc123.part").mkdir()
    (tmp_path / ".out.abc123.part" / "predicted_skin.vtp").write_bytes(b"")
    (tmp_path / ".out.lock").write_text("999999999 " + os.uname().nodename + " 0\n")
    _run(ct, plan, out)
    assert _siblings(out) == []
    assert (out / "summary.json").is_file()


def test_concurrent_runs_leave_one_complete_run(tiny_case, tmp_path):
    ct, plan = tiny_case
    out = tmp_path / "out"
    procs = [subprocess.Popen(_command(ct, plan, out), env=_env(), cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
             for _ in range(2)]
    assert [p.wait(timeout=300) for p in procs] == [0, 0]
    assert _assert_one_run(out, {}) == "new run"
    assert _siblings(out) == []


def test_files_take_the_umask(tiny_case, tmp_path):
    ct, plan = tiny_case
    out = tmp_path / "out"
    old = os.umask(0o022)
    try:
        _run(ct, plan, out)
    finally:
        os.umask(old)
    assert (out.stat().st_mode & 0o777) == 0o755
    assert {p.stat().st_mode & 0o777 for p in out.iterdir()} == {0o644}


@pytest.mark.skipif(not hasattr(signal, "pthread_sigmask"), reason="POSIX signal masks only")
@pytest.mark.parametrize("maker", ["mkdtemp", "mkstemp"])
def test_ctrl_c_while_a_temporary_is_made_leaves_nothing(tmp_path, monkeypatch, maker):
    """A Ctrl-C arriving right after the temporary exists (before the code that removes
    it knows its name) is held back until it does, so nothing is left beside the target."""
    import tempfile

    from pvcmf._atomic import atomic_dir, atomic_path

    real = getattr(tempfile, maker)

    def made_then_interrupted(*args, **kwargs):
        made = real(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGINT)  # delivered at once unless held
        return made

    monkeypatch.setattr(tempfile, maker, made_then_interrupted)
    writer = atomic_dir if maker == "mkdtemp" else atomic_path
    # a process started in the background of a shell inherits SIGINT ignored: make Ctrl-C
    # raise KeyboardInterrupt here whatever the runner's shell did
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            with writer(tmp_path / "out.vtp"):
                pass
    finally:
        signal.signal(signal.SIGINT, previous)
    assert sorted(p.name for p in tmp_path.iterdir()) == []
