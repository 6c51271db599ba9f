"""Mission files: a strict, versioned TOML schema and the checks a control engineer expects.

A mission file is decoded into :class:`Mission` with msgspec (unknown fields are errors), then
:func:`validate` checks what a type cannot say: the graph (Assumption 1, self-loops, weights, ids),
dimensions, the law's parameters, and finiteness. Every error names the field by its path in the
file (``agents[2].offset``) and says how to fix it, as ``"<what is wrong>; <how to fix it>"``.
:func:`load` does both and returns a :class:`Mission`; it raises :class:`MissionError` listing every
problem found, not only the first (a type error stops decoding, so it is reported alone).

The file format, field by field, is documented in ``docs/mission.md``.
"""

from __future__ import annotations

import difflib
import json
import math
import re
import tomllib
from pathlib import Path
from typing import Literal

import msgspec
import msgspec.inspect
import msgspec.structs

from tether.netprofile import Network, validate_network

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
    """Initial velocity [m/s; world frame]; zeros when omitted. ``velocity_schedule`` and
    ``waypoints`` define it themselves: when given with them it must agree (``segments[0].v``;
    zeros)."""
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


class ThrustIntegrator(_Strict):
    """An inner integral of the acceleration error ``u - p''`` (vertical by default) added to the
    command (the integral of the Crazyflie's own velocity PIDs), clamped (anti-windup)."""

    gain: float
    """``k_i`` [1/s]: the integral corrects a constant pull at this rate."""
    limit: float
    """Bound of the correction [m/s^2]."""
    axes: Literal["z", "xyz"] = "z"
    """``z``: the vertical axis only; ``xyz``: every axis (the Crazyflie's velocity PIDs on x, y, z)."""


class PointMassPlant(_Kind, tag="point_mass"):
    """A 3D point mass of ``mass`` whose ideal inner loop flies ``u`` exactly and cancels its own
    weight (Remark 1 taken as true); a disturbance acts as the force ``mass * d``. Hosts the
    payload options (``plant/vehicle.py``)."""

    mass: float = 0.029
    """[kg]; a Crazyflie 2.1 by default."""
    feedforward_mass: float = 0.0
    """The vehicle's share of a payload's mass [kg], added to the mass its thrust is computed for."""
    integrator: ThrustIntegrator | None = None


class QuadrotorPlant(_Kind, tag="quadrotor"):
    """A Crazyflie 2.1-class quadrotor: rigid body (Eq. 1-3), Eq. 4 from ``u`` to thrust and
    attitude, a 500 Hz attitude and rate PID, motors with limits (``plant/quadrotor.py``,
    ``docs/quadrotor.md``); a disturbance acts as the force ``mass * d``."""

    mass: float = 0.029
    """[kg]."""
    yaw: float = 0.0
    """The yaw Eq. 4 holds [rad]."""
    tilt_max: float = 20.0
    """Eq. 4's tilt limit [deg]."""
    feedforward_mass: float = 0.0
    """The vehicle's share of a payload's mass [kg], added to the mass Eq. 4 uses."""
    integrator: ThrustIntegrator | None = None


class CrazyfliePlant(_Kind, tag="crazyflie"):
    """A Crazyflie through cflib, real (``radio://``, ``usb://``) or the software one (``udp://``,
    ``python -m plant.cfsim``); real time only (``plant/crazyflie.py``)."""

    uri: str
    """e.g. ``radio://0/80/2M/E7E7E7E701`` or ``udp://127.0.0.1:19850``."""
    mode: Literal["attitude", "full_state"] = "attitude"
    """``attitude``: Eq. 4 to ``send_setpoint`` (the paper's two loops); ``full_state``:
    ``send_full_state_setpoint`` (the onboard position controller closes a loop of its own)."""
    takeoff_height: float = 0.5
    """Height the high-level commander takes off to before the run starts [m]."""
    takeoff_time: float = 2.0
    """[s]."""
    land_time: float = 2.0
    """[s]."""
    connect_timeout: float = 10.0
    """Give up connecting (and waiting for the first state estimate) after this long [s]."""
    mass: float = 0.029
    """The mass Eq. 4 uses [kg]."""
    feedforward_mass: float = 0.0
    """A payload share added to it [kg]."""
    tilt_max: float = 20.0
    """Eq. 4's tilt limit [deg]."""
    yaw: float = 0.0
    """The yaw Eq. 4 assumes [rad] (the vehicle's heading at take-off)."""


PlantSpec = DoubleIntegrator | PointMassPlant | QuadrotorPlant | CrazyfliePlant


class Cable(_Strict):
    """One-sided spring-damper: pulls when stretched beyond ``length``, never pushes."""

    length: float
    """Rest length [m]."""
    stiffness: float = 200.0
    """[N/m]."""
    damping: float = 0.3
    """[N s/m]."""


class Payload(_Strict):
    """A point-mass payload hung from every vehicle on its own cable: one ``world`` process then
    hosts every vehicle (``point_mass`` or ``quadrotor`` plants) and serves each on the same keys
    as a single plant (``plant/payload.py``, ``docs/payload.md``)."""

    mass: float
    """[kg]."""
    cable: Cable
    p0: Vector | None = None
    """Initial position [m]; omitted: on the floor under the vehicles' centroid when the mission
    has a ``floor`` and the cables would be slack there, else hanging at rest below them."""
    substep: float = 0.001
    """Integration substep [s]: a whole fraction of the control period."""


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
    feedforward: Literal["measured", "commanded", "none"] = "measured"
    """What Eq. 17's ``sum_j a_ij vdot_j`` uses for an agent neighbour's ``vdot_j``: its measured
    acceleration (the mean over the previous period; the paper's law as written), its command of
    the previous tick (``vdot_j = u_j`` under Remark 1's two-loop assumption: immune to the inner
    loop's lag), or nothing. The leader's term is always its reference acceleration, except with
    ``none``, which drops the whole sum."""


class LinkPolicy(_Strict):
    """What an agent does with its in-neighbours' samples (part of the law's implementation).

    Samples older than the newest held are never used (sequence numbers). A neighbour whose newest
    sample is older than ``max_age`` (or that has sent none yet) is treated as in formation and
    not accelerating: it contributes nothing to xi, zeta or the feed-forward, as if its edge were
    absent but kappa_i kept; an agent that hears nobody commands u = 0 and coasts
    (:func:`agent.law.neighbour_sample`)."""

    max_age: float = 0.5
    """Oldest neighbour sample an agent uses [s]."""
    compensate: bool = False
    """Latency compensation: move each neighbour sample forward by its age with its own v and a."""


class Geofence(_Strict):
    """An axis-aligned box the vehicles must stay in [m; world frame]. In 3D its ``min`` z is the
    floor of the flight volume."""

    min: list[float]
    max: list[float]
    action: Literal["hold", "land", "estop"] = "land"
    """What a vehicle does when its position leaves the box."""


class Avoidance(_Strict):
    """Decentralised collision avoidance after the law (``agent/avoid.py``): a safety filter on each
    agent's command from the positions of the vehicles within ``sensing`` (heard on their state
    keys, as a range sensor or a broadcast would give them), kept apart from the law's inputs."""

    radius: float = 0.3
    """Minimum distance between two vehicles' centres the filter keeps [m]."""
    sensing: float = 2.0
    """Vehicles closer than this are considered [m]."""
    gain: float = 4.0
    """Class-K gain of the barrier constraint h' >= -gain * h [1/s]."""


class Safety(_Strict):
    """What every agent's safety supervisor and every plant's command watchdog enforce
    (``docs/safety.md``). The defaults are wide enough that no shipped mission reaches them while
    nothing goes wrong (measured there), and tight enough to stop what is not flying any more."""

    max_accel: float = 20.0
    """Largest command norm that leaves an agent [m/s^2] (2 g; a Crazyflie 2.1 has about 1.9 g
    of thrust): the law's command is scaled down to it (saturation after Eq. 17)."""
    max_speed: float = 30.0
    """Largest plausible speed of any vehicle or of the leader [m/s]: an own speed beyond it sends
    the vehicle to HOLD, and a sample that moved further than this allows since the sender's
    last accepted one is rejected as implausible."""
    jump_margin: float = 1.0
    """Slack on the plausible-jump bound [m] (noise, a restart)."""
    future_window: int = 2
    """Samples stamped more than this many ticks ahead of the receiver's own tick are rejected."""
    max_formation_error: float = 50.0
    """‖xi_i‖ beyond this [m] is divergence."""
    gain_cap: float = 1000.0
    """A gain beyond this is divergence."""
    divergence_action: Literal["hold", "land", "estop"] = "land"
    leader_timeout: float = 0.5
    """An agent that hears the leader holds when its newest leader sample is older than this [s]
    (or the leader's liveliness token is gone)."""
    neighbour_timeout: float = 1.0
    """An in-neighbour (agent) silent this long [s], or whose token is gone, is lost: its edge is
    dropped and kappa_i re-normalised while the leader still reaches this agent, else HOLD."""
    land_after: float = 2.0
    """HOLD for a lost input turns into LAND after this long [s] if the input has not come back."""
    land_speed: float = 0.3
    """Descent rate in LAND [m/s] (3D)."""
    ground: float = 0.0
    """Height of the ground [m] (3D): LAND ends, and the vehicle disarms, there."""
    hold_kp: float = 1.0
    """HOLD's position gain [1/s^2]: u = -hold_kv v - hold_kp (p - p_hold), saturated."""
    hold_kv: float = 2.0
    """HOLD's velocity gain [1/s]."""
    cmd_timeout: float = 0.5
    """A plant with no valid command for this long [s] holds (brakes to zero velocity, level)."""
    cmd_cutoff: float = 2.0
    """A plant with no valid command for this long [s] lands (never just stops)."""
    geofence: Geofence | None = None
    avoid: Avoidance | None = None


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
    """Seed of every random part of the run (random disturbances, network models)."""
    netem: Network | None = None
    """Network degradation per directed link j -> i (``docs/netem.md``); none: ideal links."""
    links: "LinkPolicy" = msgspec.field(default_factory=lambda: LinkPolicy())
    """What agents do with old neighbour data."""
    safety: Safety = msgspec.field(default_factory=lambda: Safety())
    """The failsafes every agent and plant enforce (``docs/safety.md``)."""
    payload: Payload | None = None
    """A cable-suspended payload shared by every vehicle (3D only)."""
    floor: float | None = None
    """Height of the ground [m] (3D only): the payload rests on it until lifted."""
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
    """A mission file is not valid. ``problems`` holds one ``(field, message)`` pair per problem.

    ``field`` is the path of the offending value in the file (``agents[2].offset``, ``law.kp0[1]``),
    ``"<file>"`` for the file as a whole. Every message reads ``"<what is wrong>; <how to fix it>"``.
    """

    def __init__(self, source: str, problems: list[tuple[str, str]]):
        self.source = source
        self.problems = problems
        lines = [f"{source}: {len(problems)} problem(s)"]
        lines += [f"  {field}: {msg}" for field, msg in problems]
        super().__init__("\n".join(lines))


# --------------------------------------------------------------------------- decoding
def loads(text: str | bytes, source: str = "<mission>") -> Mission:
    """Decode and validate a mission from TOML text. Raises :class:`MissionError`.

    Type errors stop decoding, so at most one of them is reported (with its fix); a mission that
    decodes is then checked by :func:`validate`, which reports every problem it finds.
    """
    try:
        raw = tomllib.loads(text.decode() if isinstance(text, bytes) else text)
    except tomllib.TOMLDecodeError as exc:
        raise MissionError(source, [("<file>", f"is not valid TOML: {exc}; fix the syntax there")]) from None
    except UnicodeDecodeError:
        raise MissionError(source, [("<file>", "is not UTF-8 text; save it as UTF-8")]) from None
    if "version" not in raw:
        raise MissionError(source, [("version", f"is missing; add `version = {SCHEMA_VERSION}` "
                                                f"(this release reads version {SCHEMA_VERSION})")])
    version = raw["version"]
    if type(version) is not int or version != SCHEMA_VERSION:
        raise MissionError(
            source,
            [("version", f"is {_toml(version)} but this release reads version {SCHEMA_VERSION}; set "
                         f"`version = {SCHEMA_VERSION}` after checking the fields against docs/mission.md")],
        )
    try:
        mission = msgspec.convert(raw, type=Mission)
    except msgspec.ValidationError as exc:
        raise MissionError(source, [_field_of(str(exc), raw)]) from None
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


# --------------------------------------------------------------------------- decode messages
_MISSION_TYPE = msgspec.inspect.type_info(Mission)
_KIND_NOUNS = {"profile": "leader profile", "disturbance": "disturbance", "plant": "plant"}
"""What the ``kind`` of each tagged union selects, by the name of the field holding the union."""
_GOT_NOUNS = {"str": "a string", "float": "a number", "int": "an integer", "bool": "a boolean",
              "array": "an array", "object": "a table", "datetime": "a date-time", "date": "a date",
              "time": "a time"}
"""msgspec's names of the TOML value types, as a mission author calls them."""

_KeyPath = list[str | int]
"""A field path split into names and indices: ``agents[0].p0`` is ``["agents", 0, "p0"]``."""


def _field_of(msg: str, raw: object = None) -> tuple[str, str]:
    """Turn a msgspec validation message into ``(field path, message-with-fix)``.

    ``msg`` reads like ``"Expected `float`, got `str` - at `$.agents[0].p0`"``. ``raw`` is the
    decoded TOML document: it tells which member of a tagged union a path is in (from its ``kind``),
    so that the message can list that member's fields, and which ``dim`` to use in examples.
    """
    text, where = msg, ""
    if " - at `$" in msg:
        text, _, at = msg.partition(" - at `$")
        where = at.rstrip("`").lstrip(".")
    path = _tokens(where)
    dim = raw.get("dim") if isinstance(raw, dict) and raw.get("dim") in (2, 3) else 3
    if text.startswith("Object contains unknown field") and text.count("`") >= 2:
        name = text.split("`")[1]
        known = _field_names(_type_at(path, raw))
        close = difflib.get_close_matches(name, known, n=1)
        fix = f"rename it to `{close[0]}` if that is what you meant, or remove it" if close else "remove it"
        listing = (f"the fields here are {', '.join(known)}" if len(known) > 1
                   else f"this table takes only `{known[0]}`" if known else "this table takes no fields")
        return _join(where, name), f"is not a known field; {fix} ({listing})"
    if text.startswith("Object missing required field") and text.count("`") >= 2:
        name = text.split("`")[1]
        field = _join(where, name)
        t = _type_at([*path, name], raw)
        if t is None:
            return field, "is required; add it (see docs/mission.md)"
        if isinstance(t, msgspec.inspect.LiteralType):
            return field, f"is required; add `{name} = ...` set to {_choices(t.values)}"
        return field, f"is required; {_add(t, name, where, dim)}"
    t = _type_at(path, raw)
    if text.startswith(("Invalid value", "Invalid enum value")) and isinstance(t, msgspec.inspect.LiteralType):
        value = _toml(_value_at(path, raw))
        noun = _KIND_NOUNS.get(str(path[-2])) if len(path) >= 2 and path[-1] == "kind" else None
        what = f"is {value}, not a {noun} kind" if noun else f"is {value}"
        return where or "<file>", f"{what}; use {_choices(t.values)}"
    if text.startswith("Expected `") and ", got `" in text and t is not None:
        got = text.split("`")[3]
        got_noun = _GOT_NOUNS.get(got, f"`{got}`")
        if isinstance(t, msgspec.inspect.LiteralType):
            return where or "<file>", f"is {got_noun}; use {_choices(t.values)}"
        want = _noun(t)
        name = path[-1] if path and isinstance(path[-1], str) else None
        example = _example(t, dim)
        sample = f"`{name} = {example}`" if name else f"`{example}`"
        numeric = isinstance(t, (msgspec.inspect.FloatType, msgspec.inspect.IntType))
        quotes = " (no quotes)" if got == "str" and numeric else ""
        return where or "<file>", f"is {got_noun} but must be {want}; write {want}{quotes}, e.g. {sample}"
    plain = text[:1].lower() + text[1:]
    return where or "<file>", f"{plain}; see docs/mission.md for this field's type"


def _add(t: msgspec.inspect.Type, name: str, where: str, dim: int) -> str:
    """How to add the missing field ``name`` of type ``t`` to the table at ``where``."""
    if not where and isinstance(t, msgspec.inspect.StructType):
        return f"add a [{name}] table (see docs/mission.md)"
    if not where and isinstance(t, msgspec.inspect.ListType) and isinstance(t.item_type, msgspec.inspect.StructType):
        return f"add one [[{name}]] table per item (see docs/mission.md)"
    return f"add it ({_noun(t)}), e.g. `{name} = {_example(t, dim)}`"


def _tokens(where: str) -> _KeyPath:
    """``"agents[0].p0"`` -> ``["agents", 0, "p0"]``."""
    return [int(idx) if idx else name for name, idx in re.findall(r"([^.\[\]]+)|\[(\d+)\]", where)]


def _join(where: str, name: str) -> str:
    return f"{where}.{name}" if where else name


def _members(t: msgspec.inspect.Type) -> list[msgspec.inspect.Type]:
    """The members of a union (``None`` left out), or ``[t]``."""
    if isinstance(t, msgspec.inspect.UnionType):
        return [m for m in t.types if not isinstance(m, msgspec.inspect.NoneType)]
    return [t]


def _tags(t: msgspec.inspect.Type) -> tuple[str, ...]:
    """The ``kind`` values of a tagged union (or of one tagged struct); empty if ``t`` is not tagged."""
    members = _members(t)
    if all(isinstance(m, msgspec.inspect.StructType) and m.tag_field for m in members):
        return tuple(str(m.tag) for m in members)
    return ()


def _resolve(t: msgspec.inspect.Type, value: object) -> msgspec.inspect.Type:
    """The member of a union that ``value`` selects (by its ``kind``, or list vs number); else ``t``."""
    members = _members(t)
    if len(members) == 1:
        return members[0]
    for m in members:
        if isinstance(m, msgspec.inspect.StructType) and m.tag_field and isinstance(value, dict):
            if value.get(m.tag_field) == m.tag:
                return m
        elif isinstance(m, msgspec.inspect.ListType) and isinstance(value, list):
            return m
    return t


def _type_at(path: _KeyPath, raw: object) -> msgspec.inspect.Type | None:
    """The schema type of the value at ``path`` (a union member when the file selects one), or None.

    A tagged union's ``kind`` field comes back as a ``LiteralType`` of every kind of the union.
    """
    t: msgspec.inspect.Type = _MISSION_TYPE
    value = raw
    for k, tok in enumerate(path):
        if isinstance(tok, str) and tok == "kind" and k == len(path) - 1 and _tags(t):
            return msgspec.inspect.LiteralType(values=_tags(t))
        t = _resolve(t, value)
        if isinstance(tok, int):
            if not isinstance(t, msgspec.inspect.ListType):
                return None
            t = t.item_type
            value = value[tok] if isinstance(value, list) and tok < len(value) else None
            continue
        if not isinstance(t, msgspec.inspect.StructType):
            return None
        field = next((f for f in t.fields if f.encode_name == tok), None)
        if field is None:
            return None
        t = field.type
        value = value.get(tok) if isinstance(value, dict) else None
    return _resolve(t, value)


def _value_at(path: _KeyPath, raw: object) -> object:
    value = raw
    for tok in path:
        if isinstance(tok, int) and isinstance(value, list) and tok < len(value):
            value = value[tok]
        elif isinstance(tok, str) and isinstance(value, dict):
            value = value.get(tok)
        else:
            return None
    return value


def _field_names(t: msgspec.inspect.Type | None) -> list[str]:
    """The fields a table of type ``t`` takes, ``kind`` first for a member of a tagged union."""
    if not isinstance(t, msgspec.inspect.StructType):
        return []
    return ([t.tag_field] if t.tag_field else []) + [f.encode_name for f in t.fields]


def _noun(t: msgspec.inspect.Type) -> str:
    """How a mission author calls a value of type ``t``: "a number", "an array of numbers", ..."""
    if isinstance(t, msgspec.inspect.FloatType):
        return "a number"
    if isinstance(t, msgspec.inspect.IntType):
        return "an integer"
    if isinstance(t, msgspec.inspect.StrType):
        return "a string"
    if isinstance(t, msgspec.inspect.BoolType):
        return "true or false"
    if isinstance(t, msgspec.inspect.LiteralType):
        return _choices(t.values)
    if isinstance(t, msgspec.inspect.ListType):
        items = {"FloatType": "numbers", "IntType": "integers", "StrType": "strings", "StructType": "tables"}
        return f"an array of {items.get(type(t.item_type).__name__, 'values')}"
    if _tags(t):
        return "a table with a `kind`"
    if isinstance(t, msgspec.inspect.StructType):
        return "a table"
    return " or ".join(_noun(m) for m in _members(t))


def _example(t: msgspec.inspect.Type, dim: int) -> str:
    """A TOML value of type ``t`` to show in a fix."""
    if isinstance(t, msgspec.inspect.FloatType):
        return "1.0"
    if isinstance(t, msgspec.inspect.IntType):
        return "1"
    if isinstance(t, msgspec.inspect.StrType):
        return '"..."'
    if isinstance(t, msgspec.inspect.LiteralType):
        return _toml(t.values[0])
    if isinstance(t, msgspec.inspect.ListType):
        if isinstance(t.item_type, msgspec.inspect.StructType):
            return "[{ ... }, ...]"
        count = dim if isinstance(t.item_type, msgspec.inspect.FloatType) else 1  # a vector, or a sample
        return "[" + ", ".join([_example(t.item_type, dim)] * count) + "]"
    if _tags(t):
        first = _members(t)[0]
        more = ", ..." if isinstance(first, msgspec.inspect.StructType) and first.fields else ""
        return f"{{ kind = {_toml(_tags(t)[0])}{more} }}"
    if isinstance(t, msgspec.inspect.StructType):
        return "{ ... }"
    return _example(_members(t)[0], dim)


def _toml(value: object) -> str:
    """``value`` as it is written in TOML (strings in double quotes)."""
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def _choices(values: tuple[object, ...] | list[object]) -> str:
    """``one of "a", "b" or "c"`` (or the one value)."""
    shown = [_toml(v) for v in values]
    if len(shown) == 1:
        return shown[0]
    return f"one of {', '.join(shown[:-1])} or {shown[-1]}"


# --------------------------------------------------------------------------- validation
Problems = list[tuple[str, str]]
"""``(field path, "<what is wrong>; <how to fix it>")`` pairs."""


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


def per_axis(v: PerAxis, dim: int) -> list[float]:
    """Expand a :data:`PerAxis` value to ``dim`` components (a list is returned as floats, unchanged
    in length: :func:`validate` checks it has ``dim``)."""
    return [float(v)] * dim if not isinstance(v, list) else [float(x) for x in v]


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
        for name in ("radius", "sensing", "gain"):
            if not getattr(av, name) > 0:
                out.append((f"safety.avoid.{name}", f"is {getattr(av, name)}; give a value > 0"))
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


# --------------------------------------------------------------------------- encode
def dumps(m: Mission) -> str:
    """``m`` as mission-file TOML that :func:`loads` reads back to an equal mission (defaults and
    unset optional fields are written out or left out as the schema encodes them)."""
    raw = msgspec.to_builtins(m)
    plain = {k: v for k, v in raw.items() if not _is_table(v) and not _is_table_array(v)}
    lines = [f"{k} = {_inline(v)}" for k, v in plain.items() if v is not None]
    for k, v in raw.items():
        if _is_table(v):
            lines += ["", f"[{k}]"] + [f"{kk} = {_inline(vv)}" for kk, vv in v.items() if vv is not None]
        elif _is_table_array(v):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_inline(vv)}" for kk, vv in item.items() if vv is not None]
    return "\n".join(lines) + "\n"


def _is_table(v: object) -> bool:
    return isinstance(v, dict)


def _is_table_array(v: object) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def _inline(v: object) -> str:
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k) if not k.isidentifier() else k} = {_inline(x)}"
                                for k, x in v.items() if x is not None) + " }"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_inline(x) for x in v) + "]"
    if isinstance(v, float):
        return "inf" if v == math.inf else "-inf" if v == -math.inf else "nan" if v != v else repr(v)
    return _toml(v)
