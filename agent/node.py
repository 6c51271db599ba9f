"""Agent i's process: Eq. 17 on what it hears from its plant and its in-neighbours only.

Tick k: take what it hears (:class:`agent.hearing.Hearing`: the plant's measurement of tick k, each
in-neighbour's state of tick k, the vehicles near it, the operator's orders), run the agent's tick
(:meth:`agent.tick.AgentTick.step`: the law, then the safety supervisor, then collision avoidance
when the mission asks for it), send the command to its plant and say what it did
(:class:`agent.report.Report`). In real time the agent ticks half a period after its plant and the
leader (:data:`tether.clock.AGENT_PHASE`), so that the tick-k samples are usually in by then.
"""

from __future__ import annotations

import logging
import math

from agent.hearing import Hearing
from agent.report import Report
from agent.tick import AgentTick, Heard
from netem import control as netem_control
from tether import transport as tp
from tether import vec
from tether import wire
from tether.clock import AGENT_PHASE
from tether.node import Node

log = logging.getLogger("tether")


async def run(node: Node) -> None:
    m = node.mission
    aid = node.args.node_id
    tick = AgentTick.from_mission(m, aid)
    state = node.publisher(node.keys.topic("agent", aid, "state"))
    onboard = None
    if node.args.colocate:  # lockstep: this process computes its plant (plant/onboard.py); no plant process runs
        node.clock.require("lockstep", "--colocate-plant is for lockstep runs: in real time the plant is a process "
                                       "of its own")
        from plant.onboard import Onboard

        onboard = Onboard(m, aid)

    def publish_state(msg: wire.PlantState) -> None:
        state.send(wire.State, msg.k, msg.t, p=msg.p, vel=msg.vel, a=tick.shared(msg.a), mode=tick.supervisor.mode)

    hearing = Hearing(node, tick, publish_state, onboard=onboard is not None)
    netem_control.serve(node)
    cmd = node.publisher(node.keys.topic("agent", aid, "cmd"), tp.COMMAND) if onboard is None else None
    report = Report(node, hearing, onboard=onboard is not None)
    last_cmd: wire.Command | None = None
    """With a co-located plant: the command of the previous tick, which its plant flies next."""
    await node.ready(phase=AGENT_PHASE, rejoin=hearing.rejoin.epoch)
    hearing.started()
    sf = m.safety
    first = 0
    rejoining = node.rejoined
    ramp = Ramp(sf.max_accel * m.dt / REJOIN_RAMP, m.dim) if node.rejoined else None
    if node.rejoined:
        first = min(m.steps, math.floor(node.mission_time() / m.dt) + 1)
        log.warning("rejoined a run under way at tick %d (t = %.2f s): tick 0 at %.3f, from the earliest of %d "
                    "samples of plant %d; gains K(0); holding until every input is fresh", first, first * m.dt,
                    hearing.rejoin.epoch() or 0.0, hearing.rejoin.samples, aid)
    for k in range(first, m.steps + 1):
        await node.tick(k)
        t = k * m.dt
        own: wire.PlantState | None
        silence: list[wire.SafetyEvent] = []
        if onboard is not None:
            own = onboard.advance(k, last_cmd, hearing.order)
            publish_state(own)
            got, far = await hearing.around(k)
            stale = restarting = False
        else:
            own, got, far = await hearing.inputs(k, first)
            if own is None:  # real time, before the plant's first sample: nothing to act on
                hearing.clocks()
                continue
            stale, restarting, silence = hearing.plant_stale(k, t, own, tick.supervisor.mode)
        heard: list[Heard | None] = [None if msg is None else (msg.t, msg.p, msg.vel, msg.a) for msg in got]
        status = hearing.status(k, got, plant_silent=stale and k < m.steps, rejoining=rejoining)
        near: list[tuple[list[float], list[float]]] = []
        if sf.avoid is not None:
            seen = [got[n] for n in hearing.vehicles] + far
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
        report.send(k, t, own, tick, out, u, events)
    if onboard is not None:
        onboard.close()


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
