"""A limit the user asked for on a diagnosis (``doe diagnose --wall-limit-s``, ``--cpu-budget-s``).

There is no default limit: without one, a selection ends only by its own rules (the criterion,
the fits' evaluation counts and tolerances, the screening by score), so the same file and options
give the same names and parameters on an idle machine, beside another job or on a slower CPU.
A limit is opt-in and load-dependent by nature: where it ends anything (a round of candidates, a
fit under way, the backward pass, a rerun), :class:`Deadline` records it (``hit``) and the
diagnosis says INCOMPLETE and lists the candidates it did not try
(:meth:`~metrology.diagnosis.result.Diagnosis.to_dict`); ``doe diagnose`` then exits with
:data:`~metrology.cli.diagnose.EXIT_INCOMPLETE`. Nothing forecasts what the time left could pay: a
step either runs to its end or the limit cuts it.

CPU seconds are this process's (its worker threads included) and its finished children's.
"""

from __future__ import annotations

import resource
import time

__all__ = ["Deadline", "FitStop", "cpu_seconds"]


def cpu_seconds() -> float:
    """CPU seconds of this process (its worker threads included) and of its finished children."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class Deadline:
    """Where a user's limit ends a diagnosis: a CPU-clock instant (:func:`cpu_seconds`) and a
    wall-clock one (``time.monotonic``), either None for none (the default: no limit at all).

    Attributes
    ----------
    cpu, wall : float or None
    hit : str or None
        ``"cpu"`` or ``"wall"`` once :meth:`past` found that limit passed (it then stays set): the
        diagnosis it was asked for is incomplete.
    """

    def __init__(self, cpu: float | None = None, wall: float | None = None):
        self.cpu, self.wall = cpu, wall
        self.hit: str | None = None

    @classmethod
    def after(cls, cpu_budget_s: float | None = None, wall_limit_s: float | None = None) -> Deadline:
        """``cpu_budget_s`` CPU seconds and ``wall_limit_s`` wall seconds from now (None: no such limit)."""
        return cls(None if cpu_budget_s is None else cpu_seconds() + float(cpu_budget_s),
                   None if wall_limit_s is None else time.monotonic() + float(wall_limit_s))

    @property
    def active(self) -> bool:
        """Whether any limit was asked for."""
        return self.cpu is not None or self.wall is not None

    def past(self) -> bool:
        """Whether a limit is passed (recorded in ``hit``); always False without a limit."""
        if self.hit is None:
            if self.cpu is not None and cpu_seconds() > self.cpu:
                self.hit = "cpu"
            elif self.wall is not None and time.monotonic() > self.wall:
                self.hit = "wall"
        return self.hit is not None


class FitStop:
    """A fit's ``stop`` (:func:`~metrology.diagnosis.fitting.fit_effects`): true once ``deadline``
    is past; ``fired`` says a fit was stopped by it, short of convergence."""

    def __init__(self, deadline: Deadline):
        self.deadline, self.fired = deadline, False

    def __call__(self) -> bool:
        self.fired = self.fired or self.deadline.past()
        return self.fired
