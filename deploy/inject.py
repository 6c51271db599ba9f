"""The launcher's eyes and hands on a run: what it watches (:class:`Monitor`) and the faults it
fires (:class:`Injector`).

Faults (``tether run --fault``, parsed by ``deploy/faults.py``), each fired by the launcher at its
mission time and recorded in ``faults.json``:

* ``kill`` — SIGKILL the process (it gets no chance to close its Zenoh session; its peers see its
  link go at once);
* ``freeze`` — SIGSTOP, then SIGCONT ``D`` seconds later: the process holds its sockets but
  answers nothing; its link is dropped after the lease (``--lease``), so the others see its token
  go, and it resumes (and reconnects) on SIGCONT with a backlog of stale samples;
* ``partition`` — the process's one link (to the launcher's router) goes through a relay
  (``deploy/relay.py``) that forwards nothing for ``D`` seconds: a black hole, not a reset. The
  process keeps running and publishing into the void; both sides drop the link after the lease and
  the process reconnects when the cut ends. Only that process's link is cut (not a two-sided split of
  the swarm), only in the ``star`` network (peers of a mesh link directly), and packet-level effects
  inside the link (loss, reordering) are not emulated: TCP hides them;
* ``forge`` — the launcher publishes one well-formed sample on the victim's state key:
  the victim's newest real sample with ``seq + 1``, tick ``k + 1`` (the victim's next tick, so it
  competes with the real one) and every position coordinate moved by
  :data:`~deploy.faults.FORGE_OFFSET` (10^6 m). Sender id and schema are the victim's; only the access
  rules of a deployment (``deploy/acl.py``) keep such a sample out, and locally there are none.

Mission time is real time since tick 0 (``--clock realtime``) or ``k h`` of the tick the run has
reached (lockstep: the launcher holds the clock's grant at the fault's tick until it has fired, so
the fault lands between ticks ``K`` and ``K + 1`` of every process). ``D`` is wall time.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import msgspec
import zenoh

from deploy.faults import FORGE_OFFSET, Fault
from deploy.relay import Relay
from tether import handoff
from tether import mission as ms
from tether import transport as tp
from tether import wire

log = logging.getLogger("tether")

FINAL = frozenset({wire.LANDED, wire.ESTOP})
"""Modes after which a vehicle does nothing more."""
JUDGED = frozenset({wire.FLYING, wire.HOLD})
"""Modes in which an agent's formation error and gains are judged for divergence (as its supervisor does)."""


@dataclass
class Event:
    """Something that went wrong in a run, reported once."""

    t: float | None
    """Mission time [s] (None: before tick 0)."""
    who: str
    """``agent/2``."""
    what: str
    """``died``, ``froze``, ``back``, ``failsafe``, ``diverged``, ``silent``, ``fault``, ``skew``."""
    why: str

    def line(self) -> str:
        when = "before tick 0" if self.t is None else f"t = {self.t:7.2f} s"
        return f"{when}  {self.who:<12} {self.what}: {self.why}"

    def to_json(self) -> dict[str, Any]:
        return {"t": self.t, "who": self.who, "what": self.what, "why": self.why}


LOST = frozenset({"died", "froze", "silent"})
"""Events that mean a process was lost (exit status 4)."""
FAILSAFE = frozenset({"failsafe", "diverged"})
"""Events that mean a failsafe fired or a value diverged (exit status 3)."""


# What the monitor reads of the messages it hears: a decoder of these skips every other field of a
# message (an agent's link statistics, drops, gate counts, vectors it does not judge) without building
# it; a record of 16 ticks decoded in half the time of the whole message (19 against 39 µs, hot)
class _Telemetry(msgspec.Struct, tag_field="type", tag="telemetry", frozen=True):
    sender: int
    k: int
    t: float
    xi: list[float]
    kp: list[float]
    kv: list[float]
    mode: int = wire.FLYING
    events: list[wire.SafetyEvent] = msgspec.field(default_factory=list)
    clock: list[wire.ClockLink] = msgspec.field(default_factory=list)


class _PlantState(msgspec.Struct, tag_field="type", tag="plant_state", frozen=True):
    sender: int
    k: int
    t: float
    p: list[float]
    mode: int = wire.FLYING


class _State(msgspec.Struct, tag_field="type", tag="state", frozen=True):
    sender: int
    k: int
    t: float


class _Record(msgspec.Struct, tag_field="type", tag="record", frozen=True):
    sender: int
    k: int
    plant: list[_PlantState] = msgspec.field(default_factory=list)
    telemetry: list[_Telemetry] = msgspec.field(default_factory=list)


_Heard = _Telemetry | _PlantState | _State | _Record


def _name(role: str, nid: int) -> str:
    return f"{role}/{nid}"


def describe_exit(status: int) -> str:
    if status < 0:
        try:
            return f"killed by {signal.Signals(-status).name}"
        except ValueError:
            return f"killed by signal {-status}"
    return f"exited with status {status}"


class Monitor:
    """Watches a run from the launcher's session: every liveliness token, every agent's telemetry
    (``mode``, ``events``, xi and gains), every plant's state (``mode``) and the leader's state.
    Zenoh's callbacks only queue raw samples (bounded FIFO, drop-oldest); :meth:`poll` decodes them
    on the event loop and turns what it sees into :class:`Event` records, each reported once."""

    CONFIRM = 1.0
    """A token gone while its process runs is reported as a freeze after this long [s] (a process
    that is ending withdraws its token moments before it exits)."""

    REJOIN = 3.0
    """After the launcher itself was late (:meth:`poll`), how long beyond twice the lease [s] its
    processes get to link again and declare their tokens anew before a token still gone is theirs to
    answer for (a client redials its router about once a second)."""

    def __init__(self, session: zenoh.Session, mission: ms.Mission, keys: wire.Keys,
                 members: list[tuple[str, int]], clock: Callable[[], float | None], forge_agents: bool = False,
                 leader: bool = True, lease: float = 2.0):
        self.lease = lease
        """The links' lease [s]: the launcher late by this much may have let every link to its router
        lapse (its own freeze or starvation, not its processes')."""
        self._last_poll: float | None = None
        self.excused: tuple[float, float] | None = None
        """Monotonic interval [s] in which tokens lost are not blamed on their processes: from the
        start of the launcher's own latest lateness to :data:`REJOIN` and twice the lease after it."""
        self.resumed: float | None = None
        """Monotonic time [s] the launcher last ran again after being late by a lease or more."""
        self.mission = mission
        self.keys = keys
        self.members = members
        self.mission_time = clock
        """Current mission time [s], or None before tick 0."""
        self.wake = handoff.Wakeup()
        self.fifo: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(1 << 16, self.wake)
        self.token_events: handoff.BoundedFifo[tp.TokenEvent] = handoff.BoundedFifo(4096, self.wake)
        self.events: list[Event] = []
        self.modes: dict[str, int] = {}
        """Newest mode of each agent (telemetry) and plant (plant state) heard."""
        self.height: dict[str, float] = {}
        """Newest height (last coordinate, finite) of each plant heard [m]."""
        self.heard: set[str] = set()
        self.newest: dict[str, bytes] = {}
        """Newest raw sample of each state key (for forging)."""
        self.alive_token: dict[str, bool] = {}
        self._diverged: set[str] = set()
        self._skewed: set[tuple[str, str, int]] = set()
        """(agent, sender role, sender id) of the links already reported skewed."""
        self._decoder = msgspec.msgpack.Decoder(_Heard)
        ns = keys.ns
        self._subs = [
            tp.declare_subscriber(session, f"tether/{ns}/agent/*/telemetry", self.fifo),
            tp.declare_subscriber(session, f"tether/{ns}/plant/*/state", self.fifo),
            # a plant co-located in its agent (--colocate-plants): both streams in one record
            tp.declare_subscriber(session, f"tether/{ns}/agent/*/record", self.fifo),
            tp.watch_tokens(session, keys.tokens, self.token_events),
        ]
        if leader:  # what the monitor learns from the leader's state: that it was heard, and a sample to forge
            self._subs.append(tp.declare_subscriber(session, f"tether/{ns}/leader/*/state", self.fifo))
        if forge_agents:  # an agent's state is only needed to forge it
            self._subs.append(tp.declare_subscriber(session, f"tether/{ns}/agent/*/state", self.fifo))
        self._vanished: dict[str, tuple[float, float | None]] = {}
        """Tokens gone, not yet confirmed: name -> (monotonic time, mission time) of the loss."""
        self.proc_alive: Callable[[str], bool] = lambda name: True

    def close(self) -> None:
        for s in self._subs:
            try:
                s.undeclare()
            except zenoh.ZError:
                pass
        self._subs.clear()

    def report(self, who: str, what: str, why: str, t: float | None = None) -> Event:
        ev = Event(self.mission_time() if t is None else t, who, what, why)
        self.events.append(ev)
        (log.info if what in ("back", "fault") else log.warning)("%s", ev.line())
        return ev

    def _self_late(self, now: float) -> None:
        """Whether the launcher itself ran late (its previous poll a lease or more ago: stopped, or
        starved of CPU): then its router kept no link alive, and every token may vanish and return
        for its lateness, not the processes'. Reported once per lateness as the launcher's own."""
        last, self._last_poll = self._last_poll, now
        if last is None or now - last < self.lease:
            return
        until = now + 2 * self.lease + self.REJOIN
        start = last if self.excused is None or self.excused[1] < last else self.excused[0]
        self.excused = (start, until)
        self.resumed = now
        self.report("launcher", "froze", f"the launcher itself did not run for {now - last:.1f} s (stopped, or "
                                         "starved of CPU): the links to its router lapsed meanwhile, so tokens "
                                         f"lost until {until - now:.1f} s after it resumed are not blamed on its "
                                         "processes")

    def _is_excused(self, since: float) -> bool:
        return self.excused is not None and self.excused[0] <= since <= self.excused[1]

    def poll(self) -> None:
        """Decode what was heard, turn token losses into events; blocks for nothing."""
        self._self_late(time.monotonic())
        for rec in self.fifo.drain():
            try:
                role, nid, topic = wire.Keys.parse(rec.key)
                msg = self._decoder.decode(rec.payload)
            except (ValueError, msgspec.DecodeError, msgspec.ValidationError):
                continue
            if isinstance(msg, _Record):  # the plant's samples, then the agent's telemetry
                items: list[tuple[str, _Heard]] = [(_name("plant", nid), x) for x in msg.plant]
                items += [(_name("agent", nid), x) for x in msg.telemetry]
            else:
                items = [(_name(role, nid), msg)]
                if topic == "state":
                    self.newest[rec.key] = rec.payload
            for name, msg in items:
                self._observe(name, msg)
        for ev in self.token_events.drain():
            try:
                role, nid = wire.Keys.parse_token(ev.key)
            except ValueError:
                continue
            name = _name(role, nid)
            was = self.alive_token.get(name)
            self.alive_token[name] = ev.alive
            if was and not ev.alive:
                self._vanished[name] = (time.monotonic(), self.mission_time())
            elif ev.alive and was is False:
                pending = self._vanished.pop(name, None)
                if pending is not None and self.proc_alive(name) and not self._is_excused(pending[0]):
                    # back within CONFIRM: a process that is ending never gets its token back, so this
                    # one was lost for a while (a freeze or a cut-off about as long as the lease)
                    t = pending[1]
                    if t is None or t < self.mission.duration:
                        self.report(name, "froze", "its liveliness token was gone for a while as its process "
                                                   "ran on (stopped, cut off, or hung)", t=t)
                self.report(name, "back", "its liveliness token is back")
        now = time.monotonic()
        for name, (since, t_gone) in list(self._vanished.items()):
            if now - since < self.CONFIRM:
                continue
            if self._is_excused(since) and self.excused is not None and now < self.excused[1]:
                continue  # lost while the launcher was late: judged once its processes could link again
            del self._vanished[name]
            t = t_gone
            if self.proc_alive(name) and not self.alive_token.get(name) and (t is None or t < self.mission.duration):
                self.report(name, "froze", "its liveliness token is gone while its process still runs "
                                           "(stopped, cut off, or hung)", t=t)
            elif self.alive_token.get(name):
                self.report(name, "back", "its liveliness token is back")

    def _observe(self, name: str, msg: _Heard) -> None:
        """What one agent's telemetry or one plant's state says: mode changes, skew, divergence."""
        sf = self.mission.safety
        self.heard.add(name)
        judged = self.modes.get(name, wire.FLYING) in JUDGED
        if isinstance(msg, _PlantState) and msg.p and math.isfinite(msg.p[-1]):
            self.height[name] = msg.p[-1]
        if isinstance(msg, (_Telemetry, _PlantState)):
            mode = msg.mode
            before = self.modes.get(name, wire.FLYING)
            self.modes[name] = mode
            if mode != before:
                why = "; ".join(e.reason for e in getattr(msg, "events", []) if e.dst == mode)
                self.report(name, "failsafe" if mode != wire.FLYING else "back",
                            f"mode {wire.MODES[before] if 0 <= before < 5 else before} -> "
                            f"{wire.MODES[mode] if 0 <= mode < 5 else mode}" + (f" ({why})" if why else ""),
                            t=msg.t)
        if isinstance(msg, _Telemetry):
            for c in msg.clock:
                if c.warn and (name, c.role, c.src) not in self._skewed:
                    self._skewed.add((name, c.role, c.src))
                    self.report(name, "skew", f"link {c.role}/{c.src}: clock offset bound {1000 * c.offset:+.1f} ms "
                                              "(arrival minus sample time; tether/skew.py)", t=msg.t)
        if isinstance(msg, _Telemetry) and name not in self._diverged and judged:
            # a vehicle that was landing (or landed, or stopped) has left the formation on purpose: its
            # xi against a leader that flies on is not a divergence. Its supervisor judges a tick by
            # the mode it began in, so the tick a divergence sends it to LAND is still judged here.
            xi = math.sqrt(sum(x * x for x in msg.xi))
            gains = max([*msg.kp, *msg.kv], default=0.0)
            if not math.isfinite(xi) or xi > sf.max_formation_error or not gains <= sf.gain_cap:
                self._diverged.add(name)
                self.report(name, "diverged", f"|xi| = {xi:.3g} m (limit {sf.max_formation_error:g}), "
                                              f"largest gain {gains:.3g} (cap {sf.gain_cap:g})", t=msg.t)

    def vehicles_settled(self, live: set[str]) -> bool:
        """Every live agent and plant reports a final mode (LANDED or ESTOP)."""
        names = [n for n in live if n.startswith(("agent/", "plant/"))]
        return bool(names) and all(self.modes.get(n, wire.FLYING) in FINAL for n in names)

    def unsettled_heights(self, live: set[str]) -> dict[str, float]:
        """The newest height of each live plant not reporting a final mode (LANDED or ESTOP)."""
        return {n: h for n, h in self.height.items()
                if n in live and n.startswith("plant/") and self.modes.get(n, wire.FLYING) not in FINAL}

    def any_obeying(self, live: set[str]) -> bool:
        """Some live agent or plant reports a mode other than FLYING."""
        return any(self.modes.get(n, wire.FLYING) != wire.FLYING for n in live)


@dataclass
class _Firing:
    fault: Fault
    pid: int
    fired: float | None = None
    fired_wall: float | None = None
    ended: float | None = None
    detail: dict[str, Any] = field(default_factory=dict)


class Injector:
    """Fires the faults of a run at their mission times (see the module docstring)."""

    def __init__(self, faults: tuple[Fault, ...], mission: ms.Mission, keys: wire.Keys, session: zenoh.Session,
                 pids: dict[tuple[str, int], int], relays: dict[tuple[str, int], Relay], monitor: Monitor):
        self.mission = mission
        self.keys = keys
        self.relays = relays
        self.monitor = monitor
        self.firings = [_Firing(f, pids[f.member(mission)]) for f in sorted(faults, key=lambda f: f.at)
                        if f.kind != "skew"]
        self.skews = [f for f in faults if f.kind == "skew"]
        """Clock skews: given to their processes at launch (``--clock-skew``), nothing fires."""
        self._pubs: dict[str, zenoh.Publisher] = {}
        for f in faults:
            if f.kind == "forge":
                key = self.state_key(f)
                if key not in self._pubs:
                    self._pubs[key] = tp.declare_publisher(session, key, tp.SYNC)

    def state_key(self, f: Fault) -> str:
        role, nid = f.member(self.mission)
        return self.keys.topic(role, nid, "state")

    def next_tick(self) -> int | None:
        """Lockstep: the tick of the earliest fault not yet fired."""
        dt = self.mission.dt
        ticks = [round(x.fault.at / dt) for x in self.firings if x.fired is None]
        return min(ticks) if ticks else None

    def next_due(self, now: float) -> float | None:
        """Seconds from mission time ``now`` until the next fault fires or ends (None: none left)."""
        wall = time.monotonic()
        waits = [x.fault.at - now for x in self.firings if x.fired is None]
        waits += [x.fired_wall + x.fault.duration - wall for x in self.firings
                  if x.fired_wall is not None and x.ended is None and x.fault.duration is not None]
        return max(0.0, min(waits)) if waits else None

    def fire_due(self, now: float) -> None:
        """Fire every fault due by mission time ``now`` [s]; end freezes and partitions whose
        duration has passed (wall time)."""
        for x in self.firings:
            if x.fired is None and x.fault.at <= now + 1e-9:
                x.fired, x.fired_wall = now, time.monotonic()
                self._fire(x)
                self.monitor.report(_name(*x.fault.member(self.mission)), "fault", f"--fault {x.fault.text} fired at t = {now:.3f} s "
                                                            f"(asked {x.fault.at:g} s)", t=now)
        wall = time.monotonic()
        for x in self.firings:
            if x.fired is not None and x.fired_wall is not None and x.ended is None and x.fault.duration is not None \
                    and wall >= x.fired_wall + x.fault.duration:
                self._end(x)
                x.ended = x.fired + (wall - x.fired_wall)
                log.info("--fault %s ended", x.fault.text)

    def _signal(self, pid: int, sig: signal.Signals) -> bool:
        try:
            os.kill(pid, sig)
            return True
        except ProcessLookupError:
            return False

    def _fire(self, x: _Firing) -> None:
        f = x.fault
        if f.kind == "kill":
            x.detail["delivered"] = self._signal(x.pid, signal.SIGKILL)
        elif f.kind == "freeze":
            x.detail["delivered"] = self._signal(x.pid, signal.SIGSTOP)
        elif f.kind == "partition":
            self.relays[f.member(self.mission)].cut()
            x.detail["delivered"] = True
        else:
            self._forge(x)

    def _end(self, x: _Firing) -> None:
        if x.fault.kind == "freeze":
            self._signal(x.pid, signal.SIGCONT)
        elif x.fault.kind == "partition":
            self.relays[x.fault.member(self.mission)].restore()

    def _forge(self, x: _Firing) -> None:
        f, m = x.fault, self.mission
        key = self.state_key(f)
        role, nid = f.member(m)
        raw = self.monitor.newest.get(key)
        if raw is not None:
            fields = msgspec.msgpack.decode(raw)
        else:  # nothing heard yet: a sample of the current tick, from the mission's start state
            k = max(0, round((x.fired or 0.0) / m.dt))
            p0 = m.leader.p0 if role == "leader" else next(a.p0 for a in m.agents if a.id == nid)
            zero = [0.0] * m.dim
            fields = {"type": "plant_state" if role == "plant" else "state", "v": wire.WIRE_VERSION,
                      "sender": nid, "seq": k - 1, "k": k - 1, "t": (k - 1) * m.dt, "p": list(p0), "vel": zero,
                      "a": zero}
            if role == "plant":
                fields["d"] = zero
        fields["seq"] += 1
        fields["k"] += 1
        fields["t"] = fields["k"] * m.dt
        fields["p"] = [p + FORGE_OFFSET for p in fields["p"]]
        msg = msgspec.msgpack.decode(msgspec.msgpack.encode(fields), type=wire.State | wire.PlantState)  # checked
        self._pubs[key].put(wire.encode(msg))
        x.detail.update({"key": key, "sender": msg.sender, "seq": msg.seq, "k": msg.k, "p": list(msg.p)})

    def close(self) -> None:
        """End every freeze and partition still on (so that the processes can be stopped)."""
        for x in self.firings:
            if x.fired is not None and x.ended is None and x.fault.duration is not None:
                self._end(x)
        for pub in self._pubs.values():
            try:
                pub.undeclare()
            except zenoh.ZError:
                pass

    def records(self) -> list[dict[str, Any]]:
        """``faults.json``: one record per fault, in firing order."""
        return [{"kind": x.fault.kind, "target": x.fault.target, "fault": x.fault.text, "at": x.fault.at,
                 "duration": x.fault.duration, "fired": x.fired, "ended": x.ended, **x.detail}
                for x in self.firings] + [{"kind": "skew", "target": f.target, "fault": f.text, "skew": f.skew}
                                          for f in self.skews]
