"""Open a report in a headless Chromium: its DOM after scripts ran, console errors, a PNG.

:func:`check_page` runs the browser once from the command line (``--dump-dom`` and
``--screenshot`` together, ``--virtual-time-budget`` so that the page's scripts finish,
``--enable-logging=stderr`` to collect console messages) with WebGL on the SwiftShader
software rasteriser (``--use-angle=swiftshader --enable-unsafe-swiftshader``), so that it
works on machines without a GPU or a display. Chromium logs every console message at one
level, so errors are read from the page itself: the report records ``console.error``
calls, uncaught exceptions and rejected promises in ``<pre id="pvcmf-errors">`` (see
:data:`pvcmf.report.html.ERROR_HOOK_JS`); uncaught errors of any page also show in the
log as ``Uncaught ...``. Delegates to :mod:`subprocess`; the
browser is Debian's ``chromium`` (or ``PVCMF_CHROMIUM``).
"""

from __future__ import annotations

import html
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
#: console lines of Chromium's log: ``[pid:tid:time:INFO:CONSOLE:line] "message", source: url``
_CONSOLE = re.compile(r"^\[[^\]]*:(?P<level>[A-Z]+):CONSOLE[^\]]*\]\s*(?P<text>.*)$")
_ERRORS = re.compile(r'<pre id="pvcmf-errors"[^>]*>(.*?)</pre>', re.S)


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


def _console(stderr, dom):
    lines = [m.group("text") for m in map(_CONSOLE.match, map(str.strip, stderr.splitlines()))
             if m]
    errors = [t for t in lines if t.lstrip('"').startswith("Uncaught")]
    m = _ERRORS.search(dom)
    if m:
        errors += [html.unescape(e) for e in m.group(1).splitlines() if e.strip()]
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
    shot = None if screenshot is None else Path(screenshot).resolve()
    extra = [] if shot is None else [f"--screenshot={shot}"]
    proc = _run([*base, *extra, "--dump-dom", url], timeout)
    console, errors = _console(proc.stderr, proc.stdout)
    if shot is not None and not shot.exists():
        raise RuntimeError(f"chromium wrote no screenshot: {proc.stderr[-2000:]}")
    return PageCheck(dom=proc.stdout, console=console, errors=errors, screenshot=shot,
                     seconds=time.perf_counter() - start)
