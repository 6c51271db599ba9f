"""CRTP packets as they travel over cflib's UDP driver: one packet per datagram. Pure.

A datagram is ``header, data[0..29]``. The header packs the port (bits 7..4) and the channel
(bits 1..0); bits 3..2 are set by cflib for the bootloader's sake and carry nothing. The UDP driver
adds no framing, checksum or retransmission. ``0xFF`` alone (port 15, channel 3) is the *null
packet* cflib's ``scan_interface`` sends as a probe; any answer counts as "a Crazyflie is here".

Ports, channels and command codes are the ones the Crazyflie firmware and cflib agree on
(cflib ``crtp/crtpstack.py``; firmware ``src/modules/interface/crtp.h``).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

MAX_DATA = 30
"""Largest CRTP payload [bytes] (``CRTP_MAX_DATA_SIZE``)."""

PROTOCOL_VERSION = 12
"""CRTP protocol version this simulator answers (the firmware's ``CRTP_PROTOCOL_VERSION`` when the
supervisor port arrived). cflib switches on it: >= 4 the v2 TOC commands (16-bit ids), >= 12 the
supervisor port for arming and state queries."""

FIRMWARE_TAG = "cfsim"
"""What a firmware-version query answers (the real firmware answers its git tag)."""

DEVICE_TYPE = "CF21"
"""What a device-type query answers (the Crazyflie 2.1's name)."""


class Port(enum.IntEnum):
    CONSOLE = 0x0
    PARAM = 0x2
    COMMANDER = 0x3
    MEM = 0x4
    LOG = 0x5
    LOCALIZATION = 0x6
    COMMANDER_GENERIC = 0x7
    SETPOINT_HL = 0x8
    SUPERVISOR = 0x9
    PLATFORM = 0xD
    LINKCTRL = 0xF


# Channels of the TOC-based ports (log, param).
TOC_CHANNEL = 0
# log port
LOG_SETTINGS_CHANNEL = 1
LOG_DATA_CHANNEL = 2
# param port
PARAM_READ_CHANNEL = 1
PARAM_WRITE_CHANNEL = 2
PARAM_MISC_CHANNEL = 3
# mem port
MEM_INFO_CHANNEL = 0
# generic commander port
GENERIC_SETPOINT_CHANNEL = 0
GENERIC_META_CHANNEL = 1
# platform port
PLATFORM_COMMAND_CHANNEL = 0
PLATFORM_VERSION_CHANNEL = 1
PLATFORM_APP_CHANNEL = 2
# link control port
LINK_ECHO_CHANNEL = 0
LINK_SOURCE_CHANNEL = 1
LINK_SINK_CHANNEL = 2
# supervisor port
SUPERVISOR_INFO_CHANNEL = 0
SUPERVISOR_COMMAND_CHANNEL = 1

# TOC commands (log and param ports, channel 0). Only the v2 pair is served (protocol >= 4).
TOC_ITEM_V2 = 2
TOC_INFO_V2 = 3

# Command codes: the first payload byte of a port's packets (a channel's, where noted).
# log port, settings channel (``log.c``)
LOG_CREATE, LOG_APPEND, LOG_DELETE, LOG_START, LOG_STOP, LOG_RESET = 0, 1, 2, 3, 4, 5
LOG_CREATE_V2, LOG_APPEND_V2, LOG_START_V2 = 6, 7, 8
# param port, misc channel (``param_logic.c``)
PARAM_MISC_SETBYNAME, PARAM_MISC_GET_EXTENDED_TYPE_V2, PARAM_MISC_GET_DEFAULT_V2 = 0, 7, 8
PARAM_MISC_PERSISTENT_STORE, PARAM_MISC_PERSISTENT_GET_STATE, PARAM_MISC_PERSISTENT_CLEAR = 3, 4, 5
# mem port (``crtp_mem.c``): info commands on channel 0, reads and writes on their own channels
MEM_INFO_VER, MEM_INFO_NBR, MEM_INFO_DETAILS = 0, 1, 2
MEM_READ_CHANNEL, MEM_WRITE_CHANNEL = 1, 2
MEM_TRAJ_ID = 0
"""The trajectory memory's id: the only memory of the simulated vehicle."""
# high-level commander port (``crtp_commander_high_level.c``)
HL_SET_GROUP_MASK, HL_STOP, HL_TAKEOFF_2, HL_LAND_2, HL_SPIRAL, HL_GO_TO_2 = 0, 3, 7, 8, 11, 12
HL_START_TRAJECTORY, HL_DEFINE_TRAJECTORY, HL_START_TRAJECTORY_2 = 5, 6, 13
# generic commander port: setpoint types on channel 0, meta commands on channel 1
# (``crtp_commander_generic.c``)
GENERIC_STOP, GENERIC_FULL_STATE, GENERIC_POSITION, GENERIC_VELOCITY_WORLD = 0, 6, 7, 8
GENERIC_VELOCITY_WORLD_LEGACY, GENERIC_ZDISTANCE_LEGACY, GENERIC_HOVER_LEGACY = 1, 2, 5
GENERIC_ZDISTANCE, GENERIC_HOVER, GENERIC_MANUAL = 9, 10, 11
META_NOTIFY_SETPOINT_STOP = 0
# platform port: version channel, command channel (``platformservice.c``)
PLATFORM_VERSION_PROTOCOL, PLATFORM_VERSION_FIRMWARE, PLATFORM_VERSION_DEVICE = 0, 1, 2
PLATFORM_ARM, PLATFORM_RECOVER, PLATFORM_NOTIFY = 1, 2, 3
# supervisor port (``crtp_supervisor.c``); an answer repeats the command with the response bit set
SUPERVISOR_GET_STATE_BITFIELD = 0x0C
SUPERVISOR_ARM, SUPERVISOR_RECOVER, SUPERVISOR_EMERGENCY_STOP = 0x01, 0x02, 0x03
SUPERVISOR_EMERGENCY_STOP_WATCHDOG = 0x04
# localization port (``crtp_localization_service.c``): channels, and the generic channel's types
LOC_EXT_POSITION_CHANNEL, LOC_GENERIC_CHANNEL, LOC_EXT_POSITION_PACKED_CHANNEL = 0, 1, 2
LOC_EMERGENCY_STOP, LOC_EMERGENCY_STOP_WATCHDOG, LOC_EXT_POSE, LOC_EXT_POSE_PACKED = 3, 4, 8, 9
SUPERVISOR_RESPONSE = 0x80

NULL_HEADER = 0xFF
"""Header of the null packet (port 15, channel 3, no payload)."""


class CrtpError(ValueError):
    """A datagram that is not a CRTP packet (empty, or longer than header + 30 bytes)."""


@dataclass(frozen=True, slots=True)
class Packet:
    """One CRTP packet: port (0..15), channel (0..3) and payload (at most 30 bytes)."""

    port: int
    channel: int
    data: bytes = b""

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 0xF or not 0 <= self.channel <= 3:
            raise CrtpError(f"port {self.port} / channel {self.channel} out of range")
        if len(self.data) > MAX_DATA:
            raise CrtpError(f"payload of {len(self.data)} bytes exceeds {MAX_DATA}")

    @property
    def is_null(self) -> bool:
        return self.port == 0xF and self.channel == 3 and not self.data


def header(port: int, channel: int) -> int:
    """The header byte for ``port``/``channel`` (bits 3..2 set, as cflib and the firmware do)."""
    return ((port & 0xF) << 4) | 0x0C | (channel & 0x3)


def decode(datagram: bytes) -> Packet:
    """One datagram to a packet; raises :class:`CrtpError` if it cannot be one."""
    if not datagram:
        raise CrtpError("empty datagram")
    if len(datagram) > MAX_DATA + 1:
        raise CrtpError(f"datagram of {len(datagram)} bytes exceeds {MAX_DATA + 1}")
    h = datagram[0]
    return Packet((h >> 4) & 0xF, h & 0x3, bytes(datagram[1:]))


def encode(packet: Packet) -> bytes:
    """A packet to one datagram."""
    return bytes((header(packet.port, packet.channel),)) + packet.data
