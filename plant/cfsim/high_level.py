"""The simulated Crazyflie's high-level commander: its plans (take-off, landing, go-to, spiral,
uploaded trajectory) and the packets that start them. Pure.

What the firmware keeps in ``crtp_commander_high_level.c`` (packet decoding, the group mask, the
trajectory definitions) and ``planner.c`` (the plan state and its segments) lives here; the
trajectory memory and the evaluation of uploaded polynomials are :mod:`plant.cfsim.trajectory`.
Every tick the vehicle can fly, the firmware asks :meth:`HighLevelCommander.step` for a setpoint
and offers it at priority HIGH_LEVEL.
"""

from __future__ import annotations

import enum
import errno
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

from plant.cfsim import crtp, trajectory
from plant.cfsim.commander import ZERO3, Track, Vec3, finite, vec3
from plant.cfsim.crtp import Packet, Port
from plant.cfsim.services import ParamService
from plant.quadrotor import wrap_angle

GROUP_MASK = "hlCommander.groupmask"
"""The parameter holding the vehicle's group mask (set by ``set_group_mask``)."""


# ------------------------------------------------------------------------------------- plans
def smoothstep7(tau: float) -> tuple[float, float, float]:
    """The rest-to-rest 7th-order polynomial ``s(tau) = 35 tau^4 - 84 tau^5 + 70 tau^6 - 20 tau^7``
    on [0, 1] (zero velocity, acceleration and jerk at both ends) and its first two derivatives
    with respect to ``tau``; clamped outside [0, 1]."""
    if tau <= 0.0:
        return 0.0, 0.0, 0.0
    if tau >= 1.0:
        return 1.0, 0.0, 0.0
    t2, r = tau * tau, 1.0 - tau
    s = t2 * t2 * (35.0 + tau * (-84.0 + tau * (70.0 - 20.0 * tau)))
    ds = 140.0 * t2 * tau * r * r * r
    dds = 420.0 * t2 * r * r * (1.0 - 2.0 * tau)
    return s, ds, dds


@dataclass(frozen=True, slots=True)
class Segment:
    """A straight move from ``p0``/``yaw0`` to ``p1``/``yaw1`` starting at ``t0`` [s] and lasting
    ``duration`` [s], along :func:`smoothstep7` (or at constant speed if ``linear``); at rest
    before and after."""

    t0: float
    duration: float
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    yaw0: float
    yaw1: float
    linear: bool = False

    def finished(self, t: float) -> bool:
        return t >= self.t0 + self.duration

    def eval(self, t: float) -> Track:
        if self.duration <= 0.0 or t >= self.t0 + self.duration:
            return Track(self.p1, ZERO3, ZERO3, self.yaw1)
        tau = max(0.0, (t - self.t0) / self.duration)
        if self.linear:
            s, ds, dds = tau, 1.0, 0.0
        else:
            s, ds, dds = smoothstep7(tau)
        d = [b - a for a, b in zip(self.p0, self.p1)]
        T = self.duration
        pos = vec3(a + di * s for a, di in zip(self.p0, d))
        vel = vec3(di * ds / T for di in d)
        acc = vec3(di * dds / (T * T) for di in d)
        return Track(pos, vel, acc, self.yaw0 + (self.yaw1 - self.yaw0) * s)


@dataclass(frozen=True, slots=True)
class Spiral:
    """The high-level commander's spiral (``spiral(angle, r0, rF, ascent, duration, sideways,
    clockwise)``), started at ``t0`` from position ``p0`` and yaw ``yaw0``.

    The firmware (``planner.c`` ``plan_spiral_from``) fits one 7th-order polynomial to the spiral's
    start and end (position, velocity, acceleration, yaw); this is the spiral itself, which meets
    those same end conditions: the yaw turns at the constant rate ``omz = -sense angle / duration``
    (``sense`` = +1 clockwise, -1 counter-clockwise), the radius goes linearly from ``r0`` to ``rF``
    and the height rises linearly by ``ascent``. The vehicle faces along the path (or, ``sideways``,
    across it). ``angle`` is clamped to [-2 pi, 2 pi], the radii to >= 0, as the firmware does."""

    t0: float
    duration: float
    p0: tuple[float, float, float]
    yaw0: float
    angle: float
    r0: float
    rf: float
    ascent: float
    sideways: bool
    clockwise: bool

    def finished(self, t: float) -> bool:
        return t >= self.t0 + self.duration

    def _axes(self, theta: float) -> tuple[tuple[float, float], tuple[float, float]]:
        s, c = math.sin(theta), math.cos(theta)
        if self.sideways:
            return (-c, -s), (s, -c)
        return (-s, c), (-c, -s)

    def eval(self, t: float) -> Track:
        sense = 1.0 if self.clockwise else -1.0
        angle = max(-2.0 * math.pi, min(2.0 * math.pi, self.angle))
        r0, rf = max(0.0, self.r0), max(0.0, self.rf)
        T = self.duration
        omz, dr, dz = -sense * angle / T, (rf - r0) / T, self.ascent / T
        a0, _ = self._axes(wrap_angle(self.yaw0))
        centre = (self.p0[0] - sense * r0 * a0[0], self.p0[1] - sense * r0 * a0[1])
        tau = min(max(0.0, t - self.t0), T)
        theta = wrap_angle(self.yaw0) + omz * tau
        r = r0 + dr * tau
        (ax, ay), (bx, by) = self._axes(theta)
        pos = (centre[0] + sense * r * ax, centre[1] + sense * r * ay, self.p0[2] + dz * tau)
        if self.finished(t):
            return Track(vec3(pos), ZERO3, ZERO3, theta)
        vel = (sense * (dr * ax + r * omz * bx), sense * (dr * ay + r * omz * by), dz)
        acc = (sense * (2.0 * dr * omz * bx - r * omz * omz * ax), sense * (2.0 * dr * omz * by - r * omz * omz * ay), 0.0)
        return Track(vec3(pos), vec3(vel), vec3(acc), theta)


@dataclass(slots=True)
class Uploaded:
    """An uploaded trajectory (``start_trajectory``) as the planner flies it: the points of
    :class:`plant.cfsim.trajectory.Piecewise`, read from the trajectory memory at every tick.

    A point that is not finite (the memory was rewritten with garbage while the trajectory flew)
    ends the trajectory: the vehicle holds the last good point at rest (the firmware would disable
    its planner and let the watchdog cut the motors)."""

    traj: trajectory.Piecewise
    last: Track
    fault: bool = False
    reported: bool = False

    def finished(self, t: float) -> bool:
        return self.fault or self.traj.finished(t)

    def eval(self, t: float) -> Track:
        if not self.fault:
            pos, vel, acc, yaw = self.traj.point(t)
            if all(math.isfinite(v) for v in (*pos, *vel, *acc, yaw)):
                self.last = Track(pos, vel, acc, yaw)
                return self.last
            self.fault = True
        return Track(self.last.pos, ZERO3, ZERO3, self.last.yaw)


Plan = Segment | Spiral | Uploaded


class HlState(enum.Enum):
    IDLE = "idle"
    """Stopped: offers "motors off" (``plan_is_stopped``)."""
    FLYING = "flying"
    """Following a segment, then hovering at its end."""
    LANDING = "landing"
    """Following a landing segment; idle once it ends."""


# --------------------------------------------------------------------------------- commander
class HighLevelCommander:
    """The planner and its port. Not thread-safe; every call returns immediately.

    Attributes:
        state: what the planner does.
        plan: the present (or last) plan; None until one starts.
        pos, yaw: where the next plan starts [m; world], [rad]: the last setpoint offered, or the
            state estimate while idle.
        ignored: well-formed commands this simulator does not implement.
    """

    def __init__(self, pos: Vec3, yaw: float, memory: trajectory.TrajectoryMemory, params: ParamService,
                 console: Callable[[str], None]) -> None:
        self.state = HlState.IDLE
        self.plan: Plan | None = None
        self.pos, self.yaw = pos, yaw
        self.memory = memory
        """The trajectory memory uploaded trajectories are read from (shared with the mem port)."""
        self.definitions: dict[int, trajectory.Definition] = {}
        """``define_trajectory`` slots (undefined slots are absent)."""
        self.ignored = 0
        self._params = params
        self._console = console

    @property
    def active(self) -> bool:
        """Flying or landing a plan."""
        return self.state in (HlState.FLYING, HlState.LANDING)

    def finished(self, t: float) -> bool:
        """Whether the present plan has ended at ``t`` [s]."""
        return self.plan is not None and self.plan.finished(t)

    def stop(self) -> None:
        """Stop planning (a low-level setpoint took the commander)."""
        self.state = HlState.IDLE

    def hold(self, pos: Vec3, yaw: float) -> None:
        """Start the next plan from ``pos`` [m; world] and ``yaw`` [rad]."""
        self.pos, self.yaw = pos, yaw

    def step(self, t: float) -> Track:
        """The setpoint at ``t`` [s] of a vehicle that is not idle; a landing that ended goes idle."""
        assert self.plan is not None
        ev = self.plan.eval(t)
        plan = self.plan
        if isinstance(plan, Uploaded) and plan.fault and not plan.reported:
            plan.reported = True
            self._console("CFSIM: trajectory point not finite: holding the last good point\n")
        if self.state is HlState.LANDING and plan.finished(t):
            self.state = HlState.IDLE
        self.pos, self.yaw = ev.pos, ev.yaw
        return ev

    # ------------------------------------------------------------------------------ packets
    def handle(self, pkt: Packet, t: float, locked: bool) -> list[Packet]:
        """Answer one high-level commander packet at ``t`` [s]; ``locked``: the supervisor is locked.
        The answer repeats the first three bytes and adds the command's status."""
        d = pkt.data
        ret = self._command(d[0], d, t, locked)
        head = (d[:3] + b"\0\0\0")[:3]
        return [Packet(Port.SETPOINT_HL, pkt.channel, head + bytes((ret,)))]

    def _command(self, cmd: int, d: bytes, t: float, locked: bool) -> int:
        if cmd == crtp.HL_SET_GROUP_MASK:
            self._params.put(GROUP_MASK, struct.unpack("<BB", d)[1])
            return 0
        if cmd == crtp.HL_DEFINE_TRAJECTORY:
            _, ident, location, kind, offset, n_pieces = struct.unpack("<BBBBIB", d)
            if ident >= trajectory.NUM_DEFINITIONS:
                return errno.ENOEXEC
            self.definitions[ident] = trajectory.Definition(location, kind, offset, n_pieces)
            return 0
        group = d[1]
        if group != 0 and not (group & int(self._params.get(GROUP_MASK))):
            return 0
        if cmd == crtp.HL_STOP:
            self.state = HlState.IDLE
            return 0
        if locked:
            return errno.EBUSY
        if cmd in (crtp.HL_TAKEOFF_2, crtp.HL_LAND_2):
            return self._takeoff_or_land(cmd, d, t)
        if cmd == crtp.HL_SPIRAL:
            return self._spiral(d, t)
        if cmd == crtp.HL_GO_TO_2:
            return self._go_to(d, t)
        if cmd in (crtp.HL_START_TRAJECTORY, crtp.HL_START_TRAJECTORY_2):
            if cmd == crtp.HL_START_TRAJECTORY:
                _, _, relative, reverse, ident, scale = struct.unpack("<BBBBBf", d)
                relative_yaw = False
            else:
                _, _, relative, relative_yaw, reverse, ident, scale = struct.unpack("<BBBBBBf", d)
            return self._start_trajectory(t, ident, scale, bool(relative), bool(relative_yaw), bool(reverse))
        self.ignored += 1
        return errno.ENOEXEC

    def _from(self, t: float) -> tuple[Vec3, float]:
        """Where a plan started at ``t`` begins: the hold point while idle, else the present plan's."""
        if self.state is HlState.IDLE:
            return self.pos, self.yaw
        assert self.plan is not None
        ev = self.plan.eval(t)
        return ev.pos, ev.yaw

    def _takeoff_or_land(self, cmd: int, d: bytes, t: float) -> int:
        _, _, height, yaw, use_current, duration = struct.unpack("<BBff?f", d)
        if cmd == crtp.HL_TAKEOFF_2 and self.state is not HlState.IDLE:
            return 1  # plan_takeoff refuses unless stopped
        if cmd == crtp.HL_LAND_2 and self.state is HlState.LANDING:
            return 1
        goal_yaw = self.yaw if use_current else yaw
        start = self.pos
        end = (start[0], start[1], float(height))
        self.plan = Segment(t, float(duration), start, end, self.yaw, self.yaw + wrap_angle(goal_yaw - self.yaw))
        self.state = HlState.FLYING if cmd == crtp.HL_TAKEOFF_2 else HlState.LANDING
        return 0

    def _spiral(self, d: bytes, t: float) -> int:
        _, _, sideways, clockwise, phi, r0, rf, dz, duration = struct.unpack("<BBBBfffff", d)
        finite(phi, r0, rf, dz, duration)
        if duration <= 0.0:
            return errno.EINVAL
        start, yaw0 = self._from(t)
        self.plan = Spiral(t, float(duration), start, yaw0, phi, r0, rf, dz, bool(sideways), bool(clockwise))
        self.state = HlState.FLYING
        return 0

    def _go_to(self, d: bytes, t: float) -> int:
        _, _, relative, linear, x, y, z, yaw, duration = struct.unpack("<BBBBfffff", d)
        start, yaw0 = self._from(t)
        goal = (x, y, z)
        if relative:
            goal = vec3(a + b for a, b in zip(start, goal))
            yaw += yaw0
        self.plan = Segment(t, float(duration), start, goal, yaw0, yaw0 + wrap_angle(yaw - yaw0), bool(linear))
        self.state = HlState.FLYING
        return 0

    def _start_trajectory(self, t: float, ident: int, scale: float, relative: bool, relative_yaw: bool,
                          reverse: bool) -> int:
        """``start_trajectory2``: an undefined id is answered 0 and nothing starts, as in the
        firmware; a definition the firmware would fly out of memory or into non-finite numbers,
        and a time scale that is not a positive number, are refused with EINVAL (and a console line)."""
        d = self.definitions.get(ident) if ident < trajectory.NUM_DEFINITIONS else None
        if d is None or d.location != trajectory.LOCATION_MEM:
            return 0
        if d.kind != trajectory.TYPE_POLY4D:
            self.ignored += 1
            self._console(f"CFSIM: trajectory {ident}: compressed trajectories are not modelled\n")
            return errno.ENOEXEC
        why = trajectory.check(self.memory, d)
        if why is None and not (math.isfinite(scale) and scale > 0.0):
            why = f"time scale {scale} is not a positive number"
        if why is not None:
            self._console(f"CFSIM: trajectory {ident} refused: {why}\n")
            return errno.EINVAL
        traj = trajectory.Piecewise(self.memory, d, t, float(scale), reverse)
        traj.start_from(self.pos, self.yaw, relative, relative_yaw)
        pos, vel, acc, yaw = traj.point(t)
        self.plan = Uploaded(traj, Track(pos, vel, acc, yaw))
        self.state = HlState.FLYING
        return 0
