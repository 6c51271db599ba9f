"""Reference profiles of the virtual leader (Eq. 6): ``t -> (p, v, a)``. Pure, no I/O.

Every profile is evaluated in closed form, so the leader process and the reference simulator read
the same numbers at the same sample times. ``t`` may be a float or an array of shape ``(T,)``;
results have shape ``(d,)`` or ``(T, d)`` (possibly a view of a ``(d, T)`` array: read, never
written): position [m], velocity [m/s], acceleration [m/s^2], all in the world frame.

:func:`scalar` evaluates the same closed forms at one time on Python floats, for a process that
loads no numpy (an agent checks the leader's samples against the profile, :mod:`tether.gate`); it
agrees with :func:`build`'s to rounding (``tests/test_gate.py``). numpy is imported where an array
is made, so that importing this module for :func:`scalar` does not load it.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from tether import mission as ms

if TYPE_CHECKING:  # an agent imports this module for :func:`scalar` and never loads numpy
    import numpy as np

Sample = tuple["np.ndarray", "np.ndarray", "np.ndarray"]


class Reference(Protocol):
    def __call__(self, t: float | np.ndarray) -> Sample:
        """Position, velocity and acceleration at time(s) ``t`` [s]."""
        ...


@dataclass(frozen=True)
class ExpAccel:
    """``a = a0 exp(-decay t)`` (Section 4 uses a0 = [1, 0], decay = 0.1 1/s)."""

    p0: np.ndarray
    v0: np.ndarray
    a0: np.ndarray
    decay: float

    def __call__(self, t: float | np.ndarray) -> Sample:
        import numpy as np
        # computed axis by axis, (d, T), and returned as (T, d) views of those: numpy's loops over a
        # (T, d) result run d elements at a time, five times slower at d = 3 (the continuous mode
        # evaluates 30 stage times per control step). The same operations on the same numbers: the
        # same bits, one time or many (tests/test_models.py).
        tt = np.atleast_1d(np.asarray(t, dtype=float))
        if self.decay == 0.0:
            e, i1, i2 = np.ones_like(tt), tt, 0.5 * tt * tt  # e, int_0^t e, int_0^t int_0^s e
        else:
            lam = self.decay
            e = np.exp(-lam * tt)
            i1 = -np.expm1(-lam * tt) / lam
            i2 = (tt - i1) / lam
        p0, v0, a0 = self.p0[:, None], self.v0[:, None], self.a0[:, None]
        return _squeeze(t, (p0 + v0 * tt + a0 * i2).T, (v0 + a0 * i1).T, (a0 * e).T)


@dataclass(frozen=True)
class PiecewiseLinearVelocity:
    """Velocity linear between knots ``(tau_m, v_m)``, constant after the last knot.

    Equal consecutive knot times encode a step; the velocity is left-continuous there (Eq. 31's
    ``0 <= t <= 5 s`` includes t = 5 in the first piece) and the impulse in acceleration is not
    represented (reported as 0).
    """

    p0: np.ndarray
    tau: np.ndarray  # (M,)
    vel: np.ndarray  # (M, d)
    _slope: np.ndarray = field(init=False, repr=False, compare=False)
    """Per-knot acceleration [m/s^2], set once in __post_init__."""
    _pk: np.ndarray = field(init=False, repr=False, compare=False)
    """Position at each knot [m], set once in __post_init__."""

    @classmethod
    def from_schedule(cls, p0: np.ndarray, segs: list[tuple[float, np.ndarray]], ramp: float) -> "PiecewiseLinearVelocity":
        import numpy as np
        tau, vel = [0.0], [segs[0][1]]
        for t, v in segs[1:]:
            tau += [t, t + ramp]
            vel += [vel[-1], v]
        return cls(p0, np.array(tau), np.array(vel, dtype=float))

    def __post_init__(self) -> None:
        import numpy as np
        # per-knot slopes and positions, once (O(M)); a sample is then a bisection, O(log M)
        tau, vel = self.tau, self.vel
        dtau = np.diff(tau)
        slope = np.zeros((len(tau), vel.shape[1]))
        nz = dtau > 0
        slope[:-1][nz] = (vel[1:][nz] - vel[:-1][nz]) / dtau[nz][:, None]
        # position at each knot: trapezoids (exact for piecewise-linear velocity)
        pk = self.p0 + np.concatenate([np.zeros((1, vel.shape[1])),
                                       np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dtau[:, None], axis=0)])
        object.__setattr__(self, "_slope", slope)
        object.__setattr__(self, "_pk", pk)

    def __call__(self, t: float | np.ndarray) -> Sample:
        import numpy as np
        tau, vel, slope, pk = self.tau, self.vel, self._slope, self._pk
        tt = np.asarray(t, dtype=float)
        m = np.clip(np.searchsorted(tau, tt, side="left") - 1, 0, len(tau) - 1)
        s = (tt - tau[m])[..., None]
        v = vel[m] + slope[m] * s
        p = pk[m] + vel[m] * s + 0.5 * slope[m] * s * s
        a = slope[m] + 0.0 * s
        return _squeeze(t, p, v, a)


@dataclass(frozen=True)
class Waypoints:
    """Minimum-jerk quintic segments between timed waypoints (zero velocity and acceleration at
    each waypoint); holds the last waypoint afterwards."""

    tau: np.ndarray  # (M,)
    pts: np.ndarray  # (M, d)

    def __call__(self, t: float | np.ndarray) -> Sample:
        import numpy as np
        tt = np.asarray(t, dtype=float)
        last = len(self.tau) - 1
        m = np.clip(np.searchsorted(self.tau, tt, side="right") - 1, 0, last - 1)
        span = self.tau[m + 1] - self.tau[m]
        x = np.clip((tt - self.tau[m]) / span, 0.0, 1.0)[..., None]
        span = np.asarray(span)[..., None]
        dp = self.pts[m + 1] - self.pts[m]
        s = x**3 * (10.0 - 15.0 * x + 6.0 * x * x)
        ds = 30.0 * x * x * (1.0 - x) ** 2
        dds = 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x)
        p = self.pts[m] + dp * s
        v = dp * ds / span
        a = dp * dds / (span * span)
        return _squeeze(t, p, v, a)


BLOCK = 1024
"""Ticks of the reference the leader process evaluates at once (:func:`at_ticks`)."""


def at_ticks(ref: Reference, h: float, k0: int, k1: int, dim: int) -> tuple[list[list[float]], ...]:
    """``ref`` at ``t_k = k h`` for ``k = k0 .. k1-1``: position, velocity and acceleration, each a
    list of ``d`` floats per tick. The profile is evaluated on the array of those times, element by
    element, as the reference simulator and the in-process engine evaluate it: each tick's numbers
    are those of ``ref(k h)`` alone (tests/test_models.py), for one numpy call a block of ticks instead
    of a dozen a tick."""
    import numpy as np
    t = np.arange(k0, k1) * h  # each k h as Python computes it
    return tuple(np.broadcast_to(np.asarray(x, dtype=float), (k1 - k0, dim)).tolist() for x in ref(t))


def _squeeze(t: float | np.ndarray, p: np.ndarray, v: np.ndarray, a: np.ndarray) -> Sample:
    import numpy as np
    if np.ndim(t) == 0:
        return p.reshape(-1), v.reshape(-1), a.reshape(-1)
    return p, v, a


def build(leader: ms.Leader, dim: int) -> Reference:
    """The :class:`Reference` a mission's leader follows."""
    import numpy as np
    p0 = np.array(leader.p0, dtype=float)
    v0 = np.array(leader.v0 if leader.v0 is not None else [0.0] * dim, dtype=float)
    prof = leader.profile
    if isinstance(prof, ms.ExpAccel):
        return ExpAccel(p0, v0, np.array(prof.a0, dtype=float), float(prof.decay))
    if isinstance(prof, ms.VelocitySchedule):
        segs = [(s.t, np.array(s.v, dtype=float)) for s in prof.segments]
        return PiecewiseLinearVelocity.from_schedule(p0, segs, prof.ramp)
    if isinstance(prof, ms.Waypoints):
        return Waypoints(np.array([w.t for w in prof.points]), np.array([w.p for w in prof.points], dtype=float))
    if isinstance(prof, ms.Hold):
        return ExpAccel(p0, v0, np.zeros(dim), 0.0)
    raise TypeError(f"unknown leader profile {type(prof).__name__}")


Floats = tuple[list[float], list[float], list[float]]
"""Position [m], velocity [m/s] and acceleration [m/s^2] at one time, ``d`` floats each."""


def scalar(leader: ms.Leader, dim: int) -> Callable[[float], Floats]:
    """The reference :func:`build` makes, at one time ``t`` [s], on Python floats (no numpy): the
    same closed forms, term for term, so that it agrees with the arrays to rounding."""
    p0 = [float(x) for x in leader.p0]
    v0 = [float(x) for x in leader.v0] if leader.v0 is not None else [0.0] * dim
    prof = leader.profile
    if isinstance(prof, (ms.ExpAccel, ms.Hold)):
        a0 = [float(x) for x in prof.a0] if isinstance(prof, ms.ExpAccel) else [0.0] * dim
        lam = float(prof.decay) if isinstance(prof, ms.ExpAccel) else 0.0

        def exp_accel(t: float) -> Floats:
            if lam == 0.0:
                e, i1, i2 = 1.0, t, 0.5 * t * t
            else:
                e = math.exp(-lam * t)
                i1 = -math.expm1(-lam * t) / lam
                i2 = (t - i1) / lam
            return ([p + v * t + a * i2 for p, v, a in zip(p0, v0, a0)], [v + a * i1 for v, a in zip(v0, a0)],
                    [a * e for a in a0])

        return exp_accel
    if isinstance(prof, ms.VelocitySchedule):
        tau, vel = [0.0], [[float(x) for x in prof.segments[0].v]]
        for s in prof.segments[1:]:
            tau += [s.t, s.t + prof.ramp]
            vel += [vel[-1], [float(x) for x in s.v]]
        slope = [[0.0] * dim for _ in tau]
        pk = [p0]
        for m in range(len(tau) - 1):
            dt = tau[m + 1] - tau[m]
            if dt > 0:
                slope[m] = [(b - a) / dt for a, b in zip(vel[m], vel[m + 1])]
            pk.append([p + 0.5 * (a + b) * dt for p, a, b in zip(pk[m], vel[m], vel[m + 1])])

        def schedule(t: float) -> Floats:
            m = min(max(bisect_left(tau, t) - 1, 0), len(tau) - 1)
            s = t - tau[m]
            return ([p + v * s + 0.5 * g * s * s for p, v, g in zip(pk[m], vel[m], slope[m])],
                    [v + g * s for v, g in zip(vel[m], slope[m])], list(slope[m]))

        return schedule
    if isinstance(prof, ms.Waypoints):
        wt = [float(w.t) for w in prof.points]
        pts = [[float(x) for x in w.p] for w in prof.points]
        last = len(wt) - 1

        def waypoints(t: float) -> Floats:
            m = min(max(bisect_right(wt, t) - 1, 0), last - 1)
            span = wt[m + 1] - wt[m]
            x = min(max((t - wt[m]) / span, 0.0), 1.0)
            s = x ** 3 * (10.0 - 15.0 * x + 6.0 * x * x)
            ds = 30.0 * x * x * (1.0 - x) ** 2
            dds = 60.0 * x * (1.0 - x) * (1.0 - 2.0 * x)
            dp = [b - a for a, b in zip(pts[m], pts[m + 1])]
            return ([a + d * s for a, d in zip(pts[m], dp)], [d * ds / span for d in dp],
                    [d * dds / (span * span) for d in dp])

        return waypoints
    raise TypeError(f"unknown leader profile {type(prof).__name__}")
