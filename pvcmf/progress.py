"""The one progress display of pvcmf: a tqdm bar when asked for and installed, log lines always.

Every long step takes ``progress_bar=False``. With ``progress_bar=True`` it shows a tqdm bar
(``tqdm`` is in the ``sweep`` and ``test`` extras); without tqdm it logs each step at INFO
instead. With ``progress_bar=False`` the steps are logged at DEBUG only.

>>> from pvcmf.progress import Progress
>>> with Progress(total=2, desc="demo", enabled=False) as bar:
...     bar.step("first")
...     bar.step("second")
>>> bar.done
2
"""

from __future__ import annotations

import logging

log = logging.getLogger("pvcmf")

__all__ = ["Progress"]


class Progress:
    """A progress display for ``total`` steps.

    Parameters
    ----------
    total : int or None
        Number of steps, when known.
    desc : str
        What is being done; starts every log line and labels the bar.
    enabled : bool
        The caller's ``progress_bar``: show a tqdm bar (or log at INFO when tqdm is missing).
        When False the steps are logged at DEBUG.
    unit : str
        The bar's unit.
    logger : logging.Logger, optional
        Where the step lines go (default: the ``pvcmf`` logger).
    """

    def __init__(self, total=None, desc="pvcmf", *, enabled=False, unit="step", logger=None):
        self.total = total
        self.desc = str(desc)
        self.enabled = bool(enabled)
        self.done = 0
        self._log = logger or log
        self._bar = None
        if self.enabled:
            try:
                from tqdm.auto import tqdm
            except ImportError:
                self._log.info("%s: progress_bar=True needs tqdm (pip install tqdm); "
                               "logging the steps instead", self.desc)
            else:
                self._bar = tqdm(total=total, desc=self.desc, unit=unit)

    def step(self, message=None, n=1):
        """Count ``n`` steps done and log ``message`` (if given)."""
        self.done += n
        if message is not None:
            level = logging.INFO if (self.enabled and self._bar is None) else logging.DEBUG
            of = f"/{self.total}" if self.total is not None else ""
            self._log.log(level, "%s [%d%s]: %s", self.desc, self.done, of, message)
        if self._bar is not None:
            if message is not None:
                self._bar.set_postfix_str(str(message), refresh=False)
            self._bar.update(n)

    def close(self):
        """Close the bar (idempotent)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
