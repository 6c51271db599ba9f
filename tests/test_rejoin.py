"""Rejoining a run under way (tether/rejoin.py), the supervisor's rejoin hold and the re-entry ramp. Pure, fast."""

from __future__ import annotations

import math

import numpy as np

from agent.node import REJOIN_RAMP, Ramp
from agent.safety import Status, Supervisor
from tests.test_safety import H, mission, step
from tether.rejoin import SAMPLES, Rejoin
from tether.wire import FLYING, HOLD, LAND


def test_the_start_instant_is_the_earliest_arrival_less_the_sample_time() -> None:
    now = [1000.0]
    r = Rejoin(lambda: now[0])
    epoch = 990.0
    for k in range(1, SAMPLES + 1):
        t = k * H
        now[0] = epoch + t + 0.002 + 0.003 * (k % 3)  # 2 ms at the least, more when queued
        r.observe(k, t)
        assert (r.epoch() is None) == (k < SAMPLES)
    assert r.epoch() is not None and abs(r.epoch() - (epoch + 0.002)) < 1e-9  # type: ignore[operator]


def test_tick_0_non_finite_times_and_lockstep_are_not_used() -> None:
    r = Rejoin(lambda: 5.0)
    for _ in range(3 * SAMPLES):
        r.observe(0, 0.0)  # what a normal start hears first
        r.observe(7, math.nan)
    assert r.samples == 0 and r.epoch() is None
    lock = Rejoin(None)
    lock.observe(3, 0.03)
    assert lock.samples == 0 and lock.epoch() is None


def test_a_rejoining_agent_holds_until_its_inputs_are_fresh_then_flies() -> None:
    sup = Supervisor(mission(), 2, (1,))
    step(sup, 100, status=Status(rejoining=True))
    assert sup.mode == HOLD and sup.cause == "rejoin"
    assert "restarted into a running swarm" in sup.events[-1].reason
    step(sup, 101, status=Status(rejoining=True))
    assert sup.mode == HOLD
    step(sup, 102)
    assert sup.mode == FLYING and sup.events[-1].reason == "rejoin recovered"


def test_inputs_that_never_come_fresh_land_it_after_land_after() -> None:
    sup = Supervisor(mission(), 2, (1,))
    k = 100
    step(sup, k, status=Status(rejoining=True))
    while sup.mode == HOLD and k < 100 + round(3 * sup.cfg.land_after / H):
        k += 1
        step(sup, k, status=Status(rejoining=True))
    assert sup.mode == LAND and abs((k - 100) * H - sup.cfg.land_after) < 2 * H


def test_the_ramp_moves_the_command_by_at_most_its_step_until_it_catches_up() -> None:
    max_accel = 20.0
    ramp = Ramp(max_accel * H / REJOIN_RAMP, 3)
    hold = np.array([0.1, 0.0, -0.2])
    assert np.array_equal(ramp.limit(hold, flying=False), hold)  # HOLD: the supervisor's command as it is
    ramp.u = hold
    law = np.array([max_accel, 0.0, 0.0])  # saturated: the vehicle fell behind
    sent = [hold]
    for _ in range(round(2 * REJOIN_RAMP / H)):
        ramp.u = ramp.limit(law, flying=True)
        sent.append(ramp.u)
        if not ramp.active:
            break
    steps = np.linalg.norm(np.diff(np.array(sent), axis=0), axis=-1)
    assert steps.max() <= max_accel * H / REJOIN_RAMP + 1e-12
    assert not ramp.active and np.array_equal(sent[-1], law)
    assert all(np.linalg.norm(u) <= max_accel + 1e-12 for u in sent)
    assert len(sent) - 1 <= round(REJOIN_RAMP / H) + 2  # from about 0 to max_accel in REJOIN_RAMP
    assert np.array_equal(ramp.limit(-law, flying=True), -law)  # caught up: off for good


# --------------------------------------------------------------------------- a restarted plant's last state
def test_a_restarted_plants_last_state_is_checked_before_it_is_resumed() -> None:
    from plant import resume
    from tether import wire

    def state(**kw: object) -> bytes:
        base = dict(sender=2, seq=5, k=400, t=4.0, p=[3.0, 4.0], vel=[1.0, 0.0], a=[0.0, 0.0], d=[0.0, 0.0], mode=1)
        return wire.encode(wire.PlantState(**(base | kw)))  # type: ignore[arg-type]

    msg, why = resume.check(state(), 2, 2, 500)
    assert msg is not None and msg.p == [3.0, 4.0] and why == ""
    for payload, says in ((b"\x93junk", "not a tether message"), (state(sender=3), "plant 3's state, not plant 2's"),
                          (state(p=[float("nan"), 0.0]), "not finite"), (state(p=[1.0, 2.0, 3.0]), "components"),
                          (state(k=500), "not before tick 500"), (state(mode=3), "LANDED: a restart does not"),
                          (state(mode=4), "ESTOP"),
                          (wire.encode(wire.Ack(sender=2, seq=0, k=0, t=0.0, role="plant")), "not a plant state")):
        msg, why = resume.check(payload, 2, 2, 500)
        assert msg is None and says in why, (says, why)


def test_a_resumed_plant_starts_where_its_last_state_was() -> None:
    from plant import resume
    from tether import wire
    from tether.catalog import builtin_path
    from tether.node import load_mission

    m = load_mission(builtin_path("section4"), 10.0)
    last = wire.PlantState(sender=2, seq=5, k=400, t=4.0, p=[3.0, 4.0], vel=[1.0, -0.5], a=[0.0, 0.0], d=[0.0, 0.0])
    plant = resume.resumed(m, 2, last, 450)
    s = plant.state()
    assert s.p.tolist() == [[3.0, 4.0]] and s.v.tolist() == [[1.0, -0.5]]
    fresh = resume.resumed(m, 2, last, 0).state()
    # the disturbance continues at tick 450, not at tick 0 (d_2 = [0.9 cos 4t, 0.2 sin 3t])
    assert np.allclose(s.d[0], [0.9 * np.cos(4 * 4.5), 0.2 * np.sin(3 * 4.5)], atol=1e-9)
    assert not np.allclose(s.d[0], fresh.d[0])
