"""Progress bars on stderr for optimizations, exports and fits (tqdm underneath).

A bar draws only when stderr is a terminal or ``DOE_PROGRESS=1``; set ``DOE_PROGRESS=0`` to
silence it. Inside :func:`silenced` no bar draws: work whose caller shows a bar of its own (the
tiles of ``doe map``, each a whole diagnosis) would otherwise print one bar per step of every
tile under the caller's. Status messages go through :mod:`logging`, never print.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TextIO

from tqdm import tqdm

__all__ = ["Progress", "progress_enabled", "silenced"]

# Per thread and per task (a ContextVar): one tile silenced in a worker thread leaves the others'.
_SILENCED: ContextVar[bool] = ContextVar("doe_progress_silenced", default=False)


@contextmanager
def silenced() -> Iterator[None]:
    """Bars made inside this block draw nothing (unless a bar is asked for with ``enabled=True``)."""
    token = _SILENCED.set(True)
    try:
        yield
    finally:
        _SILENCED.reset(token)


def progress_enabled(stream: TextIO | None = None, enabled: bool | None = None) -> bool:
    """Whether to draw: ``enabled`` if given, else nothing inside :func:`silenced`, else
    ``DOE_PROGRESS`` (``1``/``0``), else a terminal."""
    if enabled is not None:
        return bool(enabled)
    if _SILENCED.get():
        return False
    env = os.environ.get("DOE_PROGRESS")
    if env is not None:
        return env == "1"
    stream = stream if stream is not None else sys.stderr
    return bool(getattr(stream, "isatty", lambda: False)())


class Progress:
    """Progress over ``total`` steps with an optional status text (e.g. the loss).

    Use as a context manager; call :meth:`update` once per step.
    """

    def __init__(self, total: int, desc: str = "", stream: TextIO | None = None, enabled: bool | None = None) -> None:
        self.total = max(int(total), 1)
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = progress_enabled(self.stream, enabled)
        self.count = 0
        self._bar = None

    def __enter__(self) -> Progress:
        if self.enabled:
            self._bar = tqdm(total=self.total, desc=self.desc, file=self.stream, leave=True,
                             mininterval=0.1, dynamic_ncols=True)
        return self

    def __exit__(self, *exc) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def update(self, n: int = 1, status: str = "") -> None:
        """Advance by ``n`` steps and show ``status`` beside the bar."""
        step = min(self.count + n, self.total) - self.count
        self.count += step
        if self._bar is not None:
            if status:
                self._bar.set_postfix_str(status, refresh=False)
            self._bar.update(step)

    def stage(self, status: str) -> None:
        """Show ``status`` (the stage now under way) at once, without advancing."""
        if self._bar is not None:
            self._bar.set_postfix_str(status, refresh=True)
