"""Agent i's side of a formation law: its in-neighbours, weights and offsets, and one tick of the
law on Python floats. No I/O, no state of its own.

The law itself is an :class:`agent.laws.FormationLaw` (Eq. 17 ``sigma``, Eq. 30 ``benchmark``, or
a user's): a per-axis step from the agent's own sample and the weighted sums over its
in-neighbours to a command and the next state. :class:`AgentLaw` takes those sums and runs it.

Neighbour information enters only through weighted sums over the in-neighbours ``j`` of ``i``:
``sum_wp = sum_j a_ij p_j``, ``sum_wv = sum_j a_ij v_j``, ``sum_wa = sum_j a_ij a_j`` (the
neighbours' accelerations, Eq. 17's feed-forward) and the constant ``sum_wdelta = sum_j a_ij delta_ij``.
Every such sum is taken term after term in row order (:func:`weighted_sum`), as
:func:`tether.graph.neighbour_sums` and the compiled kernels take it, never by a BLAS product: a
matrix-vector product rounds with fused multiply-adds and in an order of its own kernel's choosing
(OpenBLAS's, from 4 terms on, differs from the plain sum), which would make an agent with 4 or more
in-neighbours compute a different last bit from the reference simulator, and on another CPU a
different one again.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from agent import laws
from tether.mission import Mission, in_neighbours
from tether.vec import floats, rows


def weighted_term(k: int, acc: float, w: float, x: float) -> float:
    """Term ``k`` of a weighted sum added in row order: ``w x`` for the first, ``acc + w x`` after
    it (each product and sum rounded once, on any platform). Pure, on floats: the in-process
    engine's twin (``sim/lockstep_kernel.py``) compiles this very function."""
    return w * x if k == 0 else acc + w * x


def weighted_sum(w: Sequence[float], xs: Sequence[Sequence[float]]) -> list[float]:
    """``sum_j w_j x_j``, component by component, the terms added one after the other in row order
    (``(w_0 x_0 + w_1 x_1) + w_2 x_2 ...``, :func:`weighted_term`). ``xs`` holds the ``x_j`` (at
    least one)."""
    acc = [0.0] * len(xs[0])
    for k in range(len(w)):
        wk = w[k]
        acc = [weighted_term(k, a, wk, x) for a, x in zip(acc, xs[k])]
    return acc


@dataclass(frozen=True)
class AgentLaw:
    """Everything agent i needs to run the law, derived once from the mission.

    Attributes:
        neighbours: ids of the in-neighbours j (the leader's id included when ``a_i,N+1 > 0``),
            in the order of ``weights``.
        weights: the ``a_ij``, one per in-neighbour.
        kappa: ``sum_j a_ij`` (added in row order, as :func:`tether.graph.topology` adds them).
        sum_wdelta: ``sum_j a_ij delta_ij`` [m], ``d`` floats.
        bound: the mission's law and its parameters.
        coefficients: per axis, the law step's coefficients for the mission's period.
        deltas: the offsets ``delta_ij = h_i - h_j`` [m], ``d`` floats per in-neighbour, rows in
            ``neighbours`` order.
    """

    agent_id: int
    neighbours: tuple[int, ...]
    weights: tuple[float, ...]
    kappa: float
    sum_wdelta: tuple[float, ...]
    bound: laws.Bound
    coefficients: tuple[tuple[float, ...], ...]
    deltas: tuple[tuple[float, ...], ...]

    @classmethod
    def from_mission(cls, m: Mission, agent_id: int, bound: laws.Bound | None = None) -> "AgentLaw":
        offsets = {a.id: tuple(map(float, a.offset)) for a in m.agents}
        offsets[m.leader.id] = (0.0,) * m.dim
        ins = in_neighbours(m, agent_id)
        nbrs = tuple(src for src, _ in ins)
        w = tuple(float(wt) for _, wt in ins)
        h_i = offsets[agent_id]
        kappa = total(w)
        sum_wdelta = tuple(kappa * hc - sc for hc, sc in zip(h_i, weighted_sum(w, [offsets[j] for j in nbrs])))
        deltas = tuple(tuple(hc - jc for hc, jc in zip(h_i, offsets[j])) for j in nbrs)
        bound = laws.of_mission(m) if bound is None else bound
        return cls(agent_id, nbrs, w, kappa, sum_wdelta, bound, bound.coefficients(m.dt), deltas)

    def initial(self) -> list[list[float]]:
        """The law's state at t = 0: per state variable, ``d`` floats."""
        return [list(row) for row in self.bound.initial()]

    def without(self, lost: frozenset[int]) -> "AgentLaw":
        """The law with the edges from the ``lost`` in-neighbours dropped and kappa_i re-normalised
        over the others (their rows stay, with weight 0, so samples keep the same order)."""
        w = tuple(0.0 if j in lost else wt for j, wt in zip(self.neighbours, self.weights))
        return AgentLaw(self.agent_id, self.neighbours, w, total(w), tuple(weighted_sum(w, self.deltas)),
                        self.bound, self.coefficients, self.deltas)

    def step(
        self,
        p: Sequence[float],
        v: Sequence[float],
        nb_p: Sequence[Sequence[float]],
        nb_v: Sequence[Sequence[float]],
        nb_a: Sequence[Sequence[float]],
        *state: Sequence[float],
    ) -> tuple[list[float], ...]:
        """One control tick of agent i, on Python floats (lists; numpy arrays are taken too).

        Args:
            p, v: own position [m] and velocity [m/s], ``d`` floats.
            nb_p, nb_v, nb_a: the neighbours' samples, one row of ``d`` per neighbour, rows in
                ``neighbours`` order.
            state: the law's state at ``t_k``, per state variable ``d`` floats (Eq. 17: ``kp, kv``).
        Returns:
            ``(u, xi, zeta, *state_next)``: the command for this tick, the errors, and the state
            for the next tick (per state variable ``d`` floats).
        """
        w = self.weights
        ka = self.kappa
        step = self.bound.law.step
        xi, zeta, u = [], [], []
        nxt: list[list[float]] = [[] for _ in state]
        per_axis = list(zip(*(floats(x) for x in state))) if state else [()] * len(p)
        for pc, vc, sp, sv, sa, sd, x, c in zip(floats(p), floats(v), weighted_sum(w, rows(nb_p)),
                                                weighted_sum(w, rows(nb_v)), weighted_sum(w, rows(nb_a)),
                                                self.sum_wdelta, per_axis, self.coefficients):
            uc, e, z, xn = step(ka, pc, vc, sp, sv, sa, sd, x, c)
            u.append(uc)
            xi.append(e)
            zeta.append(z)
            for col, val in zip(nxt, xn):
                col.append(val)
        return (u, xi, zeta, *nxt)


def total(w: Sequence[float]) -> float:
    """``sum_j w_j`` added in order from 0 (``np.bincount``'s order; ``ndarray.sum`` adds 8 or more
    terms pairwise)."""
    acc = 0.0
    for x in w:
        acc += x
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
    usable = sample is not None and age <= max_age
    pj, vj, aj = sample if sample is not None and usable else (p, v, a)  # unread when not usable
    axes = [neighbour_axis(pc, vc, dc, qc, wc, ac, usable, age, compensate)
            for pc, vc, dc, qc, wc, ac in zip(p, v, delta, pj, vj, aj)]
    return [x[0] for x in axes], [x[1] for x in axes], [x[2] for x in axes], usable


def neighbour_axis(p: float, v: float, delta: float, pj: float, vj: float, aj: float, usable: bool, age: float,
                   compensate: bool) -> tuple[float, float, float]:
    """One axis of :func:`neighbour_sample`: agent i's own ``p``, ``v`` and offset ``delta`` to j,
    j's sample ``pj, vj, aj`` (read only if ``usable``) and its ``age``. Pure, on floats: the
    in-process engine's twin compiles this very function."""
    if not usable:
        return p - delta, v, 0.0
    if compensate and age > 0.0:
        half = 0.5 * age * age
        return pj + vj * age + half * aj, vj + aj * age, aj
    return pj, vj, aj
