"""Clocks: one code path for lockstep sim time and real time.

Every process runs ``for k in range(first, last + 1): await clock.wait_for(k); ...``.

* :class:`LockstepClock` (studies and tests): tick k may start once the clock source has granted
  it (``Tick.grant >= k``). The source (:class:`LockstepSource`, pure) grants ``k`` once every
  process has acknowledged ``k - window``; inputs are matched by tick index, so the result does
  not depend on timing: runs are deterministic and as fast as the messages flow.
* :class:`RealtimeClock` (what flies): tick k starts at ``epoch + k h`` on the process's own
  monotonic clock; inputs are the newest samples held.

The wall clock is read only through an injected ``monotonic`` function (``time.monotonic`` in
processes, a fake in tests).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Callable, Literal, Protocol

ClockKind = Literal["lockstep", "realtime"]


class Clock(Protocol):
    kind: ClockKind

    async def wait_for(self, k: int) -> float:
        """Block until tick k may run; returns how late it starts [s] (0 in lockstep)."""
        ...


class LockstepClock:
    """Tick k runs once the source granted it. :meth:`grant` is called from the event loop."""

    kind: ClockKind = "lockstep"

    def __init__(self) -> None:
        self._granted = -1
        self._changed = asyncio.Event()

    @property
    def granted(self) -> int:
        return self._granted

    def grant(self, k: int) -> None:
        if k > self._granted:
            self._granted = k
            self._changed.set()

    async def wait_for(self, k: int) -> float:
        while self._granted < k:
            self._changed.clear()
            await self._changed.wait()
        return 0.0


class RealtimeClock:
    """Tick k at ``start + k * period`` on ``monotonic`` (seconds)."""

    kind: ClockKind = "realtime"

    def __init__(self, period: float, start: float, monotonic: Callable[[], float]) -> None:
        self.period = period
        self.start = start
        self.monotonic = monotonic
        self.late = 0
        """Ticks that started more than one period after their instant."""

    async def wait_for(self, k: int) -> float:
        due = self.start + k * self.period
        delay = due - self.monotonic()
        if delay > 0:
            await asyncio.sleep(delay)
        lateness = self.monotonic() - due
        if lateness > self.period:
            self.late += 1
        return max(0.0, lateness)


@dataclass
class LockstepSource:
    """The lockstep clock source's bookkeeping (pure): which processes acknowledged which tick.

    ``members`` are the ``(role, id)`` pairs that must acknowledge every tick; ``window`` ticks may be
    in flight at once (1 = strictly one tick at a time; more pipelines the message hops without
    changing any result, because every input is matched by tick index).
    """

    members: frozenset[tuple[str, int]]
    last: int
    window: int = 2
    _acks: dict[int, set[tuple[str, int]]] = field(default_factory=dict)
    done: int = -1
    """Highest tick that every member has acknowledged (all lower ticks too)."""

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError("window must be >= 1")

    @property
    def grant(self) -> int:
        return min(self.last, self.done + self.window)

    def ack(self, role: str, node: int, k: int) -> bool:
        """Record an acknowledgement; True when it advanced ``done`` (so ``grant`` may have moved)."""
        who = (role, node)
        if who not in self.members or k <= self.done:
            return False
        self._acks.setdefault(k, set()).add(who)
        moved = False
        while len(self._acks.get(self.done + 1, ())) == len(self.members):
            del self._acks[self.done + 1]
            self.done += 1
            moved = True
        return moved

    @property
    def finished(self) -> bool:
        return self.done >= self.last

    def missing(self) -> list[tuple[str, int]]:
        """Members that have not acknowledged the next tick (for a stall report)."""
        got = self._acks.get(self.done + 1, set())
        return sorted(self.members - got)
