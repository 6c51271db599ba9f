"""The simulated Crazyflie's firmware and world: CRTP in, CRTP out, a quadrotor in between. Pure.

No sockets, no clock, no randomness: :meth:`Firmware.handle` answers one CRTP packet at the present
simulated time, :meth:`Firmware.tick` advances the simulated time by one control period (10 ms) and
returns the log packets that fell due. The vehicle is :class:`plant.quadrotor.Quadrotor` (rigid
body, Eq. 4 and its 500 Hz attitude/rate PID), injected by the caller.

:class:`Firmware` routes each port's packets to its part, as the firmware's CRTP router does: the
commander (:mod:`plant.cfsim.commander`), the high-level commander (:mod:`plant.cfsim.high_level`),
the supervisor (:mod:`plant.cfsim.supervisor`), the localization service (external positions into
the estimator), the link, platform, log, param and mem services (:mod:`plant.cfsim.services`).

What runs every tick (100 Hz), in the firmware's order (``stabilizer.c``):

1. the high-level commander, if the vehicle can fly, offers its setpoint at priority HIGH_LEVEL
   (a trajectory point while flying or landing, "motors off" while idle);
2. the commander's setpoint is read with its age;
3. the supervisor updates its state from the age and the motors, and overrides the setpoint of a
   vehicle that must level out or stop (:mod:`plant.cfsim.supervisor`);
4. the controller turns the setpoint into a command of the quadrotor (:mod:`plant.cfsim.controller`);
5. the world advances 10 ms: the quadrotor, plus a floor at ``z = 0`` (:mod:`plant.cfsim.world`), and
   the position estimator follows the move (:mod:`plant.cfsim.estimator`; external positions reach it
   from the localization port as they come);
6. log blocks whose period elapsed are sampled.

The logged ``stateEstimate.pitch`` / ``stabilizer.pitch`` are ``-pitch`` (the firmware's legacy
frame; :mod:`plant.cfsim.commander` has the conventions at the cflib edge), motor commands are PWM
units of :mod:`plant.cfsim.motors`' thrust map.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from plant.cfsim import crtp, realism, toc, trajectory
from plant.cfsim.estimator import EstimatorConfig, PositionEstimator
from plant.cfsim.commander import (
    OFF, ZERO3, Commander, Hover, Priority, Setpoint, Track, Velocity, ZHold, generic_setpoint, vec3,
)
from plant.cfsim.controller import Controller
from plant.cfsim.crtp import Packet, Port
from plant.cfsim.high_level import HighLevelCommander, HlState
from plant.cfsim.motors import thrust_to_pwm
from plant.cfsim.services import LogService, MemService, ParamService, PlatformService, link_reply
from plant.cfsim.supervisor import BIT_CAN_FLY, BIT_FLYING, Supervisor, SupState
from plant.cfsim.world import World
from plant.quadrotor import Quadrotor

PERIOD = 0.01
"""Control period [s]: commander, high-level commander, supervisor, position controller and log
scheduling run at 100 Hz; the quadrotor's own attitude loop runs at its 500 Hz inside."""
PERIOD_MS = 10


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
    estimator: EstimatorConfig = EstimatorConfig()
    """Where the position estimate comes from (onboard positioning, or external positions only)."""
    radio_id: int = 0xE7
    """Last byte of the vehicle's radio address: the id packed external positions are matched
    against (``crtp_localization_service.c`` ``my_id``)."""


class Firmware:
    """One simulated Crazyflie: its firmware state and its vehicle. Not thread-safe; every call
    returns immediately.

    Attributes:
        k: control ticks since boot; the simulated time is ``k * PERIOD`` [s].
        dropped: packets that could not be decoded (too short, wrong length, unknown ids).
        commander, hl: the setpoint slot and the high-level commander.
        logs, params, mem, platform: the log, param, mem and platform services.
        sup, controller, world: the supervisor, the controller and the quadrotor above its floor.
    """

    def __init__(self, quad: Quadrotor, cfg: FirmwareConfig | None = None) -> None:
        self.quad = quad
        self.cfg = cfg if cfg is not None else FirmwareConfig()
        # realism
        self.noise = realism.EstimatorNoise(self.cfg.noise, PERIOD) if self.cfg.noise is not None else None
        self.battery = realism.Battery(self.cfg.battery) if self.cfg.battery is not None else None
        self.estimator = PositionEstimator(self.cfg.estimator, quad.p)
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
        # commanders, supervisor, controller, world
        self.commander = Commander()
        self.hl = HighLevelCommander(vec3(self.est_p), quad.euler()[2], self.traj_mem, self.params,
                                     self.console_print)
        self.sup = Supervisor()
        self.platform = PlatformService(self.sup)
        self.controller = Controller(quad, self.cfg.kp, self.cfg.kv, self.cfg.kv_velocity_mode,
                                     self.cfg.tilt_max_manual, PERIOD)
        self.world = World(quad, self.cfg.floor_frequency, self.cfg.floor_damping, self.cfg.contact_step)
        self._applied: Setpoint = OFF
        """The setpoint the controller flew in the last tick (after the supervisor's override)."""
        self._accel = np.zeros(3)
        """Acceleration [m/s^2; world] over the last tick."""

    # ---------------------------------------------------------------------------- reading
    @property
    def t(self) -> float:
        """Simulated time since boot [s]."""
        return self.k * PERIOD

    @property
    def ignored(self) -> int:
        """Well-formed packets of features this simulator does not implement, over every port."""
        parts = (self.logs, self.params, self.mem, self.platform, self.sup, self.hl)
        return self._ignored + sum(part.ignored for part in parts)

    @property
    def est_p(self) -> np.ndarray:
        """The position estimate [m; world]: the estimator's (:mod:`plant.cfsim.estimator`), plus the
        estimator noise of :mod:`plant.cfsim.realism`, if modelled."""
        p = self.estimator.p
        return p.copy() if self.noise is None else p + self.noise.position

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
        return self.sup.state

    @property
    def hl_state(self) -> HlState:
        return self.hl.state

    @property
    def can_fly(self) -> bool:
        return self.sup.can_fly

    def supervisor_bits(self) -> int:
        return self.sup.bits(self._hl_flying(), self.hl.finished(self.t))

    def _hl_flying(self) -> bool:
        """The high-level commander flies the vehicle: planning, and not overruled by a low-level setpoint."""
        return self.hl.active and self.commander.priority <= Priority.HIGH_LEVEL

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

    def _param_set(self, name: str, value: float) -> None:
        """What a client's parameter write does besides storing the value."""
        if name == "stabilizer.stop" and value:
            self.sup.lock()
        elif name == "kalman.resetEstimation" and value:
            self.params.put(name, 0)  # cleared once done (estimator_kalman.c)
            self.estimator.reset()
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

    def _link(self, pkt: Packet) -> list[Packet]:
        return link_reply(pkt)

    def _platform(self, pkt: Packet) -> list[Packet]:
        return self.platform.handle(pkt)

    def _supervisor(self, pkt: Packet) -> list[Packet]:
        return self.sup.handle(pkt, self._hl_flying(), self.hl.finished(self.t), self.k * PERIOD_MS)

    def _localization(self, pkt: Packet) -> list[Packet]:
        """The localization service (``crtp_localization_service.c``): external positions into the
        estimator, the deprecated emergency stop and its watchdog. Answers nothing."""
        d = pkt.data
        std = self.params.get("locSrv.extPosStdDev")
        if pkt.channel == crtp.LOC_EXT_POSITION_CHANNEL:
            self.estimator.extpos(np.array(struct.unpack("<fff", d)), std)
        elif pkt.channel == crtp.LOC_EXT_POSITION_PACKED_CHANNEL:
            if len(d) % 7:
                raise ValueError("packed external positions come in 7-byte items")
            for ident, x, y, z in struct.iter_unpack("<Bhhh", d):
                if ident == self.cfg.radio_id:  # others' positions go to peer localization: not modelled
                    self.estimator.extpos(np.array((x, y, z)) / 1000.0, std)
        elif pkt.channel == crtp.LOC_GENERIC_CHANNEL and d[0] == crtp.LOC_EMERGENCY_STOP:
            self.sup.lock()
        elif pkt.channel == crtp.LOC_GENERIC_CHANNEL and d[0] == crtp.LOC_EMERGENCY_STOP_WATCHDOG:
            self.sup.notify_estop_watchdog(self.k * PERIOD_MS)
        elif pkt.channel == crtp.LOC_GENERIC_CHANNEL and d[0] == crtp.LOC_EXT_POSE:
            _, x, y, z, *_quat = struct.unpack("<B7f", d)  # the attitude part is not modelled
            self.estimator.extpos(np.array((x, y, z)), std)
        else:
            self._ignored += 1
        return []

    def _high_level(self, pkt: Packet) -> list[Packet]:
        return self.hl.handle(pkt, self.t, self.sup.locked)

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
        Port.LOCALIZATION: _localization,
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
                    self.sup.lock()
        # 1. high-level commander
        if self.can_fly:
            if self.hl.state is HlState.IDLE:
                self.hl.hold(vec3(self.est_p), quad.euler()[2])
                self._set_setpoint(OFF, Priority.HIGH_LEVEL)
            else:
                self._set_setpoint(self.hl.step(t), Priority.HIGH_LEVEL)
        # 2.-3. setpoint age and supervisor
        now_ms = self.k * PERIOD_MS
        self.sup.update(now_ms, now_ms - self.commander.stamp_ms)
        sp = self.sup.override(self.commander.setpoint)
        # 4. controller
        self._applied = sp
        self.controller.command(sp, self.est_p, self.est_v)
        # 5. world, and the estimator's view of the move
        v0, p0 = quad.v, quad.p
        self.world.advance(PERIOD, sp)
        self.k += 1
        self._accel = (quad.v - v0) / PERIOD
        self.estimator.tick(quad.p - p0, quad.p, PERIOD)
        if any(f > 0.0 for f in quad.motor_commands):
            self.sup.motors_ran(self.k * PERIOD_MS)
        # 6. logs and console
        return self.logs.sample(self.k * PERIOD_MS, self.telemetry) + self._console_packets()

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
            "kalman.varPX": self.estimator.var[0], "kalman.varPY": self.estimator.var[1],
            "kalman.varPZ": self.estimator.var[2],
        }
        return [float(values[v.full_name]) for v in toc.LOG_VARS]
