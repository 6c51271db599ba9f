"""Reference-simulator throughput in agent-steps per second (no recording), numpy path beside the compiled kernels.

    python bench/refsim_throughput.py [--sizes 4 100 1000] [--repeats 5] [--steps 2000] [--continuous-steps 200]

Missions: N double integrators, 3D, the leader heard by agent 1, every other agent hearing one
earlier agent (a random tree) plus one random extra in-edge (mean in-degree about 2), sinusoidal
disturbances on every agent (the same model on each; then each agent its own random phases, so that
no two agents share a sine; then none), the sigma law. Prints, per engine
(``numpy``: the reference code; ``compiled``: :mod:`sim.kernel`, numba), the median and the spread
of ``--repeats`` runs, and the ratio of the medians (of wall time, and of this process's CPU time:
the figure to compare on a shared machine); then the same for the continuous mode (RK4,
10 substeps) over ``--continuous-steps`` control steps (beyond N = 100 the compiled kernel alone, on
the random tree without its extra edges). ``compiledx2``: the compiled discrete mode
on two of numba's threads (``--threads``); its wall time is the figure to read, on a quiet machine.
The compiled kernels' first call in a fresh process (import, compile or cache load) is printed
apart, cold and warm, and never enters a median.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.factories import build  # noqa: E402
from sim import kernel, refsim  # noqa: E402
from sim.setup import Engine, Mode
from tether.mission import Mission  # noqa: E402


def mission(n: int, steps: int, seed: int = 0, disturbance: bool | str = True, extra: bool = True) -> Mission:
    """``disturbance``: True the same sinusoid on every agent, ``"phases"`` each agent its own
    random phases (every agent's sines distinct), False none. ``extra``: one random extra in-edge
    per agent (most agents then form one strongly connected block); else the random tree alone."""
    rng = np.random.default_rng(seed)
    edges = {(n + 1, 1): 1.0}
    for i in range(2, n + 1):
        edges[(int(rng.integers(1, i)), i)] = 1.0
        j = int(rng.integers(1, n + 1))
        if j != i and extra:
            edges.setdefault((j, i), 0.5)
    sine = {"kind": "sinusoid", "amplitude": [0.3, 0.3, 0.1], "omega": [1.0, 2.0, 3.0]}
    agents = [{"id": i, "p0": rng.normal(0, 1, 3).tolist(), "offset": rng.normal(0, 1, 3).tolist(),
               "disturbance": ({**sine, "phase": rng.uniform(0, 6, 3).tolist()} if disturbance == "phases" else
                               sine if disturbance else {"kind": "none"})}
              for i in range(1, n + 1)]
    return build({
        "version": 1, "name": f"bench{n}", "dim": 3, "rate": 100.0, "duration": steps / 100.0,
        "law": {"kind": "sigma", "kp0": 1.5, "kv0": 1.2, "gamma_p": 0.1, "gamma_v": 0.05, "sigma": 0.1},
        "leader": {"id": n + 1, "p0": [0.0, 0.0, 1.0], "profile": {"kind": "exp_accel", "a0": [0.2, 0.0, 0.0], "decay": 0.1}},
        "agents": agents, "edges": [{"from": s, "to": d, "weight": w} for (s, d), w in edges.items()],
    })


def rate(m: Mission, mode: Mode, engine: Engine, n: int, steps: int, repeats: int,
         threads: int = 1) -> tuple[list[float], list[float]]:
    """Agent-steps per second of wall time and per second of this process's CPU time, per repeat."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        refsim.simulate(m, mode, engine=engine, record=False, threads=threads)
        wall.append(n * steps / (time.perf_counter() - t0))
        cpu.append(n * steps / max(time.process_time() - c0, 1e-9))
    return wall, cpu


def first_call() -> str:
    """The compiled kernels' start-up in a fresh process: import + compile (or cache load) + one tiny run."""
    code = ("import time; t0 = time.perf_counter(); from sim import refsim; from tests.factories import build; "
            "import bench.refsim_throughput as b; m = b.mission(4, 10); "
            "refsim.simulate(m, engine='compiled', record=False); print(time.perf_counter() - t0)")
    import subprocess
    root = str(Path(__file__).resolve().parents[1])
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root,
                          env={**__import__("os").environ, "PYTHONPATH": root})
    return done.stdout.strip() or done.stderr.strip()[-300:]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 100, 1000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--continuous-steps", type=int, default=200)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2],
                    help="also run the compiled discrete mode on this many of numba's threads (1: only one)")
    args = ap.parse_args()
    engines: list[Engine] = ["numpy", "compiled"] if kernel.AVAILABLE else ["numpy"]
    if kernel.AVAILABLE:
        print(f"compiled kernels, first call in a fresh process [s]: {float(first_call()):.2f} (then warm: "
              f"{float(first_call()):.2f})")
    else:
        print("numba is not installed: numpy path only (pip install 'tether[fast]')")
    modes: tuple[tuple[Mode, int], ...] = (("discrete", args.steps), ("continuous", args.continuous_steps))
    for mode, steps in modes:
        print(f"\n{mode}, {steps} steps; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
        print(f"{'N':>6} {'disturbance':>12} {'engine':>11} {'median agent-steps/s':>20} {'min':>10} {'max':>10} "
              f"{'us/step':>9} {'ratio':>7} {'per CPU-s':>10} {'ratio':>7}")
        for n, dist in [(n, dist) for n in args.sizes for dist in (True, "phases", False)]:
            tree = mode == "continuous" and n > 100
            if tree and (dist is not True or "compiled" not in engines):
                continue
            # continuous beyond 100 agents: the compiled kernel alone (the numpy RK4 pays Python per
            # stage: minutes at N = 1000), on the random tree without extra edges, which it solves
            # agent by agent (O(N)); with them, one block holds most agents and L1^-1 is dense
            m = mission(n, steps, disturbance=dist, extra=not tree)
            runs: list[tuple[Engine, int]] = [(e, 1) for e in engines] if not tree else [("compiled", 1)]
            if "compiled" in engines and mode == "discrete":
                runs += [("compiled", t) for t in args.threads if t > 1]
            for engine, threads in runs[1:]:
                refsim.simulate(m, mode, engine=engine, record=False, threads=threads)  # warm (compiled, loaded)
            base = cbase = None
            for engine, threads in runs:
                rates, cpu = rate(m, mode, engine, n, steps, args.repeats, threads)
                med, cmed = statistics.median(rates), statistics.median(cpu)
                base, cbase = base or med, cbase or cmed
                label = {True: "sinusoid", "phases": "sin, phases", False: "none"}[dist] + (", tree" if tree else "")
                name = engine if threads == 1 else f"{engine}x{threads}"
                print(f"{n:>6} {label:>12} {name:>11} {med:>20.3e} {min(rates):>10.2e} "
                      f"{max(rates):>10.2e} {1e6 * n / med:>9.2f} {med / base:>6.1f}x {cmed:>10.2e} "
                      f"{cmed / cbase:>6.1f}x")


if __name__ == "__main__":
    main()
