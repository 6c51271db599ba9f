"""A simulated plant's process: one double integrator with the mission's disturbance model.

Tick k: integrate ``[t_{k-1}, t_k]`` with the command of tick k-1 (lockstep: exactly that one;
real time: the newest held, zero before the first), then publish the measurement of tick k.
"""

from __future__ import annotations

import logging

import numpy as np

from plant import double_integrator
from plant.disturbance import DisturbanceBank
from tether import wire
from tether.node import Node

log = logging.getLogger("tether")


async def run(node: Node) -> None:
    m = node.mission
    pid = node.args.node_id
    me = m.agent(pid)
    dist = DisturbanceBank.from_mission(m, [pid])
    h = m.dt
    p = np.array(me.p0, dtype=float)
    v = np.array(me.v0 if me.v0 is not None else [0.0] * m.dim, dtype=float)
    a = np.zeros(m.dim)
    cmd = node.source(node.keys.topic("agent", pid, "cmd"), wire.Command, pid)
    node.watch("agent", pid, cmd)
    state = node.publisher(node.keys.topic("plant", pid, "state"))
    await node.ready()
    zero = np.zeros(m.dim)
    for k in range(m.steps + 1):
        await node.tick(k)
        if k > 0:
            msg = await node.sample(cmd, k - 1)
            u = np.array(msg.u) if msg is not None else zero
            dv, dp = dist.increments(k - 1)
            p, v, a = double_integrator.step(p, v, u, dv[0], dp[0], h)
        t = k * h
        d = dist.value(k)[0]
        state.send(wire.PlantState, k, t, p=p.tolist(), vel=v.tolist(), a=a.tolist(), d=d.tolist())
