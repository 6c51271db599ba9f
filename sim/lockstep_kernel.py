"""The in-process lockstep engine's compiled twin (numba, the ``[fast]`` extra). Pure: no clock, no I/O.

:func:`sim.lockstep.simulate` runs the agent processes' own Python (``agent/tick.py``) at every
tick. Most ticks of a study are one of a few kinds: every vehicle FLYING or holding (HOLD) while
its leader is silent or out of reach, in-neighbours' edges dropped and restored, and in 2D a vehicle
landing (LAND, held past ``land_after`` or flapping; then LANDED: its plant rests); no bound of
``[safety]`` reached. This module runs those ticks in one compiled loop, operation for operation as
the Python does (no fast-math: no reassociation, no fused multiply-adds), so that a run equals the
Python engine's bit for bit, its safety events worded the same (``tests/test_lockstep_kernel.py``).
The supervisor's rule is not written here: the loop calls ``agent.safety``'s own pure functions
(``transition``, ``hold_cause``, ``believe``, ``silent``, ``report_kind``, the graph search
``reaches_in``) and the failsafe laws' scalar cores of ``tether.failsafe`` (``hold_point``'s,
``hold``'s, ``saturate``'s, ``landed``'s), compiled (``tests/test_supervisor_rule.py``):

* what each agent hears is decided before the loop: an emulated link that only loses and delays
  (:func:`netem.channel.batchable`: Bernoulli or Gilbert-Elliott loss, a constant or jittered delay)
  does to each sample what it does whatever the sample holds, so its own
  :class:`~netem.link.Channel` decides the whole run at once (:meth:`~netem.link.Channel.decide`:
  the same generator draws), and the receiving :class:`~tether.inputs.Source`'s rules (the newest
  sequence number wins; stale, reordered and duplicate counts) give the newest sample at each tick
  (:func:`arrivals`);
* the disturbance increments and values come from the plants' own banks
  (:meth:`plant.disturbance.DisturbanceBank.span`), the leader's reference from its profile;
* the compiled loop (:func:`_ticks`) then runs, per tick and agent, ``agent.law.neighbour_sample``,
  the supervisor's link check (the leader silent; an in-neighbour silent, or believed to stop or to
  hold from its mode reports; the leader's reach over the survivors; edges dropped and kappa
  re-normalised; holding neighbours followed), ``AgentLaw.step``, the
  supervisor's bounds, its rule (HOLD anchored at ``failsafe.hold_point``, its recovery, LAND)
  and LANDED in 2D (``failsafe.landed``), ``failsafe.hold`` and ``failsafe.saturate``, and the exact double integrator of
  ``plant/double_integrator.py`` (a LANDED vehicle resting, as ``plant.rest.Resting`` has it); the events it records are worded by
  :func:`_events` as ``agent.safety.Supervisor`` words them.

The loop stops at the first tick it does not model (a bound of ``[safety]`` reached, a landing
in 3D, a value not finite where a mode would use it, a 3D vehicle through the ground): :func:`simulate` then returns None and the caller runs the mission on the Python engine
from its start. A mission outside what this twin knows (:func:`unsupported`: vehicles with mass, a
payload world, collision avoidance, a geofence, a link with duplication, reordering, corruption, a
rate limit or an outage) runs there from the start too.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from agent import safety
from agent import law as agent_law
from agent.law import AgentLaw
from plant import base as plants
from plant.disturbance import DisturbanceBank
from sim import kernel, lawkernels
from sim.setup import DIVERGE_AT, Progress, hosts_of, leader_of, meta_of, steps_of
from sim.kernel import law_load, law_record, law_shown, law_step, law_store  # the law (sim.lawkernels rebinds them)
from tether import failsafe, vec, wire
from tether.inputs import RECENT_SEQS
from tether.mission import Mission
from tether.runfile import Links, Run

if TYPE_CHECKING:
    from netem.link import Channel


CHUNK = 4096
"""Ticks per call of the compiled loop (the disturbance of so many ticks is held at once)."""

_FEED = {"measured": 0, "commanded": 1, "none": 2}

MAX_IN = 62
"""The most in-neighbours an agent may have here: its dropped edges are the bits of one machine word."""

EVENTS = 4096
"""Room for the supervisors' events of one call of the loop (more leave it to the Python engine)."""

_EDGES, _LANDED, _FOLLOW = 100, 101, 102
"""The kinds of event the loop records beside :func:`agent.safety.transition`'s (``HELD`` ...
``LAND_FLAPPING``): edges dropped or restored, LANDED (2D: still, or ``land_settle``), holding
neighbours followed or no longer."""

jit = kernel.jit

# The supervisor's rule, compiled from its one definition (agent/safety.py): never re-typed here
# (tests/test_supervisor_rule.py checks that the loop calls these and compares nothing of its own).
_transition = jit(safety.transition)
_hold_cause = jit(safety.hold_cause)
_believe = jit(safety.believe)
_report_kind = jit(safety.report_kind)
_silent = jit(safety.silent)
_STAY, _HELD = safety.STAY, safety.HELD
_REPORT_FLYING, _REPORT_HOLD, _REPORT_STOPPED = safety.REPORT_FLYING, safety.REPORT_HOLD, safety.REPORT_STOPPED

# Columns of the loop's grouped arrays. ``cfg`` (float): the engine's and ``[safety]``'s numbers.
(_H, _HH2, _GROUND, _THREE, _FEED_CODE, _MAX_AGE, _COMPENSATE, _LEADER_TIMEOUT, _NEIGHBOUR_TIMEOUT, _MAX_ERR,
 _GAIN_CAP, _MAX_SPEED, _MAX_ACCEL, _DIVERGE_AT, _LAND_AFTER, _HOLD_KP, _HOLD_KV, _LAND_SETTLE, _CONFIRM,
 _FLAP_LIMIT, _RESUME_DWELL) = range(21)
_CFG = 21
# ``sup`` (int, per agent): its supervisor's mode, HOLD's cause (agent.safety.CAUSES), the dropped
# edges and the holding neighbours followed (masks of link slots), the recoveries of the current run
_MODE, _CAUSE, _LOST, _FOLLOWED, _FLAPS = range(5)
_SUP = 5
# ``clock`` (float, per agent): since when the mode holds, since when HOLD's cause is gone, the last recovery
_SINCE, _HEALTHY, _LAST_FLAP = range(3)
_CLOCK = 3
# ``reports`` (int, per link slot): agent.safety.believe's state (the kind said, for how long, believed)
_SAID, _RUN, _BELIEF = range(3)
_REPORTS = 3
# ``outs``: the run's per-tick arrays the loop fills (``Run`` fields of that name), in this order
_OUTS = ("p", "v", "a", "u", "xi", "zeta", "law_state")

_FLYING, _HOLD, _LAND_MODE, _LANDED_MODE = wire.FLYING, wire.HOLD, wire.LAND, wire.LANDED


def unsupported(m: Mission) -> str | None:
    """Why this twin cannot run ``m`` (the Python engine then does), or None."""
    if not kernel.AVAILABLE:
        return "numba is not installed (the [fast] extra)"
    if m.payload is not None:
        return "a payload world"
    if m.safety.avoid is not None:
        return "collision avoidance ([safety.avoid])"
    if m.safety.geofence is not None:
        return "a geofence ([safety.geofence])"
    if m.law.feedforward not in _FEED:
        return f"feedforward {m.law.feedforward!r}"
    # the Python engine's hosts (its grouping of the plants decides the banks' branches)
    if any(type(host) is not plants.DoubleIntegratorPlant for host in hosts_of(m)):
        return "a vehicle with mass (only double integrators are compiled)"
    ins = {i: AgentLaw.from_mission(m, i).neighbours for i in m.agent_ids}
    if max(map(len, ins.values()), default=0) > MAX_IN:
        return f"an agent with more than {MAX_IN} in-neighbours"
    if m.netem is not None:
        from netem.channel import batchable
        from tether.netprofile import schedule

        for i, neighbours in ins.items():
            for j in neighbours:
                if not all(batchable(prof) for _, prof in schedule(m.netem, j, i)):
                    return (f"link {j}->{i}: a profile with duplication, reordering, corruption, a rate "
                            "limit or an outage")
    return None


def simulate(m: Mission, *, duration: float | None = None, record: bool = True,
             progress: Progress | None = None, diverge_at: float = DIVERGE_AT) -> Run | None:
    """:func:`sim.lockstep.simulate` of ``m``, compiled: the same run bit for bit, or None when a
    tick is one the loop does not model (or :func:`unsupported` says no) and the Python engine must
    run it."""
    if unsupported(m) is not None:
        return None
    h, d = m.dt, m.dim
    steps = steps_of(m, duration)
    ids = m.agent_ids
    n = len(ids)
    lid = m.leader.id
    col = {aid: i for i, aid in enumerate(ids)}
    col[lid] = n  # the leader's column of the sample history
    laws = [AgentLaw.from_mission(m, i) for i in ids]
    hosts = hosts_of(m)
    banks = [(DisturbanceBank.from_mission(m, list(host.ids)), [col[a] for a in host.ids]) for host in hosts]
    p = np.empty((n, d))
    v = np.empty((n, d))
    a = np.empty((n, d))
    for host, (_, rows) in zip(hosts, banks):
        s = host.state()
        p[rows], v[rows], a[rows] = s.p, s.v, s.a
        host.close()

    # the links, flattened in agent order then in-neighbour order
    off = np.zeros(n + 1, dtype=np.int64)
    l_src, l_w, l_delta, l_id = [], [], [], []
    for i, law in enumerate(laws):
        off[i + 1] = off[i] + len(law.neighbours)
        for j, w, delta in zip(law.neighbours, law.weights, law.deltas):
            l_src.append(col[j])
            l_w.append(w)
            l_delta.append(delta)
            l_id.append(j)
    links = len(l_src)
    width = max((len(law.neighbours) for law in laws), default=0)
    times = np.arange(steps + 1) * h  # each k * h as the Python engine computes t
    newest = np.empty((steps + 1, links), dtype=np.int64)
    counts = {name: np.zeros((n, width), dtype=np.int64)
              for name in ("src", "received", "used", "stale", "duplicates", "reordered", "corrupt")}
    for i in range(n):
        for s_, l in enumerate(range(off[i], off[i + 1])):
            counts["src"][i, s_] = l_id[l]
            if m.netem is None:  # every sample arrives at its own tick
                newest[:, l] = np.arange(steps + 1)
                counts["received"][i, s_] = steps + 1
                continue
            at = _channel(m, l_id[l], ids[i]).decide(times)
            newest[:, l], received, stale, dup, reord = arrivals(at, times)
            counts["received"][i, s_] = received
            counts["stale"][i, s_] = stale
            counts["duplicates"][i, s_] = dup
            counts["reordered"][i, s_] = reord

    cfg = m.safety
    # the history of what each sender sent (p, v, shared a; its mode), as a ring: a sample is read only
    # while it is younger than max_age (its values) or than its timeout (its mode)
    reach = max(cfg.neighbour_timeout, cfg.leader_timeout, m.links.max_age)
    ring = steps + 1 if not reach / h < steps else min(steps + 1, int(reach / h) + 3)
    hist = np.zeros((3, ring, n + 1, d))
    hmode = np.full((ring, n + 1), wire.FLYING, dtype=np.int64)
    # the mission's graph (out-edges by column, the leader's column n) for the supervisor's reachability
    out_ptr = np.zeros(n + 2, dtype=np.int64)
    edges = sorted((col[e.src], col[e.dst]) for e in m.edges)
    for src_c, _ in edges:
        out_ptr[src_c + 1] += 1
    out_ptr = np.cumsum(out_ptr)
    out_dst = np.array([dst_c for _, dst_c in edges], dtype=np.int64)
    lead = np.ascontiguousarray(np.stack(leader_of(m, times)))

    rows_n = steps + 1 if record else 1
    run = Run.empty(rows_n, ids, d, meta_of(m, steps), mode=wire.FLYING)
    ages = np.full((rows_n, n, width), np.nan)
    kappa = np.array([law.kappa for law in laws])
    swd = np.array([law.sum_wdelta for law in laws], dtype=float).reshape(n, d)
    # each supervisor (columns _MODE ..., _SINCE ...), p_hold, and the law over the surviving edges
    # (kappa_i, sum_wdelta)
    sup = np.zeros((n, _SUP), dtype=np.int64)
    sup[:, _MODE] = wire.FLYING
    clock = np.zeros((n, _CLOCK))
    clock[:, _HEALTHY] = math.nan
    clock[:, _LAST_FLAP] = -math.inf
    p_hold = np.zeros((n, d))
    cur_kappa = kappa.copy()
    cur_swd = swd.copy()
    events = np.zeros((EVENTS, 7), dtype=np.int64)
    floats = np.zeros((EVENTS, 2))  # LANDED's: how long it held, its speed
    fired = np.zeros(1, dtype=np.int64)
    numbers = np.zeros(_CFG)
    for col_, number in ((_H, h), (_HH2, 0.5 * h * h), (_GROUND, cfg.ground), (_THREE, d == 3),
                        (_FEED_CODE, _FEED[m.law.feedforward]), (_MAX_AGE, m.links.max_age),
                        (_COMPENSATE, m.links.compensate), (_LEADER_TIMEOUT, cfg.leader_timeout),
                        (_NEIGHBOUR_TIMEOUT, cfg.neighbour_timeout), (_MAX_ERR, cfg.max_formation_error),
                        (_GAIN_CAP, cfg.gain_cap), (_MAX_SPEED, cfg.max_speed), (_MAX_ACCEL, cfg.max_accel),
                        (_DIVERGE_AT, diverge_at), (_LAND_AFTER, cfg.land_after), (_HOLD_KP, cfg.hold_kp),
                        (_HOLD_KV, cfg.hold_kv), (_LAND_SETTLE, cfg.land_settle),
                        (_CONFIRM, cfg.mode_confirm), (_FLAP_LIMIT, cfg.flap_limit),
                        (_RESUME_DWELL, cfg.resume_dwell)):
        numbers[col_] = float(number)
    found: list[wire.SafetyEvent] = []
    bound = laws[0].bound
    # the law's state, (S, N, d) (one row of zeros for a law without state: an array numba can index)
    init = bound.initial() or ((0.0,) * d,)
    state = np.ascontiguousarray(np.stack([np.broadcast_to(np.asarray(row, dtype=float), (n, d)) for row in init]))
    coef = lawkernels.coefficients(bound, h)
    try:
        ticks = lawkernels.kernel_of("sim.lockstep_kernel", bound.law)._ticks
    except OSError:  # no writable cache for another law's kernels: the Python engine runs it
        return None
    last_u = np.zeros((n, d))
    used = np.zeros(links, dtype=np.int64)
    reports = np.zeros((links, _REPORTS), dtype=np.int64)
    l_src_a = np.array(l_src, dtype=np.int64)  # the leader's links: column n
    outs = tuple(getattr(run, name) for name in _OUTS)
    l_w_a = np.array(l_w, dtype=float)
    l_delta_a = np.array(l_delta, dtype=float).reshape(links, d)
    for k0 in range(0, steps + 1, CHUNK):
        k1 = min(steps + 1, k0 + CHUNK)
        dv = np.empty((k1 - k0, n, d))
        dp = np.empty((k1 - k0, n, d))
        for bank, rows in banks:
            value, bdv, bdp = bank.span(k0, k1)
            dv[:, rows], dp[:, rows] = bdv, bdp
            if record:
                run.d[k0:k1, rows] = value
            elif k1 == steps + 1:
                run.d[0, rows] = value[-1]
        left = ticks(k0, k1, steps, record, numbers, kappa, swd, coef, state,
                     off, l_src_a, l_w_a, l_delta_a, newest, used, hist, hmode, lead, out_ptr, out_dst,
                     p, v, a, last_u, dv, dp, outs, ages, run.safety.safety_mode, run.safety.plant_mode,
                     sup, clock, p_hold, reports, cur_kappa, cur_swd, events, floats, fired)
        if left >= 0:
            return None
        found += _events(events[:int(fired[0])], floats, h, ids, laws, cfg.land_after, cfg.resume_dwell)
        fired[0] = 0
    if record:
        run.t[:] = times
        run.leader_p[:], run.leader_v[:], run.leader_a[:] = lead
    else:
        run.t[0] = times[-1]
        run.leader_p[0], run.leader_v[0], run.leader_a[0] = lead[:, -1]
    for i in range(n):
        counts["used"][i, :off[i + 1] - off[i]] = used[off[i]:off[i + 1]]
    run.links = Links(age=ages, **counts)
    # the plant's watchdog follows HOLD (it rests or cuts its motors only for LANDED and ESTOP)
    run.safety.events = sorted(found, key=lambda e: (e.k, e.vehicle))
    run.zero_absent_shown()  # the kernel records law_state alone
    if progress is not None:  # once, at the end: a run given back to the Python engine never reports
        progress(steps, steps)  # a progress that it would then start again from 0
    return run


def _events(rows: np.ndarray, floats: np.ndarray, h: float, ids: list[int], laws: list[AgentLaw],
            land_after: float, resume_dwell: float) -> list[wire.SafetyEvent]:
    """The loop's event rows ``(k, agent, from, to, kind, m1, m2)`` as the supervisor words them
    (``agent.safety.Supervisor.links`` and ``command``): for a kind of :func:`agent.safety.transition`,
    m1 is HOLD's cause and m2 the lost in-neighbours (``HELD``) or the recoveries counted."""

    def named(i: int, mask: int) -> list[int]:
        return sorted(j for b, j in enumerate(laws[i].neighbours) if mask >> b & 1)

    out = []
    for (k, i, src, dst, kind, m1, m2), (held, speed) in zip(rows.tolist(), floats[:len(rows)].tolist()):
        if kind == _EDGES:
            why = safety.changes(named(i, m1), named(i, m2), safety.EDGES)
        elif kind == _FOLLOW:
            why = safety.changes(named(i, m1), named(i, m2), safety.FOLLOWED)
        elif kind == _HELD:
            why = (f"{safety.listed(named(i, m2))} {safety.UNREACHABLE}" if m1 == safety.UNREACHABLE_CAUSE
                   else safety.HOLD_WHY[m1])
        elif kind != _LANDED:
            why = safety.reason(kind, safety.CAUSES[m1], m2, land_after, resume_dwell)
        else:  # failsafe.why_landed, 2D
            why = failsafe.why_settled(speed, held, False)
        out.append(wire.SafetyEvent(k=k, t=k * h, vehicle=ids[i], src=src, dst=dst, reason=why))
    return out


def _channel(m: Mission, src: int, dst: int) -> "Channel":
    """Link ``src -> dst`` as :meth:`netem.link.Channel.of` makes it, without a decision log (the
    engine reads none: the decisions are the same)."""
    from netem.channel import Link, link_rng
    from netem.link import Channel
    from tether.netprofile import schedule

    assert m.netem is not None
    changes = schedule(m.netem, src, dst)
    return Channel(Link(changes[0][1], link_rng(m.seed, src, dst)), changes)


def arrivals(at: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, int, int, int, int]:
    """What a :class:`~tether.inputs.Source` behind a link holds, given each offer's delivery time
    ``at`` (offer ``s`` is the sample of tick ``s``; NaN: lost) and the ticks' times: the newest
    sequence number held at each tick (-1: none yet), and the samples received, stale, duplicate
    and reordered by the last tick. The link releases, at each tick, every copy due by then,
    earliest first (equal times in the order offered), as :class:`netem.channel.DeliveryQueue` does."""
    seq = np.nonzero(~np.isnan(at))[0]
    due = at[seq]
    keep = due <= times[-1]
    seq, due = seq[keep], due[keep]
    if len(due) == 0 or bool(np.all(np.diff(due) >= 0.0)):  # in order: nothing stale
        held = np.searchsorted(due, times, side="right")
        newest = np.where(held > 0, seq[np.maximum(held - 1, 0)], -1)
        return newest.astype(np.int64), len(seq), 0, 0, 0
    order = np.lexsort((seq, due))
    out = np.empty(len(times), dtype=np.int64)
    stats = _release(seq[order], np.searchsorted(times, due[order], side="left"), len(times), RECENT_SEQS, out)
    return out, len(seq), int(stats[0]), int(stats[1]), int(stats[2])


def _release_py(seq: np.ndarray, tick: np.ndarray, ticks: int, recent: int, out: np.ndarray) -> np.ndarray:
    """The :class:`~tether.inputs.Source` rules over copies in release order (``tick``: when each is
    released): ``out[k]`` the newest sequence number held at tick k; returns (stale, duplicates,
    reordered). Each offer arrives at most once here (no duplication), so a stale copy is a
    reordered one unless it is more than ``recent`` behind."""
    newest = -1
    stale = dup = reord = 0
    c = 0
    for k in range(ticks):
        while c < len(seq) and tick[c] <= k:
            s = seq[c]
            if newest >= 0 and s <= newest:
                stale += 1
                if newest - s > recent:
                    dup += 1
                else:
                    reord += 1
            else:
                newest = s
            c += 1
        out[k] = newest
    return np.array([stale, dup, reord], dtype=np.int64)


_release = kernel.jit(_release_py)


_norm = jit(vec.norm)  # the supervisor's speed and error norm, compiled from its one definition

# The agent's input assembly, compiled from its one definition (agent/law.py): the sample it uses for
# an in-neighbour, axis by axis, the weighted sums term by term, kappa over the edges kept
_neighbour_axis = jit(agent_law.neighbour_axis)
_weighted_term = jit(agent_law.weighted_term)
_total = jit(agent_law.total)

# The failsafe laws' arithmetic, compiled from its one definition (tether/failsafe.py): never re-typed
# here (tests/test_supervisor_rule.py checks these are failsafe's own functions and the loop calls them)
_stopping = jit(failsafe.stopping_distance)
_hold_reach = jit(failsafe.hold_reach)
_anchor_axis = jit(failsafe.anchor_axis)
_floored = jit(failsafe.floored)
_hold_axis = jit(failsafe.hold_axis)
_saturation = jit(failsafe.saturation)
_settled = jit(failsafe.settled)


def _event_py(events: np.ndarray, fired: np.ndarray, k: int, i: int, src: int, dst: int, kind: int, m1: int,
              m2: int) -> bool:
    """Record one event row; False when ``events`` is full (the loop then gives the run back)."""
    row = fired[0]
    if row >= events.shape[0]:
        return False
    events[row, 0] = k
    events[row, 1] = i
    events[row, 2] = src
    events[row, 3] = dst
    events[row, 4] = kind
    events[row, 5] = m1
    events[row, 6] = m2
    fired[0] = row + 1
    return True


_event = kernel.jit(_event_py)


_reaches_in = jit(safety.reaches_in)
""":func:`agent.safety.reaches_in` itself, compiled: the supervisor's graph search (never re-typed here)."""


def _reach_py(i: int, n: int, lo: int, hi: int, mask: int, l_src: np.ndarray, out_ptr: np.ndarray,
              out_dst: np.ndarray, seen: np.ndarray, gone: np.ndarray, stack: np.ndarray) -> bool:
    """``agent.safety.reaches``: whether the leader (column ``n``) reaches agent ``i`` without the
    in-neighbours of link slots ``lo .. hi-1`` whose bits are set in ``mask``."""
    for x in range(n + 1):
        gone[x] = False
    for l in range(lo, hi):
        if mask >> (l - lo) & 1:
            gone[l_src[l]] = True
    return _reaches_in(out_ptr, out_dst, n, i, gone, seen, stack)


_reach = kernel.jit(_reach_py)


def _ticks_py(k0: int, k1: int, steps: int, record: bool, cfg: np.ndarray, kappa: np.ndarray, swd: np.ndarray,
              coef: np.ndarray, state: np.ndarray, off: np.ndarray, l_src: np.ndarray, l_w: np.ndarray,
              l_delta: np.ndarray, newest: np.ndarray, used: np.ndarray, hist: np.ndarray, hmode: np.ndarray,
              lead: np.ndarray, out_ptr: np.ndarray, out_dst: np.ndarray, p: np.ndarray, v: np.ndarray,
              a: np.ndarray, last_u: np.ndarray, dv: np.ndarray, dp: np.ndarray, outs: tuple[np.ndarray, ...],
              out_age: np.ndarray, out_mode: np.ndarray, out_pmode: np.ndarray, sup: np.ndarray,
              clock: np.ndarray, p_hold: np.ndarray, reports: np.ndarray, cur_kappa: np.ndarray,
              cur_swd: np.ndarray, events: np.ndarray, floats: np.ndarray, fired: np.ndarray) -> int:
    """Ticks ``k0 .. k1-1`` of the in-process engine (the rows of ``outs``, the run's
    ``p, v, a, u, xi, zeta, law_state``: every tick when ``record``, else only the last tick's into row
    0). Returns -1, or the first tick this loop does not model (nothing of that tick is kept). It
    models FLYING and HOLD with the causes ``leader`` and ``unreachable``, edges dropped and
    restored, and in 2D LAND (after ``land_after``, or instead of one flap too many) and LANDED
    (``agent.safety.Supervisor``); a bound of ``[safety]`` reached, a landing in 3D or a value not
    finite where a mode would take it is left to the Python engine.

    ``cfg``: the numbers of the run (columns ``_H`` ... ``_RESUME_DWELL``). Links, flattened in agent
    order then in-neighbour order (agent i's slots ``off[i] .. off[i+1]-1``): the sender's column
    ``l_src`` (the leader's: N), weight ``l_w`` and offset ``l_delta``. State carried between calls:
    ``p, v, a`` (the plants), ``last_u``, the law's ``state`` ``(S, N, d)`` (``coef`` ``(d, C)``:
    per axis, its coefficients), ``used``, the history ring ``hist`` ``(3, R, N+1, d)`` (p, v,
    shared a; column N the leader) and ``hmode`` ``(R, N+1)`` (the mode each sample carried), each
    supervisor's ``sup`` and ``clock`` (columns ``_MODE`` ..., ``_SINCE`` ...) and ``p_hold``, the
    law over its surviving edges (``cur_kappa, cur_swd``; ``kappa, swd`` the mission's), and per
    link slot the neighbour's mode reports (``reports``: :func:`agent.safety.believe`'s state).
    Events go to ``events`` ``(E, 7)``: k, agent, from, to, kind, m1, m2 (LANDED's held time and
    speed to ``floats``); ``fired[0]`` counts them. ``dv, dp``: the disturbance increments of these
    ticks. The supervisor's rule is :mod:`agent.safety`'s own functions, compiled; every other
    expression below is the Python's, in its order (the comments name the function)."""
    out_p, out_v, out_a, out_u, out_xi, out_zeta, out_x = outs
    h = cfg[_H]
    hh2 = cfg[_HH2]
    ground = cfg[_GROUND]
    three = cfg[_THREE] != 0.0
    feed = int(cfg[_FEED_CODE])
    max_age = cfg[_MAX_AGE]
    compensate = cfg[_COMPENSATE] != 0.0
    leader_timeout = cfg[_LEADER_TIMEOUT]
    neighbour_timeout = cfg[_NEIGHBOUR_TIMEOUT]
    max_err = cfg[_MAX_ERR]
    gain_cap = cfg[_GAIN_CAP]
    max_speed = cfg[_MAX_SPEED]
    max_accel = cfg[_MAX_ACCEL]
    diverge_at = cfg[_DIVERGE_AT]
    land_after = cfg[_LAND_AFTER]
    hold_kp = cfg[_HOLD_KP]
    hold_kv = cfg[_HOLD_KV]
    land_settle = cfg[_LAND_SETTLE]
    confirm = int(cfg[_CONFIRM])
    flap_limit = int(cfg[_FLAP_LIMIT])
    resume_dwell = cfg[_RESUME_DWELL]
    n, d = p.shape
    ring = hist.shape[1]
    hp = hist[0]
    hv = hist[1]
    ha = hist[2]
    width = out_age.shape[2]
    age_of = np.empty(max(width, 1))
    u = np.empty((n, d))
    xi = np.empty(d)
    zeta = np.empty(d)
    nstate = np.empty((state.shape[0], 1, d))  # the law's next state, one agent's
    seen = np.zeros(n + 1, dtype=np.bool_)
    gone = np.zeros(n + 1, dtype=np.bool_)
    stack = np.empty(n + 1, dtype=np.int64)
    nan = math.nan
    flying, hold, land, landed = _FLYING, _HOLD, _LAND_MODE, _LANDED_MODE
    for k in range(k0, k1):
        t = k * h
        keep = record or k == steps
        r = k if record else 0
        q = k % ring
        # what each sender publishes at tick k (the leader's reference; each agent's sample, and as
        # its acceleration the measured one or its previous command: AgentTick.shared; its mode)
        for c in range(d):
            hp[q, n, c] = lead[0, k, c]
            hv[q, n, c] = lead[1, k, c]
            ha[q, n, c] = lead[2, k, c]
        hmode[q, n] = flying
        for i in range(n):
            for c in range(d):
                hp[q, i, c] = p[i, c]
                hv[q, i, c] = v[i, c]
                ha[q, i, c] = a[i, c] if feed == 0 else last_u[i, c]
            hmode[q, i] = sup[i, _MODE]
        for i in range(n):
            lo = off[i]
            hi = off[i + 1]
            # Supervisor.links: each in-neighbour's age; the leader silent; an agent neighbour lost
            # (stopped, or silent past its timeout)
            silent = False
            missing = 0
            holding = 0
            for l in range(lo, hi):
                s = newest[k, l]
                never = s < 0
                age = nan if never else t - s * h
                age_of[l - lo] = age
                if l_src[l] == n:  # the leader
                    silent = _silent(age, t, leader_timeout)
                else:
                    # the neighbour's mode report, believed once `confirm` consecutive ticks say it
                    quiet = _silent(age, t, neighbour_timeout)
                    said = _REPORT_FLYING
                    if not (quiet or never):
                        said = _report_kind(hmode[s % ring, l_src[l]])
                    reports[l, _SAID], reports[l, _RUN], reports[l, _BELIEF] = _believe(
                        said, reports[l, _SAID], reports[l, _RUN], reports[l, _BELIEF], confirm)
                    if quiet or reports[l, _BELIEF] == _REPORT_STOPPED:
                        missing |= 1 << (l - lo)
                    elif reports[l, _BELIEF] == _REPORT_HOLD:
                        holding |= 1 << (l - lo)
            reachable = True
            if missing != 0:  # tether's reaches(): the leader to this agent without the lost ones
                reachable = _reach(i, n, lo, hi, missing, l_src, out_ptr, out_dst, seen, gone, stack)
            follow_new = 0
            drop = missing
            if reachable and holding != 0:  # a holding neighbour: dropped if not needed, else followed
                if _reach(i, n, lo, hi, missing | holding, l_src, out_ptr, out_dst, seen, gone, stack):
                    drop = missing | holding
                else:
                    follow_new = holding
            new = drop if reachable else 0
            if new != sup[i, _LOST]:  # edges dropped or restored: an event, and the law over the others
                if not _event(events, fired, k, i, sup[i, _MODE], sup[i, _MODE], _EDGES, new & ~sup[i, _LOST], sup[i, _LOST] & ~new):
                    return k
                sup[i, _LOST] = new
                if new == 0:  # the mission's own law
                    cur_kappa[i] = kappa[i]
                    for c in range(d):
                        cur_swd[i, c] = swd[i, c]
                else:  # AgentLaw.without: the weights of the lost zeroed, kappa and sum_wdelta over them
                    kept = np.empty(hi - lo)
                    for l in range(lo, hi):
                        kept[l - lo] = 0.0 if new >> (l - lo) & 1 else l_w[l]
                    cur_kappa[i] = _total(kept)
                    for c in range(d):
                        sd = 0.0
                        for l in range(lo, hi):
                            sd = _weighted_term(l - lo, sd, kept[l - lo], l_delta[l, c])
                        cur_swd[i, c] = sd
            if follow_new != sup[i, _FOLLOWED]:  # holding neighbours followed, or no longer
                if not _event(events, fired, k, i, sup[i, _MODE], sup[i, _MODE], _FOLLOW, follow_new & ~sup[i, _FOLLOWED],
                              sup[i, _FOLLOWED] & ~follow_new):
                    return k
                sup[i, _FOLLOWED] = follow_new
            # agent.law.neighbour_sample per in-neighbour (neighbour_axis), AgentLaw.step (weighted_term)
            ka = cur_kappa[i]
            for c in range(d):
                sp = 0.0
                sv = 0.0
                sa = 0.0
                for l in range(lo, hi):
                    age = age_of[l - lo]
                    s = newest[k, l]
                    usable = s >= 0 and age <= max_age
                    pj = vj = aj = 0.0
                    if usable:
                        qs = s % ring
                        src = l_src[l]
                        pj = hp[qs, src, c]
                        vj = hv[qs, src, c]
                        aj = ha[qs, src, c]
                    pj, vj, aj = _neighbour_axis(p[i, c], v[i, c], l_delta[l, c], pj, vj, aj, usable, age, compensate)
                    if feed == 2:
                        aj = 0.0
                    w = 0.0 if sup[i, _LOST] >> (l - lo) & 1 else l_w[l]
                    sp = _weighted_term(l - lo, sp, w, pj)
                    sv = _weighted_term(l - lo, sv, w, vj)
                    sa = _weighted_term(l - lo, sa, w, aj)
                uu, e, z, xn = law_step(ka, p[i, c], v[i, c], sp, sv, sa, cur_swd[i, c], law_load(state, i, c),
                                        coef[c])
                xi[c] = e
                zeta[c] = z
                u[i, c] = uu
                law_store(nstate, 0, c, xn)
            # the engine's diverge_at (every mode): the run ends there
            for c in range(d):
                if not abs(xi[c]) <= diverge_at:
                    return k
            active = sup[i, _MODE] == flying or sup[i, _MODE] == hold
            if active:
                # Supervisor._diverged (|xi|, the gains, a finite command) and the speed bound: mode
                # changes this loop does not follow
                err = _norm(xi)
                if not err <= max_err:
                    return k
                for c in range(d):
                    shown = law_shown(law_load(state, i, c))
                    if not (shown[0] <= gain_cap and shown[1] <= gain_cap) or not math.isfinite(u[i, c]):
                        return k
                if _norm(v[i]) > max_speed:
                    return k
            # Supervisor.command: HOLD's cause (the loop models the leader silent, for an agent that
            # hears it, and the leader no longer reaching it) and agent.safety.transition, compiled
            if active:
                md = sup[i, _MODE]
                why = _hold_cause(False, False, False, False, silent, False, reachable)
                nm, nc, _, nsince, nhealthy, nflaps, nlast, kind = _transition(
                    md, sup[i, _CAUSE], False, clock[i, _SINCE], clock[i, _HEALTHY], sup[i, _FLAPS],
                    clock[i, _LAST_FLAP], why, t, land_after, flap_limit, resume_dwell)
                if nm == land and three:
                    return k  # a 3D landing (Landing's memory, the ground): the Python engine's
                if kind != _STAY:
                    if md == flying:  # HOLD or LAND begins: agent.safety.anchor
                        for c in range(d):
                            if not math.isfinite(p[i, c]):
                                return k  # nowhere to hold: the Python engine's (a zero command)
                        # failsafe.hold_point (3D: floor at the ground; no geofence here)
                        speed = _norm(v[i])
                        scale = _hold_reach(speed, _stopping(speed, hold_kp, max_accel))
                        if scale == scale:
                            for c in range(d):
                                p_hold[i, c] = _anchor_axis(p[i, c], v[i, c], scale)
                            if three:
                                p_hold[i, d - 1] = _floored(p[i, d - 1], p_hold[i, d - 1], ground)
                        else:
                            for c in range(d):
                                p_hold[i, c] = p[i, c]
                    if not _event(events, fired, k, i, md, nm, kind, nc, missing if kind == _HELD else nflaps):
                        return k
                sup[i, _MODE] = nm
                sup[i, _CAUSE] = nc
                sup[i, _FLAPS] = nflaps
                clock[i, _SINCE] = nsince
                clock[i, _HEALTHY] = nhealthy
                clock[i, _LAST_FLAP] = nlast
            if sup[i, _MODE] == land:  # 2D: failsafe.landed (still, or held land_settle), else HOLD's law
                held = t - clock[i, _SINCE]
                speed = _norm(v[i])
                if _settled(speed, 0.0, held, land_settle, False):
                    row = fired[0]
                    if not _event(events, fired, k, i, land, landed, _LANDED, 0, 0):
                        return k
                    floats[row, 0] = held
                    floats[row, 1] = speed
                    sup[i, _MODE] = landed
                    clock[i, _SINCE] = t
            if sup[i, _MODE] == landed:  # a zero command; the plant rests
                for c in range(d):
                    u[i, c] = 0.0
            else:
                if sup[i, _MODE] != flying:  # failsafe.hold (LAND in 2D too): brake, return to p_hold
                    for c in range(d):
                        u[i, c] = _hold_axis(p[i, c], v[i, c], p_hold[i, c], hold_kp, hold_kv)
                # failsafe.saturate
                uu = u[i, 0] * u[i, 0]
                for c in range(1, d):
                    uu = uu + u[i, c] * u[i, c]
                if not math.isfinite(uu):
                    return k  # HOLD's command not finite: the Python engine's (a zero command)
                scale = _saturation(uu, max_accel)
                if scale != 1.0:
                    for c in range(d):
                        u[i, c] = u[i, c] * scale
            if keep:
                for c in range(d):
                    out_p[r, i, c] = p[i, c]
                    out_v[r, i, c] = v[i, c]
                    out_a[r, i, c] = a[i, c]
                    out_u[r, i, c] = u[i, c]
                    out_xi[r, i, c] = xi[c]
                    out_zeta[r, i, c] = zeta[c]
                    law_record(out_x, r, i, c, law_load(state, i, c))
                out_mode[r, i] = sup[i, _MODE]
                out_pmode[r, i] = landed if sup[i, _MODE] == landed else flying  # the plant's watchdog
            for l in range(lo, hi):
                s = newest[k, l]
                age = age_of[l - lo]
                ok = s >= 0 and age <= max_age
                if ok:
                    used[l] += 1
                if keep:
                    out_age[r, i, l - lo] = age if ok else nan
            # the law's state advances while FLYING; the command is the one shared next tick
            if sup[i, _MODE] == flying:
                for c in range(d):
                    law_store(state, i, c, law_load(nstate, 0, c))
            for c in range(d):
                last_u[i, c] = u[i, c]
        if k == steps:
            break
        # plant.double_integrator.step with the bank's increments of tick k; a LANDED vehicle rests
        # where it was (plant.rest.Resting: its model, stepped on, is never reported again)
        j = k - k0
        for i in range(n):
            if sup[i, _MODE] == landed:
                for c in range(d):
                    v[i, c] = 0.0
                    a[i, c] = 0.0
                continue
            for c in range(d):
                pn = p[i, c] + h * v[i, c] + hh2 * u[i, c] + dp[j, i, c]
                vn = v[i, c] + h * u[i, c] + dv[j, i, c]
                a[i, c] = u[i, c] + dv[j, i, c] / h
                p[i, c] = pn
                v[i, c] = vn
            if three and p[i, d - 1] < ground:  # plant.rest.Resting: the ground stops it
                return k + 1
    return -1


_ticks = kernel.jit(_ticks_py)
