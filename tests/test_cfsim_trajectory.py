"""Uploaded trajectories on the software Crazyflie: the trajectory memory (CRTP port 4), the
high-level commander's ``define_trajectory`` / ``start_trajectory`` and the evaluation of poly4d
pieces with the firmware's time-scale, relative and reversed semantics.

The pure tests tick :class:`plant.cfsim.firmware.Firmware` by hand; the flights are cflib-only
clients (``TrajectoryMemory.write_data_sync``, ``define_trajectory``, ``start_trajectory``) against
one simulator process with two vehicles on two free UDP ports.
"""

from __future__ import annotations

import contextlib
import errno
import math
import struct
import threading
from collections.abc import Iterator

import numpy as np
import pytest

from plant.cfsim import commander, crtp, firmware, high_level, trajectory
from plant.cfsim.crtp import Packet, Port
from plant.quadrotor import Quadrotor, QuadrotorParams
from tests.support import SoftwareCrazyflies, free_port, software_crazyflies, wait_until

cflib_crtp = pytest.importorskip("cflib.crtp")
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.mem import MemoryElement, Poly4D  # noqa: E402
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie  # noqa: E402
from cflib.crtp.crtpstack import CRTPPacket, CRTPPort  # noqa: E402

from tests.test_cfsim_paths import Heights  # noqa: E402

FLY, BAD = 0, 1
STARTUP = 30.0
FIG_T = 10.0
"""Duration [s] of the figure-eight (its peak acceleration is about 1.1 m/s^2)."""


# ========================================================================= a figure-eight
def figure_eight(pieces: int = 5, duration: float = 10.0, r: float = 0.3) -> list[tuple[float, np.ndarray]]:
    """A figure-eight of half-width ``r`` [m] starting and ending at rest at the origin, flown once in
    ``duration`` [s], as ``pieces`` least-squares 7th-order pieces (duration, 4x8 coefficients)."""
    T = duration / pieces
    out = []
    for k in range(pieces):
        t = np.linspace(0.0, T, 200)
        tau = (k * T + t) / duration
        phase = 2.0 * math.pi * (35 * tau**4 - 84 * tau**5 + 70 * tau**6 - 20 * tau**7)  # rest to rest
        xyz = [r * np.sin(phase), 0.5 * r * np.sin(2.0 * phase), 0.1 * np.sin(phase) ** 2, 0.3 * np.sin(phase)]
        coeffs = np.array([np.polynomial.polynomial.polyfit(t, f, 7) for f in xyz])
        out.append((T, coeffs))
    return out


def poly_point(pieces: list[tuple[float, np.ndarray]], t: float) -> np.ndarray:
    """x, y, z, yaw of the pieces at ``t`` [s], evaluated directly (numpy, float32 coefficients)."""
    for T, c in pieces:
        if t <= T:
            return np.array([np.polynomial.polynomial.polyval(t, row) for row in c.astype(np.float32)])
        t -= T
    T, c = pieces[-1]
    return np.array([np.polynomial.polynomial.polyval(T, row) for row in c.astype(np.float32)])


def packed(pieces: list[tuple[float, np.ndarray]]) -> bytes:
    return b"".join(struct.pack("<32ff", *c.astype(np.float32).ravel(), T) for T, c in pieces)


# ========================================================================= pure firmware
def fresh() -> firmware.Firmware:
    return firmware.Firmware(Quadrotor(QuadrotorParams(), np.array([1.0, 2.0, 0.0])))


def upload(fw: firmware.Firmware, data: bytes, addr: int = 0) -> list[int]:
    """Write ``data`` as cflib does (24-byte chunks); the status byte of every answer."""
    out = []
    for a in range(0, len(data), 24):
        (reply,) = fw.handle(Packet(Port.MEM, 2, struct.pack("<BI", 0, addr + a) + data[a:a + 24]))
        assert reply.data[:5] == struct.pack("<BI", 0, addr + a)
        out.append(reply.data[5])
    return out


def hl(fw: firmware.Firmware, fmt: str, *values: object) -> int:
    (reply,) = fw.handle(Packet(Port.SETPOINT_HL, 0, struct.pack(fmt, *values)))
    return reply.data[3]


def define(fw: firmware.Firmware, ident: int, offset: int, n: int, kind: int = 0) -> int:
    return hl(fw, "<BBBBIB", 6, ident, 1, kind, offset, n)


def start(fw: firmware.Firmware, ident: int, scale: float = 1.0, relative: bool = False,
          relative_yaw: bool = False, reverse: bool = False) -> int:
    return hl(fw, "<BBBBBBf", 13, 0, relative, relative_yaw, reverse, ident, scale)


def test_memory_is_announced_as_the_firmware_s_trajectory_memory() -> None:
    fw = fresh()
    (n,) = fw.handle(Packet(Port.MEM, 0, bytes((1,))))
    assert n.data == bytes((1, 1))
    (info,) = fw.handle(Packet(Port.MEM, 0, bytes((2, 0))))
    assert struct.unpack_from("<BBBI", info.data) == (2, 0, MemoryElement.TYPE_TRAJ, 4096)
    assert len(info.data) == 15


@pytest.mark.parametrize("scale,reverse", [(1.0, False), (2.0, False), (0.5, True), (1.0, True)])
def test_evaluation_follows_the_pieces_with_time_scale_and_reversal(scale: float, reverse: bool) -> None:
    pieces = figure_eight()
    fw = fresh()
    assert upload(fw, packed(pieces)) == [0] * math.ceil(5 * trajectory.PIECE_SIZE / 24)
    assert define(fw, 3, 0, len(pieces)) == 0
    t0 = fw.t
    assert start(fw, 3, scale, relative=True, reverse=reverse) == 0
    plan = fw.hl.plan
    assert isinstance(plan, high_level.Uploaded)
    total = FIG_T * scale
    start_point = poly_point(pieces, FIG_T if reverse else 0.0)
    shift = np.array([1.0, 2.0, 0.0]) - start_point[:3]  # relative: the first point is the setpoint
    for tau in (0.0, 0.37, 1.9, 3.3, total - 0.01, total + 1.0):
        ev = plan.eval(t0 + tau)
        u = min(tau / scale, FIG_T)
        want = poly_point(pieces, FIG_T - u if reverse else u)
        np.testing.assert_allclose(ev.pos, want[:3] + shift, atol=1e-5)
        assert ev.yaw == pytest.approx(want[3], abs=1e-5)
        # velocity: the time derivative of the evaluated position
        h = 1e-4
        if 0.0 < tau < total - h:
            d = (np.array(plan.eval(t0 + tau + h).pos) - np.array(plan.eval(t0 + tau - h).pos)) / (2 * h)
            np.testing.assert_allclose(ev.vel, d, atol=1e-3)
    assert plan.eval(t0 + total + 1.0).vel == (0.0, 0.0, 0.0)
    assert not plan.finished(t0 + total - 0.01) and plan.finished(t0 + total)


def test_relative_yaw_rotates_about_the_origin_as_the_firmware_does() -> None:
    """Piece: x = 1 + t, yaw = 0; started at yaw pi/2 from (0, 0, 1): rotated by pi/2 after the
    shift (-1, 0, 1) is computed, so it starts at R(1, 0, 0) + shift = (-1, 1, 1)."""
    fw = fresh()
    c = np.zeros((4, 8))
    c[0, :2] = (1.0, 1.0)
    upload(fw, packed([(1.0, c)]))
    define(fw, 0, 0, 1)
    fw.hl.pos, fw.hl.yaw = (0.0, 0.0, 1.0), math.pi / 2
    assert start(fw, 0, relative=True, relative_yaw=True) == 0
    ev = fw.hl.plan.eval(fw.t + 0.5)  # type: ignore[union-attr]
    np.testing.assert_allclose(ev.pos, (-1.0, 1.5, 1.0), atol=1e-6)
    np.testing.assert_allclose(ev.vel, (0.0, 1.0, 0.0), atol=1e-6)
    assert ev.yaw == pytest.approx(math.pi / 2)


def test_refusals_and_malformed_packets_never_break_the_vehicle() -> None:
    fw = fresh()
    one = packed(figure_eight(1))
    # oversized: 32 pieces do not fit 4096 bytes; the chunk that crosses the end is refused
    status = upload(fw, one * 32)
    assert status[:170] == [0] * 170 and status[-1] == errno.EIO and errno.EIO in status
    # absurd addresses, an unknown memory, reads too long for a packet or past the end
    for data, want in ((struct.pack("<BI", 0, 0xFFFFFFFF) + b"\1\2", errno.EIO),
                       (struct.pack("<BI", 0, 4096) + b"\1", errno.EIO),
                       (struct.pack("<BI", 7, 0) + b"\1", errno.EIO),
                       (struct.pack("<BI", 0, 4095) + b"\1", 0)):
        (r,) = fw.handle(Packet(Port.MEM, 2, data))
        assert r.data[5] == want
    for data, want in ((struct.pack("<BIB", 0, 4090, 8), errno.EIO), (struct.pack("<BIB", 0, 0, 25), errno.EIO),
                       (struct.pack("<BIB", 3, 0, 4), errno.EIO), (struct.pack("<BIB", 0, 4092, 4), 0)):
        (r,) = fw.handle(Packet(Port.MEM, 1, data))
        assert r.data[5] == want
    # malformed: dropped and counted, no answer
    before = fw.dropped
    for ch, data in ((2, b"\0\1"), (1, b"\0\0\0\0\0"), (1, b"\0" * 7), (0, b"\2")):
        assert fw.handle(Packet(Port.MEM, ch, data)) == []
    assert fw.dropped == before + 4
    assert fw.handle(Packet(Port.SETPOINT_HL, 0, b"\x06\x01")) == [] and fw.dropped == before + 5
    # definitions: id beyond the 31 slots refused (ENOEXEC); beyond memory stored, then not started
    assert define(fw, 31, 0, 1) == errno.ENOEXEC
    assert define(fw, 1, 4000, 1) == 0 and start(fw, 1) == errno.EINVAL
    assert define(fw, 2, 0, 32) == 0 and start(fw, 2) == errno.EINVAL
    assert define(fw, 4, 0, 0) == 0 and start(fw, 4) == errno.EINVAL
    assert define(fw, 5, 0, 1, kind=1) == 0 and start(fw, 5) == errno.ENOEXEC  # compressed: not modelled
    assert start(fw, 9) == 0 and start(fw, 200) == 0  # undefined: answered 0, nothing starts (firmware)
    assert define(fw, 6, 0, 1) == 0
    for scale in (0.0, -1.0, float("nan"), float("inf")):
        assert start(fw, 6, scale) == errno.EINVAL
    # a non-finite coefficient
    bad = bytearray(one)
    bad[8:12] = struct.pack("<f", float("nan"))
    upload(fw, bytes(bad), addr=1320)
    assert define(fw, 7, 1320, 1) == 0 and start(fw, 7) == errno.EINVAL
    assert fw.hl_state is high_level.HlState.IDLE  # nothing of the above started anything
    assert sum("refused" in line for line in fw.console_lines) == 8
    # and the vehicle still flies a good one
    assert start(fw, 6) == 0 and fw.hl_state.value == "flying"
    for _ in range(100):
        fw.tick()
    assert math.isfinite(float(fw.quad.p.sum()))


def test_a_trajectory_rewritten_into_garbage_while_flying_is_held_not_flown() -> None:
    fw = fresh()
    climb = np.zeros((4, 8))
    climb[2, :2] = (0.0, 0.25)  # z = 0.25 t
    upload(fw, packed([(2.0, climb)]))
    define(fw, 0, 0, 1)
    assert start(fw, 0, relative=True) == 0
    for _ in range(100):
        fw.tick()
    fw.handle(Packet(Port.MEM, 2, struct.pack("<BI", 0, 64) + struct.pack("<f", float("inf"))))
    for _ in range(100):
        fw.tick()
        sp = fw._applied
        assert isinstance(sp, commander.Track) and all(math.isfinite(v) for v in (*sp.pos, *sp.vel, *sp.acc))
    assert any("not finite" in line for line in fw.console_lines)
    assert isinstance(sp, commander.Track) and sp.pos[2] == pytest.approx(0.25, abs=0.01) and fw.quad.p[2] == pytest.approx(0.25, abs=0.03)


# ========================================================================= cflib flights
@pytest.fixture(scope="module")
def sim() -> Iterator[SoftwareCrazyflies]:
    with software_crazyflies(["--count", "2", "--base-port", str(free_port(2, udp=True)), "--spacing", "1.0",
                              "--log-level", "WARNING"], STARTUP) as s:
        cflib_crtp.init_drivers()
        yield s


@contextlib.contextmanager
def sync_cf(uri: str) -> Iterator[SyncCrazyflie]:
    with SyncCrazyflie(uri, cf=Crazyflie(rw_cache=None)) as scf:
        yield scf


def cflib_pieces(pieces: list[tuple[float, np.ndarray]]) -> list[Poly4D]:
    return [Poly4D(T, *(Poly4D.Poly([float(v) for v in row]) for row in c)) for T, c in pieces]


@pytest.mark.slow
def test_uploaded_figure_eight_is_flown(sim: SoftwareCrazyflies) -> None:
    pieces = figure_eight()
    with sync_cf(sim.uris[FLY]) as scf:
        cf = scf.cf
        (mem,) = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)
        assert mem.size == 4096
        mem.trajectory = cflib_pieces(pieces)
        assert mem.write_data_sync()
        cf.high_level_commander.define_trajectory(1, 0, len(pieces))
        h = Heights(scf)
        stamps: list[int] = []  # of h.rows
        h.conf.data_received_cb.add_callback(lambda ts, _d, _c: stamps.append(ts))
        target: list[tuple[int, np.ndarray]] = []  # (firmware ms, ctrltarget x y z): a second block
        tconf = LogConfig("target", 20)
        for n in ("ctrltarget.x", "ctrltarget.y", "ctrltarget.z"):
            tconf.add_variable(n)
        tconf.data_received_cb.add_callback(
            lambda ts, d, _c: target.append((ts, np.array([d["ctrltarget.x"], d["ctrltarget.y"], d["ctrltarget.z"]]))))
        cf.log.add_config(tconf)
        tconf.start()
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.takeoff(0.5, 1.5)
        h.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.01, 10.0, "take-off to 0.5 m")
        wait_until(lambda: target and abs(target[-1][1][2] - 0.5) < 1e-6, 10.0, "the take-off's setpoint to end")
        origin = target[-1][1]
        n0, k0 = len(h.rows), len(target)
        cf.high_level_commander.start_trajectory(1, 1.0, relative_position=True)
        h.wait(lambda d: abs(d["stateEstimate.x"] - origin[0]) > 0.05, 10.0, "the trajectory to start")
        moved = next(t for t, p in target[k0:] if abs(p[0] - origin[0]) > 1e-4)
        end = h.wait(lambda d: stamps[-1] >= moved + 10500, 30.0, "the trajectory to end")
        rows, ts, tgt = list(h.rows[n0:]), list(stamps[n0:]), list(target[k0:])

        def error(t_begin_ms: int) -> float:
            return max(float(np.abs(origin + poly_point(pieces, max(0.0, (t - t_begin_ms) / 1000.0))[:3] - p).max())
                       for t, p in tgt if t >= t_begin_ms)

        # the start time in firmware ms: the 10 ms tick that fits the logged setpoints best
        t_begin = min(range(moved - 600, moved + 10, 10), key=error)
        assert error(t_begin) < 1e-4  # the setpoints are the polynomial, exactly (float32)
        checked = 0
        for t, d in zip(ts, rows):
            tau = (t - t_begin) / 1000.0
            if any(abs(tau - s) < 0.011 for s in (2.0, 4.5, 7.0, 9.5)):
                want = origin + poly_point(pieces, tau)[:3]
                got = np.array([d["stateEstimate.x"], d["stateEstimate.y"], d["stateEstimate.z"]])
                assert np.abs(got - want).max() < 0.08, (tau, got, want)  # the body lags by ~5 cm at most
                checked += 1
        assert checked >= 4
        assert end["stateEstimate.z"] == pytest.approx(0.5, abs=0.05)
        cf.high_level_commander.land(0.0, 2.0)
        h.landed()


@pytest.mark.slow
def test_oversized_upload_and_bad_definitions_are_refused_over_cflib(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[BAD]) as scf:
        cf = scf.cf
        text: list[str] = []
        refused = threading.Event()

        def on_text(s: str) -> None:
            text.append(s)
            if "".join(text).count("refused") >= 2:
                refused.set()

        cf.console.receivedChar.add_callback(on_text)
        (mem,) = cf.mem.get_mems(MemoryElement.TYPE_TRAJ)
        mem.trajectory = cflib_pieces(figure_eight(1)) * 32  # 4224 bytes
        assert not mem.write_data_sync()
        # malformed memory packets sent raw through cflib's link: no answer, no harm
        for ch, data in ((2, b"\0\1"), (1, b"\0\0"), (0, b"\2")):
            pk = CRTPPacket()
            pk.set_header(CRTPPort.MEM, ch)
            pk.data = data
            cf.send_packet(pk)
        h = Heights(scf)
        cf.high_level_commander.define_trajectory(2, 4000, 1)
        cf.high_level_commander.define_trajectory(3, 0, 32)
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.start_trajectory(2)
        cf.high_level_commander.start_trajectory(3)
        assert refused.wait(5.0), text
        assert "beyond the 4096-byte memory" in "".join(text)
        # still on the floor, still answering, and a small upload still works
        assert h.max_z < 0.01
        assert cf.param.get_value("cfsim.instance") == "1"
        mem.trajectory = cflib_pieces(figure_eight(1))
        assert mem.write_data_sync()
