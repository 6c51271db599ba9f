"""The virtual leader's process: publishes its reference sample at every tick."""

from __future__ import annotations

from leader import profile
from tether import wire
from tether.node import Node


async def run(node: Node) -> None:
    m = node.mission
    ref = profile.build(m.leader, m.dim)
    lid = m.leader.id
    state = node.publisher(node.keys.topic("leader", lid, "state"))
    await node.ready(paced=True)
    for k in range(m.steps + 1):
        await node.tick(k)
        t = k * m.dt
        p, v, a = ref(t)
        state.send(wire.State, k, t, p=p.tolist(), vel=v.tolist(), a=a.tolist())
