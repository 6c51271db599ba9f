"""Agent i's process: Eq. 17 on what it hears from its plant and its in-neighbours only.

Tick k: take its plant's measurement of tick k, publish it as agent i's state (what its
out-neighbours use), take each in-neighbour's state of tick k (lockstep) or the newest held (real
time), run :meth:`agent.law.AgentLaw.step`, publish the command to its plant and telemetry.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from agent.law import AgentLaw
from tether import wire
from tether.node import Node, Source

log = logging.getLogger("tether")


async def run(node: Node) -> None:
    m = node.mission
    aid = node.args.node_id
    law = AgentLaw.from_mission(m, aid)
    keys = node.keys
    plant = node.source(keys.topic("plant", aid, "state"), wire.PlantState, aid)
    node.watch("plant", aid, plant)
    nbrs: list[Source] = []
    for j in law.neighbours:
        role = "leader" if j == m.leader.id else "agent"
        src = node.source(keys.topic(role, j, "state"), wire.State, j)
        node.watch(role, j, src)
        nbrs.append(src)
    state = node.publisher(keys.topic("agent", aid, "state"))
    cmd = node.publisher(keys.topic("agent", aid, "cmd"))
    tele = node.publisher(keys.topic("agent", aid, "telemetry"))
    await node.ready()

    d = m.dim
    kp, kv = law.params.kp0.copy(), law.params.kv0.copy()
    used = [0] * len(nbrs)
    nb_p, nb_v, nb_a = (np.zeros((len(nbrs), d)) for _ in range(3))
    for k in range(m.steps + 1):
        await node.tick(k)
        t = k * m.dt
        own = await node.sample(plant, k)
        if own is None:  # real time, before the plant's first sample: nothing to act on
            continue
        state.send(wire.State, k, t, p=own.p, vel=own.vel, a=own.a)
        ages = []
        for n, src in enumerate(nbrs):
            msg = await node.sample(src, k)
            if msg is None:
                ages.append(math.nan)
                continue
            nb_p[n], nb_v[n], nb_a[n] = msg.p, msg.vel, msg.a
            used[n] += 1
            ages.append(t - msg.t)
        p, v = np.array(own.p), np.array(own.vel)
        u, xi, zeta, kp_next, kv_next = law.step(p, v, nb_p, nb_v, nb_a, kp, kv)
        cmd.send(wire.Command, k, t, u=u.tolist())
        links = [wire.LinkStats(src=j, received=s.received, used=used[n], stale=s.stale, age=ages[n], silent=s.silent)
                 for n, (j, s) in enumerate(zip(law.neighbours, nbrs))]
        tele.send(wire.Telemetry, k, t, p=own.p, vel=own.vel, a=own.a, u=u.tolist(), xi=xi.tolist(),
                  zeta=zeta.tolist(), kp=kp.tolist(), kv=kv.tolist(), links=links,
                  drops=dict(node.receiver.drops), late=getattr(node.clock, "late", 0))
        kp, kv = kp_next, kv_next
