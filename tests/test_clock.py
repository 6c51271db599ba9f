"""tether.clock: the lockstep source's bookkeeping, the lockstep clock's grants, the real-time clock,
and the contract both clocks keep as strategies (what a process asks of its clock).

The real-time clock reads time only through the ``monotonic`` function it is given; here that is a
fake whose readings the test sets, so a tick "in the past" costs no sleep at all and a tick in the
future costs the few milliseconds the test chooses.
"""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np
import pytest

from tether import transport as tp
from tether.clock import MAX_LAG, Clock, LockstepClock, LockstepSource, RealtimeClock
from tether.inputs import Source
from tether.evloop import TIMER_GRAIN

WAIT = 2.0
"""Upper bound [s] on a wait for something that happens within one event-loop turn."""

MEMBERS = frozenset({("recorder", 0), ("agent", 1), ("plant", 1)})


# --------------------------------------------------------------------------- LockstepSource
def test_source_grants_window_ticks_ahead_of_what_is_done() -> None:
    src = LockstepSource(MEMBERS, last=100, window=3)
    assert (src.done, src.grant, src.finished) == (-1, 2, False)  # ticks 0, 1, 2 may run at once
    for who in sorted(MEMBERS):
        src.ack(*who, 0)
    assert (src.done, src.grant) == (0, 3)


def test_source_with_window_one_runs_strictly_one_tick_at_a_time() -> None:
    src = LockstepSource(MEMBERS, last=5, window=1)
    assert src.grant == 0
    for k in range(6):
        for who in sorted(MEMBERS):
            src.ack(*who, k)
        assert src.done == k and src.grant == min(5, k + 1)
    assert src.finished


def test_source_advances_only_when_every_member_acked_and_reports_who_is_missing() -> None:
    src = LockstepSource(MEMBERS, last=10, window=2)
    assert src.missing() == sorted(MEMBERS)
    assert src.ack("agent", 1, 0) is False
    assert src.ack("plant", 1, 0) is False
    assert src.missing() == [("recorder", 0)]
    assert src.ack("recorder", 0, 0) is True  # the last one in moves `done`
    assert src.done == 0 and src.missing() == sorted(MEMBERS)


def test_source_takes_cumulative_acks_in_any_order_and_interleaving() -> None:
    """Each member acknowledges some of its ticks (an ack of k stands for every tick up to k), the
    members' acks interleaved at random, some repeated or arriving late: ``done`` is always the
    least of what every member has acknowledged so far, never goes back, and reaches the last."""
    rng = np.random.default_rng(7)
    last = 30
    for _ in range(20):
        src = LockstepSource(MEMBERS, last=last, window=4)
        upto = {who: -1 for who in MEMBERS}
        done_seen = []
        while not src.finished:
            who = sorted(MEMBERS)[rng.integers(len(MEMBERS))]
            # a tick not beyond the grant, possibly behind what this member said (late, repeated)
            k = int(rng.integers(max(0, upto[who] - 2), src.grant + 1))
            src.ack(*who, k)
            upto[who] = max(upto[who], k)
            assert src.done == min(upto.values())
            done_seen.append(src.done)
        assert done_seen == sorted(done_seen)  # never goes back
        assert src.done == last and src.grant == last


def test_source_ignores_duplicates_unknown_members_and_old_ticks() -> None:
    src = LockstepSource(MEMBERS, last=10, window=2)
    assert src.ack("agent", 1, 0) is False
    assert src.ack("agent", 1, 0) is False  # duplicate: still one member of three
    assert src.ack("agent", 99, 0) is False  # not a member
    assert src.ack("stranger", 0, 0) is False
    assert src.ack("plant", 1, 0) is False
    assert src.done == -1 and src.missing() == [("recorder", 0)]
    assert src.ack("recorder", 0, 0) is True
    assert src.done == 0
    for who in sorted(MEMBERS):  # an ack of a finished tick changes nothing
        assert src.ack(*who, 0) is False
    assert src.done == 0 and src.grant == 2


def test_one_ack_stands_for_every_tick_before_it() -> None:
    src = LockstepSource(MEMBERS, last=10, window=4)
    *first, final = sorted(MEMBERS)
    for who in first:
        assert src.ack(*who, 3) is False  # the last member has acknowledged nothing yet
    assert src.ack(*final, 2) is True  # ticks 0..2 by everyone
    assert src.done == 2 and src.grant == 6 and src.missing() == [final]
    assert src.ack(*final, 3) is True
    assert src.done == 3 and src.missing() == sorted(MEMBERS)


def test_an_ack_of_a_tick_not_granted_is_ignored() -> None:
    """Nobody can have finished a tick the source has not granted: a forged or corrupt ack beyond
    the grant must not skip ticks (with cumulative acks it would stand for all of them)."""
    src = LockstepSource(frozenset({("recorder", 0)}), last=100, window=4)
    assert src.grant == 3
    assert src.ack("recorder", 0, 4) is False
    assert src.ack("recorder", 0, 100) is False
    assert src.done == -1 and src.grant == 3
    assert src.ack("recorder", 0, 3) is True  # the granted ticks still count
    assert src.done == 3 and src.grant == 7


def test_source_grant_never_passes_the_last_tick() -> None:
    src = LockstepSource(MEMBERS, last=2, window=8)
    assert src.grant == 2
    for k in range(3):
        for who in sorted(MEMBERS):
            src.ack(*who, k)
    assert src.finished and src.grant == 2


def test_source_rejects_an_empty_window() -> None:
    with pytest.raises(ValueError, match="window"):
        LockstepSource(MEMBERS, last=10, window=0)


# --------------------------------------------------------------------------- LockstepClock
@pytest.mark.asyncio
async def test_lockstep_clock_waits_for_its_grant() -> None:
    clock = LockstepClock()
    assert clock.granted == -1
    waiter = asyncio.create_task(clock.wait_for(2))
    await asyncio.sleep(0)
    clock.grant(1)
    await asyncio.sleep(0)
    assert not waiter.done()  # 1 < 2: still waiting
    clock.grant(2)
    assert await asyncio.wait_for(waiter, WAIT) == 0.0
    assert clock.granted == 2


@pytest.mark.asyncio
async def test_lockstep_clock_returns_at_once_for_granted_ticks_and_never_goes_back() -> None:
    clock = LockstepClock()
    clock.grant(5)
    clock.grant(3)  # older grants (reordered Tick messages) are ignored
    assert clock.granted == 5
    for k in range(6):
        assert await asyncio.wait_for(clock.wait_for(k), WAIT) == 0.0


@pytest.mark.asyncio
async def test_lockstep_clock_releases_every_waiter_up_to_the_grant() -> None:
    clock = LockstepClock()
    waiters = {k: asyncio.create_task(clock.wait_for(k)) for k in range(6)}
    await asyncio.sleep(0)
    clock.grant(3)
    await asyncio.wait_for(asyncio.gather(*(waiters[k] for k in range(4))), WAIT)
    for _ in range(3):  # give the others every chance to (wrongly) wake
        await asyncio.sleep(0)
    assert not waiters[4].done() and not waiters[5].done()
    clock.grant(5)
    await asyncio.wait_for(asyncio.gather(*waiters.values()), WAIT)


# --------------------------------------------------------------------------- RealtimeClock
class FakeMonotonic:
    """A monotonic clock [s] the test sets; each reading can also advance it by a fixed step."""

    def __init__(self, now: float = 0.0, step: float = 0.0):
        self.now = now
        self.step = step
        self.reads = 0

    def __call__(self) -> float:
        self.reads += 1
        value = self.now
        self.now += self.step
        return value


@pytest.mark.asyncio
async def test_realtime_clock_does_not_sleep_for_ticks_already_due() -> None:
    # period and instants exactly representable in binary, so "exactly one period late" is exact
    fake = FakeMonotonic(now=1.0)
    slept: list[float] = []

    async def sleep(d: float) -> None:  # counted, not timed: a busy machine cannot fail a count
        slept.append(d)

    clock = RealtimeClock(period=0.25, start=0.0, monotonic=fake, sleep=sleep)
    lateness = [await clock.wait_for(k) for k in range(5)]  # due at 0, 0.25, 0.5, 0.75, 1.0; now is 1.0
    assert slept == []
    assert lateness == [1.0, 0.75, 0.5, 0.25, 0.0]
    assert clock.late == 3  # one period late (tick 3) is not "more than one period late"


@pytest.mark.asyncio
async def test_realtime_clock_counts_ticks_more_than_one_period_late() -> None:
    fake = FakeMonotonic()
    period = 0.01
    clock = RealtimeClock(period=period, start=0.0, monotonic=fake)
    # (tick, the clock's reading when the tick is asked for) -> expected lateness [s], late?
    cases = [(0, 0.0, 0.0, False), (1, 0.0105, 0.0005, False), (2, 0.0299, 0.0099, False),
             (3, 0.0500, 0.0200, True), (4, 0.0650, 0.0250, True), (10, 0.1050, 0.0050, False)]
    for n, (k, now, lateness, late) in enumerate(cases):
        fake.now = now
        before = clock.late
        assert await clock.wait_for(k) == pytest.approx(lateness, abs=1e-12)
        assert clock.late - before == int(late), f"tick {k}"
    assert clock.late == 2


@pytest.mark.asyncio
async def test_realtime_clock_sleeps_until_a_future_tick_then_reports_lateness() -> None:
    # the first reading says tick 1 is 4 ms away; the second (after the sleep) that it started 1 ms late
    readings = iter([0.006, 0.011])
    clock = RealtimeClock(period=0.01, start=0.0, monotonic=lambda: next(readings))
    t0 = time.monotonic()
    lateness = await asyncio.wait_for(clock.wait_for(1), WAIT)
    slept = time.monotonic() - t0
    assert lateness == pytest.approx(0.001, abs=1e-12)
    assert 0.004 - 0.001 <= slept < 0.5  # it really slept the 4 ms the fake clock asked for
    assert clock.late == 0


@pytest.mark.asyncio
async def test_realtime_clock_never_starts_a_tick_before_its_instant_when_the_loop_wakes_early() -> None:
    # uvloop's millisecond timers can fire up to about 1 ms early (tether/evloop.py): the rest is slept
    # again, never less than a grain (a shorter sleep would be rounded to none and spun on)
    fake = FakeMonotonic(now=0.008)
    asked: list[float] = []
    early = iter([0.0012, 0.0006, 0.0])  # how early each sleep ends

    async def sleep(d: float) -> None:
        asked.append(d)
        fake.now += d - next(early)

    clock = RealtimeClock(period=0.01, start=0.0, monotonic=fake, sleep=sleep)
    lateness = await clock.wait_for(1)  # due at 0.010
    assert asked == pytest.approx([0.002, 0.0012, TIMER_GRAIN])
    assert fake.now >= 0.010 and lateness == pytest.approx(0.0004)
    assert clock.late == 0


@pytest.mark.asyncio
async def test_realtime_clock_sleeps_once_when_the_loop_wakes_on_time() -> None:
    fake = FakeMonotonic(now=0.003)
    asked: list[float] = []

    async def sleep(d: float) -> None:
        asked.append(d)
        fake.now += d + 0.0002  # asyncio's own loop: late, never early

    clock = RealtimeClock(period=0.01, start=0.0, monotonic=fake, sleep=sleep)
    assert await clock.wait_for(1) == pytest.approx(0.0002)
    assert asked == pytest.approx([0.007])


@pytest.mark.asyncio
async def test_realtime_clock_schedule_is_start_plus_k_periods() -> None:
    fake = FakeMonotonic(now=50.0)
    clock = RealtimeClock(period=0.02, start=50.0, monotonic=fake)
    for k in range(501):
        fake.now = 50.0 + k * 0.02 + 0.03  # every tick asked for 30 ms (1.5 periods) after its instant
        assert await clock.wait_for(k) == pytest.approx(0.03, abs=1e-9)
    assert clock.late == 501


# --------------------------------------------------------------------------- the Clock contract
def _clocks() -> list[Clock]:
    """One of each strategy; the real-time one on a fake monotonic clock at 100 s and a wall clock
    at 1000 s (so tick 0 at wall 1000 maps to monotonic 100)."""
    return [LockstepClock(), RealtimeClock(period=0.01, monotonic=lambda: 100.0, wall=lambda: 1000.0)]


@pytest.mark.parametrize("clock", _clocks(), ids=lambda c: c.kind)
def test_every_clock_keeps_the_contract(clock: Clock) -> None:
    """What a process asks of its clock, asked of each: the answers have the protocol's types, and
    each strategy is consistent with itself (what it refuses, what it joins, how it publishes)."""
    other = "realtime" if clock.kind == "lockstep" else "lockstep"
    clock.require(clock.kind, "never raised")
    with pytest.raises(ValueError, match="the other"):
        clock.require(other, "the other")
    qos, keep = clock.stream(None, 4)
    assert isinstance(qos, tp.StreamQos) and keep in (0, 5)
    assert clock.stream(None, 0)[1] == 0  # no window: nothing kept
    hook = clock.hook(print, print)
    assert (hook[0] is None) != (hook[1] is None)  # a relay runs in one place
    assert clock.join(None) is None
    assert clock.departed(lambda: frozenset({3})) in (frozenset(), frozenset({3}))
    assert clock.ago(math.nan) == 0.0
    assert isinstance(clock.begin(1000.0, 0.5), str)
    assert not clock.unstarted()
    assert clock.now() == 0.0  # tick 0 now, on either clock


def test_the_lockstep_clock_judges_no_input_by_its_timing() -> None:
    """A tick waits for its inputs: nothing is silent, gone, overdue or departed, no arrival
    is judged and no offset monitored; a relay runs on the loop and no run under way is joined."""
    clock = LockstepClock()
    src = Source("k", object, 1, last=10)
    src.gone = True
    assert clock.exact and not clock.silent(src, 5) and not clock.gone(src) and not clock.overdue(9.0, 1.0)
    assert clock.departed(lambda: frozenset({2})) == frozenset()
    assert clock.arrivals(lambda: 1.0) is None and clock.offsets(0.01) is None
    assert clock.join(lambda: 1.0) is None and clock.wall is None and clock.origin is None
    assert clock.hook(print, print) == (print, None)


def test_the_realtime_clock_maps_tick_0_and_judges_inputs_by_time() -> None:
    mono = [100.0]
    clock = RealtimeClock(period=0.01, monotonic=lambda: mono[0], wall=lambda: 1000.0, max_lag=MAX_LAG)
    assert clock.unstarted() and clock.origin is None and clock.now() == 0.0
    clock.begin(1000.5, phase=0.5)  # tick 0 half a second from now
    assert not clock.unstarted() and clock.origin == 100.5 and clock.start == pytest.approx(100.505)
    mono[0] = 101.0
    assert clock.now() == pytest.approx(0.5) and clock.reached(0.01) == 50
    assert clock.arrival(100.75) == pytest.approx(0.25) and clock.ago(100.75) == pytest.approx(0.25)
    assert clock.link_time(0.1) == pytest.approx(0.5)  # now, not the sample's time
    assert clock.overdue(0.3, 0.25) and not clock.overdue(0.2, 0.25)
    assert clock.departed(lambda: frozenset({2})) == frozenset({2})
    assert clock.offsets(0.01) is not None and clock.hook(print, print) == (None, print)
    assert not clock.exact and clock.max_lag == MAX_LAG
