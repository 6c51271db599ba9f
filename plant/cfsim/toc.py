"""The simulated Crazyflie's log and parameter tables of contents (TOCs), and their wire forms. Pure.

A TOC is an ordered list of ``group.name`` variables; a variable's id is its index. cflib fetches
a TOC with the v2 commands (protocol >= 4): ``TOC_INFO_V2`` answers the count (uint16) and a CRC
(uint32) that cflib uses as its cache key, ``TOC_ITEM_V2 id`` answers
``[cmd, id (uint16), type byte, group NUL name NUL]``. The CRC here is CRC-32 over every item's
wire form, so it changes whenever the table does.

Names, types and units follow the Crazyflie firmware's own log and param groups (``stateEstimate``,
``stabilizer``, ``pm``, ...), including its conventions: ``stateEstimate.pitch`` and
``stabilizer.pitch`` are in the *legacy* CF2 body frame, where pitch is inverted (nose up is
positive); ``stateEstimate.ax/ay/az`` are the world-frame kinematic acceleration in g (gravity
removed); ``acc.*`` is the body-frame specific force in g (1 on z at rest).
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass

from plant.cfsim import crtp
from plant.cfsim.estimator import EXTPOS_STD_DEFAULT


@dataclass(frozen=True, slots=True)
class CType:
    """A C type as the log or param subsystem numbers it."""

    name: str
    code: int
    fmt: str
    """``struct`` format, little-endian."""

    @property
    def size(self) -> int:
        return struct.calcsize(self.fmt)

    @property
    def is_int(self) -> bool:
        return self.fmt[-1] not in "efd"


# Log types (firmware log.h LOG_UINT8 = 1 ... LOG_FP16 = 8; cflib LogTocElement.types).
LOG_TYPES: dict[int, CType] = {
    t.code: t
    for t in (
        CType("uint8_t", 1, "<B"),
        CType("uint16_t", 2, "<H"),
        CType("uint32_t", 3, "<I"),
        CType("int8_t", 4, "<b"),
        CType("int16_t", 5, "<h"),
        CType("int32_t", 6, "<i"),
        CType("float", 7, "<f"),
        CType("FP16", 8, "<e"),
    )
}
LOG_UINT8, LOG_UINT16, LOG_UINT32, LOG_INT8, LOG_INT16, LOG_INT32, LOG_FLOAT, LOG_FP16 = (
    LOG_TYPES[c] for c in range(1, 9)
)

# Param types (firmware param.h; cflib ParamTocElement.types): the low nibble of the type byte.
PARAM_TYPES: dict[int, CType] = {
    t.code: t
    for t in (
        CType("int8_t", 0x00, "<b"),
        CType("int16_t", 0x01, "<h"),
        CType("int32_t", 0x02, "<i"),
        CType("int64_t", 0x03, "<q"),
        CType("FP16", 0x05, "<e"),
        CType("float", 0x06, "<f"),
        CType("double", 0x07, "<d"),
        CType("uint8_t", 0x08, "<B"),
        CType("uint16_t", 0x09, "<H"),
        CType("uint32_t", 0x0A, "<I"),
        CType("uint64_t", 0x0B, "<Q"),
    )
}
PARAM_UINT8, PARAM_UINT16, PARAM_FLOAT = PARAM_TYPES[0x08], PARAM_TYPES[0x09], PARAM_TYPES[0x06]
PARAM_READ_ONLY = 0x40
"""Type-byte flag: the parameter cannot be written."""
PARAM_EXTENDED = 0x10
"""Type-byte flag: the parameter has an extended type (here always *persistent*)."""
EXTENDED_PERSISTENT = 1

_MAX_NAME = crtp.MAX_DATA - 5
"""group + name may take at most 30 - (cmd, id16, type, two NULs) = 25 characters."""


@dataclass(frozen=True, slots=True)
class LogVar:
    """One loggable variable. ``doc`` gives its meaning, unit and frame."""

    group: str
    name: str
    ctype: CType
    doc: str

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"


@dataclass(frozen=True, slots=True)
class ParamVar:
    """One parameter with its value at boot."""

    group: str
    name: str
    ctype: CType
    default: float
    read_only: bool
    doc: str
    persistent: bool = False
    """Can be stored with cflib's ``param.persistent_store`` (the firmware's EEPROM)."""

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"

    @property
    def type_byte(self) -> int:
        return (self.ctype.code | (PARAM_READ_ONLY if self.read_only else 0)
                | (PARAM_EXTENDED if self.persistent else 0))


def _log(group: str, names: str, ctype: CType, doc: str) -> list[LogVar]:
    return [LogVar(group, n, ctype, doc.format(n=n)) for n in names.split()]


LOG_VARS: tuple[LogVar, ...] = tuple(
    _log("stateEstimate", "x y z", LOG_FLOAT, "position {n} [m; world frame]")
    + _log("stateEstimate", "vx vy vz", LOG_FLOAT, "velocity {n} [m/s; world frame]")
    + _log("stateEstimate", "ax ay az", LOG_FLOAT,
           "kinematic acceleration {n}, mean over the last 10 ms, gravity removed [g; world frame]")
    + _log("stateEstimate", "roll yaw", LOG_FLOAT, "attitude, {n} (ZYX Euler angle) [deg]")
    + _log("stateEstimate", "pitch", LOG_FLOAT, "attitude, pitch, legacy sign: nose up > 0 [deg]")
    + _log("stateEstimate", "qx qy qz qw", LOG_FLOAT, "attitude quaternion, {n}, body to world [1]")
    + _log("stabilizer", "roll yaw", LOG_FLOAT, "attitude, {n} [deg] (as stateEstimate)")
    + _log("stabilizer", "pitch", LOG_FLOAT, "attitude, pitch, legacy sign: nose up > 0 [deg]")
    + _log("stabilizer", "thrust", LOG_FLOAT, "collective thrust command [PWM units, 0..65535]")
    + _log("ctrltarget", "x y z", LOG_FLOAT, "position setpoint {n} [m; world frame]")
    + _log("ctrltarget", "vx vy vz", LOG_FLOAT, "velocity setpoint {n} [m/s; world frame]")
    + _log("ctrltarget", "roll yaw", LOG_FLOAT, "attitude setpoint {n} [deg]")
    + _log("ctrltarget", "pitch", LOG_FLOAT, "attitude setpoint pitch, legacy sign [deg]")
    + _log("acc", "x y z", LOG_FLOAT, "specific force {n} (what an accelerometer reads) [g; body frame]")
    + _log("motor", "m1 m2 m3 m4", LOG_UINT16, "motor {n} command [PWM units, 0..65535]")
    + _log("pm", "vbat", LOG_FLOAT, "battery voltage [V]")
    + _log("pm", "state", LOG_INT8, "power state (0 battery, 3 low power, 4 shut down)")
    + _log("pm", "batteryLevel", LOG_UINT8, "battery charge [%]")
    + _log("supervisor", "info", LOG_UINT16,
           "supervisor bitfield (bit 1 armed, 3 can fly, 4 flying, 6 locked, 8 HL active, ...)")
    + _log("sys", "canfly isFlying isTumbled", LOG_UINT8, "supervisor flag {n} (0/1)")
    + _log("kalman", "varPX varPY varPZ", LOG_FLOAT, "variance of the position estimate, {n} [m^2]")
)

PARAM_VARS: tuple[ParamVar, ...] = (
    ParamVar("commander", "enHighLevel", PARAM_UINT8, 1, False,
             "accepted and ignored: the high-level commander is always on (as in the firmware)"),
    ParamVar("hlCommander", "groupmask", PARAM_UINT8, 0, False,
             "groups this vehicle belongs to; high-level commands for group mask 0 reach every vehicle"),
    ParamVar("hlCommander", "vtoff", PARAM_FLOAT, 0.5, False, "default take-off velocity [m/s] (unused)"),
    ParamVar("hlCommander", "vland", PARAM_FLOAT, 0.5, False, "default landing velocity [m/s] (unused)"),
    ParamVar("stabilizer", "stop", PARAM_UINT8, 0, False,
             "nonzero: emergency stop (motors off, supervisor locked)"),
    ParamVar("stabilizer", "estimator", PARAM_UINT8, 2, False,
             "estimator (1 complementary, 2 Kalman): stored, no effect (one estimator is modelled)", True),
    ParamVar("stabilizer", "controller", PARAM_UINT8, 1, False,
             "controller (1 PID, 2 Mellinger, ...): stored, no effect (one controller is modelled)", True),
    ParamVar("kalman", "resetEstimation", PARAM_UINT8, 0, False,
             "nonzero: reset the position estimate to the origin, untrusted (with estimator noise, a fresh error)"),
    ParamVar("locSrv", "extPosStdDev", PARAM_FLOAT, EXTPOS_STD_DEFAULT, False,
             "standard deviation [m] of an external position, as the estimator fuses it"),
    ParamVar("cfsim", "instance", PARAM_UINT16, 0, True, "index of this simulated vehicle in its launch"),
    ParamVar("cfsim", "mass", PARAM_FLOAT, 0.0, True, "vehicle mass [kg]"),
    ParamVar("cfsim", "hoverPwm", PARAM_UINT16, 0, True,
             "send_setpoint thrust that holds the vehicle's weight [PWM units]"),
)


def _check_names(entries: tuple[LogVar, ...] | tuple[ParamVar, ...]) -> None:
    seen: set[str] = set()
    for e in entries:
        if len(e.group) + len(e.name) > _MAX_NAME:
            raise ValueError(f"{e.full_name}: group + name longer than {_MAX_NAME} characters")
        if e.full_name in seen:
            raise ValueError(f"{e.full_name} declared twice")
        seen.add(e.full_name)


_check_names(LOG_VARS)
_check_names(PARAM_VARS)


def item_payload(ident: int, type_byte: int, group: str, name: str) -> bytes:
    """The answer to ``TOC_ITEM_V2 ident``."""
    text = group.encode("ascii") + b"\0" + name.encode("ascii") + b"\0"
    return struct.pack("<BHB", crtp.TOC_ITEM_V2, ident, type_byte) + text


def log_items(entries: tuple[LogVar, ...]) -> list[bytes]:
    return [item_payload(i, e.ctype.code, e.group, e.name) for i, e in enumerate(entries)]


def param_items(entries: tuple[ParamVar, ...]) -> list[bytes]:
    return [item_payload(i, e.type_byte, e.group, e.name) for i, e in enumerate(entries)]


def crc(items: list[bytes]) -> int:
    """The TOC's CRC: CRC-32 over its items' wire forms."""
    c = 0
    for it in items:
        c = zlib.crc32(it, c)
    return c


def info_payload(items: list[bytes]) -> bytes:
    """The answer to ``TOC_INFO_V2``: command, count (uint16), CRC (uint32). The log port appends
    its limits (blocks, variables), which cflib ignores."""
    return struct.pack("<BHI", crtp.TOC_INFO_V2, len(items), crc(items))


def pack_value(ctype: CType, value: float) -> bytes:
    """``value`` in ``ctype``'s wire form. Integer types truncate toward zero (C's float-to-int
    conversion) and saturate at the type's range instead of wrapping; FP16 saturates at +-65504;
    NaN packs as 0 in integer types."""
    if ctype.is_int:
        if isinstance(value, float):
            value = 0 if math.isnan(value) else int(max(-2.0**63, min(2.0**64, value)))
        bits = 8 * ctype.size
        lo, hi = (0, 2**bits - 1) if ctype.fmt[-1].isupper() else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
        return struct.pack(ctype.fmt, min(hi, max(lo, int(value))))
    if ctype.fmt == "<e":
        value = max(-65504.0, min(65504.0, float(value)))
    return struct.pack(ctype.fmt, float(value))


def unpack_value(ctype: CType, raw: bytes) -> float:
    """The inverse of :func:`pack_value`; raises ``struct.error`` on a wrong length."""
    (v,) = struct.unpack(ctype.fmt, raw)
    return v
