"""The simulated Crazyflie's firmware and world: CRTP in, CRTP out, a quadrotor in between. Pure.

No sockets, no clock, no randomness: :meth:`Firmware.handle` answers one CRTP packet at the present
simulated time, :meth:`Firmware.tick` advances the simulated time by one control period (10 ms) and
returns the log packets that fell due. The vehicle is :class:`plant.quadrotor.Quadrotor` (rigid
body, Eq. 4 and its 500 Hz attitude/rate PID), injected by the caller.

:class:`Firmware` routes each port's packets to its part, as the firmware's CRTP router does: the
commander (:mod:`plant.cfsim.commander`), the high-level commander (:mod:`plant.cfsim.high_level`),
the log, param and mem services (:mod:`plant.cfsim.services`); the link, platform and supervisor
ports it answers itself. It also runs the supervisor, the controller and the world.

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

The logged ``stateEstimate.pitch`` / ``stabilizer.pitch`` are ``-pitch`` (the firmware's legacy
frame; see :mod:`plant.cfsim.commander` for the conventions at the cflib edge).

Thrust map (crazyflie-firmware ``motors.c`` with battery compensation, the default): a motor
command ``pwm`` in 0..65535 gives ``pwm / 65535 * f_max`` newtons per motor, ``f_max`` being
:attr:`QuadrotorParams.motor_thrust_max` (THRUST_MAX, 0.1125 N for the CF 2.1 propellers). An RPYT
thrust therefore means a collective thrust ``T = 4 f_max pwm / 65535``.
"""

from __future__ import annotations

import enum
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from plant.cfsim import crtp, realism, toc, trajectory
from plant.cfsim.commander import (
    OFF, ZERO3, Attitude, Commander, Hover, Manual, Off, Priority, Setpoint, Track, Velocity, ZHold,
    generic_setpoint, vec3,
)
from plant.cfsim.crtp import Packet, Port
from plant.cfsim.high_level import HighLevelCommander, HlState
from plant.cfsim.services import LogService, MemService, ParamService
from plant.quadrotor import Quadrotor, wrap_angle

PERIOD = 0.01
"""Control period [s]: commander, high-level commander, supervisor, position controller and log
scheduling run at 100 Hz; the quadrotor's own attitude loop runs at its 500 Hz inside."""
PERIOD_MS = 10

PWM_FULL = 65535
"""Full-scale motor command [PWM units]."""

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


def pwm_to_thrust(pwm: float, motor_thrust_max: float) -> float:
    """Collective thrust [N] of four motors commanded at ``pwm`` [0..65535]."""
    return 4.0 * motor_thrust_max * pwm / PWM_FULL


def thrust_to_pwm(thrust: float, motor_thrust_max: float) -> float:
    """The PWM command [0..65535, not clipped] that gives collective thrust ``thrust`` [N]."""
    return thrust * PWM_FULL / (4.0 * motor_thrust_max)


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


class Firmware:
    """One simulated Crazyflie: its firmware state and its vehicle. Not thread-safe; every call
    returns immediately.

    Attributes:
        k: control ticks since boot; the simulated time is ``k * PERIOD`` [s].
        dropped: packets that could not be decoded (too short, wrong length, unknown ids).
        commander, hl: the setpoint slot and the high-level commander.
        logs, params, mem: the log, param and mem services.
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
        self._ignored = 0
        self._console: bytearray = bytearray()
        self.console_lines: list[str] = []
        """Every console line printed since boot (also sent to the client on the console port)."""
        # services
        self.logs = LogService()
        self.params = ParamService({
            "cfsim.instance": self.cfg.instance,
            "cfsim.mass": quad.mass,
            "cfsim.hoverPwm": round(thrust_to_pwm(quad.mass * self._g, self._fmax)),
        }, self._param_set)
        self.traj_mem = trajectory.TrajectoryMemory()
        self.mem = MemService(self.traj_mem)
        # commanders
        self.commander = Commander()
        self.hl = HighLevelCommander(vec3(self.est_p), quad.euler()[2], self.traj_mem, self.params,
                                     self.console_print)
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
    def ignored(self) -> int:
        """Well-formed packets of features this simulator does not implement, over every port."""
        return self._ignored + self.logs.ignored + self.params.ignored + self.mem.ignored + self.hl.ignored

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
        return self.hl.state

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
        if self.hl.active and self.commander.priority <= Priority.HIGH_LEVEL:
            bits |= 1 << BIT_HL_ACTIVE
        if self.hl.finished(self.t):
            bits |= 1 << BIT_HL_FINISHED
        return bits

    def param(self, full_name: str) -> float:
        """A parameter's present value (raises ``KeyError`` for an unknown name)."""
        return self.params.get(full_name)

    # ----------------------------------------------------------------------------- packets
    def handle(self, pkt: Packet) -> list[Packet]:
        """Answer one packet at the present simulated time; returns the replies (maybe none).
        Malformed packets are counted in :attr:`dropped` and answered with nothing."""
        handler = self._handlers.get(pkt.port)
        if handler is None:
            self._ignored += 1
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
            if cmd == crtp.PLATFORM_VERSION_PROTOCOL:
                return [Packet(Port.PLATFORM, ch, struct.pack("<Bi", cmd, crtp.PROTOCOL_VERSION))]
            if cmd == crtp.PLATFORM_VERSION_FIRMWARE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.FIRMWARE_TAG.encode())]
            if cmd == crtp.PLATFORM_VERSION_DEVICE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.DEVICE_TYPE.encode())]
            self._ignored += 1
            return []
        if ch == crtp.PLATFORM_COMMAND_CHANNEL:
            cmd = d[0]
            if cmd == crtp.PLATFORM_ARM:
                ok = self._request_arming(bool(d[1]))
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, self._armed)))]
            if cmd == crtp.PLATFORM_RECOVER:
                ok = self._sup is not SupState.LOCKED
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, 1)))]
            if cmd == crtp.PLATFORM_NOTIFY:
                return [Packet(Port.PLATFORM, ch)]
            return [pkt]  # continuous wave and the rest: echoed, as the firmware does
        self._ignored += 1
        return []

    def _supervisor(self, pkt: Packet) -> list[Packet]:
        cmd = pkt.data[0]
        if pkt.channel == crtp.SUPERVISOR_INFO_CHANNEL and cmd == crtp.SUPERVISOR_GET_STATE_BITFIELD:
            return [Packet(Port.SUPERVISOR, pkt.channel, struct.pack("<BH", cmd | crtp.SUPERVISOR_RESPONSE,
                                                                     self.supervisor_bits()))]
        if pkt.channel == crtp.SUPERVISOR_COMMAND_CHANNEL:
            if cmd == crtp.SUPERVISOR_ARM:
                ok = self._request_arming(bool(pkt.data[1]))
                return [Packet(Port.SUPERVISOR, pkt.channel,
                               bytes((cmd | crtp.SUPERVISOR_RESPONSE, ok, self._armed)))]
            if cmd == crtp.SUPERVISOR_RECOVER:
                ok = self._sup is not SupState.LOCKED
                return [Packet(Port.SUPERVISOR, pkt.channel, bytes((cmd | crtp.SUPERVISOR_RESPONSE, ok, 1)))]
            if cmd == crtp.SUPERVISOR_EMERGENCY_STOP:
                self._lock()
                return []
        self._ignored += 1
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

    def _param_set(self, name: str, value: float) -> None:
        """What a client's parameter write does besides storing the value."""
        if name == "stabilizer.stop" and value:
            self._lock()
        elif name == "kalman.resetEstimation" and value:
            if self.noise is not None:
                self.noise.reset()
            self.console_print("CFSIM: state estimate reset\n")

    def _commander(self, pkt: Packet) -> list[Packet]:
        if pkt.channel != 0:
            self._ignored += 1
            return []
        self._set_setpoint(self.commander.rpyt(pkt.data), Priority.CRTP)
        return []

    def _commander_generic(self, pkt: Packet) -> list[Packet]:
        d = pkt.data
        if pkt.channel == crtp.GENERIC_META_CHANNEL:
            if d[0] == crtp.META_NOTIFY_SETPOINT_STOP:
                struct.unpack("<BI", d)  # remain-valid milliseconds: unused, as in the firmware
                self._relax_priority()
            else:
                self._ignored += 1
            return []
        if pkt.channel != crtp.GENERIC_SETPOINT_CHANNEL:
            self._ignored += 1
            return []
        sp = generic_setpoint(d)
        if sp is None:
            self._ignored += 1
            return []
        self._set_setpoint(sp, Priority.CRTP)
        return []

    def _set_setpoint(self, sp: Setpoint, priority: Priority) -> None:
        """Offer ``sp`` to the commander; a low-level setpoint that takes it stops the high-level
        planner."""
        if self.commander.offer(sp, priority, self.k * PERIOD_MS) and priority > Priority.HIGH_LEVEL:
            self.hl.stop()

    def _relax_priority(self) -> None:
        """``commanderRelaxPriority``: the high-level commander takes over from the present state."""
        self.hl.hold(vec3(self.est_p), self.quad.euler()[2])
        self.commander.relax()

    def _high_level(self, pkt: Packet) -> list[Packet]:
        return self.hl.handle(pkt, self.t, self._sup is SupState.LOCKED)

    def _mem(self, pkt: Packet) -> list[Packet]:
        return self.mem.handle(pkt)

    def _log(self, pkt: Packet) -> list[Packet]:
        return self.logs.handle(pkt, self.k * PERIOD_MS)

    def _param(self, pkt: Packet) -> list[Packet]:
        return self.params.handle(pkt)

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
            if self.hl.state is HlState.IDLE:
                self.hl.hold(vec3(self.est_p), quad.euler()[2])
                self._set_setpoint(OFF, Priority.HIGH_LEVEL)
            else:
                self._set_setpoint(self.hl.step(t), Priority.HIGH_LEVEL)
        # 2.-3. setpoint age and supervisor
        now_ms = self.k * PERIOD_MS
        age = now_ms - self.commander.stamp_ms
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
        sp = self._override(self.commander.setpoint)
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
        return self.logs.sample(self.k * PERIOD_MS, self.telemetry) + self._console_packets()

    def _override(self, sp: Setpoint) -> Setpoint:
        """``supervisorOverrideSetpoint``."""
        if not self.can_fly:
            return OFF
        if self._sup is SupState.LEVEL_OUT:
            if isinstance(sp, Attitude):
                return Attitude(sp.thrust_pwm, 0.0, 0.0, 0.0)
            if isinstance(sp, Track):
                p = sp.pos
                return Track((float("nan"), float("nan"), p[2]), (0.0, 0.0, sp.vel[2]), ZERO3, sp.yaw)
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
    def telemetry(self) -> list[float]:
        """Every log variable's present value, in TOC order (units in :mod:`plant.cfsim.toc`)."""
        quad, g = self.quad, self._g
        p, v, a = self.est_p, self.est_v, self._accel
        roll, pitch, yaw = quad.euler()
        qw, qx, qy, qz = quad.quaternion
        spec = quad.rotation.T @ (a + np.array([0.0, 0.0, g])) / g
        thrust_sp, roll_sp, pitch_sp, yaw_sp = quad.attitude_setpoint
        sp = self._applied
        target_p = sp.pos if isinstance(sp, Track) else (0.0, 0.0, sp.z) if isinstance(sp, (Hover, ZHold)) else ZERO3
        target_v = sp.vel if isinstance(sp, (Track, Velocity)) else ZERO3
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
