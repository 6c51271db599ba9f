"""The checks a control engineer expects of a mission, beyond what its types say. Pure.

:func:`validate` takes a decoded :class:`~tether.mission.Mission` and returns every problem it finds
as ``(field path, "<what is wrong>; <how to fix it>")`` pairs: non-finite numbers, rates and
durations, ids, dimensions, the leader's profile and the disturbances, the edges (self-loops,
weights, duplicates, edges into the leader), the law's parameters (Theorem 1's ``K(0) >= 1`` and
``sigma > 0``), the vehicles and the payload, the network section, the ``[safety]`` section, and
Assumption 1 (:func:`unreachable_agents`: every agent has a directed path from the leader), the
namespace the mission's name gives its keys, physical bounds (gains, extents, a leader profile
flyable within ``[safety]``) and the run's size (:func:`run_bytes` against :data:`MAX_RUN_BYTES`).
:func:`tether.mission.loads` runs it on every mission it decodes.

Every check is O(N + edges + profile points): a 10 000-agent mission is checked in about a second.
A problem of an agent or an edge is named by the agent's id or the edge's ends, not by the table's
place in the file (``agent 7.offset``, ``edge 3 → 4.weight``; :func:`tether.mission.by_id`), which
is what a reader of a large generated mission looks for.
"""

from __future__ import annotations

import functools
import math

import msgspec
import msgspec.structs

from agent import laws

from tether.mission import (
    BoundedRandom,
    Constant,
    CrazyfliePlant,
    Disturbance,
    DisturbanceSum,
    DoubleIntegrator,
    ExpAccel,
    Mission,
    PerAxis,
    PointMassPlant,
    QuadrotorPlant,
    Safety,
    Sinusoid,
    VelocitySchedule,
    Waypoints,
    by_id,
    ordinal,
    per_axis,
)
from tether.netprofile import validate_network
from tether.schema import Problems
from tether.wire import Keys

__all__ = ["MAX_AGENT_TICKS", "MAX_EXTENT", "MAX_RATE", "MAX_RUN_BYTES", "MAX_ID", "MAX_SEED", "MIN_AGE", "MIN_RATE", "WEIGHT_RANGE",
           "run_bytes", "unreachable_agents", "validate", "validate_duration"]

# --------------------------------------------------------------------------- limits (docs/mission.md)
MIN_RATE, MAX_RATE = 0.1, 10_000.0
"""Control rate bounds [Hz]: below 0.1 Hz a period of more than 10 s is no feedback loop for a
vehicle; above 10 kHz no process ticks (a Zenoh round trip alone is ~0.1 ms)."""
MAX_RUN_BYTES = 4 * 2**30
"""Largest run a mission may ask for, by :func:`run_bytes` (4 GiB): beyond it the reference
simulator's or the recorder's arrays would not fit a laptop's memory."""
MAX_AGENT_TICKS = 10**9
"""Largest steps x agents a mission may ask for: about 3 hours of the reference simulator."""
MAX_EXTENT = 1e5
"""Largest coordinate of a position or an offset [m] (100 km): beyond it, a position in float64
has less than 1e-11 m resolution left for the law's differences, and nothing flies that far."""
WEIGHT_RANGE = (1e-6, 1e6)
"""Allowed edge weights a_ij: the ratio of the largest to the smallest weight bounds how badly
conditioned L1 (Eq. 7) is, and 1e12 leaves Lemma 3 solvable in float64; a weight like 5e-324
(subnormal) is an absent edge written as a number."""
MAX_ID = 2**31 - 1
"""Largest node id: an id is a key chunk and every message's ``sender`` (a msgpack integer)."""
MAX_SEED = 2**63 - 1
"""Largest seed (an int64 in run files and network models)."""
MIN_AGE = 1e-3
"""Smallest ``links.max_age`` and ``[safety]`` timeout [s]: 1 ms, below any network's delivery
time, so a smaller value would throw away every real-time sample."""
MAX_WAIT = 60.0
"""Longest any ``[safety]`` wait may be [s] (``leader_timeout``, ``neighbour_timeout``,
``cmd_timeout``, ``cmd_cutoff``, ``land_after``, ``land_settle``): the longest default is 10 s, and a
supervisor that leaves a lost input unanswered for more than a minute (a vehicle drifting at 1 m/s
is 60 m away by then) is switched off, not tuned."""
MAX_ACCEL = 100.0
"""Largest ``safety.max_accel`` [m/s^2] (about 10 g): twice the thrust of the most powerful racing
quadrotors; a cap above it caps nothing a multirotor can do."""
MAX_SPEED = 343.0
"""Largest ``safety.max_speed`` [m/s]: the speed of sound in air at 20 °C, which no multirotor
approaches; a plausibility bound above it rejects no sample at all."""
MAX_GAIN_CAP = 1e6
"""Largest ``safety.gain_cap``: with a gain of 10⁶ the law's command saturates at the default
``max_accel`` for any error above 20 µm, so a larger cap never tells divergence from flight."""
SERIES_RECORDED = 9 + 3
"""Per-agent ``(T, N, d)`` series of a run file: the engines' nine (``tether.runfile.SERIES``; a
number here, so that a process checking its mission does not load the run file's numpy) and the
recorder's three plant measurements."""
LINK_SERIES = 10
"""Per-edge ``(T, edges)`` link statistics the recorder keeps."""


def run_bytes(m: Mission, steps: int | None = None) -> int:
    """Estimated size of the run file's arrays for ``steps`` periods (the mission's by default) [bytes]:
    ``(steps + 1) x 8 x (SERIES_RECORDED x N x d + LINK_SERIES x edges + 4 x N + 3 x d)`` (the
    per-agent series, the link statistics, the per-agent counters and modes, the leader's p, v, a).
    The reference simulator holds the same arrays in memory; the recorder preallocates them."""
    steps = m.steps if steps is None else steps
    per_sample = SERIES_RECORDED * m.n * m.dim + LINK_SERIES * len(m.edges) + 4 * m.n + 3 * m.dim + 1
    return (steps + 1) * 8 * per_sample


def _gib(x: float) -> str:
    return f"{x / 2**30:.3g} GiB" if x >= 2**20 else f"{x / 2**20:.3g} MiB"


def validate_duration(m: Mission, duration: float, field: str = "duration") -> Problems:
    """The checks of a run length ``duration`` [s] (the mission's, or a ``--duration`` override named
    ``field``): finite, > 0, a whole number of periods, and a run within :data:`MAX_RUN_BYTES` and
    :data:`MAX_AGENT_TICKS`. Every command checks ``--duration`` with this one function."""
    out: Problems = []
    if not math.isfinite(duration) or duration <= 0:
        out.append((field, f"is {duration} s; set a duration > 0 (a finite number of seconds)"))
        return out
    if not m.rate > 0 or not math.isfinite(m.rate):
        return out
    if not _whole_periods(duration, m.rate):
        out.append((field, f"is {duration} s, not a whole number of control periods at {m.rate} Hz; "
                           f"make duration * rate an integer, e.g. "
                           f"`{field}{' ' if field.startswith('--') else ' = '}{_nearest_periods(duration, m.rate)!r}`"))
        return out
    steps = int(round(duration * m.rate))
    if steps * m.n > MAX_AGENT_TICKS:
        out.append((field, f"is {duration:g} s: {steps} steps x {m.n} agents = {steps * m.n:.3g} agent-ticks, "
                           f"beyond the limit of {MAX_AGENT_TICKS:.0e}; shorten the duration or lower the rate"))
        return out
    need = run_bytes(m, steps)
    if need > MAX_RUN_BYTES:
        out.append((field, f"is {duration:g} s: a run of {steps} steps x {m.n} agents x dim {m.dim} needs about "
                           f"{_gib(need)} of arrays, beyond the {_gib(MAX_RUN_BYTES)} limit; shorten the duration "
                           f"(at most {_longest(m, MAX_RUN_BYTES):g} s at {m.rate:g} Hz), lower the rate, or run "
                           "the library with record=False (refsim.simulate keeps only the last sample)"))
    return out


def _longest(m: Mission, budget: int) -> float:
    """The longest duration [s] whose run fits ``budget`` bytes."""
    per_step = run_bytes(m, 1) - run_bytes(m, 0)
    return max(1, budget // per_step - 1) / m.rate


def _ids(ids: list[int], most: int = 8) -> str:
    """``[1, 2, 3]``, or its first few ids and how many more."""
    if len(ids) <= most:
        return str(ids)
    return f"[{', '.join(map(str, ids[:most]))}, ... ({len(ids) - most} more)]"


def _finite_tree(obj: object, path: str, out: Problems) -> None:
    """Report every NaN/Inf number anywhere in the mission."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            out.append((path, f"is {obj}; write a finite number (NaN and infinity are not allowed)"))
    elif isinstance(obj, list):
        for k, item in enumerate(obj):
            _finite_tree(item, f"{path}[{k}]", out)
    elif isinstance(obj, msgspec.Struct):
        for name, enc in _encoded_names(type(obj)):
            _finite_tree(getattr(obj, name), f"{path}.{enc}" if path else enc, out)


@functools.cache
def _encoded_names(cls: type) -> tuple[tuple[str, str], ...]:
    """``(attribute, name in the file)`` of every field of a struct (``Edge.src`` is ``from``), read once
    per class (msgspec re-reads a class's annotations on every call)."""
    return tuple((f.name, f.encode_name) for f in msgspec.structs.fields(cls))


def _axes(dim: int) -> str:
    return "x, y" if dim == 2 else "x, y, z"


def _check_vec(v: list[float] | None, dim: int, path: str, out: Problems) -> None:
    if v is not None and len(v) != dim:
        out.append((path, f"has {len(v)} component(s) but the mission has dim = {dim}; "
                          f"give {dim} components ({_axes(dim)})"))


def _check_per_axis(v: PerAxis, dim: int, path: str, out: Problems) -> None:
    if isinstance(v, list):
        _check_vec(v, dim, path, out)


def _whole_periods(x: float, rate: float) -> bool:
    """Whether ``x`` seconds is a whole number of control periods at ``rate`` Hz."""
    return abs(x * rate - round(x * rate)) <= 1e-6


def _nearest_periods(x: float, rate: float) -> float:
    """The nearest positive whole number of control periods to ``x`` seconds, in seconds."""
    return max(1, round(x * rate)) / rate


def _and(items: list[int]) -> str:
    """``[3]`` -> ``"3"``, ``[3, 4]`` -> ``"3 and 4"``, ``[2, 3, 4]`` -> ``"2, 3 and 4"``."""
    words = [str(i) for i in items]
    return words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"


def validate(m: Mission) -> Problems:
    """Every semantic problem of a decoded mission, as ``(field, message-with-fix)`` pairs.

    Non-finite numbers are reported alone (later checks compare numbers, and NaN would only add
    confusing follow-ups); Assumption 1 is checked only once the ids and edges are otherwise right.
    """
    out: Problems = []
    _finite_tree(m, "", out)
    if out:
        return _label(m, out)
    d = m.dim

    if m.rate <= 0:
        out.append(("rate", f"is {m.rate} Hz; set a control rate > 0, e.g. `rate = 100.0`"))
    elif not MIN_RATE <= m.rate <= MAX_RATE:
        out.append(("rate", f"is {m.rate:g} Hz, outside [{MIN_RATE:g}, {MAX_RATE:g}] Hz (a feedback loop a "
                            f"process can tick); set e.g. `rate = 100.0`"))
    rate_ok = MIN_RATE <= m.rate <= MAX_RATE
    if m.duration <= 0 or rate_ok:
        out.extend(validate_duration(m, m.duration) if rate_ok else [("duration", f"is {m.duration} s; set a duration > 0")])
    if not m.name:
        out.append(("name", "is empty; name the mission, e.g. `name = \"formation-1\"` (it is the key namespace)"))
    else:
        try:
            Keys(m.name)
        except ValueError:
            bad = sorted(set("/*$#?@ ") & set(m.name))
            out.append(("name", f"is {m.name!r}, which holds {' '.join(repr(c) for c in bad)}; the name is the run's "
                                "Zenoh key namespace (one key chunk): use letters, digits, '-', '_' or '.', "
                                "e.g. " + repr(''.join('-' if c in '/*$#?@ ' else c for c in m.name))))
    if m.seed < 0:
        out.append(("seed", f"is {m.seed}; use a seed >= 0 (random generators take non-negative seeds)"))
    elif m.seed > MAX_SEED:
        out.append(("seed", f"is {m.seed}, beyond 2^63 - 1 (run files store it as int64); use a smaller seed"))

    # ids
    if not m.agents:
        out.append(("agents", "is empty; declare at least one [[agents]] table"))
    seen: dict[int, int] = {}
    for k, a in enumerate(m.agents):
        if a.id <= 0:
            out.append((f"agents[{k}].id", f"is {a.id}; use a positive integer id"))
        elif a.id > MAX_ID:
            out.append((f"agents[{k}].id", f"is {a.id}, beyond {MAX_ID} (ids go on the wire as integers and into "
                                           "keys); use a smaller positive id"))
        if a.id in seen:
            out.append((f"agents[{k}].id", f"is {a.id} in the {ordinal(seen[a.id] + 1)} and the {ordinal(k + 1)} "
                                           "[[agents]] tables; give every agent its own id"))
        seen.setdefault(a.id, k)
        if a.id == m.leader.id:
            out.append((f"agents[{k}].id", f"is {a.id}, the leader's id; give the agent and the leader "
                                           "different ids"))
        _check_vec(a.p0, d, f"agents[{k}].p0", out)
        _check_vec(a.v0, d, f"agents[{k}].v0", out)
        _check_vec(a.offset, d, f"agents[{k}].offset", out)
        _validate_disturbance(a.disturbance, d, m.rate, f"agents[{k}].disturbance", out)
    if m.leader.id <= 0:
        out.append(("leader.id", f"is {m.leader.id}; use a positive integer id"))
    elif m.leader.id > MAX_ID:
        out.append(("leader.id", f"is {m.leader.id}, beyond {MAX_ID} (ids go on the wire as integers and into "
                                 "keys); use a smaller positive id"))
    _check_vec(m.leader.p0, d, "leader.p0", out)
    _check_vec(m.leader.v0, d, "leader.v0", out)
    _validate_profile(m, out)

    # edges
    nodes = set(seen) | {m.leader.id}
    listing = _ids(sorted(nodes))
    pairs: dict[tuple[int, int], int] = {}
    lo, hi = WEIGHT_RANGE
    for k, e in enumerate(m.edges):
        where = f"edges[{k}]"
        if e.src not in nodes:
            out.append((f"{where}.from", f"is {e.src}, which is neither an agent nor the leader; "
                                         f"use one of the ids {listing}"))
        if e.dst not in nodes:
            out.append((f"{where}.to", f"is {e.dst}, which is neither an agent nor the leader; "
                                       f"use one of the ids {listing}"))
        if e.dst == m.leader.id and e.src != e.dst:
            out.append((f"{where}.to", f"is {e.dst}, the virtual leader, which hears nobody (Eq. 6); "
                                       f"remove the edge or reverse it (`from = {e.dst}, to = {e.src}`)"))
        if e.src == e.dst:
            out.append((where, f"is a self-loop on {e.src} (a_ii = 0 by definition); remove it"))
        if e.weight <= 0:
            out.append((f"{where}.weight", f"is {e.weight} but an edge has a_ij > 0; give a positive "
                                           "weight, or remove the edge for a_ij = 0"))
        elif not lo <= e.weight <= hi:
            out.append((f"{where}.weight", f"is {e.weight:g}, outside [{lo:g}, {hi:g}] (a wider "
                                           "spread of weights makes L1 numerically singular, Lemma 3); rescale "
                                           "the weights, or remove the edge for a_ij = 0"))
        key = (e.src, e.dst)
        if key in pairs:
            out.append((where, f"repeats the {ordinal(pairs[key] + 1)} [[edges]] table (both are {e.src} → {e.dst}); "
                               "merge them into one edge with one weight"))
        pairs.setdefault(key, k)

    # law: its parameters, validated by the law itself
    out.extend(laws.bind(m)[1])

    _validate_physics(m, out)
    if m.links.max_age <= 0:
        out.append(("links.max_age", f"is {m.links.max_age} s; the oldest usable sample age must be > 0 (e.g. 0.5)"))
    elif m.links.max_age < MIN_AGE:
        out.append(("links.max_age", f"is {m.links.max_age:g} s, below {MIN_AGE:g} s (no network delivers a sample "
                                     "that young, so every sample would be dropped); use e.g. 0.5"))
    _validate_bounds(m, out)
    if m.netem is not None:
        out.extend(validate_network(m.netem, set(seen) | {m.leader.id}, path="netem"))
    _validate_safety(m, out)

    # Assumption 1 only makes sense on a graph whose ids are right
    if not any(f.startswith(("edges", "agents", "leader.id")) for f, _ in out):
        unreachable = unreachable_agents(m)
        if unreachable:
            out.append(("edges", f"break Assumption 1: the leader ({m.leader.id}) has no directed path to "
                                 f"agent{'s' if len(unreachable) > 1 else ''} {_and(unreachable)}; add edges so "
                                 "that each of them hears the leader or an agent the leader reaches, e.g. "
                                 f"`{{ from = {m.leader.id}, to = {unreachable[0]} }}`"))
    return _label(m, out)


def _norm(v: list[float]) -> float:
    return math.sqrt(sum(x * x for x in v))


def _validate_bounds(m: Mission, out: Problems) -> None:
    """Physical bounds: gains within ``safety.gain_cap``, coordinates within :data:`MAX_EXTENT`,
    speeds within ``safety.max_speed``, and a leader profile the vehicles can fly within
    ``safety.max_speed`` and ``safety.max_accel`` (else the run is over before it starts: the
    supervisors call it divergence, or the reference leaves every vehicle behind)."""
    sf = m.safety
    cap = sf.gain_cap
    law = m.law
    if cap > 1 and law.kind != "custom":
        for name in ("kp0", "kv0"):
            val = getattr(law, name)
            for k, x in enumerate(val if isinstance(val, list) else [val]):
                if x > cap:
                    field = f"law.{name}" + (f"[{k}]" if isinstance(val, list) else "")
                    out.append((field, f"is {x:g}, beyond safety.gain_cap ({cap:g}): every supervisor would call "
                                       f"it divergence at t = 0; use a gain <= {cap:g} (e.g. 2.0), or raise the cap"))

    def extent(v: list[float] | None, field: str) -> None:
        if v is not None and any(abs(x) > MAX_EXTENT for x in v):
            out.append((field, f"has a coordinate of {max(abs(x) for x in v):g} m, beyond {MAX_EXTENT:g} m; give "
                               "positions and offsets within 100 km of the origin (shift the frame)"))

    def speed(v: list[float] | None, field: str, what: str = "is") -> None:
        if v is not None and sf.max_speed > 0 and _norm(v) > sf.max_speed:
            out.append((field, f"{what} a speed of {_norm(v):g} m/s, beyond safety.max_speed ({sf.max_speed:g} "
                               "m/s); give a slower velocity, or raise max_speed"))

    for k, a in enumerate(m.agents):
        extent(a.p0, f"agents[{k}].p0")
        extent(a.offset, f"agents[{k}].offset")
        speed(a.v0, f"agents[{k}].v0", "has")
    extent(m.leader.p0, "leader.p0")
    speed(m.leader.v0, "leader.v0", "has")
    if m.payload is not None:
        extent(m.payload.p0, "payload.p0")
    if sf.geofence is not None:
        extent(sf.geofence.min, "safety.geofence.min")
        extent(sf.geofence.max, "safety.geofence.max")
    if m.floor is not None and abs(m.floor) > MAX_EXTENT:
        out.append(("floor", f"is {m.floor:g} m, beyond {MAX_EXTENT:g} m; give a height within 100 km"))

    prof, path = m.leader.profile, "leader.profile"
    amax, vmax = sf.max_accel, sf.max_speed
    if not (amax > 0 and vmax > 0):
        return
    if isinstance(prof, ExpAccel):
        if _norm(prof.a0) > amax:
            out.append((f"{path}.a0", f"has a norm of {_norm(prof.a0):g} m/s^2, beyond safety.max_accel ({amax:g} "
                                      "m/s^2), which caps every command; give a smaller a0, or raise max_accel"))
        elif m.duration > 0 and len(prof.a0) == m.dim:
            lam, T = prof.decay, m.duration
            i1 = T if lam == 0 else -math.expm1(-lam * T) / lam
            v0 = m.leader.v0 or [0.0] * m.dim
            if len(v0) == m.dim:
                end = [v + a * i1 for v, a in zip(v0, prof.a0)]
                if _norm(end) > vmax:
                    out.append((f"{path}.a0", f"takes the leader to {_norm(end):.4g} m/s by t = {T:g} s, beyond "
                                              f"safety.max_speed ({vmax:g} m/s); give a smaller a0, a larger decay "
                                              "or a shorter duration"))
    elif isinstance(prof, VelocitySchedule):
        for k, seg in enumerate(prof.segments):
            speed(seg.v, f"{path}.segments[{k}].v", "has")
            if k and prof.ramp > 0:
                dv = _norm([a - b for a, b in zip(seg.v, prof.segments[k - 1].v)])
                if dv / prof.ramp > amax:
                    out.append((f"{path}.ramp", f"is {prof.ramp:g} s, so segments[{k}] asks {dv / prof.ramp:.4g} "
                                                f"m/s^2, beyond safety.max_accel ({amax:g} m/s^2); lengthen the "
                                                f"ramp to >= {dv / amax:.3g} s"))
                    break
    elif isinstance(prof, Waypoints):
        pts = prof.points
        for k, pt in enumerate(pts):
            extent(pt.p, f"{path}.points[{k}].p")
        for k in range(1, len(pts)):
            span = pts[k].t - pts[k - 1].t
            if span <= 0 or len(pts[k].p) != len(pts[k - 1].p):
                continue
            dist = _norm([a - b for a, b in zip(pts[k].p, pts[k - 1].p)])
            v_peak, a_peak = 1.875 * dist / span, 10 / math.sqrt(3) * dist / (span * span)
            if v_peak > vmax or a_peak > amax:
                need = max(1.875 * dist / vmax, math.sqrt(10 / math.sqrt(3) * dist / amax))
                out.append((f"{path}.points[{k}].t", f"is {span:.4g} s after points[{k - 1}] for {dist:.4g} m: the "
                                                     f"minimum-jerk segment peaks at {v_peak:.4g} m/s and "
                                                     f"{a_peak:.4g} m/s^2, beyond safety.max_speed ({vmax:g} m/s) or "
                                                     f"max_accel ({amax:g} m/s^2); leave at least {need:.4g} s "
                                                     "between them"))


def _label(m: Mission, out: Problems) -> Problems:
    """Name every ``agents[k]…`` problem by the agent's id and every ``edges[k]…`` one by the edge's
    ends (``agent 7.offset``, ``edge 3 → 4.weight``)."""
    return by_id(out, [a.id for a in m.agents], [(e.src, e.dst) for e in m.edges])


def _validate_safety(m: Mission, out: Problems) -> None:
    """The ``[safety]`` section: positive limits, ordered timeouts, a box that is a box."""
    sf = m.safety
    positive = {"max_accel": "m/s^2", "max_speed": "m/s", "max_formation_error": "m", "leader_timeout": "s",
                "neighbour_timeout": "s", "land_after": "s", "land_speed": "m/s", "land_settle": "s", "hold_kp": "1/s^2",
                "hold_kv": "1/s", "cmd_timeout": "s", "cmd_cutoff": "s"}
    for name, unit in positive.items():
        value = getattr(sf, name)
        if not value > 0:
            default = getattr(Safety(), name)
            out.append((f"safety.{name}", f"is {value} {unit}; give a value > 0 (the default is {default!r})"))
    for name in ("leader_timeout", "neighbour_timeout", "cmd_timeout"):
        value = getattr(sf, name)
        if 0 < value < MIN_AGE:
            out.append((f"safety.{name}", f"is {value:g} s, below {MIN_AGE:g} s (no sample arrives that fast, so it "
                                          f"would fire at once); use e.g. {getattr(Safety(), name)!r}"))
    _validate_safety_ceilings(m, out)
    if sf.jump_margin < 0:
        out.append(("safety.jump_margin", f"is {sf.jump_margin} m; use >= 0"))
    if sf.future_window < 0:
        out.append(("safety.future_window", f"is {sf.future_window} ticks; use >= 0"))
    if not sf.gain_cap > 1:
        out.append(("safety.gain_cap", f"is {sf.gain_cap}; the gains start at >= 1, so use a cap > 1 (default 1000)"))
    if sf.cmd_cutoff <= sf.cmd_timeout:
        out.append(("safety.cmd_cutoff", f"is {sf.cmd_cutoff} s, not after cmd_timeout ({sf.cmd_timeout} s); "
                                         "a plant holds first and lands later: make cmd_cutoff > cmd_timeout"))
    if sf.geofence is not None:
        g = sf.geofence
        _check_vec(g.min, m.dim, "safety.geofence.min", out)
        _check_vec(g.max, m.dim, "safety.geofence.max", out)
        if len(g.min) == len(g.max) == m.dim:
            for axis, (lo, hi) in enumerate(zip(g.min, g.max)):
                if not lo < hi:
                    out.append((f"safety.geofence.max[{axis}]", f"is {hi}, not above min[{axis}] = {lo}; "
                                                                "give a box with min < max on every axis"))
            for k, a in enumerate(m.agents):
                if not all(lo <= x <= hi for x, lo, hi in zip(a.p0, g.min, g.max)):
                    out.append((f"agents[{k}].p0", f"is {a.p0}, outside safety.geofence; start every vehicle "
                                                   "inside the fence, or widen it"))
    if sf.avoid is not None:
        av = sf.avoid
        for name in ("radius", "sensing", "gain", "brake"):
            if not getattr(av, name) > 0:
                out.append((f"safety.avoid.{name}", f"is {getattr(av, name)}; give a value > 0"))
        if av.brake > sf.max_accel:
            out.append(("safety.avoid.brake", f"is {av.brake} m/s^2, beyond max_accel ({sf.max_accel} m/s^2); "
                                              "a vehicle cannot brake harder than it may accelerate"))
        if av.sensing <= av.radius:
            out.append(("safety.avoid.sensing", f"is {av.sensing} m, not beyond radius ({av.radius} m); "
                                                "the filter must see a vehicle before it is too close"))


def _validate_safety_ceilings(m: Mission, out: Problems) -> None:
    """The ``[safety]`` values so large that they switch off what they bound, each against its
    ceiling (the constants above say why each): the waits, the speed and acceleration limits, the
    divergence bounds, the jump margin, the future window (a minute of ticks), a descent no faster
    than ``max_speed``, and HOLD gains the control rate can fly (poles within the rate: ``hold_kv``
    <= 2 rate, ``hold_kp`` <= rate^2), and a ground within :data:`MAX_EXTENT`."""
    sf = m.safety
    default = Safety()
    for name in ("leader_timeout", "neighbour_timeout", "cmd_timeout", "cmd_cutoff", "land_after", "land_settle"):
        value = getattr(sf, name)
        if value > MAX_WAIT:
            out.append((f"safety.{name}", f"is {value:g} s, beyond {MAX_WAIT:g} s: a failsafe that waits longer "
                                          f"never acts within a flight; use e.g. {getattr(default, name)!r}"))
    ceilings = (("max_accel", MAX_ACCEL, "m/s^2", "about 10 g, more than any multirotor has"),
                ("max_speed", MAX_SPEED, "m/s", "the speed of sound"),
                ("max_formation_error", MAX_EXTENT, "m", "the largest coordinate a mission may have"),
                ("jump_margin", MAX_EXTENT, "m", "the largest coordinate a mission may have"),
                ("gain_cap", MAX_GAIN_CAP, "", "a gain that saturates every command at once"))
    for name, most, unit, why in ceilings:
        value = getattr(sf, name)
        if value > most:
            out.append((f"safety.{name}", f"is {value:g}{' ' + unit if unit else ''}, beyond {most:g} ({why}), "
                                          f"which bounds nothing; use e.g. {getattr(default, name)!r}"))
    if not MIN_RATE <= m.rate <= MAX_RATE:
        return  # the rate's own problem is reported; nothing more to judge against it
    window = int(m.rate * MAX_WAIT)
    if sf.future_window > window:
        out.append(("safety.future_window", f"is {sf.future_window} ticks, beyond {window} (a minute at {m.rate:g} "
                                            f"Hz): it would take far-future stamps; use e.g. {default.future_window}"))
    if 0 < sf.max_speed < sf.land_speed:
        out.append(("safety.land_speed", f"is {sf.land_speed:g} m/s, faster than safety.max_speed "
                                         f"({sf.max_speed:g} m/s): a descent the supervisor calls implausible; use "
                                         f"e.g. {default.land_speed!r}"))
    if sf.hold_kv > 2 * m.rate:
        out.append(("safety.hold_kv", f"is {sf.hold_kv:g} 1/s, beyond 2 x rate ({2 * m.rate:g} 1/s): a HOLD loop "
                                      "faster than the control rate oscillates or diverges; use e.g. "
                                      f"{default.hold_kv!r}"))
    if sf.hold_kp > m.rate ** 2:
        out.append(("safety.hold_kp", f"is {sf.hold_kp:g} 1/s^2, beyond rate^2 ({m.rate ** 2:g} 1/s^2): a HOLD loop "
                                      "faster than the control rate oscillates or diverges; use e.g. "
                                      f"{default.hold_kp!r}"))
    if abs(sf.ground) > MAX_EXTENT:
        out.append(("safety.ground", f"is {sf.ground:g} m, beyond {MAX_EXTENT:g} m; give a height within 100 km"))


def ground_starts(m: Mission) -> list[str]:
    """What ``tether check`` warns of about the ground (3D; none in 2D, which has no ground): the
    vehicles, leader included, whose ``p0`` height is below ``safety.ground`` (inside it) or on it
    (resting, so the law must lift them before they fly), one line each; empty when none. A warning,
    not an error: a vehicle that takes off from its pad starts on the ground by design."""
    if m.dim != 3:
        return []
    g = m.safety.ground
    out: list[str] = []
    for where, word in (("below", lambda z: z < g), ("on", lambda z: z == g)):
        who = [f"agent {a.id}" for a in m.agents if len(a.p0) == 3 and word(a.p0[2])]
        if len(m.leader.p0) == 3 and word(m.leader.p0[2]):
            who.append(f"the leader ({m.leader.id})")
        if not who:
            continue
        heights = sorted({a.p0[2] for a in m.agents if len(a.p0) == 3 and word(a.p0[2])}
                         | ({m.leader.p0[2]} if len(m.leader.p0) == 3 and word(m.leader.p0[2]) else set()))
        shown = ", ".join(f"{z:g}" for z in heights[:3]) + (", ..." if len(heights) > 3 else "")
        names = ", ".join(who[:8]) + (f" and {len(who) - 8} more" if len(who) > 8 else "")
        if where == "below":
            out.append(f"{names} start{'s' if len(who) == 1 else ''} below the ground (p0 z = {shown} m < "
                       f"safety.ground = {g:g} m), inside it; raise p0[2] to the ground or above, or lower "
                       "safety.ground")
        else:
            out.append(f"{names} start{'s' if len(who) == 1 else ''} on the ground (p0 z = safety.ground = {g:g} "
                       "m): resting until the law lifts them; raise p0[2] if they should start in flight")
    return out


def _validate_physics(m: Mission, out: Problems) -> None:
    """Plants, payload and floor."""
    physical = (PointMassPlant, QuadrotorPlant)
    for k, a in enumerate(m.agents):
        p = a.plant
        where = f"agents[{k}].plant"
        if isinstance(p, DoubleIntegrator):
            continue
        # every vehicle with mass: point mass, quadrotor, Crazyflie
        if m.dim != 3:
            out.append((where, f"is a {p.__struct_config__.tag} in a {m.dim}D mission; these vehicles fly in 3D: "
                               "set `dim = 3` (and 3-vectors), or use `double_integrator`"))
        if not p.mass > 0:
            out.append((f"{where}.mass", f"is {p.mass} kg; give the vehicle's mass > 0, e.g. 0.029"))
        if p.feedforward_mass < 0:
            out.append((f"{where}.feedforward_mass", f"is {p.feedforward_mass} kg; use >= 0 (0: off)"))
        if not isinstance(p, PointMassPlant) and not 0 < p.tilt_max < 90:
            out.append((f"{where}.tilt_max", f"is {p.tilt_max} deg; use an angle in (0, 90), e.g. 20"))
        if isinstance(p, physical) and p.integrator is not None:
            if not p.integrator.gain > 0:
                out.append((f"{where}.integrator.gain", f"is {p.integrator.gain}; use a gain > 0 [1/s], e.g. 2.0, "
                                                        "or remove the integrator"))
            if not p.integrator.limit > 0:
                out.append((f"{where}.integrator.limit", f"is {p.integrator.limit}; use a bound > 0 [m/s^2], e.g. 6.0"))
        if isinstance(p, CrazyfliePlant):
            if not p.uri.startswith(("radio://", "usb://", "udp://")):
                out.append((f"{where}.uri", f"is {p.uri!r}; give a cflib URI: radio://0/80/2M/E7E7E7E701, usb://0 "
                                            "or udp://127.0.0.1:19850 (the software Crazyflie)"))
            elif (bad := _uri_problem(p.uri)) is not None:
                out.append((f"{where}.uri", f"is {p.uri!r}: {bad}"))
            for name in ("takeoff_height", "takeoff_time", "land_time", "connect_timeout"):
                if not getattr(p, name) > 0:
                    out.append((f"{where}.{name}", f"is {getattr(p, name)}; use a value > 0"))
    if m.payload is not None:
        pl = m.payload
        if m.dim != 3:
            out.append(("payload", "needs a 3D mission (gravity acts along z); set `dim = 3`"))
        for k, a in enumerate(m.agents):
            if not isinstance(a.plant, physical):
                out.append((f"agents[{k}].plant", f"is {a.plant.__struct_config__.tag} but a payload hangs from vehicles "
                                                   "with mass; use `point_mass` or `quadrotor`"))
        if not pl.mass > 0:
            out.append(("payload.mass", f"is {pl.mass} kg; give the payload's mass > 0, e.g. 0.015"))
        for name in ("length", "stiffness"):
            if not getattr(pl.cable, name) > 0:
                out.append((f"payload.cable.{name}", f"is {getattr(pl.cable, name)}; use a value > 0"))
        if pl.cable.damping < 0:
            out.append(("payload.cable.damping", f"is {pl.cable.damping}; use >= 0 [N s/m]"))
        if m.dim == 3:
            _check_vec(pl.p0, 3, "payload.p0", out)
        if not pl.substep > 0 or (m.rate > 0 and not _whole_periods(1.0 / m.rate, 1.0 / pl.substep)):
            out.append(("payload.substep", f"is {pl.substep} s; use a whole fraction of the control period "
                                           f"{1.0 / m.rate if m.rate > 0 else float('nan'):g} s, e.g. 0.001"))
        if pl.p0 is not None and m.floor is not None and len(pl.p0) == 3 and pl.p0[2] < m.floor:
            out.append(("payload.p0", f"is below the floor ({m.floor} m); raise its z to >= {m.floor}"))
    if m.floor is not None and m.dim != 3:
        out.append(("floor", "needs a 3D mission; remove it or set `dim = 3`"))


_URI_EXAMPLE = "radio://0/80/2M/E7E7E7E701, usb://0 or udp://127.0.0.1:19850"


def _uri_problem(uri: str) -> str | None:
    """What is wrong with a cflib URI past its scheme (``"<what>; <fix>"``), or None."""
    scheme, _, rest = uri.partition("://")
    if scheme == "udp":
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit():
            return f"a udp URI is udp://HOST:PORT; write e.g. udp://127.0.0.1:19850"
        if not 1 <= int(port) <= 65535:
            return f"port {port} is not a UDP port; use a port in 1..65535, e.g. udp://{host}:19850"
        return None
    if scheme == "usb":
        return None if rest.isdigit() else "a usb URI is usb://N (the dongle's index); write e.g. usb://0"
    parts = rest.split("/")  # radio://DONGLE/CHANNEL[/RATE[/ADDRESS]]
    if not 2 <= len(parts) <= 4 or not parts[0].isdigit() or not parts[1].isdigit():
        return "a radio URI is radio://DONGLE/CHANNEL/RATE/ADDRESS; write e.g. radio://0/80/2M/E7E7E7E701"
    if not 0 <= int(parts[1]) <= 125:
        return f"channel {parts[1]} is not a Crazyradio channel; use 0..125, e.g. radio://0/80/2M/E7E7E7E701"
    if len(parts) > 2 and parts[2] not in ("250K", "1M", "2M"):
        return f"data rate {parts[2]!r} is not one of 250K, 1M or 2M; write e.g. radio://0/80/2M/E7E7E7E701"
    if len(parts) > 3 and (len(parts[3]) != 10 or any(c not in "0123456789abcdefABCDEF" for c in parts[3])):
        return f"address {parts[3]!r} is not 10 hex digits; write e.g. radio://0/80/2M/E7E7E7E701"
    return None


def _validate_disturbance(dist: Disturbance, d: int, rate: float, path: str, out: Problems) -> None:
    if isinstance(dist, DisturbanceSum):
        if not dist.terms:
            out.append((f"{path}.terms", "is empty; give at least one term (a [[...disturbance.terms]] table "
                                         "with its own kind), or use kind = \"none\""))
        for j, term in enumerate(dist.terms):
            _validate_disturbance(term, d, rate, f"{path}.terms[{j}]", out)
        return
    if isinstance(dist, Sinusoid):
        for name in ("amplitude", "omega", "phase"):
            _check_vec(getattr(dist, name), d, f"{path}.{name}", out)
    elif isinstance(dist, Constant):
        _check_vec(dist.value, d, f"{path}.value", out)
    elif isinstance(dist, BoundedRandom):
        _check_per_axis(dist.bound, d, f"{path}.bound", out)
        if any(b < 0 for b in per_axis(dist.bound, d)):
            out.append((f"{path}.bound", f"is {dist.bound} but a bound is a magnitude; give values >= 0"))
        if dist.hold <= 0:
            out.append((f"{path}.hold", f"is {dist.hold} s; set a redraw period > 0 s, a whole number of "
                                        "control periods"))
        elif rate > 0 and not _whole_periods(dist.hold, rate):
            out.append((f"{path}.hold", f"is {dist.hold} s, not a whole number of control periods at {rate} Hz; "
                                        f"make hold * rate an integer, e.g. "
                                        f"`hold = {_nearest_periods(dist.hold, rate)!r}`"))


def _validate_profile(m: Mission, out: Problems) -> None:
    prof, d, path = m.leader.profile, m.dim, "leader.profile"
    v0 = m.leader.v0
    if isinstance(prof, ExpAccel):
        _check_vec(prof.a0, d, f"{path}.a0", out)
        if prof.decay < 0:
            out.append((f"{path}.decay", f"is {prof.decay} 1/s; set a decay rate >= 0 (0 keeps a0 constant)"))
    elif isinstance(prof, VelocitySchedule):
        segs = prof.segments
        if not segs:
            out.append((f"{path}.segments", "is empty; give at least one segment, the first at t = 0"))
        else:
            if segs[0].t != 0:
                out.append((f"{path}.segments[0].t", f"is {segs[0].t} s; set it to 0 (the first segment gives "
                                                     "the velocity from the start)"))
            if v0 is not None and len(v0) == d and len(segs[0].v) == d and list(v0) != list(segs[0].v):
                out.append(("leader.v0", f"is {v0} but the velocity schedule starts at segments[0].v = "
                                         f"{segs[0].v}; remove leader.v0 (the schedule sets the velocity) "
                                         "or make them equal"))
        for k, seg in enumerate(segs):
            _check_vec(seg.v, d, f"{path}.segments[{k}].v", out)
            # the first segment is the starting velocity and has no ramp: the second may start its
            # ramp at once ("hold 2 s, then ramp for 3 s" is segments t = 0 and t = 2, ramp = 3)
            prev_end = segs[k - 1].t + (prof.ramp if k > 1 else 0.0)
            if k and seg.t < prev_end:
                if k == 1:
                    out.append((f"{path}.segments[1].t", f"is {seg.t} s, earlier than segments[0].t ({segs[0].t} s); "
                                                         "sort the segments by t"))
                else:
                    out.append((f"{path}.segments[{k}].t", f"is {seg.t} s, earlier than the previous segment's "
                                                           f"t + ramp ({prev_end} s); sort the segments by t "
                                                           "or shorten the ramp"))
        if prof.ramp < 0:
            out.append((f"{path}.ramp", f"is {prof.ramp} s; set a ramp >= 0 (0 is a step)"))
    elif isinstance(prof, Waypoints):
        pts = prof.points
        if len(pts) < 2:
            out.append((f"{path}.points", f"has {len(pts)} waypoint(s); give at least two, the first at t = 0 "
                                          "and leader.p0"))
        else:
            if pts[0].t != 0:
                out.append((f"{path}.points[0].t", f"is {pts[0].t} s; set it to 0 (the leader starts at its "
                                                   "first waypoint)"))
            if len(pts[0].p) == d and len(m.leader.p0) == d and list(pts[0].p) != list(m.leader.p0):
                out.append((f"{path}.points[0].p", f"is {pts[0].p} but leader.p0 is {m.leader.p0}; make them "
                                                   "equal (the leader starts at its first waypoint)"))
        if v0 is not None and any(x != 0 for x in v0):
            out.append(("leader.v0", f"is {v0} but a waypoints profile starts at rest; remove leader.v0 "
                                     "or set it to zeros"))
        for k, pt in enumerate(pts):
            _check_vec(pt.p, d, f"{path}.points[{k}].p", out)
            if k and pt.t <= pts[k - 1].t:
                out.append((f"{path}.points[{k}].t", f"is {pt.t} s, not later than points[{k - 1}].t = "
                                                     f"{pts[k - 1].t} s; give strictly increasing times"))


def unreachable_agents(m: Mission) -> list[int]:
    """Agents with no directed path from the leader (Assumption 1 holds iff this is empty)."""
    out_edges: dict[int, list[int]] = {}
    for e in m.edges:
        out_edges.setdefault(e.src, []).append(e.dst)
    reached = {m.leader.id}
    frontier = [m.leader.id]
    while frontier:
        node = frontier.pop()
        for nxt in out_edges.get(node, []):
            if nxt not in reached:
                reached.add(nxt)
                frontier.append(nxt)
    return [a.id for a in m.agents if a.id not in reached]
