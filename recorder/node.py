"""The recorder's process: hears every sample of a run and writes one run file (``run.npz``).

It subscribes to the leader's state, every agent's telemetry and every plant's state (lockstep with
the plants co-located: the leader's and every agent's records), and fills a
:class:`~tether.runfile.Run` indexed by tick. In lockstep it acknowledges tick k once it holds
every sample of k, so the clock never runs ahead of what is recorded. In real time it records
until every producer has sent its last tick or gone, or until it is stopped; the file is written
in both cases (a stopped run is marked ``complete = false``), with ``run.mcap`` beside it when the
Foxglove SDK is installed (``recorder/export.py``, ``docs/foxglove.md``). Meanwhile every sample it
takes goes to its journal (``journal.mcap``, ``recorder/journal.py``), flushed every second, so that
a recorder killed before it writes the run file leaves one that can be rebuilt; the journal is
removed once the run file is written and synced.

The same role serves two more uses (:func:`make`): ``live`` serves every tick over the Foxglove
WebSocket protocol while the run goes on (``tether run --live``, ``tether record --live``: a
:class:`Feed`, in this process, never in an agent's), and ``attach`` is the recorder of a deployed
swarm (``tether record``): a plain client outside the swarm, with no liveliness token and no
lockstep acknowledgements, that records until the run's last tick or until it is stopped, through
members leaving and coming back.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Awaitable, Callable
from itertools import chain
from operator import attrgetter
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from recorder import journal as jr
from recorder.export import mcap_beside
from tether import gate, jsonout, wire
from tether.mission import Mission
from tether.node import Node, os_error
from tether.rejoin import Rejoin
from tether.runfile import ClockRecord, DropCounts, Links, PlantRecord, Run, RunMeta, RuntimeRecord, Source

log = logging.getLogger("tether")

STOP_GRACE = 2.0
"""Real time: when every producer has left before the last tick, how long to wait for this
process's own stop signal before calling the run cut short [s]."""


_PLANT_VECTORS = attrgetter("p", "vel", "a", "d")
_TELEMETRY_VECTORS = attrgetter("p", "vel", "a", "u", "xi", "zeta", "kp", "kv")


def _block(msgs: list[Any], vectors: attrgetter, dim: int) -> list[np.ndarray]:
    """Each of the ``vectors`` of ``msgs`` as one array (ticks, dim), from a single pass over the
    floats (converting the nested lists one series at a time cost twice as much). The messages are
    the receiver's: :class:`tether.wire.Receiver` checked every vector's size (a total that differs
    raises ValueError here all the same)."""
    rows = [vectors(msg) for msg in msgs]
    every = np.fromiter(chain.from_iterable(chain.from_iterable(rows)), float)
    return list(np.moveaxis(every.reshape(len(msgs), len(rows[0]), dim), 1, 0))


@dataclasses.dataclass(frozen=True)
class RecordingContext:
    """What the recorder's bookkeeping needs of its process (a :class:`~tether.node.Node` gives the
    same; a journal's replay gives this)."""

    mission: Mission
    lockstep: bool
    namespace: str
    mission_text: str
    arrived_ago: Callable[[], float] = lambda: 0.0
    """How long ago the sample being taken arrived [s] (the epoch hint of a recorder attaching live)."""


class Recording:
    """The run being filled, sample by sample (pure bookkeeping, no I/O until :meth:`save`)."""

    def __init__(self, node: Node | RecordingContext, out: Path, mcap: bool = True):
        m = node.mission
        if isinstance(node, RecordingContext):
            ctx = node
        else:
            ctx = RecordingContext(mission=m, lockstep=node.clock.kind == "lockstep", namespace=node.keys.ns,
                                   mission_text=node.args.mission_path.read_text(), arrived_ago=node.arrived_ago)
        self.arrived_ago = ctx.arrived_ago
        self.mcap = mcap
        """Write ``run.mcap`` beside ``run.npz`` (``--no-mcap``: not, e.g. to measure its cost)."""
        self.mission = m
        self.out = out
        self.col = {aid: i for i, aid in enumerate(m.agent_ids)}
        n, d, T = m.n, m.dim, m.steps + 1
        self.degree = {a.id: sum(1 for e in m.edges if e.dst == a.id) for a in m.agents}
        width = max(self.degree.values())
        source: Source = "runtime-lockstep" if ctx.lockstep else "runtime-realtime"
        meta = RunMeta(mission=m.name, source=source, law=m.law.kind, rate=m.rate,
                       steps=m.steps, seed=m.seed, namespace=ctx.namespace, mission_text=ctx.mission_text)
        self.run = Run.empty(T, m.agent_ids, d, meta)
        self.run.t[:] = np.arange(T) * m.dt
        self.rt = self.run.runtime = RuntimeRecord.empty(T, n, d)
        """The run's runtime record (``run.runtime``, never None here)."""
        self.lk = self.run.links = Links.empty(T, n, width)
        """The run's link statistics (``run.links``, never None here)."""
        silent, delivery, p50, p99 = self.lk.silent, self.lk.delivery, self.lk.age_p50, self.lk.age_p99
        if silent is None or delivery is None or p50 is None or p99 is None:
            raise AssertionError("Links.empty fills every per-tick field")
        self.silent, self.delivery, self.age_p50, self.age_p99 = silent, delivery, p50, p99
        """The link series that are optional in a run file but always recorded here."""
        self.netem: list[dict] = []
        """Link decisions, when the mission logs them (written to ``netem.jsonl``)."""
        self.world_series: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        """The payload's series in ``run.plant`` (position, velocity, tension, slack events), when there is one."""
        if m.payload is not None:
            pp, pv = np.full((T, 3), np.nan), np.full((T, 3), np.nan)
            tension, slack = np.full((T, n), np.nan), np.full((T, n), np.nan)
            self.run.plant = PlantRecord(payload_p=pp, payload_v=pv, tension=tension, slack_events=slack)
            self.world_series = pp, pv, tension, slack
        self.events: list[wire.SafetyEvent] = []
        """Mode changes, as the agents' telemetry reports them."""
        self.plant_events: list[wire.SafetyEvent] = []
        """The plants' watchdogs' events, as their states report them."""
        self.clock: ClockRecord | None = None
        """Real time: the agents' per-link clock-offset bounds (slots: the plant and the in-neighbours)."""
        self.clock_slots: list[dict[tuple[str, int], int]] = [{} for _ in range(n)]
        if not ctx.lockstep:
            self.clock = self.run.clock = ClockRecord.empty(T, n, width + 1)
        self.gate: list[tuple[int, dict[str, int]]] = [(-1, {}) for _ in range(n)]
        """Per agent: the newest telemetry's tick and its gate rejections since start, by reason."""
        self.count = np.zeros(T, dtype=np.int64)
        self.expected = 1 + 2 * n + (m.payload is not None)
        self.have = np.zeros((T, self.expected), dtype=bool)
        """Which sample of each tick is in: column 0 the leader's, 1 .. n the plants', n+1 .. 2n the
        agents' telemetry, 2n+1 the world's. A tick's count counts each once, so that a sample heard
        twice (a replay) cannot stand in for another that is missing."""
        self.duplicates = 0
        """Samples not recorded because their tick already held one from their producer (the first is kept)."""
        self.saved = False
        self.failed: OSError | None = None
        """Why :meth:`save` could not write the run file, if it could not."""
        self.first: float | None = None
        """The swarm's epoch as inferred from the first telemetry heard (:meth:`Node.ready`'s hint)."""
        self.cpu_ready = 0.0
        """The process's CPU time when the run started (its start-up before it) [s]."""
        self.oldest = -1
        """The first tick of which a sample was recorded (-1: none yet)."""
        self.newest = -1
        """The newest tick of which a sample was recorded."""

    def _take(self, k: int, slot: int) -> bool:
        """Whether the sample of tick ``k`` in ``slot`` (see :attr:`have`) is the first heard; if so it is counted."""
        if self.have[k, slot]:
            self.duplicates += 1
            return False
        self.have[k, slot] = True
        self.count[k] += 1
        return True

    def missing(self, k: int) -> str:
        """The samples of tick ``k`` not in yet, named by producer (for a stall report)."""
        ids = self.mission.agent_ids
        names = [f"leader {self.mission.leader.id}", *(f"plant {i}" for i in ids),
                 *(f"telemetry of agent {i}" for i in ids), "world"][:self.expected]
        gone = [name for name, got in zip(names, self.have[k]) if not got]
        return ", ".join(gone[:8]) + (f" and {len(gone) - 8} more" if len(gone) > 8 else "")

    def _heard(self, k: int) -> None:
        if k > self.newest:
            self.newest = k
        if self.oldest < 0 or k < self.oldest:
            self.oldest = k

    def leader(self, msg: wire.State) -> None:
        if 0 <= msg.k < len(self.count) and self._take(msg.k, 0):
            r = self.run
            r.leader_p[msg.k], r.leader_v[msg.k], r.leader_a[msg.k] = msg.p, msg.vel, msg.a
            self._heard(msg.k)

    def plant(self, msg: wire.PlantState) -> None:
        if 0 <= msg.k < len(self.count) and self._take(msg.k, 1 + self.col[msg.sender]):
            i, rt = self.col[msg.sender], self.rt
            rt.plant_p[msg.k, i], rt.plant_v[msg.k, i], rt.plant_a[msg.k, i] = msg.p, msg.vel, msg.a
            self.run.d[msg.k, i] = msg.d
            self.run.safety.plant_mode[msg.k, i] = msg.mode
            self.plant_events.extend(msg.events)
            self._heard(msg.k)

    def plants(self, msgs: list[wire.PlantState]) -> None:
        """One plant's samples of consecutive ticks (a :class:`~tether.wire.Record`'s, gated): one
        assignment per series when none of their ticks is recorded yet, else :meth:`plant` for each."""
        ks = self._span(msgs, 1)
        if ks is None:
            for msg in msgs:
                self.plant(msg)
            return
        i, rt = self.col[msgs[0].sender], self.rt
        rt.plant_p[ks, i], rt.plant_v[ks, i], rt.plant_a[ks, i], self.run.d[ks, i] = \
            _block(msgs, _PLANT_VECTORS, self.mission.dim)
        self.run.safety.plant_mode[ks, i] = [msg.mode for msg in msgs]
        for msg in msgs:
            self.plant_events.extend(msg.events)

    def telemetries(self, msgs: list[wire.Telemetry]) -> None:
        """One agent's telemetry of consecutive ticks (a :class:`~tether.wire.Record`'s): as
        :meth:`telemetry` for each, in one assignment per series when none of their ticks is
        recorded yet, each has as many links, and nothing per sample is still to be learnt (the
        epoch hint, real time's clock offsets); else :meth:`telemetry` for each."""
        ks = None
        if msgs and self.first is not None and self.clock is None \
                and all(len(msg.links) == len(msgs[0].links) for msg in msgs):
            ks = self._span(msgs, 1 + self.mission.n)
        if ks is None:
            for msg in msgs:
                self.telemetry(msg)
            return
        i, r, lk, rt = self.col[msgs[0].sender], self.run, self.lk, self.rt
        r.p[ks, i], r.v[ks, i], r.a[ks, i], r.u[ks, i], r.xi[ks, i], r.zeta[ks, i], r.kp[ks, i], r.kv[ks, i] = \
            _block(msgs, _TELEMETRY_VECTORS, self.mission.dim)
        for n in range(min(len(msgs[0].links), lk.src.shape[1])):
            links = [msg.links[n] for msg in msgs]
            lk.src[i, n] = links[-1].src
            lk.age[ks, i, n] = [link.age for link in links]
            lk.received[ks, i, n] = [link.received for link in links]
            lk.stale[ks, i, n] = [link.stale for link in links]
            self.silent[ks, i, n] = [float(link.silent) for link in links]
            lk.used[ks, i, n] = [link.used for link in links]
            lk.duplicates[ks, i, n] = [link.duplicates for link in links]
            lk.reordered[ks, i, n] = [link.reordered for link in links]
            lk.corrupt[ks, i, n] = [link.corrupt for link in links]
            self.delivery[ks, i, n] = [link.delivery for link in links]
            self.age_p50[ks, i, n] = [link.age_p50 for link in links]
            self.age_p99[ks, i, n] = [link.age_p99 for link in links]
        rt.drops[ks, i] = [sum(msg.drops.values()) for msg in msgs]
        rt.meas_age[ks, i] = [msg.t - msg.meas_t for msg in msgs]
        r.safety.safety_mode[ks, i] = [msg.mode for msg in msgs]
        rt.late[ks, i] = [msg.late for msg in msgs]
        for msg in msgs:
            if msg.events:
                self.events.extend(msg.events)
            for d in msg.netem:
                self.netem.append({"dst": msg.sender, "src": d.src, "seq": d.seq, "now": d.now, "event": d.event,
                                   "at": d.at})
        if ks.stop - 1 > self.gate[i][0]:
            self.gate[i] = (ks.stop - 1, dict(msgs[-1].gate))

    def _span(self, msgs: list[Any], column: int) -> slice | None:
        """The ticks of ``msgs`` (one sender's, in ``column`` + its index of :attr:`have`), taken
        and counted as :meth:`_take` takes one, when they are consecutive ticks of the run from one
        sender and none of them is in yet; else None (nothing taken)."""
        if not msgs:
            return None
        k0, k1, who = msgs[0].k, msgs[-1].k, msgs[0].sender
        if k0 < 0 or k1 >= len(self.count) or k1 - k0 != len(msgs) - 1 \
                or any(msg.k != k0 + n or msg.sender != who for n, msg in enumerate(msgs)):
            return None
        ks = slice(k0, k1 + 1)
        have = self.have[ks, column + self.col[who]]
        if have.any():
            return None
        have[:] = True
        self.count[ks] += 1
        self._heard(k0)
        self._heard(k1)
        return ks

    def world(self, msg: wire.WorldState) -> None:
        series = self.world_series
        if (series is not None and 0 <= msg.k < len(self.count)
                and len(msg.tension) == self.mission.n == len(msg.slack_events)
                and self._take(msg.k, 1 + 2 * self.mission.n)):
            pp, pv, tension, slack = series
            pp[msg.k], pv[msg.k] = msg.p, msg.vel
            tension[msg.k], slack[msg.k] = msg.tension, msg.slack_events
            self._heard(msg.k)

    def take(self, msg: wire.Message) -> None:
        """Record one message as the recorder's inputs hand it over (a journal's replay): a sample,
        or a lockstep record (the leader's states, or an agent's plant samples and telemetry, each
        already past the plausibility gate). Other messages are ignored."""
        if isinstance(msg, wire.Record):
            for s in msg.leader:
                self.leader(s)
            if msg.plant:
                self.plants(msg.plant)
            if msg.telemetry:
                self.telemetries(msg.telemetry)
        elif isinstance(msg, wire.Telemetry):
            self.telemetry(msg)
        elif isinstance(msg, wire.PlantState):
            self.plant(msg)
        elif isinstance(msg, wire.State):
            self.leader(msg)
        elif isinstance(msg, wire.WorldState):
            self.world(msg)

    def telemetry(self, msg: wire.Telemetry) -> None:
        k = msg.k
        if not 0 <= k < len(self.count) or not self._take(k, 1 + self.mission.n + self.col[msg.sender]):
            return  # outside the run, or its tick's telemetry from this agent is in (its events once)
        if self.first is None and abs(msg.t - k * self.mission.dt) <= 0.5 * self.mission.dt:
            # an agent publishes tick k's telemetry about half a period after t_k: one period
            # earlier than its arrival is an epoch never behind the swarm's (tether record, late);
            # only from a sample whose tick and time agree and lie within the mission (its arrival:
            # it may be drained up to a period later)
            self.first = time.time() - self.arrived_ago() - msg.t - self.mission.dt
        i, r, lk, rt = self.col[msg.sender], self.run, self.lk, self.rt
        r.p[k, i], r.v[k, i], r.a[k, i], r.u[k, i] = msg.p, msg.vel, msg.a, msg.u
        r.xi[k, i], r.zeta[k, i], r.kp[k, i], r.kv[k, i] = msg.xi, msg.zeta, msg.kp, msg.kv
        for n, link in enumerate(msg.links[: lk.src.shape[1]]):
            lk.src[i, n] = link.src
            lk.age[k, i, n] = link.age
            lk.received[k, i, n] = link.received
            lk.stale[k, i, n] = link.stale
            self.silent[k, i, n] = float(link.silent)
            lk.used[k, i, n] = link.used
            lk.duplicates[k, i, n] = link.duplicates
            lk.reordered[k, i, n] = link.reordered
            lk.corrupt[k, i, n] = link.corrupt
            self.delivery[k, i, n] = link.delivery
            self.age_p50[k, i, n] = link.age_p50
            self.age_p99[k, i, n] = link.age_p99
        if self.clock is not None:
            self._clock(k, i, msg.clock)
        rt.drops[k, i] = sum(msg.drops.values())
        rt.meas_age[k, i] = msg.t - msg.meas_t
        r.safety.safety_mode[k, i] = msg.mode
        self.events.extend(msg.events)
        if k > self.gate[i][0]:
            self.gate[i] = (k, dict(msg.gate))
        for d in msg.netem:
            self.netem.append({"dst": msg.sender, "src": d.src, "seq": d.seq, "now": d.now, "event": d.event,
                               "at": d.at})
        rt.late[k, i] = msg.late
        self._heard(k)

    def _clock(self, k: int, i: int, links: list[wire.ClockLink]) -> None:
        rec, slots = self.clock, self.clock_slots[i]
        if rec is None:
            return
        for c in links:
            slot = slots.get((c.role, c.src))
            if slot is None:
                if len(slots) >= rec.src.shape[1]:
                    continue  # a proximity sender (collision avoidance) beyond the law's in-links
                slot = slots[c.role, c.src] = len(slots)
                rec.role[i, slot], rec.src[i, slot] = c.role, c.src
            rec.offset[k, i, slot] = c.offset

    def save(self, complete: bool, drops: dict[str, int], sync: bool = False) -> Path:
        """Write the run file (and its views); an ``OSError`` (a full disk) is noted in
        :attr:`failed` (the stop hook then does not try again) and re-raised: :func:`tether.node.serve`
        logs it with the path and the cause (:func:`tether.node.os_error`), no traceback, and exits 1."""
        self.failed = None
        try:
            return self._save(complete, drops, sync)
        except OSError as exc:
            self.failed = exc
            raise

    def finalise(self, complete: bool, drops: dict[str, int]) -> Run:
        """The run as it stands, its metadata, events and gate counts filled in (pure; :meth:`save`
        writes it)."""
        meta, safety = self.run.meta, self.run.safety
        meta.complete = complete
        if self.duplicates:
            drops = {**drops, "duplicate_sample": self.duplicates}
            log.warning("%d samples heard again for a tick that had them (a replay?): each recorded once",
                        self.duplicates)
        meta.recorder_drops = DropCounts.of(drops)
        meta.samples_recorded = int(self.count.sum())
        meta.samples_expected = int(self.expected * len(self.count))
        safety.events = sorted(self.events, key=lambda e: (e.k, e.vehicle, e.t))
        safety.plant_events = sorted(self.plant_events, key=lambda e: (e.k, e.vehicle, e.t))
        reasons = sorted({r for _, gate in self.gate for r in gate})
        safety.gate_reasons = np.array(reasons, dtype=str)
        safety.gate_counts = np.array([[gate[r] if r in gate else 0 for r in reasons] for _, gate in self.gate],
                                      dtype=np.int64).reshape(len(self.gate), len(reasons))
        return self.run

    def _save(self, complete: bool, drops: dict[str, int], sync: bool) -> Path:
        self.finalise(complete, drops)
        cpu0, wall0 = time.process_time(), time.perf_counter()
        path = self.run.save(self.out / "run.npz", sync=sync)
        cpu1, wall1 = time.process_time(), time.perf_counter()
        try:  # the Foxglove view beside it (docs/foxglove.md); the run file is already safe
            if self.mcap:  # ticks of which nothing was heard (a stop, a late start) are left out of it
                heard = dataclasses.replace(self.run, t=np.where(self.count > 0, self.run.t, np.nan))
                mcap_beside(heard, self.mission, path)
        except Exception as exc:  # noqa: BLE001 - never lose a recording over its view
            log.warning("no run.mcap: %s: %s", type(exc).__name__, exc)
        cpu2, wall2 = time.process_time(), time.perf_counter()
        # bench/recording.py reads this line: the recorder's CPU while recording, and for each file
        log.info("recorder CPU: %.3f s recording, %.3f s run.npz, %.3f s run.mcap (wall %.3f s, %.3f s); "
                 "%.3f s of start-up before the run", cpu0, cpu1 - cpu0, cpu2 - cpu1, wall1 - wall0, wall2 - wall1,
                 self.cpu_ready)
        if self.mission.netem is not None and self.mission.netem.log:
            self.netem.sort(key=lambda d: (d["dst"], d["src"], d["seq"], d["at"] is None, d["at"] or 0.0))
            lines = "".join(jsonout.dumps(d, indent=None) + "\n" for d in self.netem)
            (self.out / "netem.jsonl").write_text(lines)
        self.saved = True
        log.info("wrote %s (%d of %d samples)", path, self.count.sum(), self.expected * len(self.count))
        return path


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
