"""Mission builders for tests: seeded random valid missions and small hand-made ones."""

from __future__ import annotations

from typing import Any

import msgspec
import numpy as np

from tether import mission as ms


def build(raw: dict[str, Any]) -> ms.Mission:
    """Decode and validate a mission given as a dict (as a TOML file would give it)."""
    m = msgspec.convert(raw, type=ms.Mission)
    problems = ms.validate(m)
    if problems:
        raise ms.MissionError("<test>", problems)
    return m


def random_mission(
    rng: np.random.Generator,
    n: int,
    *,
    dim: int = 2,
    law: str = "sigma",
    disturbance: str = "none",
    d0: float = 0.5,
    duration: float = 60.0,
    rate: float = 100.0,
    profile: dict[str, Any] | None = None,
    dense: bool = False,
) -> ms.Mission:
    """A valid random mission: a random spanning tree rooted at the leader plus random extra edges,
    weights in [0.5, 2], random offsets and initial states. ``dense``: every agent hears every
    other agent and the leader (in-degree N), weights in [0.5, 2], each agent starting within 0.3 m of
    its slot (a dense graph's first commands stay under the safety's max_accel)."""
    leader = n + 1
    order = rng.permutation(n) + 1
    edges: dict[tuple[int, int], float] = {}
    reached = [leader]
    for aid in order:  # spanning tree: each agent hears one node already reached
        src = int(reached[rng.integers(len(reached))])
        edges[(src, int(aid))] = float(rng.uniform(0.5, 2.0))
        reached.append(int(aid))
    for _ in range(int(rng.integers(0, 2 * n + 1))):
        src, dst = int(rng.integers(1, n + 2)), int(rng.integers(1, n + 1))
        if src != dst:
            edges.setdefault((src, dst), float(rng.uniform(0.5, 2.0)))
    if dense:
        for src in range(1, n + 2):
            for dst in range(1, n + 1):
                if src != dst:
                    edges.setdefault((src, dst), float(rng.uniform(0.5, 2.0)))
    agents = []
    for aid in range(1, n + 1):
        a: dict[str, Any] = {
            "id": aid,
            "p0": rng.uniform(-3, 3, dim).tolist(),
            "v0": rng.uniform(-0.5, 0.5, dim).tolist(),
            "offset": rng.uniform(-2, 2, dim).tolist(),
        }
        if dense:
            a["p0"] = (np.array(a["offset"]) + rng.uniform(-0.3, 0.3, dim)).tolist()
        if disturbance == "bounded_random":
            a["disturbance"] = {"kind": "bounded_random", "bound": float(d0 / np.sqrt(dim)), "hold": 0.5}
        elif disturbance == "sinusoid":
            a["disturbance"] = {"kind": "sinusoid", "amplitude": rng.uniform(0, d0 / np.sqrt(dim), dim).tolist(),
                                "omega": rng.uniform(0.2, 4.0, dim).tolist(),
                                "phase": rng.uniform(0, 6.28, dim).tolist()}
        elif disturbance == "constant":
            a["disturbance"] = {"kind": "constant", "value": rng.uniform(-d0, d0, dim).tolist()}
        agents.append(a)
    law_tbl: dict[str, Any] = {"kind": law, "kp0": float(rng.uniform(1, 3)), "kv0": float(rng.uniform(1, 3)),
                               "gamma_p": float(rng.uniform(0.01, 0.2)), "gamma_v": float(rng.uniform(0.01, 0.2))}
    if law == "sigma":
        law_tbl["sigma"] = float(rng.uniform(0.05, 1.0))
    return build({
        "version": 1, "name": "random", "dim": dim, "rate": rate, "duration": duration,
        "seed": int(rng.integers(1 << 31)), "law": law_tbl,
        "leader": {"id": leader, "p0": [0.0] * dim, "v0": [0.0] * dim,
                   "profile": profile if profile is not None else {"kind": "hold"}},
        "agents": agents,
        "edges": [{"from": s, "to": d, "weight": w} for (s, d), w in edges.items()],
    })


def one_agent(
    *, kp0: float = 1.0, kv0: float = 1.0, gamma: float = 0.05, sigma: float | None = 1.0,
    weight: float = 1.0, d: list[float] | None = None, p0: list[float] | None = None,
    rate: float = 100.0, duration: float = 20.0,
) -> ms.Mission:
    """One agent hearing a leader at rest at the origin, offset [1, 0], optional constant disturbance."""
    agent: dict[str, Any] = {"id": 1, "p0": p0 or [0.0, 0.0], "offset": [1.0, 0.0]}
    if d is not None:
        agent["disturbance"] = {"kind": "constant", "value": d}
    law: dict[str, Any] = {"kind": "sigma" if sigma is not None else "benchmark", "kp0": kp0, "kv0": kv0,
                           "gamma_p": gamma, "gamma_v": gamma}
    if sigma is not None:
        law["sigma"] = sigma
    return build({
        "version": 1, "name": "one", "dim": 2, "rate": rate, "duration": duration, "law": law,
        "leader": {"id": 2, "p0": [0.0, 0.0]}, "agents": [agent],
        "edges": [{"from": 2, "to": 1, "weight": weight}],
    })
