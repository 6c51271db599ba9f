"""The simulated Crazyflie's commander: setpoint types, the setpoint slot with its priorities, and the
decoders of the low-level commander ports. Pure.

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

RPYT thrust below 1000 is 0 and above 60000 is 60000 (``MIN_THRUST``/``MAX_THRUST`` of the RPYT
decoder).
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass

from plant.cfsim import crtp

RPYT_MIN_THRUST = 1000
RPYT_MAX_THRUST = 60000


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
ZERO3: Vec3 = (0.0, 0.0, 0.0)


class Priority(enum.IntEnum):
    """Commander priorities (``commander.h``)."""

    DISABLE = 0
    HIGH_LEVEL = 1
    """Also COMMANDER_PRIORITY_LOWEST, what ``notify_setpoint_stop`` relaxes to."""
    CRTP = 2


# ----------------------------------------------------------------------------------- the slot
class Commander:
    """The setpoint slot (``commander.c``): one setpoint, its priority and when it was set, and the
    RPYT decoder's thrust lock. Not thread-safe; every call returns immediately."""

    def __init__(self) -> None:
        self.priority = Priority.DISABLE
        self.setpoint: Setpoint = OFF
        self.stamp_ms = 0
        """Time [ms since boot] the setpoint in the slot was set."""
        self.thrust_locked = True

    def offer(self, sp: Setpoint, priority: Priority, now_ms: int) -> bool:
        """``commanderSetSetpoint``: ``sp`` takes the slot if ``priority`` is at least the active
        one; returns whether it did."""
        if priority < self.priority:
            return False
        self.setpoint, self.priority, self.stamp_ms = sp, priority, now_ms
        return True

    def relax(self) -> None:
        """``commanderRelaxPriority``: the high-level commander may offer setpoints again."""
        self.priority = Priority.HIGH_LEVEL

    def rpyt(self, data: bytes) -> Attitude:
        """Decode a commander-port packet (``crtp_commander_rpyt.c``), updating the thrust lock:
        locked again whenever the slot is disabled, released by a thrust of 0."""
        roll, pitch, yaw, thrust = struct.unpack("<fffH", data)
        if self.priority == Priority.DISABLE:
            self.thrust_locked = True
        if thrust == 0:
            self.thrust_locked = False
        pwm = 0.0 if self.thrust_locked or thrust < RPYT_MIN_THRUST else float(min(thrust, RPYT_MAX_THRUST))
        # legacy frame: pitch arrives inverted (cflib sent -pitch); yaw rate input is inverted
        finite(roll, pitch, yaw)
        return Attitude(pwm, math.radians(roll), -math.radians(pitch), -math.radians(yaw))


# ------------------------------------------------------------------------------- the decoders
def finite(*values: float) -> None:
    """Refuse a setpoint with a NaN or an infinity in it (the packet is then dropped)."""
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"non-finite setpoint value in {values}")


def generic_setpoint(d: bytes) -> Setpoint | None:
    """Decode a generic-commander setpoint packet (``crtp_commander_generic.c``, channel 0); None for
    a setpoint type this simulator does not implement. Raises ``struct.error`` or ``ValueError``
    for a malformed or non-finite one."""
    kind = d[0]
    if kind == crtp.GENERIC_STOP:
        return OFF
    if kind == crtp.GENERIC_POSITION:
        _, x, y, z, yaw = struct.unpack("<Bffff", d)
        finite(x, y, z, yaw)
        return Track((x, y, z), ZERO3, ZERO3, math.radians(yaw))
    if kind in (crtp.GENERIC_VELOCITY_WORLD, crtp.GENERIC_VELOCITY_WORLD_LEGACY):
        _, vx, vy, vz, yaw_rate = struct.unpack("<Bffff", d)
        finite(vx, vy, vz, yaw_rate)
        sign = -1.0 if kind == crtp.GENERIC_VELOCITY_WORLD_LEGACY else 1.0  # legacy yaw rate is inverted
        return Velocity((vx, vy, vz), sign * math.radians(yaw_rate))
    if kind in (crtp.GENERIC_HOVER, crtp.GENERIC_HOVER_LEGACY):
        _, vx, vy, yaw_rate, z = struct.unpack("<Bffff", d)
        finite(vx, vy, yaw_rate, z)
        sign = -1.0 if kind == crtp.GENERIC_HOVER_LEGACY else 1.0
        return Hover(vx, vy, z, sign * math.radians(yaw_rate))
    if kind in (crtp.GENERIC_ZDISTANCE, crtp.GENERIC_ZDISTANCE_LEGACY):
        # roll and pitch arrive as the user gave them (no -pitch here, unlike send_setpoint), and
        # the firmware reads pitch in its legacy frame: positive pitch raises the nose
        _, roll, pitch, yaw_rate, z = struct.unpack("<Bffff", d)
        finite(roll, pitch, yaw_rate, z)
        sign = -1.0 if kind == crtp.GENERIC_ZDISTANCE_LEGACY else 1.0
        return ZHold(math.radians(roll), -math.radians(pitch), z, sign * math.radians(yaw_rate))
    if kind == crtp.GENERIC_MANUAL:
        # cflib sends -pitch, as for send_setpoint; thrust 10001..60000 for 0..100 %; no thrust lock
        _, roll, pitch, yaw_rate, thrust, rate = struct.unpack("<BfffHB", d)
        finite(roll, pitch, yaw_rate)
        pwm = 0.0 if thrust < RPYT_MIN_THRUST else float(min(thrust, RPYT_MAX_THRUST))
        return Manual(pwm, math.radians(roll), -math.radians(pitch), math.radians(yaw_rate), bool(rate))
    if kind == crtp.GENERIC_FULL_STATE:
        return _full_state(d)
    return None


def _full_state(d: bytes) -> Track:
    """The full-state setpoint: position, velocity and acceleration in millimetres (per second,
    per second squared) as int16, and the attitude as a compressed quaternion."""
    v = struct.unpack("<BhhhhhhhhhIhhh", d)
    mm = [c / 1000.0 for c in v[1:10]]
    qx, qy, qz, qw = decompress_quaternion(v[10])
    yaw = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return Track(vec3(mm[0:3]), vec3(mm[3:6]), vec3(mm[6:9]), yaw)


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
