"""The agent tick's own link statistics: the sorted sliding window gives numpy's percentiles exactly."""

from __future__ import annotations

import numpy as np

from agent.tick import AgentTick, _percentile
from tether.catalog import builtin_path
from tether.node import load_mission


def test_percentile_of_a_sorted_list_is_numpys_bit_for_bit() -> None:
    rng = np.random.default_rng(1)
    for _ in range(500):
        n = int(rng.integers(1, 600))
        x = sorted((rng.exponential(0.02, n) if rng.random() < 0.7 else rng.choice([0.0, 0.01, 0.02], n)).tolist())
        for q in (0.0, 50.0, 99.0, 100.0):
            assert _percentile(x, q) == float(np.percentile(x, q))


def test_vec_dot_adds_the_products_in_order_bit_for_bit() -> None:
    """tether.vec.dot's unrolled 2- and 3-vector forms are its loop's additions, left to right,
    down to the last bit, signs of zero and non-finite terms included."""
    from tether import vec

    def in_order(x: list[float], y: list[float]) -> float:
        acc = x[0] * y[0]
        for a, b in zip(x[1:], y[1:]):
            acc += a * b
        return acc

    rng = np.random.default_rng(7)
    special = [0.0, -0.0, 1e308, -1e308, 1e-320, np.inf, -np.inf, np.nan]
    for d in (1, 2, 3, 4, 8):
        for _ in range(3000):
            x = (rng.normal(size=d) * 10.0 ** rng.integers(-8, 9, size=d)).tolist()
            y = (rng.normal(size=d) * 10.0 ** rng.integers(-8, 9, size=d)).tolist()
            if rng.random() < 0.3:
                x[int(rng.integers(d))] = float(rng.choice(special))
            got, want = vec.dot(x, y), in_order(x, y)
            assert np.array([got]).tobytes() == np.array([want]).tobytes() or (got != got and want != want), (x, y)


def test_the_sliding_window_keeps_its_sorted_copy_in_step() -> None:
    tick = AgentTick.from_mission(load_mission(builtin_path("section4")), 1)
    rng = np.random.default_rng(2)
    for k in range(2000):
        tick._remember(0, float(rng.choice([0.0, 0.01, 0.02, rng.exponential(0.05)])))
        if k % 97 == 0:
            w = list(tick.windows[0])
            assert tick._sorted[0] == sorted(w)
            assert tick.age_percentiles(0) == tuple(float(v) for v in np.percentile(w, (50, 99)))
    assert len(tick.windows[0]) == tick.windows[0].maxlen
