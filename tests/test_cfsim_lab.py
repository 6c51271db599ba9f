"""What a lab needs from the software Crazyflie, through real cflib over ``udp://`` against
``python -m plant.cfsim`` started as a real process: the Kalman variances that cflib's
``Swarm.reset_estimators`` waits on, the emergency-stop watchdog, and external positions from a
motion-capture system (the `motioncapture` package's ``mock`` backend) fused into the estimate.
The estimator model itself is checked first, purely."""

from __future__ import annotations

import math
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

from plant.cfsim import estimator, supervisor
from plant.mocap import LOST_AFTER, Bounds, FeedStats, MocapFeed, checked_position, fix_lost
from tests.support import free_port, software_crazyflies

cflib_crtp = pytest.importorskip("cflib.crtp")
from cflib.crazyflie.swarm import CachedCfFactory, Swarm  # noqa: E402

from tests.test_cfsim import CONNECT, STARTUP, LogStream, connected  # noqa: E402


# =========================================================================== pure
def test_estimator_fuses_external_positions_and_clamps_variance() -> None:
    est = estimator.PositionEstimator(estimator.EstimatorConfig(source="extpos"), np.array([1.0, 2.0, 0.0]))
    assert est.p.tolist() == [0.0, 0.0, 0.0]  # an extpos-only vehicle knows nothing at boot
    assert est.var.tolist() == [100.0, 100.0, 1.0]
    z = np.array([1.0, 2.0, 0.5])
    for _ in range(50):
        est.predict(np.zeros(3), 0.01)
        assert est.extpos(z, 0.01)
    np.testing.assert_allclose(est.p, z, atol=1e-4, rtol=0)
    assert np.all(est.var < 1e-5) and np.all(est.var >= estimator.MIN_COVARIANCE)
    # a non-finite measurement or standard deviation is refused and changes nothing
    p, var = est.p.copy(), est.var.copy()
    assert not est.extpos(np.array([math.nan, 0.0, 0.0]), 0.01)
    assert not est.extpos(z, math.inf)
    assert est.rejected == 2 and np.array_equal(est.p, p) and np.array_equal(est.var, var)
    # without measurements the variance grows, up to the firmware's clamp
    for _ in range(100):
        est.predict(np.zeros(3), 1e6)
    assert est.var.tolist() == [estimator.MAX_COVARIANCE] * 3


def test_onboard_estimate_is_the_truth_and_resets() -> None:
    est = estimator.PositionEstimator(estimator.EstimatorConfig(), np.array([1.0, 2.0, 0.0]))
    est.tick(np.array([0.1, 0.0, 0.0]), np.array([1.1, 2.0, 0.0]), 0.01)
    np.testing.assert_allclose(est.p, [1.1, 2.0, 0.0], atol=1e-12, rtol=0)
    est.reset()
    assert est.var[0] == estimator.MAX_COVARIANCE
    est.tick(np.zeros(3), np.array([1.1, 2.0, 0.0]), 0.01)
    np.testing.assert_allclose(est.p, [1.1, 2.0, 0.0], atol=1e-5, rtol=0)  # one onboard measurement
    assert np.all(est.var < 1e-4)


def test_estop_watchdog_locks_one_second_after_the_last_notification() -> None:
    sup = supervisor.Supervisor()
    sup.update(0, 0)
    assert not sup.locked and not sup.estop_watchdog_armed  # disarmed until the first notification
    sup.update(10_000, 0)
    assert not sup.locked
    sup.notify_estop_watchdog(10_000)
    sup.update(10_990, 0)
    assert not sup.locked
    sup.update(11_000, 0)
    assert sup.locked


def test_checked_position_refuses_missing_wild_and_non_finite() -> None:
    bodies = {"cf1": SimpleNamespace(position=np.array([1.0, 2.0, 0.5], dtype=np.float32)),
              "nan": SimpleNamespace(position=np.array([math.nan, 0.0, 0.0])),
              "far": SimpleNamespace(position=np.array([50.0, 0.0, 0.0]))}
    b = Bounds()
    np.testing.assert_allclose(checked_position(bodies, "cf1", b), [1.0, 2.0, 0.5])
    assert checked_position(bodies, "cf2", b) is None
    assert checked_position(bodies, "nan", b) is None
    assert checked_position(bodies, "far", b) is None


# =========================================================================== with cflib
def _bounded(fn: object, timeout: float, what: str) -> None:
    """Run ``fn()`` in a thread and fail naming ``what`` if it does not return within ``timeout`` [s]
    (cflib's own waits have no deadline)."""
    errors: list[BaseException] = []

    def run() -> None:
        try:
            fn()  # type: ignore[operator]
        except BaseException as exc:
            errors.append(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    th.join(timeout)
    assert not th.is_alive(), f"{what} did not return within {timeout:g} s"
    if errors:
        raise errors[0]


@pytest.mark.slow
def test_a_fix_is_lost_after_its_silence_or_with_the_feed() -> None:
    stats = FeedStats(sent={"cf1": 10}, refused={"cf1": 3}, last_sent={"cf1": 100.0})
    assert fix_lost(stats, "cf1", 100.0 + LOST_AFTER, 90.0, None) is None  # a few frames occluded: ridden out
    why = fix_lost(stats, "cf1", 100.0 + LOST_AFTER + 0.01, 90.0, None)
    assert why is not None and "rigid body cf1 for 0.51 s" in why and "3 frame(s)" in why
    assert fix_lost(stats, "cf2", 90.4, 90.0, None) is None  # never sent yet: counted from the feed's start
    assert fix_lost(stats, "cf2", 90.6, 90.0, None) is not None
    assert "the feed was stopped" in (fix_lost(stats, "cf1", 100.0, 90.0, "the feed was stopped") or "")


def test_swarm_reset_estimators_through_cflib() -> None:
    """Bitcraze's own swarm recipe: ``Swarm.reset_estimators`` resets each vehicle's Kalman
    estimator and waits until ``kalman.varPX/varPY/varPZ`` have settled (ten samples at 2 Hz)."""
    base = free_port(2, udp=True)
    with software_crazyflies(["--count", "2", "--base-port", str(base), "--log-level", "WARNING"], STARTUP) as sim:
        cflib_crtp.init_drivers()
        swarm = Swarm(list(sim.uris.values()), factory=CachedCfFactory(rw_cache=None))
        try:
            _bounded(swarm.open_links, 2 * CONNECT, "Swarm.open_links")
            t0 = time.monotonic()
            _bounded(swarm.reset_estimators, 30.0, "Swarm.reset_estimators")
            assert time.monotonic() - t0 >= 4.5  # ten fresh samples at 500 ms: it really waited
        finally:
            swarm.close_links()


@pytest.mark.slow
def test_estop_watchdog_cuts_a_silent_client() -> None:
    """Armed by a notification, the watchdog locks the vehicle once notifications stop for 1 s."""
    base = free_port(1, udp=True)
    with software_crazyflies(["--count", "1", "--base-port", str(base), "--log-level", "WARNING"], STARTUP) as sim:
        cflib_crtp.init_drivers()
        with connected(sim.uris[0]) as cf:
            log = LogStream(cf, ["supervisor.info"], 10)
            locked = lambda d: bool(int(d["supervisor.info"]) >> supervisor.BIT_LOCKED & 1)  # noqa: E731
            t_end = time.monotonic() + 2.0
            while time.monotonic() < t_end:  # fed every 100 ms for 2 s: never locked
                cf.supervisor.send_emergency_stop_watchdog()
                time.sleep(0.1)
            assert log.samples and not any(locked(d) for _, _, d in log.samples)
            t_last = time.monotonic()
            t_lock, _ = log.wait(locked, 5.0, "the lock after the last notification")
            assert 0.8 <= t_lock - t_last <= 2.5, t_lock - t_last


@pytest.mark.slow
def test_motion_capture_to_extpos_and_back_in_the_estimate() -> None:
    """A vehicle without a positioning deck (``--position-source extpos``) knows nothing of where it
    is; positions from the `motioncapture` mock backend, sent as extpos by :class:`MocapFeed`, bring
    its ``stateEstimate`` to the captured position and its variance down."""
    pytest.importorskip("motioncapture")
    base = free_port(1, udp=True)
    with software_crazyflies(["--count", "1", "--base-port", str(base), "--position-source", "extpos",
                              "--p0=1.0,2.0,0.0", "--log-level", "WARNING"], STARTUP) as sim:
        cflib_crtp.init_drivers()
        with connected(sim.uris[0]) as cf:
            log = LogStream(cf, ["stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "kalman.varPX",
                                 "kalman.varPZ"], 20)
            first = log.wait(lambda d: True, 5.0, "a first sample")[1]
            assert first["kalman.varPX"] > 1.0 and abs(first["stateEstimate.x"]) < 1e-6  # untrusted, at the origin
            with MocapFeed("mock", "", [("cf1", lambda p: cf.extpos.send_extpos(*p.tolist()))],
                           options={"rigid_bodies": "cf1(1.0,2.0,0.02,1,0,0,0)"}) as feed:
                _, d = log.wait(lambda d: d["kalman.varPX"] < 1e-3 and d["kalman.varPZ"] < 1e-3, 10.0,
                                "the variance to fall below 1e-3 m^2")
                np.testing.assert_allclose([d["stateEstimate.x"], d["stateEstimate.y"], d["stateEstimate.z"]],
                                           [1.0, 2.0, 0.02], atol=0.01, rtol=0)
                assert feed.error is None and feed.stats.sent["cf1"] >= 1
            # the feed stopped: the estimator no longer trusts its estimate
            log.wait(lambda d: d["kalman.varPX"] > 5e-4, 20.0, "the variance to grow without measurements")
