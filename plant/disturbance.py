"""Disturbance models ``d_i(t)`` [m/s^2; world frame] and their exact increments over a step.

Pure numpy. One :class:`DisturbanceBank` holds any mix of models for a set of agents (one row per
agent), so the same code serves one plant process (one row) and the vectorised simulator (N rows).
Each row is the sum of a constant, one sinusoid per axis, and a piecewise-constant random table;
a mission's ``none``/``constant``/``sinusoid``/``bounded_random`` each set one of these parts.

For exact zero-order-hold plants, :meth:`DisturbanceBank.increments` returns, over tick k
(``[t_k, t_k + h]``, ``t_k = k h``)::

    dv = int_{t_k}^{t_k+h} d(s) ds,      dp = int_{t_k}^{t_k+h} (t_k + h - s) d(s) ds

in closed form for every model. Random values change only on tick boundaries (``hold`` is a whole
number of control periods), so their increments are exact too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tether import mission as ms


@dataclass(frozen=True)
class DisturbanceBank:
    """Disturbances of ``n`` agents in ``d`` dimensions, sampled at control period ``h``.

    Attributes:
        h: control period [s].
        const: ``(n, d)`` constant part [m/s^2].
        amp, omega, phase: ``(n, d)`` sinusoid amplitude [m/s^2], frequency [rad/s], phase [rad].
        table: ``(n, M, d)`` random values [m/s^2]; row i uses ``table[i, k // hold_ticks[i]]``.
        hold_ticks: ``(n,)`` ticks per random value (1 where unused).
    """

    h: float
    const: np.ndarray
    amp: np.ndarray
    omega: np.ndarray
    phase: np.ndarray
    table: np.ndarray
    hold_ticks: np.ndarray
    # derived in __post_init__ (not arguments): the sinusoids' increment coefficients and which
    # models are present
    _cv_s: np.ndarray = field(init=False, repr=False, compare=False)
    _cv_c: np.ndarray = field(init=False, repr=False, compare=False)
    _cp_s: np.ndarray = field(init=False, repr=False, compare=False)
    _cp_c: np.ndarray = field(init=False, repr=False, compare=False)
    _has_sine: bool = field(init=False, repr=False, compare=False)
    _has_random: bool = field(init=False, repr=False, compare=False)
    _has_const: bool = field(init=False, repr=False, compare=False)

    @classmethod
    def from_mission(cls, m: ms.Mission, agent_ids: list[int] | None = None) -> "DisturbanceBank":
        """The bank for ``agent_ids`` (all agents by default). Random tables are drawn from
        ``numpy.random.default_rng([mission.seed, agent_id])``: the same per agent whatever the process."""
        ids = m.agent_ids if agent_ids is None else agent_ids
        n, d, h = len(ids), m.dim, m.dt
        const, amp, omega, phase = (np.zeros((n, d)) for _ in range(4))
        hold = np.ones(n, dtype=np.int64)
        randoms: dict[int, np.ndarray] = {}
        for i, aid in enumerate(ids):
            dist = m.agent(aid).disturbance
            if isinstance(dist, ms.Constant):
                const[i] = dist.value
            elif isinstance(dist, ms.Sinusoid):
                amp[i], omega[i] = dist.amplitude, dist.omega
                if dist.phase is not None:
                    phase[i] = dist.phase
            elif isinstance(dist, ms.BoundedRandom):
                hold[i] = int(round(dist.hold / h))
                count = m.steps // hold[i] + 2
                bound = np.array(ms.per_axis(dist.bound, d))
                rng = np.random.default_rng([m.seed, aid])
                randoms[i] = rng.uniform(-1.0, 1.0, size=(count, d)) * bound
        width = max((r.shape[0] for r in randoms.values()), default=1)
        table = np.zeros((n, width, d))
        for i, r in randoms.items():
            table[i, : r.shape[0]] = r
        return cls(h, const, amp, omega, phase, table, hold)

    def __post_init__(self) -> None:
        # Closed-form sinusoid increments over one period, as fixed combinations of
        # s0 = sin(theta0), c0 = cos(theta0), theta0 = omega t_k + phase (y = omega h):
        #   dv = amp (2/omega) sin(theta0 + y/2) sin(y/2) = s0 * cv_s + c0 * cv_c
        #   dp = amp (c0 (y - sin y) + s0 2 sin^2(y/2)) / omega^2 = s0 * cp_s + c0 * cp_c
        # with the omega -> 0 limits (dv = amp h sin(phase), dp = amp h^2/2 sin(phase)).
        h, w = self.h, self.omega
        moving = w != 0.0
        ws = np.where(moving, w, 1.0)
        y = ws * h
        sy2 = np.sin(0.5 * y)
        coeffs = {
            "_cv_s": np.where(moving, 2.0 * np.cos(0.5 * y) * sy2 / ws, h),
            "_cv_c": np.where(moving, 2.0 * sy2 * sy2 / ws, 0.0),
            "_cp_s": np.where(moving, 2.0 * sy2 * sy2 / (ws * ws), 0.5 * h * h),
            "_cp_c": np.where(moving, (y - np.sin(y)) / (ws * ws), 0.0),
        }
        for name, c in coeffs.items():
            object.__setattr__(self, name, self.amp * c)
        object.__setattr__(self, "_has_sine", bool(np.any(self.amp != 0.0)))
        object.__setattr__(self, "_has_random", bool(np.any(self.table != 0.0)))
        object.__setattr__(self, "_has_const", bool(np.any(self.const != 0.0)))

    @property
    def is_zero(self) -> bool:
        """True when every model of the bank is ``none`` (d = 0 for all time)."""
        return not (self._has_sine or self._has_random or self._has_const)

    def _random(self, k: int) -> np.ndarray:
        idx = np.minimum(k // self.hold_ticks, self.table.shape[1] - 1)
        return self.table[np.arange(self.table.shape[0]), idx]

    def value(self, k: int) -> np.ndarray:
        """``d(t_k)``, shape ``(n, d)``."""
        t = k * self.h
        return self.const + self.amp * np.sin(self.omega * t + self.phase) + self._random(k)

    def value_at(self, t: float) -> np.ndarray:
        """``d(t)`` at any time (for the continuous-time simulator), shape ``(n, d)``."""
        k = int(np.floor(t / self.h + 1e-9))
        return self.const + self.amp * np.sin(self.omega * t + self.phase) + self._random(k)

    def increments(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact ``(dv, dp)`` over tick k, each ``(n, d)`` (see the module docstring)."""
        h = self.h
        theta0 = self.omega * (k * h) + self.phase if self._has_sine else None
        if self._has_random or self._has_const:
            held = self.const + self._random(k)
            dv, dp = held * h, held * (0.5 * h * h)
            if theta0 is None:
                return dv, dp
        elif theta0 is None:
            return np.zeros_like(self.const), np.zeros_like(self.const)
        else:
            s0, c0 = np.sin(theta0), np.cos(theta0)
            return s0 * self._cv_s + c0 * self._cv_c, s0 * self._cp_s + c0 * self._cp_c
        s0, c0 = np.sin(theta0), np.cos(theta0)
        return dv + s0 * self._cv_s + c0 * self._cv_c, dp + s0 * self._cp_s + c0 * self._cp_c
