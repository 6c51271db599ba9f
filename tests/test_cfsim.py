"""The software Crazyflie (``plant/cfsim``) as cflib sees it: real cflib over ``udp://`` against
``python -m plant.cfsim`` started as a real process.

One simulator process with five vehicles on five free UDP ports serves the module; every test flies
its own vehicle, so the tests do not disturb each other. Every wait is on a condition with a
timeout; every cflib link is closed in ``finally`` (its threads would keep the interpreter alive).
A few pure checks of the codec and the trajectory math come first.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from plant.cfsim import commander, crtp, firmware, high_level, motors, supervisor, toc
from plant.quadrotor import Quadrotor, QuadrotorParams
from tests.support import SoftwareCrazyflies, free_port, software_crazyflies, wait_until

pytestmark = pytest.mark.slow  # software Crazyflies over real UDP sockets, flown for seconds

cflib_crtp = pytest.importorskip("cflib.crtp")
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crtp import udpdriver  # noqa: E402
from cflib.crtp.udpdriver import UdpDriver  # noqa: E402
from cflib.utils.encoding import compress_quaternion  # noqa: E402

COUNT = 5
PORT_CONNECT, PORT_LOG, PORT_HL, PORT_WATCHDOG, PORT_STOP = range(COUNT)
"""Which of the simulator's vehicles each test flies (vehicle i listens on the fixture's base port + i)."""
STARTUP = 30.0
"""Upper bound [s] on the simulator coming up (importing numpy on a loaded two-core machine)."""
CONNECT = 15.0
"""Upper bound [s] on cflib reaching fully_connected (the TOCs and every param, one at a time)."""


# =========================================================================== pure checks
def test_codec_round_trip_and_limits() -> None:
    pk = crtp.Packet(crtp.Port.LOG, crtp.LOG_DATA_CHANNEL, bytes(range(30)))
    raw = crtp.encode(pk)
    assert raw[0] == 0x5E  # port 5 << 4 | bits 3..2 | channel 2, as cflib writes it
    assert crtp.decode(raw) == pk
    assert crtp.decode(b"\xff").is_null
    with pytest.raises(crtp.CrtpError):
        crtp.decode(b"")
    with pytest.raises(crtp.CrtpError):
        crtp.decode(bytes(32))


def test_toc_items_fit_a_packet_and_crc_tracks_content() -> None:
    for items in (toc.log_items(toc.LOG_VARS), toc.param_items(toc.PARAM_VARS)):
        assert all(len(it) <= crtp.MAX_DATA for it in items)
        assert toc.crc(items) != toc.crc(items[:-1])
    assert {f"stateEstimate.{n}" for n in ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az")} \
        <= {v.full_name for v in toc.LOG_VARS}


def test_quaternion_decompression_inverts_cflib() -> None:
    rng = np.random.default_rng(7)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        back = np.array(commander.decompress_quaternion(compress_quaternion(q)))
        # same rotation (q and -q), to the 9-bit resolution of the compression
        assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 2e-3


def test_trajectory_is_rest_to_rest() -> None:
    seg = high_level.Segment(1.0, 2.0, (0.0, 0.0, 0.0), (1.0, -2.0, 0.5), 0.0, 1.0)
    start, end, mid = seg.eval(1.0), seg.eval(3.0), seg.eval(2.0)
    np.testing.assert_allclose(start.pos, (0.0, 0.0, 0.0), atol=1e-12)
    np.testing.assert_allclose(end.pos, (1.0, -2.0, 0.5), atol=1e-12)
    np.testing.assert_allclose(mid.pos, (0.5, -1.0, 0.25), atol=1e-12)
    for ev in (start, end):
        np.testing.assert_allclose(ev.vel + ev.acc, np.zeros(6), atol=1e-12)
    # velocity is the derivative of position (central difference)
    h = 1e-5
    for t in (1.3, 2.0, 2.7):
        dp = (np.array(seg.eval(t + h).pos) - np.array(seg.eval(t - h).pos)) / (2 * h)
        np.testing.assert_allclose(seg.eval(t).vel, dp, atol=1e-6)
        dv = (np.array(seg.eval(t + h).vel) - np.array(seg.eval(t - h).vel)) / (2 * h)
        np.testing.assert_allclose(seg.eval(t).acc, dv, atol=1e-5)


def test_watchdog_in_simulated_time() -> None:
    """The firmware alone, ticked by hand: level-out and shutdown at the exact setpoint ages."""
    quad = Quadrotor(QuadrotorParams(), np.zeros(3))
    fw = firmware.Firmware(quad)
    hover = int(fw.param("cfsim.hoverPwm"))

    def rpyt(roll: float, thrust: int) -> None:
        fw.handle(crtp.Packet(crtp.Port.COMMANDER, 0, struct.pack("<fffH", roll, 0.0, 0.0, thrust)))

    fw.tick()
    rpyt(0.0, 0)  # unlock the thrust
    fw.handle(crtp.Packet(crtp.Port.COMMANDER_GENERIC, crtp.GENERIC_META_CHANNEL, struct.pack("<BI", 0, 0)))
    fw.handle(crtp.Packet(crtp.Port.SETPOINT_HL, 0, struct.pack("<BBff?f", 7, 0, 0.5, 0.0, False, 1.5)))
    for _ in range(250):
        fw.tick()
    assert quad.p[2] == pytest.approx(0.5, abs=0.02)
    for _ in range(50):
        rpyt(5.0, hover)
        fw.tick()
    last = fw.k - 1  # the tick of the last setpoint
    states = []  # (tick, supervisor state after it)
    while fw.supervisor_state is not supervisor.SupState.LOCKED and fw.k < last + 300:
        k = fw.k
        fw.tick()
        states.append((k, fw.supervisor_state))
    assert next(k for k, s in states if s is supervisor.SupState.LEVEL_OUT) - last == 51  # age > 500 ms
    assert states[-1] == (last + 201, supervisor.SupState.LOCKED)  # age > 2000 ms
    assert math.degrees(quad.euler()[0]) == pytest.approx(0.0, abs=0.5)  # levelled out
    for _ in range(100):
        fw.tick()
    assert quad.p[2] == pytest.approx(0.0, abs=1e-3) and not quad.motor_commands.any()


# =========================================================================== process helpers
@pytest.fixture(scope="module")
def sim() -> Iterator[SoftwareCrazyflies]:
    base = free_port(COUNT, udp=True)
    with software_crazyflies(["--count", str(COUNT), "--base-port", str(base), "--log-level", "WARNING"],
                             STARTUP) as sim:
        assert sim.uris == {i: f"udp://127.0.0.1:{base + i}" for i in range(COUNT)}
        cflib_crtp.init_drivers()
        yield sim
        sim.proc.send_signal(signal.SIGTERM)
        assert sim.proc.wait(timeout=10) == 0, sim.stderr


@contextlib.contextmanager
def connected(uri: str) -> Iterator[Crazyflie]:
    """A cflib Crazyflie fully connected to ``uri``; its link is closed on exit, whatever happens."""
    cf = Crazyflie(rw_cache=None)
    done = threading.Event()
    failure: list[str] = []
    cf.fully_connected.add_callback(lambda _uri: done.set())
    cf.connection_failed.add_callback(lambda _uri, msg: (failure.append(msg), done.set()))
    try:
        cf.open_link(uri)
        assert done.wait(CONNECT), f"{uri}: not fully connected within {CONNECT:g} s"
        assert not failure, failure
        yield cf
    finally:
        cf.close_link()


class LogStream:
    """Samples of one log block, with the monotonic time each arrived; waits on conditions."""

    def __init__(self, cf: Crazyflie, names: list[str], period_ms: int = 10) -> None:
        self.samples: list[tuple[float, int, dict[str, float]]] = []
        self._cond = threading.Condition()
        self.config = LogConfig(f"test{id(self)}", period_ms)
        for n in names:
            self.config.add_variable(n)
        self.config.data_received_cb.add_callback(self._on_data)
        cf.log.add_config(self.config)
        self.config.start()

    def _on_data(self, stamp: int, data: dict[str, float], _conf: LogConfig) -> None:
        with self._cond:
            self.samples.append((time.monotonic(), stamp, data))
            self._cond.notify_all()

    @property
    def last(self) -> dict[str, float]:
        with self._cond:
            return self.samples[-1][2]

    def wait(self, pred: Callable[[dict[str, float]], bool], timeout: float, what: str) -> tuple[float, dict[str, float]]:
        """Wait for a sample that arrives from now on and satisfies ``pred``; returns its arrival
        time and values, or fails naming ``what``."""
        deadline = time.monotonic() + timeout
        with self._cond:
            seen = len(self.samples)
            while True:
                for t, _, d in self.samples[seen:]:
                    if pred(d):
                        return t, d
                seen = len(self.samples)
                left = deadline - time.monotonic()
                if left <= 0:
                    last = self.samples[-1][2] if self.samples else None
                    pytest.fail(f"waited {timeout:g} s for {what}; last sample {last}")
                self._cond.wait(left)

    def since(self, t0: float) -> list[tuple[float, dict[str, float]]]:
        with self._cond:
            return [(t, d) for t, _, d in self.samples if t >= t0]


def cpu_seconds(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` so far."""
    fields_ = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields_[11]) + int(fields_[12])) / os.sysconf("SC_CLK_TCK")


# =========================================================================== against cflib
def test_every_vehicle_answers_scan_connect_and_params(sim: SoftwareCrazyflies,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    # cflib scans ten ports from its fixed 19850, which another run on this machine may hold: here it
    # scans from the simulator's allocated base port instead
    monkeypatch.setattr(udpdriver, "_BASE_PORT", int(sim.uris[0].rpartition(":")[2]))
    found = {uri for uri, _ in UdpDriver().scan_interface()}
    assert {sim.uris[i] for i in range(COUNT)} <= found
    with connected(sim.uris[PORT_CONNECT]) as cf:
        assert cf.platform.get_protocol_version() == crtp.PROTOCOL_VERSION
        names = {f"{g}.{n}" for g, group in cf.log.toc.toc.items() for n in group}
        assert names == {v.full_name for v in toc.LOG_VARS}
        assert cf.param.get_value("cfsim.instance") == "0"
        mass = float(cf.param.get_value("cfsim.mass"))
        hover = int(cf.param.get_value("cfsim.hoverPwm"))
        qp = QuadrotorParams()
        assert hover == pytest.approx(motors.thrust_to_pwm(mass * qp.g, qp.motor_thrust_max), abs=1.0)
        # a write is echoed and read back
        updated = threading.Event()
        cf.param.add_update_callback(group="hlCommander", name="groupmask", cb=lambda _n, v: updated.set())
        cf.param.set_value("hlCommander.groupmask", 3)
        assert updated.wait(5.0)
        assert cf.param.get_value("hlCommander.groupmask") == "3"
        with pytest.raises(AttributeError):
            cf.param.set_value("cfsim.mass", 1.0)  # read-only in the TOC
    # several instances at once, each itself
    # (not the vehicles whose RPYT thrust lock a later test checks: cflib's close_link unlocks it
    # by sending a zero-thrust setpoint)
    with connected(sim.uris[1]) as cf1, connected(sim.uris[2]) as cf2:
        assert (cf1.param.get_value("cfsim.instance"), cf2.param.get_value("cfsim.instance")) == ("1", "2")


def test_log_block_at_100_hz(sim: SoftwareCrazyflies) -> None:
    names = [f"stateEstimate.{n}" for n in ("x", "y", "z", "vx", "vy", "vz")]
    with connected(sim.uris[PORT_LOG]) as cf:
        stream = LogStream(cf, names)
        t0, _ = stream.wait(lambda d: True, 5.0, "the first log packet")
        c0 = cpu_seconds(sim.proc.pid)
        end = t0 + 2.0
        t1, _ = stream.wait(lambda d: time.monotonic() >= end, 4.0, "two seconds of samples")
        cpu = (cpu_seconds(sim.proc.pid) - c0) / (t1 - t0)
        got = stream.since(t0)
        stamps = [s for t, s, _ in stream.samples if t >= t0]
    # five vehicles on the floor, one of them streaming: one 100 Hz wake-up serves them all
    assert cpu < 0.25, cpu
    rate = (len(got) - 1) / (got[-1][0] - got[0][0])
    assert 90 <= rate <= 110, rate
    assert set(got[-1][1]) == set(names)
    assert got[-1][1]["stateEstimate.x"] == pytest.approx(0.5, abs=1e-6)  # vehicle 1 starts at x = 0.5
    assert got[-1][1]["stateEstimate.z"] == pytest.approx(0.0, abs=1e-3)  # resting on the floor
    steps = np.diff(stamps)
    assert np.all(steps == 10), steps  # firmware timestamps [ms]: one packet every 10 ms


def test_high_level_take_off_and_land(sim: SoftwareCrazyflies) -> None:
    with connected(sim.uris[PORT_HL]) as cf:
        stream = LogStream(cf, ["stateEstimate.z", "stateEstimate.vz", "stabilizer.thrust", "supervisor.info"])
        stream.wait(lambda d: True, 5.0, "the first log packet")
        # as on a real Crazyflie: an earlier close_link left a zero setpoint at CRTP priority, which
        # the high-level commander cannot override until notify-stop relaxes the priority
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.takeoff(0.5, 2.0)
        stream.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.02 and abs(d["stateEstimate.vz"]) < 0.05,
                    6.0, "z to settle at the take-off height 0.5 m")
        assert max(d["stateEstimate.z"] for _, d in stream.since(0.0)) < 0.55  # no overshoot to speak of
        flying = int(stream.last["supervisor.info"])
        assert flying & (1 << supervisor.BIT_FLYING) and flying & (1 << supervisor.BIT_HL_ACTIVE)
        # cflib waits only 0.2 s for the answer (an empty list after that): ask again on a loaded machine
        states = wait_until(lambda: set(cf.supervisor.read_state_list()), 5.0, "the supervisor state")
        assert {"Is flying", "Can fly", "HL control is active"} <= states
        # go_to, relative, with a quarter turn (yaw counter-clockwise positive, as in the firmware)
        pose = LogStream(cf, ["stateEstimate.x", "stateEstimate.y", "stateEstimate.yaw"])
        x0 = pose.wait(lambda d: True, 2.0, "a pose sample")[1]["stateEstimate.x"]
        cf.high_level_commander.go_to(0.3, 0.0, 0.0, math.pi / 2, 1.5, relative=True)
        pose.wait(lambda d: abs(d["stateEstimate.x"] - (x0 + 0.3)) < 0.02 and abs(d["stateEstimate.yaw"] - 90) < 3,
                  4.0, "go_to: x + 0.3 m and yaw 90 deg")
        cf.high_level_commander.land(0.0, 2.0)
        stream.wait(lambda d: d["stateEstimate.z"] < 0.01 and d["stabilizer.thrust"] == 0.0, 6.0,
                    "landing: z at the floor and the motors off")
        info = int(stream.last["supervisor.info"])
        assert not info & (1 << supervisor.BIT_LOCKED) and info & (1 << supervisor.BIT_CAN_FLY)


def test_setpoints_fly_then_watchdog_levels_out_and_cuts(sim: SoftwareCrazyflies) -> None:
    with connected(sim.uris[PORT_WATCHDOG]) as cf:
        hover = int(cf.param.get_value("cfsim.hoverPwm"))
        att = LogStream(cf, ["stateEstimate.z", "stateEstimate.vz", "stateEstimate.roll", "stateEstimate.pitch",
                             "stabilizer.thrust", "stateEstimate.vy"])
        vel = LogStream(cf, ["stateEstimate.vx", "supervisor.info"])
        att.wait(lambda d: True, 5.0, "the first log packet")
        # unlock the RPYT thrust, hand back to the high-level commander, take off
        cf.commander.send_setpoint(0, 0, 0, 0)
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.takeoff(0.5, 1.5)
        att.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.03, 5.0, "take-off to 0.5 m")

        pace = threading.Event()

        def fly(seconds: float, roll: float, pitch: float) -> tuple[float, float]:
            """send_setpoint at 50 Hz with an altitude PD on the logged z; returns the monotonic
            times just before and just after the last send."""
            end = time.monotonic() + seconds
            while True:
                d = att.last
                thrust = hover + 38000 * (0.5 - d["stateEstimate.z"]) - 25000 * d["stateEstimate.vz"]
                before = time.monotonic()
                cf.commander.send_setpoint(roll, pitch, 0, int(min(60000, max(10001, thrust))))
                after = time.monotonic()
                if after >= end:
                    return before, after
                pace.wait(0.02)

        t_fly = time.monotonic()
        fly(0.8, 0.0, 5.0)  # cflib pitch +5 deg: nose down, accelerates towards +x
        d = att.last
        assert d["stateEstimate.pitch"] == pytest.approx(-5.0, abs=0.5)  # logged in the legacy sign
        assert vel.last["stateEstimate.vx"] > 0.1
        vy0 = d["stateEstimate.vy"]
        # roll +5 deg: thrust tilts towards -y; the last setpoint leaves between sent0 and sent1
        sent0, sent1 = fly(0.8, 5.0, 0.0)
        d = att.last
        assert d["stateEstimate.roll"] == pytest.approx(5.0, abs=0.5)
        assert d["stateEstimate.vy"] < vy0 - 0.1
        zs = [d["stateEstimate.z"] for _, d in att.since(t_fly)]
        assert 0.4 < min(zs) and max(zs) < 0.6, (min(zs), max(zs))  # the stream kept it flying

        # the watchdog counts from the last setpoint; the firmware ticks every 10 ms
        t_level, _ = att.wait(lambda d: abs(d["stateEstimate.roll"]) < 1.0, 3.0, "the watchdog to level out")
        still = [d["stateEstimate.roll"] for t, d in att.since(sent1) if t < sent0 + 0.45]
        assert still and min(still) > 4.0, still  # the last roll setpoint held until the watchdog
        assert sent0 + 0.48 < t_level < sent1 + 0.9, (t_level - sent0, t_level - sent1)
        t_cut, _ = att.wait(lambda d: d["stabilizer.thrust"] == 0.0, 4.0, "the watchdog to cut the motors")
        assert sent0 + 1.98 < t_cut < sent1 + 2.4, (t_cut - sent0, t_cut - sent1)
        assert all(d["stabilizer.thrust"] > 0 for t, d in att.since(sent1) if t < sent0 + 1.95)
        att.wait(lambda d: d["stateEstimate.z"] < 0.02, 3.0, "the vehicle to fall to the floor")
        vel.wait(lambda d: int(d["supervisor.info"]) & (1 << supervisor.BIT_LOCKED), 1.0, "the supervisor to lock")


def test_stop_setpoint_thrust_lock_and_notify_stop(sim: SoftwareCrazyflies) -> None:
    with connected(sim.uris[PORT_STOP]) as cf:
        hover = int(cf.param.get_value("cfsim.hoverPwm"))
        stream = LogStream(cf, ["stateEstimate.z", "stabilizer.thrust", "supervisor.info"])
        stream.wait(lambda d: True, 5.0, "the first log packet")
        # RPYT thrust is locked until a zero-thrust setpoint arrives
        for _ in range(10):
            cf.commander.send_setpoint(0, 0, 0, hover + 5000)
        stream.wait(lambda d: True, 1.0, "a log packet")
        assert stream.wait(lambda d: True, 1.0, "a log packet")[1]["stabilizer.thrust"] == 0.0
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.takeoff(0.4, 1.0)
        stream.wait(lambda d: d["stateEstimate.z"] > 0.3, 4.0, "take-off")
        # a stop setpoint cuts the motors at once and the high-level commander gives way
        cf.commander.send_stop_setpoint()
        t0 = time.monotonic()
        t_off, _ = stream.wait(lambda d: d["stabilizer.thrust"] == 0.0, 1.0, "the stop setpoint to cut the motors")
        assert t_off - t0 < 0.1
        stream.wait(lambda d: d["stateEstimate.z"] < 0.02, 3.0, "the fall to the floor")
        # notify-stop hands over to the (stopped) high-level commander, which keeps the watchdog fed
        cf.commander.send_notify_setpoint_stop()
        t1 = time.monotonic()
        stream.wait(lambda d: time.monotonic() > t1 + 2.5, 4.0, "2.5 s after notify-stop")
        info = int(stream.last["supervisor.info"])
        assert not info & (1 << supervisor.BIT_LOCKED) and info & (1 << supervisor.BIT_CAN_FLY)
        # ... so the vehicle can take off again
        cf.high_level_commander.takeoff(0.3, 1.0)
        stream.wait(lambda d: d["stateEstimate.z"] > 0.25, 4.0, "a second take-off")



def test_generic_position_full_state_and_velocity_setpoints(sim: SoftwareCrazyflies) -> None:
    with connected(sim.uris[PORT_CONNECT]) as cf:
        stream = LogStream(cf, ["stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "stateEstimate.vx",
                                "stateEstimate.yaw"])
        pace = threading.Event()

        def stream_until(cond: Callable[[dict[str, float]], bool], send: Callable[[], None], what: str,
                         timeout: float = 15.0) -> None:
            """Send the setpoint at 50 Hz until the logged state meets ``cond`` (the simulator runs in
            real time: under load it takes longer, never a different path)."""
            end = time.monotonic() + timeout
            while not (stream.last and cond(stream.last)):
                if time.monotonic() > end:
                    pytest.fail(f"no {what} within {timeout} s: last {stream.last}")
                send()
                pace.wait(0.02)

        stream.wait(lambda d: True, 5.0, "the first log packet")
        stream_until(lambda d: abs(d["stateEstimate.y"] - 0.2) < 0.03 and abs(d["stateEstimate.z"] - 0.4) < 0.03
                     and abs(d["stateEstimate.yaw"] - 30.0) < 2.0,
                     lambda: cf.commander.send_position_setpoint(0.0, 0.2, 0.4, 30.0), "position (0, 0.2, 0.4), yaw 30")
        q = [0.0, 0.0, math.sin(math.radians(-20) / 2), math.cos(math.radians(-20) / 2)]  # x, y, z, w
        stream_until(lambda d: abs(d["stateEstimate.x"] - 0.1) < 0.03 and abs(d["stateEstimate.z"] - 0.5) < 0.03
                     and abs(d["stateEstimate.yaw"] + 20.0) < 2.0,
                     lambda: cf.commander.send_full_state_setpoint((0.1, 0.0, 0.5), (0, 0, 0), (0, 0, 0), q, 0, 0, 0),
                     "full state (0.1, 0, 0.5), yaw -20")
        stream_until(lambda d: abs(d["stateEstimate.vx"] - 0.3) < 0.05,
                     lambda: cf.commander.send_velocity_world_setpoint(0.3, 0.0, 0.0, 0.0), "vx 0.3 m/s")
        # back to the high-level commander, which lands from where the vehicle is
        cf.commander.send_notify_setpoint_stop()
        cf.high_level_commander.land(0.0, 1.5)
        stream.wait(lambda d: d["stateEstimate.z"] < 0.01, 4.0, "landing")
