"""A simulated plant's process (``plant``: one vehicle) or a world's (``world``: every vehicle of
a ``[payload]`` mission and the payload), around :func:`plant.base.build`.

Tick k: advance ``[t_{k-1}, t_k]`` with each vehicle's command of tick k-1 (lockstep: exactly
that one; real time: the newest held, zero before the first), then publish each vehicle's
measurement of tick k on its own ``plant/<id>/state`` key, stamped with its id. A world also
declares each vehicle's ``plant`` liveliness token and publishes the payload's state on
``world/0/state``: agents cannot tell a world from single plants.
"""

from __future__ import annotations

import logging

import numpy as np

from plant import base
from plant.crazyflie import LinkLost
from tether import transport as tp
from tether import wire
from tether import mission as ms
from tether.node import Node

log = logging.getLogger("tether")


async def run(node: Node) -> None:
    """One vehicle: the agent ``node.args.node_id``."""
    await _host(node, [node.args.node_id], world=False)


async def run_world(node: Node) -> None:
    """Every vehicle of the mission and its payload."""
    await _host(node, node.mission.agent_ids, world=True)


async def _host(node: Node, ids: list[int], world: bool) -> None:
    m, keys = node.mission, node.keys
    live = not node.clock.lockstep
    if not live and any(isinstance(m.agent(i).plant, ms.CrazyfliePlant) for i in ids):
        raise ValueError("a crazyflie is a real vehicle: fly this mission with --clock realtime")
    (plant,) = base.build(m, ids, live=live)
    h = m.dt
    cmds = []
    for aid in ids:
        src = node.source(keys.topic("agent", aid, "cmd"), wire.Command, aid)
        node.watch("agent", aid, src)
        cmds.append(src)
    states = [node.publisher(keys.topic("plant", aid, "state"), sender=aid) for aid in ids]
    payload = node.publisher(keys.topic("world", 0, "state")) if world else None
    if world:  # each hosted vehicle is a plant to the agents, the recorder and the launcher
        node.hold(*(tp.declare_token(node.session, keys.token("plant", aid)) for aid in ids))
    await node.ready()
    zero = np.zeros(m.dim)
    try:
        for k in range(m.steps + 1):
            await node.tick(k)
            try:
                if k > 0:
                    u = []
                    for src in cmds:
                        msg = await node.sample(src, k - 1)
                        u.append(np.array(msg.u) if msg is not None else zero)
                    plant.step(np.array(u))
                s = plant.state()
            except LinkLost as exc:
                # say so (the agent sees its plant's token go and holds), keep out of the swarm's
                # way until the mission's end, then fail
                log.error("%s: withdrawing from the swarm", exc)
                node.withdraw()
                await node.tick(m.steps)
                raise
            t = k * h
            for r, pub in enumerate(states):
                pub.send(wire.PlantState, k, t, p=s.p[r].tolist(), vel=s.v[r].tolist(), a=s.a[r].tolist(),
                         d=s.d[r].tolist())
            if payload is not None:
                ex = s.extra
                payload.send(wire.WorldState, k, t, p=ex["payload_p"].tolist(), vel=ex["payload_v"].tolist(),
                             tension=ex["tension"].tolist(), slack_events=ex["slack_events"].astype(int).tolist())
    finally:
        plant.close()
