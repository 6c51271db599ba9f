"""Leader profiles, disturbance models and the exact plant discretisation."""

import numpy as np
import pytest

from leader import profile
from plant import double_integrator
from plant.disturbance import DisturbanceBank
from tether import mission as ms
from tether.catalog import builtin_path
from tests.factories import random_mission


def _simpson(f, a: float, b: float, n: int = 2000) -> np.ndarray:
    x = np.linspace(a, b, 2 * n + 1)
    y = np.array([f(t) for t in x])
    h = (b - a) / (2 * n)
    return h / 3 * (y[0] + y[-1] + 4 * y[1:-1:2].sum(axis=0) + 2 * y[2:-1:2].sum(axis=0))


@pytest.mark.parametrize("kind", ["sinusoid", "constant", "bounded_random"])
def test_disturbance_increments_are_exact_integrals(kind: str) -> None:
    m = random_mission(np.random.default_rng(4), 3, dim=3, disturbance=kind, d0=2.0, duration=20.0)
    bank = DisturbanceBank.from_mission(m)
    h = m.dt
    for k in (0, 1, 37, 1234, m.steps - 1):
        t0 = k * h
        dv, dp = bank.increments(k)
        # d is constant within a tick for the random model: sample it at the tick, not across ticks
        f = (lambda s: bank.value(k)) if kind == "bounded_random" else bank.value_at
        np.testing.assert_allclose(dv, _simpson(f, t0, t0 + h), rtol=0, atol=1e-13)
        np.testing.assert_allclose(dp, _simpson(lambda s: (t0 + h - s) * f(s), t0, t0 + h), rtol=0, atol=1e-13)


def test_bounded_random_respects_its_bound_and_seed() -> None:
    m = random_mission(np.random.default_rng(5), 4, disturbance="bounded_random", d0=0.5, duration=50.0)
    bank = DisturbanceBank.from_mission(m)
    vals = np.array([bank.value(k) for k in range(0, m.steps, 7)])
    bound = 0.5 / np.sqrt(2)
    assert np.abs(vals).max() <= bound
    assert np.abs(vals).max() > 0.8 * bound  # it does use its range
    again = DisturbanceBank.from_mission(m)
    np.testing.assert_array_equal(again.table, bank.table)
    one = DisturbanceBank.from_mission(m, [m.agents[2].id])  # a single plant process draws the same table
    np.testing.assert_array_equal(one.table[0], bank.table[2, : one.table.shape[1]])


def test_section4_disturbances_are_the_papers() -> None:
    m = ms.load(builtin_path("section4"))
    bank = DisturbanceBank.from_mission(m)
    t = 1.234
    k = int(round(t / m.dt))
    t = k * m.dt
    want = np.array([
        [0.5 * np.sin(t), 0.6 * np.cos(2 * t)],
        [0.9 * np.cos(4 * t), 0.2 * np.sin(3 * t)],
        [0.1 * np.sin(2 * t), 0.3 * np.sin(3 * t)],
        [0.4 * np.cos(4 * t), 0.7 * np.cos(t)],
    ])
    np.testing.assert_allclose(bank.value(k), want, rtol=0, atol=1e-15)


def test_section4_leader_is_the_papers() -> None:
    m = ms.load(builtin_path("section4"))
    ref = profile.build(m.leader, m.dim)
    t = np.array([0.0, 3.0, 50.0])
    p, v, a = ref(t)
    np.testing.assert_allclose(a[:, 0], np.exp(-0.1 * t), rtol=1e-15)
    np.testing.assert_allclose(v[:, 0], (1 - np.exp(-0.1 * t)) / 0.1, rtol=1e-14)
    np.testing.assert_allclose(p[:, 0], t / 0.1 - (1 - np.exp(-0.1 * t)) / 0.01, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(a[:, 1], 0.0)


def _leader(profile_tbl: dict, dim: int = 3, p0: list[float] | None = None) -> profile.Reference:
    import msgspec

    return profile.build(msgspec.convert({"id": 9, "p0": p0 or [0.0] * dim, "profile": profile_tbl}, ms.Leader), dim)


@pytest.mark.parametrize("tbl", [
    {"kind": "exp_accel", "a0": [1.0, -0.5, 0.2], "decay": 0.3},
    {"kind": "exp_accel", "a0": [1.0, -0.5, 0.2], "decay": 0.0},
    {"kind": "velocity_schedule", "ramp": 1.5, "segments": [{"t": 0.0, "v": [0.1, 0, 0]}, {"t": 4.0, "v": [0.3, -0.2, 0.05]}]},
    {"kind": "waypoints", "points": [{"t": 0.0, "p": [0.0, 0, 0]}, {"t": 3.0, "p": [1.0, 2, -1]}, {"t": 7.0, "p": [0.0, 2, 0]}]},
])
def test_profiles_are_self_consistent(tbl: dict) -> None:
    ref = _leader(tbl)
    t = np.linspace(0.01, 9.0, 500)
    eps = 1e-6
    p1, v1, a1 = ref(t + eps)
    p0, v0, a0 = ref(t - eps)
    p, v, a = ref(t)
    np.testing.assert_allclose((p1 - p0) / (2 * eps), v, rtol=0, atol=1e-6)
    np.testing.assert_allclose((v1 - v0) / (2 * eps), a, rtol=0, atol=1e-5)
    # a leader process evaluates one time at a time, the simulators many at once: the same bits
    for k in range(0, len(t), 7):
        for one, many in zip(ref(float(t[k])), (p, v, a)):
            assert one.shape == (3,) and one.tobytes() == np.ascontiguousarray(many[k]).tobytes(), k


@pytest.mark.parametrize("tbl", [
    {"kind": "exp_accel", "a0": [1.0, -0.5, 0.2], "decay": 0.3},
    {"kind": "hold"},
    {"kind": "velocity_schedule", "ramp": 1.5, "segments": [{"t": 0.0, "v": [0.1, 0, 0]}, {"t": 4.0, "v": [0.3, -0.2, 0.05]}]},
    {"kind": "waypoints", "points": [{"t": 0.0, "p": [0.0, 0, 0]}, {"t": 3.0, "p": [1.0, 2, -1]}, {"t": 7.0, "p": [0.0, 2, 0]}]},
])
def test_the_leaders_blocks_of_ticks_are_its_one_call_per_tick(tbl: dict) -> None:
    """The leader process sends ``at_ticks``' rows: each tick's floats are those of ``ref(k h)``
    alone (signs of zero included), in blocks that start anywhere and end at the mission's end."""
    ref, h = _leader(tbl, p0=[0.5, -1.0, 1.0]), 0.01
    for k0, k1 in ((0, 1100), (1100, 1101), (395, 420)):
        rows = profile.at_ticks(ref, h, k0, k1, 3)
        assert [len(r) for r in rows] == [k1 - k0] * 3
        for k in range(k0, k1):
            for got, want in zip(rows, ref(k * h)):
                assert np.array(got[k - k0]).tobytes() == want.tobytes(), (k, got[k - k0], want)


def test_eq31_velocity_schedule() -> None:
    tbl = {"kind": "velocity_schedule", "segments": [
        {"t": 0.0, "v": [0.0, 0.0, 0.0]}, {"t": 5.0, "v": [0.3, 0.0, 0.0]}, {"t": 15.0, "v": [0.0, 0.3, 0.0]}]}
    ref = _leader(tbl, p0=[-2.0, -2.0, 1.0])
    p, v, a = ref(np.array([0.0, 5.0, 5.01, 10.0, 15.0, 20.0, 25.0]))
    np.testing.assert_allclose(v[:, 0], [0, 0, 0.3, 0.3, 0.3, 0, 0])  # left-continuous: v(5) = 0, v(15) = 0.3
    np.testing.assert_allclose(v[:, 1], [0, 0, 0, 0, 0, 0.3, 0.3])
    np.testing.assert_allclose(p[-1], [-2.0 + 3.0, -2.0 + 3.0, 1.0], atol=1e-12)
    np.testing.assert_array_equal(a, 0.0)


def test_waypoints_reach_and_hold() -> None:
    tbl = {"kind": "waypoints", "points": [{"t": 0.0, "p": [0.0, 0.0]}, {"t": 2.0, "p": [1.0, -1.0]}]}
    ref = _leader(tbl, dim=2)
    p, v, a = ref(np.array([2.0, 5.0]))
    np.testing.assert_allclose(p, [[1.0, -1.0], [1.0, -1.0]], atol=1e-15)
    np.testing.assert_allclose(v, 0.0, atol=1e-15)


def test_double_integrator_step_is_exact_for_constant_input() -> None:
    p, v, u, d, h = np.array([1.0, 2.0]), np.array([-0.5, 0.3]), np.array([0.7, -1.1]), np.array([0.2, 0.1]), 0.37
    p1, v1, a1 = double_integrator.step(p, v, u, d * h, d * h * h / 2, h)
    np.testing.assert_allclose(p1, p + v * h + 0.5 * (u + d) * h * h, rtol=0, atol=1e-15)
    np.testing.assert_allclose(v1, v + (u + d) * h, rtol=0, atol=1e-15)
    np.testing.assert_allclose(a1, u + d, rtol=0, atol=1e-15)
