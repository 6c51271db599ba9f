"""Reference-simulator throughput in agent-steps per second (discrete mode, no recording).

    python bench/refsim_throughput.py [--sizes 4 100 1000] [--repeats 5] [--steps 2000]

Missions: N double integrators, 3D, the leader heard by agent 1, every other agent hearing one
earlier agent (a random tree) plus one random extra in-edge (mean in-degree about 2), sinusoidal
disturbances on every agent (and, as a second row, none), the sigma law. Prints the median and
the spread of ``--repeats`` runs.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.factories import build  # noqa: E402
from sim import refsim  # noqa: E402


def mission(n: int, steps: int, seed: int = 0, disturbance: bool = True):
    rng = np.random.default_rng(seed)
    edges = {(n + 1, 1): 1.0}
    for i in range(2, n + 1):
        edges[(int(rng.integers(1, i)), i)] = 1.0
        j = int(rng.integers(1, n + 1))
        if j != i:
            edges.setdefault((j, i), 0.5)
    sine = {"kind": "sinusoid", "amplitude": [0.3, 0.3, 0.1], "omega": [1.0, 2.0, 3.0]}
    agents = [{"id": i, "p0": rng.normal(0, 1, 3).tolist(), "offset": rng.normal(0, 1, 3).tolist(),
               "disturbance": sine if disturbance else {"kind": "none"}}
              for i in range(1, n + 1)]
    return build({
        "version": 1, "name": f"bench{n}", "dim": 3, "rate": 100.0, "duration": steps / 100.0,
        "law": {"kind": "sigma", "kp0": 1.5, "kv0": 1.2, "gamma_p": 0.1, "gamma_v": 0.05, "sigma": 0.1},
        "leader": {"id": n + 1, "p0": [0.0, 0.0, 1.0], "profile": {"kind": "exp_accel", "a0": [0.2, 0.0, 0.0], "decay": 0.1}},
        "agents": agents, "edges": [{"from": s, "to": d, "weight": w} for (s, d), w in edges.items()],
    })


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 100, 1000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=2000)
    args = ap.parse_args()
    print(f"{'N':>6} {'disturbance':>12} {'median agent-steps/s':>22} {'min':>12} {'max':>12} {'us/step':>9}")
    for n, dist in [(n, dist) for n in args.sizes for dist in (True, False)]:
        m = mission(n, args.steps, disturbance=dist)
        rates = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            refsim.simulate(m, "discrete", record=False)
            rates.append(n * args.steps / (time.perf_counter() - t0))
        med = statistics.median(rates)
        print(f"{n:>6} {'sinusoid' if dist else 'none':>12} {med:>22.3e} {min(rates):>12.3e} {max(rates):>12.3e} {1e6 * n / med:>9.1f}")


if __name__ == "__main__":
    main()
