"""One tick of agent i around the law, pure: no I/O, no Zenoh, no clock.

The agent process (``agent/node.py``) and the in-process engine (``sim/lockstep.py``) both run
:meth:`AgentTick.step`, so they cannot differ in what they do with a sample:

* the feed-forward choice (``[law] feedforward``): what the agent shares as its acceleration
  (:meth:`AgentTick.shared`) and whether the neighbours' accelerations enter Eq. 17 at all;
* the neighbour-sample policy (``[links]``, :func:`agent.law.neighbour_sample`): a sample older
  than ``max_age``, or none, stands for "in formation, not accelerating"; latency compensation;
* the law step (:meth:`agent.law.AgentLaw.step`, the mission's :class:`agent.laws.FormationLaw`)
  with its state at ``t_k``, and its state for the next tick;
* the per-link statistics the tick itself knows: samples used, and the ages of the samples used
  over the last :data:`AGE_WINDOW` ticks (their percentiles are computed only when asked);
* the safety supervisor (:class:`agent.safety.Supervisor`): lost in-neighbours dropped with
  kappa_i re-normalised, the mode, and the command that leaves the agent (saturated; HOLD, LAND,
  LANDED or ESTOP when something is wrong). The law's state advances only while FLYING.

The reference simulator (``sim/refsim.py``) keeps its vectorised form of the same arithmetic and
is tested equal to both.
"""

from __future__ import annotations

from bisect import bisect_left, insort
import math
from collections import deque
from collections.abc import Sequence
from typing import NamedTuple

from agent.avoid import filter_command
from agent.law import AgentLaw, neighbour_sample
from agent.safety import NOMINAL, Status, Supervisor
from tether import failsafe
from tether.mission import LinkPolicy, Mission
from tether.vec import Vec, floats
from tether.wire import HOLD, LAND

AGE_WINDOW = 500
"""Ticks over which each link's age-of-information percentiles are taken (5 s at 100 Hz)."""

Heard = tuple[float, Vec, Vec, Vec]
"""An in-neighbour's newest sample as the tick takes it: ``(t_j [s], p_j [m], v_j [m/s], a_j [m/s^2])``."""


class TickResult(NamedTuple):
    """What one tick computed (a named tuple: made once per tick per agent, it costs a tenth of a
    frozen dataclass).

    Attributes:
        u: the command that leaves the agent at this tick [m/s^2; world frame], ``d`` floats
            (the supervisor's: the law's saturated while FLYING).
        xi, zeta: the errors (Eq. 8, 9), ``d`` floats.
        kp, kv: the law's first two state variables at ``t_k`` (Eq. 17's gains ``K(t_k)``), ``d``
            floats each (zeros for a law with fewer).
        ages: per in-neighbour, the age of its newest sample [s] (NaN: none held).
        used: per in-neighbour, whether its sample was used (else it was substituted).
        mode: the supervisor's mode after this tick (a code of :data:`tether.wire.MODES`).
        x: the law's state at ``t_k``: per state variable (``FormationLaw.state``), ``d`` floats.
    """

    u: list[float]
    xi: list[float]
    zeta: list[float]
    kp: list[float]
    kv: list[float]
    ages: list[float]
    used: list[bool]
    mode: int
    x: list[list[float]]


class AgentTick:
    """Agent i's state between ticks (the law's, previous command, link statistics) and its tick."""

    def __init__(self, law: AgentLaw, policy: LinkPolicy, feedforward: str, dim: int,
                 supervisor: Supervisor, age_window: int = AGE_WINDOW) -> None:
        self.law = law
        self.supervisor = supervisor
        self._laws: dict[frozenset[int], AgentLaw] = {frozenset(): law}
        self.policy = policy
        self.feedforward = feedforward
        self._zero = [0.0] * dim
        self.state: list[list[float]] = law.initial()
        """The law's state at the coming tick: per state variable, ``dim`` floats."""
        self.last_u: list[float] = [0.0] * dim
        """The command of the previous tick: what the agent shares as its acceleration with
        ``feedforward = "commanded"`` (the plant's sample of tick k comes after the command of k-1)."""
        m = len(law.neighbours)
        self.used = [0] * m
        """Per in-neighbour, samples used so far."""
        self.windows: list[deque[float]] = [deque(maxlen=age_window) for _ in range(m)]
        """Per in-neighbour, the ages of the samples used over the last ``age_window`` ticks."""
        self._sorted: list[list[float]] = [[] for _ in range(m)]
        """The same ages, kept sorted (one insertion and one removal per tick: the percentiles are
        then two look-ups, where sorting the window every tick was a third of an agent's CPU)."""
        self._deltas: list[list[float]] = [list(r) for r in law.deltas]

    @classmethod
    def from_mission(cls, m: Mission, agent_id: int) -> "AgentTick":
        law = AgentLaw.from_mission(m, agent_id)
        return cls(law, m.links, m.law.feedforward, m.dim, Supervisor(m, agent_id, law.neighbours))

    def shared(self, measured: Vec) -> Vec:
        """The acceleration this agent shares with its out-neighbours for their feed-forward: its
        measured one (``feedforward = "measured"``), else its previous command (a list)."""
        return measured if self.feedforward == "measured" else self.last_u

    def step(self, k: int, t: float, p: Vec, v: Vec, a_measured: Vec,
             heard: Sequence[Heard | None], status: Status = NOMINAL,
             near: Sequence[tuple[Vec, Vec]] = ()) -> TickResult:
        """Tick ``k`` at time ``t`` [s] with the own sample ``p, v, a_measured`` and, per
        in-neighbour in ``law.neighbours`` order, its newest sample (or None); ``status`` is what
        the process knows of its inputs' liveliness and the operator; ``near``, the positions and
        velocities of other vehicles that collision avoidance (``[safety.avoid]``) may hear,
        kept apart from the law's inputs. Vectors are sequences of floats (lists as they come off the
        wire, or numpy arrays); the results are lists. Advances the gains while FLYING."""
        policy = self.policy
        max_age, compensate = policy.max_age, policy.compensate
        p, v = floats(p), floats(v)
        a = floats(a_measured) if self.feedforward == "measured" else self.last_u
        nb_p: list[list[float]] = []
        nb_v: list[list[float]] = []
        nb_a: list[list[float]] = []
        ages: list[float] = []
        oks: list[bool] = []
        deltas = self._deltas
        used = self.used
        for n, sample in enumerate(heard):
            if sample is None:
                age, got = math.nan, None
            else:
                age = t - sample[0]
                got = sample[1:]
            pj, vj, aj, ok = neighbour_sample(p, v, a, deltas[n], got, age, max_age, compensate)
            nb_p.append(pj)
            nb_v.append(vj)
            nb_a.append(aj)
            if ok:
                used[n] += 1
                self._remember(n, age)
            ages.append(age)
            oks.append(ok)
        if self.feedforward == "none":
            nb_a = [[0.0] * len(p) for _ in nb_a]
        sup = self.supervisor
        lost, reachable, leader_silent = sup.links(k, t, ages, status)
        cached = self._laws.get(lost)
        law = cached if cached is not None else self._laws.setdefault(lost, self.law.without(lost))
        state = self.state
        u_law, xi, zeta, *state_next = law.step(p, v, nb_p, nb_v, nb_a, *state)
        kp, kv = law.bound.shown(state, self._zero)
        u = sup.command(k, t, p, v, u_law, xi, kp, kv, reachable, leader_silent, status)
        av = sup.cfg.avoid
        if av is not None and near and (sup.flying or sup.mode in (HOLD, LAND)):
            filtered = filter_command(u, p, v, near, av.radius, av.sensing, av.gain, av.brake)
            safe = failsafe.saturate(filtered, sup.cfg.max_accel)
            u = u if safe is None else safe
        out = TickResult(u, xi, zeta, kp, kv, ages, oks, sup.mode, state)
        if sup.flying:
            self.state = state_next
        self.last_u = u
        return out

    def _remember(self, n: int, age: float) -> None:
        w, ordered = self.windows[n], self._sorted[n]
        if len(w) == w.maxlen:
            del ordered[bisect_left(ordered, w[0])]
        w.append(age)
        insort(ordered, age)

    def age_percentiles(self, n: int) -> tuple[float, float]:
        """Median and 99th percentile [s] of the ages of in-neighbour ``n``'s samples used over the
        window (NaN before any was used), interpolated as ``numpy.percentile`` does."""
        ordered = self._sorted[n]
        if not ordered:
            return math.nan, math.nan
        return _percentile(ordered, 50.0), _percentile(ordered, 99.0)


def _percentile(ordered: list[float], q: float) -> float:
    """``numpy.percentile(ordered, q)`` (linear method) of a sorted list, with numpy's own lerp."""
    pos = q / 100.0 * (len(ordered) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(ordered) - 1)
    t = pos - lo
    a, b = ordered[lo], ordered[hi]
    diff = b - a
    return b - diff * (1.0 - t) if t >= 0.5 else a + diff * t
