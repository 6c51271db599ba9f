"""Uploaded trajectories of the high-level commander: the trajectory memory, its definitions and the
evaluation of piecewise 7th-order 4-D polynomials (x, y, z, yaw). Pure.

What the firmware does (``crtp_commander_high_level.c``, ``planner.c``, ``pptraj.c``), modelled here:

* **Memory.** One memory of type TRAJ (0x12), 4096 bytes, zero at boot. A write of ``n`` bytes at
  ``addr`` succeeds iff ``addr + n <= 4096``; a read likewise. A piece is 132 bytes: four blocks of
  eight little-endian float32 coefficients (x, y, z, yaw; lowest order first; yaw in radians) and
  its duration [s] (cflib's ``Poly4D.pack``), so the memory holds 31 pieces.
* **Definitions.** 31 slots, each (location, type, offset, number of pieces); ``define_trajectory``
  with an id >= 31 is refused with ENOEXEC, any other definition is stored as given.
* **Evaluation** at ``t`` of a trajectory started at ``t_begin`` with time scale ``s``: the pieces are
  walked in order (reversed: from the last), the first whose stretched duration ``d s`` covers the
  time left is evaluated at it, ``p(tau / s)`` with derivatives ``p'(tau / s) / s`` and
  ``p''(tau / s) / s^2``; reversed, a piece runs backwards, ``p(d - tau / s)`` with velocity
  ``-p'(d - tau / s) / s``. After the end the last point (reversed: the first piece's start) is
  held at rest.
* **Relative start.** With ``relative_position`` the trajectory is shifted so that its first point
  (reversed: its last) is the present setpoint; with ``relative_yaw`` as well, it is rotated about
  the world's z axis by the shortest angle from its first yaw to the present one, the rotation
  applied after the shift was computed, about the origin, exactly as the firmware does (so a
  rotated trajectory whose first point is not the origin does not start at the present setpoint).
  A reversed trajectory is never rotated.

The memory is read when the trajectory is evaluated, as the firmware's trajectory points into it:
rewriting a trajectory's bytes while it flies changes what the vehicle flies.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

MEMORY_SIZE = 4096
"""Bytes of the trajectory memory (TRAJECTORY_MEMORY_SIZE)."""
MEM_TYPE_TRAJ = 0x12
NUM_DEFINITIONS = 31
"""Trajectory definition slots (NUM_TRAJECTORY_DEFINITIONS)."""
DEGREE = 7
PIECE_SIZE = 4 * (DEGREE + 1) * 4 + 4
"""Bytes of one uncompressed piece: 32 float32 coefficients and a float32 duration."""
LOCATION_INVALID, LOCATION_MEM = 0, 1
TYPE_POLY4D, TYPE_POLY4D_COMPRESSED = 0, 1
MEM_MAX_READ = 24
"""Largest read a CRTP packet can answer (30 bytes minus id, address and status)."""

_PIECE = struct.Struct("<33f")


class TrajectoryMemory:
    """The 4 KiB the trajectories are uploaded into."""

    def __init__(self) -> None:
        self.data = bytearray(MEMORY_SIZE)

    def write(self, addr: int, chunk: bytes) -> bool:
        """Copy ``chunk`` to ``addr``; False (nothing written) if it does not fit."""
        if addr < 0 or addr + len(chunk) > MEMORY_SIZE:
            return False
        self.data[addr:addr + len(chunk)] = chunk
        return True

    def read(self, addr: int, length: int) -> bytes | None:
        """``length`` bytes from ``addr``; None if they are not all inside the memory."""
        if addr < 0 or length < 0 or addr + length > MEMORY_SIZE:
            return None
        return bytes(self.data[addr:addr + length])


@dataclass(frozen=True, slots=True)
class Definition:
    """One ``define_trajectory``: where the pieces are and how many."""

    location: int
    kind: int
    offset: int
    n_pieces: int


@dataclass(frozen=True, slots=True)
class Piece:
    coeffs: tuple[tuple[float, ...], ...]
    """Four rows (x, y, z, yaw) of eight coefficients, lowest order first."""
    duration: float


def read_piece(mem: TrajectoryMemory, offset: int, index: int) -> Piece:
    """Piece ``index`` of the trajectory at ``offset`` (the caller checked it lies in memory)."""
    v = _PIECE.unpack_from(mem.data, offset + index * PIECE_SIZE)
    return Piece(tuple(tuple(v[8 * k:8 * k + 8]) for k in range(4)), v[32])


def check(mem: TrajectoryMemory, d: Definition) -> str | None:
    """Why a trajectory of definition ``d`` cannot be started, or None. The firmware starts any
    poly4d definition and reads past the memory or flies non-finite numbers if told to; the
    simulator refuses those instead."""
    if d.location != LOCATION_MEM:
        return "not defined"
    if d.kind != TYPE_POLY4D:
        return f"trajectory type {d.kind} (only uncompressed poly4d, type 0, is modelled)"
    if d.n_pieces == 0:
        return "no pieces"
    end = d.offset + d.n_pieces * PIECE_SIZE
    if end > MEMORY_SIZE:
        return f"pieces end at byte {end}, beyond the {MEMORY_SIZE}-byte memory"
    for i in range(d.n_pieces):
        p = read_piece(mem, d.offset, i)
        if not all(math.isfinite(c) for row in p.coeffs for c in row) or not math.isfinite(p.duration):
            return f"piece {i} has a non-finite value"
        if p.duration < 0.0:
            return f"piece {i} has a negative duration"
    return None


def _polyval(c: tuple[float, ...], x: float) -> tuple[float, float, float]:
    """A polynomial and its first two derivatives at ``x`` (Horner)."""
    p = dp = ddp = 0.0
    for a in reversed(c):
        ddp = ddp * x + 2.0 * dp
        dp = dp * x + p
        p = p * x + a
    return p, dp, ddp


def shortest_signed_angle(a: float, b: float) -> float:
    """The rotation [rad, in (-pi, pi]] that takes angle ``a`` to angle ``b``."""
    d = math.fmod(b - a, 2.0 * math.pi)
    if d > math.pi:
        d -= 2.0 * math.pi
    elif d <= -math.pi:
        d += 2.0 * math.pi
    return d


def normalize_radians(a: float) -> float:
    """``a`` in (-pi, pi]."""
    return shortest_signed_angle(0.0, a)


Vec3 = tuple[float, float, float]
Point = tuple[Vec3, Vec3, Vec3, float]
"""Position [m], velocity [m/s], acceleration [m/s^2] (world) and yaw [rad]."""


@dataclass(slots=True)
class Piecewise:
    """A started trajectory: pieces ``definition`` in ``mem``, from ``t_begin`` [s] at ``timescale``."""

    mem: TrajectoryMemory
    definition: Definition
    t_begin: float
    timescale: float
    reversed: bool = False
    shift: Vec3 = (0.0, 0.0, 0.0)
    shift_yaw: float = 0.0

    @property
    def duration(self) -> float:
        d = self.definition
        return self.timescale * sum(read_piece(self.mem, d.offset, i).duration for i in range(d.n_pieces))

    def finished(self, t: float) -> bool:
        return t - self.t_begin >= self.duration

    def point(self, t: float) -> Point:
        d, s = self.definition, self.timescale
        tau = t - self.t_begin
        order = range(d.n_pieces - 1, -1, -1) if self.reversed else range(d.n_pieces)
        for i in order:
            piece = read_piece(self.mem, d.offset, i)
            if tau <= piece.duration * s:
                if self.reversed:
                    return self._reversed(piece, piece.duration - tau / s, s)
                return self._forward(piece, tau / s, s)
            tau -= piece.duration * s
        if self.reversed:
            first = read_piece(self.mem, d.offset, 0)
            pos, _, _, yaw = self._reversed(first, 0.0, s)
        else:
            last = read_piece(self.mem, d.offset, d.n_pieces - 1)
            pos, _, _, yaw = self._forward(last, last.duration, s)
        zero = (0.0, 0.0, 0.0)
        return pos, zero, zero, yaw

    def _forward(self, piece: Piece, x: float, s: float) -> Point:
        ev = [_polyval(c, x) for c in piece.coeffs]
        pos = [e[0] for e in ev[:3]]
        vel = [e[1] / s for e in ev[:3]]
        acc = [e[2] / (s * s) for e in ev[:3]]
        rot = normalize_radians(self.shift_yaw)
        c, sn = math.cos(rot), math.sin(rot)

        def turn(v: list[float]) -> Vec3:
            return (c * v[0] - sn * v[1], sn * v[0] + c * v[1], v[2])

        p = turn(pos)
        sh = self.shift
        return (p[0] + sh[0], p[1] + sh[1], p[2] + sh[2]), turn(vel), turn(acc), ev[3][0] + rot

    def _reversed(self, piece: Piece, x: float, s: float) -> Point:
        ev = [_polyval(c, x) for c in piece.coeffs]
        sh = self.shift
        pos = (ev[0][0] + sh[0], ev[1][0] + sh[1], ev[2][0] + sh[2])
        vel = (-ev[0][1] / s, -ev[1][1] / s, -ev[2][1] / s)
        acc = (ev[0][2] / (s * s), ev[1][2] / (s * s), ev[2][2] / (s * s))
        return pos, vel, acc, ev[3][0]

    def start_from(self, pos: Vec3, yaw: float, relative_position: bool, relative_yaw: bool) -> None:
        """``plan_start_trajectory``'s shift and rotation for a start at setpoint ``pos``/``yaw``."""
        self.shift, self.shift_yaw = (0.0, 0.0, 0.0), 0.0
        if not relative_position:
            return
        p0, _, _, yaw0 = self.point(self.t_begin)
        self.shift = (pos[0] - p0[0], pos[1] - p0[1], pos[2] - p0[2])
        if relative_yaw:
            self.shift_yaw = shortest_signed_angle(normalize_radians(yaw0), normalize_radians(yaw))
