"""The virtual leader's process: publishes its reference sample at every tick.

Lockstep, plants co-located (``--record-batch``, given by ``tether run``): it also sends the
recorder its states of ``--record-batch`` ticks in one :class:`~tether.wire.Record`, as the agents
send theirs, and the recorder listens for those instead of every state: it then wakes once a record,
not once a tick (the leader's per-tick states go to its out-neighbours only)."""

from __future__ import annotations

from leader import profile
from tether import wire
from tether.node import Node


async def run(node: Node) -> None:
    m = node.mission
    ref = profile.build(m.leader, m.dim)
    lid = m.leader.id
    state = node.publisher(node.keys.topic("leader", lid, "state"))
    batch = node.args.record_batch  # 0 unless given (the leader's --record-batch defaults to none)
    if batch:
        node.clock.require("lockstep", "--record-batch is for lockstep runs: in real time the recorder hears every state")
    records = node.publisher(node.keys.topic("leader", lid, "record")) if batch else None
    pending: list[wire.State] = []
    await node.ready(paced=True)
    rows: tuple[list[list[float]], ...] = ([],)
    first = 0  # the tick of rows' first
    for k in range(m.steps + 1):
        await node.tick(k)
        if k - first >= len(rows[0]):  # the next block of the reference, computed at once
            first, rows = k, profile.at_ticks(ref, m.dt, k, min(m.steps + 1, k + profile.BLOCK), m.dim)
        i = k - first
        t = k * m.dt
        msg = wire.State(sender=lid, seq=state.seq, k=k, t=t, p=rows[0][i], vel=rows[1][i], a=rows[2][i])
        state.put(msg)
        if records is not None:
            pending.append(msg)
            if len(pending) >= batch or k == m.steps:  # the agents' blocks: ticks 0 .. batch-1, ...
                records.send(wire.Record, k, t, leader=pending[:])
                pending.clear()
