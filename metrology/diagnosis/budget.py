"""A diagnosis's time: the CPU clock its budget is counted on, and the deadline that ends it.

The budget is CPU seconds (a shared machine's load does not stretch them as it does wall time)
and, where a command promises a wall-clock limit, a wall-clock instant as well; whichever comes
first ends the selection (:func:`metrology.diagnosis.engine.run_diagnosis`).
"""

from __future__ import annotations

import resource
import time
from dataclasses import dataclass

__all__ = ["Deadline", "FitStop", "cpu_seconds"]


def cpu_seconds() -> float:
    """CPU seconds of this process (its worker threads included) and of its finished children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@dataclass(frozen=True)
class Deadline:
    """Where a diagnosis's time ends: a CPU-clock instant (:func:`cpu_seconds`) and a wall-clock
    one (``time.monotonic``), either None for no limit."""

    cpu: float | None = None
    wall: float | None = None

    @classmethod
    def after(cls, cpu_budget_s: float | None, wall: float | None = None) -> Deadline:
        """``cpu_budget_s`` CPU seconds from now (None: no CPU limit), and the wall instant ``wall``."""
        return cls(None if cpu_budget_s is None else cpu_seconds() + float(cpu_budget_s), wall)

    def past(self) -> bool:
        return ((self.cpu is not None and cpu_seconds() > self.cpu)
                or (self.wall is not None and time.monotonic() > self.wall))

    def affords(self, cpu_s: float, wall_s: float) -> bool:
        """Whether ``cpu_s`` more CPU seconds and ``wall_s`` more wall seconds end before it."""
        return self.refuses(cpu_s, wall_s) is None

    def refuses(self, cpu_s: float, wall_s: float) -> str | None:
        """Which limit ``cpu_s`` more CPU seconds or ``wall_s`` more wall seconds would pass:
        ``"cpu"`` (the budget, asked first), ``"wall"``, or None where both can pay."""
        if self.cpu is not None and cpu_seconds() + cpu_s > self.cpu:
            return "cpu"
        return "wall" if self.wall is not None and time.monotonic() + wall_s > self.wall else None

    def spent_by(self) -> str | None:
        """Which limit is past: ``"cpu"`` (the budget), ``"wall"`` (the wall clock) or None."""
        if self.cpu is not None and cpu_seconds() > self.cpu:
            return "cpu"
        return "wall" if self.wall is not None and time.monotonic() > self.wall else None

    def cpu_left(self) -> float | None:
        """CPU seconds left (never negative); None without a CPU limit."""
        return None if self.cpu is None else max(self.cpu - cpu_seconds(), 0.0)


class FitStop:
    """A fit's ``stop`` (:func:`~metrology.diagnosis.fitting.fit_effects`): true once ``deadline``
    is past; ``fired`` says a fit was stopped by it, short of convergence."""

    def __init__(self, deadline: Deadline):
        self.deadline, self.fired = deadline, False

    def __call__(self) -> bool:
        self.fired = self.fired or self.deadline.past()
        return self.fired
