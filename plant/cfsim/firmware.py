"""The simulated Crazyflie's firmware and world: CRTP in, CRTP out, a quadrotor in between. Pure.

No sockets, no clock, no randomness: :meth:`Firmware.handle` answers one CRTP packet at the present
simulated time, :meth:`Firmware.tick` advances the simulated time by one control period (10 ms) and
returns the log packets that fell due. The vehicle is :class:`plant.quadrotor.Quadrotor` (rigid
body, Eq. 4 and its 500 Hz attitude/rate PID), injected by the caller.

What runs every tick (100 Hz), in the firmware's order (``stabilizer.c``):

1. the high-level commander, if the vehicle can fly, offers its setpoint at priority HIGH_LEVEL
   (a trajectory point while flying or landing, "motors off" while idle);
2. the commander's setpoint is read with its age;
3. the supervisor updates its state from the age and the motors: setpoint older than 0.5 s while
   flying -> level out (roll = pitch = 0, yaw rate 0, thrust kept); older than 2 s -> motors off and
   *locked* until the simulator restarts, as the firmware's supervisor locks until a reboot;
4. the controller turns the (possibly overridden) setpoint into a command of the quadrotor:
   ``command_attitude(T, roll, pitch, yaw_rate)`` for attitude setpoints, ``command(u, yaw)`` with
   ``u = a_ref + Kp (p_ref - p) + Kv (v_ref - v)`` for position setpoints (Eq. 4 inside);
5. the world advances 10 ms: the quadrotor, plus a floor at ``z = 0``;
6. log blocks whose period elapsed are sampled.

Commander semantics (``commander.c``, ``crtp_commander.c``, ``crtp_commander_rpyt.c``): one setpoint
slot with a priority. A low-level setpoint (``send_setpoint``, ``send_stop_setpoint``, position,
velocity, full state) has priority CRTP (2) and stops the high-level planner; the high-level
commander (priority 1) is ignored until ``send_notify_setpoint_stop`` relaxes the priority to 1.
The RPYT thrust is locked at boot until one ``send_setpoint(..., thrust=0)`` arrives.

Conventions at the cflib edge (checked against cflib's ``commander.py`` and the firmware):
``send_setpoint(roll, pitch, yawrate, thrust)`` sends ``(roll, -pitch, yawrate, thrust)``; the
firmware's legacy frame inverts pitch and its RPYT decoder inverts the yaw rate, so in the
right-handed frame of :mod:`plant.quadrotor` (x forward, y left, z up)::

    roll  = +roll_deg      (positive: thrust tilts towards -y)
    pitch = +pitch_deg     (positive: nose down, thrust tilts towards +x)
    yaw rate = -yawrate    (positive cflib yawrate turns clockwise seen from above)

and the logged ``stateEstimate.pitch`` / ``stabilizer.pitch`` are ``-pitch`` (legacy).

Thrust map (crazyflie-firmware ``motors.c`` with battery compensation, the default): a motor
command ``pwm`` in 0..65535 gives ``pwm / 65535 * f_max`` newtons per motor, ``f_max`` being
:attr:`QuadrotorParams.motor_thrust_max` (THRUST_MAX, 0.1125 N for the CF 2.1 propellers). An RPYT
thrust therefore means a collective thrust ``T = 4 f_max pwm / 65535``; RPYT thrust below 1000 is
0 and above 60000 is 60000 (``MIN_THRUST``/``MAX_THRUST`` of the RPYT decoder).
"""

from __future__ import annotations

import enum
import errno
import math
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

from plant.cfsim import crtp, realism, toc, trajectory
from plant.cfsim.crtp import Packet, Port
from plant.quadrotor import Quadrotor, wrap_angle

PERIOD = 0.01
"""Control period [s]: commander, high-level commander, supervisor, position controller and log
scheduling run at 100 Hz; the quadrotor's own attitude loop runs at its 500 Hz inside."""
PERIOD_MS = 10

PWM_FULL = 65535
"""Full-scale motor command [PWM units]."""
RPYT_MIN_THRUST = 1000
RPYT_MAX_THRUST = 60000

WDT_LEVEL_OUT_MS = 500
"""Setpoint age [ms] above which a flying vehicle levels out (COMMANDER_WDT_TIMEOUT_STABILIZE)."""
WDT_SHUTDOWN_MS = 2000
"""Setpoint age [ms] above which a flying vehicle's motors stop and it locks
(COMMANDER_WDT_TIMEOUT_SHUTDOWN)."""
IS_FLYING_HYSTERESIS_MS = 2000
"""The supervisor counts the vehicle as flying until this long [ms] after the motors last ran.
(Ages are counted in whole ticks, as the firmware counts them in whole milliseconds.)"""

_MOTORS_STOPPED = 1e-4
"""A motor below this fraction of the vehicle's weight counts as stopped (motors with a lag decay
towards zero and never reach it)."""

LOG_MAX_BLOCKS = 16
LOG_MAX_OPS = 128
LOG_MAX_LEN = 26
"""Largest log block payload [bytes] (30 minus block id and 3-byte timestamp)."""


def pwm_to_thrust(pwm: float, motor_thrust_max: float) -> float:
    """Collective thrust [N] of four motors commanded at ``pwm`` [0..65535]."""
    return 4.0 * motor_thrust_max * pwm / PWM_FULL


def thrust_to_pwm(thrust: float, motor_thrust_max: float) -> float:
    """The PWM command [0..65535, not clipped] that gives collective thrust ``thrust`` [N]."""
    return thrust * PWM_FULL / (4.0 * motor_thrust_max)


# ------------------------------------------------------------------------------------ setpoints
@dataclass(frozen=True, slots=True)
class Off:
    """Motors off (the firmware's null setpoint)."""


@dataclass(frozen=True, slots=True)
class Attitude:
    """An RPYT setpoint in the right-handed frame: thrust [PWM units], roll and pitch [rad; Z-Y-X],
    yaw rate [rad/s; about world z, counter-clockwise positive]."""

    thrust_pwm: float
    roll: float
    pitch: float
    yaw_rate: float


Vec3 = tuple[float, float, float]
"""A 3-vector [world frame] as the firmware's setpoints hold it."""


def vec3(xs: Iterable[float]) -> Vec3:
    """``xs`` (exactly three numbers) as a :data:`Vec3`; ValueError otherwise."""
    x, y, z = xs
    return (float(x), float(y), float(z))


@dataclass(frozen=True, slots=True)
class Track:
    """A position setpoint: position [m], velocity [m/s], acceleration [m/s^2] (world frame) and
    yaw [rad]."""

    pos: tuple[float, float, float]
    vel: tuple[float, float, float]
    acc: tuple[float, float, float]
    yaw: float


@dataclass(frozen=True, slots=True)
class Velocity:
    """A velocity setpoint [m/s; world frame] with a yaw rate [rad/s; counter-clockwise positive]."""

    vel: tuple[float, float, float]
    yaw_rate: float


@dataclass(frozen=True, slots=True)
class Hover:
    """A hover setpoint (``send_hover_setpoint``): velocity [m/s] in the body's yaw frame (x forward,
    y left), absolute height [m] and yaw rate [rad/s; counter-clockwise positive]."""

    vx_body: float
    vy_body: float
    z: float
    yaw_rate: float


@dataclass(frozen=True, slots=True)
class ZHold:
    """A z-distance setpoint (``send_zdistance_setpoint``): roll and pitch [rad; right-handed Z-Y-X],
    absolute height [m] and yaw rate [rad/s; counter-clockwise positive]."""

    roll: float
    pitch: float
    z: float
    yaw_rate: float


@dataclass(frozen=True, slots=True)
class Manual:
    """A manual setpoint (``send_setpoint_manual``): thrust [PWM units]; roll and pitch [rad] or,
    with ``rate``, roll and pitch rates [rad/s] (right-handed); yaw rate [rad/s; counter-clockwise]."""

    thrust_pwm: float
    roll: float
    pitch: float
    yaw_rate: float
    rate: bool


Setpoint = Off | Attitude | Track | Velocity | Hover | ZHold | Manual
OFF = Off()
_ZERO3 = (0.0, 0.0, 0.0)


class Priority(enum.IntEnum):
    """Commander priorities (``commander.h``)."""

    DISABLE = 0
    HIGH_LEVEL = 1
    """Also COMMANDER_PRIORITY_LOWEST, what ``notify_setpoint_stop`` relaxes to."""
    CRTP = 2


# ------------------------------------------------------------------------------- trajectories
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
            return Track(self.p1, _ZERO3, _ZERO3, self.yaw1)
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
            return Track(vec3(pos), _ZERO3, _ZERO3, theta)
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
        return Track(self.last.pos, _ZERO3, _ZERO3, self.last.yaw)


Plan = Segment | Spiral | Uploaded


class HlState(enum.Enum):
    IDLE = "idle"
    """Stopped: offers "motors off" (``plan_is_stopped``)."""
    FLYING = "flying"
    """Following a segment, then hovering at its end."""
    LANDING = "landing"
    """Following a landing segment; idle once it ends."""


class SupState(enum.Enum):
    READY = "ready"
    """Armed, on the ground or at least not flying."""
    FLYING = "flying"
    LEVEL_OUT = "level_out"
    """Setpoint older than 0.5 s while flying: roll and pitch forced to 0."""
    LOCKED = "locked"
    """Setpoint older than 2 s while flying, or an emergency stop: motors off for good."""


# Supervisor bitfield (crtp_supervisor; cflib supervisor.py).
BIT_CAN_BE_ARMED, BIT_ARMED, BIT_AUTO_ARMED, BIT_CAN_FLY, BIT_FLYING = 0, 1, 2, 3, 4
BIT_TUMBLED, BIT_LOCKED, BIT_CRASHED, BIT_HL_ACTIVE, BIT_HL_FINISHED, BIT_HL_DISABLED = 5, 6, 7, 8, 9, 10

# Command codes.
LOG_CREATE, LOG_APPEND, LOG_DELETE, LOG_START, LOG_STOP, LOG_RESET = 0, 1, 2, 3, 4, 5
LOG_CREATE_V2, LOG_APPEND_V2, LOG_START_V2 = 6, 7, 8
PARAM_MISC_SETBYNAME, PARAM_MISC_GET_EXTENDED_TYPE_V2, PARAM_MISC_GET_DEFAULT_V2 = 0, 7, 8
PARAM_MISC_PERSISTENT_STORE, PARAM_MISC_PERSISTENT_GET_STATE, PARAM_MISC_PERSISTENT_CLEAR = 3, 4, 5
MEM_INFO_VER, MEM_INFO_NBR, MEM_INFO_DETAILS = 0, 1, 2
MEM_READ_CHANNEL, MEM_WRITE_CHANNEL = 1, 2
MEM_TRAJ_ID = 0
"""The trajectory memory's id: the only memory of the simulated vehicle."""
HL_SET_GROUP_MASK, HL_STOP, HL_TAKEOFF_2, HL_LAND_2, HL_SPIRAL, HL_GO_TO_2 = 0, 3, 7, 8, 11, 12
HL_START_TRAJECTORY, HL_DEFINE_TRAJECTORY, HL_START_TRAJECTORY_2 = 5, 6, 13
GENERIC_STOP, GENERIC_FULL_STATE, GENERIC_POSITION, GENERIC_VELOCITY_WORLD = 0, 6, 7, 8
GENERIC_VELOCITY_WORLD_LEGACY, GENERIC_ZDISTANCE_LEGACY, GENERIC_HOVER_LEGACY = 1, 2, 5
GENERIC_ZDISTANCE, GENERIC_HOVER, GENERIC_MANUAL = 9, 10, 11
META_NOTIFY_SETPOINT_STOP = 0
PLATFORM_VERSION_PROTOCOL, PLATFORM_VERSION_FIRMWARE, PLATFORM_VERSION_DEVICE = 0, 1, 2
PLATFORM_ARM, PLATFORM_RECOVER, PLATFORM_NOTIFY = 1, 2, 3
SUPERVISOR_GET_STATE_BITFIELD = 0x0C
SUPERVISOR_ARM, SUPERVISOR_RECOVER, SUPERVISOR_EMERGENCY_STOP = 0x01, 0x02, 0x03
SUPERVISOR_RESPONSE = 0x80


@dataclass(frozen=True)
class FirmwareConfig:
    """Per-vehicle settings of the simulated firmware and its world (copied on construction)."""

    instance: int = 0
    """Index of the vehicle in its launch (read-only param ``cfsim.instance``)."""
    kp: tuple[float, float, float] = (6.25, 6.25, 9.0)
    """Position gains [1/s^2] of the onboard position controller (x, y, z)."""
    kv: tuple[float, float, float] = (5.0, 5.0, 6.0)
    """Velocity gains [1/s] of the position controller; critically damped with ``kp``."""
    kv_velocity_mode: tuple[float, float, float] = (4.0, 4.0, 4.0)
    """Velocity gains [1/s] for velocity setpoints."""
    floor_frequency: float = 15.0
    """Natural frequency [Hz] of the floor's contact spring (with the vehicle's mass)."""
    floor_damping: float = 1.0
    """Damping ratio of the floor's contact spring; the same viscous coefficient brakes sliding."""
    contact_step: float = 0.002
    """Step [s] of the world near and on the floor (the contact force is held over a step)."""
    vbat: float = 3.9
    """Battery voltage [V] reported in ``pm.vbat`` without a battery model."""
    noise: realism.NoiseConfig | None = None
    """Estimator noise on the state estimate the controller flies on and the logs report (off: the
    estimate is the truth)."""
    battery: realism.BatteryConfig | None = None
    """A battery that drains with thrust (off: ``pm.vbat`` is the constant :attr:`vbat`)."""
    tilt_max_manual: float = math.radians(30.0)
    """Largest roll/pitch [rad] that integrated manual rate setpoints reach."""


@dataclass
class LogBlock:
    ident: int
    ops: list[tuple[int, toc.CType]] = field(default_factory=list)
    """(variable index, fetch type) in packet order."""
    period_ms: int | None = None
    """None while stopped; 0 = send once."""
    next_due_ms: int = 0

    @property
    def length(self) -> int:
        return sum(ct.size for _, ct in self.ops)


class Firmware:
    """One simulated Crazyflie: its firmware state and its vehicle. Not thread-safe; every call
    returns immediately.

    Attributes:
        k: control ticks since boot; the simulated time is ``k * PERIOD`` [s].
        dropped: packets that could not be decoded (too short, wrong length, unknown ids).
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self, quad: Quadrotor, cfg: FirmwareConfig | None = None) -> None:
        self.quad = quad
        self.cfg = cfg if cfg is not None else FirmwareConfig()
        # realism
        self.noise = realism.EstimatorNoise(self.cfg.noise, PERIOD) if self.cfg.noise is not None else None
        self.battery = realism.Battery(self.cfg.battery) if self.cfg.battery is not None else None
        self._fmax = quad.params.motor_thrust_max
        self._g = quad.params.g
        self.k = 0
        self.dropped = 0
        self.ignored = 0
        # TOCs and parameter values
        self._log_items = toc.log_items(toc.LOG_VARS)
        self._param_items = toc.param_items(toc.PARAM_VARS)
        self._param_index = {v.full_name: i for i, v in enumerate(toc.PARAM_VARS)}
        self._persistent: dict[int, float] = {}
        """Values stored by ``persistent_store`` (the firmware's EEPROM), by parameter index."""
        self._params: list[float] = [v.default for v in toc.PARAM_VARS]
        self._params[self._param_index["cfsim.instance"]] = self.cfg.instance
        self._params[self._param_index["cfsim.mass"]] = quad.mass
        self._params[self._param_index["cfsim.hoverPwm"]] = round(thrust_to_pwm(quad.mass * self._g, self._fmax))
        self._blocks: dict[int, LogBlock] = {}
        # commander
        self._priority = Priority.DISABLE
        self._setpoint: Setpoint = OFF
        self._stamp_ms = 0
        """Time [ms since boot] the setpoint in the slot was set."""
        self._thrust_locked = True
        # high-level commander
        self._hl = HlState.IDLE
        self._segment: Plan | None = None
        self._hl_pos = vec3(self.est_p)
        self._hl_yaw = quad.euler()[2]
        self.traj_mem = trajectory.TrajectoryMemory()
        self._traj_defs: dict[int, trajectory.Definition] = {}
        """``define_trajectory`` slots (undefined slots are absent)."""
        # supervisor
        self._sup = SupState.READY
        self._armed = True
        self._last_thrust_ms: int | None = None
        # controller
        self._vel_yaw: float | None = None
        self._applied: Setpoint = OFF
        self._accel = np.zeros(3)
        self._manual_att = (0.0, 0.0)
        """Roll and pitch [rad] integrated from manual rate setpoints."""
        self._console: bytearray = bytearray()
        self.console_lines: list[str] = []
        """Every console line printed since boot (also sent to the client on the console port)."""
        # floor
        m = quad.mass
        w = 2.0 * math.pi * self.cfg.floor_frequency
        self._k_floor = m * w * w
        self._c_floor = 2.0 * self.cfg.floor_damping * m * w
        self._z_contact = m * self._g / self._k_floor
        """The floor spring is preloaded so that a vehicle at rest on it sits at z = 0."""

    # ---------------------------------------------------------------------------- reading
    @property
    def t(self) -> float:
        """Simulated time since boot [s]."""
        return self.k * PERIOD

    @property
    def est_p(self) -> np.ndarray:
        """The position estimate [m; world]: the truth plus the estimator's error, if modelled."""
        return self.quad.p if self.noise is None else self.quad.p + self.noise.position

    @property
    def est_v(self) -> np.ndarray:
        """The velocity estimate [m/s; world]."""
        return self.quad.v if self.noise is None else self.quad.v + self.noise.velocity

    def console_print(self, text: str) -> None:
        """Print ``text`` on the console (CRTP port 0): sent to the client with the next tick."""
        self._console += text.encode("ascii", "replace")
        self.console_lines.extend(line for line in text.splitlines() if line)

    def _console_packets(self) -> list[Packet]:
        out = []
        while self._console:
            chunk, self._console = bytes(self._console[:crtp.MAX_DATA]), self._console[crtp.MAX_DATA:]
            out.append(Packet(Port.CONSOLE, 0, chunk))
        return out

    @property
    def supervisor_state(self) -> SupState:
        return self._sup

    @property
    def hl_state(self) -> HlState:
        return self._hl

    @property
    def can_fly(self) -> bool:
        return self._armed and self._sup is not SupState.LOCKED

    def supervisor_bits(self) -> int:
        bits = (1 << BIT_AUTO_ARMED)
        if self._armed:
            bits |= 1 << BIT_ARMED
        elif self._sup is not SupState.LOCKED:
            bits |= 1 << BIT_CAN_BE_ARMED
        if self.can_fly:
            bits |= 1 << BIT_CAN_FLY
        if self._sup in (SupState.FLYING, SupState.LEVEL_OUT):
            bits |= 1 << BIT_FLYING
        if self._sup is SupState.LOCKED:
            bits |= 1 << BIT_LOCKED
        if self._hl in (HlState.FLYING, HlState.LANDING) and self._priority <= Priority.HIGH_LEVEL:
            bits |= 1 << BIT_HL_ACTIVE
        if self._segment is not None and self._segment.finished(self.t):
            bits |= 1 << BIT_HL_FINISHED
        return bits

    def param(self, full_name: str) -> float:
        """A parameter's present value (raises ``KeyError`` for an unknown name)."""
        return self._params[self._param_index[full_name]]

    # ----------------------------------------------------------------------------- packets
    def handle(self, pkt: Packet) -> list[Packet]:
        """Answer one packet at the present simulated time; returns the replies (maybe none).
        Malformed packets are counted in :attr:`dropped` and answered with nothing."""
        handler = self._handlers.get(pkt.port)
        if handler is None:
            self.ignored += 1
            return []
        try:
            return handler(self, pkt)
        except (struct.error, IndexError, UnicodeDecodeError, ValueError):
            self.dropped += 1
            return []

    def _link(self, pkt: Packet) -> list[Packet]:
        if pkt.channel == crtp.LINK_ECHO_CHANNEL:
            return [pkt]
        if pkt.channel == crtp.LINK_SOURCE_CHANNEL:
            return [Packet(Port.LINKCTRL, crtp.LINK_SOURCE_CHANNEL, b"Bitcraze Crazyflie".ljust(crtp.MAX_DATA, b"\0"))]
        if pkt.is_null:
            return [Packet(0xF, 3)]  # cflib's scan probe: any answer will do
        return []  # sink: swallowed

    def _platform(self, pkt: Packet) -> list[Packet]:
        ch, d = pkt.channel, pkt.data
        if ch == crtp.PLATFORM_VERSION_CHANNEL:
            cmd = d[0]
            if cmd == PLATFORM_VERSION_PROTOCOL:
                return [Packet(Port.PLATFORM, ch, struct.pack("<Bi", cmd, crtp.PROTOCOL_VERSION))]
            if cmd == PLATFORM_VERSION_FIRMWARE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.FIRMWARE_TAG.encode())]
            if cmd == PLATFORM_VERSION_DEVICE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.DEVICE_TYPE.encode())]
            self.ignored += 1
            return []
        if ch == crtp.PLATFORM_COMMAND_CHANNEL:
            cmd = d[0]
            if cmd == PLATFORM_ARM:
                ok = self._request_arming(bool(d[1]))
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, self._armed)))]
            if cmd == PLATFORM_RECOVER:
                ok = self._sup is not SupState.LOCKED
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, 1)))]
            if cmd == PLATFORM_NOTIFY:
                return [Packet(Port.PLATFORM, ch)]
            return [pkt]  # continuous wave and the rest: echoed, as the firmware does
        self.ignored += 1
        return []

    def _supervisor(self, pkt: Packet) -> list[Packet]:
        cmd = pkt.data[0]
        if pkt.channel == crtp.SUPERVISOR_INFO_CHANNEL and cmd == SUPERVISOR_GET_STATE_BITFIELD:
            return [Packet(Port.SUPERVISOR, pkt.channel, struct.pack("<BH", cmd | SUPERVISOR_RESPONSE,
                                                                     self.supervisor_bits()))]
        if pkt.channel == crtp.SUPERVISOR_COMMAND_CHANNEL:
            if cmd == SUPERVISOR_ARM:
                ok = self._request_arming(bool(pkt.data[1]))
                return [Packet(Port.SUPERVISOR, pkt.channel, bytes((cmd | SUPERVISOR_RESPONSE, ok, self._armed)))]
            if cmd == SUPERVISOR_RECOVER:
                ok = self._sup is not SupState.LOCKED
                return [Packet(Port.SUPERVISOR, pkt.channel, bytes((cmd | SUPERVISOR_RESPONSE, ok, 1)))]
            if cmd == SUPERVISOR_EMERGENCY_STOP:
                self._lock()
                return []
        self.ignored += 1
        return []

    def _request_arming(self, arm: bool) -> bool:
        if self._sup is SupState.LOCKED:
            return False
        self._armed = arm
        if not arm:
            self._sup = SupState.READY
        return True

    def _lock(self) -> None:
        self._sup = SupState.LOCKED

    def _mem(self, pkt: Packet) -> list[Packet]:
        """The memory port (``crtp_mem.c``) with one memory: the trajectory memory, id 0.

        The firmware asserts (and reboots) on an unknown memory id and overruns its packet on a
        read longer than a packet can carry; the simulator answers those with EIO instead."""
        ch, d = pkt.channel, pkt.data
        if ch == crtp.MEM_INFO_CHANNEL:
            cmd = d[0]
            if cmd == MEM_INFO_NBR:
                return [Packet(Port.MEM, ch, bytes((cmd, 1)))]
            if cmd == MEM_INFO_DETAILS and d[1] == MEM_TRAJ_ID:
                body = struct.pack("<BBBI", cmd, MEM_TRAJ_ID, trajectory.MEM_TYPE_TRAJ, trajectory.MEMORY_SIZE)
                return [Packet(Port.MEM, ch, body + bytes(8))]  # no serial number: 8 zero bytes
            if cmd == MEM_INFO_VER:
                return [Packet(Port.MEM, ch, bytes((cmd, 1)))]
            self.ignored += 1
            return []
        if ch == MEM_READ_CHANNEL:
            mem_id, addr, length = struct.unpack("<BIB", d)
            data = self.traj_mem.read(addr, length) if mem_id == MEM_TRAJ_ID and length <= trajectory.MEM_MAX_READ \
                else None
            if data is None:
                return [Packet(Port.MEM, ch, d[:5] + bytes((errno.EIO,)))]
            return [Packet(Port.MEM, ch, d[:5] + b"\0" + data)]
        if ch == MEM_WRITE_CHANNEL:
            mem_id, addr = struct.unpack_from("<BI", d)
            ok = mem_id == MEM_TRAJ_ID and self.traj_mem.write(addr, d[5:])
            return [Packet(Port.MEM, ch, d[:5] + bytes((0 if ok else errno.EIO,)))]
        self.ignored += 1
        return []

    # log port
    def _log(self, pkt: Packet) -> list[Packet]:
        ch, d = pkt.channel, pkt.data
        if ch == crtp.TOC_CHANNEL:
            return self._toc(Port.LOG, d, self._log_items,
                             extra=bytes((LOG_MAX_BLOCKS, LOG_MAX_OPS)))
        if ch != crtp.LOG_SETTINGS_CHANNEL:
            self.ignored += 1
            return []
        cmd = d[0]
        ident = d[1] if len(d) > 1 else 0
        if cmd in (LOG_CREATE, LOG_CREATE_V2, LOG_APPEND, LOG_APPEND_V2):
            ret = self._log_add(cmd, ident, d[2:])
        elif cmd == LOG_DELETE:
            ret = 0 if self._blocks.pop(ident, None) is not None else errno.ENOENT
        elif cmd in (LOG_START, LOG_START_V2):
            period = d[2] * 10 if cmd == LOG_START else struct.unpack_from("<H", d, 2)[0]
            ret = self._log_start(ident, period)
        elif cmd == LOG_STOP:
            block = self._blocks.get(ident)
            if block is not None:
                block.period_ms = None
            ret = 0 if block is not None else errno.ENOENT
        elif cmd == LOG_RESET:
            self._blocks.clear()
            ret = 0
        else:
            ret = errno.ENOEXEC
        return [Packet(Port.LOG, ch, bytes((cmd, ident, ret)))]

    def _log_add(self, cmd: int, ident: int, ops: bytes) -> int:
        create = cmd in (LOG_CREATE, LOG_CREATE_V2)
        if create:
            if ident in self._blocks:
                return errno.EEXIST
            if len(self._blocks) >= LOG_MAX_BLOCKS:
                return errno.ENOMEM
            self._blocks[ident] = LogBlock(ident)
        block = self._blocks.get(ident)
        if block is None:
            return errno.ENOENT
        v2 = cmd in (LOG_CREATE_V2, LOG_APPEND_V2)
        width = 3 if v2 else 2
        if len(ops) % width:
            raise ValueError("truncated log operation")
        n_ops = sum(len(b.ops) for b in self._blocks.values())
        for i in range(0, len(ops), width):
            type_byte = ops[i]
            var = struct.unpack_from("<H", ops, i + 1)[0] if v2 else ops[i + 1]
            fetch = toc.LOG_TYPES.get(type_byte & 0x0F)
            if fetch is None or var >= len(toc.LOG_VARS):
                return errno.ENOENT  # also raw-memory variables (id 0xFFFF): there is no memory here
            if block.length + fetch.size > LOG_MAX_LEN:
                return errno.E2BIG
            if n_ops >= LOG_MAX_OPS:
                return errno.ENOMEM
            block.ops.append((var, fetch))
            n_ops += 1
        return 0

    def _log_start(self, ident: int, period_ms: int) -> int:
        block = self._blocks.get(ident)
        if block is None:
            return errno.ENOENT
        block.period_ms = period_ms
        block.next_due_ms = self.k * PERIOD_MS + period_ms
        return 0

    def _toc(self, port: Port, d: bytes, items: list[bytes], extra: bytes = b"") -> list[Packet]:
        cmd = d[0]
        if cmd == crtp.TOC_INFO_V2:
            return [Packet(port, crtp.TOC_CHANNEL, toc.info_payload(items) + extra)]
        if cmd == crtp.TOC_ITEM_V2:
            ident = struct.unpack_from("<H", d, 1)[0]
            if ident < len(items):
                return [Packet(port, crtp.TOC_CHANNEL, items[ident])]
            return [Packet(port, crtp.TOC_CHANNEL, bytes((cmd,)))]
        self.ignored += 1  # the v1 TOC commands (protocol < 4) are not served
        return []

    # param port
    def _param(self, pkt: Packet) -> list[Packet]:
        ch, d = pkt.channel, pkt.data
        if ch == crtp.TOC_CHANNEL:
            return self._toc(Port.PARAM, d, self._param_items)
        if ch == crtp.PARAM_READ_CHANNEL:
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(toc.PARAM_VARS):
                return [Packet(Port.PARAM, ch, d[:2] + bytes((errno.ENOENT,)))]
            raw = toc.pack_value(toc.PARAM_VARS[ident].ctype, self._params[ident])
            return [Packet(Port.PARAM, ch, d[:2] + b"\0" + raw)]
        if ch == crtp.PARAM_WRITE_CHANNEL:
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(toc.PARAM_VARS):
                return [Packet(Port.PARAM, ch, d[:2] + bytes((errno.ENOENT,)))]
            var = toc.PARAM_VARS[ident]
            if var.read_only:
                return []  # the firmware does not answer writes of read-only parameters
            self._set_param(ident, toc.unpack_value(var.ctype, d[2:]))
            return [pkt]
        if ch == crtp.PARAM_MISC_CHANNEL:
            return self._param_misc(d)
        self.ignored += 1
        return []

    def _param_misc(self, d: bytes) -> list[Packet]:
        cmd = d[0]
        if cmd == PARAM_MISC_SETBYNAME:
            end_group = d.index(0, 1)
            end_name = d.index(0, end_group + 1)
            name = d[1:end_group].decode("ascii") + "." + d[end_group + 1:end_name].decode("ascii")
            type_byte = d[end_name + 1]
            ident = self._param_index.get(name)
            if ident is None:
                err = errno.ENOENT
            elif type_byte != toc.PARAM_VARS[ident].ctype.code:
                err = errno.EINVAL
            elif toc.PARAM_VARS[ident].read_only:
                err = errno.EACCES
            else:
                self._set_param(ident, toc.unpack_value(toc.PARAM_VARS[ident].ctype, d[end_name + 2:]))
                err = 0
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, d[:end_name + 1] + bytes((err,)))]
        if cmd in (PARAM_MISC_GET_EXTENDED_TYPE_V2, PARAM_MISC_GET_DEFAULT_V2):
            ident = struct.unpack_from("<H", d, 1)[0]
            head = d[:3]
            if cmd == PARAM_MISC_GET_DEFAULT_V2 and ident < len(toc.PARAM_VARS):
                var = toc.PARAM_VARS[ident]
                default = self._params[ident] if var.read_only else var.default
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0" + toc.pack_value(var.ctype, default))]
            if cmd == PARAM_MISC_GET_EXTENDED_TYPE_V2 and ident < len(toc.PARAM_VARS) \
                    and toc.PARAM_VARS[ident].persistent:
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((0, toc.EXTENDED_PERSISTENT)))]
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((errno.ENOENT,)))]
        if cmd in (PARAM_MISC_PERSISTENT_STORE, PARAM_MISC_PERSISTENT_GET_STATE, PARAM_MISC_PERSISTENT_CLEAR):
            ident = struct.unpack_from("<H", d, 1)[0]
            head = d[:3]
            if ident >= len(toc.PARAM_VARS) or not toc.PARAM_VARS[ident].persistent:
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((errno.ENOENT,)))]
            var = toc.PARAM_VARS[ident]
            if cmd == PARAM_MISC_PERSISTENT_STORE:
                self._persistent[ident] = self._params[ident]
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0")]
            if cmd == PARAM_MISC_PERSISTENT_CLEAR:
                self._persistent.pop(ident, None)
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0")]
            stored = self._persistent.get(ident)
            body = toc.pack_value(var.ctype, var.default)
            if stored is None:
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0" + body)]
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\1" + body + toc.pack_value(var.ctype, stored))]
        self.ignored += 1
        return []

    def _set_param(self, ident: int, value: float) -> None:
        var = toc.PARAM_VARS[ident]
        if not math.isfinite(value):
            raise ValueError(f"{var.full_name}: non-finite value")
        self._params[ident] = value
        if var.full_name == "stabilizer.stop" and value:
            self._lock()
        elif var.full_name == "kalman.resetEstimation" and value:
            if self.noise is not None:
                self.noise.reset()
            self.console_print("CFSIM: state estimate reset\n")

    # commander ports
    def _commander(self, pkt: Packet) -> list[Packet]:
        if pkt.channel != 0:
            self.ignored += 1
            return []
        roll, pitch, yaw, thrust = struct.unpack("<fffH", pkt.data)
        if self._priority == Priority.DISABLE:
            self._thrust_locked = True
        if thrust == 0:
            self._thrust_locked = False
        pwm = 0.0 if self._thrust_locked or thrust < RPYT_MIN_THRUST else float(min(thrust, RPYT_MAX_THRUST))
        # legacy frame: pitch arrives inverted (cflib sent -pitch); yaw rate input is inverted
        _finite(roll, pitch, yaw)
        sp = Attitude(pwm, math.radians(roll), -math.radians(pitch), -math.radians(yaw))
        self._set_setpoint(sp, Priority.CRTP)
        return []

    def _commander_generic(self, pkt: Packet) -> list[Packet]:
        d = pkt.data
        if pkt.channel == crtp.GENERIC_META_CHANNEL:
            if d[0] == META_NOTIFY_SETPOINT_STOP:
                struct.unpack("<BI", d)  # remain-valid milliseconds: unused, as in the firmware
                self._relax_priority()
            else:
                self.ignored += 1
            return []
        if pkt.channel != crtp.GENERIC_SETPOINT_CHANNEL:
            self.ignored += 1
            return []
        kind = d[0]
        sp: Setpoint
        if kind == GENERIC_STOP:
            sp = OFF
        elif kind == GENERIC_POSITION:
            _, x, y, z, yaw = struct.unpack("<Bffff", d)
            _finite(x, y, z, yaw)
            sp = Track((x, y, z), _ZERO3, _ZERO3, math.radians(yaw))
        elif kind in (GENERIC_VELOCITY_WORLD, GENERIC_VELOCITY_WORLD_LEGACY):
            _, vx, vy, vz, yaw_rate = struct.unpack("<Bffff", d)
            _finite(vx, vy, vz, yaw_rate)
            sign = -1.0 if kind == GENERIC_VELOCITY_WORLD_LEGACY else 1.0  # legacy yaw rate is inverted
            sp = Velocity((vx, vy, vz), sign * math.radians(yaw_rate))
        elif kind in (GENERIC_HOVER, GENERIC_HOVER_LEGACY):
            _, vx, vy, yaw_rate, z = struct.unpack("<Bffff", d)
            _finite(vx, vy, yaw_rate, z)
            sign = -1.0 if kind == GENERIC_HOVER_LEGACY else 1.0
            sp = Hover(vx, vy, z, sign * math.radians(yaw_rate))
        elif kind in (GENERIC_ZDISTANCE, GENERIC_ZDISTANCE_LEGACY):
            # roll and pitch arrive as the user gave them (no -pitch here, unlike send_setpoint), and
            # the firmware reads pitch in its legacy frame: positive pitch raises the nose
            _, roll, pitch, yaw_rate, z = struct.unpack("<Bffff", d)
            _finite(roll, pitch, yaw_rate, z)
            sign = -1.0 if kind == GENERIC_ZDISTANCE_LEGACY else 1.0
            sp = ZHold(math.radians(roll), -math.radians(pitch), z, sign * math.radians(yaw_rate))
        elif kind == GENERIC_MANUAL:
            # cflib sends -pitch, as for send_setpoint; thrust 10001..60000 for 0..100 %; no thrust lock
            _, roll, pitch, yaw_rate, thrust, rate = struct.unpack("<BfffHB", d)
            _finite(roll, pitch, yaw_rate)
            pwm = 0.0 if thrust < RPYT_MIN_THRUST else float(min(thrust, RPYT_MAX_THRUST))
            sp = Manual(pwm, math.radians(roll), -math.radians(pitch), math.radians(yaw_rate), bool(rate))
        elif kind == GENERIC_FULL_STATE:
            v = struct.unpack("<BhhhhhhhhhIhhh", d)
            mm = [c / 1000.0 for c in v[1:10]]
            qx, qy, qz, qw = decompress_quaternion(v[10])
            yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
            sp = Track(tuple(mm[0:3]), tuple(mm[3:6]), tuple(mm[6:9]), yaw)
        else:
            self.ignored += 1
            return []
        self._set_setpoint(sp, Priority.CRTP)
        return []

    def _set_setpoint(self, sp: Setpoint, priority: Priority) -> bool:
        """``commanderSetSetpoint``: accepted if ``priority`` is at least the active one; a
        low-level setpoint stops the high-level planner."""
        if priority < self._priority:
            return False
        self._setpoint, self._priority, self._stamp_ms = sp, priority, self.k * PERIOD_MS
        if priority > Priority.HIGH_LEVEL:
            self._hl = HlState.IDLE
        return True

    def _relax_priority(self) -> None:
        """``commanderRelaxPriority``: the high-level commander takes over from the present state."""
        self._hl_pos = vec3(self.est_p)
        self._hl_yaw = self.quad.euler()[2]
        self._priority = Priority.HIGH_LEVEL

    # high-level commander
    def _high_level(self, pkt: Packet) -> list[Packet]:
        d = pkt.data
        cmd = d[0]
        ret = self._hl_command(cmd, d)
        head = (d[:3] + b"\0\0\0")[:3]
        return [Packet(Port.SETPOINT_HL, pkt.channel, head + bytes((ret,)))]

    def _hl_command(self, cmd: int, d: bytes) -> int:
        gi = self._param_index["hlCommander.groupmask"]
        if cmd == HL_SET_GROUP_MASK:
            self._params[gi] = struct.unpack("<BB", d)[1]
            return 0
        if cmd == HL_DEFINE_TRAJECTORY:
            _, ident, location, kind, offset, n_pieces = struct.unpack("<BBBBIB", d)
            if ident >= trajectory.NUM_DEFINITIONS:
                return errno.ENOEXEC
            self._traj_defs[ident] = trajectory.Definition(location, kind, offset, n_pieces)
            return 0
        group = d[1]
        if group != 0 and not (group & int(self._params[gi])):
            return 0
        t = self.t
        if cmd == HL_STOP:
            self._hl = HlState.IDLE
            return 0
        if self._sup is SupState.LOCKED:
            return errno.EBUSY
        if cmd in (HL_TAKEOFF_2, HL_LAND_2):
            _, _, height, yaw, use_current, duration = struct.unpack("<BBff?f", d)
            if cmd == HL_TAKEOFF_2 and self._hl is not HlState.IDLE:
                return 1  # plan_takeoff refuses unless stopped
            if cmd == HL_LAND_2 and self._hl is HlState.LANDING:
                return 1
            goal_yaw = self._hl_yaw if use_current else yaw
            start = self._hl_pos
            end = (start[0], start[1], float(height))
            self._segment = Segment(t, float(duration), start, end, self._hl_yaw,
                                    self._hl_yaw + wrap_angle(goal_yaw - self._hl_yaw))
            self._hl = HlState.FLYING if cmd == HL_TAKEOFF_2 else HlState.LANDING
            return 0
        if cmd == HL_SPIRAL:
            _, _, sideways, clockwise, phi, r0, rf, dz, duration = struct.unpack("<BBBBfffff", d)
            _finite(phi, r0, rf, dz, duration)
            if duration <= 0.0:
                return errno.EINVAL
            if self._hl is HlState.IDLE:
                start, yaw0 = self._hl_pos, self._hl_yaw
            else:
                assert self._segment is not None
                ev = self._segment.eval(t)
                start, yaw0 = ev.pos, ev.yaw
            self._segment = Spiral(t, float(duration), start, yaw0, phi, r0, rf, dz, bool(sideways), bool(clockwise))
            self._hl = HlState.FLYING
            return 0
        if cmd == HL_GO_TO_2:
            _, _, relative, linear, x, y, z, yaw, duration = struct.unpack("<BBBBfffff", d)
            if self._hl is HlState.IDLE:
                start, yaw0 = self._hl_pos, self._hl_yaw
            else:
                assert self._segment is not None
                ev = self._segment.eval(t)
                start, yaw0 = ev.pos, ev.yaw
            goal = (x, y, z)
            if relative:
                goal = vec3(a + b for a, b in zip(start, goal))
                yaw += yaw0
            self._segment = Segment(t, float(duration), start, goal, yaw0,
                                    yaw0 + wrap_angle(yaw - yaw0), bool(linear))
            self._hl = HlState.FLYING
            return 0
        if cmd in (HL_START_TRAJECTORY, HL_START_TRAJECTORY_2):
            if cmd == HL_START_TRAJECTORY:
                _, _, relative, reverse, ident, scale = struct.unpack("<BBBBBf", d)
                relative_yaw = False
            else:
                _, _, relative, relative_yaw, reverse, ident, scale = struct.unpack("<BBBBBBf", d)
            return self._start_trajectory(t, ident, scale, bool(relative), bool(relative_yaw), bool(reverse))
        self.ignored += 1
        return errno.ENOEXEC

    def _start_trajectory(self, t: float, ident: int, scale: float, relative: bool, relative_yaw: bool,
                          reverse: bool) -> int:
        """``start_trajectory2``: an undefined id is answered 0 and nothing starts, as in the
        firmware; a definition the firmware would fly out of memory or into non-finite numbers,
        and a time scale that is not a positive number, are refused with EINVAL (and a console line)."""
        d = self._traj_defs.get(ident) if ident < trajectory.NUM_DEFINITIONS else None
        if d is None or d.location != trajectory.LOCATION_MEM:
            return 0
        if d.kind != trajectory.TYPE_POLY4D:
            self.ignored += 1
            self.console_print(f"CFSIM: trajectory {ident}: compressed trajectories are not modelled\n")
            return errno.ENOEXEC
        why = trajectory.check(self.traj_mem, d)
        if why is None and not (math.isfinite(scale) and scale > 0.0):
            why = f"time scale {scale} is not a positive number"
        if why is not None:
            self.console_print(f"CFSIM: trajectory {ident} refused: {why}\n")
            return errno.EINVAL
        traj = trajectory.Piecewise(self.traj_mem, d, t, float(scale), reverse)
        traj.start_from(self._hl_pos, self._hl_yaw, relative, relative_yaw)
        pos, vel, acc, yaw = traj.point(t)
        self._segment = Uploaded(traj, Track(pos, vel, acc, yaw))
        self._hl = HlState.FLYING
        return 0

    _handlers: dict[int, Callable[[Firmware, Packet], list[Packet]]] = {
        Port.LINKCTRL: _link,
        Port.PLATFORM: _platform,
        Port.SUPERVISOR: _supervisor,
        Port.MEM: _mem,
        Port.LOG: _log,
        Port.PARAM: _param,
        Port.COMMANDER: _commander,
        Port.COMMANDER_GENERIC: _commander_generic,
        Port.SETPOINT_HL: _high_level,
    }

    # -------------------------------------------------------------------------------- time
    def tick(self) -> list[Packet]:
        """Advance one control period; returns the log packets due at its end."""
        t = self.t
        quad = self.quad
        # 0. estimator, power management
        if self.noise is not None:
            self.noise.step()
        if self.battery is not None:
            before = self.battery.state
            self.battery.step(float(quad.motor_thrusts.sum()), quad.mass * self._g, PERIOD)
            if self.battery.state != before:
                if self.battery.state == realism.PM_LOW_POWER:
                    self.console_print(f"PM: battery low, {self.battery.vbat:.2f} V\n")
                elif self.battery.state == realism.PM_SHUTDOWN:
                    self.console_print("PM: battery empty, motors off\n")
                    self._lock()
        # 1. high-level commander
        if self.can_fly:
            if self._hl is HlState.IDLE:
                self._hl_pos = vec3(self.est_p)
                self._hl_yaw = quad.euler()[2]
                self._set_setpoint(OFF, Priority.HIGH_LEVEL)
            else:
                assert self._segment is not None
                ev = self._segment.eval(t)
                seg = self._segment
                if isinstance(seg, Uploaded) and seg.fault and not seg.reported:
                    seg.reported = True
                    self.console_print("CFSIM: trajectory point not finite: holding the last good point\n")
                if self._hl is HlState.LANDING and self._segment.finished(t):
                    self._hl = HlState.IDLE
                self._set_setpoint(ev, Priority.HIGH_LEVEL)
                self._hl_pos, self._hl_yaw = ev.pos, ev.yaw
        # 2.-3. setpoint age and supervisor
        now_ms = self.k * PERIOD_MS
        age = now_ms - self._stamp_ms
        flying = self._last_thrust_ms is not None and now_ms - self._last_thrust_ms < IS_FLYING_HYSTERESIS_MS
        sup = self._sup
        if sup is SupState.READY and flying and self._armed:
            sup = SupState.FLYING
        elif sup in (SupState.FLYING, SupState.LEVEL_OUT):
            if age > WDT_SHUTDOWN_MS:
                sup = SupState.LOCKED
            elif age > WDT_LEVEL_OUT_MS:
                sup = SupState.LEVEL_OUT
            elif not flying:
                sup = SupState.READY
            else:
                sup = SupState.FLYING
        self._sup = sup
        sp = self._override(self._setpoint)
        # 4. controller
        self._control(sp)
        # 5. world
        v0 = quad.v
        self._advance_world(sp)
        self.k += 1
        self._accel = (quad.v - v0) / PERIOD
        if any(f > 0.0 for f in quad.motor_commands):
            self._last_thrust_ms = self.k * PERIOD_MS
        # 6. logs and console
        return self._logs_due() + self._console_packets()

    def _override(self, sp: Setpoint) -> Setpoint:
        """``supervisorOverrideSetpoint``."""
        if not self.can_fly:
            return OFF
        if self._sup is SupState.LEVEL_OUT:
            if isinstance(sp, Attitude):
                return Attitude(sp.thrust_pwm, 0.0, 0.0, 0.0)
            if isinstance(sp, Track):
                p = sp.pos
                return Track((float("nan"), float("nan"), p[2]), (0.0, 0.0, sp.vel[2]), _ZERO3, sp.yaw)
            if isinstance(sp, Velocity):
                return Velocity((float("nan"), float("nan"), sp.vel[2]), 0.0)
            if isinstance(sp, (Hover, ZHold)):
                return ZHold(0.0, 0.0, sp.z, 0.0)
            if isinstance(sp, Manual):
                return Manual(sp.thrust_pwm, 0.0, 0.0, 0.0, False)
        return sp

    def _control(self, sp: Setpoint) -> None:
        quad = self.quad
        self._applied = sp
        if isinstance(sp, Off):
            quad.command_attitude(0.0, 0.0, 0.0, 0.0)
            self._vel_yaw = None
        elif isinstance(sp, Attitude):
            quad.command_attitude(pwm_to_thrust(sp.thrust_pwm, self._fmax), sp.roll, sp.pitch, sp.yaw_rate)
            self._vel_yaw = None
        elif isinstance(sp, Manual):
            if sp.rate:
                lim = self.cfg.tilt_max_manual
                r, pt = self._manual_att
                self._manual_att = (max(-lim, min(lim, r + sp.roll * PERIOD)),
                                    max(-lim, min(lim, pt + sp.pitch * PERIOD)))
            else:
                self._manual_att = (sp.roll, sp.pitch)
            quad.command_attitude(pwm_to_thrust(sp.thrust_pwm, self._fmax), *self._manual_att, sp.yaw_rate)
            self._vel_yaw = None
        elif isinstance(sp, ZHold):
            p, v = self.est_p, self.est_v
            uz = self.cfg.kp[2] * (sp.z - p[2]) - self.cfg.kv[2] * v[2]
            tilt = max(0.1, math.cos(sp.roll) * math.cos(sp.pitch))
            thrust = min(quad.params.collective_thrust_max, max(0.0, quad.mass * (self._g + uz) / tilt))
            quad.command_attitude(thrust, sp.roll, sp.pitch, sp.yaw_rate)
            self._vel_yaw = None
        elif isinstance(sp, Hover):
            p, v = self.est_p, self.est_v
            if self._vel_yaw is None:
                self._vel_yaw = quad.euler()[2]
            self._vel_yaw = wrap_angle(self._vel_yaw + sp.yaw_rate * PERIOD)
            c, s = math.cos(self._vel_yaw), math.sin(self._vel_yaw)
            vref = (c * sp.vx_body - s * sp.vy_body, s * sp.vx_body + c * sp.vy_body)
            kv = self.cfg.kv_velocity_mode
            u = [kv[0] * (vref[0] - v[0]), kv[1] * (vref[1] - v[1]),
                 self.cfg.kp[2] * (sp.z - p[2]) - self.cfg.kv[2] * v[2]]
            quad.command(np.array(u), self._vel_yaw)
        elif isinstance(sp, Track):
            p, v = self.est_p, self.est_v
            kp, kv = self.cfg.kp, self.cfg.kv
            u = [0.0 if math.isnan(sp.pos[i]) else
                 sp.acc[i] + kp[i] * (sp.pos[i] - p[i]) + kv[i] * (sp.vel[i] - v[i]) for i in range(3)]
            quad.command(np.array(u), sp.yaw)
            self._vel_yaw = None
        else:
            v = self.est_v
            kv = self.cfg.kv_velocity_mode
            if self._vel_yaw is None:
                self._vel_yaw = quad.euler()[2]
            self._vel_yaw = wrap_angle(self._vel_yaw + sp.yaw_rate * PERIOD)
            u = [0.0 if math.isnan(sp.vel[i]) else kv[i] * (sp.vel[i] - v[i]) for i in range(3)]
            quad.command(np.array(u), self._vel_yaw)

    def _advance_world(self, sp: Setpoint) -> None:
        """Advance the quadrotor by one period with the floor: one call while it cannot reach the
        floor within the period, steps of ``contact_step`` with the contact force held otherwise,
        nothing at all while it lies still on the floor with its motors off."""
        quad = self.quad
        remaining = PERIOD
        while remaining > 1e-12:
            p, v = quad.p, quad.v
            lowest = p[2] + min(0.0, v[2]) * remaining - 0.5 * self._g * remaining * remaining
            if lowest > self._z_contact:
                quad.advance(remaining)
                return
            if (isinstance(sp, Off) or (isinstance(sp, (Attitude, Manual)) and sp.thrust_pwm == 0.0)) \
                    and p[2] <= self._z_contact and float(np.abs(v).max()) < 1e-3 \
                    and float(np.abs(quad.omega).max()) < 1e-2 \
                    and float(quad.motor_thrusts.max()) < _MOTORS_STOPPED * quad.mass * self._g:
                return  # at rest on the floor, motors off: nothing moves
            h = min(self.cfg.contact_step, remaining)
            quad.advance(h, self._floor_force(p, v))
            remaining -= h

    def _floor_force(self, p: np.ndarray, v: np.ndarray) -> np.ndarray | None:
        """The floor's push [N; world]: a one-sided, preloaded spring-damper under ``z_contact``,
        with viscous friction on the horizontal velocity while in contact."""
        depth = self._z_contact - p[2]
        if depth <= 0.0:
            return None
        c = self._c_floor
        return np.array([-c * v[0], -c * v[1], max(0.0, self._k_floor * depth - c * v[2])])

    # --------------------------------------------------------------------------------- logs
    def _logs_due(self) -> list[Packet]:
        now = self.k * PERIOD_MS
        due = [b for b in self._blocks.values() if b.period_ms is not None and b.next_due_ms <= now]
        if not due:
            return []
        values = self.telemetry()
        stamp = struct.pack("<I", now & 0xFFFFFF)[:3]
        out = []
        for b in due:
            period = b.period_ms  # due blocks are started: not None
            if period is None or period == 0:
                b.period_ms = None
            else:
                b.next_due_ms += period
                if b.next_due_ms <= now:
                    b.next_due_ms = now + period
            body = b"".join(toc.pack_value(ct, values[i]) for i, ct in b.ops)
            out.append(Packet(Port.LOG, crtp.LOG_DATA_CHANNEL, bytes((b.ident,)) + stamp + body))
        return out

    def telemetry(self) -> list[float]:
        """Every log variable's present value, in TOC order (units in :mod:`plant.cfsim.toc`)."""
        quad, g = self.quad, self._g
        p, v, a = self.est_p, self.est_v, self._accel
        roll, pitch, yaw = quad.euler()
        qw, qx, qy, qz = quad.quaternion
        spec = quad.rotation.T @ (a + np.array([0.0, 0.0, g])) / g
        thrust_sp, roll_sp, pitch_sp, yaw_sp = quad.attitude_setpoint
        sp = self._applied
        target_p = sp.pos if isinstance(sp, Track) else (0.0, 0.0, sp.z) if isinstance(sp, (Hover, ZHold)) else _ZERO3
        target_v = sp.vel if isinstance(sp, (Track, Velocity)) else _ZERO3
        motors = [thrust_to_pwm(4.0 * f, self._fmax) for f in quad.motor_commands]
        bits = self.supervisor_bits()
        deg = math.degrees
        bat = self.battery
        vbat = self.cfg.vbat if bat is None else bat.vbat
        level = max(0.0, min(100.0, (vbat - 3.0) / 1.2 * 100.0)) if bat is None else bat.level
        values = {
            "stateEstimate.x": p[0], "stateEstimate.y": p[1], "stateEstimate.z": p[2],
            "stateEstimate.vx": v[0], "stateEstimate.vy": v[1], "stateEstimate.vz": v[2],
            "stateEstimate.ax": a[0] / g, "stateEstimate.ay": a[1] / g, "stateEstimate.az": a[2] / g,
            "stateEstimate.roll": deg(roll), "stateEstimate.pitch": -deg(pitch), "stateEstimate.yaw": deg(yaw),
            "stateEstimate.qx": qx, "stateEstimate.qy": qy, "stateEstimate.qz": qz, "stateEstimate.qw": qw,
            "stabilizer.roll": deg(roll), "stabilizer.pitch": -deg(pitch), "stabilizer.yaw": deg(yaw),
            "stabilizer.thrust": thrust_to_pwm(thrust_sp, self._fmax),
            "ctrltarget.x": target_p[0], "ctrltarget.y": target_p[1], "ctrltarget.z": target_p[2],
            "ctrltarget.vx": target_v[0], "ctrltarget.vy": target_v[1], "ctrltarget.vz": target_v[2],
            "ctrltarget.roll": deg(roll_sp), "ctrltarget.pitch": -deg(pitch_sp), "ctrltarget.yaw": deg(yaw_sp),
            "acc.x": spec[0], "acc.y": spec[1], "acc.z": spec[2],
            "motor.m1": motors[0], "motor.m2": motors[1], "motor.m3": motors[2], "motor.m4": motors[3],
            "pm.vbat": vbat, "pm.state": realism.PM_BATTERY if bat is None else bat.state, "pm.batteryLevel": level,
            "supervisor.info": bits,
            "sys.canfly": (bits >> BIT_CAN_FLY) & 1, "sys.isFlying": (bits >> BIT_FLYING) & 1, "sys.isTumbled": 0,
        }
        return [float(values[v.full_name]) for v in toc.LOG_VARS]


def _finite(*values: float) -> None:
    """Refuse a setpoint with a NaN or an infinity in it (the packet is then dropped)."""
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite setpoint value in {values}")


def decompress_quaternion(comp: int) -> tuple[float, float, float, float]:
    """The inverse of cflib's ``compress_quaternion`` (firmware ``quatcompress.h``): ``(x, y, z, w)``.

    Layout, most significant first: the index of the largest-magnitude component (2 bits), then for
    each other component in index order a sign bit and a 9-bit magnitude scaled by ``511 / sqrt(1/2)``;
    the largest component is positive and follows from the unit norm."""
    largest = comp >> 30
    q = [0.0, 0.0, 0.0, 0.0]
    total = 0.0
    for i in (3, 2, 1, 0):
        if i == largest:
            continue
        mag = (comp & 0x1FF) / 511.0 * math.sqrt(0.5)
        q[i] = -mag if comp & 0x200 else mag
        total += mag * mag
        comp >>= 10
    q[largest] = math.sqrt(max(0.0, 1.0 - total))
    return q[0], q[1], q[2], q[3]
