"""Clocks: lockstep sim time and real time, two strategies behind one :class:`Clock` protocol.

Every process runs ``for k in range(first, last + 1): await node.tick(k); ...``; the clock it was
handed decides what that means, once, where the process is built (:func:`make`):

* :class:`LockstepClock` (studies and tests): tick k may start once the clock source has granted
  it (``Tick.grant >= k``). The source (:class:`LockstepSource`, pure) grants ``k`` once every
  process has acknowledged ``k - window``; inputs are matched by tick index, so the result does
  not depend on timing: runs are deterministic and as fast as the messages flow.
* :class:`RealtimeClock` (what flies): tick k starts at ``epoch + k h`` on the process's own
  monotonic clock; inputs are the newest samples held.

Besides time, each strategy holds what the two ways of running differ in for a process: how its
streams are published, how its inputs are queued, offered and aligned, how a tick is gated. The
process (:class:`tether.node.Node`) calls these and never asks which clock it holds.

This module is the only one of a process that reads the wall or the monotonic clock, and only
through functions injected into :class:`RealtimeClock` (the real ones by default, fakes in tests).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal, Protocol

from tether import transport as tp
from tether.evloop import TIMER_GRAIN
from tether.skew import SkewMonitor

if TYPE_CHECKING:
    from tether.handoff import Sink
    from tether.inputs import Source

ClockKind = Literal["lockstep", "realtime"]

EPOCH_TOLERANCE = 3600.0
"""A start instant further than this from the host's wall clock [s] is refused (the clocks of the
launcher and this host disagree: NTP is not running, or the start message is not this run's)."""

MAX_LAG = 8
"""Real time: an input whose newest sample is more than this many ticks older than the tick being
run takes no part in aligning the others (:meth:`RealtimeClock.align`), and samples older than
that are forgotten: a silent or late stream then never holds the others back to its old tick."""

AGENT_PHASE = 0.5
"""Real time: agents tick at ``epoch + (k + AGENT_PHASE) h``; plants and the leader at ``epoch + k h``,
so that the samples of tick k are usually in when an agent runs it."""


class ClockError(RuntimeError):
    """The run's start instant cannot be mapped onto this host's clock; the message says why."""


class Inbox(Protocol):
    """What a clock strategy asks of a process's inputs (:class:`tether.ingress.Ingress` is one)."""

    copies: int
    """Copies received of samples already had (lockstep resends), dropped."""

    @property
    def fifo(self) -> Sink[tp.Received]:
        """Every sample, in arrival order, each waking the event loop."""
        ...

    @property
    def deferred(self) -> Sink[tp.Received]:
        """Samples that wake nobody, drained at the latest one control period after they arrive."""
        ...

    def release(self, now: float, only: Source | None = None) -> None: ...

    def bounded(self, key: str, expect: type, quiet: bool, tap: Callable[[tp.Received], None] | None
                ) -> Sink[tp.Received]: ...

    def offer(self, src: Source, msg: Any, at: float, missed: bool) -> None: ...


class Waiter(Protocol):
    """What a clock strategy asks of a process to pace it (:class:`tether.node.Node` is one)."""

    @property
    def stall_timeout(self) -> float:
        """Lockstep: how long a tick waits for one input [s] before :class:`~tether.node.Stalled`."""
        ...

    def drain(self) -> None: ...

    async def until(self, ready: Callable[[], bool], timeout: float | None, what: str | Callable[[], str],
                    resend: bool = False) -> None: ...

    def release(self, now: float, only: Source | None = None) -> None: ...

    def tick_source(self, grant: Callable[[int], None]) -> None: ...

    def recorded_source(self) -> Source: ...

    async def pump(self) -> None: ...

    async def pace(self) -> None: ...


class Clock(Protocol):
    """What a process ticks on, and how it hears and speaks meanwhile. ``Node`` is given one by
    :func:`tether.node.serve`; nothing else in a process reads time or asks which clock it has."""

    kind: ClockKind
    """Which strategy this is, for what a run records and logs (never to choose a behaviour)."""
    late: int
    """Ticks that started more than one period after their instant (0 in lockstep)."""

    @property
    def wall(self) -> Callable[[], float] | None:
        """This process's wall clock [s since the Unix epoch], what a rejoin measures the start
        instant with (:class:`tether.rejoin.Rejoin`); None in lockstep, where no run is joined."""
        ...

    def begin(self, epoch: float, phase: float = 0.0) -> str:
        """The run starts: tick 0 is at wall-clock instant ``epoch`` [s since the Unix epoch]; this
        process's tick k at ``epoch + (k + phase) h``. Returns a line for the log saying so;
        raises :class:`ClockError`."""
        ...

    @property
    def origin(self) -> float | None:
        """The run's tick 0 [s, on :meth:`reading`'s scale] once :meth:`begin` mapped it; None
        before, and in lockstep, where tick 0 is no instant."""
        ...

    def join(self, rejoin: Callable[[], float | None] | None) -> Callable[[], float | None] | None:
        """The rejoin hook a process honours while it waits for the start (``rejoin``: tells the
        start instant of a run under way, once it can): itself in real time; None in lockstep,
        where a run under way is never joined (ticks follow the clock source's grants)."""
        ...

    def unstarted(self) -> bool:
        """True while samples heard belong to a run this process has not begun (real time, before
        :meth:`begin`: a restarted process hears a run under way); always False in lockstep."""
        ...

    def now(self) -> float:
        """Mission time [s since tick 0] (the emulated network's time base in real time; 0 in
        lockstep and before :meth:`begin`, where the network runs on sample times instead)."""
        ...

    def reading(self) -> float:
        """The clock's own reading [s, on the scale of its arrival stamps; monotonic in real time,
        0 in lockstep]."""
        ...

    def arrival(self, at: float) -> float:
        """The mission time [s] of an arrival stamp ``at`` [s, :meth:`reading`'s scale]; NaN (not
        stamped): now."""
        ...

    def ago(self, at: float) -> float:
        """How long ago [s] the arrival stamp ``at`` was taken (NaN, not stamped: 0)."""
        ...

    def reached(self, h: float) -> int | None:
        """The tick of period ``h`` [s] this clock has reached, whatever this process has run (a
        late process is behind it); None in lockstep, where ticks follow the grants."""
        ...

    def link_time(self, offered: float) -> float:
        """When a change of an emulated link takes effect if it names no instant [s, mission
        time]: now in real time; in lockstep, where links run on sample times, ``offered`` (the
        sample time of the newest sample offered to the link)."""
        ...

    def require(self, kind: ClockKind, why: str) -> None:
        """Raise ValueError(``why``) unless this clock is of ``kind``: a feature that exists only
        in one of the two ways of running, refused in the other."""
        ...

    async def wait_for(self, k: int) -> float:
        """Block until tick k may run; returns how late it starts [s] (0 in lockstep)."""
        ...

    # ---- what a role judges differently on it
    exact: bool
    """Inputs are matched by tick index: a tick runs with exactly its tick's samples, so nothing
    heard can be silent, stale or late, and a sample's arrival time means nothing (lockstep).
    False: a tick takes the newest held, judged by when it came (real time)."""

    def silent(self, src: Source, k: int) -> bool:
        """``src`` went silent before delivering tick ``k`` (:meth:`~tether.inputs.Source.silent_at`)."""
        ...

    def gone(self, src: Source) -> bool:
        """``src``'s producer's liveliness token is gone (:attr:`~tether.inputs.Source.gone`)."""
        ...

    def overdue(self, age: float, limit: float) -> bool:
        """A sample ``age`` seconds old is past ``limit`` [s]."""
        ...

    def departed(self, gone: Callable[[], frozenset[int]]) -> frozenset[int]:
        """Of the members whose tokens went (``gone()`` says which), those to count as gone."""
        ...

    def received(self, src: Source, k: int) -> int:
        """Samples of ``src`` counted as received at tick ``k``."""
        ...

    def sent(self, src: Source, k: int) -> int:
        """Samples ``src``'s sender had sent at tick ``k``, as far as its newest received tells."""
        ...

    def arrivals(self, now: Callable[[], float]) -> Callable[[], float] | None:
        """What a plausibility gate reads as a sample's arrival: ``now`` [s, mission time], or None
        where arrival times mean nothing."""
        ...

    def offsets(self, period: float) -> SkewMonitor | None:
        """A monitor of the input links' clock offsets (:mod:`tether.skew`), where they can be seen."""
        ...

    def hook(self, on_loop: Callable[[Any], None], on_thread: Callable[[tp.Received], None]
             ) -> tuple[Callable[[Any], None] | None, Callable[[tp.Received], None] | None]:
        """Where a relay of an input runs: the ``on_message`` and ``tap`` to give
        :meth:`tether.node.Node.source`, one of them None."""
        ...

    # ---- what the process does differently on it
    def stream(self, qos: tp.StreamQos | None, window: int) -> tuple[tp.StreamQos, int]:
        """A publisher's QoS (``qos`` asked, None: the default) and how many ticks of its messages
        it keeps to send again after a stall (``window``: the lockstep clock's)."""
        ...

    def subscription(self, inbox: Inbox, wake: bool) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        """Where a wildcard subscription's samples go, and the stamp read in its callback (None:
        not stamped). ``wake=False``: samples that need not wake the loop as they come."""
        ...

    def input_sink(self, inbox: Inbox, key: str, expect: type, quiet: bool,
                   tap: Callable[[tp.Received], None] | None) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        """Where one input key's samples go, and the stamp read in its callback. ``quiet``: read at
        the tick only; ``tap``: also handed each sample on Zenoh's thread."""
        ...

    def offer(self, inbox: Inbox, src: Source, msg: Any, rec: tp.Received) -> None:
        """Hand a decoded sample ``msg`` (received as ``rec``) to its source, or to the emulated
        link it crosses."""
        ...

    def deliver(self, inbox: Inbox) -> None:
        """After a drain: hand what the emulated links have delivered by now to their sources."""
        ...

    async def align(self, node: Waiter, sources: list[Source], k: int, dt: float, drain: bool) -> list[Any]:
        """One sample per source for tick ``k`` of period ``dt`` [s] (see :meth:`tether.node.Node.aligned`)."""
        ...

    async def gate(self, node: Waiter, k: int) -> float:
        """Wait until tick ``k`` may run, inputs drained as it returns; its lateness [s]."""
        ...

    def prepare(self, node: Waiter, paced: bool, member: bool) -> Source | None:
        """Before the start: declare what this clock needs heard (``paced``: a role that follows
        the clock's grants; ``member``: a process the launcher waits for at the end). Returns the
        source of the launcher's word that every sample is recorded, or None."""
        ...

    def companions(self, node: Waiter, deferring: bool) -> list[tuple[str, Coroutine[Any, Any, None]]]:
        """After the start: the tasks that run beside the role (named), none in lockstep."""
        ...


class LockstepClock:
    """Tick k runs once the source granted it, inputs matched by tick index. :meth:`grant` is
    called from the event loop."""

    kind: ClockKind = "lockstep"
    wall: None = None
    origin: None = None

    def __init__(self) -> None:
        self._granted = -1
        self._changed = asyncio.Event()
        self._paced = False
        self.late = 0

    @property
    def granted(self) -> int:
        return self._granted

    def grant(self, k: int) -> None:
        if k > self._granted:
            self._granted = k
            self._changed.set()

    def begin(self, epoch: float, phase: float = 0.0) -> str:
        """Sim time has no wall-clock instant: nothing to map."""
        return "lockstep: ticks follow the clock source's grants"

    def join(self, rejoin: Callable[[], float | None] | None) -> Callable[[], float | None] | None:
        return None

    def unstarted(self) -> bool:
        return False

    def now(self) -> float:
        return 0.0

    def reading(self) -> float:
        return 0.0

    def arrival(self, at: float) -> float:
        return 0.0

    def ago(self, at: float) -> float:
        return 0.0

    def reached(self, h: float) -> int | None:
        return None

    def link_time(self, offered: float) -> float:
        return offered

    def require(self, kind: ClockKind, why: str) -> None:
        if kind != self.kind:
            raise ValueError(why)

    async def wait_for(self, k: int) -> float:
        while self._granted < k:
            self._changed.clear()
            await self._changed.wait()
        return 0.0

    exact = True

    def silent(self, src: Source, k: int) -> bool:
        return False  # a tick waits for its inputs: nothing can be silent

    def gone(self, src: Source) -> bool:
        return False

    def overdue(self, age: float, limit: float) -> bool:
        return False

    def departed(self, gone: Callable[[], frozenset[int]]) -> frozenset[int]:
        return frozenset()  # a member that finished first is not lost

    def received(self, src: Source, k: int) -> int:
        return src.received_upto(k)  # what tick k could have seen, whatever arrived early

    def sent(self, src: Source, k: int) -> int:
        return 0 if src.newest is None else min(src.newest.seq, k) + 1  # one a tick, of ticks <= k

    def arrivals(self, now: Callable[[], float]) -> Callable[[], float] | None:
        return None

    def offsets(self, period: float) -> SkewMonitor | None:
        return None

    def hook(self, on_loop: Callable[[Any], None], on_thread: Callable[[tp.Received], None]
             ) -> tuple[Callable[[Any], None] | None, Callable[[tp.Received], None] | None]:
        return on_loop, None  # in order, from the loop (a callback must not publish BLOCK)

    def stream(self, qos: tp.StreamQos | None, window: int) -> tuple[tp.StreamQos, int]:
        """Always :data:`~tether.transport.SYNC` (BLOCK): a lost sample would stall the run
        (measured here, DROP state streams lost samples under load and stalled lockstep runs);
        the last ``window + 1`` ticks kept (none without a window)."""
        return tp.SYNC, window + 1 if window else 0

    def subscription(self, inbox: Inbox, wake: bool) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        return inbox.fifo, None  # a tick waits for its inputs: every sample wakes the loop

    def input_sink(self, inbox: Inbox, key: str, expect: type, quiet: bool,
                   tap: Callable[[tp.Received], None] | None) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        return inbox.fifo, None  # every sample is needed, in order; none is dropped for a newer one

    def offer(self, inbox: Inbox, src: Source, msg: Any, rec: tp.Received) -> None:
        if src.channel is None:
            if src.had(msg):
                # a copy sent again after a stall (resend) of a sample this source has; not a link's
                # duplicate: whether a resend happens depends on the machine's load, and the run's
                # arrays (link statistics, drops) must not
                inbox.copies += 1
                return
            src.offer(msg, missed=True)  # not stamped: arrival times mean nothing here
            return
        if msg.k <= src.raw_k:
            # a copy sent again after a stall of a tick the emulated link has had; offered again, it
            # would draw the link's random decisions anew and change the run
            inbox.copies += 1
            return
        src.raw_k = msg.k
        src.channel.send(msg.t, rec.payload)

    def deliver(self, inbox: Inbox) -> None:
        """Links run on sample times here: a source takes what its link delivered at its tick (:meth:`align`)."""

    async def align(self, node: Waiter, sources: list[Source], k: int, dt: float, drain: bool) -> list[Any]:
        """The samples of tick ``k`` (waits for each); through an emulated link, the newest it had
        delivered by ``t_k`` (possibly older, or None)."""
        out = []
        if drain:
            node.drain()  # once for all: a source already holding its tick needs no wait (nor its timer)
        for src in sources:
            if src.channel is None:
                if k not in src.by_tick:
                    await node.until(lambda: k in src.by_tick, node.stall_timeout,
                                      f"tick {k} on {src.key}", resend=True)
                out.append(src.by_tick[k])
                src.forget_before(k)
                continue
            # once the sender's tick k has entered the link, what the link has delivered by t_k is
            # known; use the newest of it (possibly older, or none)
            if src.raw_k < k:
                await node.until(lambda: src.raw_k >= k, node.stall_timeout,
                                  f"tick {k} sent on {src.key}", resend=True)
            node.release(k * dt, only=src)
            held = [t for t in src.by_tick if t <= k]
            out.append(src.by_tick[max(held)] if held else None)
            src.forget_before(max(held) if held else 0)
        return out

    async def gate(self, node: Waiter, k: int) -> float:
        """A paced role waits for the grant of tick ``k``; every other is gated by its inputs of
        tick ``k`` (:meth:`align`), which is what makes the run deterministic."""
        if self._paced:
            await node.until(lambda: self._granted >= k, node.stall_timeout,
                              f"the clock's grant of tick {k}", resend=True)
        else:
            node.drain()
        return 0.0

    def prepare(self, node: Waiter, paced: bool, member: bool) -> Source | None:
        self._paced = paced
        if paced:
            node.tick_source(self.grant)
        return node.recorded_source() if member else None

    def companions(self, node: Waiter, deferring: bool) -> list[tuple[str, Coroutine[Any, Any, None]]]:
        return []


class RealtimeClock:
    """Tick k at ``start + k * period`` on ``monotonic`` (seconds); inputs are the newest held.

    ``monotonic``, ``wall`` (seconds since the Unix epoch) and ``sleep`` are injected: processes
    use ``time.monotonic``, ``time.time`` and ``asyncio.sleep``; tests pass fakes. ``max_lag``
    [ticks]: see :data:`MAX_LAG`."""

    kind: ClockKind = "realtime"

    def __init__(self, period: float, start: float = 0.0,
                 monotonic: Callable[[], float] = time.monotonic,
                 wall: Callable[[], float] = time.time,
                 sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
                 max_lag: int = MAX_LAG) -> None:
        self.period = period
        self.start = start
        """This process's tick 0 [s, on ``monotonic``] (the run's tick 0 plus the phase)."""
        self.monotonic = monotonic
        self.wall = wall
        self.sleep = sleep
        self.max_lag = max_lag
        self.origin: float | None = None
        """The run's tick 0 [s, on ``monotonic``], once :meth:`begin` mapped it."""
        self.late = 0
        """Ticks that started more than one period after their instant."""

    def begin(self, epoch: float, phase: float = 0.0) -> str:
        offset = epoch - self.wall()
        if not abs(offset) <= EPOCH_TOLERANCE:
            raise ClockError(f"the start instant {epoch} is more than an hour from this host's clock; "
                             "check the clocks (NTP) of the launcher and this host")
        self.origin = self.monotonic() + offset
        self.start = self.origin + phase * self.period
        return f"real time: tick 0 at {epoch:.3f}, phase {phase:.2f}"

    def join(self, rejoin: Callable[[], float | None] | None) -> Callable[[], float | None] | None:
        return rejoin

    def unstarted(self) -> bool:
        return self.origin is None

    def now(self) -> float:
        return self.monotonic() - self.origin if self.origin is not None else 0.0

    def reading(self) -> float:
        return self.monotonic()

    def arrival(self, at: float) -> float:
        if at == at and self.origin is not None:  # stamped (not NaN)
            return at - self.origin
        return self.now()

    def ago(self, at: float) -> float:
        return self.monotonic() - at if at == at else 0.0

    def reached(self, h: float) -> int | None:
        return math.floor(self.now() / h)

    def link_time(self, offered: float) -> float:
        return self.now()

    def require(self, kind: ClockKind, why: str) -> None:
        if kind != self.kind:
            raise ValueError(why)

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

    exact = False

    def silent(self, src: Source, k: int) -> bool:
        return src.silent_at(k)

    def gone(self, src: Source) -> bool:
        return src.gone

    def overdue(self, age: float, limit: float) -> bool:
        return age > limit

    def departed(self, gone: Callable[[], frozenset[int]]) -> frozenset[int]:
        return gone()

    def received(self, src: Source, k: int) -> int:
        return src.received

    def sent(self, src: Source, k: int) -> int:
        return 0 if src.newest is None else src.newest.seq + 1

    def arrivals(self, now: Callable[[], float]) -> Callable[[], float] | None:
        return now

    def offsets(self, period: float) -> SkewMonitor | None:
        return SkewMonitor(period)

    def hook(self, on_loop: Callable[[Any], None], on_thread: Callable[[tp.Received], None]
             ) -> tuple[Callable[[Any], None] | None, Callable[[tp.Received], None] | None]:
        return None, on_thread  # as it arrives, on Zenoh's thread, without waiting for the loop

    def stream(self, qos: tp.StreamQos | None, window: int) -> tuple[tp.StreamQos, int]:
        """``qos``, by default :data:`~tether.transport.STATE` (DROP: the newest supersedes); nothing kept."""
        return qos or tp.STATE, 0

    def subscription(self, inbox: Inbox, wake: bool) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        if wake:
            return inbox.fifo, None
        return inbox.deferred, self.monotonic  # stamped: a plausibility gate judges the arrival, not the drain

    def input_sink(self, inbox: Inbox, key: str, expect: type, quiet: bool,
                   tap: Callable[[tp.Received], None] | None) -> tuple[Sink[tp.Received], Callable[[], float] | None]:
        # the newest, bounded: a flood on one key costs the loop a budget, not the run
        return inbox.bounded(key, expect, quiet, tap), self.monotonic if quiet or tap is not None else None

    def offer(self, inbox: Inbox, src: Source, msg: Any, rec: tp.Received) -> None:
        if src.channel is None:
            inbox.offer(src, msg, rec.at, missed=False)
            return
        src.raw_k = max(src.raw_k, msg.k)
        src.channel.send(self.now(), rec.payload)

    def deliver(self, inbox: Inbox) -> None:
        inbox.release(self.now())

    async def align(self, node: Waiter, sources: list[Source], k: int, dt: float, drain: bool) -> list[Any]:
        """Among the sources whose newest sample is at most :attr:`max_lag` ticks old, the newest
        tick ``c <= k`` that all of them hold, so that a tick never mixes, say, an own measurement
        of k-1 with neighbours' of k (which would show as a spurious formation error of about one
        period of motion); a source older than that (silent, or not started) gives its newest
        sample, or None. An emulated link's delay is what is being studied: its input is the
        newest it has delivered."""
        if drain:
            node.drain()
        lag = self.max_lag
        newest = [max((t for t in s.by_tick if t <= k), default=-1) for s in sources]
        live = [t for s, t in zip(sources, newest) if t >= k - lag and s.channel is None]
        common = min(live) if live else -1
        out = []
        for src, t in zip(sources, newest):
            if src.channel is not None:
                msg = src.by_tick.get(t)
            else:
                msg = src.by_tick.get(common) if t >= k - lag else None
            out.append(msg if msg is not None else src.newest)
            src.forget_before(k - lag)
        return out

    async def gate(self, node: Waiter, k: int) -> float:
        late = await self.wait_for(k)
        node.drain()
        return late

    def prepare(self, node: Waiter, paced: bool, member: bool) -> Source | None:
        return None  # every process ticks on its own clock; the end is a linger, not a word

    def companions(self, node: Waiter, deferring: bool) -> list[tuple[str, Coroutine[Any, Any, None]]]:
        """The input pump (``on_message`` hooks run as samples arrive, not at the next tick) and,
        with deferred subscriptions, their per-period wake-up."""
        out: list[tuple[str, Coroutine[Any, Any, None]]] = [("input pump", node.pump())]
        if deferring:
            out.append(("deferred inputs", node.pace()))
        return out


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
