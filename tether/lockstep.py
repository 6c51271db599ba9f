"""The lockstep runtime with its emulated network, in one process. Pure: no clock, no I/O.

``tether run --clock lockstep`` spreads a mission over processes that exchange samples through
Zenoh; a lockstep run is fully determined by the mission (seed included), so the same arithmetic
done in one loop gives the same run. This module is that loop, written against the very functions
the processes call, in the order they call them:

* the plants (``plant/node.py``, ``plant/world.py``): :func:`plant.base.build`'s plants, stepped
  with the commands of tick k-1 (an exact double integrator per agent, vehicles with mass, or a
  payload world hosting all of them);
* agent i relays its plant's sample of tick k as a :class:`~tether.wire.State` with sequence
  number k; the leader publishes its profile at ``t_k`` the same way;
* every in-link ``j -> i`` of a mission with a ``[netem]`` section is a :class:`netem.channel.Link`
  seeded with :func:`~netem.channel.link_rng`, offered j's encoded sample at its sample time and
  following the link's profile schedule (``tether.node.Channel``); at tick k agent i takes the
  newest sample its links have delivered by ``t_k`` (``Node.aligned``);
* :func:`agent.law.neighbour_sample` applies the ``[links]`` policy, then
  :meth:`agent.law.AgentLaw.step` gives ``u_i``, the errors and the next gains.

The result equals a ``tether run --clock lockstep`` of the same mission bit for bit (checked by
``tests/test_lockstep.py`` against real processes under a degraded network), several times faster
(``bench/sweep_engine.py``): it is what ``tether sweep`` runs by default. The reference simulator
(:mod:`tether.refsim`) has no network; with an ideal one all three agree.

A run with a component of a formation error beyond every physical scale (``diverge_at``) or not
finite is stopped there: the rest of its samples are NaN and ``meta["diverged_at"]`` says when.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from agent.law import AgentLaw, neighbour_sample
from leader import profile
from plant import base as plants
from tether import wire
from tether.mission import Mission
from tether.node import Channel, Source
from tether.runfile import Run

Progress = Callable[[int, int], None]

DIVERGE_AT = 1e6
"""A formation error beyond this [m] counts as divergence and ends the run."""


@dataclass
class _InLink:
    """Agent i's input from in-neighbour j: the runtime's own :class:`~tether.node.Source` (the
    samples accepted, newest first, stale/duplicate/reordered counts) behind its
    :class:`~tether.node.Channel` (the emulated link; None without ``[netem]``)."""

    src: int
    source: Source
    channel: Channel | None
    used: int = 0

    def release(self, now: float) -> None:
        """Hand the copies the link delivers by ``now`` to the source, as ``Node.release`` does."""
        for copy in self.channel.release(now):
            if copy.corrupted:  # fails its checksum at the receiver
                self.source.corrupt += 1
                continue
            self.source.offer(wire.decode(copy.payload))


def simulate(m: Mission, *, duration: float | None = None, record: bool = True,
             progress: Progress | None = None, diverge_at: float = DIVERGE_AT) -> Run:
    """Run ``m`` as the lockstep runtime would. ``duration`` overrides the mission's (a whole
    number of periods). ``record=False`` keeps only the last sample (and the link statistics).

    The returned run carries the runtime recorder's link statistics in ``extra``: ``link_src``,
    ``link_received``, ``link_used``, ``link_stale``, ``link_duplicates``, ``link_reordered``,
    ``link_corrupt`` (run totals, ``(N, width)``)
    and ``link_age`` (``(T, N, width)``, NaN where nothing was usable)."""
    h, d = m.dt, m.dim
    steps = m.steps if duration is None else int(round(duration * m.rate))
    ids = m.agent_ids
    n = len(ids)
    lid = m.leader.id
    ref = profile.build(m.leader, d)
    laws = [AgentLaw.from_mission(m, i) for i in ids]
    hosts = plants.build(m)
    row_of = {aid: (h, r) for h in hosts for r, aid in enumerate(h.ids)}
    order = [row_of[aid] for aid in ids]
    policy = m.links
    net = m.netem

    def in_link(j: int, i: int) -> _InLink:
        source = Source(f"{j}->{i}", wire.State, j, keep=False)
        return _InLink(j, source, None if net is None else Channel.of(m, j, i))

    links = [[in_link(j, i) for j in law.neighbours] for i, law in zip(ids, laws)]
    nb = [np.zeros((3, len(row), d)) for row in links]  # per agent: the neighbours' p, v, a
    width = max((len(row) for row in links), default=0)
    senders = sorted({j for law in laws for j in law.neighbours})

    extras: dict[str, np.ndarray] = {}
    feed = m.law.feedforward
    u_prev = [np.zeros(d) for _ in ids]
    kp = [law.params.kp0.copy() for law in laws]
    kv = [law.params.kv0.copy() for law in laws]
    meta = {"mission": m.name, "source": "lockstep-inprocess", "law": m.law.kind, "rate": m.rate,
            "steps": steps, "seed": m.seed, "diverged_at": None}
    run = Run.empty(steps + 1 if record else 1, ids, d, meta)
    ages = np.full((steps + 1 if record else 1, n, width), np.nan)
    every = max(1, steps // 100)

    for k in range(steps + 1):
        t = k * h
        samples = {id(host): host.state() for host in hosts}
        p, v, a, dist = ([samples[id(host)].__dict__[f][r] for host, r in order] for f in ("p", "v", "a", "d"))
        lp, lv, la = ref(t)
        # what each sender publishes at tick k: the leader's reference, each agent's relayed sample
        sent: dict[int, tuple[float, np.ndarray, np.ndarray, np.ndarray]] = {
            lid: (t, np.asarray(lp, dtype=float), np.asarray(lv, dtype=float), np.asarray(la, dtype=float))}
        shared = a if feed == "measured" else u_prev  # what each agent shares for the feed-forward
        for i, aid in enumerate(ids):
            sent[aid] = (t, p[i], v[i], shared[i])
        payloads = {}
        if net is not None:
            for j in senders:
                tj, pj, vj, aj = sent[j]
                payloads[j] = wire.encode(wire.State(sender=j, seq=k, k=k, t=tj, p=pj.tolist(),
                                                     vel=vj.tolist(), a=aj.tolist()))
        r = k if record else 0
        keep = record or k == steps
        us = []
        worst = 0.0
        for i, (law, row) in enumerate(zip(laws, links)):
            nb_p, nb_v, nb_a = nb[i]
            for s, lk in enumerate(row):
                if lk.channel is None:
                    sample, age = sent[lk.src][1:], 0.0
                    lk.source.received += 1
                else:
                    lk.channel.send(t, payloads[lk.src])
                    lk.release(t)
                    newest = lk.source.newest
                    if newest is None:
                        sample, age = None, math.nan
                    else:
                        sample = (np.array(newest.p), np.array(newest.vel), np.array(newest.a))
                        age = t - newest.t
                nb_p[s], nb_v[s], nb_a[s], ok = neighbour_sample(p[i], v[i], shared[i], law.deltas[s], sample, age,
                                                                 policy.max_age, policy.compensate)
                lk.used += ok
                if keep:
                    ages[r, i, s] = age if ok else math.nan
            if feed == "none":
                nb_a[:] = 0.0
            u, xi, zeta, kp_next, kv_next = law.step(p[i], v[i], nb_p, nb_v, nb_a, kp[i], kv[i])
            us.append(u)
            worst = max(worst, abs(xi).max())
            if keep:
                run.p[r, i], run.v[r, i], run.a[r, i], run.u[r, i] = p[i], v[i], a[i], u
                run.xi[r, i], run.zeta[r, i], run.kp[r, i], run.kv[r, i] = xi, zeta, kp[i], kv[i]
                run.d[r, i] = dist[i]
            kp[i], kv[i] = kp_next, kv_next
        if keep:
            run.t[r] = t
            run.leader_p[r], run.leader_v[r], run.leader_a[r] = lp, lv, la
            _record_extras(extras, [samples[id(host)] for host in hosts], r, steps + 1 if record else 1)
        if not (worst <= diverge_at):  # also catches NaN
            run.meta["diverged_at"] = t
            if record:
                for name in ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d"):
                    getattr(run, name)[k + 1:] = np.nan
                run.t[k + 1:] = np.arange(k + 1, steps + 1) * h
                run.leader_p[k + 1:] = np.nan
            break
        if k == steps:
            break
        u_prev = us
        for host in hosts:
            host.step(np.array([us[ids.index(aid)] for aid in host.ids]))
        if progress is not None and k % every == 0:
            progress(k, steps)
    if progress is not None:
        progress(steps, steps)

    ex = run.extra
    ex["link_src"] = np.zeros((n, width), dtype=np.int64)
    for name in ("link_received", "link_used", "link_stale", "link_duplicates", "link_reordered", "link_corrupt"):
        ex[name] = np.zeros((n, width), dtype=np.int64)
    for i, row in enumerate(links):
        for s, lk in enumerate(row):
            ex["link_src"][i, s] = lk.src
            src = lk.source
            ex["link_received"][i, s] = src.received
            ex["link_used"][i, s] = lk.used
            ex["link_stale"][i, s] = src.stale
            ex["link_duplicates"][i, s] = src.duplicates
            ex["link_reordered"][i, s] = src.reordered
            ex["link_corrupt"][i, s] = src.corrupt
    ex["link_age"] = ages
    ex.update(extras)
    for host in hosts:
        host.close()
    return run


def _record_extras(extras: dict[str, np.ndarray], samples: list, r: int, rows: int) -> None:
    """The plants' own records (``Sample.extra``) of tick row ``r``, as ``(T, ...)`` arrays; the
    rows of several plants are stacked along the vehicle axis where they have one."""
    names = {name for s in samples for name in s.extra}
    for name in names:
        parts = [np.asarray(s.extra[name]) for s in samples if name in s.extra]
        value = np.concatenate(parts) if len(parts) > 1 else parts[0]
        if name not in extras:
            extras[name] = np.full((rows, *value.shape), np.nan)
        extras[name][r] = value
