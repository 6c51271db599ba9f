"""Clocks: one code path for lockstep sim time and real time.

Every process runs ``for k in range(first, last + 1): await clock.wait_for(k); ...``.

* :class:`LockstepClock` (studies and tests): tick k may start once the clock source has granted
  it (``Tick.grant >= k``). The source (:class:`LockstepSource`, pure) grants ``k`` once every
  process has acknowledged ``k - window``; inputs are matched by tick index, so the result does
  not depend on timing: runs are deterministic and as fast as the messages flow.
* :class:`RealtimeClock` (what flies): tick k starts at ``epoch + k h`` on the process's own
  monotonic clock; inputs are the newest samples held.

This module is the only one of a process that reads the wall or the monotonic clock, and only
through functions injected into :class:`RealtimeClock` (the real ones by default, fakes in tests).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Literal, Protocol

from tether.evloop import TIMER_GRAIN

ClockKind = Literal["lockstep", "realtime"]

EPOCH_TOLERANCE = 3600.0
"""A start instant further than this from the host's wall clock [s] is refused (the clocks of the
launcher and this host disagree: NTP is not running, or the start message is not this run's)."""


class ClockError(RuntimeError):
    """The run's start instant cannot be mapped onto this host's clock; the message says why."""


class Clock(Protocol):
    """What a process ticks on. ``Node`` is given one; nothing else in a process reads time."""

    kind: ClockKind
    late: int
    """Ticks that started more than one period after their instant (0 in lockstep)."""

    @property
    def lockstep(self) -> bool:
        """True when inputs are matched by tick index (sim time), False when by arrival (real time)."""
        ...

    def begin(self, epoch: float, phase: float = 0.0) -> None:
        """The run starts: tick 0 is at wall-clock instant ``epoch`` [s since the Unix epoch]; this
        process's tick k at ``epoch + (k + phase) h``. Raises :class:`ClockError`."""
        ...

    def now(self) -> float:
        """Mission time [s since tick 0] (the emulated network's time base in real time; 0 in
        lockstep and before :meth:`begin`, where the network runs on sample times instead)."""
        ...

    async def wait_for(self, k: int) -> float:
        """Block until tick k may run; returns how late it starts [s] (0 in lockstep)."""
        ...


class LockstepClock:
    """Tick k runs once the source granted it. :meth:`grant` is called from the event loop."""

    kind: ClockKind = "lockstep"
    lockstep = True

    def __init__(self) -> None:
        self._granted = -1
        self._changed = asyncio.Event()
        self.late = 0

    @property
    def granted(self) -> int:
        return self._granted

    def grant(self, k: int) -> None:
        if k > self._granted:
            self._granted = k
            self._changed.set()

    def begin(self, epoch: float, phase: float = 0.0) -> None:
        """Sim time has no wall-clock instant: nothing to map."""

    def now(self) -> float:
        return 0.0

    async def wait_for(self, k: int) -> float:
        while self._granted < k:
            self._changed.clear()
            await self._changed.wait()
        return 0.0


class RealtimeClock:
    """Tick k at ``start + k * period`` on ``monotonic`` (seconds).

    ``monotonic``, ``wall`` (seconds since the Unix epoch) and ``sleep`` are injected: processes
    use ``time.monotonic``, ``time.time`` and ``asyncio.sleep``; tests pass fakes."""

    kind: ClockKind = "realtime"
    lockstep = False

    def __init__(self, period: float, start: float = 0.0,
                 monotonic: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep) -> None:
        self.period = period
        self.start = start
        """This process's tick 0 [s, on ``monotonic``] (the run's tick 0 plus the phase)."""
        self.monotonic = monotonic
        self.wall = wall
        self.sleep = sleep
        self.origin: float | None = None
        """The run's tick 0 [s, on ``monotonic``], once :meth:`begin` mapped it."""
        self.late = 0
        """Ticks that started more than one period after their instant."""

    def begin(self, epoch: float, phase: float = 0.0) -> None:
        offset = epoch - self.wall()
        if not abs(offset) <= EPOCH_TOLERANCE:
            raise ClockError(f"the start instant {epoch} is more than an hour from this host's clock; "
                             "check the clocks (NTP) of the launcher and this host")
        self.origin = self.monotonic() + offset
        self.start = self.origin + phase * self.period

    def now(self) -> float:
        return self.monotonic() - self.origin if self.origin is not None else 0.0

    async def wait_for(self, k: int) -> float:
        due = self.start + k * self.period
        now = self.monotonic()
        if now < due:
            await self.sleep(due - now)
            now = self.monotonic()
            # never before the instant: uvloop's timers can fire up to about a millisecond early
            # (tether/evloop.py); the rest is slept again, a grain at least (shorter would spin)
            while now < due:
                await self.sleep(max(due - now, TIMER_GRAIN))
                now = self.monotonic()
        lateness = now - due
        if lateness > self.period:
            self.late += 1
        return max(0.0, lateness)


SKEW_LIMIT = 10.0
"""The largest clock offset [s] a process may be given (``--clock-skew``, ``--fault skew:...``)."""


def check_skew(skew: float, what: str = "--clock-skew") -> str | None:
    """Why ``skew`` [s] cannot be a process's clock offset (naming ``what``), or None."""
    if not math.isfinite(skew):
        return f"{what}: is {skew}; give a finite number of seconds, e.g. +0.05"
    if abs(skew) > SKEW_LIMIT:
        return f"{what}: is {skew:g} s; give at most {SKEW_LIMIT:g} s either way (a host that far off is refused no " \
               "matter what: a start more than an hour off its clock is an error)"
    return None


def make(kind: ClockKind, period: float, skew: float = 0.0) -> LockstepClock | RealtimeClock:
    """The clock of a process: the one place that turns a ``--clock`` choice into an object.

    ``skew`` [s]: real time only, this process's wall clock reads ``skew`` seconds ahead of the
    host's (an emulated unsynchronised host: its ticks, its mission time and every sample time it
    stamps are ``skew`` early). Raises ValueError for a skew :func:`check_skew` refuses, or a
    non-zero one in lockstep (ticks follow the clock source there, not a clock)."""
    if (why := check_skew(skew)) is not None:
        raise ValueError(why)
    if kind == "lockstep":
        if skew != 0.0:
            raise ValueError("--clock-skew: lockstep ticks follow the clock source, not a clock; use --clock realtime")
        return LockstepClock()
    if kind == "realtime":
        if skew == 0.0:
            return RealtimeClock(period)
        return RealtimeClock(period, wall=lambda: time.time() + skew)
    raise ValueError(f"clock must be 'lockstep' or 'realtime', not {kind!r}")


@dataclass
class LockstepSource:
    """The lockstep clock source's bookkeeping (pure): how far each process has acknowledged.

    ``members`` are the ``(role, id)`` pairs that must acknowledge every tick; an acknowledgement of
    tick k stands for every tick up to k (:class:`~tether.wire.Ack`). ``window`` ticks may be in
    flight at once (1 = strictly one tick at a time; more pipelines the message hops without
    changing any result, because every input is matched by tick index).
    """

    members: frozenset[tuple[str, int]]
    last: int
    window: int = 2
    _upto: dict[tuple[str, int], int] = field(default_factory=dict)
    done: int = -1
    """Highest tick that every member has acknowledged (all lower ticks too)."""

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError("window must be >= 1")

    @property
    def grant(self) -> int:
        return min(self.last, self.done + self.window)

    def ack(self, role: str, node: int, k: int) -> bool:
        """Record that ``(role, node)`` has finished every tick up to ``k``; True when it advanced
        ``done`` (so ``grant`` may have moved). Not a member, an older or repeated acknowledgement,
        or one of a tick not granted yet (nobody can have finished it: a forged or corrupt one,
        which would otherwise skip ticks): ignored, False."""
        who = (role, node)
        if who not in self.members or k > self.grant or k <= self._upto.get(who, -1):
            return False
        self._upto[who] = k
        done = min(self._upto.get(m, -1) for m in self.members)
        if done <= self.done:
            return False
        self.done = done
        return True

    @property
    def finished(self) -> bool:
        return self.done >= self.last

    def missing(self) -> list[tuple[str, int]]:
        """Members that have not acknowledged the next tick (for a stall report)."""
        return sorted(m for m in self.members if self._upto.get(m, -1) <= self.done)
