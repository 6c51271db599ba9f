"""The crazyflie plant with a fleet file, against software Crazyflies through real cflib: pre-flight
refusal naming the vehicle, the fleet's mass in Eq. 4, and a motion-capture vehicle whose estimate
converges on the `motioncapture` mock backend's positions before take-off. The pre-flight judgement
itself is checked purely first."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from plant import preflight
from tests import support
from tether import mission as ms
from tether.catalog import builtin_path

OK = preflight.Readings(vbat=3.9, pm_state=0, supervisor=0b1010, variance=(1e-5, 1e-5, 1e-5), link=1.0)


def test_refusals_name_every_reason() -> None:
    lim = preflight.Limits(battery_min=3.8, variance_max=1e-3, link_min=0.9)
    assert preflight.refusals(OK, lim) == []
    bad = preflight.Readings(vbat=3.5, pm_state=3, supervisor=1 << preflight.BIT_LOCKED, variance=(1.0, 1e-5, 1e-5),
                             link=0.5)
    why = " | ".join(preflight.refusals(bad, lim))
    for words in ("battery 3.50 V is below 3.80 V", "low power", "locked", "50 %", "not converged"):
        assert words in why, why
    no_fly = preflight.Readings(3.9, 0, 0, (1e-5,) * 3, 1.0)
    assert any("cannot fly" in w for w in preflight.refusals(no_fly, lim))
    nan = preflight.Readings(float("nan"), 0, 0b1000, (float("nan"),) * 3, float("nan"))
    assert len(preflight.refusals(nan, lim)) == 3  # a non-finite reading never passes
    # plausible but false: the estimate is fine but puts the vehicle on another's spot
    here = preflight.Readings(3.9, 0, 0b1000, (1e-5,) * 3, 1.0, position=(1.0, 0.0, 0.0))
    assert preflight.refusals(here, lim, place=(1.1, 0.1, 0.0)) == []
    (why,) = preflight.refusals(here, lim, place=(0.0, 0.0, 0.0))
    assert "1.00 m from its place in the fleet file" in why and "rigid body" in why
    nowhere = preflight.Readings(3.9, 0, 0b1000, (1e-5,) * 3, 1.0)
    assert "nowhere" in preflight.refusals(nowhere, lim, place=(0.0, 0.0, 0.0))[0]


def test_a_flying_vehicle_is_down_when_its_firmware_says_it_cut_the_motors() -> None:
    assert preflight.down(OK.supervisor) is None
    flying = 1 << 3 | 1 << 4 | 1 << 1  # can fly, flying, armed
    assert preflight.down(flying) is None
    for bit, word in ((preflight.BIT_LOCKED, "locked"), (preflight.BIT_TUMBLED, "tumbled"),
                      (preflight.BIT_CRASHED, "crashed")):
        why = preflight.down(flying | 1 << bit)
        assert why is not None and word in why and "restart the vehicle" in why, why
    why = preflight.down(1 << preflight.BIT_CRASHED | 1 << preflight.BIT_TUMBLED)
    assert why is not None and "crashed, tumbled" in why


FLEET = """
version = 1
[types.cf]
mass = {mass}
position_source = "{source}"
params = {{ "stabilizer.estimator" = 2, "locSrv.extPosStdDev" = 0.01 }}
[health]
battery_min = 3.8
settle_timeout = 5.0
{mocap}
[[vehicles]]
name = "cf1"
uri = "udp://127.0.0.1:{port}"
type = "cf"
p0 = [0.5, 0.5, 0.0]
"""


def _mission(tmp: Path, port: int, mass: float = 0.029, source: str = "onboard", mocap: str = "") -> ms.Mission:
    (tmp / "fleet.toml").write_text(FLEET.format(mass=mass, source=source, mocap=mocap, port=port))
    m = ms.load(builtin_path("exp1"))
    spec = ms.CrazyfliePlant(uri=f"udp://127.0.0.1:{port}", takeoff_height=0.8)
    return msgspec.structs.replace(m, agents=[msgspec.structs.replace(a, plant=spec) for a in m.agents],
                                   fleet=str(tmp / "fleet.toml"))


@pytest.mark.slow
def test_a_low_battery_is_refused_before_take_off_naming_the_vehicle(tmp_path: Path) -> None:
    from plant.crazyflie import CrazyfliePlant

    port = support.free_port(udp=True)
    with support.software_crazyflies(["--count", "1", "--base-port", str(port), "--vbat", "3.5",
                                      "--p0=0.5,0.5,0"]):
        plant = CrazyfliePlant(_mission(tmp_path, port), [1])
        with pytest.raises(preflight.PreflightRefused) as err:
            plant.open()
        assert "crazyflie 1 (udp://127.0.0.1:" in str(err.value) and "fleet vehicle cf1" in str(err.value)
        assert "battery 3.50 V is below 3.80 V" in str(err.value)
        assert plant._pos is not None and plant._pos[2] < 0.01  # never left the floor


@pytest.mark.slow
def test_the_fleets_mass_feeds_eq4(tmp_path: Path) -> None:
    """A vehicle 12 % heavier than a Crazyflie 2.1 (``--mass 0.0325``), commanded only to brake its
    vertical velocity (u = -4 v_z): with the plant table's default mass Eq. 4's thrust is short by
    ~1.06 m/s^2 and it sinks at ~0.26 m/s; with the fleet's mass it holds its height. The rate is the
    least-squares slope of the logged height over the second second."""
    from plant.crazyflie import CrazyfliePlant

    def sink_rate(fleet: bool) -> float:
        port = support.free_port(udp=True)
        with support.software_crazyflies(["--count", "1", "--base-port", str(port), "--mass", "0.0325",
                                          "--p0=0.5,0.5,0"]):
            m = _mission(tmp_path, port, mass=0.0325)
            m = m if fleet else msgspec.structs.replace(m, fleet=None)
            plant = CrazyfliePlant(m, [1]).open()
            try:
                t0 = time.monotonic()
                samples: list[tuple[float, float]] = []
                while time.monotonic() < t0 + 2.0:
                    s = plant.state()
                    samples.append((time.monotonic() - t0, float(s.p[0, 2])))
                    plant.step(np.array([[0.0, 0.0, -4.0 * float(s.v[0, 2])]]))
                    time.sleep(0.01)
            finally:
                plant.close()
        late = np.array([(t, z) for t, z in samples if t >= 1.0])
        assert len(late) >= 10, samples  # a loop starved for a whole second measures nothing
        return float(-np.polyfit(late[:, 0], late[:, 1], 1)[0])

    port = support.free_port(udp=True)
    plain = msgspec.structs.replace(_mission(tmp_path, port, mass=0.0325), fleet=None)
    assert CrazyfliePlant(plain, [1]).mass == 0.029
    without, with_fleet = sink_rate(False), sink_rate(True)
    print(f"\n12 % heavier vehicle under u = -4 v_z: sinks at {without:.3f} m/s with the mission's mass, "
          f"{with_fleet:.3f} m/s with the fleet's")
    assert without > 0.15, without
    assert abs(with_fleet) < 0.08, with_fleet


@pytest.mark.slow
def test_a_motion_capture_vehicle_converges_on_its_rigid_body_before_take_off(tmp_path: Path) -> None:
    """No positioning deck (``--position-source extpos``): the plant starts the fleet's motion-capture
    feed (here the `motioncapture` mock backend), resets the estimator, and passes pre-flight once
    the estimate sits on the rigid body's position."""
    pytest.importorskip("motioncapture")
    from plant.crazyflie import CrazyfliePlant

    port = support.free_port(udp=True)
    mocap = '[mocap]\nbackend = "mock"\noptions = { rigid_bodies = "cf1(0.5,0.5,0.0,1,0,0,0)" }'
    with support.software_crazyflies(["--count", "1", "--base-port", str(port), "--position-source", "extpos",
                                      "--p0=0.5,0.5,0"]):
        plant = CrazyfliePlant(_mission(tmp_path, port, source="mocap", mocap=mocap), [1])
        plant._connect()
        try:
            plant._prepare()
            assert plant.health is not None and max(plant.health.variance) < 1e-3
            np.testing.assert_allclose(plant.state().p[0], [0.5, 0.5, 0.0], atol=0.01, rtol=0)
            assert plant._mocap is not None and plant._mocap.stats.sent["cf1"] > 0
        finally:
            plant._stopped = True  # on the floor: close without a landing
            plant.close()
        assert plant._mocap is None  # the feed stops with the plant


@pytest.mark.slow
def test_a_vehicle_that_loses_its_motion_capture_is_landed(tmp_path: Path) -> None:
    """A vehicle flying on motion capture whose positions stop coming (the capture system gone: its
    feed stopped) is unfit to fly within ``plant.mocap.LOST_AFTER``: the plant reports it unhealthy
    naming the motion capture, and its recovery lands it rather than reconnecting. On the ground here
    (the mock backend's bodies hold still, so a flight on them would not be a flight); the same
    failsafe as a failed link's (``test_radio_monitor.py`` flies that one)."""
    pytest.importorskip("motioncapture")
    from plant import mocap
    from plant.crazyflie import CrazyfliePlant, LinkLost

    port = support.free_port(udp=True)
    body = '[mocap]\nbackend = "mock"\noptions = { rigid_bodies = "cf1(0.5,0.5,0.0,1,0,0,0)" }'
    with support.software_crazyflies(["--count", "1", "--base-port", str(port), "--position-source", "extpos",
                                      "--p0=0.5,0.5,0"]):
        plant = CrazyfliePlant(_mission(tmp_path, port, source="mocap", mocap=body), [1]).open(take_off=False)
        try:
            assert plant.healthy()
            feed = plant._mocap
            assert feed is not None
            feed.__exit__(None, None, None)  # the capture system goes away
            gone = time.monotonic()
            support.wait_until(lambda: not plant.healthy(), 5.0, "the lost fix to be seen")
            seen = time.monotonic() - gone
            print(f"\nmotion capture stopped: unfit to fly after {seen:.2f} s")
            assert seen < mocap.LOST_AFTER + 0.5, seen
            with pytest.raises(LinkLost, match="motion capture lost"):
                plant.state()
            assert asyncio.run(plant.recover()) is False  # no reconnection: it lands
        finally:
            plant._stopped = True
            plant.close()
