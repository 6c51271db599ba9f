"""Experiments 1 and 2 in simulation: Remark 1 tested, the payload carried, and the distributed
world and quadrotor plants equal to the in-process engine."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agent.law import AgentLaw
from leader import profile
from sim import experiments, lockstep, metrics
from tether import mission as ms
from tether.catalog import builtin_path
from tether.runfile import Run

pytestmark = pytest.mark.slow  # Experiments 1 and 2: long simulations, and real-process runs


def offsets(m: ms.Mission) -> np.ndarray:
    return np.array([a.offset for a in m.agents], dtype=float)


def lagged_ring(tau: float, feed: str, duration: float = 40.0) -> float:
    """Experiment 1's law and graph on vehicles whose acceleration follows the command through a
    first-order lag ``tau`` (a crude inner loop); returns the tracking error over the last 10 s."""
    m = ms.load(builtin_path("exp1"))
    laws = [AgentLaw.from_mission(m, i) for i in m.agent_ids]
    ref = profile.build(m.leader, 3)
    idx = {a: i for i, a in enumerate(m.agent_ids)}
    h, sub = m.dt, 10
    p = np.array([a.p0 for a in m.agents], dtype=float)
    v, acc, lag, u_prev = (np.zeros((4, 3)) for _ in range(4))
    kp = [np.array(law.initial()[0]) for law in laws]
    kv = [np.array(law.initial()[1]) for law in laws]
    worst = 0.0
    steps = int(duration / h)
    for k in range(steps):
        lp, lv, la = ref(k * h)
        shared = acc if feed == "measured" else u_prev
        us = np.zeros((4, 3))
        for i, law in enumerate(laws):
            nb = [(lp, lv, la) if j == m.leader.id else (p[idx[j]], v[idx[j]], shared[idx[j]]) for j in law.neighbours]
            us[i], _, _, kp[i], kv[i] = law.step(p[i], v[i], *(np.array(x) for x in zip(*nb)), kp[i], kv[i])
        v0 = v.copy()
        for _ in range(sub):
            dt = h / sub
            lag = lag + dt * (us - lag) / tau if tau > 0 else us
            p, v = p + dt * v + 0.5 * dt * dt * lag, v + dt * lag
        acc, u_prev = (v - v0) / h, us
        if k * h >= duration - 10.0:
            worst = max(worst, float(np.linalg.norm(p - offsets(m) - lp, axis=1).max()))
    return worst


def test_a_lagging_inner_loop_makes_the_measured_feed_forward_oscillate_around_the_ring() -> None:
    assert lagged_ring(0.0, "measured") < 0.05  # the ideal double integrator: fine
    assert lagged_ring(0.15, "measured") > 1.0  # the quadrotor's lag: a growing formation-wide swing
    assert lagged_ring(0.15, "commanded") < 0.05  # feeding forward the commands: immune to the lag


def test_remark1_quadrotors_fly_experiment1_like_double_integrators() -> None:
    m = ms.load(builtin_path("exp1"))
    v = experiments.exp1_variants(m)
    quad = lockstep.simulate(v["quadrotors, commanded feed-forward (mission)"])
    ideal = lockstep.simulate(v["double integrators, commanded feed-forward"])
    assert np.abs(quad.p - ideal.p).max() < 0.06  # the stated margin (measured 0.040 m)
    for run in (quad, ideal):
        assert metrics.tracking_error(run, offsets(m)) < 0.02
        assert np.nanmax(run.kp) < 1.6 and np.nanmax(run.kv) < 1.3
    summary = experiments.summary(m, quad)
    assert summary["formation_reached_s"] < 5.0
    # and with the measured accelerations fed forward, only the quadrotors go wrong
    measured = lockstep.simulate(v["quadrotors, measured feed-forward"])
    assert metrics.tracking_error(measured, offsets(m)) > 1.0


def test_an_aggressive_reference_breaks_the_two_loop_assumption() -> None:
    m = ms.load(builtin_path("exp1"))
    # a_ref = 6 m/s^2 along x decaying at 0.5 /s: beyond what a 20 deg tilt gives (3.57 m/s^2)
    lead = msgspec.structs.replace(m.leader, profile=ms.ExpAccel(a0=[6.0, 0.0, 0.0], decay=0.5))
    v = experiments.exp1_variants(msgspec.structs.replace(m, leader=lead, duration=10.0))
    quad = lockstep.simulate(v["quadrotors, commanded feed-forward (mission)"])
    ideal = lockstep.simulate(v["double integrators, commanded feed-forward"])
    late = quad.t >= 2.0
    q, d = np.nanmax(metrics.xi_norm(quad)[late]), np.nanmax(metrics.xi_norm(ideal)[late])
    assert q > 1.0 and q > 4.0 * d, (q, d)


def test_experiment2_carries_the_payload_and_the_plain_law_sags() -> None:
    m = ms.load(builtin_path("exp2"))
    v = experiments.exp2_variants(m)
    run = lockstep.simulate(m)
    s = experiments.summary(m, run)
    assert s["payload_error_m"] < 0.05  # the stated delivery error
    assert s["payload_lifted_at_s"] < 5.0
    assert s["vertical_tension_sum_end_over_weight"] == pytest.approx(1.0, abs=0.01)
    assert s["ultimate_bound_xi_m"] < 0.05 and not s["diverged"]
    plain = experiments.summary(m, lockstep.simulate(v["plain law (payload as a disturbance only)"]))
    assert plain["tracking_error_end_m"] > 0.3  # Eq. 17 has no integral action: a steady sag


def _run(path: Path, out: Path, duration: float) -> Run:
    r = subprocess.run([sys.executable, "-m", "cli", "run", str(path), "--out", str(out), "--duration",
                        str(duration), "--quiet", "--separate-plants"], capture_output=True, text=True, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    return Run.load(out)


@pytest.mark.parametrize("name", ["exp1", "exp2"])
def test_quadrotor_plants_and_the_payload_world_as_processes_equal_the_in_process_engine(tmp_path: Path,
                                                                                         name: str) -> None:
    got = _run(builtin_path(name), tmp_path / name, 2.0)
    want = lockstep.simulate(msgspec.structs.replace(ms.load(builtin_path(name)), duration=2.0))
    for field in ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field), err_msg=field)
    if name == "exp2":  # the world's own records: payload and cables
        for field in ("payload_p", "tension", "slack_events"):
            np.testing.assert_array_equal(getattr(got.plant, field), getattr(want.plant, field), err_msg=field)
        assert np.nanmax(got.plant.tension) > 0  # the cables did something in 2 s
