"""The recorder's process: hears every sample of a run and writes one run file (``run.npz``).

It subscribes to the leader's state, every agent's telemetry and every plant's state (lockstep with
the plants co-located: the leader's and every agent's records), and fills a
:class:`~tether.runfile.Run` indexed by tick. In lockstep it acknowledges tick k once it holds
every sample of k, so the clock never runs ahead of what is recorded. In real time it records
until every producer has sent its last tick or gone, or until it is stopped; the file is written
in both cases (a stopped run is marked ``complete = false``), with ``run.mcap`` beside it when the
Foxglove SDK is installed (``recorder/export.py``, ``docs/foxglove.md``). Meanwhile every sample it
takes goes to its journal (``journal.mcap``, ``recorder/journal.py``), flushed every second of wall
and of mission time, so that a recorder killed before it writes the run file leaves one that can be
rebuilt; the journal is removed once the run file is written and synced.

The same role serves two more uses (:func:`make`): ``live`` serves every tick over the Foxglove
WebSocket protocol while the run goes on (``tether run --live``, ``tether record --live``: a
:class:`Feed`, in this process, never in an agent's), and ``attach`` is the recorder of a deployed
swarm (``tether record``): a plain client outside the swarm, with no liveliness token and no
lockstep acknowledgements, that records until the run's last tick or until it is stopped, through
members leaving and coming back.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from recorder import journal as jr
from recorder.recording import Recording
from tether import gate, wire
from tether.node import Node, os_error
from tether.rejoin import Rejoin
from tether.runfile import Run

log = logging.getLogger("tether")

STOP_GRACE = 2.0
"""Real time: when every producer has left before the last tick, how long to wait for this
process's own stop signal before calling the run cut short [s]."""


class Feed:
    """The live view of a recording (``--live``): a Foxglove WebSocket server in the recorder's
    process, fed tick by tick from the run being filled (the same channels as ``run.mcap``,
    ``recorder.viz.Live``). A tick goes out once every sample of it is in, or, in real time, once
    :data:`LAG` newer ticks have been heard (its missing samples then go out as nulls)."""

    LAG = 5

    def __init__(self, rec: Recording, port: int, host: str = "127.0.0.1"):
        from recorder import viz  # the viz extra, only with --live

        self.rec = rec
        self.live = viz.Live(port=port, host=host, speed=0.0, mission=rec.mission)
        self.next = -1
        """The next tick to send (-1: none heard yet; a recorder that attaches late starts at the first heard)."""
        self.sent = 0
        self.cpu = 0.0
        """Ticks sent, and the CPU time spent sending them [s] (logged at the end: bench/recording.py)."""
        log.info("live view: ws://%s:%d (Foxglove: Open connection, Foxglove WebSocket)", host, self.live.port)

    def step(self, flush: bool = False) -> None:
        """Send every tick that is ready (O(1) when none is); ``flush``: every tick heard (the end)."""
        rec = self.rec
        if rec.newest < 0:
            return
        if self.next < 0:
            self.next = rec.oldest
        count, expected, newest = rec.count, rec.expected, rec.newest
        run, events = rec.run, rec.events
        t0 = time.process_time()
        while self.next <= newest and (flush or count[self.next] >= expected or newest - self.next >= self.LAG):
            self.live.tick(run, self.next, events=events, plant_events=rec.plant_events)
            self.next += 1
            self.sent += 1
        self.cpu += time.process_time() - t0

    def close(self) -> None:
        self.step(flush=True)
        self.live.finish(self.rec.run)
        self.live.close()
        log.info("live view: sent %d ticks in %.3f s of CPU", self.sent, self.cpu)


def _drops(node: Node) -> dict[str, int]:
    """What the run file's ``recorder_drops`` says: the receiver's drops by reason, and (``copy``)
    the lockstep copies of samples already had, a peer's resend after a stall or a replay: the same
    bytes, so the same answer (:attr:`tether.node.Node.copies`)."""
    return {**node.receiver.drops, "copy": node.copies} if node.copies else dict(node.receiver.drops)


def _journaled(journal: jr.Journal, take: Callable[[Any], None]) -> Callable[[Any], None]:
    """``take`` after journaling its message (a sample that passed its gate)."""

    def both(msg: Any) -> None:
        journal.add(msg)
        take(msg)

    return both


async def _keep(node: Node, journal: jr.Journal) -> None:
    """Flush the journal every :data:`recorder.journal.FLUSH_PERIOD` (with the drop counts), then
    ``fsync`` it on a worker thread, until it is closed."""
    while not journal.closed:
        await asyncio.sleep(jr.FLUSH_PERIOD)
        journal.drops(_drops(node))
        journal.flush()
        if journal.error is not None:
            log.error("journal: %s; recording goes on without it (the run file is written at the end)",
                      os_error(journal.error))
            return
        await asyncio.to_thread(journal.sync)


def _leader_records(node: Node, rec: Recording, leader_gate: Callable[[wire.State], str | None],
                    journal: jr.Journal | None = None) -> Callable[[wire.Record], None]:
    """What the recorder does with the leader's :class:`~tether.wire.Record` (lockstep, plants
    co-located): each state passes the plausibility gate as one that came alone would, then is
    recorded as if it had (and journaled, the record of the states that passed)."""

    def take(msg: wire.Record) -> None:
        states = []
        for s in msg.leader:
            why = leader_gate(s)
            if why is not None:
                node.count_drop("gate")
                log.warning("record of the leader: state of tick %d rejected (%s)", s.k, why)
                continue
            states.append(s)
        if journal is not None and states:
            journal.add(msg if len(states) == len(msg.leader) else msgspec.structs.replace(msg, leader=states))
        for s in states:
            rec.leader(s)

    return take


def _records(node: Node, rec: Recording, plant_gate: Callable[[wire.PlantState], str | None],
             journal: jr.Journal | None = None) -> Callable[[wire.Record], None]:
    """What the recorder does with one agent's :class:`~tether.wire.Record` (its plant co-located):
    each plant sample passes the plausibility gate as a plant's own would, then both streams are
    recorded as if they had come alone. (Records are lockstep's alone: a copy of a record had, a
    peer's resend after a stall or a replay, never gets here (:attr:`tether.node.Node.copies`,
    ``copy`` in the run file); one missed and sent again after newer ones does, and is recorded.) A record that was lost
    or dropped leaves its ticks short of samples, which the run file's counts show."""

    def take(msg: wire.Record) -> None:
        plants = []
        for p in msg.plant:
            why = plant_gate(p)
            if why is not None:
                node.count_drop("gate")
                log.warning("record of agent %d: plant sample of tick %d rejected (%s)", msg.sender, p.k, why)
                continue
            plants.append(p)
        if journal is not None:
            journal.add(msg if len(plants) == len(msg.plant) else msgspec.structs.replace(msg, plant=plants))
        rec.plants(plants)
        rec.telemetries(msg.telemetry)

    return take


def _save(node: Node, rec: Recording, journal: jr.Journal | None, complete: bool) -> None:
    """Write the run file (synced, when a journal stands for it meanwhile), then remove the journal.
    A failed write leaves the journal flushed and closed: the run can be rebuilt from it."""
    if journal is None:
        rec.save(complete=complete, drops=_drops(node))
        return
    journal.drops(_drops(node))
    journal.flush()
    try:
        rec.save(complete=complete, drops=_drops(node), sync=True)
    except OSError:
        journal.finish()
        raise
    log.info("journal: %d messages, %d bytes, %d flushes; fsync %d times, %.3f s in all, longest %.3f s",
             journal.messages, journal.size(), journal.flushes, journal.syncs, journal.sync_seconds,
             journal.sync_max)
    journal.discard()


class Recorder:
    """The recorder role writing to ``out`` (:meth:`run`), and its stop hook (:meth:`on_stop`:
    writes a partial file).

    ``live``: also serve the run over the Foxglove WebSocket protocol on this port (:class:`Feed`).
    ``attach``: record a swarm from outside it (``tether record``): no token, no acknowledgements,
    records until the last tick or a stop, whoever comes and goes. ``mcap``: write ``run.mcap``."""

    def __init__(self, out: Path, live: int | None = None, attach: bool = False, mcap: bool = True,
                 live_host: str = "127.0.0.1") -> None:
        self.out, self.live, self.attach, self.mcap, self.live_host = out, live, attach, mcap, live_host
        self.rec: Recording | None = None
        """The run being filled, once :meth:`run` began."""
        self.journal: jr.Journal | None = None
        self.feed: Feed | None = None
        """The live view, while it runs."""
        self.started = False
        """The run has started (:meth:`tether.node.Node.ready` returned)."""

    async def run(self, node: Node) -> None:
        out, attach, live = self.out, self.attach, self.live
        m, keys = node.mission, node.keys
        rec = self.rec = Recording(node, out, mcap=self.mcap)
        out.mkdir(parents=True, exist_ok=True)
        journal = self.journal = jr.Journal.create(out, jr.Header(
            mission=m.name, mission_text=rec.run.meta.mission_text or "", namespace=keys.ns, duration=m.duration,
            lockstep=node.clock.kind == "lockstep", started_ns=time.time_ns()))
        keeper = asyncio.get_running_loop().create_task(_keep(node, journal), name="journal")
        # three wildcard subscriptions, not 2N+1: each subscription costs a callback thread woken
        # per sample (measured: half the recorder's CPU, docs/benchmarks.md)
        # the record passes the same plausibility gate as the agents (tether/gate.py): a forged far-off
        # sample for a coming tick must not take the real one's place in the file
        # real time: a sample is judged at its arrival (the wildcard streams below are drained up to
        # a period later: they do not wake the loop)
        now = node.clock.arrivals(node.arrival)
        # a recorder restarted mid-run joins it from the leader's samples (tether/rejoin.py); before
        # its start, samples are not recorded
        rejoin = Rejoin(node.clock.wall)
        leader_gate = gate.for_sender(m, m.leader.id, now).check
        colocated = node.args.colocate
        if colocated:
            # lockstep, plants co-located: the leader's states come in its records too (one wake-up
            # a record, not one a tick; leader/node.py)
            node.source(keys.topic("leader", m.leader.id, "record"), wire.Record, m.leader.id, keep=False,
                        on_message=_leader_records(node, rec, leader_gate, journal))
        else:
            def admit_leader(msg: wire.State) -> str | None:
                if node.clock.unstarted():
                    rejoin.observe(msg.k, msg.t)
                    return "before start"
                return leader_gate(msg)

            leader = node.source(keys.topic("leader", m.leader.id, "state"), wire.State, m.leader.id,
                                 on_message=_journaled(journal, rec.leader), keep=False)
            leader.admit = admit_leader
        producers = [("leader", m.leader.id)]
        for aid in m.agent_ids:
            plant_gate = gate.for_sender(m, aid, now).check
            if colocated:  # lockstep, plants inside their agents: both streams in the agent's records
                src = node.source(keys.topic("agent", aid, "record"), wire.Record, aid, subscribe=False, keep=False)
                src.on_message = _records(node, rec, plant_gate, journal)
                producers.append(("agent", aid))
                continue
            node.source(keys.topic("agent", aid, "telemetry"), wire.Telemetry, aid,
                        on_message=_journaled(journal, rec.telemetry), subscribe=False, keep=False)
            plant = node.source(keys.topic("plant", aid, "state"), wire.PlantState, aid,
                                on_message=_journaled(journal, rec.plant), subscribe=False, keep=False)
            plant.admit = plant_gate
            producers += [("agent", aid), ("plant", aid)]
        if m.payload is not None:
            node.source(keys.topic("world", 0, "state"), wire.WorldState, 0, on_message=_journaled(journal, rec.world),
                        keep=False)
            producers.append(("world", 0))
        if colocated:
            node.subscribe(f"tether/{keys.ns}/agent/*/record")
        else:
            # real time: a tick's samples are recorded in one drain a period at most after they
            # arrive, not one wake-up each (the recorder reacts to none of them)
            node.subscribe(f"tether/{keys.ns}/agent/*/telemetry", wake=False)
            node.subscribe(f"tether/{keys.ns}/plant/*/state", wake=False)
        ack = None if attach else node.publisher(keys.topic("recorder", node.args.node_id, "ack"))
        seen: set[str] = set()
        gone: set[str] = set()
        wanted = {keys.token(r, i) for r, i in producers}
        for r, i in producers:
            node.watch(r, i)
        feed = None
        if live is not None:
            try:
                feed = self.feed = Feed(rec, live, self.live_host)
            except Exception as exc:  # noqa: BLE001 - the port was taken since it was checked: record anyway
                log.error("--live: no live view on port %d (%s: %s); recording without it",
                          live, type(exc).__name__, exc)
        if attach:
            log.info("waiting for namespace %r to start (Ctrl-C: stop; nothing is written before a sample)", keys.ns)
            await node.ready(token=False,
                             rejoin=lambda: rec.first if rec.first is not None else rejoin.epoch())
        else:
            await node.ready(rejoin=rejoin.epoch)
        rec.cpu_ready = time.process_time()
        wall = node.clock.wall
        if wall is not None:  # real time: tick 0's Unix time, for lining the run up with other logs
            rec.run.meta.epoch_ns = round((wall() - node.mission_time()) * 1e9)
        self.started = True
        if node.rejoined and not attach:
            log.warning("rejoined a run under way at t = %.2f s (start instant from %d samples of the leader): "
                        "the ticks before are missing from the run file", node.mission_time(), rejoin.samples)
        last = m.steps
        if node.clock.exact:  # the clock source waits for this process's acknowledgements
            for k in range(last + 1):
                await node.until(lambda: rec.count[k] >= rec.expected, node.args.stall_timeout,
                                 lambda: f"every sample of tick {k} (have {rec.count[k]} of {rec.expected}; "
                                         f"missing: {rec.missing(k)})")
                # one acknowledgement for the ticks completed together (an agent's record brings
                # several): it stands for every tick up to k. The next tick is never complete beyond
                # the clock's grant, so the clock hears of each grant's ticks.
                if ack is not None and (k == last or rec.count[k + 1] < rec.expected):
                    ack.send(wire.Ack, k, k * m.dt, role="recorder")
                if feed is not None:
                    feed.step()
            if ack is not None:
                log.info("lockstep: %d acknowledgements for %d ticks", ack.seq, last + 1)
        else:
            if feed is not None and node.tasks is not None:
                async def follow(f: Feed) -> None:
                    while True:
                        await asyncio.sleep(m.dt)
                        f.step()

                node.tasks.create_task(follow(feed), name="live view")

            def finished() -> bool:
                for key, alive in node.token_log:
                    (seen if alive else gone).add(key)
                node.token_log.clear()
                if rec.count[last] >= rec.expected:
                    return True
                # every producer away at once before the end (a router restarting takes them all, and
                # gives them back; members of a deployed swarm come and go): wait for them until the
                # mission's end on this clock
                if not (seen >= wanted and all(node.alive.get(key) is False for key in wanted)):
                    return False
                return node.mission_time() >= m.duration

            async def poke() -> None:  # re-check while nothing arrives (every producer away)
                while True:
                    await asyncio.sleep(0.5)
                    node.wakeup.notify()

            poker = asyncio.get_running_loop().create_task(poke())
            try:
                await node.until(finished, None, "the end of the run")
            finally:
                poker.cancel()
        complete = bool(np.all(rec.count >= rec.expected))
        if feed is not None:
            self.feed = None
            feed.close()
        keeper.cancel()
        _save(node, rec, journal, complete)
        if rec.count[last] == 0 and not attach and node.mission_time() < m.duration:
            # the producers may have left because the run is being stopped (Ctrl-C): then this
            # process's own stop follows within moments, and ends it as stopped, not failed
            try:
                async with asyncio.timeout(STOP_GRACE):
                    await node.stop.wait()
                    await asyncio.Event().wait()  # stopping: serve() cancels this task (exit 143)
            except TimeoutError:
                pass
            raise RuntimeError("every producer left before the last tick: the run was cut short "
                               f"(recorded {int(rec.count.sum())} of {rec.expected * len(rec.count)} samples)")

    def on_stop(self, node: Node) -> None:
        """After a stop: write what was recorded (a partial run file), unless it was written."""
        out, attach = self.out, self.attach
        feed, self.feed = self.feed, None
        if feed is not None:
            try:
                feed.close()
            except Exception as exc:  # noqa: BLE001 - the files matter more than the live view
                log.warning("live view: %s: %s", type(exc).__name__, exc)
        rec, journal = self.rec, self.journal
        if rec is None or rec.saved or rec.failed is not None:
            return
        if attach and not rec.count.any():
            log.warning("stopped before any sample of namespace %r was heard: no run file written", node.keys.ns)
            if journal is not None:
                journal.discard()
            return
        if not self.started:  # stopped before any start: another process's file stays
            log.warning("stopped before the run started: no run file written")
            if journal is not None:
                journal.discard()
            return
        # what has arrived waits in the input queues until the next drain (the wildcard streams up to a
        # period): decoded into the file, not dropped with the process (a vehicle's LANDED, the moment
        # before the launcher stops the run, was lost so)
        try:
            node.drain()
        except Exception:  # noqa: BLE001 - the file matters more than the last samples
            log.exception("stopped: the last drain failed; writing what was decoded before it")
        log.info("stopped: writing %s and run.mcap (%d of %d samples)", out / "run.npz", int(rec.count.sum()),
                 rec.expected * len(rec.count))
        _save(node, rec, journal, complete=False)


def make(out: Path, live: int | None = None, attach: bool = False, mcap: bool = True,
         live_host: str = "127.0.0.1") -> tuple[Callable[[Node], Awaitable[None]], Callable[[Node], None]]:
    """The recorder role writing to ``out``, and its stop hook (:class:`Recorder`'s arguments)."""
    recorder = Recorder(out, live, attach, mcap, live_host)
    return recorder.run, recorder.on_stop
