"""A plant's process (``plant``: one vehicle) or a world's (``world``: every vehicle of a
``[payload]`` mission and the payload, or every simulated vehicle of a mission without one when
``tether run --shared-plants`` asks, as a :class:`plant.base.Fleet`), around :func:`plant.build.build`
and one command watchdog per vehicle (:mod:`plant.watchdog`).

Tick k: advance ``[t_{k-1}, t_k]`` with what each vehicle's watchdog decides from its agent's
command of tick k-1 (lockstep: exactly that one, which always arrives, so the watchdog only acts on
the operator; real time: the newest held, whose age is ``t_k`` minus its stamp, and one for a tick
beyond the plant's own is not valid), the operator's last :class:`~tether.wire.SafetyCommand` (on
``control/0/safety``, sender 0, obeyed at the next tick) and the vehicle's measurement of tick k-1;
then publish each vehicle's measurement of tick k with its watchdog's mode on its own
``plant/<id>/state`` key, stamped with its id. Every mode change is logged with its reason. What
LANDED and ESTOP do to a simulated vehicle is :class:`plant.rest.Resting`'s; a Crazyflie does it
itself. A world also declares each vehicle's ``plant`` liveliness token and publishes the
payload's state (if any) on ``world/0/state``: agents cannot tell a world from single plants. A
world never hosts a Crazyflie: each real vehicle has a process of its own.

A Crazyflie's blocking cflib calls (connect and take-off, landing and close) run in a thread; a
Crazyflie whose link goes down publishes nothing until it is back (:meth:`~plant.crazyflie.CrazyfliePlant.recover`
runs meanwhile, as a task), and one that cannot be brought back withdraws from the swarm.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from plant import base, resume

from plant.build import build
from plant.onboard import Trust
from plant.rest import Resting
from plant.watchdog import Watchdog
from tether import transport as tp
from tether.gate import health_of
from tether import wire
from tether import mission as ms
from tether.node import Node, report_drops

if TYPE_CHECKING:  # a simulated plant's process does not load the Crazyflie driver
    from plant.crazyflie import CrazyfliePlant

log = logging.getLogger("tether")


class _NoLinkLost(Exception):
    """Stands for :class:`plant.crazyflie.LinkLost` in a process without a Crazyflie (never raised)."""


async def run(node: Node) -> None:
    """One vehicle: the agent ``node.args.node_id``."""
    await _host(node, [node.args.node_id], world=False)


async def run_world(node: Node) -> None:
    """Every vehicle of the mission and its payload."""
    await _host(node, node.mission.agent_ids, world=True)


async def _host(node: Node, ids: list[int], world: bool) -> None:
    m, keys = node.mission, node.keys
    real = any(isinstance(m.agent(i).plant, ms.CrazyfliePlant) for i in ids)
    if real:
        node.clock.require("realtime", "a crazyflie is a real vehicle: fly this mission with --clock realtime")
    if world and real:
        raise ValueError("a crazyflie is a real vehicle: its own plant process talks to it (tether plant --id I), "
                         "never a world hosting others")
    built = build(m, ids, live=real)  # a crazyflie is flown in real time only (refused above otherwise)
    # a [payload] world is one plant; a world of simulated vehicles without one (--shared-plants), a fleet
    plant = built[0] if len(built) == 1 else base.Fleet(built)
    if real:  # only then is the driver loaded (build has loaded it already)
        from plant.crazyflie import CrazyfliePlant, LinkLost
    if real and isinstance(plant, CrazyfliePlant):
        # connect and pre-flight, on the ground: seconds, off the event loop; the take-off waits for
        # the run's start (_fly), so that a process (re)started when no run is about to begin, or in
        # one already under way, never takes its vehicle up
        await asyncio.to_thread(plant.open, False)
        vehicle: Resting | CrazyfliePlant = plant
        lost: type[Exception] = LinkLost
    else:
        vehicle = Resting(plant, m.dim, m.safety.ground)
        lost = _NoLinkLost
    try:
        await _fly(node, ids, world, vehicle, lost)
    finally:
        if not isinstance(vehicle, Resting):
            await asyncio.to_thread(plant.close)  # lands: seconds
        else:
            plant.close()


async def _fly(node: Node, ids: list[int], world: bool, plant: Resting | CrazyfliePlant,
               link_lost: type[Exception]) -> None:
    m, keys = node.mission, node.keys
    h = m.dt
    cmds = []
    # a process that may be a restart (real time, one simulated vehicle: plant/resume.py) learns the
    # run's start instant from the commands it hears before its own start: those must wake the loop
    resumable = not world and isinstance(plant, Resting)
    for aid in ids:
        # otherwise read at the tick only: a command does not wake the loop as it arrives (real time)
        src = node.source(keys.topic("agent", aid, "cmd"), wire.Command, aid, wake=resumable)
        src.health = health_of(m)  # the conflict rule: two different commands for one tick contest it
        node.watch("agent", aid, src)
        cmds.append(src)
    operator: list[str | None] = [None]

    def on_safety(msg: wire.SafetyCommand) -> None:
        if operator[0] != "estop":  # an e-stop is final
            log.warning("operator: %s%s", msg.action, f" ({msg.reason})" if msg.reason else "")
            operator[0] = msg.action

    node.source(keys.safety, wire.SafetyCommand, 0, on_message=on_safety, keep=False)
    qos = tp.FLEET_STATE if len(ids) > 1 else tp.STATE  # one session's burst: batched (see FLEET_STATE)
    states = [node.publisher(keys.topic("plant", aid, "state"), qos, sender=aid) for aid in ids]
    payload = node.publisher(keys.topic("world", 0, "state")) if world and m.payload is not None else None
    if world:  # each hosted vehicle is a plant to the agents, the recorder and the launcher
        node.hold(*(tp.declare_token(node.session, keys.token("plant", aid)) for aid in ids))
    dogs = [Watchdog(m.safety, m.dim, h) for _ in ids]
    trusts = [Trust() for _ in ids]
    noted: list[list[wire.SafetyEvent]] = [[] for _ in ids]
    """Per vehicle, its watchdog's events not yet published (they ride on its next PlantState)."""
    # real time, one simulated vehicle: a restarted process resumes from its last state (plant/resume.py)
    resumer = resume.Resumer(node, ids[0], cmds) if not world and isinstance(plant, Resting) else None
    await node.ready(rejoin=None if resumer is None else resumer.epoch)
    for src in cmds:  # started: the commands are read at the tick, and need not wake the loop any more
        node.quieten(src)
    if not isinstance(plant, Resting):  # a real vehicle takes off for this run, in the start's lead before tick 0
        await asyncio.to_thread(plant.take_off)
        if (late := node.mission_time()) > 0:
            log.warning("crazyflie %d: airborne %.2f s after tick 0: give the start a longer lead", ids[0], late)
    first = 0
    if node.rejoined and resumer is not None:
        first = min(m.steps, math.floor(node.mission_time() / h) + 1)
        last = await resumer.ask(first)
        plant = resume.resumed(m, ids[0], last, first)
        log.warning("rejoined a run under way at tick %d (t = %.2f s): tick 0 at %.3f; resuming from the last state "
                    "on the wire, tick %d (t = %.2f s) at p = %s", first, first * h, resumer.epoch() or 0.0, last.k,
                    last.t, last.p)
    cf = None if isinstance(plant, Resting) else plant
    """The real vehicle, the only plant whose link can be lost (``link_lost``: plant.crazyflie.LinkLost)."""
    recovering: asyncio.Task[bool] | None = None
    s: base.Sample | None = None
    for k in range(first, m.steps + 1):
        await node.tick(k)
        t = k * h
        if k > first:
            u, modes = [], []
            # real time: the tick the plant's clock has reached (a late plant is behind it)
            k_clock = node.clock.reached(h)
            for r, (aid, src, dog, trust) in enumerate(zip(ids, cmds, dogs, trusts)):
                # node.tick has just drained: no drain per vehicle
                msg = await node.sample(src, k - 1, drain=False)
                health = src.health
                msg, judged = trust.judge(msg, msg is not None and src.is_contested(msg),
                                          health is not None and health.suspect, t, dog.mode)
                if msg is not None:
                    dog.offer(msg.u, msg.t, msg.k, k, msg.mode, k_clock=k_clock)
                d = dog.step(t, None if s is None else s.p[r], None if s is None else s.v[r], operator[0],
                             down=None if cf is None else cf.down())
                for ev in (*judged, *d.events):
                    log.warning("vehicle %d: %s", aid, ev)
                    noted[r].append(ev.wire(k, aid))
                u.append(d.u)
                modes.append(d.rest)
            plant.step(np.array(u), modes)
        try:
            s = plant.state()
        except link_lost as exc:
            if cf is None:
                raise
            s = None
            if recovering is None:
                log.error("%s", exc)
                recovering = asyncio.create_task(cf.recover())
        if cf is not None and recovering is not None and recovering.done():
            if not recovering.result():
                # say so (the agent sees its plant's token go and holds), keep out of the swarm's
                # way until the mission's end, then fail
                log.error("%s: withdrawing from the swarm", cf.spec.uri)
                node.withdraw()
                await node.tick(m.steps)
                raise link_lost(f"crazyflie {ids[0]} ({cf.spec.uri}): the link did not come back")
            recovering = None
        if s is None:
            continue  # nothing measured: nothing to publish
        for r, pub in enumerate(states):
            pub.send(wire.PlantState, k, t, p=s.p[r].tolist(), vel=s.v[r].tolist(), a=s.a[r].tolist(),
                     d=s.d[r].tolist(), mode=dogs[r].mode, events=noted[r])
            noted[r] = []
        if payload is not None:
            ex = s.extra
            payload.send(wire.WorldState, k, t, p=ex["payload_p"].tolist(), vel=ex["payload_v"].tolist(),
                         tension=ex["tension"].tolist(), slack_events=ex["slack_events"].astype(int).tolist())
    for aid, dog, trust, src in zip(ids, dogs, trusts, cmds):
        report_drops(dog.invalid, f"vehicle {aid}: commands rejected by its watchdog")
        report_drops({"conflict": src.conflicts, "contested": trust.contested},
                     f"vehicle {aid}: commands in conflict, and contested ones flown as none")
        report_drops({"not finite": dog.garbled}, f"vehicle {aid}: own measurements flown as none")
    if cf is not None and recovering is not None:  # the mission ended with the link still down: the vehicle is lost
        recovering.cancel()
        raise link_lost(f"crazyflie {ids[0]} ({cf.spec.uri}): the link was still down at the mission's end")
