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
