"""A restarted simulated plant resumes from the last state its own samples put on the wire.

A simulated vehicle lives in its plant process: when that process is killed and its unit's
``Restart=`` brings it back, a new process would start again from the mission's initial state,
a teleport. Instead the new process

1. **learns the run's start instant and tick** from its agent's commands, which still come (the
   agent holds on ``plant silent`` meanwhile): each leaves at ``epoch + (k + AGENT_PHASE) h`` on
   the agent's clock (same host, same clock), so the earliest ``wall - t - AGENT_PHASE h`` over
   :data:`tether.rejoin.SAMPLES` of them is the start instant, late by the smallest
   agent-to-plant delay (:class:`tether.rejoin.Rejoin`);
2. **asks its agent for its last state** (``agent/<i>/lastplant``, a Zenoh queryable its agent
   answers with the newest ``plant/<i>/state`` sample it received: the last state the plant itself
   published, as it was encoded, stamp and sender included);
3. **resumes there**: position and velocity of that sample, at the next tick; the time it was down
   is a frozen vehicle (no invented physics for a process that was not running); the attitude and
   body rates of a quadrotor restart level and at rest, its integrators empty; the disturbance
   models continue at the mission time they would have reached.

It **refuses to start** (exit status 1, the reason logged) rather than teleport when no valid last
state comes within :data:`ASK_FOR` seconds (the agent is down too, or never heard its plant),
when the state is malformed, not finite, of another sender, or stamped after the tick it would
resume at, or when the vehicle was on the ground or stopped (``LANDED``, ``ESTOP``: a restart does
not take off again). Samples of the run heard before this process's start (the agent's commands)
are not acted on.

A Crazyflie is a real vehicle with its own state and is not resumed here (its link is re-opened:
:meth:`plant.crazyflie.CrazyfliePlant.recover`); a world (``[payload]``) holds every vehicle and the
payload in one process and is not resumed either.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import TYPE_CHECKING, Any

import msgspec

from tether import mission as ms
from tether import wire
from tether.clock import AGENT_PHASE
from tether.rejoin import Rejoin

if TYPE_CHECKING:
    import zenoh

    from plant.rest import Resting
    from tether.inputs import Source
    from tether.node import Node

log = logging.getLogger("tether")

TOPIC = "lastplant"
"""``agent/<i>/lastplant``: agent i's queryable answering its plant's newest sample."""
ASK_FOR = 3.0
"""How long a restarted plant waits for its agent's answer [s]."""


def key(node: Node, aid: int) -> str:
    return node.keys.topic("agent", aid, TOPIC)


# --------------------------------------------------------------------------- the agent's side
def serve(node: Node, aid: int, plant: Source) -> None:
    """Agent ``aid`` answers queries on ``agent/<aid>/lastplant`` with the newest sample its plant
    source holds (nothing before the first one)."""

    def answer(query: zenoh.Query) -> None:
        newest = plant.newest
        if newest is not None:
            query.reply(key(node, aid), wire.encode(newest))

    node.queryable(key(node, aid), answer)


# --------------------------------------------------------------------------- the plant's side
def check(payload: bytes, aid: int, dim: int, before: int) -> tuple[wire.PlantState | None, str]:
    """The answer ``payload`` as the state to resume vehicle ``aid`` from, or ``None`` and why not.
    ``before``: the tick it would resume at (the state must be older)."""
    try:
        msg = wire.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
        return None, "the answer is not a tether message"
    if not isinstance(msg, wire.PlantState) or msg.v != wire.WIRE_VERSION:
        return None, "the answer is not a plant state of this wire version"
    if msg.sender != aid:
        return None, f"the answer is plant {msg.sender}'s state, not plant {aid}'s"
    if len(msg.p) != dim or len(msg.vel) != dim:
        return None, f"the state has {len(msg.p)}/{len(msg.vel)} components, not {dim}"
    if not all(math.isfinite(x) for x in (*msg.p, *msg.vel, msg.t)):
        return None, "the state is not finite"
    if not 0 <= msg.k < before:
        return None, f"the state is of tick {msg.k}, not before tick {before} it would resume at"
    if msg.mode in (wire.MODES.index("LANDED"), wire.MODES.index("ESTOP")):
        return None, f"the vehicle was {wire.MODES[msg.mode]}: a restart does not take it off again"
    return msg, ""


class Resumer:
    """What a restarted plant process of vehicle ``aid`` needs to rejoin: the start instant, from
    its agent's commands heard before its own start (``cmds``: its command sources), and the last
    state, asked of its agent after the start."""

    def __init__(self, node: Node, aid: int, cmds: list[Source]):
        self.node, self.aid = node, aid
        self.rejoin = Rejoin(node.clock.wall)
        self.lag = AGENT_PHASE * node.mission.dt
        for src in cmds:
            src.admit = self._admit

    def _admit(self, msg: Any) -> str | None:
        if self.node.clock.unstarted():
            self.rejoin.observe(msg.k, msg.t)  # before this process's start: a run under way
            return "before start"
        return None

    def epoch(self) -> float | None:
        e = self.rejoin.epoch()
        return None if e is None else e - self.lag

    async def ask(self, before: int) -> wire.PlantState:
        """The last state to resume from; raises :class:`~tether.node.Stalled` (the process exits
        1) with the reason when there is none."""
        from tether.node import Stalled

        m, node = self.node.mission, self.node
        where = key(node, self.aid)

        def get() -> list[bytes]:
            out = []
            for reply in node.session.get(where, timeout=ASK_FOR):
                if reply.ok is not None:
                    out.append(reply.ok.payload.to_bytes())
            return out

        answers = await asyncio.to_thread(get)
        why = f"no answer on {where} within {ASK_FOR:g} s (its agent is down, or never heard its plant)"
        best: wire.PlantState | None = None
        for payload in answers:
            msg, why = check(payload, self.aid, m.dim, before)
            if msg is not None and (best is None or msg.k > best.k):
                best = msg
        if best is None:
            raise Stalled(f"plant {self.aid} restarted into a run under way and has no last state to resume from "
                          f"({why}); refusing to start rather than restart from the initial state")
        return best


def resumed(m: ms.Mission, aid: int, last: wire.PlantState, k: int) -> Resting:
    """Vehicle ``aid``'s simulated plant placed at ``last``'s position and velocity, its
    disturbances at tick ``k``."""
    from plant import base
    from plant.build import build
    from plant.rest import Resting

    d = m.dim
    v0 = list(last.vel) + [0.0] * (len(m.agent(aid).p0) - d)
    agents = [msgspec.structs.replace(a, p0=list(last.p), v0=v0[:len(last.p)]) if a.id == aid else a
              for a in m.agents]
    (inner,) = build(msgspec.structs.replace(m, agents=agents), [aid], live=True)
    if not isinstance(inner, (base.DoubleIntegratorPlant, base.VehiclePlant)):
        raise TypeError(f"agent {aid}: a {type(inner).__name__} is not resumed (plant/resume.py)")
    inner.seek(k)
    return Resting(inner, d, m.safety.ground)
