"""A small text progress bar on stderr for optimizations and exports.

It draws only when stderr is a terminal or ``DOE_PROGRESS=1``; set ``DOE_PROGRESS=0``
to silence it. Status messages go through :mod:`logging`, never print.
"""

from __future__ import annotations

import os
import sys
import time


class Progress:
    """Progress over ``total`` steps with an optional status text (e.g. the loss).

    Use as a context manager; call :meth:`update` once per step.
    """

    def __init__(self, total, desc="", stream=None, enabled=None):
        self.total = max(int(total), 1)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        env = os.environ.get("DOE_PROGRESS")
        if enabled is None:
            enabled = env == "1" if env is not None else self.stream.isatty()
        self.enabled = enabled
        self.count = 0
        self.start = time.perf_counter()
        self._last_draw = 0.0

    def __enter__(self):
        self._draw("")
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self._draw(self._status if hasattr(self, "_status") else "", force=True)
            self.stream.write("\n")
            self.stream.flush()
        return False

    def update(self, n=1, status=""):
        """Advance by ``n`` steps and show ``status`` beside the bar."""
        self.count = min(self.count + n, self.total)
        self._status = status
        self._draw(status)

    def _draw(self, status, force=False):
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self._last_draw < 0.1 and self.count < self.total:
            return
        self._last_draw = now
        frac = self.count / self.total
        width = 28
        bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
        elapsed = now - self.start
        self.stream.write(f"\r{self.desc} [{bar}] {self.count}/{self.total} "
                          f"{elapsed:5.1f}s {status}".rstrip() + "\x1b[K")
        self.stream.flush()
