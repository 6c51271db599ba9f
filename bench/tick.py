"""What one agent tick costs, piece by piece: the law alone, the tick with the safety supervisor, the
plausibility gate, collision avoidance, and the link statistics' percentiles.

    python bench/tick.py [--mission section4] [--ticks 20000] [--repeats 7]

Prints, per piece, the median over ``--repeats`` runs of the mean cost per tick [µs] and its ratio
to the law alone, all measured in one run (the machine is shared: compare ratios, not absolute
figures across runs). Pure code only: no processes, no Zenoh.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from agent.avoid import filter_command
from tether.gate import Gate
from agent.safety import NOMINAL
from agent.tick import AgentTick
from tether import wire
from tether.catalog import builtin_path
from tether.node import load_mission


def timed(fn: Callable[[int], None], ticks: int, repeats: int) -> float:
    """Median over ``repeats`` of the mean time per call of ``fn(k)`` [µs]."""
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for k in range(ticks):
            fn(k)
        runs.append((time.perf_counter() - t0) / ticks * 1e6)
    return statistics.median(runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mission", default="section4")
    ap.add_argument("--agent", type=int, default=None, help="agent id (default: the first)")
    ap.add_argument("--ticks", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    m = load_mission(builtin_path(args.mission))
    aid = args.agent if args.agent is not None else m.agent_ids[0]
    d = m.dim
    rng = np.random.default_rng(0)
    tick = AgentTick.from_mission(m, aid)
    law = tick.law
    nb = len(law.neighbours)
    p, v, a = rng.normal(size=d) * 0.1, rng.normal(size=d) * 0.1, np.zeros(d)
    heard = [(0.0, p + 0.01 * rng.normal(size=d), v.copy(), a.copy()) for _ in range(nb)]
    nb_p = np.array([h[1] for h in heard])
    nb_v = np.array([h[2] for h in heard])
    nb_a = np.zeros((nb, d))
    kp, kv = (np.array(x) for x in law.initial())
    h = m.dt
    # the tick takes samples as they come off the wire: lists of floats
    pl, vl, al = p.tolist(), v.tolist(), a.tolist()
    heard_l = [(t0, hp.tolist(), hv.tolist(), ha.tolist()) for t0, hp, hv, ha in heard]
    nb_pl, nb_vl, nb_al, kpl, kvl = nb_p.tolist(), nb_v.tolist(), nb_a.tolist(), kp.tolist(), kv.tolist()

    def law_only(k: int) -> None:
        law.step(pl, vl, nb_pl, nb_vl, nb_al, kpl, kvl)

    fresh = AgentTick.from_mission(m, aid)  # the full tick on its own state

    def full_tick(k: int) -> None:
        t = k * h
        fresh.step(k, t, pl, vl, al, [(t, hp, hv, ha) for _, hp, hv, ha in heard_l], NOMINAL)

    gate = Gate(h, m.safety.max_speed, m.safety.jump_margin, p.tolist())
    msgs = [wire.State(sender=1, seq=k, k=k, t=k * h, p=p.tolist(), vel=v.tolist(), a=a.tolist()) for k in range(256)]

    def gate_check(k: int) -> None:
        for _ in range(nb):
            gate.check(msgs[k % 256])

    # on lists, as the agent runs it (agent/node.py passes the samples' lists)
    near = [([c + o for c, o in zip(pl, [0.5] + [0.0] * (d - 1))], [-c for c in vl])]
    one = [1.0] * d

    def avoid(k: int) -> None:
        filter_command(one, pl, vl, near, 0.3, 2.0, 1.0, 2.0)

    for n in range(nb):
        for j in range(500):
            tick._remember(n, 0.001 * (j % 37))

    def percentiles(k: int) -> None:
        for n in range(nb):
            tick.age_percentiles(n)

    base = timed(law_only, args.ticks, args.repeats)
    rows = [("law alone (AgentLaw.step)", base),
            ("agent tick: policy + law + supervisor (AgentTick.step)", timed(full_tick, args.ticks, args.repeats)),
            (f"plausibility gate, {nb} sample(s)", timed(gate_check, args.ticks, args.repeats)),
            ("collision avoidance, one vehicle near", timed(avoid, args.ticks // 4, args.repeats)),
            (f"link age percentiles, {nb} link(s), 500-tick window", timed(percentiles, args.ticks // 4, args.repeats))]
    print(f"mission {m.name}, agent {aid} ({nb} in-neighbour(s)), d = {d}; median of {args.repeats} runs")
    print(f"{'piece':58s} {'µs/tick':>9s} {'× law':>7s}")
    for name, us in rows:
        print(f"{name:58s} {us:9.2f} {us / base:7.2f}")


if __name__ == "__main__":
    main()
