"""What every engine of :mod:`sim` derives from a mission before it runs: the reference simulator's
arrays (:class:`Setup`), the in-process engine's hosts, leader reference and run metadata, and the
types both take. Pure: no engine, no compiler."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np

from agent import laws
from leader import profile
from plant import base as plants
from plant.build import build
from plant.disturbance import DisturbanceBank
from tether import graph
from tether.mission import Mission
from tether.runfile import Run, RunMeta

Mode = Literal["discrete", "continuous"]
Engine = Literal["auto", "numpy", "compiled"]
Progress = Callable[[int, int], None]
OnTick = Callable[[Run, int], None]
"""Called with the run being filled and the index of the sample just recorded (live views)."""


@dataclass(frozen=True)
class Setup:
    """Arrays derived once from a mission."""

    mission: Mission
    topo: graph.Topology
    bound: laws.Bound
    ref: profile.Reference
    dist: DisturbanceBank
    offsets: np.ndarray  # (N+1, d), the leader's row 0
    sum_wdelta: np.ndarray  # (N, d): sum_j a_ij delta_ij
    p0: np.ndarray  # (N, d)
    v0: np.ndarray  # (N, d)

    @classmethod
    def of(cls, m: Mission) -> "Setup":
        topo = graph.topology(m)
        n, d = m.n, m.dim
        offsets = np.zeros((n + 1, d))
        offsets[:n] = [a.offset for a in m.agents]
        sum_wdelta = topo.kappa[:, None] * offsets[:n] - graph.neighbour_sums(topo, offsets)  # O(edges), no N x N
        p0 = np.array([a.p0 for a in m.agents], dtype=float)
        v0 = np.array([a.v0 if a.v0 is not None else [0.0] * d for a in m.agents], dtype=float)
        return cls(m, topo, laws.of_mission(m), profile.build(m.leader, d),
                   DisturbanceBank.from_mission(m), offsets, sum_wdelta, p0, v0)


DIVERGE_AT = 1e6
"""A formation error beyond this [m] counts as divergence and ends the run."""


def check_continuous(m: Mission) -> None:
    """The continuous mode feeds forward the exact accelerations, and runs a law's continuous-time
    form (``rate``, :mod:`agent.laws`): a mission asking otherwise is refused."""
    law = laws.of_mission(m).law
    if getattr(law, "rate", None) is None:
        raise ValueError(f"law {law.name!r} has no continuous-time form (a `rate`, docs/laws.md): run the discrete "
                         "mode")
    if m.law.feedforward != "measured":
        raise ValueError(f"law.feedforward = {m.law.feedforward!r}: the continuous mode feeds forward the exact "
                         "accelerations only; use the discrete mode")


def steps_of(m: Mission, duration: float | None) -> int:
    """The run's last tick: the mission's, or ``duration`` [s] at its rate."""
    return m.steps if duration is None else int(round(duration * m.rate))


def meta_of(m: Mission, steps: int) -> RunMeta:
    """The in-process engine's run metadata (either form of it)."""
    bound = laws.of_mission(m)
    return RunMeta(mission=m.name, source="lockstep-inprocess", law=bound.law.name, rate=m.rate, steps=steps,
                   seed=m.seed, law_state=bound.law.state, law_units=bound.units)


def leader_of(m: Mission, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The leader's reference ``p, v, a`` at every tick time, ``(T, d)`` each (numpy evaluates the
    profile element by element: the same values as the leader process's one call per tick)."""
    p, v, a = (np.broadcast_to(np.asarray(x, dtype=float), (len(times), m.dim))
               for x in profile.build(m.leader, m.dim)(times))
    return p, v, a


def hosts_of(m: Mission) -> list[plants.Plant]:
    """:func:`plant.build.build`'s plants, the double integrators whose disturbance banks take the
    same branches (their models' flags) hosted together: one row per vehicle of one vectorised
    host, each row's arithmetic element-wise that of its own plant process."""
    built = build(m)
    if m.payload is not None:
        return built
    groups: dict[tuple, list[int]] = {}
    out: list[plants.Plant] = []
    for host in built:
        key = _branches(m, host)
        if key is None:
            out.append(host)
        else:
            groups.setdefault(key, []).extend(host.ids)
    return out + [plants.DoubleIntegratorPlant(m, group) for group in groups.values()]


def _branches(m: Mission, host: plants.Plant) -> tuple | None:
    """Which branches of :class:`~plant.disturbance.DisturbanceBank` a one-vehicle double
    integrator's bank takes (None: not such a plant, or a bank whose flags are unknown here)."""
    if type(host) is not plants.DoubleIntegratorPlant:
        return None
    bank = DisturbanceBank.from_mission(m, list(host.ids))
    return bank.flags if bank.layout_known else None
