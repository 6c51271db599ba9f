"""Link monitoring: the pure judge (:class:`plant.radio.LinkMonitor`), and a Crazyflie plant flying
real cflib through a software radio that degrades (``python -m plant.cfsim --radio --degrade``):
first a warning, then the failsafe (the vehicle holds, then lands on its own)."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from plant import radio
from tests import support
from tether import mission as ms
from tether.catalog import builtin_path


# =========================================================================== the pure judge
def _feed(mon: radio.LinkMonitor, t0: float, t1: float, rate: float) -> list[str]:
    """Packets at ``rate`` from ``t0`` to ``t1`` [s], judged every 10 ms as a plant does; the states."""
    states, due = [], t0
    for t in np.arange(t0, t1, 0.01):
        while due < t + 0.01:
            mon.packet(float(due))
            due += 1.0 / rate
        states.append(mon.judge(float(t) + 0.01).state)
    return states


def test_a_full_stream_is_ok_a_thin_one_warns_then_fails_and_stays_failed() -> None:
    mon = radio.LinkMonitor(200.0, radio.LinkLimits(fail_after=1.0))
    assert set(_feed(mon, 0.0, 2.0, 200.0)) == {radio.OK}
    states = _feed(mon, 2.0, 4.0, 170.0)  # 85 %: below Crazyswarm2's 0.9
    assert states[-1] == radio.WARN and radio.FAIL not in states
    assert mon.judge(4.0).rate == pytest.approx(0.85, abs=0.01)
    states = _feed(mon, 4.0, 6.5, 60.0)  # 30 %: below 50 % from about 4.7 s
    failed = 4.0 + 0.01 * states.index(radio.FAIL)
    assert 5.5 <= failed <= 5.9, failed  # after fail_after (1 s) below the limit
    assert set(_feed(mon, 6.5, 9.0, 200.0)) == {radio.FAIL}  # a failed link is landed, not flown again


def test_a_dropout_shorter_than_fail_after_does_not_fail_the_link() -> None:
    mon = radio.LinkMonitor(100.0)
    _feed(mon, 0.0, 2.0, 100.0)
    states = _feed(mon, 2.0, 5.0, 1e-9) + _feed(mon, 5.0, 8.0, 100.0)  # three seconds silent (a starved host)
    assert radio.FAIL not in states and radio.WARN in states and states[-1] == radio.OK


def test_a_slow_ping_warns_and_a_very_slow_one_fails() -> None:
    mon = radio.LinkMonitor(100.0, radio.LinkLimits(fail_after=1.0))
    _feed(mon, 0.0, 1.0, 100.0)
    for k in range(10):  # pings at 10 Hz; one stalled one is no trend
        mon.round_trip(1.0 + 0.1 * k, 1.2 if k == 3 else 0.01)
    _feed(mon, 1.0, 2.0, 100.0)
    assert mon.judge(2.0).state == radio.OK
    for k in range(10):
        mon.round_trip(2.0 + 0.1 * k, 0.08)
    _feed(mon, 2.0, 3.0, 100.0)
    assert mon.judge(3.0).state == radio.WARN and mon.latency == pytest.approx(0.08)
    states = []
    for k in range(25):
        mon.round_trip(3.0 + 0.1 * k, 0.4)
        states += _feed(mon, 3.0 + 0.1 * k, 3.1 + 0.1 * k, 100.0)
    assert states[0] == radio.WARN and states[-1] == radio.FAIL


def test_nothing_is_judged_before_a_whole_window() -> None:
    mon = radio.LinkMonitor(100.0)
    assert mon.judge(0.0).state == radio.OK
    mon.packet(10.0)
    assert mon.judge(10.5).state == radio.OK
    assert mon.judge(11.5).state == radio.WARN


@pytest.mark.parametrize("limits", [dict(warn_rate=0.5, fail_rate=0.6), dict(warn_latency=0.0),
                                    dict(window=0.0), dict(fail_latency=0.01)])
def test_inconsistent_limits_are_refused(limits: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="link limits"):
        radio.LinkLimits(**limits)


# =========================================================================== real cflib, a degrading radio
WARN_AT, FAIL_AT = 14.0, 24.0
"""When the software radio degrades [s after it started]: attempts lost at 70 % (4 tries: 24 % of the
packets lost, a warning), then at 88 % (60 % lost: failed after 4 s). The plant must be airborne by WARN_AT."""


@pytest.mark.slow
def test_a_degrading_radio_warns_then_holds_and_lands_the_vehicle(tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("cflib.crtp")
    from plant.crazyflie import CrazyfliePlant, LinkLost

    port = support.free_port(udp=True)
    trace = tmp_path / "trace.txt"
    with support.software_crazyflies(["--count", "1", "--base-port", str(port), "--radio", "--seed", "4",
                                      "--degrade", f"{WARN_AT}:0.7", "--degrade", f"{FAIL_AT}:0.88",
                                      "--trace", str(trace), "--log-level", "WARNING"]) as sim:
        t0 = time.monotonic()
        base = ms.load(builtin_path("exp1"))
        spec = ms.CrazyfliePlant(uri=sim.uris[0], takeoff_height=0.8)
        m = msgspec.structs.replace(base, agents=[msgspec.structs.replace(a, plant=spec) for a in base.agents])
        caplog.set_level(logging.WARNING, logger="tether")
        plant = CrazyfliePlant(m, [1]).open()
        try:
            assert time.monotonic() - t0 < WARN_AT - 2.0, "airborne too late for the schedule"
            assert plant.state().p[0, 2] > 0.7
            failed_at = None
            deadline = t0 + FAIL_AT + 15.0
            while time.monotonic() < deadline:  # hover on the plant's own setpoints until the link fails
                try:
                    s = plant.state()
                except LinkLost as exc:
                    assert "link failed" in str(exc), exc
                    failed_at = time.monotonic() - t0
                    break
                plant.step(np.array([[-1.0 * s.v[0, 0], -1.0 * s.v[0, 1], 2.0 * (0.8 - s.p[0, 2]) - 2.0 * s.v[0, 2]]]))
                time.sleep(0.01)
            warned = [r for r in caplog.records if "link degraded" in r.getMessage()]
            assert warned, "no warning while 24 % of the packets were lost"
            assert failed_at is not None and failed_at > FAIL_AT, failed_at
            assert min(r.created for r in warned) - time.time() + time.monotonic() - t0 < FAIL_AT
            assert asyncio.run(plant.recover()) is False  # no reconnection mends a failing radio: it lands
        finally:
            plant.close()
        assert plant.final_position is not None and plant.final_position[2] <= 0.1
        assert any("landed on its own" in r.getMessage() for r in caplog.records)
    rows = np.loadtxt(trace, usecols=range(9))  # k instance x y z vx vy vz thrust (supervisor)
    t = rows[:, 0] * 0.01
    off_aloft = (t > WARN_AT) & (rows[:, 4] > 0.2) & (rows[:, 8] <= 0.1)
    longest = max((len(run) for run in np.split(off_aloft, np.flatnonzero(~off_aloft)) if run.size), default=0)
    assert longest <= 10, f"the motors were off in the air for {longest} ticks"  # a hand-over's blip, not a stop
    assert np.max(np.abs(rows[t > FAIL_AT, 7])) < 1.2  # a 2 s landing from 0.8 m peaks at 0.9 m/s; a fall at 4
    assert rows[-1, 4] < 0.1


def test_log_rates_follow_the_control_rate_so_that_the_radio_budget_holds() -> None:
    pytest.importorskip("cflib.crtp")
    from plant.crazyflie import log_periods

    assert log_periods(0.01) == (10, 20)  # 100 Hz: position every tick, acceleration every other
    assert log_periods(0.02) == (20, 40)  # 50 Hz: eight vehicles fit on one radio
    assert log_periods(0.002) == (10, 20)  # never faster than cflib's 100 Hz
