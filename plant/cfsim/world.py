"""The simulated Crazyflie's world: the quadrotor and a floor at ``z = 0``. Pure.

The floor is a one-sided, preloaded spring-damper (natural frequency and damping ratio with the
vehicle's mass) with viscous friction on the horizontal velocity while in contact; a vehicle at
rest on it with its motors off does not move at all.
"""

from __future__ import annotations

import math

import numpy as np

from plant.cfsim.commander import Attitude, Manual, Off, Setpoint
from plant.quadrotor import Quadrotor

_MOTORS_STOPPED = 1e-4
"""A motor below this fraction of the vehicle's weight counts as stopped (motors with a lag decay
towards zero and never reach it)."""


class World:
    """The quadrotor above its floor. ``frequency`` [Hz] and ``damping`` are the contact spring's;
    ``contact_step`` [s] is the step of the world near and on the floor (the contact force is held
    over a step)."""

    def __init__(self, quad: Quadrotor, frequency: float, damping: float, contact_step: float) -> None:
        self.quad = quad
        self.contact_step = contact_step
        m = quad.mass
        self._g = quad.params.g
        w = 2.0 * math.pi * frequency
        self._k_floor = m * w * w
        self._c_floor = 2.0 * damping * m * w
        self._z_contact = m * self._g / self._k_floor
        """The floor spring is preloaded so that a vehicle at rest on it sits at z = 0."""

    def advance(self, period: float, sp: Setpoint) -> None:
        """Advance the quadrotor by ``period`` [s] with the floor: one call while it cannot reach the
        floor within the period, steps of ``contact_step`` with the contact force held otherwise,
        nothing at all while it lies still on the floor with its motors off (``sp`` says whether
        they are meant to be)."""
        quad = self.quad
        remaining = period
        while remaining > 1e-12:
            p, v = quad.p, quad.v
            lowest = p[2] + min(0.0, v[2]) * remaining - 0.5 * self._g * remaining * remaining
            if lowest > self._z_contact:
                quad.advance(remaining)
                return
            if (isinstance(sp, Off) or (isinstance(sp, (Attitude, Manual)) and sp.thrust_pwm == 0.0)) \
                    and p[2] <= self._z_contact and float(np.abs(v).max()) < 1e-3 \
                    and float(np.abs(quad.omega).max()) < 1e-2 \
                    and float(quad.motor_thrusts.max()) < _MOTORS_STOPPED * quad.mass * self._g:
                return  # at rest on the floor, motors off: nothing moves
            h = min(self.contact_step, remaining)
            quad.advance(h, self._floor_force(p, v))
            remaining -= h

    def _floor_force(self, p: np.ndarray, v: np.ndarray) -> np.ndarray | None:
        """The floor's push [N; world]: a one-sided, preloaded spring-damper under ``z_contact``,
        with viscous friction on the horizontal velocity while in contact."""
        depth = self._z_contact - p[2]
        if depth <= 0.0:
            return None
        c = self._c_floor
        return np.array([-c * v[0], -c * v[1], max(0.0, self._k_floor * depth - c * v[2])])
