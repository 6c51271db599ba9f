"""Collision avoidance after the law: a decentralised control-barrier-function filter. Pure.

The paper leaves collision avoidance to future work. This is the double-integrator safety barrier
of Wang, Ames and Egerstedt (IEEE T-RO 2017, "Safety barrier certificates for collisions-free
multirobot systems"), each agent taking half of every pairwise constraint, so no agent needs
another's command. For vehicles i and j at ``dp = p_i - p_j``, ``dv = v_i - v_j``, with a braking
capacity ``alpha`` each and a safety distance ``Ds``::

    h_ij = sqrt(4 alpha (|dp| - Ds)) + dp . dv / |dp|         (>= 0: they can still stop apart)
    agent i keeps  -dp . u_i <= b_ij / 2,
    b_ij = gamma h^3 |dp| - (dv . dp)^2 / |dp|^2 + |dv|^2 + 2 alpha (dv . dp) / sqrt(4 alpha (|dp| - Ds))

and the command that leaves the filter is the one closest to the law's ``u`` (Euclidean) that
keeps every constraint of the vehicles within ``sensing`` (a small QP, solved exactly by Hildreth's
dual coordinate ascent; with no vehicle near, the law's ``u`` is returned untouched, the same
object). A pair already closer than ``Ds`` is pushed apart at the braking capacity.

What the filter may hear is kept apart from the law's inputs: the positions and velocities of the
vehicles within ``sensing``, as an on-board range sensor or a local broadcast would give them.
These can be more vehicles than the formation neighbours (the agent process subscribes to every
agent's state key for it, ``agent/node.py``), and they never enter ξ, ζ or the gains.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from tether.vec import Vec, dot, floats, norm

ITERATIONS = 200
"""Hildreth sweeps at most (a handful of constraints converge in a few)."""


def constraints(p: Vec, v: Vec, near: Sequence[tuple[Vec, Vec]], radius: float,
                sensing: float, gain: float, alpha: float) -> tuple[list[list[float]], list[float]]:
    """The half-planes ``A u <= b`` agent i keeps against each vehicle ``(p_j, v_j)`` within
    ``sensing``: the rows of ``A`` and ``b`` (lists; empty when nobody is within ``sensing``)."""
    p, v = floats(p), floats(v)
    rows: list[list[float]] = []
    rhs: list[float] = []
    for pj, vj in near:
        dp = [a - b for a, b in zip(p, floats(pj))]
        dv = [a - b for a, b in zip(v, floats(vj))]
        dist = norm(dp)
        if not (dist < sensing) or dist == 0.0:
            continue
        gap = dist - radius
        proj = dot(dp, dv) / dist
        if gap <= 0.0:  # already too close: push apart as hard as the vehicle may brake
            rows.append([-c / dist for c in dp])
            rhs.append(-alpha)
            continue
        root = math.sqrt(4.0 * alpha * gap)
        h = root + proj
        b = gain * h ** 3 * dist - proj * proj + dot(dv, dv) + 2.0 * alpha * proj / root
        rows.append([-c for c in dp])
        rhs.append(0.5 * b)
    return rows, rhs


def project(u: Vec, a: Sequence[Vec], b: Sequence[float], tol: float = 1e-12) -> Vec:
    """``argmin |x - u|`` subject to ``a x <= b`` (Hildreth), a new list; ``u`` itself when it is feasible."""
    if not a or all(dot(row, u) <= bi for row, bi in zip(a, b)):
        return u
    lam = [0.0] * len(a)
    norms = [dot(row, row) for row in a]
    x = list(floats(u))
    for _ in range(ITERATIONS):
        moved = 0.0
        for i, row in enumerate(a):
            if norms[i] == 0.0:
                continue
            new = max(0.0, lam[i] + (dot(row, x) - b[i]) / norms[i])
            step = new - lam[i]
            if step:
                x = [xc - step * ac for xc, ac in zip(x, row)]
                lam[i] = new
                moved = max(moved, abs(step))
        if moved <= tol:
            break
    return x


def filter_command(u: Vec, p: Vec, v: Vec, near: Sequence[tuple[Vec, Vec]],
                   radius: float, sensing: float, gain: float, alpha: float) -> Vec:
    """The law's ``u`` made safe against the vehicles ``near`` (``u`` itself when nothing is near,
    else a new list)."""
    if not near:
        return u
    a, b = constraints(p, v, near, radius, sensing, gain, alpha)
    return project(u, a, b)
