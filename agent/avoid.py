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

import numpy as np

ITERATIONS = 200
"""Hildreth sweeps at most (a handful of constraints converge in a few)."""


def constraints(p: np.ndarray, v: np.ndarray, near: Sequence[tuple[np.ndarray, np.ndarray]], radius: float,
                sensing: float, gain: float, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """The half-planes ``A u <= b`` agent i keeps against each vehicle ``(p_j, v_j)`` within ``sensing``."""
    rows, rhs = [], []
    for pj, vj in near:
        dp, dv = p - pj, v - vj
        dist = math.sqrt(float(dp @ dp))
        if not (dist < sensing) or dist == 0.0:
            continue
        gap = dist - radius
        proj = float(dp @ dv) / dist
        if gap <= 0.0:  # already too close: push apart as hard as the vehicle may brake
            rows.append(-dp / dist)
            rhs.append(-alpha)
            continue
        root = math.sqrt(4.0 * alpha * gap)
        h = root + proj
        b = gain * h ** 3 * dist - proj * proj + float(dv @ dv) + 2.0 * alpha * proj / root
        rows.append(-dp)
        rhs.append(0.5 * b)
    if not rows:
        return np.zeros((0, p.shape[0])), np.zeros(0)
    return np.array(rows), np.array(rhs)


def project(u: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float = 1e-12) -> np.ndarray:
    """``argmin |x - u|`` subject to ``a x <= b`` (Hildreth). ``u`` itself when it is feasible."""
    if a.shape[0] == 0 or np.all(a @ u <= b):
        return u
    lam = np.zeros(a.shape[0])
    norms = np.einsum("ij,ij->i", a, a)
    x = u.copy()
    for _ in range(ITERATIONS):
        moved = 0.0
        for i in range(a.shape[0]):
            if norms[i] == 0.0:
                continue
            new = max(0.0, lam[i] + (float(a[i] @ x) - b[i]) / norms[i])
            step = new - lam[i]
            if step:
                x -= step * a[i]
                lam[i] = new
                moved = max(moved, abs(step))
        if moved <= tol:
            break
    return x


def filter_command(u: np.ndarray, p: np.ndarray, v: np.ndarray, near: Sequence[tuple[np.ndarray, np.ndarray]],
                   radius: float, sensing: float, gain: float, alpha: float) -> np.ndarray:
    """The law's ``u`` made safe against the vehicles ``near`` (``u`` itself when nothing is near)."""
    if not near:
        return u
    a, b = constraints(p, v, near, radius, sensing, gain, alpha)
    return project(u, a, b)
