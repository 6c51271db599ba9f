"""Agent i's process: Eq. 17 on what it hears from its plant and its in-neighbours only.

Its plant's measurement is relayed as agent i's state (what its out-neighbours use) as soon as it
arrives, stamped with the measurement's own tick and sample time: in real time on Zenoh's callback
thread, without waiting for the event loop (:mod:`agent.relay`), in lockstep from the loop. Tick k: take the plant's
measurement of tick k and each in-neighbour's state of tick k (lockstep: exactly those; real
time: the newest held), run the agent's tick (:meth:`agent.tick.AgentTick.step`: the law, then the
safety supervisor, then collision avoidance when the mission asks for it), publish the command to
its plant and telemetry. Every sample passes the plausibility gate (:mod:`tether.gate`) before it is
stored; the operator's orders arrive on ``control/0/safety``. In real time the agent ticks half a period after its plant and the leader
(``AGENT_PHASE``), so that the tick-k samples are usually in by then.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from leader import profile
from tether.gate import Gate, PlantModes, for_sender, health_of, merged
from agent.relay import Relay
from agent.safety import Status
from agent.tick import AgentTick, Heard
from netem import control as netem_control
from plant import resume
from tether import vec
from tether import transport as tp
from tether import wire
from tether import skew
from tether.clock import AGENT_PHASE
from tether.inputs import Source
from tether.mission import nearby_vehicles
from tether.rejoin import Rejoin
from tether.skew import SkewMonitor
from tether.node import Node, Stalled

log = logging.getLogger("tether")

async def run(node: Node) -> None:
    m = node.mission
    aid = node.args.node_id
    tick = AgentTick.from_mission(m, aid)
    law = tick.law
    keys = node.keys
    state = node.publisher(keys.topic("agent", aid, "state"))
    onboard = None
    if node.args.colocate:  # lockstep: this process computes its plant (plant/onboard.py); no plant process runs
        node.clock.require("lockstep", "--colocate-plant is for lockstep runs: in real time the plant is a process "
                                       "of its own")
        from plant.onboard import Onboard

        onboard = Onboard(m, aid)

    def publish_state(msg: wire.PlantState) -> None:
        state.send(wire.State, msg.k, msg.t, p=msg.p, vel=msg.vel, a=tick.shared(msg.a), mode=tick.supervisor.mode)

    def relay(msg: wire.PlantState) -> None:
        if msg is not plant.newest:  # not newer than the last (a replay, a duplicate): never re-published as fresh
            node.count_drop("stale_relay")
            return
        publish_state(msg)

    lockstep = node.clock.kind == "lockstep"  # TEMP
    sf = m.safety
    gates: list[Gate] = []

    # real time: each input link's clock offset, from sample times against arrival times
    # (tether/skew.py), observed before the gate, which rejects a sender too far ahead
    clocks = None if lockstep else SkewMonitor(m.dt)

    # real time: a restarted agent rejoins a run under way; its plant (same host, same clock) is
    # still ticking, and the earliest arrival of its samples gives the run's start instant
    rejoin = Rejoin(node.clock.wall)

    # the leader's samples are checked against its profile (the mission's [leader]), in plain floats
    expected = profile.scalar(m.leader, m.dim)

    def gate(sender: int, role: str) -> Callable[[Any], str | None]:
        # real time: a sample is judged at its arrival (a neighbour's waits in its queue until the tick)
        g = for_sender(m, sender, None if lockstep else node.arrival,
                       expect=expected if role == "leader" else None)
        gates.append(g)

        def admit(msg: Any) -> str | None:
            if node.clock.unstarted():
                # before this process's start: samples of a run already under way
                if role == "plant":
                    rejoin.observe(msg.k, msg.t)
                return "before start"
            if clocks is not None:
                clocks.observe(role, sender, msg.t, node.arrival())
            why = g.check(msg)
            if why is not None and g.rejected[why] in (1, 10, 100, 1000):  # say so, without flooding the log
                log.warning("gate: sample of %d for tick %d rejected (%s), %d so far", sender, msg.k, why,
                            g.rejected[why])
            return why

        return admit

    operator: list[str] = []
    """The operator's orders received (``land``, ``estop``), in order."""

    def order(msg: wire.SafetyCommand) -> None:
        if msg.action not in operator:
            log.warning("operator: %s (%s)", msg.action, msg.reason or "no reason given")
            operator.append(msg.action)

    node.source(keys.safety, wire.SafetyCommand, 0, on_message=order, keep=False)
    own_inputs: list[Source] = []
    modes = PlantModes(sf.mode_confirm)
    """The own plant's report of its mode, believed as far as its samples agree (from its key alone)."""
    relay_rt: Relay | None = None
    if onboard is None:
        key = keys.topic("plant", aid, "state")
        if lockstep:
            plant = node.source(key, wire.PlantState, aid, on_message=relay)
        else:
            # real time: relayed on Zenoh's callback thread as it arrives (agent/relay.py); the tick
            # reads it at its drain (until the start each sample wakes the loop: a restarted agent
            # learns the run's start from them)
            relay_rt = Relay(aid, m.dim, m.dt, for_sender(m, aid, None), lambda: node.clock.origin, publish_state, node.count_drop)
            relay_rt.alive_at = math.inf  # no stall before the first tick (it relays nothing before the start)
            plant = node.source(key, wire.PlantState, aid, tap=relay_rt)
        plant.admit = gate(aid, "plant")
        plant.health = health_of(m)
        plant.consistent = lambda msg: modes.observe(msg.k, msg.mode)
        node.watch("plant", aid, plant)
        own_inputs.append(plant)
        resume.serve(node, aid, plant)  # a restarted plant asks for its last state (plant/resume.py)
    if m.netem is not None:
        from netem.link import Channel  # only a mission with [netem] loads the emulator
    nbrs: list[Source] = []
    channels = []  # the emulated in-links, for their decision log
    witnesses: list[Source] = []
    """Real time: each agent in-neighbour's own plant's measurements (plant/j/state, which only plant j
    may publish), against which its relayed state is corroborated."""
    for j in law.neighbours:
        role = "leader" if j == m.leader.id else "agent"
        channel = Channel.of(m, j, aid) if m.netem is not None else None
        witness = None
        if role == "agent" and not lockstep and channel is None:
            # declared first: a drain decodes it before the neighbour's relay of the same sample
            witness = node.source(keys.topic("plant", j, "state"), wire.PlantState, j, wake=False)
            witnesses.append(witness)
        # read at the tick only: their samples do not wake the loop as they arrive (real time)
        src = node.source(keys.topic(role, j, "state"), wire.State, j, channel=channel, wake=False)
        src.admit = gate(j, role)
        if witness is not None:
            src.corroborate = _corroborated_by(witness)
        src.health = health_of(m)
        node.watch(role, j, src)
        nbrs.append(src)
        if channel is not None:
            channels.append((j, channel))
    # collision avoidance hears every other vehicle's state, apart from the law's inputs (a range
    # sensor or a local broadcast would give it these); a formation neighbour's is the law's own sample
    avoid = m.safety.avoid is not None
    proximity: list[Source] = []
    for j in nearby_vehicles(m, aid):  # none without [safety.avoid]
        src = node.source(keys.topic("agent", j, "state"), wire.State, j, wake=False)
        src.admit = gate(j, "agent")
        proximity.append(src)
    vehicles = [n for n, j in enumerate(law.neighbours) if j != m.leader.id]
    netem_control.serve(node)
    cmd = node.publisher(keys.topic("agent", aid, "cmd"), tp.COMMAND) if onboard is None else None
    tele = node.publisher(keys.topic("agent", aid, "telemetry"), tp.TELEMETRY) if onboard is None else None
    records = node.publisher(keys.topic("agent", aid, "record")) if onboard is not None else None
    batch = max(1, node.args.record_batch)
    pending: tuple[list[wire.PlantState], list[wire.Telemetry]] = ([], [])
    """With a co-located plant: the plant samples and telemetry not yet sent to the recorder."""
    last_cmd: wire.Command | None = None
    """With a co-located plant: the command of the previous tick, which its plant flies next."""
    tele_seq = 0
    await node.ready(phase=AGENT_PHASE, rejoin=rejoin.epoch)
    judged = [(aid, s) for s in own_inputs] + list(zip(law.neighbours, nbrs))
    """Each stream whose health the supervisor hears, by sender."""
    for _, s in judged:  # what was turned away before the start (a rejoin's) is no evidence
        if s.health is not None:
            s.health.reset()
    if relay_rt is not None and (origin := node.clock.origin) is not None:
        # started: the plant's samples are relayed by the tap and read at the tick; the relay goes on
        # while this loop ticks (from its first tick's instant)
        relay_rt.alive_at = max(origin + AGENT_PHASE * m.dt, node.clock.reading())
    first = 0
    rejoining = node.rejoined
    ramp = Ramp(sf.max_accel * m.dt / REJOIN_RAMP, m.dim) if node.rejoined else None
    if node.rejoined:
        first = min(m.steps, math.floor(node.mission_time() / m.dt) + 1)
        log.warning("rejoined a run under way at tick %d (t = %.2f s): tick 0 at %.3f, from the earliest of %d "
                    "samples of plant %d; gains K(0); holding until every input is fresh", first, first * m.dt,
                    rejoin.epoch() or 0.0, rejoin.samples, aid)

    holding = False
    gone_at: int | None = None
    """The tick of the plant's newest sample when its token was last seen gone (its process died)."""
    neighbours = set(law.neighbours)
    clock: list[wire.ClockLink] = []
    reported: list[skew.LinkClock] | None = None
    for k in range(first, m.steps + 1):
        await node.tick(k)
        if relay_rt is not None:
            relay_rt.alive_at = node.clock.reading()
        t = k * m.dt
        if onboard is not None:
            own = onboard.advance(k, last_cmd, _order(operator))
            publish_state(own)
            got = await node.aligned([*nbrs, *proximity], k)
        else:
            # node.tick has just drained
            own, *got = await node.aligned([*own_inputs, *nbrs, *proximity], k, drain=False)
            if k == first and relay_rt is not None:  # real time, the first tick
                if own is None and await _first_sample(node, plant):
                    own, *got = await node.aligned([*own_inputs, *nbrs, *proximity], k)
                node.quieten(plant)  # from now on read at the tick only (it woke the loop until the first)
        for w in witnesses:  # read by the corroboration alone: keep the window aligned() keeps
            w.forget_before(k - WITNESS_TICKS)
        if clocks is not None:
            estimates = clocks.report()
            if estimates is not reported:  # an estimate moved (once a block at most): said anew
                reported = estimates
                clock = [wire.ClockLink(role=c.role, src=c.src, offset=c.offset, warn=c.warn) for c in estimates]
                for c in clocks.newly_flagged(estimates):
                    log.warning("%s", skew.describe(c, f"agent/{aid}", clocks.limits))
        got, far = got[:len(nbrs)], got[len(nbrs):]
        if own is None:  # real time, before the plant's first sample: nothing to act on
            continue
        # the plant's measurements stopped while its process lives: the agent
        # sends no command (one computed from its last measurement would be flown on the vehicle as
        # it is now: a stale HOLD flew a vehicle 38 m backwards at 20 m/s), so that the plant's own
        # watchdog holds the vehicle on its fresh measurement (no valid command for cmd_timeout),
        # then lands it (cmd_cutoff); the supervisor holds meanwhile (cause "plant", LAND after
        # land_after, as the watchdog does), and the agent relays nothing, so its neighbours count it out
        stale = not lockstep and (own_inputs[0].silent_at(k) or t - own.t > sf.cmd_timeout)
        if not lockstep and own_inputs[0].gone:
            gone_at = own.k
        # a plant whose process died flies nothing until it is restarted, and a restarted one learns
        # the run's start from its agent's commands (plant/resume.py) before it publishes again
        restarting = gone_at is not None and own.k <= gone_at
        plant_silent = stale and k < m.steps
        silence: list[wire.SafetyEvent] = []
        if stale != holding:
            why = (f"plant silent (newest sample {own.t:.2f} s): no command sent until it is back; its watchdog "
                   "holds the vehicle on its own measurement" if stale else "plant back: commands sent again")
            mode = tick.supervisor.mode  # an event, logged below with the supervisor's
            silence.append(wire.SafetyEvent(k=k, t=t, vehicle=aid, src=mode, dst=mode, reason=why))
            holding = stale
        heard: list[Heard | None] = [None if msg is None else (msg.t, msg.p, msg.vel, msg.a) for msg in got]
        said = [wire.FLYING if msg is None else msg.mode for msg in got]
        suspect = frozenset(j for j, s in judged if s.health is not None and s.health.suspect)
        if lockstep or k == m.steps:
            # lockstep: a tick waits for its inputs, so nothing can be silent; the last tick:
            # the others may already have finished and left
            status = Status(modes=said, operator=_order(operator), plant_mode=modes.believed, suspect=suspect)
        else:
            # an agent that left after its last tick is not lost; only the last ticks can see that;
            # a gone leader reaches nobody
            gone = (node.gone("agent") - neighbours - {aid}) | node.gone("leader") if k < m.steps - 1 else set()
            status = Status(gone=[s.silent_at(k) for s in nbrs], modes=said, others_gone=frozenset(gone),
                            operator=_order(operator), plant_silent=plant_silent, plant_mode=modes.believed,
                            rejoining=rejoining, suspect=suspect)
        near: list[tuple[list[float], list[float]]] = []
        if avoid:
            seen = [got[n] for n in vehicles] + far
            near = [(msg.p, msg.vel) for msg in seen if msg is not None and t - msg.t <= m.links.max_age]
        out = tick.step(k, t, own.p, own.vel, own.a, heard, status, near)
        if rejoining and t - own.t <= m.dt and all(msg is not None and t - msg.t <= m.dt for msg in got):
            rejoining = False  # every input fresh (the first tick always holds): the supervisor may fly again
            log.warning("rejoin: every input fresh at t = %.2f s", t)
        if ramp is not None:
            ramp.u = ramp.limit(out.u, out.mode == wire.FLYING)
            u = ramp.u
            if not ramp.active and out.mode == wire.FLYING:
                log.warning("rejoin: the command has caught up with the law's at t = %.2f s", t)
                ramp = None
        else:
            u = out.u
        if cmd is None:
            last_cmd = wire.Command(sender=aid, seq=k, k=k, t=t, u=u, mode=out.mode)
        elif not stale or restarting:
            # restarting: the plant resumes from the last state on the wire, which these were computed from
            cmd.send(wire.Command, k, t, u=u, mode=out.mode)
        events = silence + tick.supervisor.take_events()
        for ev in events:
            log.warning("safety: t = %.2f s: %s -> %s: %s", ev.t, wire.MODES[ev.src], wire.MODES[ev.dst], ev.reason)
        links = []
        for n, (j, s) in enumerate(zip(law.neighbours, nbrs)):
            received = s.received_upto(k) if lockstep else s.received
            p50, p99 = tick.age_percentiles(n)
            # samples j sent up to its newest received (lockstep: of ticks <= k; j sends one per tick)
            sent = 0 if s.newest is None else (min(s.newest.seq, k) if lockstep else s.newest.seq) + 1
            links.append(wire.LinkStats(
                src=j, received=received, used=tick.used[n], stale=s.stale, age=out.ages[n], silent=s.silent_at(k),
                duplicates=s.duplicates, reordered=s.reordered, corrupt=s.corrupt,
                delivery=(received - s.duplicates) / sent if sent else 0.0, age_p50=p50, age_p99=p99))
        decisions = [wire.LinkDecision(src=j, seq=d.seq, now=d.now, event=d.event, at=d.at)
                     for j, ch in channels for d in ch.link.take_decisions()]
        report = wire.Telemetry(
            sender=aid, seq=tele_seq, k=k, t=t, clock=clock, netem=decisions, meas_t=own.t, p=own.p, vel=own.vel,
            a=own.a, u=u, xi=out.xi, zeta=out.zeta, kp=out.kp, kv=out.kv,
            links=links, drops=dict(node.receiver.drops), late=node.clock.late, mode=out.mode, events=events,
            gate=_with_conflicts(merged(gates), [s for _, s in judged]))
        tele_seq += 1
        if tele is not None:
            tele.put(report)
        elif records is not None:
            # one message per `batch` ticks for the recorder, within the clock's window: the
            # recorder acknowledges tick k (and the clock grants further) only once it holds it
            pending[0].append(own)
            pending[1].append(report)
            if len(pending[1]) >= batch or k == m.steps:
                records.send(wire.Record, k, t, plant=pending[0][:], telemetry=pending[1][:])
                pending[0].clear()
                pending[1].clear()
    if onboard is not None:
        onboard.close()


async def _first_sample(node: Node, plant: Source) -> bool:
    """Real time, the first tick, the plant not heard yet: wait for its first sample, ``cmd_timeout``
    at most (its plant's watchdog waits as long for a first command). At a loaded start (16 agents on
    two cores: 34 processes begin their loops at one instant) an agent's first tick often came before
    its plant's first sample had been drained; skipped, it left that agent's command and telemetry of
    tick 0 out of the run (exit 5 in most such runs). The tick is now late instead. The plant's samples
    wake the loop until then (quietened after the first tick), so the wait ends as the sample arrives.
    True once the plant has been heard; False if it stays silent (the tick has nothing to act on, and
    later ticks do not wait)."""
    try:
        await node.until(lambda: plant.newest is not None, node.mission.safety.cmd_timeout,
                         f"plant {plant.sender}'s first sample")
    except Stalled:
        pass
    return plant.newest is not None


class Ramp:
    """After a rejoin: the command leaving the agent changes by at most ``step`` [m/s^2] per tick
    once the supervisor flies again, from the HOLD command it flew, until it has caught up with the
    law's (then :attr:`active` is False and the ramp is dropped). Every command is a point between
    two commands within ``max_accel``, so within it too."""

    def __init__(self, step: float, dim: int):
        self.step = step
        self.u = [0.0] * dim
        """The command sent last (before the first: zero, what a plant holding at rest flies)."""
        self.active = True

    def limit(self, want: list[float], flying: bool) -> list[float]:
        if not flying or not self.active:
            return want
        du = [w - u for w, u in zip(want, self.u)]
        size = vec.norm(du)
        if size <= self.step:
            self.active = False
            return want
        scale = self.step / size
        return [u + d * scale for u, d in zip(self.u, du)]


REJOIN_RAMP = 1.0
"""After a rejoin, the command may go from 0 to ``max_accel`` in no less than this [s]."""


WITNESS_TICKS = 8
"""Real time: ticks of a neighbour's plant measurements kept to corroborate its relayed states (the
window :meth:`tether.node.Node.aligned` keeps of every input)."""


def _corroborated_by(witness: Source) -> Callable[[wire.State], bool]:
    """Whether a neighbour's state agrees with its plant's own measurement of the same tick, when
    that is held (the agent relays it as is: its time, position and velocity are the plant's, bit
    for bit). An insider holding the agent's key can forge ``agent/j/state``, not ``plant/j/state``."""
    def agrees(msg: wire.State) -> bool:
        seen = witness.by_tick.get(msg.k)
        return seen is None or (seen.t == msg.t and seen.p == msg.p and seen.vel == msg.vel)

    return agrees


def _with_conflicts(rejected: dict[str, int], sources: list[Source]) -> dict[str, int]:
    """The gate's rejections by reason, and the samples that conflicted with their own stream
    (``conflict``: two contents for one tick, or a plant's mode report against its earlier ones)."""
    n = sum(s.conflicts for s in sources)
    return {**rejected, "conflict": n} if n else rejected


def _order(orders: list[str]) -> str | None:
    """The operator's standing order: estop beats land."""
    return "estop" if "estop" in orders else "land" if "land" in orders else None
