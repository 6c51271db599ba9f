"""Agent i's process: Eq. 17 on what it hears from its plant and its in-neighbours only.

Its plant's measurement is relayed as agent i's state (what its out-neighbours use) as soon as it
arrives, stamped with the measurement's own tick and sample time. Tick k: take the plant's
measurement of tick k and each in-neighbour's state of tick k (lockstep: exactly those; real
time: the newest held), run :meth:`agent.law.AgentLaw.step`, publish the command to its plant and
telemetry. In real time the agent ticks half a period after its plant and the leader
(``AGENT_PHASE``), so that the tick-k samples are usually in by then.
"""

from __future__ import annotations

import logging
import math
from collections import deque

import numpy as np

from agent.law import AgentLaw, neighbour_sample
from tether import transport as tp
from tether import wire
from tether.node import Node, Source

log = logging.getLogger("tether")

AGENT_PHASE = 0.5
AGE_WINDOW = 500
"""Ticks over which each link's age-of-information percentiles are taken (5 s at 100 Hz)."""
"""Real time: agents tick at ``epoch + (k + AGENT_PHASE) h``; plants and the leader at ``epoch + k h``."""


async def run(node: Node) -> None:
    m = node.mission
    aid = node.args.node_id
    law = AgentLaw.from_mission(m, aid)
    keys = node.keys
    state = node.publisher(keys.topic("agent", aid, "state"))

    feed = m.law.feedforward
    last_u = [0.0] * m.dim
    """The command of the previous tick: what the agent shares as its acceleration with
    ``feedforward = "commanded"`` (the plant's sample of tick k comes after the command of k-1)."""

    def relay(msg: wire.PlantState) -> None:
        state.send(wire.State, msg.k, msg.t, p=msg.p, vel=msg.vel, a=msg.a if feed == "measured" else last_u)

    plant = node.source(keys.topic("plant", aid, "state"), wire.PlantState, aid, on_message=relay)
    node.watch("plant", aid, plant)
    nbrs: list[Source] = []
    for j in law.neighbours:
        role = "leader" if j == m.leader.id else "agent"
        src = node.source(keys.topic(role, j, "state"), wire.State, j, link=True)
        node.watch(role, j, src)
        nbrs.append(src)
    node.netem_control()
    cmd = node.publisher(keys.topic("agent", aid, "cmd"), tp.COMMAND)
    tele = node.publisher(keys.topic("agent", aid, "telemetry"), tp.TELEMETRY)
    await node.ready(phase=AGENT_PHASE)

    d = m.dim
    lockstep = node.args.clock == "lockstep"
    policy = m.links
    kp, kv = law.params.kp0.copy(), law.params.kv0.copy()
    used = [0] * len(nbrs)
    nb_p, nb_v, nb_a = (np.zeros((len(nbrs), d)) for _ in range(3))
    holding = False
    windows = [deque(maxlen=AGE_WINDOW) for _ in nbrs]
    """Per link, the ages of the samples used over the last AGE_WINDOW ticks."""
    for k in range(m.steps + 1):
        await node.tick(k)
        t = k * m.dt
        own, *heard = await node.aligned([plant, *nbrs], k)
        if own is None:  # real time, before the plant's first sample: nothing to act on
            continue
        if not lockstep and plant.silent_at(k):
            # the vehicle is gone (its plant withdrew or died): hold, i.e. command nothing; its
            # neighbours stop hearing this agent and count it out after max_age
            if not holding:
                log.warning("plant %d is silent at t = %.2f s: holding (no commands)", aid, t)
            holding = True
            continue
        if holding:
            log.warning("plant %d is back at t = %.2f s", aid, t)
            holding = False
        p, v = np.array(own.p), np.array(own.vel)
        a = np.array(own.a if feed == "measured" else last_u)  # what this agent shares
        ages, oks = [], []
        for n, msg in enumerate(heard):
            age = t - msg.t if msg is not None else math.nan
            sample = (np.array(msg.p), np.array(msg.vel), np.array(msg.a)) if msg is not None else None
            nb_p[n], nb_v[n], nb_a[n], ok = neighbour_sample(p, v, a, law.deltas[n], sample, age,
                                                             policy.max_age, policy.compensate)
            used[n] += ok
            ages.append(age)
            oks.append(ok)
        if feed == "none":
            nb_a[:] = 0.0
        u, xi, zeta, kp_next, kv_next = law.step(p, v, nb_p, nb_v, nb_a, kp, kv)
        last_u = u.tolist()
        cmd.send(wire.Command, k, t, u=last_u)
        links = []
        for n, (j, s) in enumerate(zip(law.neighbours, nbrs)):
            received = s.received_upto(k) if lockstep else s.received
            if oks[n]:
                windows[n].append(ages[n])
            p50, p99 = np.percentile(windows[n], (50, 99)).tolist() if windows[n] else (math.nan, math.nan)
            # samples j sent up to its newest received (lockstep: of ticks <= k; j sends one per tick)
            sent = 0 if s.newest is None else (min(s.newest.seq, k) if lockstep else s.newest.seq) + 1
            links.append(wire.LinkStats(
                src=j, received=received, used=used[n], stale=s.stale, age=ages[n], silent=s.silent_at(k),
                duplicates=s.duplicates, reordered=s.reordered, corrupt=s.corrupt,
                delivery=(received - s.duplicates) / sent if sent else 0.0, age_p50=p50, age_p99=p99))
        decisions = [wire.LinkDecision(src=j, seq=d.seq, now=d.now, event=d.event, at=d.at)
                     for j, s in zip(law.neighbours, nbrs) if s.channel is not None
                     for d in s.channel.link.take_decisions()]
        tele.send(wire.Telemetry, k, t, netem=decisions, meas_t=own.t, p=own.p, vel=own.vel, a=own.a, u=last_u, xi=xi.tolist(),
                  zeta=zeta.tolist(), kp=kp.tolist(), kv=kv.tolist(), links=links,
                  drops=dict(node.receiver.drops), late=getattr(node.clock, "late", 0))
        kp, kv = kp_next, kv_next
