"""The checks a control engineer expects of a mission, beyond what its types say. Pure.

:func:`validate` takes a decoded :class:`~tether.mission.Mission` and returns every problem it finds
as ``(field path, "<what is wrong>; <how to fix it>")`` pairs: non-finite numbers, rates and
durations, ids, dimensions, the leader's profile and the disturbances, the edges (self-loops,
weights, duplicates, edges into the leader), the law's parameters (Theorem 1's ``K(0) >= 1`` and
``sigma > 0``), the vehicles and the payload, the network section, the ``[safety]`` section, and
Assumption 1 (:func:`unreachable_agents`: every agent has a directed path from the leader).
:func:`tether.mission.loads` runs it on every mission it decodes.
"""

from __future__ import annotations

import math

import msgspec
import msgspec.structs

from tether.mission import (
    BoundedRandom,
    Constant,
    CrazyfliePlant,
    Disturbance,
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
    per_axis,
)
from tether.netprofile import validate_network
from tether.schema import Problems

__all__ = ["unreachable_agents", "validate"]


def _finite_tree(obj: object, path: str, out: Problems) -> None:
    """Report every NaN/Inf number anywhere in the mission."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            out.append((path, f"is {obj}; write a finite number (NaN and infinity are not allowed)"))
    elif isinstance(obj, list):
        for k, item in enumerate(obj):
            _finite_tree(item, f"{path}[{k}]", out)
    elif isinstance(obj, msgspec.Struct):
        for name in obj.__struct_fields__:
            enc = _encoded_name(type(obj), name)
            _finite_tree(getattr(obj, name), f"{path}.{enc}" if path else enc, out)


def _encoded_name(cls: type, name: str) -> str:
    """The name a struct field has in the file (``Edge.src`` is ``from``)."""
    for f in msgspec.structs.fields(cls):
        if f.name == name:
            return f.encode_name
    return name


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
        return out
    d = m.dim

    if m.rate <= 0:
        out.append(("rate", f"is {m.rate} Hz; set a control rate > 0, e.g. `rate = 100.0`"))
    if m.duration <= 0:
        out.append(("duration", f"is {m.duration} s; set a duration > 0"))
    elif m.rate > 0 and not _whole_periods(m.duration, m.rate):
        out.append(("duration", f"is {m.duration} s, not a whole number of control periods at {m.rate} Hz; "
                                f"make duration * rate an integer, e.g. "
                                f"`duration = {_nearest_periods(m.duration, m.rate)!r}`"))
    if m.seed < 0:
        out.append(("seed", f"is {m.seed}; use a seed >= 0 (random generators take non-negative seeds)"))

    # ids
    if not m.agents:
        out.append(("agents", "is empty; declare at least one [[agents]] table"))
    seen: dict[int, int] = {}
    for k, a in enumerate(m.agents):
        if a.id <= 0:
            out.append((f"agents[{k}].id", f"is {a.id}; use a positive integer id"))
        if a.id in seen:
            out.append((f"agents[{k}].id", f"is {a.id}, the id of agents[{seen[a.id]}]; give every agent its own id"))
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
    _check_vec(m.leader.p0, d, "leader.p0", out)
    _check_vec(m.leader.v0, d, "leader.v0", out)
    _validate_profile(m, out)

    # edges
    nodes = sorted(set(seen) | {m.leader.id})
    pairs: dict[tuple[int, int], int] = {}
    for k, e in enumerate(m.edges):
        where = f"edges[{k}]"
        if e.src not in nodes:
            out.append((f"{where}.from", f"is {e.src}, which is neither an agent nor the leader; "
                                         f"use one of the ids {nodes}"))
        if e.dst not in nodes:
            out.append((f"{where}.to", f"is {e.dst}, which is neither an agent nor the leader; "
                                       f"use one of the ids {nodes}"))
        if e.dst == m.leader.id and e.src != e.dst:
            out.append((f"{where}.to", f"is {e.dst}, the virtual leader, which hears nobody (Eq. 6); "
                                       f"remove the edge or reverse it (`from = {e.dst}, to = {e.src}`)"))
        if e.src == e.dst:
            out.append((where, f"is a self-loop on {e.src} (a_ii = 0 by definition); remove it"))
        if e.weight <= 0:
            out.append((f"{where}.weight", f"is {e.weight} but an edge has a_ij > 0; give a positive weight, "
                                           "or remove the edge for a_ij = 0"))
        key = (e.src, e.dst)
        if key in pairs:
            out.append((where, f"repeats edges[{pairs[key]}] ({e.src} -> {e.dst}); merge them into one edge "
                               "with one weight"))
        pairs.setdefault(key, k)

    # law
    law = m.law
    _check_per_axis(law.kp0, d, "law.kp0", out)
    _check_per_axis(law.kv0, d, "law.kv0", out)
    floor = 1.0 if law.kind == "sigma" else 0.0
    why = ("Theorem 1 needs K(0) >= 1 for the sigma law" if law.kind == "sigma"
           else "Eq. 30 needs K(0) >= 0")
    for name, val in (("kp0", law.kp0), ("kv0", law.kv0)):
        values = val if isinstance(val, list) else [val]
        for k, x in enumerate(values):
            if x < floor:
                field = f"law.{name}" + (f"[{k}]" if isinstance(val, list) else "")
                out.append((field, f"is {x}, below {floor:g} ({why}); raise it to >= {floor:g}"))
    for name in ("gamma_p", "gamma_v"):
        value = getattr(law, name)
        if value <= 0:
            out.append((f"law.{name}", f"is {value}; set an adaptation rate > 0, e.g. `{name} = 0.05`"))
    if law.kind == "sigma":
        if law.sigma is None:
            out.append(("law.sigma", "is missing but the sigma law (Eq. 17) needs it; add e.g. `sigma = 1.0`, "
                                     "or use kind = \"benchmark\""))
        elif law.sigma <= 0:
            out.append(("law.sigma", f"is {law.sigma} but Theorem 1 needs sigma > 0; set e.g. `sigma = 1.0`, "
                                     "or use kind = \"benchmark\" for a law without leakage"))
    elif law.sigma is not None:
        out.append(("law.sigma", "is set but the benchmark law (Eq. 30) has no sigma; remove it, "
                                 "or use kind = \"sigma\""))

    _validate_physics(m, out)
    if m.links.max_age <= 0:
        out.append(("links.max_age", f"is {m.links.max_age} s; the oldest usable sample age must be > 0 (e.g. 0.5)"))
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
    return out


def _validate_safety(m: Mission, out: Problems) -> None:
    """The ``[safety]`` section: positive limits, ordered timeouts, a box that is a box."""
    sf = m.safety
    positive = {"max_accel": "m/s^2", "max_speed": "m/s", "max_formation_error": "m", "leader_timeout": "s",
                "neighbour_timeout": "s", "land_after": "s", "land_speed": "m/s", "hold_kp": "1/s^2",
                "hold_kv": "1/s", "cmd_timeout": "s", "cmd_cutoff": "s"}
    for name, unit in positive.items():
        value = getattr(sf, name)
        if not value > 0:
            default = getattr(Safety(), name)
            out.append((f"safety.{name}", f"is {value} {unit}; give a value > 0 (the default is {default!r})"))
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


def _validate_disturbance(dist: Disturbance, d: int, rate: float, path: str, out: Problems) -> None:
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
            if k and seg.t < segs[k - 1].t + prof.ramp:
                out.append((f"{path}.segments[{k}].t", f"is {seg.t} s, earlier than the previous segment's t + ramp "
                                                       f"({segs[k - 1].t + prof.ramp} s); sort the segments by t "
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
