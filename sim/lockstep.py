"""The lockstep runtime with its emulated network, in one process. Pure: no clock, no I/O.

``tether run --clock lockstep`` spreads a mission over processes that exchange samples through
Zenoh; a lockstep run is fully determined by the mission (seed included), so the same arithmetic
done in one loop gives the same run. This module is that loop, written against the very functions
the processes call, in the order they call them:

* the plants (``plant/node.py``, ``plant/world.py``): :func:`plant.build.build`'s plants, stepped
  with the commands of tick k-1 (an exact double integrator per agent, vehicles with mass, or a
  payload world hosting all of them);
* agent i relays its plant's sample of tick k as a :class:`~tether.wire.State` with sequence
  number k; the leader publishes its profile at ``t_k`` the same way;
* every in-link ``j -> i`` of a mission with a ``[netem]`` section is a :class:`netem.channel.Link`
  seeded with :func:`~netem.channel.link_rng`, offered j's encoded sample at its sample time and
  following the link's profile schedule (:class:`netem.link.Channel`); at tick k agent i takes the
  newest sample its links have delivered by ``t_k`` (``Node.aligned``);
* every agent runs the agent process's own tick, :meth:`agent.tick.AgentTick.step` (the
  ``[links]`` policy, the feed-forward choice, the law and the next gains).

The result equals a ``tether run --clock lockstep`` of the same mission bit for bit (checked by
``tests/test_lockstep.py`` against real processes under a degraded network), several times faster
(``bench/sweep_engine.py``): it is what ``tether sweep`` runs by default. The reference simulator
(:mod:`sim.refsim`) has no network; with an ideal one all three agree.

A run in which an agent's safety supervisor catches a divergence (``[safety]``: the formation error,
a gain or the command past its bound), or with a component of a formation error beyond every
physical scale (``diverge_at``) or not finite, is stopped there: the rest of its samples are NaN and
``meta.diverged_at`` says when.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from agent.safety import Status
from agent.tick import AgentTick, Heard
from leader import profile
from plant import base as plants
from plant.rest import Resting
from tether import wire
from tether.inputs import Source
from tether.mission import Mission
from sim.setup import DIVERGE_AT, Progress, hosts_of, leader_of, meta_of, steps_of
from tether.runfile import Links, PlantRecord, Run

if TYPE_CHECKING:
    from netem.link import Channel


@dataclass
class _InLink:
    """Agent i's input from in-neighbour j: the runtime's own :class:`~tether.inputs.Source` (the
    samples accepted, newest first, stale/duplicate/reordered counts) behind its
    :class:`~netem.link.Channel` (the emulated link; None without ``[netem]``)."""

    src: int
    source: Source
    channel: "Channel | None"


def simulate(m: Mission, *, duration: float | None = None, record: bool = True,
             progress: Progress | None = None, diverge_at: float = DIVERGE_AT, engine: str = "auto") -> Run:
    """Run ``m`` as the lockstep runtime would. ``duration`` overrides the mission's (a whole
    number of periods). ``record=False`` keeps only the last sample (and the link statistics).

    ``engine``: ``"python"`` runs the agents' own tick below; ``"compiled"`` runs
    :mod:`sim.lockstep_kernel`'s twin of it, which covers FLYING, HOLD, dropped edges and 2D landings
    (it raises ``ValueError`` for a mission it does not support, and returns the Python engine's run
    when a tick is one it does not model, a 3D landing for one); ``"auto"`` (the default) takes the twin where it
    applies. The result is the same, bit for bit.

    The returned run carries the runtime recorder's link statistics in ``links``
    (:class:`~tether.runfile.Links`): ``src``, ``received``, ``used``, ``stale``, ``duplicates``,
    ``reordered``, ``corrupt`` (run totals, ``(N, width)``) and ``age`` (``(T, N, width)``, NaN where
    nothing was usable); the plants' own records in ``plant``; the safety modes in ``safety``."""
    if engine not in ("auto", "python", "compiled"):
        raise ValueError(f"engine is {engine!r}; one of auto, python, compiled")
    if engine != "python":
        from sim import lockstep_kernel

        why = lockstep_kernel.unsupported(m) if engine == "compiled" else None
        if why is not None:
            raise ValueError(f"the compiled engine cannot run {m.name}: {why}")
        from agent import laws
        from sim import warm

        # one compile per machine: the first run compiles under a lock that other processes wait on
        fast = warm.first_run("lockstep", laws.of_mission(m).law, lambda: lockstep_kernel.simulate(
            m, duration=duration, record=record, progress=progress, diverge_at=diverge_at)) \
            if lockstep_kernel.unsupported(m) is None else None  # None: unsupported, or given back
        if fast is not None:
            return fast
    h, d = m.dt, m.dim
    steps = steps_of(m, duration)
    ids = m.agent_ids
    n = len(ids)
    lid = m.leader.id
    ticks = [AgentTick.from_mission(m, i) for i in ids]
    # each plant rests on the ground or cuts its motors when its agent's supervisor says so, as the
    # plant process's watchdog does (transparent while every vehicle flies)
    hosts = [Resting(host, d, m.safety.ground) for host in hosts_of(m)]
    row_of = {aid: (h, r) for h in hosts for r, aid in enumerate(h.ids)}
    order = [row_of[aid] for aid in ids]
    host_rows = [[ids.index(aid) for aid in host.ids] for host in hosts]
    net = m.netem
    if net is not None:
        from netem.link import Channel  # only a mission with [netem] loads the emulator

    def in_link(j: int, i: int) -> _InLink:
        channel = None if net is None else Channel.of(m, j, i)
        return _InLink(j, Source(f"{j}->{i}", wire.State, j, keep=False, channel=channel), channel)

    links = [[in_link(j, i) for j in tk.law.neighbours] for i, tk in zip(ids, ticks)]
    width = max((len(row) for row in links), default=0)
    senders = sorted({j for tk in ticks for j in tk.law.neighbours})

    avoid = m.safety.avoid is not None  # every vehicle hears the others' states (range sensing)
    meta = meta_of(m, steps)
    rows = steps + 1 if record else 1
    run = Run.empty(rows, ids, d, meta)
    ages = np.full((rows, n, width), np.nan)
    every = max(1, steps // 100)
    # the leader's reference at every tick at once (numpy evaluates it element by element: the
    # same values as the leader process's one call per tick)
    lead_p, lead_v, lead_a = leader_of(m, np.arange(steps + 1) * h)
    single = len(hosts) == 1 and order == [(hosts[0], r) for r in range(n)]  # one host, in agent order
    out_rows: list[list] = [[] for _ in range(7)]  # this tick's u, xi, zeta, kp, kv, modes and law states, per agent

    for k in range(steps + 1):
        t = k * h
        states = [host.state() for host in hosts]
        by_host = {id(host): st for host, st in zip(hosts, states)}
        # the agents' ticks take plain floats (agent/tick.py): each tick's samples as lists, once
        if single:
            st = states[0]
            p, v, a = st.p.tolist(), st.v.tolist(), st.a.tolist()
            dist: np.ndarray | list[np.ndarray] = st.d
        else:
            picked = [(by_host[id(host)], r) for host, r in order]
            p = [st.p[r].tolist() for st, r in picked]
            v = [st.v[r].tolist() for st, r in picked]
            a = [st.a[r].tolist() for st, r in picked]
            dist = [st.d[r] for st, r in picked]
        lp, lv, la = lead_p[k].tolist(), lead_v[k].tolist(), lead_a[k].tolist()
        # what each sender publishes at tick k: the leader's reference, each agent's relayed sample
        sent: dict[int, Heard] = {lid: (t, lp, lv, la)}
        modes = {lid: wire.FLYING}  # each sender's mode, as its state message carries it
        for i, aid in enumerate(ids):  # what each agent shares for the feed-forward
            sent[aid] = (t, p[i], v[i], ticks[i].shared(a[i]))
            modes[aid] = ticks[i].supervisor.mode
        payloads = {}
        if net is not None:
            for j in senders:
                tj, pj, vj, aj = sent[j]
                payloads[j] = wire.encode(wire.State(sender=j, seq=k, k=k, t=tj, p=list(pj), vel=list(vj), a=list(aj),
                                                     mode=modes[j]))
        r = k if record else 0
        keep = record or k == steps
        us = []
        worst = 0.0
        for i, (tk, row) in enumerate(zip(ticks, links)):
            heard: list[Heard | None] = []
            reported: list[int] = []
            for lk in row:
                if lk.channel is None:
                    heard.append(sent[lk.src])
                    reported.append(modes[lk.src])
                    lk.source.received += 1
                    continue
                lk.channel.send(t, payloads[lk.src])
                lk.source.deliver(t, wire.decode)  # a corrupted copy fails its checksum, counted
                newest = lk.source.newest
                heard.append(None if newest is None else (newest.t, newest.p, newest.vel, newest.a))
                reported.append(wire.FLYING if newest is None else newest.mode)
            near = [(p[j], v[j]) for j in range(n) if j != i] if avoid else ()
            out = tk.step(k, t, p[i], v[i], a[i], heard, Status(modes=reported), near=near)
            us.append(out.u)
            worst = max(worst, _abs_max(out.xi))
            if keep:
                if width:
                    ages[r, i, :len(row)] = [age if ok else math.nan for age, ok in zip(out.ages, out.used)]
                for col, x in zip(out_rows, (out.u, out.xi, out.zeta, out.kp, out.kv, out.mode, out.x)):
                    col.append(x)
        if keep:
            run.t[r] = t
            run.p[r], run.v[r], run.a[r], run.d[r] = p, v, a, dist
            run.u[r], run.xi[r], run.zeta[r], run.kp[r], run.kv[r] = out_rows[:5]
            # the one place this engine records a safety mode: the agent's supervisor, and the
            # plant's command watchdog (the in-process plants follow every command, and rest or
            # cut their motors with their agent, as Command.mode makes the plant process do)
            run.law_state[:, r] = np.reshape(out_rows[6], (n, len(run.law_state), d)).transpose(1, 0, 2)
            run.safety.safety_mode[r] = out_rows[5]
            run.safety.plant_mode[r] = [mode if mode in (wire.LANDED, wire.ESTOP) else wire.FLYING
                                        for mode in out_rows[5]]
            for col in out_rows:
                col.clear()
            run.leader_p[r], run.leader_v[r], run.leader_a[r] = lp, lv, la
            _record_plants(run.plant, by_host, order, r, rows)
        caught = any(tk.supervisor.diverged is not None for tk in ticks)
        if caught or not (worst <= diverge_at):  # also catches NaN
            run.meta.diverged_at = t
            if record:
                for name in ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d"):
                    getattr(run, name)[k + 1:] = np.nan
                run.law_state[:, k + 1:] = np.nan
                run.t[k + 1:] = np.arange(k + 1, steps + 1) * h
                run.leader_p[k + 1:] = np.nan
            break
        if k == steps:
            break
        for host, hrows in zip(hosts, host_rows):
            host.step(np.array([us[i] for i in hrows]), [ticks[i].supervisor.mode for i in hrows])
        if progress is not None and k % every == 0:
            progress(k, steps)
    if progress is not None:
        progress(steps, steps)
    run.safety.events = sorted((ev for tk in ticks for ev in tk.supervisor.events), key=lambda e: (e.k, e.vehicle))

    counts = {name: np.zeros((n, width), dtype=np.int64)
              for name in ("src", "received", "used", "stale", "duplicates", "reordered", "corrupt")}
    for i, (tk, row) in enumerate(zip(ticks, links)):
        for s, lk in enumerate(row):
            src = lk.source
            counts["src"][i, s] = lk.src
            counts["received"][i, s] = src.received
            counts["used"][i, s] = tk.used[s]
            counts["stale"][i, s] = src.stale
            counts["duplicates"][i, s] = src.duplicates
            counts["reordered"][i, s] = src.reordered
            counts["corrupt"][i, s] = src.corrupt
    run.links = Links(age=ages, **counts)
    for host in hosts:
        host.close()
    return run


def _abs_max(xs: list[float]) -> float:
    """``numpy.abs(xs).max()`` of a short list: NaN if any element is."""
    return math.nan if any(x != x for x in xs) else max(map(abs, xs))


def _record_plants(rec: PlantRecord, samples: dict[int, plants.Sample], order: list, r: int, rows: int) -> None:
    """The plants' own records of tick row ``r`` into ``rec``, as ``(T, ...)`` arrays. ``samples``:
    each host's sample by ``id(host)``; ``order``: agent i's (host, row). A vehicle whose plant has
    no attitude reads NaN there."""
    n = len(order)
    if any(s.attitude is not None for s in samples.values()):
        if rec.attitude is None:
            rec.attitude = np.full((rows, n, 3), np.nan)
        for i, (host, row) in enumerate(order):
            att = samples[id(host)].attitude
            if att is not None:
                rec.attitude[r, i] = att[row]
    worlds = [s.payload for s in samples.values() if s.payload is not None]
    if worlds:  # a payload world hosts every vehicle, in the mission's order
        pl = worlds[0]
        pp, pv, tension, slack = rec.payload_p, rec.payload_v, rec.tension, rec.slack_events
        if pp is None or pv is None or tension is None or slack is None:
            pp, pv = rec.payload_p, rec.payload_v = np.full((rows, 3), np.nan), np.full((rows, 3), np.nan)
            tension, slack = rec.tension, rec.slack_events = np.full((rows, n), np.nan), np.full((rows, n), np.nan)
        pp[r], pv[r], tension[r], slack[r] = pl.p, pl.v, pl.tension, pl.slack_events
