"""The simulated Crazyflie's services: link control, platform, log blocks, parameters and memory,
each answering its CRTP port. Pure.

As in the firmware (``crtpservice.c``, ``platformservice.c``, ``log.c``, ``param_logic.c``,
``crtp_mem.c``), a service knows nothing of what it serves: the log service samples the values it
is handed, the parameter service tells its owner which parameter changed, the memory service reads
and writes the memory it is given, the platform service asks the supervisor to arm.
"""

from __future__ import annotations

import errno
import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from plant.cfsim import crtp, toc, trajectory
from plant.cfsim.crtp import Packet, Port
from plant.cfsim.supervisor import Supervisor

LOG_MAX_BLOCKS = 16
LOG_MAX_OPS = 128
LOG_MAX_LEN = 26
"""Largest log block payload [bytes] (30 minus block id and 3-byte timestamp)."""


# ---------------------------------------------------------------------- link and platform
def link_reply(pkt: Packet) -> list[Packet]:
    """Answer one link-control packet: echo, the source's fixed text, the null packet; a sink packet
    is swallowed."""
    if pkt.channel == crtp.LINK_ECHO_CHANNEL:
        return [pkt]
    if pkt.channel == crtp.LINK_SOURCE_CHANNEL:
        return [Packet(Port.LINKCTRL, crtp.LINK_SOURCE_CHANNEL, b"Bitcraze Crazyflie".ljust(crtp.MAX_DATA, b"\0"))]
    if pkt.is_null:
        return [Packet(0xF, 3)]  # cflib's scan probe: any answer will do
    return []


class PlatformService:
    """The platform port: version queries, and the arming and recovery commands older cflib sends
    here instead of to the supervisor port. Not thread-safe; calls return at once.

    Attributes:
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self, sup: Supervisor) -> None:
        self.sup = sup
        self.ignored = 0

    def handle(self, pkt: Packet) -> list[Packet]:
        """Answer one platform-port packet."""
        ch, d = pkt.channel, pkt.data
        if ch == crtp.PLATFORM_VERSION_CHANNEL:
            cmd = d[0]
            if cmd == crtp.PLATFORM_VERSION_PROTOCOL:
                return [Packet(Port.PLATFORM, ch, struct.pack("<Bi", cmd, crtp.PROTOCOL_VERSION))]
            if cmd == crtp.PLATFORM_VERSION_FIRMWARE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.FIRMWARE_TAG.encode())]
            if cmd == crtp.PLATFORM_VERSION_DEVICE:
                return [Packet(Port.PLATFORM, ch, bytes((cmd,)) + crtp.DEVICE_TYPE.encode())]
            self.ignored += 1
            return []
        if ch == crtp.PLATFORM_COMMAND_CHANNEL:
            cmd = d[0]
            if cmd == crtp.PLATFORM_ARM:
                ok = self.sup.request_arming(bool(d[1]))
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, self.sup.armed)))]
            if cmd == crtp.PLATFORM_RECOVER:
                ok = not self.sup.locked
                return [Packet(Port.PLATFORM, ch, bytes((cmd, ok, 1)))]
            if cmd == crtp.PLATFORM_NOTIFY:
                return [Packet(Port.PLATFORM, ch)]
            return [pkt]  # continuous wave and the rest: echoed, as the firmware does
        self.ignored += 1
        return []


# ------------------------------------------------------------------------------------- TOC
def toc_reply(port: Port, d: bytes, items: list[bytes], extra: bytes = b"") -> list[Packet] | None:
    """Answer a TOC command (channel 0 of the log and param ports) from the wire forms ``items``;
    ``extra`` follows the TOC info. None for the v1 commands (protocol < 4), which are not served."""
    cmd = d[0]
    if cmd == crtp.TOC_INFO_V2:
        return [Packet(port, crtp.TOC_CHANNEL, toc.info_payload(items) + extra)]
    if cmd == crtp.TOC_ITEM_V2:
        ident = struct.unpack_from("<H", d, 1)[0]
        if ident < len(items):
            return [Packet(port, crtp.TOC_CHANNEL, items[ident])]
        return [Packet(port, crtp.TOC_CHANNEL, bytes((cmd,)))]
    return None


# ------------------------------------------------------------------------------------- log
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


class LogService:
    """The log port (``log.c``): blocks of variables of :data:`plant.cfsim.toc.LOG_VARS`, created,
    started and stopped by the client and sampled when due. Not thread-safe; calls return at once.

    Attributes:
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self) -> None:
        self.items = toc.log_items(toc.LOG_VARS)
        self.blocks: dict[int, LogBlock] = {}
        self.ignored = 0

    def handle(self, pkt: Packet, now_ms: int) -> list[Packet]:
        """Answer one log-port packet at ``now_ms`` [ms since boot]."""
        ch, d = pkt.channel, pkt.data
        if ch == crtp.TOC_CHANNEL:
            reply = toc_reply(Port.LOG, d, self.items, extra=bytes((LOG_MAX_BLOCKS, LOG_MAX_OPS)))
            if reply is None:
                self.ignored += 1
                return []
            return reply
        if ch != crtp.LOG_SETTINGS_CHANNEL:
            self.ignored += 1
            return []
        cmd = d[0]
        ident = d[1] if len(d) > 1 else 0
        if cmd in (crtp.LOG_CREATE, crtp.LOG_CREATE_V2, crtp.LOG_APPEND, crtp.LOG_APPEND_V2):
            ret = self._add(cmd, ident, d[2:])
        elif cmd == crtp.LOG_DELETE:
            ret = 0 if self.blocks.pop(ident, None) is not None else errno.ENOENT
        elif cmd in (crtp.LOG_START, crtp.LOG_START_V2):
            period = d[2] * 10 if cmd == crtp.LOG_START else struct.unpack_from("<H", d, 2)[0]
            ret = self._start(ident, period, now_ms)
        elif cmd == crtp.LOG_STOP:
            block = self.blocks.get(ident)
            if block is not None:
                block.period_ms = None
            ret = 0 if block is not None else errno.ENOENT
        elif cmd == crtp.LOG_RESET:
            self.blocks.clear()
            ret = 0
        else:
            ret = errno.ENOEXEC
        return [Packet(Port.LOG, ch, bytes((cmd, ident, ret)))]

    def _add(self, cmd: int, ident: int, ops: bytes) -> int:
        create = cmd in (crtp.LOG_CREATE, crtp.LOG_CREATE_V2)
        if create:
            if ident in self.blocks:
                return errno.EEXIST
            if len(self.blocks) >= LOG_MAX_BLOCKS:
                return errno.ENOMEM
            self.blocks[ident] = LogBlock(ident)
        block = self.blocks.get(ident)
        if block is None:
            return errno.ENOENT
        v2 = cmd in (crtp.LOG_CREATE_V2, crtp.LOG_APPEND_V2)
        width = 3 if v2 else 2
        if len(ops) % width:
            raise ValueError("truncated log operation")
        n_ops = sum(len(b.ops) for b in self.blocks.values())
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

    def _start(self, ident: int, period_ms: int, now_ms: int) -> int:
        block = self.blocks.get(ident)
        if block is None:
            return errno.ENOENT
        block.period_ms = period_ms
        block.next_due_ms = now_ms + period_ms
        return 0

    def sample(self, now_ms: int, telemetry: Callable[[], list[float]]) -> list[Packet]:
        """The data packets of the blocks due at ``now_ms`` [ms since boot], from ``telemetry()``
        (every log variable's value in TOC order, asked for only if a block is due)."""
        due = [b for b in self.blocks.values() if b.period_ms is not None and b.next_due_ms <= now_ms]
        if not due:
            return []
        values = telemetry()
        stamp = struct.pack("<I", now_ms & 0xFFFFFF)[:3]
        out = []
        for b in due:
            period = b.period_ms  # due blocks are started: not None
            if period is None or period == 0:
                b.period_ms = None
            else:
                b.next_due_ms += period
                if b.next_due_ms <= now_ms:
                    b.next_due_ms = now_ms + period
            body = b"".join(toc.pack_value(ct, values[i]) for i, ct in b.ops)
            out.append(Packet(Port.LOG, crtp.LOG_DATA_CHANNEL, bytes((b.ident,)) + stamp + body))
        return out


# ----------------------------------------------------------------------------------- param
class ParamService:
    """The param port (``param_logic.c``): the values of :data:`plant.cfsim.toc.PARAM_VARS`, read,
    written, and stored in a simulated EEPROM by the client. Not thread-safe; calls return at once.

    Attributes:
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self, overrides: Mapping[str, float], on_set: Callable[[str, float], None]) -> None:
        """``overrides``: values replacing the defaults (read-only parameters the vehicle sets at
        boot); ``on_set(name, value)`` is called after a client wrote a parameter."""
        self.items = toc.param_items(toc.PARAM_VARS)
        self.index = {v.full_name: i for i, v in enumerate(toc.PARAM_VARS)}
        self.values: list[float] = [v.default for v in toc.PARAM_VARS]
        for name, value in overrides.items():
            self.values[self.index[name]] = value
        self.persistent: dict[int, float] = {}
        """Values stored by ``persistent_store`` (the firmware's EEPROM), by parameter index."""
        self.ignored = 0
        self._on_set = on_set

    def get(self, full_name: str) -> float:
        """A parameter's present value (raises ``KeyError`` for an unknown name)."""
        return self.values[self.index[full_name]]

    def put(self, full_name: str, value: float) -> None:
        """Set a parameter from inside the vehicle (no check, no notification)."""
        self.values[self.index[full_name]] = value

    def handle(self, pkt: Packet) -> list[Packet]:
        """Answer one param-port packet."""
        ch, d = pkt.channel, pkt.data
        if ch == crtp.TOC_CHANNEL:
            reply = toc_reply(Port.PARAM, d, self.items)
            if reply is None:
                self.ignored += 1
                return []
            return reply
        if ch == crtp.PARAM_READ_CHANNEL:
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(toc.PARAM_VARS):
                return [Packet(Port.PARAM, ch, d[:2] + bytes((errno.ENOENT,)))]
            raw = toc.pack_value(toc.PARAM_VARS[ident].ctype, self.values[ident])
            return [Packet(Port.PARAM, ch, d[:2] + b"\0" + raw)]
        if ch == crtp.PARAM_WRITE_CHANNEL:
            ident = struct.unpack_from("<H", d, 0)[0]
            if ident >= len(toc.PARAM_VARS):
                return [Packet(Port.PARAM, ch, d[:2] + bytes((errno.ENOENT,)))]
            var = toc.PARAM_VARS[ident]
            if var.read_only:
                return []  # the firmware does not answer writes of read-only parameters
            self._set(ident, toc.unpack_value(var.ctype, d[2:]))
            return [pkt]
        if ch == crtp.PARAM_MISC_CHANNEL:
            return self._misc(d)
        self.ignored += 1
        return []

    def _misc(self, d: bytes) -> list[Packet]:
        cmd = d[0]
        if cmd == crtp.PARAM_MISC_SETBYNAME:
            return self._set_by_name(d)
        if cmd in (crtp.PARAM_MISC_GET_EXTENDED_TYPE_V2, crtp.PARAM_MISC_GET_DEFAULT_V2):
            ident = struct.unpack_from("<H", d, 1)[0]
            head = d[:3]
            if cmd == crtp.PARAM_MISC_GET_DEFAULT_V2 and ident < len(toc.PARAM_VARS):
                var = toc.PARAM_VARS[ident]
                default = self.values[ident] if var.read_only else var.default
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0" + toc.pack_value(var.ctype, default))]
            if cmd == crtp.PARAM_MISC_GET_EXTENDED_TYPE_V2 and ident < len(toc.PARAM_VARS) \
                    and toc.PARAM_VARS[ident].persistent:
                return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((0, toc.EXTENDED_PERSISTENT)))]
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((errno.ENOENT,)))]
        if cmd in (crtp.PARAM_MISC_PERSISTENT_STORE, crtp.PARAM_MISC_PERSISTENT_GET_STATE,
                   crtp.PARAM_MISC_PERSISTENT_CLEAR):
            return self._persistent(cmd, d)
        self.ignored += 1
        return []

    def _set_by_name(self, d: bytes) -> list[Packet]:
        end_group = d.index(0, 1)
        end_name = d.index(0, end_group + 1)
        name = d[1:end_group].decode("ascii") + "." + d[end_group + 1:end_name].decode("ascii")
        type_byte = d[end_name + 1]
        ident = self.index.get(name)
        if ident is None:
            err = errno.ENOENT
        elif type_byte != toc.PARAM_VARS[ident].ctype.code:
            err = errno.EINVAL
        elif toc.PARAM_VARS[ident].read_only:
            err = errno.EACCES
        else:
            self._set(ident, toc.unpack_value(toc.PARAM_VARS[ident].ctype, d[end_name + 2:]))
            err = 0
        return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, d[:end_name + 1] + bytes((err,)))]

    def _persistent(self, cmd: int, d: bytes) -> list[Packet]:
        ident = struct.unpack_from("<H", d, 1)[0]
        head = d[:3]
        if ident >= len(toc.PARAM_VARS) or not toc.PARAM_VARS[ident].persistent:
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + bytes((errno.ENOENT,)))]
        var = toc.PARAM_VARS[ident]
        if cmd == crtp.PARAM_MISC_PERSISTENT_STORE:
            self.persistent[ident] = self.values[ident]
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0")]
        if cmd == crtp.PARAM_MISC_PERSISTENT_CLEAR:
            self.persistent.pop(ident, None)
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0")]
        stored = self.persistent.get(ident)
        body = toc.pack_value(var.ctype, var.default)
        if stored is None:
            return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\0" + body)]
        return [Packet(Port.PARAM, crtp.PARAM_MISC_CHANNEL, head + b"\1" + body + toc.pack_value(var.ctype, stored))]

    def _set(self, ident: int, value: float) -> None:
        var = toc.PARAM_VARS[ident]
        if not math.isfinite(value):
            raise ValueError(f"{var.full_name}: non-finite value")
        self.values[ident] = value
        self._on_set(var.full_name, value)


# ------------------------------------------------------------------------------------- mem
class MemService:
    """The memory port (``crtp_mem.c``) with one memory: the trajectory memory, id 0. Not
    thread-safe; calls return at once.

    The firmware asserts (and reboots) on an unknown memory id and overruns its packet on a read
    longer than a packet can carry; the simulator answers those with EIO instead.

    Attributes:
        ignored: well-formed packets of features this simulator does not implement.
    """

    def __init__(self, memory: trajectory.TrajectoryMemory) -> None:
        self.memory = memory
        self.ignored = 0

    def handle(self, pkt: Packet) -> list[Packet]:
        """Answer one mem-port packet."""
        ch, d = pkt.channel, pkt.data
        if ch == crtp.MEM_INFO_CHANNEL:
            cmd = d[0]
            if cmd == crtp.MEM_INFO_NBR:
                return [Packet(Port.MEM, ch, bytes((cmd, 1)))]
            if cmd == crtp.MEM_INFO_DETAILS and d[1] == crtp.MEM_TRAJ_ID:
                body = struct.pack("<BBBI", cmd, crtp.MEM_TRAJ_ID, trajectory.MEM_TYPE_TRAJ, trajectory.MEMORY_SIZE)
                return [Packet(Port.MEM, ch, body + bytes(8))]  # no serial number: 8 zero bytes
            if cmd == crtp.MEM_INFO_VER:
                return [Packet(Port.MEM, ch, bytes((cmd, 1)))]
            self.ignored += 1
            return []
        if ch == crtp.MEM_READ_CHANNEL:
            mem_id, addr, length = struct.unpack("<BIB", d)
            data = self.memory.read(addr, length) \
                if mem_id == crtp.MEM_TRAJ_ID and length <= trajectory.MEM_MAX_READ else None
            if data is None:
                return [Packet(Port.MEM, ch, d[:5] + bytes((errno.EIO,)))]
            return [Packet(Port.MEM, ch, d[:5] + b"\0" + data)]
        if ch == crtp.MEM_WRITE_CHANNEL:
            mem_id, addr = struct.unpack_from("<BI", d)
            ok = mem_id == crtp.MEM_TRAJ_ID and self.memory.write(addr, d[5:])
            return [Packet(Port.MEM, ch, d[:5] + bytes((0 if ok else errno.EIO,)))]
        self.ignored += 1
        return []
