"""The common cflib paths, end to end, against the software Crazyflie: every client here is cflib
alone (``MotionCommander``, ``PositionHlCommander``, the commander's hover / z-distance / manual
setpoints, the high-level spiral, the console, persistent parameters), as a lab script would be;
each flight is checked on the logged ``stateEstimate.z``: the commanded height is reached and the
vehicle lands. Then the realism options: seeded, deterministic, off by default.

One simulator process serves the flights, one vehicle per test (eight free UDP ports); the realism
flight has its own process (one more).
"""

from __future__ import annotations

import contextlib
import math
import socket
import struct
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from plant.cfsim import crtp, firmware, high_level, realism
from plant.quadrotor import Quadrotor, QuadrotorParams
from tests.support import SoftwareCrazyflies, free_port, software_crazyflies

cflib_crtp = pytest.importorskip("cflib.crtp")
from cflib.crazyflie import Crazyflie  # noqa: E402
from cflib.crazyflie.log import LogConfig  # noqa: E402
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie  # noqa: E402
from cflib.positioning.motion_commander import MotionCommander  # noqa: E402
from cflib.positioning.position_hl_commander import PositionHlCommander  # noqa: E402

COUNT = 8
MC, HOVER, ZDIST, MANUAL, SPIRAL, POSHL, CONSOLE, PARAMS = range(COUNT)
STARTUP = 30.0


# =========================================================================== pure: realism
def _hover_run(noise: realism.NoiseConfig | None, battery: realism.BatteryConfig | None,
               ticks: int = 400) -> list[list[float]]:
    """The firmware alone, ticked by hand: take off to 0.5 m and hover; every tick's telemetry."""
    fw = firmware.Firmware(Quadrotor(QuadrotorParams(), np.zeros(3)),
                           firmware.FirmwareConfig(noise=noise, battery=battery))
    fw.handle(crtp.Packet(crtp.Port.SETPOINT_HL, 0, struct.pack("<BBff?f", 7, 0, 0.5, 0.0, False, 1.0)))
    out = []
    for _ in range(ticks):
        fw.tick()
        out.append(fw.telemetry())
    return out


def _col(rows: list[list[float]], name: str) -> np.ndarray:
    from plant.cfsim import toc
    i = [v.full_name for v in toc.LOG_VARS].index(name)
    return np.array([r[i] for r in rows])


@pytest.mark.parametrize("what", ["noise", "battery"])
def test_realism_is_deterministic_for_a_seed(what: str) -> None:
    def run(seed: int) -> list[list[float]]:
        if what == "noise":
            return _hover_run(realism.NoiseConfig(0.1, 0.05, 0.5, seed), None)
        return _hover_run(None, realism.BatteryConfig(capacity_mah=1.0, charge=1.0))
    a, b = run(3), run(3)
    assert a == b  # bit for bit
    if what == "noise":
        c = run(4)
        assert a != c
        # the estimate is off the truth by about sigma, the controller flies on it
        err = _col(a, "stateEstimate.z")[200:] - 0.5
        assert 0.01 < float(np.std(err)) < 0.3


def test_noise_off_by_default_and_of_the_stated_size() -> None:
    plain = _hover_run(None, None)
    assert abs(_col(plain, "stateEstimate.z")[-1] - 0.5) < 0.01  # the truth, as before
    assert np.all(_col(plain, "pm.vbat") == 3.9)
    noise = realism.EstimatorNoise(realism.NoiseConfig(0.1, 0.05, 0.5, 11), firmware.PERIOD)
    errs = []
    for _ in range(40000):
        noise.step()
        errs.append(noise.error.copy())
    e = np.array(errs)
    np.testing.assert_allclose(e[:, :3].std(axis=0), 0.1, rtol=0.15)
    np.testing.assert_allclose(e[:, 3:].std(axis=0), 0.05, rtol=0.15)


def test_battery_drains_with_thrust_and_reports_low_power() -> None:
    cfg = realism.BatteryConfig(capacity_mah=20.0)
    idle, flying = realism.Battery(cfg), realism.Battery(cfg)
    states = []
    for _ in range(6000):  # 60 s
        idle.step(0.0, 0.284, 0.01)
        flying.step(0.284, 0.284, 0.01)
        states.append(flying.state)
    assert idle.charge > 0.95 and idle.state == realism.PM_BATTERY
    assert flying.charge < idle.charge and flying.vbat < idle.vbat
    assert realism.PM_LOW_POWER in states  # on the way down
    assert states[-1] == realism.PM_SHUTDOWN  # 2.15 A for 60 s empties 20 mAh


def test_link_model_is_deterministic_and_loses_the_stated_share() -> None:
    cfg = realism.LinkConfig(latency=0.02, jitter=0.01, loss=0.2, seed=5)
    a = [realism.LinkModel(cfg).decide() for _ in range(1)]
    m1, m2 = realism.LinkModel(cfg), realism.LinkModel(cfg)
    d1 = [m1.decide() for _ in range(5000)]
    d2 = [m2.decide() for _ in range(5000)]
    assert d1 == d2 and a[0] == d1[0]
    lost = sum(d is None for d in d1) / len(d1)
    assert 0.18 < lost < 0.22
    assert all(0.02 <= d <= 0.03 for d in d1 if d is not None)
    with pytest.raises(ValueError, match="loss"):
        realism.LinkConfig(loss=1.5)
    with pytest.raises(ValueError, match="latency"):
        realism.LinkConfig(latency=float("nan"))


def test_spiral_meets_the_firmware_end_conditions() -> None:
    """The spiral's start and end velocities are the ones ``plan_spiral_from`` imposes."""
    r0, rf, T, angle = 0.3, 0.5, 4.0, math.pi
    sp = high_level.Spiral(0.0, T, (1.0, 2.0, 0.5), 0.0, angle, r0, rf, 0.2, False, False)
    start, mid = sp.eval(0.0), sp.eval(T - 1e-9)
    sense, omz, dr = -1.0, math.pi / T, (rf - r0) / T
    np.testing.assert_allclose(start.pos, (1.0, 2.0, 0.5), atol=1e-12)
    np.testing.assert_allclose(start.vel, (-sense * r0 * omz, sense * dr, 0.2 / T), atol=1e-12)  # phi0 = 0
    assert mid.pos[2] == pytest.approx(0.7) and mid.yaw == pytest.approx(angle)
    centre = (1.0 + sense * r0 * 0.0, 2.0 - sense * r0 * 1.0)
    assert math.dist(mid.pos[:2], centre) == pytest.approx(rf)


# =========================================================================== real processes
@pytest.fixture(scope="module")
def sim() -> Iterator[SoftwareCrazyflies]:
    with software_crazyflies(["--count", str(COUNT), "--base-port", str(free_port(COUNT, udp=True)), "--spacing", "1.0",
                              "--log-level", "WARNING"], STARTUP) as s:
        cflib_crtp.init_drivers()
        yield s


@contextlib.contextmanager
def sync_cf(uri: str) -> Iterator[SyncCrazyflie]:
    """cflib's own SyncCrazyflie (closes the link on exit)."""
    with SyncCrazyflie(uri, cf=Crazyflie(rw_cache=None)) as scf:
        yield scf


class Heights:
    """``stateEstimate.z`` (and friends) logged at 50 Hz by cflib; waits on conditions."""

    def __init__(self, scf: SyncCrazyflie, extra: tuple[str, ...] = ()) -> None:
        self.rows: list[dict[str, float]] = []
        self._cond = threading.Condition()
        self.conf = LogConfig("heights", 20)
        for n in ("stateEstimate.z", "stateEstimate.x", "stateEstimate.y", "stabilizer.thrust", *extra):
            self.conf.add_variable(n)
        self.conf.data_received_cb.add_callback(self._on)
        scf.cf.log.add_config(self.conf)
        self.conf.start()
        self.wait(lambda d: True, 5.0, "the first log packet")

    def _on(self, _t: int, data: dict[str, float], _c: LogConfig) -> None:
        with self._cond:
            self.rows.append(data)
            self._cond.notify_all()

    def wait(self, pred: Callable[[dict[str, float]], bool], timeout: float, what: str) -> dict[str, float]:
        deadline = time.monotonic() + timeout
        with self._cond:
            seen = len(self.rows)
            while True:
                for d in self.rows[seen:]:
                    if pred(d):
                        return d
                seen = len(self.rows)
                left = deadline - time.monotonic()
                if left <= 0:
                    pytest.fail(f"waited {timeout:g} s for {what}; last {self.rows[-1] if self.rows else None}")
                self._cond.wait(left)

    def landed(self, timeout: float = 6.0) -> None:
        self.wait(lambda d: d["stateEstimate.z"] < 0.02 and d["stabilizer.thrust"] == 0.0, timeout,
                  "landing: z at the floor, motors off")

    @property
    def max_z(self) -> float:
        with self._cond:
            return max(d["stateEstimate.z"] for d in self.rows)


def stream(seconds: float, send: Callable[[], None], period: float = 0.02) -> None:
    pace = threading.Event()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        send()
        pace.wait(period)


@pytest.mark.slow
def test_motion_commander_takes_off_moves_and_lands(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[MC]) as scf:
        h = Heights(scf)
        x0 = h.rows[-1]["stateEstimate.x"]
        with MotionCommander(scf, default_height=0.4) as mc:  # resets kalman.resetEstimation first
            h.wait(lambda d: abs(d["stateEstimate.z"] - 0.4) < 0.05, 4.0, "take-off to 0.4 m")
            mc.forward(0.3)
            h.wait(lambda d: abs(d["stateEstimate.x"] - (x0 + 0.3)) < 0.05, 3.0, "forward 0.3 m")
        h.landed()
        assert 0.35 < h.max_z < 0.5


@pytest.mark.slow
def test_hover_setpoints_fly_and_land(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[HOVER]) as scf:
        h = Heights(scf, ("stateEstimate.vy",))
        cf = scf.cf
        for i in range(50):  # climb to 0.5 m in 1 s
            cf.commander.send_hover_setpoint(0.0, 0.0, 0.0, 0.5 * i / 50)
            time.sleep(0.02)
        stream(1.5, lambda: cf.commander.send_hover_setpoint(0.0, 0.2, 0.0, 0.5))  # body y = left
        d = h.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.03, 2.0, "hover at 0.5 m")
        assert d["stateEstimate.vy"] == pytest.approx(0.2, abs=0.05)
        for i in range(50, 0, -1):
            cf.commander.send_hover_setpoint(0.0, 0.0, 0.0, 0.5 * i / 50)
            time.sleep(0.02)
        cf.commander.send_stop_setpoint()
        cf.commander.send_notify_setpoint_stop()
        h.landed()


@pytest.mark.slow
def test_zdistance_setpoints_hold_the_height(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[ZDIST]) as scf:
        h = Heights(scf, ("stateEstimate.roll", "stateEstimate.vx"))
        cf = scf.cf
        stream(2.5, lambda: cf.commander.send_zdistance_setpoint(0.0, 0.0, 0.0, 0.4))
        h.wait(lambda d: abs(d["stateEstimate.z"] - 0.4) < 0.03, 1.0, "z-distance hold at 0.4 m")
        stream(0.5, lambda: cf.commander.send_zdistance_setpoint(4.0, 0.0, 0.0, 0.4))
        d = h.wait(lambda d: True, 1.0, "a sample")
        assert d["stateEstimate.roll"] == pytest.approx(4.0, abs=0.7)
        assert abs(d["stateEstimate.z"] - 0.4) < 0.05
        stream(1.5, lambda: cf.commander.send_zdistance_setpoint(0.0, 0.0, 0.0, 0.02))
        cf.commander.send_stop_setpoint()
        cf.commander.send_notify_setpoint_stop()
        h.landed()


@pytest.mark.slow
def test_manual_setpoints_fly(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[MANUAL]) as scf:
        h = Heights(scf, ("stateEstimate.vz",))
        cf = scf.cf
        hover = int(cf.param.get_value("cfsim.hoverPwm"))
        hover_pct = (hover - 10001) / (60000 - 10001) * 100.0
        end = time.monotonic() + 3.0
        pace = threading.Event()
        while time.monotonic() < end:  # an altitude PD on the logged height, in thrust percent
            d = h.rows[-1]
            pct = hover_pct + 70.0 * (0.5 - d["stateEstimate.z"]) - 45.0 * d["stateEstimate.vz"]
            cf.commander.send_setpoint_manual(0.0, 0.0, 0.0, min(100.0, max(0.0, pct)), False)
            pace.wait(0.02)
        h.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.08, 1.0, "manual flight near 0.5 m")
        assert h.max_z < 0.8
        cf.commander.send_stop_setpoint()
        cf.commander.send_notify_setpoint_stop()
        h.landed()


@pytest.mark.slow
def test_high_level_spiral(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[SPIRAL]) as scf:
        h = Heights(scf)
        hl = scf.cf.high_level_commander
        scf.cf.commander.send_notify_setpoint_stop()
        hl.takeoff(0.4, 1.5)
        start = h.wait(lambda d: abs(d["stateEstimate.z"] - 0.4) < 0.02, 4.0, "take-off to 0.4 m")
        hl.spiral(math.pi, 0.3, 0.3, 0.3, 3.0)  # half a turn, counter-clockwise, rising 0.3 m
        end = h.wait(lambda d: abs(d["stateEstimate.z"] - 0.7) < 0.03, 5.0, "the spiral to end at 0.7 m")
        moved = math.dist((start["stateEstimate.x"], start["stateEstimate.y"]),
                          (end["stateEstimate.x"], end["stateEstimate.y"]))
        assert moved == pytest.approx(0.6, abs=0.06)  # half a turn of radius 0.3: across the diameter
        hl.land(0.0, 2.0)
        h.landed()


@pytest.mark.slow
def test_position_hl_commander(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[POSHL]) as scf:
        h = Heights(scf)
        x0 = h.rows[-1]["stateEstimate.x"]
        scf.cf.commander.send_notify_setpoint_stop()
        with PositionHlCommander(scf, x=x0, y=0.0, z=0.0, default_height=0.5, default_velocity=0.5,
                                 controller=PositionHlCommander.CONTROLLER_PID) as pc:
            h.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.03, 3.0, "take-off to 0.5 m")
            pc.forward(0.3)
            h.wait(lambda d: abs(d["stateEstimate.x"] - (x0 + 0.3)) < 0.03, 3.0, "forward 0.3 m")
        assert scf.cf.param.get_value("stabilizer.controller") == "1"
        h.landed()


@pytest.mark.slow
def test_console_prints_text(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[CONSOLE]) as scf:
        text: list[str] = []
        got = threading.Event()

        def on_text(s: str) -> None:
            text.append(s)
            if "estimate reset" in "".join(text):
                got.set()

        scf.cf.console.receivedChar.add_callback(on_text)
        scf.cf.param.set_value("kalman.resetEstimation", "1")
        assert got.wait(5.0), text
        assert "CFSIM: state estimate reset\n" in "".join(text)


@pytest.mark.slow
def test_lab_params_and_persistence(sim: SoftwareCrazyflies) -> None:
    with sync_cf(sim.uris[PARAMS]) as scf:
        p = scf.cf.param
        assert p.get_value("stabilizer.estimator") == "2"
        assert p.get_value("stabilizer.controller") == "1"
        assert p.get_value("commander.enHighLevel") == "1"
        assert p.get_value("kalman.resetEstimation") == "0"
        toc = p.toc.get_element_by_complete_name("stabilizer.controller")
        assert toc.is_persistent()
        done = threading.Event()
        result: list[object] = []

        def cb(name: str, value: object) -> None:
            result.append(value)
            done.set()

        p.set_value("stabilizer.controller", "2")
        p.persistent_store("stabilizer.controller", cb)
        assert done.wait(5.0) and result == [True]
        done.clear()
        p.persistent_get_state("stabilizer.controller", cb)
        assert done.wait(5.0)
        state = result[-1]
        assert state.is_stored and state.default_value == 1 and state.stored_value == 2  # type: ignore[attr-defined]
        log = scf.cf.log.toc
        assert {"vbat", "state", "batteryLevel"} <= set(log.toc["pm"])
        assert {"roll", "pitch", "yaw", "thrust"} <= set(log.toc["stabilizer"])


@pytest.mark.slow
def test_realism_flight_noise_battery_and_latency() -> None:
    """Noise, a nearly empty battery and 30 ms each way on the link: cflib still flies the vehicle,
    the battery reports low power under thrust, the link echo comes back late."""
    port = free_port(udp=True)
    args = ["--count", "1", "--base-port", str(port), "--noise", "0.05", "--seed", "2", "--battery",
            "--battery-charge", "0.2", "--latency", "30", "--log-level", "WARNING"]
    with software_crazyflies(args, STARTUP) as s:
        cflib_crtp.init_drivers()
        # the latency, seen with a plain UDP socket: a link echo (port 15, channel 0)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(2.0)
            t0 = time.monotonic()
            sock.sendto(bytes((0xFC,)) + b"ping", ("127.0.0.1", port))
            assert sock.recv(64)[1:] == b"ping"
            assert time.monotonic() - t0 >= 0.06
        with sync_cf(s.uris[0]) as scf:
            h = Heights(scf, ("pm.vbat", "pm.state"))
            rest = h.rows[-1]
            assert rest["pm.state"] == realism.PM_BATTERY and 3.2 < rest["pm.vbat"] < 3.3
            scf.cf.commander.send_notify_setpoint_stop()
            scf.cf.high_level_commander.takeoff(0.5, 1.5)
            h.wait(lambda d: abs(d["stateEstimate.z"] - 0.5) < 0.15, 4.0, "take-off to about 0.5 m")
            low = h.wait(lambda d: d["pm.state"] == realism.PM_LOW_POWER, 8.0, "low power (5 s under 3.2 V)")
            assert low["pm.vbat"] < 3.2
            scf.cf.high_level_commander.land(0.0, 1.5)
            h.wait(lambda d: d["stateEstimate.z"] < 0.15 and d["stabilizer.thrust"] == 0.0, 6.0, "landing")
