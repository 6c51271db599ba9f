"""What agent i hears: its plant, its in-neighbours, the vehicles near it and the operator, each
sample checked by the plausibility gate (:mod:`tether.gate`) before it is stored.

Its plant's measurement is relayed as agent i's state (what its out-neighbours use) as soon as it
arrives, stamped with the measurement's own tick and sample time, where the clock says
(:meth:`tether.clock.Clock.hook`: in real time on Zenoh's callback thread, without waiting for the
event loop, :mod:`agent.relay`; in lockstep from the loop). At tick k, :meth:`Hearing.inputs`
takes the plant's measurement of tick k and each in-neighbour's state of tick k (lockstep:
exactly those; real time: the newest held), and :meth:`Hearing.status` says what the supervisor
must know beyond the samples: who is silent or gone, the operator's order, the plant's mode.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from agent.relay import Relay
from agent.safety import Status
from agent.tick import AgentTick
from leader import profile
from plant import resume
from tether import skew, wire
from tether.clock import AGENT_PHASE
from tether.gate import Gate, PlantModes, for_sender, health_of
from tether.inputs import Source
from tether.mission import nearby_vehicles
from tether.node import Node, Stalled
from tether.rejoin import Rejoin

log = logging.getLogger("tether")

LEAD_LIMIT = 0.05
"""The most [s] the gate's ``future`` bound is moved for a sender whose clock is seen ahead
(:func:`sender_lead`): 50 ms, ten times what hosts synchronised by chrony or PTP disagree by on a
LAN, and five periods at 100 Hz. A sender further ahead is not corrected for beyond it (its samples
stay rejected as ``future`` and the link stays flagged: its host's clock must be fixed), and no
estimate, however forged, opens the gate wider."""

FIRST_SAMPLES = 5
"""The gate allows for a sender's lead once its link has this many samples (:func:`link_offset`), so
that a skewed sender's first samples are not all rejected as ``future`` and its stream judged a
forgery before the link's estimate is in (0.75 s)."""

WITNESS_TICKS = 8
"""Real time: ticks of a neighbour's plant measurements kept to corroborate its relayed states (the
window :meth:`tether.node.Node.aligned` keeps of every input, :data:`tether.clock.MAX_LAG`)."""


def sender_lead(estimate: float | None, period: float, limit: float = LEAD_LIMIT) -> float:
    """How far ahead [s] the gate takes a sender's clock to be, for its ``future`` check: where the
    link's offset bound ``estimate`` (:func:`link_offset`) proves the sender ahead by more than half a
    period (below ``-period / 2``, the flag of :func:`tether.skew.bounds`), ``-estimate`` up to
    ``limit``; otherwise (no bound yet, within the bounds, the receiver ahead, not finite) 0. Pure.

    Nothing moves the gate by more than ``limit``, however forged, and a sample let through must
    still be where its sender could be (the gate's ``jump`` rule)."""
    if estimate is None or not estimate < skew.bounds(period)[0]:
        return 0.0
    return min(-estimate, limit)


def link_offset(link: skew.LinkEstimator) -> float | None:
    """The offset bound [s] the gate allows for on ``link``: the smallest ``now - t`` of the link's
    window (its complete blocks' minima and the block being filled: the last 2 s), from
    :data:`FIRST_SAMPLES` samples on; None before. Pure.

    Not the link's reported estimate (the median of the minima, :mod:`tether.skew`): a delay never
    makes a sender look ahead, but a stall (a loaded host delivering a burst late) raises the median
    for seconds, and a skewed sender's samples were then rejected as ``future`` again (measured:
    a rehearsal's estimate at +50..+600 ms for 3 s, agent 4 holding). The smallest value is the
    strongest proof of a lead in the window; only a real lead or a forged stamp lowers it, and a
    forged one moves the gate by :data:`LEAD_LIMIT` at most, for the 2 s it stays in the window."""
    if link.samples < FIRST_SAMPLES:
        return None
    return min([*link.minima, link.current_min])


class Hearing:
    """Agent ``node.args.node_id``'s inputs, declared on ``node`` (before :meth:`Node.ready`).

    ``publish_state``: relays a plant measurement as the agent's state. ``onboard``: the plant is
    computed in this process (:mod:`plant.onboard`), so no plant stream is heard."""

    def __init__(self, node: Node, tick: AgentTick, publish_state: Callable[[wire.PlantState], None],
                 onboard: bool) -> None:
        m = node.mission
        aid = node.args.node_id
        keys = node.keys
        clock = node.clock
        self.node, self.m, self.aid, self.neighbours = node, m, aid, tick.law.neighbours
        self.last = m.steps
        self.cmd_timeout = m.safety.cmd_timeout
        self.gates: list[Gate] = []
        # each input link's clock offset, from sample times against arrival times (tether/skew.py),
        # observed before the gate, which rejects a sender too far ahead (real time)
        self.offsets = clock.offsets(m.dt)
        self.clock: list[wire.ClockLink] = []
        """The offsets as last reported (telemetry's ``clock``)."""
        self._reported: list[skew.LinkClock] | None = None
        # a restarted agent rejoins a run under way (real time); its plant (same host, same clock) is
        # still ticking, and the earliest arrival of its samples gives the run's start instant
        self.rejoin = Rejoin(clock.wall)
        # the leader's samples are checked against its profile (the mission's [leader]), in plain floats
        self._expected = profile.scalar(m.leader, m.dim)
        self.operator: list[str] = []
        """The operator's orders received (``land``, ``estop``), in order."""
        node.source(keys.safety, wire.SafetyCommand, 0, on_message=self._order, keep=False)
        self.own: list[Source] = []
        """The own plant's stream (none with the plant on board)."""
        self.modes = PlantModes(m.safety.mode_confirm)
        """The own plant's report of its mode, believed as far as its samples agree (from its key alone)."""
        self.relay: Relay | None = None
        self.plant: Source | None = None
        if not onboard:
            key = keys.topic("plant", aid, "state")
            # until the start each sample wakes the loop: a restarted agent learns the run's start from them
            relay = self.relay = Relay(aid, m.dim, m.dt, for_sender(m, aid, None), lambda: clock.origin,
                                       publish_state, node.count_drop)
            relay.alive_at = math.inf  # no stall before the first tick (it relays nothing before the start)

            def on_loop(msg: wire.PlantState) -> None:
                if msg is not plant.newest:  # not newer than the last (a replay, a duplicate): never fresh
                    node.count_drop("stale_relay")
                    return
                publish_state(msg)

            on_message, tap = clock.hook(on_loop, relay)
            plant = self.plant = node.source(key, wire.PlantState, aid, on_message=on_message, tap=tap)
            plant.admit = self._gate(aid, "plant")
            plant.health = health_of(m)
            plant.consistent = lambda msg: self.modes.observe(msg.k, msg.mode)
            node.watch("plant", aid, plant)
            self.own.append(plant)
            resume.serve(node, aid, plant)  # a restarted plant asks for its last state (plant/resume.py)
        if m.netem is not None:
            from netem.link import Channel  # only a mission with [netem] loads the emulator
        self.nbrs: list[Source] = []
        self.channels: list[tuple[int, Any]] = []
        """The emulated in-links, for their decision log."""
        self.witnesses: list[Source] = []
        """Real time: each agent in-neighbour's own plant's measurements (plant/j/state, which only
        plant j may publish), against which its relayed state is corroborated."""
        for j in self.neighbours:
            role = "leader" if j == m.leader.id else "agent"
            channel = Channel.of(m, j, aid) if m.netem is not None else None
            witness = None
            if role == "agent" and not clock.exact and channel is None:  # real time, as the arrival checks
                # declared first: a drain decodes it before the neighbour's relay of the same sample
                witness = node.source(keys.topic("plant", j, "state"), wire.PlantState, j, wake=False)
                self.witnesses.append(witness)
            # read at the tick only: their samples do not wake the loop as they arrive (real time)
            src = node.source(keys.topic(role, j, "state"), wire.State, j, channel=channel, wake=False)
            src.admit = self._gate(j, role)
            if witness is not None:
                src.corroborate = _corroborated_by(witness)
            src.health = health_of(m)
            node.watch(role, j, src)
            self.nbrs.append(src)
            if channel is not None:
                self.channels.append((j, channel))
        # collision avoidance hears every other vehicle's state, apart from the law's inputs (a range
        # sensor or a local broadcast would give it these); a formation neighbour's is the law's own sample
        self.proximity: list[Source] = []
        for j in nearby_vehicles(m, aid):  # none without [safety.avoid]
            src = node.source(keys.topic("agent", j, "state"), wire.State, j, wake=False)
            src.admit = self._gate(j, "agent")
            self.proximity.append(src)
        self.vehicles = [n for n, j in enumerate(self.neighbours) if j != m.leader.id]
        """The positions in :attr:`nbrs` of the in-neighbours that are vehicles (not the leader)."""
        self.judged = [(aid, s) for s in self.own] + list(zip(self.neighbours, self.nbrs))
        """Each stream whose health the supervisor hears, by sender."""
        self._all = [*self.own, *self.nbrs, *self.proximity]
        """Every input read at the tick, in :meth:`inputs`' order."""
        self._others = set(self.neighbours) | {aid}
        self._holding = False
        self._gone_at: int | None = None
        """The tick of the plant's newest sample when its token was last seen gone (its process died)."""

    def _order(self, msg: wire.SafetyCommand) -> None:
        if msg.action not in self.operator:
            log.warning("operator: %s (%s)", msg.action, msg.reason or "no reason given")
            self.operator.append(msg.action)

    @property
    def order(self) -> str | None:
        """The operator's standing order: estop beats land."""
        return "estop" if "estop" in self.operator else "land" if "land" in self.operator else None

    def _gate(self, sender: int, role: str) -> Callable[[Any], str | None]:
        node, clock, rejoin, offsets = self.node, self.node.clock, self.rejoin, self.offsets
        # real time: a sample is judged at its arrival (a neighbour's waits in its queue until the tick),
        # on the receiver's clock moved by the sender's estimated lead, where the link is flagged
        # for a sender ahead (sender_lead): a skewed sender is not taken for one from the future
        now = clock.arrivals(node.arrival)
        if now is not None and offsets is not None:
            now = self._corrected(now, offsets.link(role, sender))
        g = for_sender(self.m, sender, now, expect=self._expected if role == "leader" else None)
        self.gates.append(g)

        def admit(msg: Any) -> str | None:
            if clock.unstarted():
                # before this process's start: samples of a run already under way
                if role == "plant":
                    rejoin.observe(msg.k, msg.t)
                return "before start"
            if offsets is not None:
                offsets.observe(role, sender, msg.t, node.arrival())
            why = g.check(msg)
            if why is not None and g.rejected[why] in (1, 10, 100, 1000):  # say so, without flooding the log
                log.warning("gate: sample of %d for tick %d rejected (%s), %d so far", sender, msg.k, why,
                            g.rejected[why])
            return why

        return admit

    def _corrected(self, now: Callable[[], float], link: skew.LinkEstimator) -> Callable[[], float]:
        """``now`` [s, mission time] moved by :func:`sender_lead` of ``link``'s offset bound
        (:func:`link_offset`, a minimum over at most 9 numbers: cheap at every sample)."""
        h = self.m.dt

        def corrected() -> float:
            return now() + sender_lead(link_offset(link), h)

        return corrected

    def started(self) -> None:
        """The run has started (:meth:`Node.ready` returned): what was turned away before (a
        rejoin's) is no evidence; the relay goes on while the loop ticks, from its first tick's instant."""
        for _, s in self.judged:
            if s.health is not None:
                s.health.reset()
        origin = self.node.clock.origin
        if self.relay is not None and origin is not None:
            self.relay.alive_at = max(origin + AGENT_PHASE * self.m.dt, self.node.clock.reading())

    async def inputs(self, k: int, first: int) -> tuple[wire.PlantState | None, list[Any], list[Any]]:
        """The own plant's measurement (None: not heard yet, real time), the in-neighbours' states
        and the nearby vehicles' at tick ``k`` (called right after :meth:`Node.tick`, which drained)."""
        node = self.node
        if self.relay is not None:
            self.relay.alive_at = node.clock.reading()
        sources = self._all
        got = await node.aligned(sources, k, drain=False)
        if self.plant is not None and k == first:
            if got[0] is None and await _first_sample(node, self.plant):
                got = await node.aligned(sources, k)
            node.quieten(self.plant)  # from now on read at the tick only (it woke the loop until the first)
        for w in self.witnesses:  # read by the corroboration alone: keep the window aligned() keeps
            w.forget_before(k - WITNESS_TICKS)
        own = got[0] if self.own else None
        rest = got[len(self.own):]
        return own, rest[:len(self.nbrs)], rest[len(self.nbrs):]

    async def around(self, k: int) -> tuple[list[Any], list[Any]]:
        """With the plant on board: the in-neighbours' and the nearby vehicles' states at tick ``k``."""
        got = await self.node.aligned([*self.nbrs, *self.proximity], k)
        return got[:len(self.nbrs)], got[len(self.nbrs):]

    def clocks(self) -> list[wire.ClockLink]:
        """The input links' clock offsets, said anew when an estimate moved (once a block at most);
        the flagged ones logged once."""
        offsets = self.offsets
        if offsets is not None:
            estimates = offsets.report()
            if estimates is not self._reported:
                self._reported = estimates
                self.clock = [wire.ClockLink(role=c.role, src=c.src, offset=c.offset, warn=c.warn) for c in estimates]
                for c in offsets.newly_flagged(estimates):
                    log.warning("%s", skew.describe(c, f"agent/{self.aid}", offsets.limits))
        return self.clock

    def _gone(self, k: int) -> frozenset[int]:
        """The other members whose tokens went, as far as this agent's reachability goes at tick ``k``:
        an agent that left after its last tick is not lost (only the last ticks can see that); a
        gone leader reaches nobody."""
        if k >= self.last - 1:
            return frozenset()
        gone = self.node.ingress.gone
        return (gone("agent") - self._others) | gone("leader")

    def plant_stale(self, k: int, t: float, own: wire.PlantState, mode: int) -> tuple[bool, bool, list[wire.SafetyEvent]]:
        """Whether the plant's measurements stopped while its process lives (``stale``), whether
        it is restarting after its process died, and the event of a change of either, at tick
        ``k`` (``t`` [s]), the supervisor in ``mode``.

        Stale, the agent sends no command (one computed from its last measurement would be flown on
        the vehicle as it is now: a stale HOLD flew a vehicle 38 m backwards at 20 m/s), so that the
        plant's own watchdog holds the vehicle on its fresh measurement (no valid command for
        cmd_timeout), then lands it (cmd_cutoff); the supervisor holds meanwhile (cause "plant",
        LAND after land_after, as the watchdog does), and the agent relays nothing, so its
        neighbours count it out. A plant whose process died flies nothing until it is restarted,
        and a restarted one learns the run's start from its agent's commands (plant/resume.py)
        before it publishes again."""
        clock, plant = self.node.clock, self.own[0]
        stale = clock.silent(plant, k) or clock.overdue(t - own.t, self.cmd_timeout)
        if clock.gone(plant):
            self._gone_at = own.k
        restarting = self._gone_at is not None and own.k <= self._gone_at
        silence: list[wire.SafetyEvent] = []
        if stale != self._holding:
            why = (f"plant silent (newest sample {own.t:.2f} s): no command sent until it is back; its watchdog "
                   "holds the vehicle on its own measurement" if stale else "plant back: commands sent again")
            silence.append(wire.SafetyEvent(k=k, t=t, vehicle=self.aid, src=mode, dst=mode, reason=why))
            self._holding = stale
        return stale, restarting, silence

    def status(self, k: int, got: list[Any], plant_silent: bool, rejoining: bool) -> Status:
        """What the supervisor knows at tick ``k`` beyond the samples ``got`` of the in-neighbours."""
        last, clock = self.last, self.node.clock
        said = [wire.FLYING if msg is None else msg.mode for msg in got]
        suspect = frozenset(j for j, s in self.judged if s.health is not None and s.health.suspect)
        if k == last:
            # the last tick: the others may already have finished and left
            return Status(modes=said, operator=self.order, plant_mode=self.modes.believed, suspect=suspect)
        return Status(gone=[clock.silent(s, k) for s in self.nbrs], modes=said,
                      others_gone=clock.departed(lambda: self._gone(k)), operator=self.order,
                      plant_silent=plant_silent, plant_mode=self.modes.believed, rejoining=rejoining,
                      suspect=suspect)


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


def _corroborated_by(witness: Source) -> Callable[[wire.State], bool]:
    """Whether a neighbour's state agrees with its plant's own measurement of the same tick, when
    that is held (the agent relays it as is: its time, position and velocity are the plant's, bit
    for bit). An insider holding the agent's key can forge ``agent/j/state``, not ``plant/j/state``."""
    def agrees(msg: wire.State) -> bool:
        seen = witness.by_tick.get(msg.k)
        return seen is None or (seen.t == msg.t and seen.p == msg.p and seen.vel == msg.vel)

    return agrees
