"""The double integrator ``p' = v, v' = u + d`` (Eq. 5), discretised exactly. Pure.

Works on one vehicle (``(d,)``), many (``(N, d)``), or one axis of one vehicle in plain floats
(:class:`plant.onboard.Onboard`): the same operations in the same order, so the same bits. Over
one control period ``h`` the command ``u`` is held (zero-order hold) and the disturbance enters
through its exact increments (:meth:`plant.disturbance.DisturbanceBank.increments`)::

    p+ = p + h v + (h^2 / 2) u + dp,     v+ = v + h u + dv,     a+ = u + dv / h

``a+`` is the mean acceleration over the period, what an accelerometer averaged over the period
reads: it is the "measured acceleration" every vehicle shares with its neighbours.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

X = TypeVar("X", float, np.ndarray)


def step(p: X, v: X, u: X, dv: X, dp: X, h: float) -> tuple[X, X, X]:
    """Advance one period; returns ``(p+ [m], v+ [m/s], a+ [m/s^2])``."""
    p_next = p + h * v + (0.5 * h * h) * u + dp
    v_next = v + h * u + dv
    a_next = u + dv / h
    return p_next, v_next, a_next
