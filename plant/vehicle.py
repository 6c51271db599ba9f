"""The vehicle interface of the payload world, and its simplest implementation, a point mass.

Pure numpy. Frames and units: world frame, z up; position [m], velocity [m/s], acceleration
[m/s^2], force [N], mass [kg]; gravity ``-G e_z`` with ``G = 9.81 m/s^2``.

A :class:`Vehicle` is what :class:`plant.payload.PayloadWorld` hosts: a body whose centre of mass
the world reads (``p``, ``v``) and pushes on (the cable force ``f_ext``, held over each call of
:meth:`Vehicle.advance`), and which flies the formation law's command ``u``, the *desired
acceleration* of Eq. 5 [m/s^2]. The vehicle's own inner loop compensates its own weight, so
``u = 0`` is hover; whatever else pulls on it (the payload) is the paper's disturbance ``d_i``.

:class:`PointMass` is the ideal closed inner loop of the paper's Remark 1. Without options its
translational dynamics are Eq. 5 with ``d = f_ext / m`` exactly::

    thrust = m (u + G e_z),      m p'' = thrust - m G e_z + f_ext   =>   p'' = u + f_ext / m

Two optional inner-loop additions for a vehicle that carries a payload (both off by default):

``feedforward_mass`` ``m_ff`` [kg]
    the vehicle's share of the payload mass, added to the mass the inner loop believes it flies.
    Thrust is Eq. 4 with ``m`` replaced by ``m + m_ff``, i.e. the thrust *vector* is::

        thrust = (m + m_ff) (u + G e_z)   =>   p'' = u + (m_ff / m) (u + G e_z) + f_ext / m

    In hover (``u = 0``) this lifts an extra weight ``m_ff G``; a share ``m_ff`` that moves
    rigidly with the vehicle (``f_ext = -m_ff (p'' + G e_z)``) then gives back ``p'' = u``
    exactly, on every axis. It scales the effective gain of ``u`` by ``(m + m_ff) / m`` whenever
    the payload does not follow.

``integrator`` (:class:`Integrator`: gain ``k_i`` [1/s], limit ``I_max`` [m/s^2])
    an integral of the vertical acceleration tracking error, added to the vertical command::

        thrust = (m + m_ff) (u + (G + I) e_z),     I' = k_i (u_z - p''_z),     |I| <= I_max

    ``k_i * integral(u_z - p''_z)`` is ``k_i`` times the vertical velocity error against the
    velocity the commands ask for, so this is the thrust integral of the Crazyflie's own velocity
    PID on z (``pidVZ`` in crazyflie-firmware's ``position_controller_pid.c``: its integral term
    on the z-velocity error, added to the base thrust, clamped by the PID's integral limit). With
    a constant pull the loop is first order: ``I -> I*`` with rate ``k_i (m + m_ff) / m``, after
    which ``p''_z = u_z`` (no steady sag). Anti-windup is clamping: ``I`` stays in
    ``[-I_max, I_max]``.

:meth:`PointMass.advance` is exact for a held ``u`` and ``f_ext`` (zero-order hold), the
integrator included: between clamps ``I`` is a decaying exponential, integrated in closed form
(the clamp time is solved for exactly). The point mass has no thrust limit and no attitude: it is
the model the formation law is designed for, with the payload as the only departure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

G = 9.81
"""Gravitational acceleration [m/s^2], along ``-e_z`` of the world frame."""


@runtime_checkable
class Vehicle(Protocol):
    """A body whose centre of mass the payload world reads and pushes on.

    Attributes:
        mass: vehicle mass [kg] (the cable's attach point is the centre of mass).
        p: centre-of-mass position, shape ``(3,)`` [m; world frame, z up].
        v: centre-of-mass velocity, shape ``(3,)`` [m/s; world frame].
    """

    @property
    def mass(self) -> float: ...

    @property
    def p(self) -> np.ndarray: ...

    @property
    def v(self) -> np.ndarray: ...

    def command(self, u: np.ndarray, yaw: float = 0.0) -> None:
        """Set the desired acceleration ``u`` ``(3,)`` [m/s^2; world frame] and yaw [rad], held until
        the next call. ``u = 0`` is hover: the vehicle's inner loop compensates its own weight.
        Returns immediately."""
        ...

    def advance(self, dt: float, f_ext: np.ndarray | None = None) -> None:
        """Integrate ``dt`` [s] with the external force ``f_ext`` ``(3,)`` [N; world frame] held
        (``None``: no external force)."""
        ...

    def accel(self) -> np.ndarray:
        """Mean acceleration of the centre of mass over the last :meth:`advance` span, ``(3,)``
        [m/s^2; world frame] (zeros before the first call)."""
        ...


@dataclass(frozen=True)
class Integrator:
    """The inner loop's integral action on the vertical acceleration tracking error.

    Attributes:
        gain: ``k_i`` [1/s]; the integral ``I`` [m/s^2] obeys ``I' = k_i (u_z - p''_z)``.
        limit: anti-windup clamp ``I_max`` [m/s^2]; ``I`` stays in ``[-I_max, I_max]``.
    """

    gain: float
    limit: float
    axes: str = "z"
    """``"z"`` (the vertical axis only, the default) or ``"xyz"`` (every axis, each with its own
    integral, as the Crazyflie's velocity PIDs on x, y and z have)."""

    def __post_init__(self) -> None:
        if self.axes not in ("z", "xyz"):
            raise ValueError(f"integrator axes must be 'z' or 'xyz', not {self.axes!r}")
        if not (math.isfinite(self.gain) and self.gain > 0.0):
            raise ValueError(f"integrator gain must be finite and > 0 [1/s], not {self.gain!r}")
        if not (math.isfinite(self.limit) and self.limit > 0.0):
            raise ValueError(f"integrator limit must be finite and > 0 [m/s^2], not {self.limit!r}")


def _vec3(x: np.ndarray | list[float] | tuple[float, ...], name: str) -> np.ndarray:
    a = np.array(x, dtype=float).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be 3 finite numbers, not {x!r}")
    return a


class PointMass:
    """A point-mass vehicle with an ideal inner loop (see the module docstring for the equations).

    Args:
        mass: ``m`` [kg], > 0.
        p0, v0: initial position [m] and velocity [m/s], ``(3,)``, world frame.
        feedforward_mass: ``m_ff`` [kg] >= 0, the payload share the thrust carries (0: off).
        integrator: the vertical integral action, or ``None`` (off).
        g: gravity [m/s^2].

    Attributes:
        mass: ``m`` [kg].
        p, v: centre of mass position [m] and velocity [m/s], ``(3,)``, world frame.
        integral: the integrator's state ``I`` [m/s^2] (0 when off).
    """

    def __init__(
        self,
        mass: float,
        p0: np.ndarray | list[float],
        v0: np.ndarray | list[float] | None = None,
        feedforward_mass: float = 0.0,
        integrator: Integrator | None = None,
        *,
        g: float = G,
    ) -> None:
        if not (math.isfinite(mass) and mass > 0.0):
            raise ValueError(f"mass must be finite and > 0 [kg], not {mass!r}")
        if not (math.isfinite(feedforward_mass) and feedforward_mass >= 0.0):
            raise ValueError(f"feedforward_mass must be finite and >= 0 [kg], not {feedforward_mass!r}")
        self.mass = float(mass)
        self.feedforward_mass = float(feedforward_mass)
        self.integrator = integrator
        self.g = float(g)
        self.p = _vec3(p0, "p0")
        self.v = np.zeros(3) if v0 is None else _vec3(v0, "v0")
        self._integral = np.zeros(3)
        self._axes = () if integrator is None else ((2,) if integrator.axes == "z" else (0, 1, 2))
        self._u = np.zeros(3)
        self._yaw = 0.0
        self._a = np.zeros(3)
        self._ff = self.feedforward_mass / self.mass  # m_ff / m
        self._gz = np.array([0.0, 0.0, self.g])

    @property
    def u(self) -> np.ndarray:
        """The held command [m/s^2; world frame] (a copy)."""
        return self._u.copy()

    @property
    def yaw(self) -> float:
        """The held yaw command [rad] (a point mass has no attitude: recorded only)."""
        return self._yaw

    def command(self, u: np.ndarray, yaw: float = 0.0) -> None:
        """Hold the desired acceleration ``u`` ``(3,)`` [m/s^2] and yaw [rad]. Returns immediately."""
        self._u = _vec3(u, "u")
        self._yaw = float(yaw)

    def accel(self) -> np.ndarray:
        """Mean acceleration over the last :meth:`advance` span [m/s^2; world frame] (a copy)."""
        return self._a.copy()

    def ground_contact(self, z: float) -> None:
        """The ground at height ``z`` [m] stops downward motion: the height is at least ``z`` and a
        downward velocity is zeroed; the vehicle climbs again as soon as it is commanded up."""
        if self.p[2] < z:
            self.p = self.p.copy()
            self.p[2] = z
        if self.v[2] < 0.0:
            self.v = self.v.copy()
            self.v[2] = 0.0

    def advance(self, dt: float, f_ext: np.ndarray | None = None) -> None:
        """Integrate exactly over ``dt`` [s] with ``u`` and ``f_ext`` [N; world frame] held."""
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0 [s], not {dt!r}")
        u = self._u
        # acceleration without the integral: u + (m_ff/m)(u + g e_z) + f/m, written so that the
        # plain point mass is u + f/m to the last bit
        a = u if f_ext is None else u + f_ext / self.mass
        if self._ff:
            a = a + self._ff * (u + self._gz)
        if self.integrator is None:
            self.p = self.p + dt * self.v + (0.5 * dt * dt) * a
            self.v = self.v + dt * a
            self._a = a
            return
        v0 = self.v
        r = 1.0 + self._ff
        self.p = self.p + dt * v0 + (0.5 * dt * dt) * a
        self.v = v0 + dt * a
        for ax in self._axes:  # each integral enters its axis as r * I
            dv_i, dp_i, self._integral[ax] = _integral_flow(
                self._integral[ax], (u[ax] - a[ax]) / r, self.integrator.gain * r, self.integrator.limit, dt)
            self.p[ax] += r * dp_i
            self.v[ax] += r * dv_i
        self._a = (self.v - v0) / dt

    @property
    def integral(self) -> float | np.ndarray:
        """The integrator's state ``I`` [m/s^2]: the vertical one (a number) for ``axes = "z"``,
        all three otherwise (0 when off)."""
        return float(self._integral[2]) if self._axes == (2,) else self._integral.copy()


def _segment(i0: float, target: float, rate: float, t: float) -> tuple[float, float, float]:
    """``I' = -rate (I - target)`` from ``I(0) = i0`` over ``[0, t]``: returns
    ``(I(t), int_0^t I, int_0^t (t - s) I(s) ds)``."""
    x = rate * t
    e = math.exp(-x)
    one_minus_e = -math.expm1(-x)  # 1 - e^{-x}
    gap = i0 - target
    i_t = target + gap * e
    int1 = target * t + gap * one_minus_e / rate
    # int_0^t (t - s) e^{-rate s} ds = (x - (1 - e^{-x})) / rate^2; series for small x (cancellation)
    if x < 1e-3:
        k2 = t * t * (0.5 - x / 6.0 + x * x / 24.0 - x * x * x / 120.0)
    else:
        k2 = (x - one_minus_e) / (rate * rate)
    int2 = target * 0.5 * t * t + gap * k2
    return i_t, int1, int2


def _integral_flow(i0: float, target: float, rate: float, limit: float, t: float) -> tuple[float, float, float]:
    """The clamped integrator over ``[0, t]``: ``I`` relaxes to ``target`` at ``rate`` [1/s] and is
    held at ``+-limit`` from the instant it reaches it. Returns
    ``(int_0^t I, int_0^t (t - s) I(s) ds, I(t))``. ``I`` is monotone on the way, so the clamp is hit
    at most once, at a time solved in closed form."""
    i0 = min(max(i0, -limit), limit)
    bound = limit if target > limit else (-limit if target < -limit else None)
    if bound is not None and i0 != bound:
        t_c = math.log((target - i0) / (target - bound)) / rate
        if t_c < t:
            _, int1, int2 = _segment(i0, target, rate, t_c)
            rest = t - t_c
            return int1 + bound * rest, int2 + rest * int1 + bound * 0.5 * rest * rest, bound
    elif bound is not None:
        return bound * t, bound * 0.5 * t * t, bound
    i_t, int1, int2 = _segment(i0, target, rate, t)
    return int1, int2, i_t
