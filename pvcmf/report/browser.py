"""Open a report in a headless Chromium: its DOM after scripts ran, console errors, a PNG.

:func:`check_page` runs the browser twice from the command line (``--dump-dom`` and
``--screenshot``, each with ``--virtual-time-budget`` so that the page's scripts finish,
``--enable-logging=stderr`` to collect console messages) with WebGL on the SwiftShader
software rasteriser (``--use-angle=swiftshader --enable-unsafe-swiftshader``), so that it
works on machines without a GPU or a display. Delegates to :mod:`subprocess`; the
browser is Debian's ``chromium`` (or ``PVCMF_CHROMIUM``).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["PageCheck", "check_page", "find_chromium"]

_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--hide-scrollbars",
          "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--mute-audio",
          "--no-first-run", "--no-default-browser-check", "--disable-extensions",
          "--allow-file-access-from-files", "--enable-logging=stderr", "--v=0")
#: console lines of Chromium's log: ``CONSOLE(line)] "message", source: url``, or the
#: newer ``:CONSOLE:...`` form; the level is in the ``INFO/WARNING/ERROR`` tag before it
_CONSOLE = re.compile(r"^\[[^\]]*:(?P<level>[A-Z]+):CONSOLE[^\]]*\]\s*(?P<text>.*)$")


def find_chromium():
    """Path of a Chromium/Chrome executable (``PVCMF_CHROMIUM`` first), or ``None``."""
    env = os.environ.get("PVCMF_CHROMIUM")
    if env:
        return env if Path(env).exists() or shutil.which(env) else None
    for name in _NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


@dataclass
class PageCheck:
    """What :func:`check_page` saw."""

    dom: str
    console: list = field(default_factory=list)
    errors: list = field(default_factory=list)
    screenshot: Path | None = None
    seconds: float = 0.0


def _run(cmd, timeout):
    with tempfile.TemporaryDirectory(prefix="pvcmf-chromium-") as profile:
        proc = subprocess.run([*cmd[:1], f"--user-data-dir={profile}", *cmd[1:]],
                              capture_output=True, text=True, timeout=timeout, check=False)
    return proc


def _console(stderr):
    lines, errors = [], []
    for line in stderr.splitlines():
        m = _CONSOLE.match(line.strip())
        if m:
            lines.append(m.group("text"))
            if m.group("level") in ("ERROR", "FATAL"):
                errors.append(m.group("text"))
    return lines, errors


def check_page(path, screenshot=None, *, size=(1280, 1800), budget_ms=30_000, timeout=180,
               chromium=None):
    """Load ``path`` in headless Chromium; return its DOM, console and a screenshot.

    Parameters
    ----------
    path : str or pathlib.Path
        HTML file.
    screenshot : str or pathlib.Path, optional
        PNG to write (the top ``size`` pixels of the page); none if omitted.
    size : (int, int)
        Window size in pixels.
    budget_ms : int
        Virtual time the page gets to run its scripts before the DOM / picture is taken.
    timeout : float
        Seconds before each browser run is killed.
    chromium : str, optional
        Browser executable (default :func:`find_chromium`).

    Returns
    -------
    PageCheck
        ``dom`` (serialised after the scripts ran), ``console`` (all console messages),
        ``errors`` (console errors), ``screenshot`` and the wall ``seconds``.
    """
    exe = chromium or find_chromium()
    if exe is None:
        raise FileNotFoundError("no Chromium found (install Debian's 'chromium' or set "
                                "PVCMF_CHROMIUM)")
    url = Path(path).resolve().as_uri()
    base = [exe, *_FLAGS, f"--window-size={size[0]},{size[1]}",
            f"--virtual-time-budget={int(budget_ms)}"]
    start = time.perf_counter()
    proc = _run([*base, "--dump-dom", url], timeout)
    console, errors = _console(proc.stderr)
    shot = None
    if screenshot is not None:
        shot = Path(screenshot).resolve()
        run = _run([*base, f"--screenshot={shot}", url], timeout)
        more, more_errors = _console(run.stderr)
        console += more
        errors += more_errors
        if not shot.exists():
            raise RuntimeError(f"chromium wrote no screenshot: {run.stderr[-2000:]}")
    return PageCheck(dom=proc.stdout, console=console, errors=errors, screenshot=shot,
                     seconds=time.perf_counter() - start)
