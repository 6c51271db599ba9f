"""Mission files: a strict, versioned TOML schema and the checks a control engineer expects.

A mission file is decoded into :class:`Mission` with msgspec (unknown fields are errors), then
:func:`validate` checks what a type cannot say: the graph (Assumption 1, self-loops, weights, ids),
dimensions, the law's parameters, and finiteness. Every error names the field by its path in the
file and says how to fix it. :func:`load` does both and returns a :class:`Mission`; it raises
:class:`MissionError` listing every problem found, not only the first.

The file format, field by field, is documented in ``docs/mission.md``.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Literal

import msgspec

SCHEMA_VERSION = 1
"""The mission-file version this release reads."""

Vector = list[float]
"""A vector of ``dim`` components (2 or 3), in the world frame."""

PerAxis = float | list[float]
"""One value for every axis, or a list of ``dim`` values (x, y[, z])."""


class _Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Base of every mission struct: unknown fields are errors, instances are immutable."""


class _Kind(_Strict, tag_field="kind"):
    """Base of the members of a tagged union, told apart by their ``kind`` field."""


# --------------------------------------------------------------------------- leader profiles
class ExpAccel(_Kind, tag="exp_accel"):
    """Leader acceleration ``a_ref(t) = a0 * exp(-decay * t)`` per axis (Section 4: a0 = [1, 0], decay = 0.1)."""

    a0: Vector
    """Initial acceleration [m/s^2; world frame]."""
    decay: float
    """Decay rate [1/s]; 0 gives a constant acceleration."""


class VelocitySegment(_Strict):
    """From ``t`` on, the leader's velocity is ``v`` (reached after the profile's ``ramp``)."""

    t: float
    """Segment start [s]."""
    v: Vector
    """Velocity [m/s; world frame]."""


class VelocitySchedule(_Kind, tag="velocity_schedule"):
    """Piecewise-constant velocity (Eq. 31, Eq. 32), optionally with linear ramps between segments."""

    segments: list[VelocitySegment]
    ramp: float = 0.0
    """Duration of each velocity change [s]; 0 is a step (the acceleration is then an impulse and is
    reported as 0)."""


class Waypoint(_Strict):
    """The leader is at ``p`` at time ``t`` with zero velocity and acceleration."""

    t: float
    """Time [s]."""
    p: Vector
    """Position [m; world frame]."""


class Waypoints(_Kind, tag="waypoints"):
    """Minimum-jerk (quintic) segments between timed waypoints; the first waypoint's time must be 0
    and its position the leader's ``p0``. After the last waypoint the leader holds position."""

    points: list[Waypoint]


class Hold(_Kind, tag="hold"):
    """The leader keeps its initial velocity forever (zero acceleration)."""


Profile = ExpAccel | VelocitySchedule | Waypoints | Hold


class Leader(_Strict):
    """The virtual leader (node N+1 in the paper): an exo-system that hears nobody."""

    id: int
    p0: Vector
    """Initial position [m; world frame]."""
    v0: Vector | None = None
    """Initial velocity [m/s; world frame]; zeros when omitted (ignored by ``velocity_schedule``
    and ``waypoints``, which define it)."""
    profile: Profile = Hold()


# --------------------------------------------------------------------------- disturbances
class NoDisturbance(_Kind, tag="none"):
    """``d = 0``."""


class Sinusoid(_Kind, tag="sinusoid"):
    """``d_k(t) = amplitude_k * sin(omega_k * t + phase_k)`` per axis k (Section 4's disturbances;
    a cosine is ``phase = pi/2``)."""

    amplitude: Vector
    """Amplitude [m/s^2]."""
    omega: Vector
    """Angular frequency [rad/s]."""
    phase: Vector | None = None
    """Phase [rad]; zeros when omitted."""


class Constant(_Kind, tag="constant"):
    """``d = value`` for all time."""

    value: Vector
    """[m/s^2; world frame]."""


class BoundedRandom(_Kind, tag="bounded_random"):
    """Piecewise-constant random disturbance, uniform in the box ``|d_k| <= bound_k``, redrawn every
    ``hold`` seconds from a generator seeded by the mission seed and the agent id."""

    bound: PerAxis
    """Per-axis bound [m/s^2]."""
    hold: float
    """Time between redraws [s]."""


Disturbance = NoDisturbance | Sinusoid | Constant | BoundedRandom


# --------------------------------------------------------------------------- plants
class DoubleIntegrator(_Kind, tag="double_integrator"):
    """``p' = v, v' = u + d``, discretised exactly under a zero-order hold on ``u``."""


PlantSpec = DoubleIntegrator


# --------------------------------------------------------------------------- agents, graph, law
class Agent(_Strict):
    id: int
    p0: Vector
    """Initial position [m; world frame]."""
    offset: Vector
    """Formation offset ``h_i`` relative to the leader [m; world frame]."""
    v0: Vector | None = None
    """Initial velocity [m/s; world frame]; zeros when omitted."""
    plant: PlantSpec = DoubleIntegrator()
    disturbance: Disturbance = NoDisturbance()


class Edge(_Strict):
    """``src -> dst``: agent ``dst`` hears ``src`` with weight ``a_{dst,src} > 0``."""

    src: int = msgspec.field(name="from")
    dst: int = msgspec.field(name="to")
    weight: float = 1.0


class Law(_Strict):
    """Eq. 17 (``kind = "sigma"``) or the benchmark Eq. 30 (``kind = "benchmark"``, no ``sigma``)."""

    kind: Literal["sigma", "benchmark"]
    kp0: PerAxis
    """Initial position gains ``Kp(0)`` per axis [1/s^2 after the 1/kappa scaling]."""
    kv0: PerAxis
    """Initial velocity gains ``Kv(0)`` per axis [1/s]."""
    gamma_p: float
    """Adaptation rate ``Gamma_p`` of Kp."""
    gamma_v: float
    """Adaptation rate ``Gamma_v`` of Kv."""
    sigma: float | None = None
    """Leakage ``sigma`` of the sigma-modification [1/s]; required for ``sigma``, absent for ``benchmark``."""


class Mission(_Strict):
    version: int
    name: str
    dim: Literal[2, 3]
    """Spatial dimension of every vector in the file."""
    rate: float
    """Control rate [Hz]."""
    duration: float
    """Run length [s]."""
    law: Law
    leader: Leader
    agents: list[Agent]
    edges: list[Edge]
    seed: int = 0
    """Seed of every random part of the run (random disturbances; later, network models)."""
    description: str = ""
    assumed: list[str] = []
    """What the mission assumes that its source does not state (e.g. topology read off a figure)."""

    @property
    def n(self) -> int:
        """Number of agents N (the leader excluded)."""
        return len(self.agents)

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return 1.0 / self.rate

    @property
    def steps(self) -> int:
        """Number of control periods in the run."""
        return int(round(self.duration * self.rate))

    @property
    def agent_ids(self) -> list[int]:
        return [a.id for a in self.agents]

    def index_of(self, node_id: int) -> int:
        """Row of a node in the simulator's arrays: agents ``0..N-1`` in file order, the leader ``N``."""
        if node_id == self.leader.id:
            return self.n
        return self.agent_ids.index(node_id)

    def agent(self, agent_id: int) -> Agent:
        for a in self.agents:
            if a.id == agent_id:
                return a
        raise KeyError(f"no agent with id {agent_id}")


# --------------------------------------------------------------------------- errors
class MissionError(ValueError):
    """A mission file is not valid. ``problems`` holds one ``(field, message)`` pair per problem."""

    def __init__(self, source: str, problems: list[tuple[str, str]]):
        self.source = source
        self.problems = problems
        lines = [f"{source}: {len(problems)} problem(s)"]
        lines += [f"  {field}: {msg}" for field, msg in problems]
        super().__init__("\n".join(lines))


# --------------------------------------------------------------------------- decoding
def loads(text: str | bytes, source: str = "<mission>") -> Mission:
    """Decode and validate a mission from TOML text. Raises :class:`MissionError`."""
    if isinstance(text, str):
        text = text.encode()
    try:
        raw = tomllib.loads(text.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MissionError(source, [("<file>", f"not valid TOML ({exc}); fix the syntax")]) from None
    version = raw.get("version") if isinstance(raw, dict) else None
    if version != SCHEMA_VERSION:
        raise MissionError(
            source,
            [("version", f"is {version!r}; this release reads version = {SCHEMA_VERSION}: "
                         f"set `version = {SCHEMA_VERSION}` and check the fields against docs/mission.md")],
        )
    try:
        mission = msgspec.convert(raw, type=Mission)
    except msgspec.ValidationError as exc:
        raise MissionError(source, [_field_of(str(exc))]) from None
    problems = validate(mission)
    if problems:
        raise MissionError(source, problems)
    return mission


def load(path: str | Path) -> Mission:
    """Read, decode and validate a mission file. Raises :class:`MissionError` (also for a missing file)."""
    path = Path(path)
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise MissionError(str(path), [("<file>", f"cannot be read ({exc.strerror}); check the path")]) from None
    return loads(text, source=str(path))


def _field_of(msg: str) -> tuple[str, str]:
    """Turn msgspec's ``"... - at `$.agents[0].p0`"`` into ``("agents[0].p0", fix)``."""
    where = "<root>"
    if " - at `$" in msg:
        msg, _, at = msg.partition(" - at `$")
        where = at.rstrip("`").lstrip(".") or "<root>"
    fix = "see docs/mission.md for the field's type"
    if msg.startswith("Object contains unknown field"):
        name = msg.split("`")[1]
        where = f"{where}.{name}" if where != "<root>" else name
        fix = "remove it or fix its spelling (unknown fields are errors)"
        msg = "unknown field"
    elif msg.startswith("Object missing required field"):
        name = msg.split("`")[1]
        where = f"{where}.{name}" if where != "<root>" else name
        msg = "is required"
        fix = "add it"
    elif "Invalid value" in msg and where.endswith("kind"):
        fix = "use one of the kinds listed in docs/mission.md"
    elif msg.startswith("Expected `object`, got") and where != "<root>":
        fix = "write a table here"
    return where, f"{msg.lower() if msg[:1].isupper() and msg != 'is required' else msg}; {fix}"


# --------------------------------------------------------------------------- validation
def _finite_tree(obj: object, path: str, out: list[tuple[str, str]]) -> None:
    """Report every NaN/Inf number anywhere in the mission."""
    if isinstance(obj, float):
        if not math.isfinite(obj):
            out.append((path, f"is {obj}; every number must be finite"))
    elif isinstance(obj, list):
        for k, item in enumerate(obj):
            _finite_tree(item, f"{path}[{k}]", out)
    elif isinstance(obj, msgspec.Struct):
        for name in obj.__struct_fields__:
            enc = _encoded_name(type(obj), name)
            _finite_tree(getattr(obj, name), f"{path}.{enc}" if path else enc, out)


def _encoded_name(cls: type, name: str) -> str:
    info = msgspec.structs.fields(cls)
    for f in info:
        if f.name == name:
            return f.encode_name
    return name


def _check_vec(v: list[float] | None, dim: int, path: str, out: list[tuple[str, str]]) -> None:
    if v is not None and len(v) != dim:
        out.append((path, f"has {len(v)} components but the mission has dim = {dim}; give {dim}"))


def _check_per_axis(v: PerAxis, dim: int, path: str, out: list[tuple[str, str]]) -> None:
    if isinstance(v, list):
        _check_vec(v, dim, path, out)


def per_axis(v: PerAxis, dim: int) -> list[float]:
    """Expand a :data:`PerAxis` value to ``dim`` components."""
    return [float(v)] * dim if not isinstance(v, list) else [float(x) for x in v]


def validate(m: Mission) -> list[tuple[str, str]]:
    """Every semantic problem of a decoded mission, as ``(field, message-with-fix)`` pairs."""
    out: list[tuple[str, str]] = []
    _finite_tree(m, "", out)
    if out:
        return out  # later checks compare numbers; NaN would only add confusing follow-ups
    d = m.dim

    if m.rate <= 0:
        out.append(("rate", f"is {m.rate} Hz; the control rate must be > 0 (e.g. 100)"))
    if m.duration <= 0:
        out.append(("duration", f"is {m.duration} s; the duration must be > 0"))
    elif m.rate > 0 and abs(m.duration * m.rate - round(m.duration * m.rate)) > 1e-6:
        out.append(("duration", f"{m.duration} s is not a whole number of control periods at {m.rate} Hz; "
                                "make duration * rate an integer"))

    # ids
    if not m.agents:
        out.append(("agents", "is empty; declare at least one [[agents]] table"))
    seen: dict[int, int] = {}
    for k, a in enumerate(m.agents):
        if a.id <= 0:
            out.append((f"agents[{k}].id", f"is {a.id}; ids must be positive integers"))
        if a.id in seen:
            out.append((f"agents[{k}].id", f"duplicates agents[{seen[a.id]}].id = {a.id}; give every agent its own id"))
        seen.setdefault(a.id, k)
        if a.id == m.leader.id:
            out.append((f"agents[{k}].id", f"{a.id} is the leader's id; agents and the leader need distinct ids"))
        _check_vec(a.p0, d, f"agents[{k}].p0", out)
        _check_vec(a.v0, d, f"agents[{k}].v0", out)
        _check_vec(a.offset, d, f"agents[{k}].offset", out)
        _validate_disturbance(a.disturbance, d, m.rate, f"agents[{k}].disturbance", out)
    if m.leader.id <= 0:
        out.append(("leader.id", f"is {m.leader.id}; ids must be positive integers"))
    _check_vec(m.leader.p0, d, "leader.p0", out)
    _check_vec(m.leader.v0, d, "leader.v0", out)
    _validate_profile(m, out)

    # edges
    nodes = set(seen) | {m.leader.id}
    pairs: dict[tuple[int, int], int] = {}
    for k, e in enumerate(m.edges):
        where = f"edges[{k}]"
        if e.src not in nodes:
            out.append((f"{where}.from", f"{e.src} is not an agent or the leader; use one of {sorted(nodes)}"))
        if e.dst not in nodes:
            out.append((f"{where}.to", f"{e.dst} is not an agent or the leader; use one of {sorted(nodes)}"))
        if e.dst == m.leader.id:
            out.append((f"{where}.to", f"{e.dst} is the virtual leader, which hears nobody (Eq. 6); "
                                       "remove the edge or reverse it"))
        if e.src == e.dst:
            out.append((where, f"is a self-loop on {e.src}; a_ii = 0 by definition: remove it"))
        if e.weight <= 0:
            out.append((f"{where}.weight", f"is {e.weight}; a_ij > 0 for an edge (omit the edge for a_ij = 0)"))
        key = (e.src, e.dst)
        if key in pairs:
            out.append((where, f"duplicates edges[{pairs[key]}] ({e.src} -> {e.dst}); merge them into one weight"))
        pairs.setdefault(key, k)

    # law
    law = m.law
    _check_per_axis(law.kp0, d, "law.kp0", out)
    _check_per_axis(law.kv0, d, "law.kv0", out)
    floor = 1.0 if law.kind == "sigma" else 0.0
    why = ("Theorem 1 needs K(0) >= 1 for the sigma law" if law.kind == "sigma"
           else "Eq. 30 needs K(0) >= 0")
    for name, val in (("kp0", law.kp0), ("kv0", law.kv0)):
        for k, x in enumerate(per_axis(val, d)):
            if x < floor:
                field = f"law.{name}" + (f"[{k}]" if isinstance(val, list) else "")
                out.append((field, f"is {x}; {why}: raise it to >= {floor:g}"))
    for name in ("gamma_p", "gamma_v"):
        if getattr(law, name) <= 0:
            out.append((f"law.{name}", f"is {getattr(law, name)}; the adaptation rate must be > 0"))
    if law.kind == "sigma":
        if law.sigma is None:
            out.append(("law.sigma", "is required for the sigma law; add e.g. `sigma = 1.0`"))
        elif law.sigma <= 0:
            out.append(("law.sigma", f"is {law.sigma}; sigma must be > 0 (use kind = \"benchmark\" for no leakage)"))
    elif law.sigma is not None:
        out.append(("law.sigma", "is set but the benchmark law (Eq. 30) has no sigma; remove it or use kind = \"sigma\""))

    # Assumption 1 only makes sense on a graph whose ids are right
    if not any(msg for f, msg in out if f.startswith("edges") or f.startswith("agents")):
        unreachable = unreachable_agents(m)
        if unreachable:
            out.append(("edges", f"break Assumption 1: the leader ({m.leader.id}) has no directed path to "
                                 f"agent(s) {unreachable}; add edges so that each hears the leader or an agent "
                                 "the leader reaches"))
    return out


def _validate_disturbance(dist: Disturbance, d: int, rate: float, path: str, out: list[tuple[str, str]]) -> None:
    if isinstance(dist, Sinusoid):
        for name in ("amplitude", "omega", "phase"):
            _check_vec(getattr(dist, name), d, f"{path}.{name}", out)
    elif isinstance(dist, Constant):
        _check_vec(dist.value, d, f"{path}.value", out)
    elif isinstance(dist, BoundedRandom):
        _check_per_axis(dist.bound, d, f"{path}.bound", out)
        if any(b < 0 for b in per_axis(dist.bound, d)):
            out.append((f"{path}.bound", "has a negative component; bounds are magnitudes >= 0"))
        if dist.hold <= 0:
            out.append((f"{path}.hold", f"is {dist.hold} s; the redraw period must be > 0"))
        elif rate > 0 and abs(dist.hold * rate - round(dist.hold * rate)) > 1e-6:
            out.append((f"{path}.hold", f"{dist.hold} s is not a whole number of control periods at {rate} Hz; "
                                        "make hold * rate an integer"))


def _validate_profile(m: Mission, out: list[tuple[str, str]]) -> None:
    prof, d, path = m.leader.profile, m.dim, "leader.profile"
    if isinstance(prof, ExpAccel):
        _check_vec(prof.a0, d, f"{path}.a0", out)
        if prof.decay < 0:
            out.append((f"{path}.decay", f"is {prof.decay}; the decay rate must be >= 0"))
    elif isinstance(prof, VelocitySchedule):
        if not prof.segments:
            out.append((f"{path}.segments", "is empty; give at least one segment starting at t = 0"))
        elif prof.segments[0].t != 0:
            out.append((f"{path}.segments[0].t", f"is {prof.segments[0].t}; the first segment must start at t = 0"))
        for k, seg in enumerate(prof.segments):
            _check_vec(seg.v, d, f"{path}.segments[{k}].v", out)
            if k and seg.t < prof.segments[k - 1].t + prof.ramp:
                out.append((f"{path}.segments[{k}].t", "must come at least `ramp` after the previous segment's t; "
                                                        "sort the segments or shorten the ramp"))
        if prof.ramp < 0:
            out.append((f"{path}.ramp", f"is {prof.ramp}; the ramp duration must be >= 0"))
    elif isinstance(prof, Waypoints):
        pts = prof.points
        if len(pts) < 2:
            out.append((f"{path}.points", "needs at least two waypoints"))
        else:
            if pts[0].t != 0:
                out.append((f"{path}.points[0].t", f"is {pts[0].t}; the first waypoint must be at t = 0"))
            if len(pts[0].p) == d and len(m.leader.p0) == d and list(pts[0].p) != list(m.leader.p0):
                out.append((f"{path}.points[0].p", "must equal leader.p0 (the leader starts at its first waypoint)"))
        for k, pt in enumerate(pts):
            _check_vec(pt.p, d, f"{path}.points[{k}].p", out)
            if k and pt.t <= pts[k - 1].t:
                out.append((f"{path}.points[{k}].t", "must be later than the previous waypoint's t"))


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
