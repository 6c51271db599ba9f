"""The simulated Crazyflie's supervisor: arming, whether the vehicle flies, the setpoint watchdog
and the lock. Pure.

As the firmware's ``supervisor.c`` (with the watchdog of ``commander.c``): a setpoint older than
0.5 s while flying levels the vehicle out (roll = pitch = 0, yaw rate 0, thrust kept); older than
2 s, the motors stop and the vehicle is *locked* until the simulator restarts, as the firmware's
supervisor locks until a reboot. An emergency stop or the ``stabilizer.stop`` parameter locks it too,
and so does the emergency-stop watchdog (``supervisor.c`` ``checkEmergencyStopWatchdog``): armed by the
first notification (supervisor command 0x04, or the deprecated localization type 4), it locks the
vehicle once no notification came for 1 s, flying or not.
"""

from __future__ import annotations

import enum
import struct

from plant.cfsim import crtp
from plant.cfsim.commander import OFF, ZERO3, Attitude, Hover, Manual, Setpoint, Track, Velocity, ZHold
from plant.cfsim.crtp import Packet, Port

WDT_LEVEL_OUT_MS = 500
"""Setpoint age [ms] above which a flying vehicle levels out (COMMANDER_WDT_TIMEOUT_STABILIZE)."""
WDT_SHUTDOWN_MS = 2000
"""Setpoint age [ms] above which a flying vehicle's motors stop and it locks
(COMMANDER_WDT_TIMEOUT_SHUTDOWN)."""
ESTOP_WATCHDOG_MS = 1000
"""Once a client has notified the emergency-stop watchdog, silence from it for this long [ms] is an
emergency stop (``supervisor.c`` DEFAULT_EMERGENCY_STOP_WATCHDOG_TIMEOUT)."""
IS_FLYING_HYSTERESIS_MS = 2000
"""The supervisor counts the vehicle as flying until this long [ms] after the motors last ran.
(Ages are counted in whole ticks, as the firmware counts them in whole milliseconds.)"""


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


class Supervisor:
    """The supervisor's state. Not thread-safe; every call returns immediately.

    Attributes:
        state: what the supervisor holds the vehicle to be doing.
        armed: the vehicle is armed (auto-armed at boot).
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self) -> None:
        self.state = SupState.READY
        self.armed = True
        self.ignored = 0
        self._estop_notified_ms: int | None = None
        """When [ms since boot] the emergency-stop watchdog was last notified; None: never (disarmed)."""
        self._last_thrust_ms: int | None = None
        """When [ms since boot] the motors last ran; None if they never did."""

    @property
    def locked(self) -> bool:
        return self.state is SupState.LOCKED

    @property
    def can_fly(self) -> bool:
        return self.armed and not self.locked

    def lock(self) -> None:
        """Motors off until the simulator restarts."""
        self.state = SupState.LOCKED

    def notify_estop_watchdog(self, now_ms: int) -> None:
        """A client's emergency-stop watchdog notification at ``now_ms`` [ms since boot]."""
        self._estop_notified_ms = now_ms

    @property
    def estop_watchdog_armed(self) -> bool:
        return self._estop_notified_ms is not None

    def request_arming(self, arm: bool) -> bool:
        """Arm or disarm; refused (False) once locked."""
        if self.locked:
            return False
        self.armed = arm
        if not arm:
            self.state = SupState.READY
        return True

    def bits(self, hl_active: bool, hl_finished: bool) -> int:
        """The state bitfield (``BIT_*``) that the supervisor port and ``supervisor.info`` report;
        ``hl_active``: the high-level commander flies the vehicle; ``hl_finished``: its plan ended."""
        bits = (1 << BIT_AUTO_ARMED)
        if self.armed:
            bits |= 1 << BIT_ARMED
        elif not self.locked:
            bits |= 1 << BIT_CAN_BE_ARMED
        if self.can_fly:
            bits |= 1 << BIT_CAN_FLY
        if self.state in (SupState.FLYING, SupState.LEVEL_OUT):
            bits |= 1 << BIT_FLYING
        if self.locked:
            bits |= 1 << BIT_LOCKED
        if hl_active:
            bits |= 1 << BIT_HL_ACTIVE
        if hl_finished:
            bits |= 1 << BIT_HL_FINISHED
        return bits

    def handle(self, pkt: Packet, hl_active: bool, hl_finished: bool, now_ms: int) -> list[Packet]:
        """Answer one supervisor-port packet (``crtp_supervisor.c``) at ``now_ms`` [ms since boot]:
        the state bitfield (see :meth:`bits` for the two flags), arming, recovery, emergency stop and
        its watchdog."""
        cmd = pkt.data[0]
        if pkt.channel == crtp.SUPERVISOR_INFO_CHANNEL and cmd == crtp.SUPERVISOR_GET_STATE_BITFIELD:
            return [Packet(Port.SUPERVISOR, pkt.channel, struct.pack("<BH", cmd | crtp.SUPERVISOR_RESPONSE,
                                                                     self.bits(hl_active, hl_finished)))]
        if pkt.channel == crtp.SUPERVISOR_COMMAND_CHANNEL:
            if cmd == crtp.SUPERVISOR_ARM:
                ok = self.request_arming(bool(pkt.data[1]))
                return [Packet(Port.SUPERVISOR, pkt.channel, bytes((cmd | crtp.SUPERVISOR_RESPONSE, ok, self.armed)))]
            if cmd == crtp.SUPERVISOR_RECOVER:
                ok = not self.locked
                return [Packet(Port.SUPERVISOR, pkt.channel, bytes((cmd | crtp.SUPERVISOR_RESPONSE, ok, 1)))]
            if cmd == crtp.SUPERVISOR_EMERGENCY_STOP:
                self.lock()
                return []
            if cmd == crtp.SUPERVISOR_EMERGENCY_STOP_WATCHDOG:
                self.notify_estop_watchdog(now_ms)
                return []
        self.ignored += 1
        return []

    def update(self, now_ms: int, age_ms: int) -> None:
        """The tick's transition at ``now_ms`` [ms since boot], the setpoint being ``age_ms`` old."""
        notified = self._estop_notified_ms
        if notified is not None and now_ms >= notified + ESTOP_WATCHDOG_MS:
            self.lock()
        last = self._last_thrust_ms
        flying = last is not None and now_ms - last < IS_FLYING_HYSTERESIS_MS
        sup = self.state
        if sup is SupState.READY and flying and self.armed:
            sup = SupState.FLYING
        elif sup in (SupState.FLYING, SupState.LEVEL_OUT):
            if age_ms > WDT_SHUTDOWN_MS:
                sup = SupState.LOCKED
            elif age_ms > WDT_LEVEL_OUT_MS:
                sup = SupState.LEVEL_OUT
            elif not flying:
                sup = SupState.READY
            else:
                sup = SupState.FLYING
        self.state = sup

    def motors_ran(self, now_ms: int) -> None:
        """The motors ran during the tick that ended at ``now_ms`` [ms since boot]."""
        self._last_thrust_ms = now_ms

    def override(self, sp: Setpoint) -> Setpoint:
        """``supervisorOverrideSetpoint``: motors off unless the vehicle can fly; levelled out (the
        horizontal axes released, the height and thrust kept) while the setpoint is stale."""
        if not self.can_fly:
            return OFF
        if self.state is SupState.LEVEL_OUT:
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
