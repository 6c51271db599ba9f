"""The plant's command watchdog (pure, every transition on a fake time series) and the ground and
motors-off model of simulated vehicles (plant.rest)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from plant import base

from plant.build import build
from plant.rest import Resting
from plant.vehicle import G
from plant.watchdog import ABSURD, Watchdog
from tests import factories
from tether import failsafe
from tether import mission as ms
from tether.wire import ESTOP, FLYING, HOLD, LAND, LANDED

H = 0.02
SAFETY = ms.Safety(land_after=2.0, cmd_cutoff=2.0)
"""The firmware's 2 s from a silent agent to LAND (shorter than the defaults, so that the landings fit these runs)."""


class Fake:
    """A 3D (or 2D) point driven by the watchdog's own output, exactly integrated (a double integrator)."""

    def __init__(self, dim: int, p0: list[float], v0: list[float] | None = None):
        self.p = np.array(p0, dtype=float)
        self.v = np.array(v0 if v0 is not None else [0.0] * dim, dtype=float)

    def advance(self, u: list[float]) -> None:
        ua = np.asarray(u)
        self.p = self.p + self.v * H + 0.5 * H * H * ua
        self.v = self.v + ua * H


def fly(dog: Watchdog, veh: Fake, k0: int, k1: int, command=None, operator=None, log=None):
    """Ticks k0..k1-1: the agent sends ``command(k)`` (None: silent) stamped k H; returns the modes."""
    modes = []
    for k in range(k0, k1):
        t = k * H
        if command is not None:
            u = command(k)
            if u is not None:
                dog.offer(u, (k - 1) * H, k - 1, k)
        d = dog.step(t, veh.p, veh.v, operator(k) if operator else None)
        assert np.all(np.isfinite(d.u)) and np.linalg.norm(d.u) <= SAFETY.max_accel + 1e-12
        if log is not None:
            log.extend(d.events)
        veh.advance(d.u)
        modes.append(d.mode)
    return modes


def first(modes: list[int], mode: int, k0: int = 0) -> int:
    return k0 + modes.index(mode)


def test_flying_passes_the_agents_command_through_bit_for_bit() -> None:
    dog = Watchdog(SAFETY, 3, H)
    rng = np.random.default_rng(1)
    for k in range(1, 50):
        u = rng.normal(size=3)
        assert dog.offer(u.tolist(), (k - 1) * H, k - 1, k)
        d = dog.step(k * H, np.array([0.0, 0.0, 1.0]), np.zeros(3))
        assert d.mode == FLYING and not d.events and np.array_equal(d.u, u)


def test_silence_holds_after_cmd_timeout_then_lands_at_cmd_cutoff_then_rests() -> None:
    dog, veh, events = Watchdog(SAFETY, 3, H), Fake(3, [1.0, 2.0, 1.5], [0.8, -0.4, 0.2]), []
    modes = fly(dog, veh, 1, 50, command=lambda k: [0.0, 0.0, 0.0], log=events)
    assert set(modes) == {FLYING}
    last_cmd = 48 * H  # the last command's stamp
    modes = fly(dog, veh, 50, 1500, log=events)
    k_hold = first(modes, HOLD, 50)
    assert k_hold * H - last_cmd > SAFETY.cmd_timeout and (k_hold - 1) * H - last_cmd <= SAFETY.cmd_timeout
    k_land = first(modes, LAND, 50)
    assert k_land * H - last_cmd >= SAFETY.cmd_cutoff > (k_land - 1) * H - last_cmd
    k_landed = first(modes, LANDED, 50)
    assert modes[-1] == LANDED and veh.p[2] - SAFETY.ground <= 0.02
    # HOLD braked: slow by LAND, near where HOLD began horizontally
    assert [e.dst for e in events] == [HOLD, LAND, LANDED]
    assert "no valid command" in events[0].reason and events[0].t == pytest.approx(k_hold * H)
    assert np.linalg.norm(dog.p_hold[:2] - veh.p[:2]) < 0.05
    assert k_landed > k_land


def test_a_command_back_during_hold_flies_again_but_not_after_land() -> None:
    dog, veh = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 1.0])
    fly(dog, veh, 1, 10, command=lambda k: [0.1, 0.0, 0.0])
    modes = fly(dog, veh, 10, 50)
    assert modes[-1] == HOLD
    assert fly(dog, veh, 50, 52, command=lambda k: [0.1, 0.0, 0.0]) == [FLYING, FLYING]
    modes = fly(dog, veh, 52, 200)
    assert modes[-1] == LAND
    assert set(fly(dog, veh, 200, 210, command=lambda k: [0.1, 0.0, 0.0])) == {LAND}


def test_operator_land_lands_at_once_and_never_flies_again() -> None:
    dog, veh, events = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 1.0]), []
    modes = fly(dog, veh, 1, 600, command=lambda k: [0.0, 0.0, 0.0],
                operator=lambda k: "land" if k >= 5 else None, log=events)
    assert modes[:4] == [FLYING] * 4 and modes[4] == LAND
    assert modes[-1] == LANDED and set(modes[4:]) <= {LAND, LANDED}
    assert events[0].reason == "operator land"


@pytest.mark.parametrize("before", [FLYING, HOLD, LAND, LANDED])
def test_operator_estop_is_immediate_and_terminal(before: int) -> None:
    dog, veh = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 0.3])
    silent_for = {FLYING: 0, HOLD: 30, LAND: 110, LANDED: 700}[before]
    fly(dog, veh, 1, 5, command=lambda k: [0.0, 0.0, 0.0])
    fly(dog, veh, 5, 5 + silent_for)
    assert dog.mode == before
    d = dog.step((6 + silent_for) * H, veh.p, veh.v, "estop")
    assert d.mode == ESTOP and np.array_equal(d.u, np.zeros(3)) and d.events[0].reason == "operator estop"
    assert set(fly(dog, veh, 7 + silent_for, 30 + silent_for, command=lambda k: [1.0, 0.0, 0.0])) == {ESTOP}
    assert dog.terminal


@pytest.mark.parametrize("before", [FLYING, HOLD, LAND])
def test_a_vehicle_that_says_it_is_down_is_estopped_for_good(before: int) -> None:
    """A Crazyflie whose firmware cut its motors (``plant.preflight.down``) lies on the floor: flying
    it on would have its agent command it up and its neighbours follow. ESTOP at once, latched: no
    later word (its agent landed, fresh commands, the reason gone) takes it out of ESTOP."""
    dog, veh = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 0.8])
    silent_for = {FLYING: 0, HOLD: 30, LAND: 110}[before]
    fly(dog, veh, 1, 5, command=lambda k: [0.0, 0.0, 0.0])
    fly(dog, veh, 5, 5 + silent_for)
    assert dog.mode == before
    k = 6 + silent_for
    d = dog.step(k * H, veh.p, veh.v, None, down="its firmware has cut the motors (locked)")
    assert d.mode == ESTOP and d.u == [0.0, 0.0, 0.0]
    assert [e.reason for e in d.events if e.dst == ESTOP] == ["vehicle down: its firmware has cut the motors (locked)"]
    assert dog.terminal
    assert set(fly(dog, veh, k + 1, k + 40, command=lambda k: [1.0, 0.0, 3.0])) == {ESTOP}  # the reason not repeated
    dog.offer([0.0, 0.0, 0.0], (k + 40) * H, k + 40, k + 41, LANDED)  # its agent says landed
    assert dog.step((k + 41) * H, veh.p, veh.v).mode == ESTOP
    assert dog.step((k + 42) * H, veh.p, veh.v, "estop").mode == ESTOP  # the operator's e-stop changes nothing


def test_invalid_commands_do_not_count_and_nothing_unsafe_leaves() -> None:
    dog, veh = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 1.0])
    fly(dog, veh, 1, 5, command=lambda k: [0.0, 0.0, 0.0])
    bad = [[math.nan, 0.0, 0.0], [math.inf, 0.0, 0.0], [ABSURD * SAFETY.max_accel * 2, 0.0, 0.0]]
    modes = fly(dog, veh, 5, 60, command=lambda k: bad[k % 3])
    assert modes[-1] == HOLD  # a stream of garbage is silence
    assert dog.invalid == {"nonfinite": 36, "absurd": 19}
    # a strong but plausible command is saturated, not dropped
    assert dog.offer([3 * SAFETY.max_accel, 0.0, 0.0], 60 * H, 60, 61)
    d = dog.step(61 * H, veh.p, veh.v)
    assert d.mode == FLYING and d.u == pytest.approx([SAFETY.max_accel, 0.0, 0.0])
    # a command for a tick beyond the plant's own is not valid
    assert not dog.offer([0.0, 0.0, 0.0], 70 * H, 70, 62)
    assert dog.invalid["future"] == 1


def test_no_measurement_holds_and_its_return_lands_unless_the_agent_resumed() -> None:
    for resumed in (True, False):
        dog = Watchdog(SAFETY, 3, H)
        p, v = np.array([0.0, 0.0, 1.0]), np.zeros(3)
        dog.offer([0.0, 0.0, 0.0], 0.0, 0, 1)
        assert dog.step(H, p, v).mode == FLYING
        assert dog.step(2 * H, None, None).mode == HOLD
        k = 80  # 1.6 s blind: past cmd_timeout
        if resumed:
            dog.offer([0.0, 0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, p, v)
        assert d.mode == (FLYING if resumed else LAND), d.events


def test_2d_lands_by_stopping() -> None:
    dog, veh = Watchdog(SAFETY, 2, H), Fake(2, [0.0, 0.0], [1.0, 0.5])
    fly(dog, veh, 1, 3, command=lambda k: [0.0, 0.0])
    modes = fly(dog, veh, 3, 800)
    assert modes[-1] == LANDED and np.linalg.norm(veh.v) < 0.05


class Swaying(Fake):
    """A 2D :class:`Fake` under a cable's steady circular sway (0.5 m/s^2) that HOLD cannot cancel."""

    def __init__(self, p0: list[float]):
        super().__init__(2, p0)
        self.t = 0.0

    def advance(self, u: list[float]) -> None:
        super().advance(list(np.asarray(u) + 0.5 * np.array([math.cos(self.t), math.sin(self.t)])))
        self.t += H


def test_2d_lands_under_a_sway_after_land_settle_at_most() -> None:
    """Its agent dead, a 2D plant under a sway that keeps it moving lands (stops) after
    ``land_settle`` in LAND instead of holding for ever."""
    dog, veh, events = Watchdog(SAFETY, 2, H), Swaying([0.0, 0.0]), []
    fly(dog, veh, 1, 3, command=lambda k: [0.0, 0.0])
    modes = fly(dog, veh, 3, 3 + round((SAFETY.cmd_cutoff + 2 * SAFETY.land_settle) / H), log=events)
    assert [e.dst for e in events] == [HOLD, LAND, LANDED]
    land, landed = events[1], events[2]
    assert landed.t - land.t == pytest.approx(SAFETY.land_settle, abs=1.01 * H)
    assert "land_settle" in landed.reason and "still moving" in landed.reason, landed.reason
    assert modes[-1] == LANDED and np.linalg.norm(veh.v) > 0.05  # the model moves on; the plant rests it


class Pushed(Fake):
    """A 3D :class:`Fake` under a steady push up [m/s^2] (a 5 % thrust error), resting on the ground."""

    def advance(self, u: list[float]) -> None:
        super().advance(list(np.asarray(u) + [0.0, 0.0, 0.5]))
        if self.p[2] <= 0.0:
            self.p[2], self.v[:] = 0.0, 0.0


def test_a_plant_whose_agent_died_lands_against_a_steady_push_up() -> None:
    """LAND's proportional descent alone hovered 25 cm above the ground for ever under this push."""
    dog, veh, events = Watchdog(SAFETY, 3, H), Pushed(3, [0.0, 0.0, 1.0]), []
    fly(dog, veh, 1, 3, command=lambda k: [0.0, 0.0, -0.5])
    modes = fly(dog, veh, 3, round(40.0 / H), log=events)
    assert [e.dst for e in events] == [HOLD, LAND, LANDED], events
    assert modes[-1] == LANDED and events[-1].reason == "on the ground"  # (the fake has no rest: it rises after)


@pytest.mark.parametrize("resumed", [True, False])
def test_a_non_finite_measurement_is_no_measurement(resumed: bool) -> None:
    """A diverged estimator (a Crazyflie's Kalman filter) or a corrupted log gives NaN: the plant
    flies it as a lost measurement (HOLD blind, a zero command), never holds about it, and once
    the estimate is finite again flies on if its agent's command is fresh, else lands there."""
    dog, veh, events = Watchdog(SAFETY, 3, H), Fake(3, [0.0, 0.0, 1.0], [0.2, 0.0, 0.0]), []
    fly(dog, veh, 1, 10, command=lambda k: [0.0, 0.0, 0.0], log=events)
    for k, bad in enumerate(([math.nan, 0.0, 1.0], [0.0, math.inf, 1.0]), start=10):
        dog.offer([0.0, 0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, bad, veh.v)
        events.extend(d.events)
        assert d.mode == HOLD and d.u == [0.0, 0.0, 0.0]
    last = 12 if resumed else 12 + round(2 * SAFETY.cmd_timeout / H)  # silent agent: its command goes stale
    for k in range(12, last + 1):
        d = dog.step(k * H, veh.p, [math.nan, 0.0, 0.0])
        assert d.mode == HOLD and d.u == [0.0, 0.0, 0.0] and dog.p_hold is None
    assert events[0].reason == "own measurement not finite" and dog.garbled == last - 9
    if resumed:
        dog.offer([0.0, 0.0, 0.0], last * H, last, last + 1)
    d = dog.step((last + 1) * H, veh.p, veh.v)
    assert d.mode == (FLYING if resumed else LAND), d.events
    if not resumed:
        # lands where its brake brings it to rest from where it is measured again
        assert dog.p_hold == failsafe.hold_point(veh.p.tolist(), veh.v.tolist(), SAFETY.hold_kp, SAFETY.max_accel,
                                                 SAFETY.ground)
        assert dog.p_hold[0] > veh.p[0]  # ahead of it: it moves on at 0.2 m/s
    assert all(np.isfinite(d.u))


# --------------------------------------------------------------------------- plant.rest
def one_vehicle(dim: int, p0: list[float], v0: list[float], plant: dict | None = None) -> ms.Mission:
    agent = {"id": 1, "p0": p0, "v0": v0, "offset": [0.0] * dim}
    if plant is not None:
        agent["plant"] = plant
    return factories.build({
        "version": 1, "name": "rest", "dim": dim, "rate": 1 / H, "duration": 10.0,
        "law": {"kind": "benchmark", "kp0": 1.0, "kv0": 1.0, "gamma_p": 0.05, "gamma_v": 0.05},
        "leader": {"id": 2, "p0": [0.0] * dim}, "agents": [agent], "edges": [{"from": 2, "to": 1, "weight": 1.0}]})


def test_resting_is_transparent_while_the_vehicle_flies() -> None:
    m = one_vehicle(3, [0.0, 0.0, 1.0], [0.3, 0.0, 0.1])
    (bare,), (inner,) = build(m), build(m)
    wrapped = Resting(inner, 3, 0.0)
    rng = np.random.default_rng(2)
    for _ in range(50):
        u = rng.normal(size=(1, 3))
        bare.step(u)
        wrapped.step(u, [rng.choice([FLYING, HOLD, LAND])])
        a, b = bare.state(), wrapped.state()
        assert np.array_equal(a.p, b.p) and np.array_equal(a.v, b.v) and np.array_equal(a.a, b.a)


@pytest.mark.parametrize("plant", [None, {"kind": "quadrotor"}])
def test_estop_falls_under_gravity_to_the_ground_then_rests(plant: dict | None) -> None:
    m = one_vehicle(3, [0.5, 0.0, 1.0], [0.0, 0.0, 0.0], plant)
    (inner,) = build(m)
    veh = Resting(inner, 3, 0.0)
    zs = []
    for _ in range(200):
        veh.step(np.zeros((1, 3)), [ESTOP])
        zs.append(veh.state().p[0, 2])
    s = veh.state()
    if plant is None:  # lost thrust: the double integrator falls at g exactly
        assert zs[9] == pytest.approx(1.0 - 0.5 * G * (10 * H) ** 2, abs=1e-12)
    assert veh.resting(0) and s.p[0, 2] == 0.0 and np.array_equal(s.v[0], np.zeros(3))
    assert np.all(np.diff(zs) <= 1e-12) and min(zs) >= 0.0  # down, never through the ground
    t_fall = math.sqrt(2.0 / G)
    assert zs.index(0.0) * H == pytest.approx(t_fall, abs=0.1 if plant else 2 * H)


def test_landed_rests_where_it_touched_down_and_2d_estop_stops() -> None:
    m = one_vehicle(3, [0.5, 0.2, 0.01], [0.0, 0.0, -0.05])
    (inner,) = build(m)
    veh = Resting(inner, 3, 0.0)
    veh.step(np.zeros((1, 3)), [LANDED])
    rest = veh.state()
    for _ in range(20):
        veh.step(np.array([[5.0, 0.0, 5.0]]), [LANDED])
        s = veh.state()
        assert np.array_equal(s.p, rest.p) and not np.any(s.v)
    m2 = one_vehicle(2, [0.5, 0.2], [1.0, 0.0])
    (inner2,) = build(m2)
    veh2 = Resting(inner2, 2, 0.0)
    p0 = veh2.state().p.copy()
    veh2.step(np.zeros((1, 2)), [ESTOP])
    veh2.step(np.zeros((1, 2)), [ESTOP])
    assert np.array_equal(veh2.state().p, p0) and not np.any(veh2.state().v)


@pytest.mark.parametrize("agent_mode, want", [(LANDED, LANDED), (ESTOP, ESTOP)])
def test_the_agents_supervisor_mode_rides_on_its_command(agent_mode: int, want: int) -> None:
    """An agent whose supervisor has landed (or stopped) its vehicle says so in its command: the
    plant rests (or cuts its motors) at once, without waiting for its own timeouts."""
    dog = Watchdog(SAFETY, 3, H)
    assert dog.offer([0.0, 0.0, 0.0], 0.0, 0, 1, FLYING)
    assert dog.step(H, np.zeros(3), np.zeros(3)).mode == FLYING
    assert dog.offer([0.0, 0.0, 0.0], H, 1, 2, agent_mode)
    d = dog.step(2 * H, np.zeros(3), np.zeros(3))
    assert d.mode == want and not any(d.u) and d.events[-1].reason.startswith("agent")


def test_the_ground_stops_a_vehicle_its_agent_lands_while_the_watchdog_says_flying() -> None:
    """An agent's supervisor lands its vehicle with the plant's watchdog in FLYING (it follows the
    agent's LAND commands): the ground must stop the vehicle all the same (measured before the fix:
    8 cm below the ground, bench/faults.py freeze:agent/1)."""
    m = one_vehicle(3, [0.5, 0.0, 0.05], [0.0, 0.0, -0.6])
    (inner,) = build(m)
    veh = Resting(inner, 3, 0.0)
    dog = Watchdog(SAFETY, 3, H)
    zs = []
    for k in range(1, 51):
        dog.offer([0.0, 0.0, 0.5], (k - 1) * H, k - 1, k, LAND)  # braking too late to stop above the ground
        s = veh.state()
        d = dog.step(k * H, s.p[0], s.v[0])
        assert d.mode == FLYING and d.rest == LAND and not d.events  # the agent lands it: no contact event
        veh.step(np.array([d.u]), [d.rest])
        zs.append(veh.state().p[0, 2])
    assert min(zs) >= 0.0 and veh.resting(0)
    s = veh.state()
    assert s.p[0, 2] == 0.0 and not np.any(s.v)
