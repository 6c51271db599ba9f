"""Disturbance models ``d_i(t)`` [m/s^2; world frame] and their exact increments over a step.

Pure numpy. One :class:`DisturbanceBank` holds any mix of models for a set of agents (one row per
agent), so the same code serves one plant process (one row) and the vectorised simulator (N rows).
Each row is the sum of a constant, sinusoid layers and piecewise-constant random layers; a
mission's ``none``/``constant``/``sinusoid``/``bounded_random`` each set one of these parts, and a
``sum`` sets several (its constants add into the constant part; its j-th sinusoid is layer j, its
j-th random term random layer j). A bank has as many layers as its agent with the most such
terms; rows with fewer have zero layers, which add exact zeros, so a single model gives the same
numbers, bit for bit, as it did before sums existed.

For exact zero-order-hold plants, :meth:`DisturbanceBank.increments` returns, over tick k
(``[t_k, t_k + h]``, ``t_k = k h``)::

    dv = int_{t_k}^{t_k+h} d(s) ds,      dp = int_{t_k}^{t_k+h} (t_k + h - s) d(s) ds

in closed form for every model. Random values change only on tick boundaries (``hold`` is a whole
number of control periods), so their increments are exact too.

Both depend on the tick alone, so :meth:`DisturbanceBank.value` and
:meth:`DisturbanceBank.increments` compute them for a block of ticks at once (:data:`CACHE_NUMBERS`
numbers a block, at most :data:`CACHE_TICKS` ticks) and hand out read-only rows of it: the same
element-wise operations in the same order as one tick at a time (:meth:`DisturbanceBank.value_of`,
:meth:`DisturbanceBank.increments_of`, kept as the readable form and tested equal bit for bit),
without a dozen numpy calls on a 2- or 3-vector every tick, which were most of a one-vehicle
plant's step.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from tether import mission as ms

CACHE_NUMBERS = 1 << 16
"""Numbers of ``d(t_k)`` a bank computes at once, per block of ticks (``n d`` per tick and layer)."""

CACHE_TICKS = 1024
"""Most ticks of one block (a one-vehicle plant: about 50 KiB for the three series)."""


@dataclass(frozen=True)
class DisturbanceBank:
    """Disturbances of ``n`` agents in ``d`` dimensions, sampled at control period ``h``.

    Attributes:
        h: control period [s].
        const: ``(n, d)`` constant part [m/s^2].
        amp, omega, phase: ``(n, d)`` sinusoid amplitude [m/s^2], frequency [rad/s], phase [rad],
            or ``(L, n, d)`` for L sinusoid layers.
        table: ``(n, M, d)`` random values [m/s^2]; row i uses ``table[i, k // hold_ticks[i]]``;
            or ``(R, n, M, d)`` for R random layers.
        hold_ticks: ``(n,)`` ticks per random value (1 where unused), or ``(R, n)``.
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
    _block: dict = field(init=False, repr=False, compare=False)
    """The block of ticks computed last: ``k0`` and ``d(t_k)``, ``dv``, ``dp`` as ``(ticks, n, d)``."""

    @classmethod
    def from_mission(cls, m: ms.Mission, agent_ids: list[int] | None = None) -> "DisturbanceBank":
        """The bank for ``agent_ids`` (all agents by default). Random tables are drawn from
        ``numpy.random.default_rng([mission.seed, agent_id])``: the same per agent whatever the process."""
        ids = m.agent_ids if agent_ids is None else agent_ids
        n, d, h = len(ids), m.dim, m.dt
        terms = [ms.disturbance_terms(m.agent(aid).disturbance) for aid in ids]
        n_sine = max([1] + [sum(isinstance(t, ms.Sinusoid) for t in ts) for ts in terms])
        n_rand = max([1] + [sum(isinstance(t, ms.BoundedRandom) for t in ts) for ts in terms])
        const = np.zeros((n, d))
        amp, omega, phase = (np.zeros((n_sine, n, d)) for _ in range(3))
        hold = np.ones((n_rand, n), dtype=np.int64)
        randoms: dict[tuple[int, int], np.ndarray] = {}
        for i, (aid, ts) in enumerate(zip(ids, terms)):
            j_sine = j_rand = 0
            for dist in ts:
                if isinstance(dist, ms.Constant):
                    const[i] = const[i] + np.asarray(dist.value, dtype=float)
                elif isinstance(dist, ms.Sinusoid):
                    amp[j_sine, i], omega[j_sine, i] = dist.amplitude, dist.omega
                    if dist.phase is not None:
                        phase[j_sine, i] = dist.phase
                    j_sine += 1
                elif isinstance(dist, ms.BoundedRandom):
                    hold[j_rand, i] = int(round(dist.hold / h))
                    count = m.steps // hold[j_rand, i] + 2
                    bound = np.array(ms.per_axis(dist.bound, d))
                    # the first random term draws exactly as a single bounded_random model does
                    rng = np.random.default_rng([m.seed, aid] if j_rand == 0 else [m.seed, aid, j_rand])
                    randoms[(j_rand, i)] = rng.uniform(-1.0, 1.0, size=(count, d)) * bound
                    j_rand += 1
        width = max((r.shape[0] for r in randoms.values()), default=1)
        table = np.zeros((n_rand, n, width, d))
        for (j, i), r in randoms.items():
            table[j, i, : r.shape[0]] = r
        if n_sine == 1:
            amp, omega, phase = amp[0], omega[0], phase[0]
        if n_rand == 1:
            return cls(h, const, amp, omega, phase, table[0], hold[0])
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
        object.__setattr__(self, "_block", {"k0": 0, "ticks": 0})

    @property
    def flags(self) -> tuple[bool, bool, bool]:
        """Which models the bank holds: ``(sinusoids, random terms, constants)``."""
        return bool(self._has_sine), bool(self._has_random), bool(self._has_const)

    @property
    def layout_known(self) -> bool:
        """Whether this bank's fields are those :meth:`arrays` describes (a bank of a subclass, or of
        a model added since, is not: the compiled engines then use its methods)."""
        return type(self) is DisturbanceBank and frozenset(f.name for f in fields(self)) == _LAYOUT

    def arrays(self) -> tuple[Any, ...]:
        """The bank as the compiled kernels take it (``sim.kernel``): ``const, amp, omega, phase,
        table, hold_ticks`` (int64), the sinusoids' increment coefficients ``cv_s, cv_c, cp_s, cp_c``
        (``dv = sin cv_s + cos cv_c``, ``dp = sin cp_s + cos cp_c``), then :attr:`flags`."""
        return (self.const, self.amp, self.omega, self.phase, self.table, self.hold_ticks.astype(np.int64),
                self._cv_s, self._cv_c, self._cp_s, self._cp_c, *self.flags)

    @property
    def is_zero(self) -> bool:
        """True when every model of the bank is ``none`` (d = 0 for all time)."""
        return not (self._has_sine or self._has_random or self._has_const)

    def _random(self, k: int) -> np.ndarray:
        return self._random_block(np.array([k]))[0]

    def _sine(self, t: float) -> np.ndarray:
        return _layers(self.amp * np.sin(self.omega * t + self.phase), 0)

    def value(self, k: int) -> np.ndarray:
        """``d(t_k)``, shape ``(n, d)`` (read-only: a row of the block holding tick ``k``)."""
        return self._rows(k)[0]

    def value_of(self, k: int) -> np.ndarray:
        """:meth:`value` computed for tick ``k`` alone (the readable form; the same bits)."""
        t = k * self.h
        return self.const + self._sine(t) + self._random(k)

    def value_at(self, t: float) -> np.ndarray:
        """``d(t)`` at any time (for the continuous-time simulator), shape ``(n, d)``."""
        k = int(np.floor(t / self.h + 1e-9))
        return self.const + self._sine(t) + self._random(k)

    def increments(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Exact ``(dv, dp)`` over tick k, each ``(n, d)`` (see the module docstring; read-only rows
        of the block holding tick ``k``)."""
        _, dv, dp = self._rows(k)
        return dv, dp

    def span(self, k0: int, k1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`value` and :meth:`increments` of ticks ``k0 .. k1-1`` at once: new arrays
        ``(k1 - k0, n, d)`` of ``(value, dv, dp)``, each row that tick's (the same bits)."""
        shape = (max(0, k1 - k0), *self.const.shape)
        value, dv, dp = out = (np.empty(shape), np.empty(shape), np.empty(shape))
        k = k0
        while k < k1:
            self._rows(k)  # the block holding tick k
            b = self._block
            r = k - b["k0"]
            m = min(b["ticks"] - r, k1 - k)
            for dst, src in zip(out, (b["value"], b["dv"], b["dp"])):
                dst[k - k0:k - k0 + m] = src[r:r + m]
            k += m
        return value, dv, dp

    def _rows(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        b = self._block
        r = k - b["k0"]
        if not 0 <= r < b["ticks"]:
            self._fill(k)
            r = 0
        return b["value"][r], b["dv"][r], b["dp"][r]

    def _fill(self, k0: int) -> None:
        """Compute the block of ticks from ``k0``: :meth:`value_of` and :meth:`increments_of` with a
        leading axis of ticks, every element's operations those of its own tick."""
        per_tick = max(1, self.amp.size, self.const.size)
        ticks = max(1, min(CACHE_TICKS, CACHE_NUMBERS // per_tick))
        ks = np.arange(k0, k0 + ticks)
        h = self.h
        t = ks * h  # each k * h as Python computes it (exact int to float below 2^53, then one product)
        theta = self.omega * t.reshape((ticks,) + (1,) * self.omega.ndim) + self.phase
        s0 = np.sin(theta)  # for d(t_k) and, with the cosines, the increments
        rnd = self._random_block(ks)
        value = self.const + _layers(self.amp * s0, 1) + rnd
        if self._has_random or self._has_const:
            held = self.const + rnd
            dv, dp = held * h, held * (0.5 * h * h)
            if self._has_sine:
                sv, sp = self._sine_increments(s0, np.cos(theta))
                dv, dp = dv + sv, dp + sp
        elif not self._has_sine:
            dv = dp = np.zeros((ticks, *self.const.shape))
        else:
            dv, dp = self._sine_increments(s0, np.cos(theta))
        for x in (value, dv, dp):
            x.flags.writeable = False
        self._block.update(k0=k0, ticks=ticks, value=value, dv=dv, dp=dp)

    def _random_block(self, ks: np.ndarray) -> np.ndarray:
        """:meth:`_random` of every tick of ``ks``, ``(len(ks), n, d)``."""
        if self.table.ndim == 3:
            idx = np.minimum(ks[:, None] // self.hold_ticks[None, :], self.table.shape[1] - 1)
            return self.table[np.arange(self.table.shape[0])[None, :], idx]
        rows = np.arange(self.table.shape[1])[None, :]
        out = np.zeros((len(ks), *self.const.shape))
        for table, hold in zip(self.table, self.hold_ticks):
            out = out + table[rows, np.minimum(ks[:, None] // hold[None, :], table.shape[1] - 1)]
        return out

    def increments_of(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`increments` computed for tick ``k`` alone (the readable form; the same bits)."""
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
            return self._sine_increments(np.sin(theta0), np.cos(theta0))
        sv, sp = self._sine_increments(np.sin(theta0), np.cos(theta0))
        return dv + sv, dp + sp

    def _sine_increments(self, s0: np.ndarray, c0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The sinusoids' ``(dv, dp)`` from the sines and cosines of their angles at the start of the
        tick: ``(n, d)`` or ``(L, n, d)`` for one tick; with a leading axis of ticks for a block."""
        dv, dp = s0 * self._cv_s + c0 * self._cv_c, s0 * self._cp_s + c0 * self._cp_c
        lead = s0.ndim - self._cv_s.ndim
        return _layers(dv, lead), _layers(dp, lead)


_LAYOUT = frozenset({"h", "const", "amp", "omega", "phase", "table", "hold_ticks", "_cv_s", "_cv_c", "_cp_s", "_cp_c",
                     "_has_sine", "_has_random", "_has_const", "_block"})
"""The fields :meth:`DisturbanceBank.arrays` describes."""


def _layers(x: np.ndarray, lead: int) -> np.ndarray:
    """The sum of sinusoid layers, added in order (``x[0] + x[1] + ...`` along the layer axis), of
    ``x`` shaped ``(*lead, n, d)`` (one layer: ``x`` itself) or ``(*lead, L, n, d)``, ``lead`` the
    number of leading axes (1 for a block of ticks)."""
    if x.ndim - lead == 2:
        return x
    out = x[(slice(None),) * lead + (0,)]
    for j in range(1, x.shape[lead]):
        out = out + x[(slice(None),) * lead + (j,)]
    return out
