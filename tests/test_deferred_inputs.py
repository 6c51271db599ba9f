"""Inputs that do not wake the event loop (``tether/node.py``), real time, over real Zenoh sessions
on loopback: a :class:`~tether.node.Node` (router session) and a client session that publishes.

* ``Node.subscribe(pattern, wake=False)`` (the recorder's wildcard streams): a sample that arrives
  wakes nobody; it waits, stamped with its arrival, until the per-period timer (``Node.pace``)
  wakes the loop, at most one period later; the source's gate then sees the stamped arrival, not
  the (later) drain;
* ``Node.quieten(src)`` (a plant's commands once it has started): the source's samples stop
  waking the loop from then on and are decoded at the next drain, none lost;
* lockstep ignores both: a tick waits for its inputs, so every sample must wake the loop.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest
import zenoh

from tether import handoff
from tether import ingress as ig
from tether import node as nd
from tether import transport as tp
from tether import wire
from tether.catalog import builtin_path
from tether.clock import LockstepClock, RealtimeClock

pytestmark = pytest.mark.asyncio

WAIT = 10.0


def state(sender: int, k: int, h: float) -> bytes:
    return wire.encode(wire.State(sender=sender, seq=k, k=k, t=k * h, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0]))


async def until(ready: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


@asynccontextmanager
async def live(role: str, clock: RealtimeClock | LockstepClock,
               **more: Any) -> AsyncIterator[tuple[nd.Node, zenoh.Session]]:
    """A node of ``role`` on Section 4 around a router session on a fresh loopback port, and a client
    session connected to it (what the test publishes from); the node is closed at the end. ``more``:
    other :class:`~tether.node.NodeArgs` fields."""
    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    args = nd.NodeArgs(mission_path=builtin_path("section4"), role=role, node_id=0, clock=clock.kind,
                       zenoh=tp.ZenohSettings(mode="router", listen=(endpoint,), scouting_delay=0.0), **more)
    client = tp.ZenohSettings(mode="client", connect=(endpoint,), scouting_delay=0.0)
    async with tp.open_session(args.zenoh) as session, tp.open_session(client) as other:
        node = nd.Node(args, nd.load_mission(args.mission_path), session, clock)
        try:
            yield node, other
        finally:
            node.close()


def woke_nobody(node: nd.Node) -> bool:
    return not node.wakeup._event.is_set() and not node.wakeup._pending


H = nd.load_mission(builtin_path("section4")).dt


async def test_a_deferred_subscription_wakes_nobody_and_is_drained_within_a_period_at_its_arrival() -> None:
    clock = RealtimeClock(H)
    async with live("recorder", clock) as (node, other):
        keys = node.keys
        key = keys.topic("agent", 1, "state")
        seen: list[tuple[float, float]] = []  # (what the gate saw as arrival, the drain's now)

        def admit(msg: wire.State) -> str | None:
            seen.append((node.arrival(), clock.now()))
            return None

        src = node.source(key, wire.State, 1, subscribe=False, keep=False)
        src.admit = admit
        node.subscribe(f"tether/{keys.ns}/agent/*/state", wake=False)
        clock.begin(time.time())
        pub = tp.declare_publisher(other, key, tp.STATE)
        await tp.wait_for_subscribers(pub, WAIT)
        pub.put(state(1, 0, H))
        await until(lambda: len(node.deferred) == 1, "the sample in the deferred queue")
        assert woke_nobody(node)
        arrived = clock.now()
        pacer = asyncio.get_running_loop().create_task(node.pace())
        t0 = time.monotonic()
        assert await node.wakeup.wait(WAIT)  # the period's timer
        assert time.monotonic() - t0 < 1.0  # a period (10 ms) after the timer started, give or take a loaded machine
        await asyncio.sleep(0.2 * H)  # the drain comes later than the arrival
        node.drain()
        assert src.received == 1 and len(node.deferred) == 0
        (at, now), = seen
        assert at <= arrived + 1e-6 < now  # judged at its arrival, stamped in the callback
        pacer.cancel()
        pub.undeclare()


async def test_a_quietened_source_stops_waking_the_loop_and_loses_nothing() -> None:
    async with live("plant", RealtimeClock(H)) as (node, other):
        key = node.keys.topic("agent", 1, "cmd")
        src = node.source(key, wire.State, 1)
        pub = tp.declare_publisher(other, key, tp.COMMAND)
        await tp.wait_for_subscribers(pub, WAIT)
        pub.put(state(1, 0, H))
        assert await node.wakeup.wait(WAIT)  # before: each sample wakes the loop
        node.drain()
        assert src.received == 1
        node.quieten(src)
        for k in range(1, 4):
            pub.put(state(1, k, H))
        await until(lambda: len(node.inputs[key]) == 3, "three samples queued")
        assert woke_nobody(node)  # after
        node.drain()
        assert src.received == 4 and src.newest.k == 3
        pub.undeclare()


async def test_lockstep_ignores_both_every_sample_wakes_the_loop() -> None:
    async with live("recorder", LockstepClock()) as (node, other):
        keys = node.keys
        key = keys.topic("agent", 1, "state")
        src = node.source(key, wire.State, 1, subscribe=False)
        node.subscribe(f"tether/{keys.ns}/agent/*/state", wake=False)
        pub = tp.declare_publisher(other, key, tp.SYNC)
        await tp.wait_for_subscribers(pub, WAIT)
        pub.put(state(1, 0, H))
        assert await node.wakeup.wait(WAIT)
        node.drain()
        assert src.received == 1 and len(node.deferred) == 0
        pub.undeclare()


async def test_aligned_without_a_drain_reads_what_was_drained_and_lockstep_still_gets_its_tick() -> None:
    """``aligned(drain=False)`` (a caller that has just drained: a world reading its vehicles'
    commands one by one, an agent right after its real-time tick): real time, a sample still queued
    waits for the next drain; lockstep, a missing sample is still waited for (the wait drains)."""
    clock = RealtimeClock(H)
    async with live("agent", clock) as (node, _):
        clock.begin(time.time())
        key = node.keys.topic("agent", 1, "state")
        src = node.source(key, wire.State, 1, subscribe=False)
        queue: handoff.InputQueue[tp.Received] = handoff.InputQueue(8, None)
        node.inputs[key] = queue
        queue.put(tp.Received(key, state(1, 0, H), time.monotonic()))
        assert await node.aligned([src], 0, drain=False) == [None] and len(queue) == 1  # not drained
        got = await node.aligned([src], 0)
        assert got[0] is not None and got[0].k == 0 and len(queue) == 0
    async with live("agent", LockstepClock()) as (node, _):
        key = node.keys.topic("agent", 1, "state")
        src = node.source(key, wire.State, 1, subscribe=False)
        node.fifo.put(tp.Received(key, state(1, 0, H)))
        got = await node.sample(src, 0, drain=False)  # not held yet: the wait for it drains
        assert got.k == 0 and len(node.fifo) == 0


async def test_a_lockstep_tick_that_waits_sends_its_streams_kept_messages_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """A peer of a mesh can miss a stream's first samples for good (put before its subscription
    reached the publisher): a lockstep run stalled at tick 0. Here the subscriber comes after three
    samples were put, and answers only once it has tick 0; the node's tick waits for that answer and,
    after RESEND, sends its kept messages again (the last ``window + 1``), so both go on. A wait for
    anything else (the end's linger) sends nothing."""
    monkeypatch.setattr(nd, "RESEND", 0.2)
    async with live("agent", LockstepClock(), window=4, stall_timeout=6.0) as (node, other):
        keys = node.keys
        mine, theirs = keys.topic("agent", 1, "state"), keys.topic("agent", 2, "state")
        pub = node.publisher(mine, sender=1)
        src = node.source(theirs, wire.State, 2)
        for k in range(3):  # nobody subscribes yet: these go nowhere
            pub.send(wire.State, k, k * H, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0])
        heard: list[int] = []
        sub = other.declare_subscriber(mine, lambda s: heard.append(wire.decode(s.payload.to_bytes()).k))
        answer = tp.declare_publisher(other, theirs, tp.SYNC)

        async def answer_once_tick_0_is_heard() -> None:
            await until(lambda: 0 in heard, "tick 0 sent again")
            answer.put(state(2, 0, H))

        task = asyncio.create_task(answer_once_tick_0_is_heard())
        got = await node.sample(src, 0)
        await task
        assert got.k == 0 and node.resent >= 3 and sorted(set(heard)) == [0, 1, 2]
        for k in range(3, 10):  # more than the window: only the last window + 1 ticks are kept
            pub.send(wire.State, k, k * H, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0])
        assert pub.kept is not None and [k for k, _ in pub.kept] == [5, 6, 7, 8, 9] and node.resend("a test") == 5
        before = node.resent
        with pytest.raises(nd.Stalled):
            await node.until(lambda: False, 0.5, "nothing")  # no resend unless asked
        assert node.resent == before
        sub.undeclare()
        answer.undeclare()


async def test_a_copy_sent_again_does_not_enter_an_emulated_link_twice() -> None:
    """Lockstep, an input through an emulated link (``[netem]``): a copy of a tick the link has had
    (a resend after a stall) is counted apart (``Node.copies``, not a drop the run records) and not
    offered again, which would draw the link's random decisions anew and change the run."""
    from msgspec.structs import replace

    from netem.link import Channel
    from tether.netprofile import Bernoulli, LinkProfile, Network

    async with live("agent", LockstepClock()) as (node, _):
        m = replace(node.mission, netem=Network(default=LinkProfile(loss=Bernoulli(p=0.3))))
        channel = Channel.of(m, 2, 1)
        key = node.keys.topic("agent", 2, "state")
        node.source(key, wire.State, 2, channel=channel, subscribe=False)
        for k in (0, 1, 1, 0, 2):  # ticks 1 and 0 again: copies sent again
            node.fifo.put(tp.Received(key, state(2, k, H)))
        node.drain()
        assert channel.link.counts["offered"] == 3 and node.copies == 2 and node.receiver.drops == {}


async def test_copies_sent_again_leave_a_lockstep_links_statistics_as_without_the_stall() -> None:
    """Lockstep, a direct input: whether a peer resends after a stall depends on the machine's load
    (two runs at once on a busy machine), so the copies must not show in what a run records. A copy
    of a sample had is dropped and counted apart (``Node.copies``); one missed (its subscription
    came late) and sent again after newer ones is taken as if it had come in its turn. In real
    time the same arrivals are the link's duplicates and reordered samples, as before."""
    async with live("agent", LockstepClock()) as (node, _):
        key = node.keys.topic("agent", 2, "state")
        src = node.source(key, wire.State, 2, subscribe=False)
        for k in (1, 2, 3, 0, 1, 2, 3, 4):  # tick 0 missed, then the last window's ticks sent again
            node.fifo.put(tp.Received(key, state(2, k, H)))
        node.drain()
        assert (src.received, src.stale, src.duplicates, src.reordered) == (5, 0, 0, 0)
        assert node.copies == 3 and node.receiver.drops == {} and sorted(src.by_tick) == [0, 1, 2, 3, 4]
        assert src.newest.k == 4
    clock = RealtimeClock(H)
    async with live("agent", clock) as (node, _):
        clock.begin(time.time())
        key = node.keys.topic("agent", 2, "state")
        src = node.source(key, wire.State, 2, subscribe=False)
        for k in (1, 2, 3, 0, 1, 2, 3, 4):
            node.fifo.put(tp.Received(key, state(2, k, H), time.monotonic()))
        node.drain()
        assert (src.received, src.stale, src.duplicates, src.reordered) == (8, 4, 3, 1) and node.copies == 0


async def test_a_flood_of_deferred_samples_keeps_the_newest_and_counts_the_rest() -> None:
    """More samples within a period than the deferred queue holds: the oldest are dropped and
    counted as ``overflow`` (what the recorder writes into its run file's drop counts), the newest
    decoded, in order; said once in the log."""
    clock = RealtimeClock(H)
    async with live("recorder", clock) as (node, _):
        node.ingress.deferred = handoff.BoundedFifo(4)  # FIFO_CAPACITY's role, small
        key = node.keys.topic("agent", 1, "state")
        src = node.source(key, wire.State, 1, subscribe=False, keep=False)
        node.subscribe(f"tether/{node.keys.ns}/agent/*/state", wake=False)
        clock.begin(time.time())
        for k in range(6):
            node.deferred.put(tp.Received(key, state(1, k, H), time.monotonic()))
        node.drain()
        assert node.receiver.drops == {"overflow": 2}
        assert src.received == 4 and src.newest.k == 5 and src.stale == 0
        for k in range(6, 8):  # within capacity: nothing more counted
            node.deferred.put(tp.Received(key, state(1, k, H), time.monotonic()))
        node.drain()
        assert node.receiver.drops == {"overflow": 2} and src.received == 6


async def test_a_tap_runs_on_each_sample_its_failures_are_counted_and_it_stops_when_the_node_closes() -> None:
    """A source's ``tap`` gets each sample on Zenoh's thread; a tap that raises is logged and
    counted (``tap_error``), never raised into Zenoh. A tap already running when the node closes
    holds the close (``TapGuard``) until it leaves: nothing the node declared (the publishers a
    relay puts on) is undeclared under it, no tap starts once the close has begun, and none runs
    after it."""
    import threading

    tapped: list[tp.Received] = []
    fail = [False]
    inside, release = threading.Event(), threading.Event()

    def tap(rec: tp.Received) -> None:
        if rec.at == -1.0:  # the racing sample: stays inside until released
            inside.set()
            assert release.wait(WAIT), "the test never released the racing tap"
        if fail[0]:
            raise RuntimeError("a tap that fails")
        tapped.append(rec)

    async with live("agent", RealtimeClock(H)) as (node, other):
        key = node.keys.topic("plant", 1, "state")
        node.source(key, wire.State, 1, tap=tap)
        pub = tp.declare_publisher(other, key, tp.STATE)
        await tp.wait_for_subscribers(pub, WAIT)
        pub.put(state(1, 0, H))
        await until(lambda: len(tapped) == 1, "the tap's first sample")
        assert tapped[0].at == tapped[0].at  # stamped
        fail[0] = True
        pub.put(state(1, 1, H))
        await until(lambda: node.receiver.drops.get("tap_error") == 1, "the failing tap counted")
        assert len(node.inputs[key]) == 2  # both queued all the same
        fail[0] = False
        pub.undeclare()

        sink = ig._Tapped(node.inputs[key], tap, node.ingress)
        racing = threading.Thread(target=sink.put, args=(tp.Received(key, state(1, 2, H), -1.0),))
        racing.start()
        await until(inside.is_set, "the racing tap to run")
        closer = threading.Thread(target=node.close)
        closer.start()
        await until(lambda: node.ingress.taps.closed, "the close to begin")
        sink.put(tp.Received(key, state(1, 3, H), 0.0))  # the close has begun: queued, not tapped
        assert closer.is_alive() and node.ingress.declared, "the close undeclared under a running tap"
        release.set()
        await until(lambda: not closer.is_alive() and not racing.is_alive(), "the close to end")
        assert not node.ingress.declared
        assert [r.at for r in tapped[1:]] == [-1.0]  # the racing tap ran to its end; the later one never
        sink.put(tp.Received(key, state(1, 4, H), 0.0))  # after the close: the tap is not called
        assert len(tapped) == 2 and node.receiver.drops == {"tap_error": 1}


async def test_a_stopped_recorder_writes_the_samples_still_waiting_in_its_queues(tmp_path: Path) -> None:
    """The wildcard streams are drained up to a period after they arrive: a recorder stopped in
    between (the launcher ends a run the moment every vehicle has landed) decodes what waits before it
    writes the run file; it dropped it, and a vehicle's final LANDED was missing from the file."""
    import contextlib

    import numpy as np

    from recorder import node as recorder
    from tether.runfile import Run

    clock = RealtimeClock(H)
    out = tmp_path / "out"
    async with live("recorder", clock) as (node, other):
        run, on_stop = recorder.make(out, mcap=False)

        async def serving() -> None:  # as tether.node.serve runs a role: its helpers in a task group
            async with asyncio.TaskGroup() as tasks:
                node.tasks = tasks
                await run(node)

        task = asyncio.get_running_loop().create_task(serving())
        start = tp.declare_publisher(other, node.keys.start, tp.SYNC)
        await tp.wait_for_subscribers(start, WAIT)
        start.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=time.time() - 0.05)))
        await until(lambda: clock.origin is not None, "the recorder's start")
        await asyncio.sleep(0)  # the run's body goes on to its loop
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        m = node.mission
        aid = m.agent_ids[0]
        landed = wire.PlantState(sender=aid, seq=0, k=0, t=0.0, p=list(m.agent(aid).p0), vel=[0.0] * m.dim,
                                 a=[0.0] * m.dim, d=[0.0] * m.dim, mode=wire.LANDED)
        key = node.keys.topic("plant", aid, "state")
        node.deferred.put(tp.Received(key, wire.encode(landed), time.monotonic()))  # arrived, not yet drained
        on_stop(node)
    rec = Run.load(out)
    col = list(rec.agent_ids).index(aid)
    assert rec.safety.plant_mode[0, col] == wire.LANDED
    assert rec.runtime is not None, "a real-time recording without its runtime record"
    assert np.isfinite(rec.runtime.plant_p[0, col]).all()
