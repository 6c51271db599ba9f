"""The formation law of Su, Bhowmick & Lanzon (2023) as pure functions. No I/O, no state.

Every function works on one agent (vectors of shape ``(d,)``, scalar ``kappa``) and on all agents
at once (arrays ``(N, d)``, ``kappa`` of shape ``(N, 1)``) through broadcasting, so the agent
process and the vectorised reference simulator run the same arithmetic.

Neighbour information enters only through weighted sums over the in-neighbours ``j`` of ``i``:
``sum_wp = sum_j a_ij p_j``, ``sum_wv = sum_j a_ij v_j``, ``sum_wa = sum_j a_ij a_j`` (the
neighbours' accelerations, Eq. 17's feed-forward) and the constant ``sum_wdelta = sum_j a_ij delta_ij``.
Every such sum is taken term after term in row order (:func:`weighted_sum`), as
:func:`tether.graph.neighbour_sums` and the compiled kernels take it, never by a BLAS product: a
matrix-vector product rounds with fused multiply-adds and in an order of its own kernel's choosing
(OpenBLAS's, from 4 terms on, differs from the plain sum), which would make an agent with 4 or more
in-neighbours compute a different last bit from the reference simulator, and on another CPU a
different one again.

Eq. 8, 9:  xi_i   = sum_j a_ij (p_i - p_j - delta_ij) = kappa_i p_i - sum_wp - sum_wdelta
           zeta_i = sum_j a_ij (v_i - v_j)            = kappa_i v_i - sum_wv
Eq. 17:    u_i = (sum_wa - Kp * xi_i - Kv * zeta_i) / kappa_i          (per-axis gains)
           Kp' = -sigma (Kp - 1) + Gamma_p xi^2,   Kv' = -sigma (Kv - 1) + Gamma_v zeta^2
Eq. 30:    the same with sigma = 0 (the benchmark law: no leakage, its gains can only grow).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from tether.mission import Mission, in_neighbours, per_axis
from tether.vec import floats, rows

if TYPE_CHECKING:  # the agent process never loads numpy (13 MiB of its memory); the simulators pass arrays
    import numpy as np


@dataclass(frozen=True)
class LawParams:
    """Parameters of the law, shared by every agent of a mission.

    Attributes:
        sigma: leakage [1/s]; 0 selects the benchmark law (Eq. 30).
        gamma_p, gamma_v: adaptation rates (> 0).
        kp0, kv0: initial per-axis gains, ``d`` floats.
    """

    sigma: float
    gamma_p: float
    gamma_v: float
    kp0: tuple[float, ...]
    kv0: tuple[float, ...]

    @classmethod
    def from_mission(cls, m: Mission) -> "LawParams":
        law = m.law
        sigma = float(law.sigma) if law.kind == "sigma" and law.sigma is not None else 0.0
        return cls(
            sigma=sigma,
            gamma_p=float(law.gamma_p),
            gamma_v=float(law.gamma_v),
            kp0=tuple(map(float, per_axis(law.kp0, m.dim))),
            kv0=tuple(map(float, per_axis(law.kv0, m.dim))),
        )


def weighted_sum(w: Sequence[float], xs: Sequence[Sequence[float]]) -> list[float]:
    """``sum_j w_j x_j``, component by component, the terms added one after the other in row order
    (``(w_0 x_0 + w_1 x_1) + w_2 x_2 ...``): each product and sum rounded once, on any platform.
    ``xs`` holds the ``x_j`` (at least one)."""
    w0 = w[0]
    acc = [w0 * x for x in xs[0]]
    for k in range(1, len(w)):
        wk = w[k]
        acc = [a + wk * x for a, x in zip(acc, xs[k])]
    return acc


def errors(
    kappa: float | np.ndarray,
    p: np.ndarray,
    v: np.ndarray,
    sum_wp: np.ndarray,
    sum_wv: np.ndarray,
    sum_wdelta: np.ndarray | Sequence[float],
) -> tuple[np.ndarray, np.ndarray]:
    """Formation error ``xi`` [m] (Eq. 8) and velocity error ``zeta`` [m/s] (Eq. 9)."""
    xi = kappa * p - sum_wp - sum_wdelta
    zeta = kappa * v - sum_wv
    return xi, zeta


def control(
    kappa: float | np.ndarray,
    sum_wa: np.ndarray,
    xi: np.ndarray,
    zeta: np.ndarray,
    kp: np.ndarray,
    kv: np.ndarray,
) -> np.ndarray:
    """Eq. 17's command ``u`` [m/s^2; world frame] from the errors and the current gains."""
    return (sum_wa - kp * xi - kv * zeta) / kappa


@dataclass(frozen=True)
class GainStep:
    """Coefficients of the exact gain update over one control period ``h``.

    For an error ``e`` held over the period, ``K' = -sigma (K - 1) + Gamma e^2`` is linear in K and
    integrates exactly to ``K+ = 1 + (K - 1) decay + Gamma e^2 gain`` with ``decay = exp(-sigma h)``
    and ``gain = (1 - exp(-sigma h)) / sigma`` (``= h`` when sigma = 0). As ``decay <= 1`` and
    ``gain >= 0``, ``K >= 1`` is preserved in discrete time, as in Theorem 1's proof.
    """

    decay: float
    gain: float

    @classmethod
    def over(cls, sigma: float, h: float) -> "GainStep":
        if sigma == 0.0:
            return cls(1.0, h)
        return cls(math.exp(-sigma * h), -math.expm1(-sigma * h) / sigma)


def gain_update(k: np.ndarray, e: np.ndarray, gamma: float | np.ndarray, step: GainStep) -> np.ndarray:
    """One exact step of the adaptive gain ODE (see :class:`GainStep`); same shapes as ``k``
    (``gamma`` broadcasts, so Kp and Kv stacked on a leading axis advance in one call)."""
    return 1.0 + (k - 1.0) * step.decay + (gamma * step.gain) * (e * e)


def gain_rate(k: np.ndarray, e: np.ndarray, gamma: float, sigma: float) -> np.ndarray:
    """The gain ODE's right-hand side ``-sigma (K - 1) + Gamma e^2`` (for the continuous-time mode)."""
    return -sigma * (k - 1.0) + gamma * (e * e)


@dataclass(frozen=True)
class AgentLaw:
    """Everything agent i needs to run the law, derived once from the mission.

    Attributes:
        neighbours: ids of the in-neighbours j (the leader's id included when ``a_i,N+1 > 0``),
            in the order of ``weights``.
        weights: the ``a_ij``, one per in-neighbour.
        kappa: ``sum_j a_ij`` (added in row order, as :func:`tether.graph.topology` adds them).
        sum_wdelta: ``sum_j a_ij delta_ij`` [m], ``d`` floats.
        deltas: the offsets ``delta_ij = h_i - h_j`` [m], ``d`` floats per in-neighbour, rows in
            ``neighbours`` order.
    """

    agent_id: int
    neighbours: tuple[int, ...]
    weights: tuple[float, ...]
    kappa: float
    sum_wdelta: tuple[float, ...]
    params: LawParams
    gains: GainStep
    deltas: tuple[tuple[float, ...], ...]

    @classmethod
    def from_mission(cls, m: Mission, agent_id: int) -> "AgentLaw":
        offsets = {a.id: tuple(map(float, a.offset)) for a in m.agents}
        offsets[m.leader.id] = (0.0,) * m.dim
        ins = in_neighbours(m, agent_id)
        nbrs = tuple(src for src, _ in ins)
        w = tuple(float(wt) for _, wt in ins)
        h_i = offsets[agent_id]
        kappa = _total(w)
        sum_wdelta = tuple(kappa * hc - sc for hc, sc in zip(h_i, weighted_sum(w, [offsets[j] for j in nbrs])))
        deltas = tuple(tuple(hc - jc for hc, jc in zip(h_i, offsets[j])) for j in nbrs)
        params = LawParams.from_mission(m)
        return cls(agent_id, nbrs, w, kappa, sum_wdelta, params, GainStep.over(params.sigma, m.dt), deltas)

    def without(self, lost: frozenset[int]) -> "AgentLaw":
        """The law with the edges from the ``lost`` in-neighbours dropped and kappa_i re-normalised
        over the others (their rows stay, with weight 0, so samples keep the same order)."""
        w = tuple(0.0 if j in lost else wt for j, wt in zip(self.neighbours, self.weights))
        return AgentLaw(self.agent_id, self.neighbours, w, _total(w), tuple(weighted_sum(w, self.deltas)),
                        self.params, self.gains, self.deltas)

    def step(
        self,
        p: Sequence[float],
        v: Sequence[float],
        nb_p: Sequence[Sequence[float]],
        nb_v: Sequence[Sequence[float]],
        nb_a: Sequence[Sequence[float]],
        kp: Sequence[float],
        kv: Sequence[float],
    ) -> tuple[list[float], list[float], list[float], list[float], list[float]]:
        """One control tick of agent i, on Python floats (lists; numpy arrays are taken too).

        Args:
            p, v: own position [m] and velocity [m/s], ``d`` floats.
            nb_p, nb_v, nb_a: the neighbours' samples, one row of ``d`` per neighbour, rows in
                ``neighbours`` order.
            kp, kv: the gains ``K(t_k)``.
        Returns:
            ``(u, xi, zeta, kp_next, kv_next)``: the command for this tick, the errors, and the
            gains for the next tick.
        """
        # errors(), control() and gain_update() term by term on Python floats: the same IEEE
        # operations in the same order as numpy's elementwise ones (bit for bit, tests/test_law.py),
        # without a numpy temporary per operation on a 2- or 3-vector.
        w = self.weights
        ka = self.kappa
        prm, gs = self.params, self.gains
        decay, gp, gv = gs.decay, prm.gamma_p * gs.gain, prm.gamma_v * gs.gain
        xi, zeta, u, kp_next, kv_next = [], [], [], [], []
        for pc, vc, sp, sv, sa, sd, kpc, kvc in zip(floats(p), floats(v), weighted_sum(w, rows(nb_p)),
                                                    weighted_sum(w, rows(nb_v)), weighted_sum(w, rows(nb_a)),
                                                    self.sum_wdelta, floats(kp), floats(kv)):
            e = ka * pc - sp - sd
            z = ka * vc - sv
            xi.append(e)
            zeta.append(z)
            u.append((sa - kpc * e - kvc * z) / ka)
            kp_next.append(1.0 + (kpc - 1.0) * decay + gp * (e * e))
            kv_next.append(1.0 + (kvc - 1.0) * decay + gv * (z * z))
        return u, xi, zeta, kp_next, kv_next

    def step_numpy(
        self,
        p: np.ndarray,
        v: np.ndarray,
        nb_p: np.ndarray,
        nb_v: np.ndarray,
        nb_a: np.ndarray,
        kp: np.ndarray,
        kv: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`step` written with this module's vectorised functions (the readable form; tested equal)."""
        w = self.weights
        xi, zeta = errors(self.kappa, p, v, _rows_sum(w, nb_p), _rows_sum(w, nb_v), self.sum_wdelta)
        u = control(self.kappa, _rows_sum(w, nb_a), xi, zeta, kp, kv)
        prm = self.params
        return (u, xi, zeta, gain_update(kp, xi, prm.gamma_p, self.gains),
                gain_update(kv, zeta, prm.gamma_v, self.gains))


def _total(w: Sequence[float]) -> float:
    """``sum_j w_j`` added in order from 0 (``np.bincount``'s order; ``ndarray.sum`` adds 8 or more
    terms pairwise)."""
    acc = 0.0
    for x in w:
        acc += x
    return acc


def _rows_sum(w: Sequence[float], x: np.ndarray) -> np.ndarray:
    """:func:`weighted_sum` in numpy: ``w[0] x[0] + w[1] x[1] + ...`` one row at a time."""
    acc = w[0] * x[0]
    for k in range(1, len(w)):
        acc = acc + w[k] * x[k]
    return acc


def neighbour_sample(
    p: Sequence[float], v: Sequence[float], a: Sequence[float], delta: Sequence[float],
    sample: tuple[Sequence[float], Sequence[float], Sequence[float]] | None, age: float, max_age: float,
    compensate: bool,
) -> tuple[list[float], list[float], list[float], bool]:
    """What agent i uses for in-neighbour j at a tick: ``(p_j, v_j, a_j, used)``, lists of floats.

    ``sample`` is j's newest sample ``(p, v, a)`` and ``age`` how old it is [s]. A sample older
    than ``max_age``, or none, is replaced by j "in formation and not accelerating":
    ``p_j = p_i - delta_ij``, ``v_j = v_i``, ``a_j = 0``, so that j adds nothing to xi_i, zeta_i
    or the feed-forward (``used`` is then False); an agent that hears nobody then commands
    ``u = 0`` and coasts. (Substituting ``a_j = a_i``, the agent's own measured acceleration, makes
    an agent that hears nobody integrate its disturbance into its command, ``u_k = u_{k-1} + d``:
    measured to diverge by hundreds of metres within 4 s on Section 4.) With ``compensate``, a usable sample
    is moved forward by its age with its own velocity and acceleration (constant-acceleration
    extrapolation).
    """
    if sample is None or not age <= max_age:
        return [pc - dc for pc, dc in zip(p, delta)], list(v), [0.0] * len(a), False
    pj, vj, aj = sample
    if compensate and age > 0.0:
        half = 0.5 * age * age
        return ([pc + vc * age + half * ac for pc, vc, ac in zip(pj, vj, aj)],
                [vc + ac * age for vc, ac in zip(vj, aj)], list(aj), True)
    return list(pj), list(vj), list(aj), True
