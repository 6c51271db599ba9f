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
    rows: tuple[list[list[float]], ...] = ([],)
    first = 0  # the tick of rows' first
    for k in range(m.steps + 1):
        await node.tick(k)
        if k - first >= len(rows[0]):  # the next block of the reference, computed at once
            first, rows = k, profile.at_ticks(ref, m.dt, k, min(m.steps + 1, k + profile.BLOCK), m.dim)
        i = k - first
        state.send(wire.State, k, k * m.dt, p=rows[0][i], vel=rows[1][i], a=rows[2][i])
