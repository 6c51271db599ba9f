"""The plant protocol: whatever flies the agents' commands, one control period at a time. Pure.

A :class:`Plant` hosts one or more vehicles (the agents ``ids``). At tick k it reports each
vehicle's measurement (:meth:`Plant.state`: position, velocity, and the mean acceleration over
the previous period, as the runtime's semantics require) and then advances one period with the
commands of tick k held (:meth:`Plant.step`). The mission chooses the plant by name:

==================  =======================================================================
``double_integrator``  Eq. 5 discretised exactly (:mod:`plant.double_integrator`): the oracle.
``point_mass``         a 3D point mass with an ideal inner loop (:class:`plant.vehicle.PointMass`).
``quadrotor``          a Crazyflie 2.1-class rigid body with its 500 Hz inner loop
                       (:class:`plant.quadrotor.Quadrotor`).
``[payload]``          one :class:`PayloadPlant` hosting every vehicle and a cable-suspended
                       payload (:class:`plant.payload.PayloadWorld`).
==================  =======================================================================

A mission disturbance ``d_i(t)`` [m/s^2] acts on a vehicle with mass as the force ``m d_i``,
held over each period at its value at the period's midpoint (the double integrator integrates it
exactly instead). :func:`plant.build.build` makes the plants of a mission; the plant process and
the in-process engine (:mod:`sim.lockstep`) both use it, so they fly the same arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

from plant import double_integrator
from plant.disturbance import DisturbanceBank
from tether import mission as ms

if TYPE_CHECKING:  # loaded only by the plants that use them
    from plant.quadrotor import Quadrotor
    from plant.vehicle import PointMass, Vehicle


@dataclass
class Sample:
    """What a plant reports at one tick, one row per vehicle (``ids`` order)."""

    p: np.ndarray
    """``(n, d)`` position [m]."""
    v: np.ndarray
    """``(n, d)`` velocity [m/s]."""
    a: np.ndarray
    """``(n, d)`` mean acceleration over the previous period [m/s^2] (zero at tick 0)."""
    d: np.ndarray
    """``(n, d)`` the disturbance acting [m/s^2]: the mission's at ``t_k``, or, with a payload, the
    cable force over mass averaged over the previous period."""
    attitude: np.ndarray | None = None
    """``(n, 3)`` roll, pitch, yaw [rad] of vehicles with mass; None for a plant without attitude."""
    payload: "PayloadSample | None" = None
    """A payload world's own state (:class:`PayloadPlant`); None otherwise."""

    @property
    def extra(self) -> dict[str, np.ndarray]:
        """The payload record by its wire/run-file names (``payload_p``, ``payload_v``, ``tension``,
        ``slack_events``): what ``plant/node.py`` publishes as a ``WorldState``. New code reads
        :attr:`payload` instead."""
        pl = self.payload
        if pl is None:
            return {}
        return {"payload_p": pl.p, "payload_v": pl.v, "tension": pl.tension, "slack_events": pl.slack_events}


@dataclass(frozen=True)
class PayloadSample:
    """A cable-suspended payload at one tick."""

    p: np.ndarray
    """``(3,)`` payload position [m; world frame]."""
    v: np.ndarray
    """``(3,)`` payload velocity [m/s; world frame]."""
    tension: np.ndarray
    """``(n,)`` cable tension per vehicle [N] (``ids`` order)."""
    slack_events: np.ndarray
    """``(n,)`` int: taut -> slack transitions per cable since the start."""


@runtime_checkable
class Plant(Protocol):
    ids: tuple[int, ...]

    def state(self) -> Sample:
        """The measurement of the current tick."""

    def step(self, u: np.ndarray) -> None:
        """Advance one control period with ``u`` ``(n, d)`` [m/s^2] held."""

    def close(self) -> None:
        """Release what the plant holds (nothing for simulated ones)."""


@runtime_checkable
class Grounded(Protocol):
    """A simulated plant whose vehicles the ground can stop (:class:`plant.rest.Resting`)."""

    def ground_contact(self, row: int, z: float) -> None:
        """The ground at height ``z`` [m] stops vehicle ``row``'s downward motion: its height is at
        least ``z``, a downward velocity is zeroed; it climbs again when commanded up."""


class DoubleIntegratorPlant:
    """One exact double integrator per id, with the mission's disturbance models."""

    def __init__(self, m: ms.Mission, ids: list[int]):
        self.ids = tuple(ids)
        self._dist = DisturbanceBank.from_mission(m, list(ids))
        self._h = m.dt
        self._k = 0
        d = m.dim
        self._p = np.array([m.agent(i).p0 for i in ids], dtype=float).reshape(len(ids), d)
        self._v = np.array([m.agent(i).v0 if m.agent(i).v0 is not None else [0.0] * d for i in ids],
                           dtype=float).reshape(len(ids), d)
        self._a = np.zeros((len(ids), d))

    def state(self) -> Sample:
        return Sample(self._p.copy(), self._v.copy(), self._a.copy(), self._dist.value(self._k))

    def positions(self) -> np.ndarray:
        """``state().p`` without the rest of the sample (read-only: a view of the plant's own)."""
        return self._p

    def step(self, u: np.ndarray) -> None:
        dv, dp = self._dist.increments(self._k)
        # all rows at once: element-wise, each row's arithmetic is one plant process's
        self._p, self._v, self._a = double_integrator.step(self._p, self._v, np.asarray(u, dtype=float), dv, dp,
                                                           self._h)
        self._k += 1

    def seek(self, k: int) -> None:
        """Continue at tick ``k`` (a restarted process resuming a run: :mod:`plant.resume`); the
        disturbance models take their values there."""
        self._k = k

    @property
    def bank(self) -> DisturbanceBank:
        """The disturbance models of its vehicles (read-only)."""
        return self._dist

    def ground_contact(self, row: int, z: float) -> None:
        """See :class:`Grounded`."""
        if self._p[row, -1] < z:
            self._p[row, -1] = z
        if self._v[row, -1] < 0.0:
            self._v[row, -1] = 0.0

    def take_over(self, k: int, p: list[list[float]], v: list[list[float]], a: list[list[float]]) -> None:
        """Continue from tick ``k`` with these rows, stepped elsewhere until now with the same
        arithmetic (:class:`plant.onboard.Onboard`'s plain floats)."""
        self._p, self._v, self._a = (np.array(x, dtype=float).reshape(self._p.shape) for x in (p, v, a))
        self._k = k

    def close(self) -> None:
        pass


def _vehicle(m: ms.Mission, aid: int) -> PointMass | Quadrotor:
    """The vehicle model of agent ``aid`` (``point_mass`` or ``quadrotor``)."""
    a = m.agent(aid)
    spec = a.plant
    v0 = a.v0 if a.v0 is not None else [0.0, 0.0, 0.0]
    if isinstance(spec, ms.PointMassPlant):
        from plant.vehicle import Integrator, PointMass

        integ = Integrator(spec.integrator.gain, spec.integrator.limit, spec.integrator.axes) if spec.integrator else None
        return PointMass(spec.mass, a.p0, v0, spec.feedforward_mass, integ)
    if isinstance(spec, ms.QuadrotorPlant):
        from plant.quadrotor import Quadrotor, QuadrotorParams

        prm = QuadrotorParams(mass=spec.mass, tilt_max=math.radians(spec.tilt_max),
                              feedforward_mass=spec.feedforward_mass,
                              z_integrator_gain=spec.integrator.gain if spec.integrator else 0.0,
                              z_integrator_limit=spec.integrator.limit if spec.integrator else 2.0,
                              integrator_axes=spec.integrator.axes if spec.integrator else "z")
        return Quadrotor(prm, np.array(a.p0, dtype=float), np.array(v0, dtype=float), spec.yaw)
    raise ValueError(f"agent {aid}: plant {type(spec).__name__} is not a vehicle with mass")


def _yaw(m: ms.Mission, aid: int) -> float:
    spec = m.agent(aid).plant
    return spec.yaw if isinstance(spec, ms.QuadrotorPlant) else 0.0


def _attitude(veh: Vehicle) -> np.ndarray:
    return np.array(veh.euler()) if hasattr(veh, "euler") else np.zeros(3)


class VehiclePlant:
    """Free-flying vehicles with mass (``point_mass``, ``quadrotor``), one per id; the mission's
    disturbance acts on each as the force ``m d(t_k + h/2)``, held over the period."""

    def __init__(self, m: ms.Mission, ids: list[int]):
        self.ids = tuple(ids)
        self._veh = [_vehicle(m, i) for i in ids]
        self._yaw = [_yaw(m, i) for i in ids]
        self._dist = DisturbanceBank.from_mission(m, list(ids))
        self._h = m.dt
        self._k = 0
        self._a = np.zeros((len(ids), 3))

    def state(self) -> Sample:
        return Sample(np.array([v.p for v in self._veh]), np.array([v.v for v in self._veh]), self._a.copy(),
                      self._dist.value(self._k), attitude=np.array([_attitude(v) for v in self._veh]))

    def step(self, u: np.ndarray) -> None:
        d = None if self._dist.is_zero else self._dist.value_at((self._k + 0.5) * self._h)
        for r, veh in enumerate(self._veh):
            veh.command(np.asarray(u[r], dtype=float), self._yaw[r])
            veh.advance(self._h, None if d is None else veh.mass * d[r])
            self._a[r] = veh.accel()
        self._k += 1

    def seek(self, k: int) -> None:
        """Continue at tick ``k`` (see :meth:`DoubleIntegratorPlant.seek`)."""
        self._k = k

    def ground_contact(self, row: int, z: float) -> None:
        """See :class:`Grounded`."""
        self._veh[row].ground_contact(z)

    def close(self) -> None:
        pass


class PayloadPlant:
    """Every vehicle of the mission and one payload on cables (``[payload]``); records the payload's
    position and velocity, the cable tensions and the slack events (taut -> slack) per cable."""

    def __init__(self, m: ms.Mission, ids: list[int]):
        from plant.payload import CableParams, PayloadWorld, hover_equilibrium

        if sorted(ids) != sorted(m.agent_ids):
            raise ValueError("a payload world hosts every vehicle of the mission")
        pl = m.payload
        if pl is None:
            raise ValueError("a payload world needs the mission's [payload] section")
        self.ids = tuple(ids)
        vehicles = [_vehicle(m, i) for i in ids]
        self._yaw = [_yaw(m, i) for i in ids]
        cable = CableParams(pl.cable.length, pl.cable.stiffness, pl.cable.damping)
        p0 = np.array([veh.p for veh in vehicles])
        if pl.p0 is not None:
            start = np.array(pl.p0, dtype=float)
        else:
            below = p0.mean(axis=0)
            if m.floor is not None:
                below[2] = m.floor
            if m.floor is not None and np.all(np.linalg.norm(p0 - below, axis=1) <= pl.cable.length):
                start = below  # on the floor, cables slack
            else:
                start = hover_equilibrium(p0, pl.mass, cable, tol=1e-9).payload_p
        self._dist = DisturbanceBank.from_mission(m, list(ids))
        self._vehicles = vehicles
        self.world = PayloadWorld(vehicles, pl.mass, start, None, cable, pl.substep, floor=m.floor)
        self._h = m.dt
        self._k = 0
        self._a = np.zeros((len(ids), 3))
        self._d = np.zeros((len(ids), 3))

    def state(self) -> Sample:
        w = self.world
        payload = PayloadSample(w.payload_p, w.payload_v, w.tensions, w.slack_events)
        return Sample(w.p, w.v, self._a.copy(), self._d.copy(), attitude=np.array([_attitude(v) for v in w.vehicles]),
                      payload=payload)

    def step(self, u: np.ndarray) -> None:
        w = self.world
        for r in range(len(self.ids)):
            w.command(r, u[r], self._yaw[r])
        w.advance(self._h)
        self._a = w.accel
        self._d = w.implied_disturbance
        self._k += 1

    def ground_contact(self, row: int, z: float) -> None:
        """See :class:`Grounded` (the cables' pull is the world's next substep's)."""
        self._vehicles[row].ground_contact(z)

    def close(self) -> None:
        pass


class Fleet:
    """Several plants stepped as one: a world process hosting many vehicles without a payload
    (``tether run --shared-plants``). Each vehicle keeps its own plant, the very object its own
    process would step, so that its arithmetic is that process's; the rows are the plants' rows,
    in order."""

    def __init__(self, plants: list[Plant]):
        if not plants:
            raise ValueError("a fleet hosts at least one plant")
        self.plants = plants
        self.ids = tuple(i for p in plants for i in p.ids)
        rows, start = [], 0
        for p in plants:
            rows.append(slice(start, start + len(p.ids)))
            start += len(p.ids)
        self._rows = rows

    def state(self) -> Sample:
        ss = [p.state() for p in self.plants]
        attitude = None
        if any(s.attitude is not None for s in ss):  # a vehicle without attitude (a double integrator): NaN
            attitude = np.concatenate([s.attitude if s.attitude is not None else np.full((len(s.p), 3), np.nan)
                                       for s in ss])
        return Sample(np.concatenate([s.p for s in ss]), np.concatenate([s.v for s in ss]),
                      np.concatenate([s.a for s in ss]), np.concatenate([s.d for s in ss]), attitude=attitude)

    def positions(self) -> np.ndarray:
        """``state().p`` (a plant that can give its positions alone does: see ``DoubleIntegratorPlant``)."""
        return np.concatenate([fast() if (fast := getattr(p, "positions", None)) is not None else p.state().p
                               for p in self.plants])

    def step(self, u: np.ndarray) -> None:
        u = np.asarray(u, dtype=float)
        for p, rows in zip(self.plants, self._rows):
            p.step(u[rows])

    def ground_contact(self, row: int, z: float) -> None:
        """See :class:`Grounded` (a hosted plant that the ground cannot stop: nothing)."""
        for p, rows in zip(self.plants, self._rows):
            if rows.start <= row < rows.stop and isinstance(p, Grounded):
                p.ground_contact(row - rows.start, z)

    def close(self) -> None:
        for p in self.plants:
            p.close()
