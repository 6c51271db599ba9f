"""The safety layer, pure: every supervisor transition, the plausibility gate, kappa re-normalisation,
the failsafe command laws. No processes here (the real-process faults are in test_faults.py)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from tether.gate import Gate
from agent.safety import Status, Supervisor, reaches
from agent.tick import AgentTick
from tests.factories import build
from tether import failsafe, wire
from tether.inputs import Source
from tether.wire import ESTOP, FLYING, HOLD, LAND, LANDED

H = 0.01


def mission(safety: dict[str, Any] | None = None, dim: int = 3) -> Any:
    """A ring 1 -> 2 -> 3 -> 1 with the leader (4) heard by 1 and 3, so that losing 1 leaves 2
    unreachable from the leader, while losing 2 leaves 3 reachable (it hears the leader)."""
    z = [1.0] if dim == 3 else []
    raw: dict[str, Any] = {
        "version": 1, "name": "ring", "dim": dim, "rate": 100.0, "duration": 20.0,
        "law": {"kind": "sigma", "kp0": 1.5, "kv0": 1.2, "gamma_p": 0.1, "gamma_v": 0.05, "sigma": 0.1},
        "leader": {"id": 4, "p0": [0.0, 0.0, *z]},
        "agents": [{"id": i, "p0": [float(i), 0.0, *z], "offset": [float(i), 0.0, *([0.0] if dim == 3 else [])]}
                   for i in (1, 2, 3)],
        "edges": [{"from": 4, "to": 1}, {"from": 1, "to": 2}, {"from": 2, "to": 3}, {"from": 3, "to": 1},
                  {"from": 4, "to": 3}],
    }
    if safety is not None:
        raw["safety"] = safety
    return build(raw)


def step(sup: Supervisor, k: int, *, p=None, v=None, u=None, xi=None, kp=None, kv=None, reachable=True,
         leader_silent=False, status: Status = Status()) -> np.ndarray:
    d = 3
    p = np.array([0.0, 0.0, 1.0]) if p is None else np.asarray(p, float)
    v = np.zeros(d) if v is None else np.asarray(v, float)
    u = np.array([0.1, 0.0, 0.0]) if u is None else np.asarray(u, float)
    xi = np.zeros(d) if xi is None else np.asarray(xi, float)
    kp = np.ones(d) if kp is None else np.asarray(kp, float)
    kv = np.ones(d) if kv is None else np.asarray(kv, float)
    out = sup.command(k, k * H, p, v, u, xi, kp, kv, reachable, leader_silent, status)
    assert np.all(np.isfinite(out)) and np.linalg.norm(out) <= sup.cfg.max_accel * (1 + 1e-12)
    return out


# --------------------------------------------------------------------------- FLYING and limits
def test_flying_passes_the_law_through_untouched_below_the_limit() -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    u = np.array([0.3, -0.2, 0.1])
    out = sup.command(0, 0.0, np.zeros(3), np.zeros(3), u, np.zeros(3), np.ones(3), np.ones(3), True, False)
    assert out == u.tolist() and sup.mode == FLYING and sup.events == []  # untouched, bit for bit


def test_saturation_keeps_the_direction_and_caps_the_norm() -> None:
    sup = Supervisor(mission({"max_accel": 5.0}), 1, (3, 4))
    out = step(sup, 0, u=[30.0, 40.0, 0.0])
    np.testing.assert_allclose(out, [3.0, 4.0, 0.0], rtol=0, atol=1e-12)
    assert sup.mode == FLYING


@pytest.mark.parametrize("what, kwargs", [
    ("non-finite command", {"u": [math.nan, 0.0, 0.0]}),
    ("infinite command", {"u": [math.inf, 0.0, 0.0]}),
    ("formation error", {"xi": [60.0, 0.0, 0.0]}),
    ("gain", {"kp": [1.0, 2000.0, 1.0]}),
])
def test_divergence_lands_and_never_passes_the_value_on(what: str, kwargs: dict) -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    step(sup, 0, **kwargs)
    assert sup.mode == LAND, what
    assert sup.events[-1].reason.startswith("divergence") and sup.diverged is not None


def test_divergence_action_estop_cuts_at_once() -> None:
    sup = Supervisor(mission({"divergence_action": "estop"}), 1, (3, 4))
    out = step(sup, 0, xi=[100.0, 0.0, 0.0])
    assert sup.mode == ESTOP and not any(out)
    step(sup, 1)  # terminal
    assert sup.mode == ESTOP


def test_overspeed_holds_latched_then_lands() -> None:
    sup = Supervisor(mission({"max_speed": 5.0, "land_after": 1.0}), 1, (3, 4))
    step(sup, 0, v=[6.0, 0.0, 0.0])
    assert sup.mode == HOLD
    step(sup, 1, v=[1.0, 0.0, 0.0])  # slower again: still holding (latched)
    assert sup.mode == HOLD
    step(sup, 100, v=[0.0, 0.0, 0.0])
    assert sup.mode == LAND


# --------------------------------------------------------------------------- lost inputs
def test_leader_silence_holds_recovers_and_lands_when_it_lasts() -> None:
    sup = Supervisor(mission({"land_after": 2.0}), 1, (3, 4))
    step(sup, 0)
    out = step(sup, 1, p=[1.0, 0.0, 1.0], v=[2.0, 0.0, 0.0], leader_silent=True)
    assert sup.mode == HOLD and out[0] < 0  # braking against the motion
    step(sup, 2, leader_silent=False)
    assert sup.mode == FLYING and sup.events[-1].reason == "leader recovered"
    step(sup, 10, leader_silent=True)
    step(sup, 10 + 199, leader_silent=True)
    assert sup.mode == HOLD
    step(sup, 10 + 200, leader_silent=True)
    assert sup.mode == LAND
    step(sup, 400, leader_silent=False)  # LAND does not go back
    assert sup.mode == LAND


def test_links_time_out_a_silent_leader_and_lost_neighbours() -> None:
    m = mission()
    sup = Supervisor(m, 1, (3, 4))
    lost, reachable, leader_silent = sup.links(10, 0.1, [0.0, 0.0], Status())
    assert (lost, reachable, leader_silent) == (frozenset(), True, False)
    _, _, leader_silent = sup.links(60, 0.6, [0.0, m.safety.leader_timeout + 0.01], Status())
    assert leader_silent
    _, _, leader_silent = sup.links(61, 0.61, [0.0, 0.0], Status(gone=[False, True]))
    assert leader_silent  # token gone


def test_a_lost_neighbour_is_dropped_with_kappa_renormalised_while_the_leader_reaches() -> None:
    m = mission()
    tick = AgentTick.from_mission(m, 3)  # hears 2 and the leader
    assert tick.law.neighbours == (2, 4) and tick.law.kappa == 2.0
    heard = [(0.0, np.array([2.0, 0.0, 1.0]), np.zeros(3), np.zeros(3)), (0.0, np.array([0.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))]
    p = np.array([3.0, 0.0, 1.0])
    tick.step(0, 0.0, p, np.zeros(3), np.zeros(3), heard)
    out = tick.step(1, 0.01, p, np.zeros(3), np.zeros(3), heard, Status(gone=[True, False]))
    assert out.mode == FLYING
    assert tick.supervisor.lost == {2} and "edge dropped" in tick.supervisor.events[-1].reason
    law = tick._laws[frozenset({2})]
    assert law.kappa == 1.0 and law.weights == (0.0, 1.0)
    # only the leader's term is left: agent 3 at its slot (leader + offset 3) has zero error
    np.testing.assert_allclose(out.xi, [0.0, 0.0, 0.0], atol=1e-12)
    out = tick.step(2, 0.02, p, np.zeros(3), np.zeros(3), heard, Status())
    assert tick.supervisor.lost == frozenset() and "restored" in tick.supervisor.events[-1].reason


def test_a_lost_neighbour_without_another_path_from_the_leader_holds_then_lands() -> None:
    m = mission({"land_after": 1.0})
    tick = AgentTick.from_mission(m, 2)  # hears only 1
    heard = [(0.0, np.array([1.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))]
    p = np.array([2.0, 0.0, 1.0])
    out = tick.step(0, 0.0, p, np.zeros(3), np.zeros(3), heard, Status(gone=[True]))
    assert out.mode == HOLD and "no longer reaches" in tick.supervisor.events[-1].reason
    kp = list(tick.state[0])
    for k in range(1, 101):
        out = tick.step(k, k * H, p, np.zeros(3), np.zeros(3), heard, Status(gone=[True]))
    assert out.mode == LAND
    np.testing.assert_array_equal(tick.state[0], kp)  # gains frozen while not flying


def test_reachability_is_assumption_1_on_the_surviving_graph() -> None:
    out = {4: [1, 3], 1: [2], 2: [3], 3: [1]}
    assert reaches(out, 4, 2) and reaches(out, 4, 3, removed={2}) and reaches(out, 4, 1, removed={3})
    assert not reaches(out, 4, 2, removed={1}) and not reaches(out, 4, 1, removed={4})


# --------------------------------------------------------------------------- operator, fence, landing
def test_operator_land_then_landed_on_the_ground() -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    step(sup, 0)
    out = step(sup, 1, p=[0.0, 0.0, 1.0], status=Status(operator="land"))
    assert sup.mode == LAND and out[2] < 0  # descending
    step(sup, 2, p=[0.0, 0.0, 0.01], v=[0.0, 0.0, -0.01], status=Status(operator="land"))
    assert sup.mode == LANDED
    assert not any(step(sup, 3, status=Status(operator="land")))
    step(sup, 4, status=Status(operator="estop"))
    assert sup.mode == ESTOP


def test_operator_estop_is_terminal() -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    assert not any(step(sup, 0, status=Status(operator="estop")))
    assert sup.mode == ESTOP
    assert not any(step(sup, 1)) and sup.mode == ESTOP


def test_geofence_breach_outside_and_predicted() -> None:
    fence = {"geofence": {"min": [-10.0, -10.0, 0.0], "max": [10.0, 10.0, 5.0], "action": "hold"}}
    sup = Supervisor(mission(fence), 1, (3, 4))
    step(sup, 0, p=[5.0, 0.0, 1.0], v=[1.0, 0.0, 0.0])
    assert sup.mode == FLYING
    step(sup, 1, p=[9.0, 0.0, 1.0], v=[4.0, 0.0, 0.0])  # would not stop inside the box
    assert sup.mode == HOLD and "would leave" in sup.events[-1].reason
    sup = Supervisor(mission(fence), 1, (3, 4))
    step(sup, 0, p=[11.0, 0.0, 1.0])
    assert sup.mode == HOLD and "outside" in sup.events[-1].reason


def test_every_event_names_tick_vehicle_modes_and_reason() -> None:
    sup = Supervisor(mission(), 2, (1,))
    step(sup, 7, status=Status(operator="land"))
    (ev,) = sup.take_events()
    assert (ev.k, ev.vehicle, ev.src, ev.dst, ev.reason) == (7, 2, FLYING, LAND, "operator land")
    assert sup.take_events() == []


# --------------------------------------------------------------------------- failsafe laws
def test_hold_brakes_a_double_integrator_to_rest_near_where_it_began() -> None:
    cfg = mission().safety
    p, v = np.array([0.0, 0.0, 1.0]), np.array([3.0, -1.0, 0.5])
    start = p.copy()
    for _ in range(2000):
        u = np.array(failsafe.hold(p, v, start, cfg.hold_kp, cfg.hold_kv, cfg.max_accel))
        assert np.linalg.norm(u) <= cfg.max_accel + 1e-12
        p, v = p + v * H + 0.5 * u * H * H, v + u * H
    assert np.linalg.norm(v) < 1e-3 and np.linalg.norm(p - start) < 1e-2


def fly_landing(push: float, memory: bool = True, seconds: float = 60.0) -> tuple[bool, float, list[float]]:
    """A 3D double integrator landing from 2 m under a steady vertical disturbance ``push`` [m/s^2]
    (up if positive), with :class:`failsafe.Landing` (or :func:`failsafe.land` alone). Returns whether
    it landed, when [s], and its vertical velocities."""
    cfg = mission().safety
    p, v = np.array([0.0, 0.0, 2.0]), np.zeros(3)
    start = p.copy()
    landing = failsafe.Landing(cfg.hold_kp, cfg.hold_kv, cfg.max_accel, cfg.land_speed, cfg.ground)
    rates: list[float] = []
    for k in range(round(seconds / H)):
        if failsafe.landed(p, v, cfg.ground):
            return True, k * H, rates
        u = np.array(landing.command(k * H, p, v, start) if memory else
                     failsafe.land(p, v, start, cfg.hold_kp, cfg.hold_kv, cfg.max_accel, cfg.land_speed, cfg.ground))
        assert np.all(np.isfinite(u)) and np.linalg.norm(u) <= cfg.max_accel * (1 + 1e-12)
        a = u + [0.0, 0.0, push]
        p, v = p + v * H + 0.5 * a * H * H, v + a * H
        rates.append(float(v[2]))
        if p[2] <= cfg.ground:  # the ground: contact stops it (plant.rest)
            p[2], v[:] = cfg.ground, 0.0
    return False, seconds, rates


def test_land_descends_at_the_set_rate_and_settles_on_the_ground() -> None:
    landed, _, rates = fly_landing(0.0)
    assert landed
    assert min(rates) >= -mission().safety.land_speed * 1.05  # the integral's overshoot is under 5 %


@pytest.mark.parametrize("push", [0.1, 0.5, 2.0])
def test_a_steady_push_up_does_not_stall_a_landing(push: float) -> None:
    """A proportional descent loop settles push / kv slower than wanted: near the ground, where it
    wants 0.05 m/s, a push of 0.1 m/s^2 (1 % of g) or more held the vehicle above the ground for
    ever. Landing's integral term lands it."""
    stalled, _, rates = fly_landing(push, memory=False)
    assert not stalled  # without the memory: hovering (or climbing), never landing
    landed, when, rates = fly_landing(push)
    assert landed and when < 40.0, when
    assert min(rates) >= -mission().safety.land_speed * 1.05


def test_a_landings_memory_ignores_non_finite_measurements_and_gaps() -> None:
    cfg = mission().safety
    landing = failsafe.Landing(cfg.hold_kp, cfg.hold_kv, cfg.max_accel, cfg.land_speed, cfg.ground)
    hold = [0.0, 0.0, 1.0]
    landing.command(0.0, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], hold)
    landing.command(0.01, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], hold)
    before = landing.bias
    assert before < 0  # slower than wanted: push down
    out = landing.command(0.02, [0.0, 0.0, 1.0], [0.0, 0.0, math.nan], hold)
    assert out == [0.0, 0.0, 0.0] and landing.bias == before
    landing.command(1e6, [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], hold)  # a gap integrates MAX_STEP at most
    assert landing.bias == pytest.approx(before + cfg.hold_kv ** 2 / 16 * -cfg.land_speed * failsafe.MAX_STEP)
    for k in range(10**5):  # bounded, however long it is held from descending
        landing.command(1e6 + k * 0.1, [0.0, 0.0, 1.0], [0.0, 0.0, 0.5], hold)
    assert landing.bias == -cfg.max_accel


def test_a_supervisor_lands_a_3d_vehicle_against_a_steady_push_up() -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    p, v = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    for k in range(round(60.0 / H)):
        out = step(sup, k, p=p, v=v, status=Status(operator="land"))
        if sup.mode == LANDED:
            break
        a = np.asarray(out) + [0.0, 0.0, 0.5]
        p, v = p + v * H + 0.5 * a * H * H, v + a * H
        if p[2] <= 0.0:
            p[2], v[:] = 0.0, 0.0
    assert sup.mode == LANDED and k * H < 30.0, (sup.mode, p)


def sway(t: float) -> np.ndarray:
    """A cable's steady circular sway [m/s^2]: HOLD's spring and damper turn it into a velocity of
    constant norm (0.25 m/s here), so a holding vehicle is never still."""
    return 0.5 * np.array([math.cos(t), math.sin(t)])


def land_2d(cfg_over: dict[str, Any], d, ticks: int) -> tuple[Supervisor, list[int], list[float]]:
    """A 2D agent flying zero, ordered to land at tick 100, under the disturbance ``d(t)``
    (exact zero-order-hold double integrator). Returns the supervisor, its modes and speeds."""
    sup = Supervisor(mission(cfg_over, dim=2), 1, (3, 4))
    p, v = np.array([1.0, 0.0]), np.zeros(2)
    z, one = np.zeros(2), np.ones(2)
    modes, speeds = [], []
    for k in range(ticks):
        t = k * H
        out = np.asarray(sup.command(k, t, p, v, z, z, one, one, True, False,
                                     Status(operator="land") if k >= 100 else Status()))
        assert np.all(np.isfinite(out)) and np.linalg.norm(out) <= sup.cfg.max_accel * (1 + 1e-12)
        modes.append(sup.mode)
        speeds.append(float(np.linalg.norm(v)))
        a = out + d(t)
        p, v = p + v * H + 0.5 * a * H * H, v + a * H
    return sup, modes, speeds


def test_a_2d_landing_under_a_sway_hold_cannot_cancel_ends_after_land_settle() -> None:
    """2D has no ground: LAND is HOLD until still. Against a disturbance HOLD cannot cancel that was
    never (``tether land`` on ``section4`` ran to the mission's end); ``land_settle`` bounds it."""
    sup, modes, speeds = land_2d({}, sway, round(3 * mission().safety.land_settle / H))
    k_land, k_landed = modes.index(LAND), modes.index(LANDED)
    assert k_land == 100
    assert (k_landed - k_land) * H == pytest.approx(sup.cfg.land_settle, abs=1.01 * H)
    assert min(speeds[k_land:k_landed + 1]) > failsafe.STILL  # never still: the bound ended it
    ev = sup.events[-1]
    assert (ev.src, ev.dst, ev.k) == (LAND, LANDED, k_landed)
    assert "land_settle" in ev.reason and "still moving at 0.2" in ev.reason, ev.reason
    assert set(modes[k_landed:]) == {LANDED}
    # a longer bound is that much longer
    sup, modes, _ = land_2d({"land_settle": 8.0}, sway, round(10.0 / H))
    assert (modes.index(LANDED) - modes.index(LAND)) * H == pytest.approx(8.0, abs=1.01 * H)


def test_a_2d_landing_without_a_disturbance_ends_when_still_before_the_bound() -> None:
    # pushed to 1 m/s before the order, then nothing: HOLD brakes it to still
    sup, modes, speeds = land_2d({}, lambda t: np.array([1.0 if t < 1.0 else 0.0, 0.0]), 1000)
    k_landed = modes.index(LANDED)
    assert (k_landed - modes.index(LAND)) * H < sup.cfg.land_settle  # nothing moved it: still at once
    assert sup.events[-1].reason == "still" and speeds[k_landed] < failsafe.STILL


def test_a_3d_landing_is_never_ended_in_the_air_by_the_bound() -> None:
    assert not failsafe.landed([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], 0.0, held=1e9, settle=5.0)
    assert not failsafe.landed([0.0, 0.0, 0.01], [0.5, 0.0, 0.0], 0.0, held=1e9, settle=5.0)  # sliding
    assert failsafe.landed([0.0, 0.0, 0.01], [0.05, 0.0, 0.0], 0.0, held=0.0, settle=5.0)
    assert failsafe.landed([0.0, 0.0], [0.5, 0.0], 0.0, held=5.0, settle=5.0)
    assert not failsafe.landed([0.0, 0.0], [0.5, 0.0], 0.0, held=4.99, settle=5.0)


def test_a_hold_begun_on_a_non_finite_position_holds_about_the_first_finite_one() -> None:
    """It held about the origin before: a vehicle 40 m away was pulled across the arena at max_accel."""
    sup = Supervisor(mission(), 1, (3, 4))
    step(sup, 0, p=[40.0, 0.0, 1.0])
    nan = [math.nan, 0.0, 1.0]
    out = sup.command(1, H, nan, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0] * 3, [1.0] * 3, [1.0] * 3, True, True)
    assert sup.mode == HOLD and out == [0.0, 0.0, 0.0] and sup.p_hold is None  # leader silent, nowhere known
    out = step(sup, 2, p=[40.0, 0.5, 1.0], leader_silent=True)
    assert sup.p_hold == [40.0, 0.5, 1.0] and np.allclose(out, 0.0)  # held where it is, not pulled to 0


def test_saturate_refuses_non_finite() -> None:
    assert failsafe.saturate(np.array([math.nan, 0.0]), 1.0) is None
    np.testing.assert_allclose(failsafe.saturate(np.array([3.0, 4.0]), 1.0), [0.6, 0.8])


# --------------------------------------------------------------------------- the gate
def state(k: int, p: list[float], vel: list[float] | None = None, t: float | None = None) -> wire.State:
    return wire.State(sender=4, seq=k, k=k, t=k * H if t is None else t, p=p, vel=vel or [0.0, 0.0, 0.0],
                      a=[0.0, 0.0, 0.0])


def test_gate_rejects_each_reason_and_moves_its_reference_only_on_accept() -> None:
    clock = [0.0]
    g = Gate(H, max_speed=10.0, margin=0.5, p_ref=[0.0, 0.0, 1.0], future_window=2, now=lambda: clock[0])
    assert g.check(state(0, [0.1, 0.0, 1.0])) is None
    assert g.check(state(1, [0.1, 0.0, 1.0], t=0.5)) == "stamp"
    assert g.check(state(5, [0.1, 0.0, 1.0])) == "future"
    assert g.check(state(1, [1e6, 0.0, 1.0])) == "jump"
    assert g.check(state(2, [0.2, 0.0, 1.0], vel=[50.0, 0.0, 0.0])) == "speed"
    clock[0] = 0.02
    assert g.check(state(2, [0.2, 0.0, 1.0])) is None
    assert g.rejected == {"stamp": 1, "future": 1, "jump": 1, "speed": 1}
    assert g.p_ref == [0.2, 0.0, 1.0]


def test_a_replayed_old_sample_does_not_take_the_reference_back() -> None:
    """The sender flies 10 m/s along x; a replay of its tick-0 sample passes (it was true once) but
    leaves the reference at the newest sample, so that a forgery 20 m behind the truth, within reach
    of the old position after a second, is still rejected."""
    g = Gate(H, max_speed=10.0, margin=0.5, p_ref=[0.0, 0.0, 1.0])
    real = [state(k, [0.1 * k, 0.0, 1.0], vel=[10.0, 0.0, 0.0]) for k in range(101)]
    for s in real:
        assert g.check(s) is None
    assert (g.p_ref, g.t_ref) == (real[100].p, real[100].t)
    assert g.check(real[0]) is None  # replayed: plausible, so not rejected...
    assert g.check(real[50]) is None
    assert (g.p_ref, g.t_ref) == (real[100].p, real[100].t)  # ...but the reference stays the newest
    assert g.accepted == 103
    assert g.check(state(101, [-9.9, 0.0, 1.0])) == "jump"  # 10.1 m from p(0) in 1.01 s would pass
    assert g.check(state(101, [10.1, 0.0, 1.0], vel=[10.0, 0.0, 0.0])) is None
    assert g.p_ref == [10.1, 0.0, 1.0]


def test_a_forged_sample_for_a_coming_tick_never_shadows_the_real_one() -> None:
    """A Source keeps the first sample of each tick; the forgery comes first, far away."""
    g = Gate(H, max_speed=30.0, margin=1.0, p_ref=[0.0, 0.0, 1.0])
    src = Source("leader", wire.State, 4, admit=g.check)
    src.offer(state(0, [0.0, 0.0, 1.0]))
    src.offer(state(3, [1e6, 0.0, 1.0]))  # forged for tick 3, before tick 3 is real
    for k in (1, 2, 3):
        src.offer(state(k, [0.01 * k, 0.0, 1.0]))
    assert src.by_tick[3].p == [0.03, 0.0, 1.0]
    assert src.rejected == 1 and src.received == 4 and g.rejected == {"jump": 1}


# --------------------------------------------------------------------------- collision avoidance
def _min_pair(p: np.ndarray) -> float:
    n = p.shape[1]
    return min(float(np.linalg.norm(p[:, i] - p[:, j], axis=-1).min()) for i in range(n) for j in range(i + 1, n))


def test_the_swap_collides_without_the_filter_and_keeps_apart_with_it() -> None:
    import msgspec

    from sim import lockstep
    from tether.catalog import builtin_path
    from tether.node import load_mission

    m = load_mission(builtin_path("swap"))
    assert m.safety.avoid is not None
    bare = msgspec.structs.replace(m, safety=msgspec.structs.replace(m.safety, avoid=None))
    with_filter, without = lockstep.simulate(m), lockstep.simulate(bare)
    assert _min_pair(without.p) < 0.1  # they would collide
    assert _min_pair(with_filter.p) >= m.safety.avoid.radius * 0.95
    # and the formation is reached once past
    assert np.linalg.norm(with_filter.xi[-100:], axis=-1).max() < 0.01
    assert np.all(np.isfinite(with_filter.u)) and np.linalg.norm(with_filter.u, axis=-1).max() <= m.safety.max_accel


def test_the_filter_returns_the_law_untouched_when_nobody_is_near() -> None:
    from agent.avoid import filter_command

    u = np.array([1.0, 0.0, 0.0])
    far = [(np.array([10.0, 0.0, 0.0]), np.zeros(3))]
    assert filter_command(u, np.zeros(3), np.zeros(3), far, 0.3, 2.0, 1.0, 2.0) is u
    # head-on at 1 m, closing at 2 m/s: the filter brakes along the line between them
    near = [(np.array([1.0, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]))]
    out = filter_command(u, np.zeros(3), np.array([1.0, 0.0, 0.0]), near, 0.3, 2.0, 1.0, 2.0)
    assert out[0] < u[0]


# --------------------------------------------------------------------------- what the fault table found
def reports(tick: AgentTick, modes: list[list[int]], k0: int = 0) -> list[int]:
    """Tick ``tick`` (an agent of :func:`mission` at rest in its slot) once per row of ``modes`` (its
    in-neighbours' reported modes); the supervisor's mode after each."""
    slots = {1: [1.0, 0.0, 1.0], 2: [2.0, 0.0, 1.0], 3: [3.0, 0.0, 1.0], 4: [0.0, 0.0, 1.0]}
    out = []
    for k, row in enumerate(modes, start=k0):
        t = k * H
        heard = [(t, np.array(slots[j]), np.zeros(3), np.zeros(3)) for j in tick.law.neighbours]
        own = np.array(slots[tick.supervisor.agent_id])
        out.append(tick.step(k, t, own, np.zeros(3), np.zeros(3), heard, Status(modes=row)).mode)
    return out


def test_a_neighbours_hold_is_believed_after_mode_confirm_ticks_and_never_holds_the_follower() -> None:
    """Agent 2 hears only agent 1 (its only path from the leader). Agent 1 says HOLD: believed after
    ``mode_confirm`` consecutive ticks, then followed (an event), never a HOLD of agent 2's own."""
    m = mission()
    tick = AgentTick.from_mission(m, 2)
    sup = tick.supervisor
    n = m.safety.mode_confirm
    assert reports(tick, [[HOLD]] * (n - 1)) == [FLYING] * (n - 1) and sup.followed == frozenset()
    assert reports(tick, [[HOLD]] * 3, k0=n - 1) == [FLYING] * 3
    assert sup.followed == {1} and sup.lost == frozenset()
    assert sup.events[-1].reason == "neighbour 1 holding, the only path from the leader: followed"
    assert sup.events[-1].src == sup.events[-1].dst == FLYING  # an event, not a mode change
    # it flies again: believed after as many ticks
    reports(tick, [[FLYING]] * n, k0=10)
    assert sup.followed == frozenset() and sup.events[-1].reason == "neighbour 1 no longer followed as holding"
    assert all(e.src == e.dst == FLYING for e in sup.events)


def test_reports_that_alternate_move_no_belief() -> None:
    """Forged HOLD reports interleaved with genuine FLYING ones (or a flapping sender): no run of
    ``mode_confirm`` agrees, so nothing is believed, nothing is dropped, no event, no mode change."""
    m = mission()
    for aid, row in ((2, [HOLD]), (3, [HOLD, FLYING])):
        tick = AgentTick.from_mission(m, aid)
        got = reports(tick, [row if k % 2 else [FLYING] * len(row) for k in range(200)])
        assert got == [FLYING] * 200 and tick.supervisor.events == [] and tick.supervisor.lost == frozenset()


def test_a_holding_neighbour_with_a_path_around_it_is_dropped_and_a_stopping_one_is_lost() -> None:
    """Agent 3 hears 2 and the leader: 2 holding is dropped (kappa re-normalised), never followed.
    Agent 2 hears only 1: 1 landing (LAND, LANDED, ESTOP or an unknown code) is lost, and the leader
    no longer reaches 2: HOLD, as for a silent neighbour."""
    m = mission()
    n = m.safety.mode_confirm
    tick = AgentTick.from_mission(m, 3)
    assert reports(tick, [[HOLD, FLYING]] * n) == [FLYING] * n
    assert tick.supervisor.lost == {2} and tick.supervisor.followed == frozenset()
    assert tick.supervisor.events[-1].reason == "neighbour 2 lost: edge dropped, kappa re-normalised"
    for said in (LAND, LANDED, ESTOP, 99):
        tick = AgentTick.from_mission(m, 2)
        assert reports(tick, [[said]] * n) == [FLYING] * (n - 1) + [HOLD], said
        assert tick.supervisor.events[-1].reason == "neighbour 1 lost and the leader no longer reaches this agent"
    # LAND then LANDED: one kind of report (it stops), believed without starting over
    tick = AgentTick.from_mission(m, 2)
    assert reports(tick, [[LAND]] * (n - 1) + [[LANDED]]) == [FLYING] * (n - 1) + [HOLD]


def test_a_silent_neighbours_old_report_is_not_believed() -> None:
    """A sample older than ``neighbour_timeout`` reports nothing: the neighbour is lost for its
    silence, and its last HOLD is not counted towards a belief."""
    m = mission()
    tick = AgentTick.from_mission(m, 3)
    old = m.safety.neighbour_timeout + 0.1
    t = 2.0
    heard = [(t - old, np.array([2.0, 0.0, 1.0]), np.zeros(3), np.zeros(3)), (t, np.zeros(3) + [0, 0, 1], np.zeros(3), np.zeros(3))]
    for k in range(5):
        tick.step(200 + k, t + k * H, np.array([3.0, 0.0, 1.0]), np.zeros(3), np.zeros(3), heard,
                  Status(modes=[HOLD, FLYING]))
    assert tick.supervisor.lost == {2} and tick.supervisor.believed[0] == 0 and tick.supervisor.followed == frozenset()


def test_a_gone_leader_reaches_nobody() -> None:
    tick = AgentTick.from_mission(mission(), 2)  # does not hear the leader
    heard = [(0.0, np.array([1.0, 0.0, 1.0]), np.zeros(3), np.zeros(3))]
    out = tick.step(0, 0.0, np.array([2.0, 0.0, 1.0]), np.zeros(3), np.zeros(3), heard, Status(others_gone=frozenset({4})))
    assert out.mode == HOLD


def test_the_agent_follows_its_plant_watchdog_down_and_holds_while_the_plant_is_silent() -> None:
    sup = Supervisor(mission(), 1, (3, 4))
    step(sup, 0, status=Status(plant_silent=True))
    assert sup.mode == HOLD and sup.events[-1].reason == "plant silent"
    step(sup, 1, status=Status())
    assert sup.mode == FLYING and sup.events[-1].reason == "plant recovered"
    step(sup, 2, status=Status(plant_mode=LAND))
    assert sup.mode == LAND and sup.events[-1].reason == "plant reports LAND: not flying the law"


@pytest.mark.parametrize("reported", [wire.ESTOP, LAND, wire.LANDED])
def test_a_plant_that_reports_it_stopped_makes_the_agent_land_never_estop(reported: int) -> None:
    """Only the operator's e-stop and the supervisor's own checks cut motors: a plant's report of
    ESTOP (which may be forged) stops the law and lands the vehicle."""
    sup = Supervisor(mission(), 1, (3, 4))
    for k in range(50):
        step(sup, k, status=Status(plant_mode=reported))
        assert sup.mode in (FLYING, LAND, wire.LANDED)
    assert [e.dst for e in sup.events][:1] == [LAND]
    assert sup.events[0].reason == f"plant reports {wire.MODES[reported]}: not flying the law"
    assert all(e.dst != wire.ESTOP for e in sup.events)


def test_the_gates_first_reference_is_where_each_sender_really_starts() -> None:
    import msgspec

    from tether import mission as ms
    from tether.gate import initial_positions

    m = mission()
    ref = initial_positions(m)
    assert ref[4] == [0.0, 0.0, 1.0] and ref[2] == [2.0, 0.0, 1.0]
    leader = msgspec.structs.replace(m.leader, profile=ms.Waypoints(points=[ms.Waypoint(t=0.0, p=[5.0, 5.0, 2.0]),
                                                                          ms.Waypoint(t=10.0, p=[6.0, 5.0, 2.0])]))
    cf = ms.CrazyfliePlant(uri="udp://127.0.0.1:19850", takeoff_height=0.8)
    agents = [msgspec.structs.replace(a, plant=cf) if a.id == 1 else a for a in m.agents]
    ref = initial_positions(msgspec.structs.replace(m, leader=leader, agents=agents))
    assert ref[4] == [5.0, 5.0, 2.0]  # the first waypoint, not p0
    assert ref[1] == [1.0, 0.0, 1.8]  # above p0 by the take-off height


def test_after_ctrl_c_a_descent_still_under_way_extends_the_launchers_wait_and_a_stalled_one_does_not() -> None:
    """``deploy.supervise.Descent`` (pure): 3D without ``--land-timeout``, the wait lasts the nominal bound
    and then as long as some vehicle not yet landed came LAND_PROGRESS lower in the last LAND_STALL
    seconds, LAND_CAP times the bound at most; a vehicle hovering (pushed up as hard as it pushes
    down) ends it; 2D or a given ``--land-timeout``: the bound, whatever the vehicles do."""
    from deploy.supervise import LAND_CAP, LAND_PROGRESS, LAND_STALL, Descent

    bound = 6.0
    fixed = Descent(False, bound)
    assert all(fixed.limit(t, {"plant/1": 2.0 - 0.1 * t}) == bound for t in range(20))
    d = Descent(True, bound)
    h, t = 2.0, 0.0
    while t < 12.0:  # descending at 0.1 m/s: the wait keeps ahead of it
        assert d.limit(t, {"plant/1": h, "plant/2": 1.0}) > t
        t, h = t + 0.05, h - 0.005
    hover = h
    ends = [d.limit(t + s, {"plant/1": hover - 0.5 * LAND_PROGRESS, "plant/2": 1.0}) for s in (0.0, 1.0, 2.0)]
    assert ends[0] == ends[1] == ends[2] <= t + LAND_STALL  # hovering: no more extension
    slow = Descent(True, bound)  # a descent that never ends: the cap
    assert max(slow.limit(s * 0.1, {"plant/1": -s * 0.01}) for s in range(2000)) == LAND_CAP * bound
    assert slow.limit(0.0, {}) >= bound


def test_a_suspect_stream_is_an_event_and_a_lost_input() -> None:
    """Agent 1 hears the leader (4) and agent 3 in ``mission()``: a suspect neighbour is dropped
    (kappa re-normalised) while the leader reaches it; a suspect leader or own plant stream holds, then
    lands after land_after; each verdict and its end is an event naming the stream."""
    m = mission()
    sup = Supervisor(m, 1, (3, 4))
    lost, reachable, silent = sup.links(0, 0.0, [0.0, 0.0], Status(suspect=frozenset({3})))
    assert lost == frozenset({3}) and reachable and not silent
    assert "neighbour 3 mostly rejected" in sup.events[0].reason and sup.events[0].dst == FLYING
    lost, _, _ = sup.links(1, H, [0.0, 0.0], Status())
    assert lost == frozenset() and [e.reason for e in sup.events[-2:]] == [
        "neighbour 3 trusted again", "neighbour 3 back: edge restored"]
    for who, cause in ((4, "leader's stream suspect"), (1, "own plant's stream suspect")):
        sup = Supervisor(m, 1, (3, 4))
        bad = Status(suspect=frozenset({who}))
        for k in range(int(m.safety.land_after / H) + 2):
            sup.links(k, k * H, [0.0, 0.0], bad)
            step(sup, k, status=bad)
        assert [e.dst for e in sup.events if e.src != e.dst] == [HOLD, LAND]
        assert cause in sup.events[1].reason
