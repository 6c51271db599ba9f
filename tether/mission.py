"""Mission files: a strict, versioned TOML schema, its decoding with fixes, and its writing.

A mission file is decoded into :class:`Mission` with msgspec (unknown fields are errors; the bases
and the error come from :mod:`tether.schema`), then :func:`validate` (:mod:`tether.checks`) checks
what a type cannot say: the graph (Assumption 1, self-loops, weights, ids), dimensions, the law's
parameters, and finiteness. Every error names the field by its path in the file, with an agent
named by its id and an edge by its ends (``agent 7.offset``, ``edge 3 → 4.weight``, see
:func:`by_id`), and says how to fix it, as ``"<what is wrong>; <how to fix it>"``.
:func:`load` does both and returns a :class:`Mission`; it raises :class:`MissionError` listing every
problem found, not only the first (a type error stops decoding, so it is reported alone).

The file format, field by field, is documented in ``docs/mission.md``.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec
import msgspec.inspect
import msgspec.structs

from tether.netprofile import Network
from tether.schema import KeyPath, Kind, Problems, SchemaError, Strict, close_matches, read_issue

SCHEMA_VERSION = 1
"""The mission-file version this release reads."""

MAX_FILE_BYTES = 64 * 2**20
"""Largest mission file read (64 MiB: about 300 000 agents); a larger one is refused before parsing."""

Vector = list[float]
"""A vector of ``dim`` components (2 or 3), in the world frame."""

PerAxis = float | list[float]
"""One value for every axis, or a list of ``dim`` values (x, y[, z])."""


# --------------------------------------------------------------------------- leader profiles
class ExpAccel(Kind, tag="exp_accel", frozen=True):
    """Leader acceleration ``a_ref(t) = a0 * exp(-decay * t)`` per axis (Section 4: a0 = [1, 0], decay = 0.1)."""

    a0: Vector
    """Initial acceleration [m/s^2; world frame]."""
    decay: float
    """Decay rate [1/s]; 0 gives a constant acceleration."""


class VelocitySegment(Strict, frozen=True):
    """From ``t`` on, the leader's velocity is ``v`` (reached after the profile's ``ramp``)."""

    t: float
    """Segment start [s]."""
    v: Vector
    """Velocity [m/s; world frame]."""


class VelocitySchedule(Kind, tag="velocity_schedule", frozen=True):
    """Piecewise-constant velocity (Eq. 31, Eq. 32), optionally with linear ramps between segments."""

    segments: list[VelocitySegment]
    ramp: float = 0.0
    """Duration of each velocity change [s]; 0 is a step (the acceleration is then an impulse and is
    reported as 0)."""


class Waypoint(Strict, frozen=True):
    """The leader is at ``p`` at time ``t`` with zero velocity and acceleration."""

    t: float
    """Time [s]."""
    p: Vector
    """Position [m; world frame]."""


class Waypoints(Kind, tag="waypoints", frozen=True):
    """Minimum-jerk (quintic) segments between timed waypoints; the first waypoint's time must be 0
    and its position the leader's ``p0``. After the last waypoint the leader holds position."""

    points: list[Waypoint]


class Hold(Kind, tag="hold", frozen=True):
    """The leader keeps its initial velocity forever (zero acceleration)."""


Profile = ExpAccel | VelocitySchedule | Waypoints | Hold


class Leader(Strict, frozen=True):
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
class NoDisturbance(Kind, tag="none", frozen=True):
    """``d = 0``."""


class Sinusoid(Kind, tag="sinusoid", frozen=True):
    """``d_k(t) = amplitude_k * sin(omega_k * t + phase_k)`` per axis k (Section 4's disturbances;
    a cosine is ``phase = pi/2``)."""

    amplitude: Vector
    """Amplitude [m/s^2]."""
    omega: Vector
    """Angular frequency [rad/s]."""
    phase: Vector | None = None
    """Phase [rad]; zeros when omitted."""


class Constant(Kind, tag="constant", frozen=True):
    """``d = value`` for all time."""

    value: Vector
    """[m/s^2; world frame]."""


class BoundedRandom(Kind, tag="bounded_random", frozen=True):
    """Piecewise-constant random disturbance, uniform in the box ``|d_k| <= bound_k``, redrawn every
    ``hold`` seconds from a generator seeded by the mission seed and the agent id."""

    bound: PerAxis
    """Per-axis bound [m/s^2]."""
    hold: float
    """Time between redraws [s]."""


SingleDisturbance = NoDisturbance | Sinusoid | Constant | BoundedRandom


class DisturbanceSum(Kind, tag="sum", frozen=True):
    """``d = terms[0] + terms[1] + ...``: a sum of single models, each evaluated exactly as it is
    alone (a bounded random term j > 0 draws from its own generator, seeded by the mission seed,
    the agent id and j). In TOML, one ``[[agents.disturbance.terms]]`` table per term."""

    terms: list[SingleDisturbance]


Disturbance = NoDisturbance | Sinusoid | Constant | BoundedRandom | DisturbanceSum


def disturbance_terms(dist: Disturbance) -> list[SingleDisturbance]:
    """The single models a disturbance adds up (one for a single model)."""
    return list(dist.terms) if isinstance(dist, DisturbanceSum) else [dist]


# --------------------------------------------------------------------------- plants
class DoubleIntegrator(Kind, tag="double_integrator", frozen=True):
    """``p' = v, v' = u + d``, discretised exactly under a zero-order hold on ``u``."""


class ThrustIntegrator(Strict, frozen=True):
    """An inner integral of the acceleration error ``u - p''`` (vertical by default) added to the
    command (the integral of the Crazyflie's own velocity PIDs), clamped (anti-windup)."""

    gain: float
    """``k_i`` [1/s]: the integral corrects a constant pull at this rate."""
    limit: float
    """Bound of the correction [m/s^2]."""
    axes: Literal["z", "xyz"] = "z"
    """``z``: the vertical axis only; ``xyz``: every axis (the Crazyflie's velocity PIDs on x, y, z)."""


class PointMassPlant(Kind, tag="point_mass", frozen=True):
    """A 3D point mass of ``mass`` whose ideal inner loop flies ``u`` exactly and cancels its own
    weight (Remark 1 taken as true); a disturbance acts as the force ``mass * d``. Hosts the
    payload options (``plant/vehicle.py``)."""

    mass: float = 0.029
    """[kg]; a Crazyflie 2.1 by default."""
    feedforward_mass: float = 0.0
    """The vehicle's share of a payload's mass [kg], added to the mass its thrust is computed for."""
    integrator: ThrustIntegrator | None = None


class QuadrotorPlant(Kind, tag="quadrotor", frozen=True):
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


class CrazyfliePlant(Kind, tag="crazyflie", frozen=True):
    """A Crazyflie through cflib, real (``radio://``, ``usb://``) or the software one (``udp://``,
    ``python -m plant.cfsim``); real time only (``plant/crazyflie.py``)."""

    uri: str
    """e.g. ``radio://0/80/2M/E7E7E7E701`` or ``udp://127.0.0.1:19850``."""
    mode: Literal["attitude", "full_state"] = "attitude"
    """``attitude``: Eq. 4 to ``send_setpoint`` (the paper's two loops); ``full_state``:
    ``send_full_state_setpoint`` (the onboard position controller closes a loop of its own)."""
    takeoff_height: float = 0.5
    """Height the high-level commander takes off to in the start's lead, before tick 0 [m]."""
    takeoff_time: float = 2.0
    """[s]; the start's lead is at least this plus :data:`TAKEOFF_MARGIN` (:func:`start_lead`)."""
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


class Cable(Strict, frozen=True):
    """One-sided spring-damper: pulls when stretched beyond ``length``, never pushes."""

    length: float
    """Rest length [m]."""
    stiffness: float = 200.0
    """[N/m]."""
    damping: float = 0.3
    """[N s/m]."""


class Payload(Strict, frozen=True):
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
class Agent(Strict, frozen=True):
    id: int
    p0: Vector
    """Initial position [m; world frame]."""
    offset: Vector
    """Formation offset ``h_i`` relative to the leader [m; world frame]."""
    v0: Vector | None = None
    """Initial velocity [m/s; world frame]; zeros when omitted."""
    plant: PlantSpec = DoubleIntegrator()
    disturbance: Disturbance = NoDisturbance()


class Edge(Strict, frozen=True):
    """``src -> dst``: agent ``dst`` hears ``src`` with weight ``a_{dst,src} > 0``."""

    src: int = msgspec.field(name="from")
    dst: int = msgspec.field(name="to")
    weight: float = 1.0


class Law(Strict, frozen=True):
    """The formation law: Eq. 17 (``kind = "sigma"``), the benchmark Eq. 30 (``kind = "benchmark"``,
    no ``sigma``), or a law of one's own (``use = "package.module:Class"``, its parameters in
    ``[law.params]``; ``docs/laws.md``)."""

    kind: Literal["sigma", "benchmark", "custom"] = "custom"
    """A law shipped with tether; ``custom`` (the default when ``use`` is given) runs ``use``."""
    kp0: PerAxis = 1.0
    """Initial position gains ``Kp(0)`` per axis [1/s^2 after the 1/kappa scaling] (sigma, benchmark)."""
    kv0: PerAxis = 1.0
    """Initial velocity gains ``Kv(0)`` per axis [1/s] (sigma, benchmark)."""
    gamma_p: PerAxis = 0.0
    """Adaptation rate ``Gamma_p`` of Kp, one or one per axis (``diag(Gamma_p)``; sigma, benchmark: > 0)."""
    gamma_v: PerAxis = 0.0
    """Adaptation rate ``Gamma_v`` of Kv, one or one per axis (sigma, benchmark: > 0)."""
    sigma: float | None = None
    """Leakage ``sigma`` of the sigma-modification [1/s]; required for ``sigma``, absent for ``benchmark``."""
    use: str = ""
    """With ``kind = "custom"``: the law's class, ``"package.module:Class"`` (:func:`agent.laws.resolve`)."""
    params: dict[str, Any] = {}
    """With ``kind = "custom"``: the law's parameters, decoded into its ``Params``."""
    feedforward: Literal["measured", "commanded", "none"] = "measured"
    """What Eq. 17's ``sum_j a_ij vdot_j`` uses for an agent neighbour's ``vdot_j``: its measured
    acceleration (the mean over the previous period; the paper's law as written), its command of
    the previous tick (``vdot_j = u_j`` under Remark 1's two-loop assumption: immune to the inner
    loop's lag), or nothing. The leader's term is always its reference acceleration, except with
    ``none``, which drops the whole sum."""


class LinkPolicy(Strict, frozen=True):
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


class Geofence(Strict, frozen=True):
    """An axis-aligned box the vehicles must stay in [m; world frame]. In 3D its ``min`` z is the
    floor of the flight volume."""

    min: list[float]
    max: list[float]
    action: Literal["hold", "land", "estop"] = "land"
    """What a vehicle does when its position leaves the box."""


class Avoidance(Strict, frozen=True):
    """Decentralised collision avoidance after the law (``agent/avoid.py``): a safety filter on each
    agent's command from the positions of the vehicles within ``sensing`` (heard on their state
    keys, as a range sensor or a broadcast would give them), kept apart from the law's inputs."""

    radius: float = 0.3
    """Minimum distance between two vehicles' centres the filter keeps [m]."""
    sensing: float = 2.0
    """Vehicles closer than this are considered [m]."""
    gain: float = 1.0
    """Class-K gain of the barrier constraint ``h' >= -gain h^3`` (Wang, Ames & Egerstedt 2017)."""
    brake: float = 2.0
    """Braking capacity each vehicle is assumed to keep for avoidance [m/s^2] (below max_accel)."""


class Safety(Strict, frozen=True):
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
    profile_margin: Annotated[float, msgspec.Meta(gt=0.0)] = 0.01
    """The leader's samples may depart from its profile at their own time by at most this [m; m/s;
    m/s^2, each of position, velocity and acceleration]; more is rejected (``profile``)."""
    suspect_window: Annotated[int, msgspec.Meta(ge=4, le=100_000)] = 50
    """Samples over which each input stream is judged (0.5 s at 100 Hz)."""
    suspect_share: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.5
    """A stream with at least this share of its last ``suspect_window`` samples rejected or in
    conflict is suspect (a forgery or a sensor fault) and treated as a lost input."""
    mode_confirm: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 3
    """A plant's report of a mode other than FLYING, and an in-neighbour's report of its mode (or
    of flying again), is believed once this many samples of consecutive ticks say it."""
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
    land_after: float = 10.0
    """HOLD for a lost input turns into LAND after this long [s] if the input has not come back.
    Longer than a restart of a killed agent (the unit's ``RestartSec=2`` and a cold start: kill to
    rejoined 2.8-4.8 s measured, ``docs/watchdog.md``), so that the vehicles it cut off hold rather
    than land while it comes back; a held vehicle brakes to rest where it is (``docs/safety.md``)."""
    flap_limit: Annotated[int, msgspec.Meta(ge=1, le=1000)] = 3
    """Recoveries from HOLD, each within 60 s of the last, after which the next HOLD is a LAND
    instead (``docs/safety.md``, *No flapping*)."""
    resume_dwell: Annotated[float, msgspec.Meta(ge=0.0, le=60.0)] = 0.5
    """HOLD → FLYING waits for the cause to be gone this long [s] times the recent recoveries (not
    at all after none)."""
    land_speed: float = 0.3
    """Descent rate in LAND [m/s] (3D)."""
    ground: float = 0.0
    """Height of the ground [m] (3D): LAND ends, and the vehicle disarms, there."""
    land_settle: float = 5.0
    """2D (no ground): LAND holds until the vehicle is still (below 0.05 m/s) or for at most this
    long [s], then it is LANDED (stopped, disarmed). A disturbance HOLD cannot cancel (the cable's
    steady sway) can keep a holding vehicle moving for ever; 5 s is five time constants of the
    default HOLD loop (hold_kp 1, hold_kv 2: both poles at -1/s)."""
    hold_kp: float = 1.0
    """HOLD's position gain [1/s^2]: u = -hold_kv v - hold_kp (p - p_hold), saturated."""
    hold_kv: float = 2.0
    """HOLD's velocity gain [1/s]."""
    cmd_timeout: float = 0.5
    """A plant with no valid command for this long [s] holds (brakes to zero velocity, level)."""
    cmd_cutoff: float = 10.0
    """A plant with no valid command for this long [s] lands (never just stops); until then it holds
    (from ``cmd_timeout``), so that its agent, restarted by its unit, finds it in the air and flies
    it again (``docs/watchdog.md``, "Restart and rejoin")."""
    geofence: Geofence | None = None
    avoid: Avoidance | None = None


class Mission(Strict, frozen=True):
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
    fleet: str | None = None
    """The lab's fleet file (``tether/fleet.py``, ``docs/lab.md``), relative to the mission file: each
    ``crazyflie`` plant flies as the fleet's vehicle of the same URI. :func:`load` makes it absolute."""

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
        """Row of a node in the simulator's arrays: agents ``0..N-1`` in file order, the leader ``N``. O(1)."""
        if node_id == self.leader.id:
            return self.n
        row = _rows(self.agents).get(node_id)
        if row is None:
            raise ValueError(f"{node_id} is not an agent of mission {self.name!r}")
        return row

    def agent(self, agent_id: int) -> Agent:
        """The agent with id ``agent_id`` (the first, should the file repeat it). O(1)."""
        row = _rows(self.agents).get(agent_id)
        if row is None:
            raise KeyError(f"no agent with id {agent_id}")
        return self.agents[row]


_ROWS: dict[int, tuple[list[Agent], dict[int, int]]] = {}
"""``id(agents)`` -> (the list, agent id -> first row): the rows of the last few missions' agents,
so that looking an agent up by id is O(1), not O(N) (a 10 000-agent mission looks up every agent).
The entry holds the list itself, so its ``id`` cannot be reused while it is here."""


def _rows(agents: list[Agent]) -> dict[int, int]:
    hit = _ROWS.get(id(agents))
    if hit is None or hit[0] is not agents:
        rows: dict[int, int] = {}
        for k, a in enumerate(agents):
            rows.setdefault(a.id, k)
        if len(_ROWS) >= 16:
            _ROWS.clear()
        hit = _ROWS[id(agents)] = (agents, rows)
    return hit[1]


# --------------------------------------------------------------------------- errors
class MissionError(SchemaError):
    """A mission file is not valid. ``problems`` holds one ``(field, message)`` pair per problem.

    ``field`` is the path of the offending value in the file, an agent named by its id and an edge
    by its ends (``agent 7.offset``, ``edge 3 → 4.weight``, ``law.kp0[1]``; :func:`by_id`),
    ``"<file>"`` for the file as a whole. Every message reads ``"<what is wrong>; <how to fix it>"``.
    """


_TABLE = re.compile(r"^(?P<table>agents|edges)\[(?P<k>\d+)\](?P<rest>.*)$", re.DOTALL)


def ordinal(n: int) -> str:
    """``1`` -> ``"1st"``, ``2`` -> ``"2nd"``, ``11`` -> ``"11th"``, ``23`` -> ``"23rd"``."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def by_id(problems: Problems, agent_ids: list[int | None], edge_ends: list[tuple[int, int] | None]) -> Problems:
    """``problems`` with every ``agents[k]…`` / ``edges[k]…`` field named as a reader of the file
    looks for it: ``agent 7.offset``, ``edge 3 → 4.weight``. Pure.

    ``agent_ids[k]`` is the id of the file's k-th ``[[agents]]`` table and ``edge_ends[k]`` the
    ``(from, to)`` of its k-th ``[[edges]]`` table, ``None`` where the file gives none (then, and
    only then, the table is named by its place: ``3rd [[agents]]``); an id or a pair of ends that
    the file repeats is named with its place too (``agent 2 (5th [[agents]])``), since the id alone
    would not say which table is meant.
    """
    ids: dict[int, int] = {}
    for i in agent_ids:
        if i is not None:
            ids[i] = ids.get(i, 0) + 1
    ends: dict[tuple[int, int], int] = {}
    for e in edge_ends:
        if e is not None:
            ends[e] = ends.get(e, 0) + 1

    def name(table: str, k: int) -> str:
        place = f"{ordinal(k + 1)} [[{table}]]"
        if table == "agents":
            i = agent_ids[k] if k < len(agent_ids) else None
            if i is None:
                return place
            return f"agent {i} ({place})" if ids[i] > 1 else f"agent {i}"
        e = edge_ends[k] if k < len(edge_ends) else None
        if e is None:
            return place
        return f"edge {e[0]} → {e[1]} ({place})" if ends[e] > 1 else f"edge {e[0]} → {e[1]}"

    out: Problems = []
    for field, msg in problems:
        m = _TABLE.match(field)
        out.append((name(m["table"], int(m["k"])) + m["rest"], msg) if m else (field, msg))
    return out


def raw_ends(raw: object) -> tuple[list[int | None], list[tuple[int, int] | None]]:
    """The agent ids and edge ends a decoded TOML document gives (``None`` where one is absent or
    not an integer), for :func:`by_id` before the document is a :class:`Mission`."""
    def integer(x: object) -> int | None:
        return x if type(x) is int else None

    tables = raw if isinstance(raw, dict) else {}
    agents = tables.get("agents")
    edges = tables.get("edges")
    ids = [integer(a.get("id")) if isinstance(a, dict) else None for a in (agents if isinstance(agents, list) else [])]
    ends: list[tuple[int, int] | None] = []
    for e in edges if isinstance(edges, list) else []:
        src, dst = (integer(e.get("from")), integer(e.get("to"))) if isinstance(e, dict) else (None, None)
        ends.append((src, dst) if src is not None and dst is not None else None)
    return ids, ends


# --------------------------------------------------------------------------- decoding
def loads(text: str | bytes, source: str = "<mission>") -> Mission:
    """Decode and validate a mission from TOML text. Raises :class:`MissionError`.

    Type errors stop decoding, so at most one of them is reported (with its fix); a mission that
    decodes is then checked by :func:`validate`, which reports every problem it finds.
    """
    if len(text) > MAX_FILE_BYTES:
        raise MissionError(source, [("<file>", f"is {len(text) / 2**20:.1f} MiB, beyond the {MAX_FILE_BYTES // 2**20} "
                                               "MiB a mission file may have; generate fewer agents or edges")])
    try:
        raw = tomllib.loads(text.decode() if isinstance(text, bytes) else text)
    except tomllib.TOMLDecodeError as exc:
        raise MissionError(source, [("<file>", f"is not valid TOML: {exc}; fix the syntax there")]) from None
    except UnicodeDecodeError:
        raise MissionError(source, [("<file>", "is not UTF-8 text; save it as UTF-8")]) from None
    except RecursionError:
        raise MissionError(source, [("<file>", "nests arrays or tables too deeply to read (hundreds of levels); "
                                               "a mission nests at most a few levels: fix the brackets")]) from None
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
        raise MissionError(source, by_id([_field_of(exc, raw)], *raw_ends(raw))) from None
    except RecursionError:
        raise MissionError(source, [("<file>", "nests arrays or tables too deeply to read; a mission nests at "
                                               "most a few levels: fix the brackets")]) from None
    problems = validate(mission)
    if problems:
        raise MissionError(source, problems)
    return mission


def load(path: str | Path) -> Mission:
    """Read, decode and validate a mission file. Raises :class:`MissionError` (also for a missing file)."""
    path = Path(path)
    try:
        if path.is_dir():
            raise MissionError(str(path), [("<file>", "is a directory; give a mission file (.toml)")])
        with open(path, "rb") as fh:
            text = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise MissionError(str(path), [("<file>", f"cannot be read ({exc.strerror or exc}); check the path")]) from None
    return _with_fleet(loads(text, source=str(path)), path)


def _with_fleet(m: Mission, path: Path) -> Mission:
    """``m`` with its fleet file's path made absolute, once the fleet is valid and holds every
    ``crazyflie`` plant's URI. Raises :class:`tether.fleet.FleetError` or :class:`MissionError`."""
    if m.fleet is None:
        return m
    from tether import fleet as fl

    where = (path.parent / m.fleet).resolve()
    f = fl.load(where)
    problems: Problems = []
    for a in m.agents:
        if not isinstance(a.plant, CrazyfliePlant):
            continue
        v = f.by_uri(a.plant.uri)
        if v is None:
            problems.append((f"agent {a.id}.plant.uri", f"{a.plant.uri} is no vehicle of the fleet {m.fleet}; "
                                                        "add it there as a [[vehicles]] table or fix the URI"))
        elif len(a.p0) == len(v.p0) and math.dist(a.p0, v.p0) > fl.PLACE_TOLERANCE:
            problems.append((f"agent {a.id}.p0", f"is {a.p0} but the fleet puts vehicle {v.name} ({a.plant.uri}) "
                                                 f"at {v.p0}; make them agree (the vehicle starts where it stands)"))
    if problems:
        raise MissionError(str(path), problems)
    return msgspec.structs.replace(m, fleet=str(where))


def with_duration(m: Mission, duration: float | None, source: str = "<mission>") -> Mission:
    """``m`` with its run length replaced by ``duration`` [s] (a ``--duration`` override), checked by
    :func:`tether.checks.validate_duration` like the mission's own; ``None`` returns ``m``. Raises
    :class:`MissionError` naming ``--duration``. The one check every command's ``--duration`` gets."""
    if duration is None:
        return m
    from tether import checks

    problems = checks.validate_duration(m, float(duration), field="--duration")
    if problems:
        raise MissionError(f"{source} with --duration {duration}", problems)
    out = msgspec.structs.replace(m, duration=float(duration))
    problems = checks.validate(out)  # what else the run length decides (a leader profile that runs away by then)
    if problems:
        raise MissionError(f"{source} with --duration {duration}", problems)
    return out


# --------------------------------------------------------------------------- decode messages
_MISSION_TYPE = msgspec.inspect.type_info(Mission)
_KIND_NOUNS = {"profile": "leader profile", "disturbance": "disturbance", "plant": "plant"}
"""What the ``kind`` of each tagged union selects, by the name of the field holding the union."""
_GOT_NOUNS = {"str": "a string", "float": "a number", "int": "an integer", "bool": "a boolean",
              "array": "an array", "object": "a table", "datetime": "a date-time", "date": "a date",
              "time": "a time"}
"""msgspec's names of the TOML value types, as a mission author calls them."""

def _field_of(msg: str | msgspec.ValidationError, raw: object = None) -> tuple[str, str]:
    """Turn a msgspec validation error into ``(field path, message-with-fix)``.

    ``msg`` reads like ``"Expected `float`, got `str` - at `$.agents[0].p0`"``. ``raw`` is the
    decoded TOML document: it tells which member of a tagged union a path is in (from its ``kind``),
    so that the message can list that member's fields, and which ``dim`` to use in examples.
    """
    issue = read_issue(msg)
    path, where = issue.path, issue.where
    dim: int = raw["dim"] if isinstance(raw, dict) and raw.get("dim") in (2, 3) else 3
    if issue.kind == "unknown_field" and issue.name is not None:
        known = _field_names(_type_at(path, raw))
        close = close_matches(issue.name, known, n=1)
        fix = f"rename it to `{close[0]}` if that is what you meant, or remove it" if close else "remove it"
        listing = (f"the fields here are {', '.join(known)}" if len(known) > 1
                   else f"this table takes only `{known[0]}`" if known else "this table takes no fields")
        return issue.field, f"is not a known field; {fix} ({listing})"
    if issue.kind == "missing_field" and issue.name is not None:
        name, field = issue.name, issue.field
        t = _type_at((*path, name), raw)
        if t is None:
            return field, "is required; add it (see docs/mission.md)"
        if isinstance(t, msgspec.inspect.LiteralType):
            return field, f"is required; add `{name} = ...` set to {_choices(t.values)}"
        return field, f"is required; {_add(t, name, where, dim)}"
    t = _type_at(path, raw)
    if issue.kind == "invalid_value" and issue.value is not None and isinstance(t, msgspec.inspect.LiteralType):
        value = _toml(_value_at(path, raw))
        noun = _KIND_NOUNS.get(str(path[-2])) if len(path) >= 2 and path[-1] == "kind" else None
        what = f"is {value}, not a {noun} kind" if noun else f"is {value}"
        return where or "<file>", f"{what}; use {_choices(t.values)}"
    if issue.kind == "wrong_type" and issue.got is not None and t is not None:
        got = issue.got
        got_noun = _GOT_NOUNS.get(got, f"`{got}`")
        if isinstance(t, msgspec.inspect.LiteralType):
            return where or "<file>", f"is {got_noun}; use {_choices(t.values)}"
        want = _noun(t)
        key = path[-1] if path and isinstance(path[-1], str) else None
        example = _example(t, dim)
        sample = f"`{key} = {example}`" if key else f"`{example}`"
        numeric = isinstance(t, (msgspec.inspect.FloatType, msgspec.inspect.IntType))
        quotes = " (no quotes)" if got == "str" and numeric else ""
        return where or "<file>", f"is {got_noun} but must be {want}; write {want}{quotes}, e.g. {sample}"
    return where or "<file>", f"{issue.sentence}; see docs/mission.md for this field's type"


def _add(t: msgspec.inspect.Type, name: str, where: str, dim: int) -> str:
    """How to add the missing field ``name`` of type ``t`` to the table at ``where``."""
    if not where and isinstance(t, msgspec.inspect.StructType):
        return f"add a [{name}] table (see docs/mission.md)"
    if not where and isinstance(t, msgspec.inspect.ListType) and isinstance(t.item_type, msgspec.inspect.StructType):
        return f"add one [[{name}]] table per item (see docs/mission.md)"
    return f"add it ({_noun(t)}), e.g. `{name} = {_example(t, dim)}`"


def _members(t: msgspec.inspect.Type) -> list[msgspec.inspect.Type]:
    """The members of a union (``None`` left out), or ``[t]``."""
    if isinstance(t, msgspec.inspect.UnionType):
        return [m for m in t.types if not isinstance(m, msgspec.inspect.NoneType)]
    return [t]


def _tags(t: msgspec.inspect.Type) -> tuple[str, ...]:
    """The ``kind`` values of a tagged union (or of one tagged struct); empty if ``t`` is not tagged."""
    members = _members(t)
    tags = tuple(str(m.tag) for m in members if isinstance(m, msgspec.inspect.StructType) and m.tag_field)
    return tags if len(tags) == len(members) else ()


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


def _type_at(path: KeyPath, raw: object) -> msgspec.inspect.Type | None:
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


def _value_at(path: KeyPath, raw: object) -> object:
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


# --------------------------------------------------------------------------- semantics
def per_axis(v: PerAxis, dim: int) -> list[float]:
    """Expand a :data:`PerAxis` value to ``dim`` components (a list is returned as floats, unchanged
    in length: :func:`tether.checks.validate` checks it has ``dim``)."""
    return [float(v)] * dim if not isinstance(v, list) else [float(x) for x in v]



TAKEOFF_MARGIN = 2.0
"""[s] a start's lead leaves a Crazyflie beyond its ``takeoff_time``: the take-off order over the
radio, the climb's last tenth (the plant waits for 90 % of the height) and a busy host's delay."""


def start_lead(m: Mission, lead: float) -> float:
    """The lead [s] from a run's start announcement to tick 0: ``lead``, or longer where a Crazyflie
    takes off in it (its plant takes off on hearing the start, never before: :mod:`plant.node`),
    the largest ``takeoff_time`` plus :data:`TAKEOFF_MARGIN`. Pure."""
    need = [a.plant.takeoff_time + TAKEOFF_MARGIN for a in m.agents if isinstance(a.plant, CrazyfliePlant)]
    return max([lead, *need])


def in_neighbours(m: Mission, agent_id: int) -> list[tuple[int, float]]:
    """The nodes agent ``agent_id`` hears, as ``(node id, a_ij)`` pairs in row order
    (:meth:`Mission.index_of`: agents in file order, the leader last), the order
    ``agent.law.AgentLaw`` sums its neighbours in. Empty for an id that hears nobody."""
    ins = sorted((m.index_of(e.src), e.src, e.weight) for e in m.edges if e.dst == agent_id)
    return [(src, weight) for _, src, weight in ins]


def nearby_vehicles(m: Mission, agent_id: int) -> list[int]:
    """The other agents whose states collision avoidance (``[safety.avoid]``) hears besides agent
    ``agent_id``'s in-neighbours, in file order (none without ``[safety.avoid]``): what the agent
    process subscribes to and what the run's access rules grant it (``deploy/acl.py``)."""
    if m.safety.avoid is None:
        return []
    ins = {j for j, _ in in_neighbours(m, agent_id)}
    return [j for j in m.agent_ids if j != agent_id and j not in ins]


def validate(m: Mission) -> Problems:
    """Every semantic problem of a decoded mission: :func:`tether.checks.validate` (kept here for its
    many callers)."""
    from tether import checks  # checks imports this module's types

    return checks.validate(m)


def unreachable_agents(m: Mission) -> list[int]:
    """Agents with no directed path from the leader: :func:`tether.checks.unreachable_agents`."""
    from tether import checks

    return checks.unreachable_agents(m)


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
