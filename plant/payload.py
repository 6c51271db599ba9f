"""The cable-suspended payload world: N vehicles and a point-mass payload on N elastic cables.

Pure numpy; no clock, no I/O. Frames and units: world frame, z up; [m], [m/s], [m/s^2], [N], [kg].
The paper treats the payload of Experiment 2 as an unknown bounded disturbance ``d_i`` in Eq. 5;
here it is a body, and ``d_i`` is what its cable really does to vehicle i.

Model
-----
Vehicle i (any :class:`plant.vehicle.Vehicle`, mass ``m_i``, centre of mass ``p_i``) and the
payload (mass ``m_L``, position ``p_L``) are joined by cable i, attached at the vehicle's **centre
of mass** (as in the paper's Experiment 2, where the string is tied near the battery, so the cable
exerts no torque on the vehicle) and at the payload's single point. With ::

    r_i = p_i - p_L,   L_i = |r_i|,   e_i = r_i / L_i,   L_i' = e_i . (v_i - v_L)

the cable is a one-sided spring-damper (rest length ``L0_i``, stiffness ``k_i``, damping ``c_i``)::

    T_i = max(0, k_i (L_i - L0_i) + c_i L_i')   if L_i > L0_i,        T_i = 0 otherwise

A slack cable (``L_i <= L0_i``) exerts exactly no force, and a taut one only pulls: the damper is
clipped with the spring, so a fast-shortening taut cable does not push either. The cable pulls
vehicle i with ``-T_i e_i`` and the payload with ``+T_i e_i``; the payload also weighs
``-m_L g e_z`` (``g = 9.81``). The cables are massless and straight; a taut cable stores
``k_i (L_i - L0_i)^2 / 2``.

Integration
-----------
The world advances in fixed substeps ``dt`` (default :data:`DEFAULT_SUBSTEP` = 1 ms, 1 kHz). Every
substep the cable forces are evaluated once, at the *drifted midpoint* ``x + v dt/2`` of every
body (velocities at the start of the substep), and held over the substep: the payload integrates
exactly under the held force, each vehicle through ``vehicle.advance(dt, f_cable_i)``. For
point masses this is position Verlet (drift-kick-drift), symplectic and second order: the
undamped world conserves energy up to a bounded O((omega dt)^2) ripple, with no drift, and it is
stable for ``omega dt < 2`` on the stiffest cable mode ``omega``. The damper uses start-of-substep
velocities, which adds O(c dt / mu) to the decay rate (+1.5 % at the defaults, measured in the tests).

Defaults (:class:`CableParams`): ``k = 200 N/m`` is a thin monofilament string of about half a
metre (``EA / L0`` with ``EA`` of 60-100 N): stiff, since the static stretch under a 15 g payload
shared by four cables is a fraction of a millimetre, yet its axial modes stay well inside the
step: the Gershgorin bound :func:`frequency_bound` gives ``omega <= 327 rad/s`` for a 15 g payload
on four cables (``8 k / m_L``), ``omega dt = 0.33`` at 1 kHz. ``c = 0.3 N s/m`` damps the
single-cable mode of a 30 g vehicle and a 15 g payload (``mu = 10 g``, ``omega = 141 rad/s``) at
``zeta = c / (2 sqrt(k mu)) = 0.11``: lightly, as a string is, but enough that the ringing is gone
within a few tenths of a second instead of aliasing into the 100 Hz control loop for ever.
The world refuses parameters whose bounds give ``omega dt > 1`` or a damper rate ``c dt / mu > 0.5``.

The implied disturbance
-----------------------
Over one control period ``h = n dt`` the world reports, per vehicle, the mean cable force per unit
vehicle mass, ``d_i = (1/n) sum_s f_i(s) / m_i`` (:attr:`PayloadWorld.implied_disturbance`): for
a plain :class:`plant.vehicle.PointMass` it is exactly the ``d_i`` of Eq. 5 over that period
(``accel_i = u_i + d_i``). :attr:`PayloadWorld.model_residual` is ``accel_i - u_i``, the
disturbance as the formation law feels it after the vehicle's own inner loop (feed-forward,
integrator, attitude lag of a quadrotor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from plant.vehicle import G, Vehicle

DEFAULT_SUBSTEP = 1e-3
"""Integration substep [s] (1 kHz): see the module docstring for the choice."""

MAX_OMEGA_DT = 1.0
"""Largest accepted ``omega_bound * dt`` (position Verlet is stable below 2)."""

MAX_DAMPING_DT = 0.5
"""Largest accepted ``damping_bound * dt`` (the explicit damper's rate per substep)."""


@dataclass(frozen=True)
class CableParams:
    """One cable (massless, straight, one-sided spring-damper).

    Attributes:
        rest_length: ``L0`` [m] > 0, the length at which the cable becomes taut.
        stiffness: ``k`` [N/m] > 0 (default: a ~0.5 m monofilament string, see the module docstring).
        damping: ``c`` [N s/m] >= 0 (default: ``zeta`` ~ 0.1 on a 30 g vehicle / 15 g payload pair).
    """

    rest_length: float
    stiffness: float = 200.0
    damping: float = 0.3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rest_length) and self.rest_length > 0.0):
            raise ValueError(f"cable rest_length must be finite and > 0 [m], not {self.rest_length!r}")
        if not (math.isfinite(self.stiffness) and self.stiffness > 0.0):
            raise ValueError(f"cable stiffness must be finite and > 0 [N/m], not {self.stiffness!r}")
        if not (math.isfinite(self.damping) and self.damping >= 0.0):
            raise ValueError(f"cable damping must be finite and >= 0 [N s/m], not {self.damping!r}")


@dataclass(frozen=True)
class CableArrays:
    """The parameters of N cables as arrays ``(N,)``: ``L0`` [m], ``k`` [N/m], ``c`` [N s/m]."""

    L0: np.ndarray
    k: np.ndarray
    c: np.ndarray

    @classmethod
    def of(cls, cables: CableParams | Sequence[CableParams], n: int) -> "CableArrays":
        """One :class:`CableParams` for all ``n`` cables, or one per cable."""
        seq = [cables] * n if isinstance(cables, CableParams) else list(cables)
        if len(seq) != n or not all(isinstance(c, CableParams) for c in seq):
            raise ValueError(f"cables must be one CableParams or a list of {n}, not {cables!r}")
        return cls(np.array([c.rest_length for c in seq]), np.array([c.stiffness for c in seq]),
                   np.array([c.damping for c in seq]))


def cable_forces(
    p: np.ndarray, v: np.ndarray, p_load: np.ndarray, v_load: np.ndarray, cab: CableArrays
) -> tuple[np.ndarray, np.ndarray]:
    """Tensions and forces of N cables.

    Args:
        p, v: vehicle positions [m] and velocities [m/s], ``(N, 3)``.
        p_load, v_load: payload position [m] and velocity [m/s], ``(3,)``.
        cab: the cables.

    Returns:
        ``(T, f)``: tensions ``(N,)`` [N] (>= 0; exactly 0 for a slack cable) and the cable forces
        on the vehicles ``(N, 3)`` [N; world frame] (the payload feels ``-f.sum(axis=0)``).
    """
    r = p - p_load
    length = np.sqrt((r * r).sum(axis=1))
    stretch = length - cab.L0
    taut = stretch > 0.0
    e = r / np.where(taut, length, 1.0)[:, None]
    rate = (e * (v - v_load)).sum(axis=1)
    tension = np.where(taut, np.maximum(cab.k * stretch + cab.c * rate, 0.0), 0.0)
    return tension, e * -tension[:, None]


def frequency_bound(vehicle_masses: np.ndarray, payload_mass: float, cab: CableArrays) -> tuple[float, float]:
    """Upper bounds on the world's stiffest axial mode and on its fastest damper rate.

    Gershgorin's theorem on ``M^-1 K`` (and ``M^-1 C``) of the linearised cables (each taut cable
    contributes at most ``k`` to a diagonal entry and ``k`` to an off-diagonal one, per axis)::

        omega^2 <= max(2 sum_i k_i / m_L,  max_i 2 k_i / m_i),   rate <= max(2 sum_i c_i / m_L, max_i 2 c_i / m_i)

    Returns ``(omega_bound [rad/s], damping_bound [1/s])``.
    """
    m = np.asarray(vehicle_masses, dtype=float)
    w2 = max(2.0 * float(cab.k.sum()) / payload_mass, float(np.max(2.0 * cab.k / m)))
    rate = max(2.0 * float(cab.c.sum()) / payload_mass, float(np.max(2.0 * cab.c / m)))
    return math.sqrt(w2), rate


@dataclass(frozen=True)
class Equilibrium:
    """A static equilibrium of the payload under fixed vehicles.

    Attributes:
        payload_p: payload position ``(3,)`` [m; world frame].
        tensions: ``(N,)`` [N].
        stretch: ``L_i - L0_i`` ``(N,)`` [m] (negative: slack).
        forces: the cable forces on the vehicles ``(N, 3)`` [N; world frame]; they sum to
            ``-m_L g e_z``.
    """

    payload_p: np.ndarray
    tensions: np.ndarray
    stretch: np.ndarray
    forces: np.ndarray

    def feedforward_masses(self, g: float = G) -> np.ndarray:
        """Each vehicle's vertical share of the payload, ``-f_iz / g`` ``(N,)`` [kg] (they sum to
        ``m_L``): the ``feedforward_mass`` that cancels the vertical pull at ``u = 0``."""
        return -self.forces[:, 2] / g

    def hold_accel(self, vehicle_masses: np.ndarray) -> np.ndarray:
        """``-f_i / m_i`` ``(N, 3)`` [m/s^2]: the constant command that holds a plain point mass
        (no feed-forward, no integrator) still against its cable."""
        return -self.forces / np.asarray(vehicle_masses, dtype=float)[:, None]


def hover_equilibrium(
    vehicle_p: np.ndarray,
    payload_mass: float,
    cables: CableParams | Sequence[CableParams],
    *,
    g: float = G,
    tol: float = 1e-13,
    max_iter: int = 100,
) -> Equilibrium:
    """The payload's rest position under vehicles held at ``vehicle_p`` ``(N, 3)`` [m].

    It minimises the potential ``U(x) = m_L g x_z + sum_i k_i max(0, |p_i - x| - L0_i)^2 / 2``,
    which is convex (so the equilibrium is unique when the taut cables' directions span space, or
    the cables hang vertically), by Newton's method with a backtracking line search, starting below
    the centroid at a depth where every cable is taut. A symmetric formation gives a payload
    straight below its centroid. Converges when the net force on the payload is below
    ``tol * m_L g``; raises ``RuntimeError`` otherwise.
    """
    p = np.array(vehicle_p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 1 or not np.all(np.isfinite(p)):
        raise ValueError(f"vehicle_p must be (N, 3) finite, not shape {p.shape}")
    if not (math.isfinite(payload_mass) and payload_mass > 0.0):
        raise ValueError(f"payload_mass must be finite and > 0 [kg], not {payload_mass!r}")
    cab = CableArrays.of(cables, p.shape[0])
    weight = payload_mass * g
    centroid = p.mean(axis=0)
    horiz = np.hypot(p[:, 0] - centroid[0], p[:, 1] - centroid[1])
    depth = np.sqrt(np.maximum(cab.L0 ** 2 - horiz ** 2, 0.0)) - (p[:, 2] - centroid[2])
    x = centroid - np.array([0.0, 0.0, float(depth.max()) + weight / float(cab.k.sum())])

    def potential(x: np.ndarray) -> float:
        s = np.maximum(np.linalg.norm(p - x, axis=1) - cab.L0, 0.0)
        return weight * x[2] + 0.5 * float(np.dot(cab.k, s * s))

    zero_v = np.zeros_like(p)
    for _ in range(max_iter):
        tension, f = cable_forces(p, zero_v, x, np.zeros(3), CableArrays(cab.L0, cab.k, np.zeros_like(cab.c)))
        grad = np.array([0.0, 0.0, weight]) + f.sum(axis=0)  # dU/dx = m_L g e_z - sum_i T_i e_i
        if np.linalg.norm(grad) <= tol * weight:
            length = np.linalg.norm(p - x, axis=1)
            return Equilibrium(x, tension, length - cab.L0, f)
        r = p - x
        length = np.linalg.norm(r, axis=1)
        hess = np.zeros((3, 3))
        for i in np.flatnonzero(length > cab.L0):
            e = r[i] / length[i]
            q = cab.L0[i] / length[i]
            hess += cab.k[i] * ((1.0 - q) * np.eye(3) + q * np.outer(e, e))
        try:
            step = -np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            step = -grad / float(cab.k.sum())
        u0, slope, alpha = potential(x), float(grad @ step), 1.0
        while potential(x + alpha * step) > u0 + 1e-4 * alpha * slope and alpha > 1e-12:
            alpha *= 0.5
        x = x + alpha * step
    raise RuntimeError(f"hover_equilibrium did not converge in {max_iter} iterations")


class PayloadWorld:
    """N vehicles and a point-mass payload on N cables, advanced together in fixed substeps.

    Args:
        vehicles: the N vehicles (:class:`plant.vehicle.Vehicle`); the world advances them, and
            owns them from now on.
        payload_mass: ``m_L`` [kg] > 0.
        payload_p0, payload_v0: the payload's initial position [m] and velocity [m/s] ``(3,)``
            (``None``: at rest).
        cables: one :class:`CableParams` for every cable, or one per vehicle.
        substep: integration substep ``dt`` [s] (default 1 ms); a control period must be a whole
            number of substeps.
        g: gravity [m/s^2].
        floor: height [m] of a rigid, frictionless floor under the payload (``None``: no floor).
            The payload rests on it (inelastic contact: a downward velocity is cancelled and the
            floor takes whatever net downward force remains) until the cables lift it.

    Every array the world returns is a copy.
    """

    def __init__(
        self,
        vehicles: Sequence[Vehicle],
        payload_mass: float,
        payload_p0: np.ndarray | Sequence[float],
        payload_v0: np.ndarray | Sequence[float] | None,
        cables: CableParams | Sequence[CableParams],
        substep: float = DEFAULT_SUBSTEP,
        *,
        g: float = G,
        floor: float | None = None,
    ) -> None:
        self.vehicles = list(vehicles)
        n = len(self.vehicles)
        if n < 1:
            raise ValueError("a payload world needs at least one vehicle")
        if not (math.isfinite(payload_mass) and payload_mass > 0.0):
            raise ValueError(f"payload_mass must be finite and > 0 [kg], not {payload_mass!r}")
        if not (math.isfinite(substep) and substep > 0.0):
            raise ValueError(f"substep must be finite and > 0 [s], not {substep!r}")
        self.cables = CableArrays.of(cables, n)
        self.payload_mass = float(payload_mass)
        self.substep = float(substep)
        self.g = float(g)
        self.floor = None if floor is None else float(floor)
        self.masses = np.array([float(veh.mass) for veh in self.vehicles])
        omega, damp = frequency_bound(self.masses, self.payload_mass, self.cables)
        if omega * self.substep > MAX_OMEGA_DT or damp * self.substep > MAX_DAMPING_DT:
            raise ValueError(
                f"substep {self.substep} s is too long for these cables: omega_bound dt = {omega * self.substep:.3g} "
                f"(max {MAX_OMEGA_DT}), damping_bound dt = {damp * self.substep:.3g} (max {MAX_DAMPING_DT})")
        self._pl = np.array(payload_p0, dtype=float).reshape(3)
        self._vl = np.zeros(3) if payload_v0 is None else np.array(payload_v0, dtype=float).reshape(3)
        self._gvec = np.array([0.0, 0.0, -self.g])
        self._u = np.zeros((n, 3))
        self._substeps = 0
        self._events = np.zeros(n, dtype=np.int64)
        tension, f = cable_forces(self._stack("p"), self._stack("v"), self._pl, self._vl, self.cables)
        self._tension, self._f = tension, f
        self._d = f / self.masses[:, None]
        self._al = f.sum(axis=0) / -self.payload_mass + self._gvec
        self._acc = np.zeros((n, 3))
        self._residual = np.zeros((n, 3))

    # -- commands -----------------------------------------------------------------------------
    def command(self, i: int, u: np.ndarray, yaw: float = 0.0) -> None:
        """Hold the desired acceleration ``u`` ``(3,)`` [m/s^2] (and yaw [rad]) on vehicle ``i``
        (0-based). Returns immediately."""
        u = np.array(u, dtype=float).reshape(3)
        self.vehicles[i].command(u, yaw)
        self._u[i] = u

    def command_all(self, u: np.ndarray) -> None:
        """Hold ``u`` ``(N, 3)`` [m/s^2] on every vehicle (yaw 0)."""
        u = np.array(u, dtype=float)
        if u.shape != self._u.shape:
            raise ValueError(f"u must have shape {self._u.shape}, not {u.shape}")
        for i, veh in enumerate(self.vehicles):
            veh.command(u[i], 0.0)
        self._u = u

    # -- time ---------------------------------------------------------------------------------
    def advance(self, h: float) -> None:
        """Advance one control period ``h`` [s], a whole number of substeps, with the held commands."""
        n = round(h / self.substep)
        if n < 1 or abs(n * self.substep - h) > 1e-9 * max(h, self.substep):
            raise ValueError(f"h = {h!r} s is not a whole number of substeps of {self.substep} s")
        dt, half = self.substep, 0.5 * self.substep
        vehicles, cab = self.vehicles, self.cables
        inv_ml = 1.0 / self.payload_mass
        gvec = self._gvec
        pl, vl = self._pl, self._vl
        vl_start = vl
        v_start = self._stack("v")
        p, v = self._stack("p"), v_start
        f_sum = np.zeros_like(p)
        taut_prev = self._tension > 0.0
        events = self._events
        tension, f = self._tension, self._f
        for _ in range(n):
            tension, f = cable_forces(p + half * v, v, pl + half * vl, vl, cab)
            taut = tension > 0.0
            events += taut_prev & ~taut
            taut_prev = taut
            f_sum += f
            for veh, fi in zip(vehicles, f):
                veh.advance(dt, fi)
            a_l = f.sum(axis=0) * -inv_ml + gvec
            pl = pl + dt * vl + (half * dt) * a_l
            vl = vl + dt * a_l
            if self.floor is not None and pl[2] < self.floor:  # resting on the floor
                pl[2] = self.floor
                vl[2] = max(vl[2], 0.0)
            p = np.array([veh.p for veh in vehicles])
            v = np.array([veh.v for veh in vehicles])
        self._pl, self._vl = pl, vl
        self._tension, self._f = tension, f
        self._d = f_sum / (n * self.masses[:, None])
        self._al = (vl - vl_start) / (n * dt)
        self._acc = (v - v_start) / (n * dt)
        self._residual = self._acc - self._u
        self._substeps += n

    def _stack(self, name: str) -> np.ndarray:
        return np.array([getattr(veh, name) for veh in self.vehicles], dtype=float)

    # -- state --------------------------------------------------------------------------------
    @property
    def n(self) -> int:
        """Number of vehicles (and cables)."""
        return len(self.vehicles)

    @property
    def substeps(self) -> int:
        """Substeps integrated since construction."""
        return self._substeps

    @property
    def t(self) -> float:
        """Simulated time since construction [s] (``substeps * substep``)."""
        return self._substeps * self.substep

    @property
    def p(self) -> np.ndarray:
        """Vehicle positions ``(N, 3)`` [m; world frame]."""
        return self._stack("p")

    @property
    def v(self) -> np.ndarray:
        """Vehicle velocities ``(N, 3)`` [m/s; world frame]."""
        return self._stack("v")

    @property
    def accel(self) -> np.ndarray:
        """Vehicles' mean accelerations over the last control period ``(N, 3)`` [m/s^2] (what each
        vehicle shares as its measured acceleration; zeros before the first period)."""
        return self._acc.copy()

    @property
    def u(self) -> np.ndarray:
        """The held commands ``(N, 3)`` [m/s^2]."""
        return self._u.copy()

    @property
    def payload_p(self) -> np.ndarray:
        """Payload position ``(3,)`` [m; world frame]."""
        return self._pl.copy()

    @property
    def payload_v(self) -> np.ndarray:
        """Payload velocity ``(3,)`` [m/s; world frame]."""
        return self._vl.copy()

    @property
    def payload_accel(self) -> np.ndarray:
        """Payload's mean acceleration over the last control period ``(3,)`` [m/s^2] (before the
        first period: its acceleration at the initial state)."""
        return self._al.copy()

    @property
    def tensions(self) -> np.ndarray:
        """Cable tensions ``(N,)`` [N] held over the last substep (at construction: at the initial
        state)."""
        return self._tension.copy()

    @property
    def taut(self) -> np.ndarray:
        """``(N,)`` bool: the cable pulled (tension > 0) over the last substep."""
        return self._tension > 0.0

    @property
    def cable_forces(self) -> np.ndarray:
        """Cable forces on the vehicles ``(N, 3)`` [N; world frame] held over the last substep."""
        return self._f.copy()

    @property
    def implied_disturbance(self) -> np.ndarray:
        """``d_i`` ``(N, 3)`` [m/s^2]: cable force on vehicle i over ``m_i``, averaged over the last
        control period (at construction: at the initial state)."""
        return self._d.copy()

    @property
    def model_residual(self) -> np.ndarray:
        """``accel_i - u_i`` ``(N, 3)`` [m/s^2] over the last control period: the disturbance of
        Eq. 5 as the formation law meets it, after the vehicle's inner loop (zeros before the
        first period)."""
        return self._residual.copy()

    @property
    def slack_events(self) -> np.ndarray:
        """Taut-to-slack transitions per cable since construction ``(N,)`` int: counted between
        consecutive substeps (the initial state counts as the first)."""
        return self._events.copy()

    def energy(self) -> float:
        """Mechanical energy [J] of bodies and cables: kinetic energy of all bodies, the payload's
        gravitational potential and the cables' elastic energy. Vehicles' weight and thrust are
        left out (they do work the world does not see); with ``u = 0``, no feed-forward and no
        integrator they cancel exactly, and an undamped world conserves this quantity."""
        p, v = self._stack("p"), self._stack("v")
        kin = 0.5 * float(np.dot(self.masses, np.einsum("ij,ij->i", v, v)))
        kin += 0.5 * self.payload_mass * float(self._vl @ self._vl)
        stretch = np.maximum(np.linalg.norm(p - self._pl, axis=1) - self.cables.L0, 0.0)
        return kin + self.payload_mass * self.g * float(self._pl[2]) + 0.5 * float(
            np.dot(self.cables.k, stretch * stretch))

    @classmethod
    def at_equilibrium(
        cls,
        vehicles: Sequence[Vehicle],
        payload_mass: float,
        cables: CableParams | Sequence[CableParams],
        substep: float = DEFAULT_SUBSTEP,
        *,
        g: float = G,
    ) -> tuple["PayloadWorld", Equilibrium]:
        """A world whose payload hangs at rest in :func:`hover_equilibrium` under the vehicles'
        current positions. The vehicles hold still only if their inner loops cancel the cable
        forces: with plain point masses, command ``eq.hold_accel(world.masses)``; with
        ``feedforward_mass = eq.feedforward_masses()`` the vertical pull is cancelled at ``u = 0``
        and the horizontal one needs ``u_h = -f_h / (m + m_ff)``."""
        vs = list(vehicles)
        eq = hover_equilibrium(np.array([veh.p for veh in vs], dtype=float), payload_mass, cables, g=g)
        return cls(vs, payload_mass, eq.payload_p, None, cables, substep, g=g), eq
