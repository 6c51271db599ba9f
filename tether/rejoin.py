"""Joining a real-time run already under way, after a restart. Pure bookkeeping: the wall clock is injected.

A process restarted mid-run (a unit's ``Restart=``) cannot hear the start message: it was published
once, before the process existed. It can hear the run itself: every sample carries its tick's time
``t = k h`` on its sender's clock and leaves at about ``epoch + k h`` there, so ``wall - t`` at
arrival is ``epoch + L`` (plus the sender's clock offset against this host's), and its minimum over
a few samples is the start instant, late by the smallest delay of that link. An agent uses its own
plant's samples (same host, same clock: late by a millisecond or two through the router); the
recorder the leader's (it records by tick index, so the delay and a skew only shift when it
considers the run over).
"""

from __future__ import annotations

import math
from collections.abc import Callable

SAMPLES = 20
"""Samples taken before the estimate of the start instant is trusted."""


class Rejoin:
    """The start instant of a run under way, from samples heard before this process's start.
    ``wall``: the process's wall clock (None in lockstep, where nothing can be joined)."""

    def __init__(self, wall: Callable[[], float] | None, samples: int = SAMPLES):
        self.wall = wall
        self.need = samples
        self.samples = 0
        self.best = math.inf

    def observe(self, k: int, t: float) -> None:
        """A sample of tick ``k`` stamped ``t`` [s] arrived now. Tick 0 and non-finite times are not
        used (tick 0 is what a normal start also hears first)."""
        if self.wall is None or not math.isfinite(t) or k <= 0:
            return
        self.samples += 1
        self.best = min(self.best, self.wall() - t)

    def epoch(self) -> float | None:
        """The run's start instant [s since the Unix epoch], once enough samples came; else None."""
        return self.best if self.samples >= self.need and math.isfinite(self.best) else None
