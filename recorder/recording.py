"""The run being filled, sample by sample: the recorder's bookkeeping (no I/O until
:meth:`Recording.save`), shared by the recorder's process (:mod:`recorder.node`) and the
rebuilding of a run from its journal (:mod:`recorder.journal`).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from itertools import chain
from operator import attrgetter
from pathlib import Path
from typing import Any

import numpy as np

from recorder.export import mcap_beside
from agent import laws
from tether import jsonout, wire
from tether.mission import Mission
from tether.node import Node
from tether.runfile import ClockRecord, DropCounts, Links, PlantRecord, Run, RunMeta, RuntimeRecord, Source

log = logging.getLogger("tether")


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
        bound = laws.of_mission(m)
        self.states = len(bound.law.state)
        """The law's state variables per axis (each telemetry's ``x`` holds ``states * d`` floats)."""
        meta = RunMeta(mission=m.name, source=source, law=bound.law.name, rate=m.rate,
                       steps=m.steps, seed=m.seed, namespace=ctx.namespace, mission_text=ctx.mission_text,
                       law_state=bound.law.state, law_units=bound.units)
        self.run = Run.empty(T, m.agent_ids, d, meta)
        self.state_mismatch = 0
        """Telemetry whose law state ``x`` is not the law's size (recorded without it; counted as
        the drop reason ``law_state``)."""
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
        self._law_state(msgs, ks, i)
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

    def _law_state(self, msgs: list[wire.Telemetry], ks: int | slice, i: int) -> None:
        """The law's state ``x`` of agent ``i``'s telemetry ``msgs`` (of ticks ``ks``) into
        ``law_state``, after ``kp``/``kv`` (its first two, as the message says them): a message
        without it leaves the rest NaN; one of another size or other names than the law's is
        counted, not used."""
        size, names = self.states * self.mission.dim, list(self.run.meta.law_state)

        def fits(msg: wire.Telemetry) -> bool:
            return len(msg.x) == size and (not msg.x_names or msg.x_names == names)

        if not size:
            return
        if not all(fits(msg) for msg in msgs):
            self.state_mismatch += sum(1 for msg in msgs if msg.x and not fits(msg))
            for n, msg in enumerate(msgs):
                if fits(msg):
                    self._law_state([msg], ks if isinstance(ks, int) else ks.start + n, i)
            return
        rows = np.array([msg.x for msg in msgs], dtype=float).reshape(len(msgs), self.states, self.mission.dim)
        self.run.law_state[:, ks, i] = rows[0] if isinstance(ks, int) else rows.transpose(1, 0, 2)

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
        self._law_state([msg], k, i)
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
        if self.state_mismatch:
            drops = {**drops, "law_state": self.state_mismatch}
            log.warning("%d telemetry messages carried a law state other than the law's %s: their law_state is NaN",
                        self.state_mismatch, ", ".join(self.run.meta.law_state))
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
