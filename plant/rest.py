"""What the ground does to a simulated vehicle, and what a vehicle does once its watchdog says
LANDED or ESTOP (motors off): what the plant models themselves do not have. Pure.

:class:`Resting` wraps any :class:`plant.base.Plant` and takes the modes the ground and the motors
act on with each step (``docs/watchdog.md``; :attr:`plant.watchdog.Decision.rest`):

=========  ==================================================================================
FLYING,    the command is passed through untouched. 3D: the ground holds a vehicle up and never
HOLD       down: a step that ends below ``ground`` leaves the vehicle at ``ground`` with its
           downward velocity zeroed (:meth:`plant.base.Grounded.ground_contact`); its horizontal
           motion goes on, and it climbs again as soon as it is commanded up. While every
           vehicle flies above the ground the wrapper is transparent, bit for bit (the plant
           process and the in-process engine then fly the same arithmetic)
LAND       the command is passed through; 3D: a vehicle that reaches ``ground`` rests there
           (the landing law may overshoot it by millimetres; the ground does not let it). The
           same while the vehicle's agent lands it and its watchdog follows in FLYING.
LANDED     the vehicle rests where it touched down: its reported position is frozen there
           (3D: not below ``ground``), its velocity and acceleration are zero
ESTOP      motors off. 3D: the vehicle falls, commanded ``u = (0, 0, -g)`` (what lost thrust
           is: the double integrator falls at g, a quadrotor's Eq. 4 gives zero thrust), until
           it reaches ``ground``, where it rests (position clamped to the ground, velocity zero).
           2D: no vertical axis, so it stops where it is.
=========  ==================================================================================

A resting vehicle's model is still stepped (with a zero command) but no longer reported: the
ground holds the vehicle, not the model. In a payload world the cables' pull on a resting vehicle
is ignored (it is on the ground), while the payload still feels the model's vehicle: a limitation
of this ground model. :attr:`Resting.touching` says which vehicles the ground stopped at the last
step (the watchdog makes the contact an event from the measurement itself).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from plant.base import Grounded, Plant, Sample
from plant.vehicle import G
from tether.wire import ESTOP, LAND, LANDED


class Resting:
    """``inner`` with ground contact and motors-off for LANDED and ESTOP vehicles (module docstring)."""

    def __init__(self, inner: Plant, dim: int, ground: float, g: float = G):
        self.inner = inner
        self.ids = inner.ids
        self._dim = dim
        self._ground = ground
        self._g = g
        self._rest: dict[int, np.ndarray] = {}
        """Row -> rest position [m]."""
        self.touching: frozenset[int] = frozenset()
        """Rows the ground stopped (height clamped, downward velocity zeroed) at the last step."""

    def resting(self, row: int) -> bool:
        """Vehicle ``row`` is at rest on the ground (or stopped, 2D)."""
        return row in self._rest

    def _settle(self, row: int, p: np.ndarray) -> None:
        p = np.array(p, dtype=float)
        if self._dim == 3:
            p[-1] = max(p[-1], self._ground)
        self._rest[row] = p

    def state(self) -> Sample:
        s = self.inner.state()
        if not self._rest:
            return s
        p, v, a = s.p.copy(), s.v.copy(), s.a.copy()
        for row, rest in self._rest.items():
            p[row], v[row], a[row] = rest, 0.0, 0.0
        return Sample(p, v, a, s.d, s.attitude, s.payload)

    def step(self, u: np.ndarray, modes: Sequence[int] | None = None) -> None:
        """Advance one period with ``u`` ``(n, d)`` [m/s^2] for vehicles in FLYING, HOLD or LAND and
        what LANDED and ESTOP mean for the others (``modes``: one code of
        :data:`tether.wire.MODES` per vehicle; None: all flying)."""
        if modes is None or all(mode not in (LAND, LANDED, ESTOP) for mode in modes):
            if not self._rest:
                self.inner.step(u)
                self._contact(())
                return
        u = np.array(u, dtype=float)
        falling: list[int] = []
        now = self.inner.state()
        for row, mode in enumerate(modes if modes is not None else [0] * len(self.ids)):
            if row in self._rest:
                u[row] = 0.0
            elif mode == LANDED or (mode == ESTOP and (self._dim < 3 or now.p[row, -1] <= self._ground)):
                self._settle(row, now.p[row])
                u[row] = 0.0
            elif mode == ESTOP:
                u[row] = 0.0
                u[row, -1] = -self._g
                falling.append(row)
            elif mode == LAND and self._dim == 3:
                falling.append(row)  # descending onto the ground: contact stops it there
        self.inner.step(u)
        self._contact(falling)

    def _contact(self, falling: Sequence[int]) -> None:
        """3D ground contact after a step: a vehicle descending in LAND or ESTOP (``falling``)
        rests once it reaches the ground; any other vehicle that went through it is put back on
        it with no downward velocity, and flies on (a plant that the ground cannot stop rests it
        instead, as a last resort)."""
        if self._dim < 3:
            return
        # the positions alone when the plant can give them (a double integrator): a whole sample
        # evaluates the disturbance models too, which the next state() does anyway
        fast = getattr(self.inner, "positions", None)
        after = fast() if fast is not None else self.inner.state().p
        touching = []
        for row in range(len(self.ids)):
            if row in self._rest:
                continue
            z = after[row, -1]
            if row in falling and z <= self._ground:
                self._settle(row, after[row])
            elif z < self._ground:
                if isinstance(self.inner, Grounded):
                    self.inner.ground_contact(row, self._ground)
                    touching.append(row)
                else:
                    self._settle(row, after[row])
        self.touching = frozenset(touching)

    def close(self) -> None:
        self.inner.close()
