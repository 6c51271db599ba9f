"""Pre-flight checks of a Crazyflie: what must hold before it takes off. Pure (the plant reads the
vehicle, :func:`refusals` judges the readings).

A vehicle is refused take-off, with every reason named, when

* its battery voltage (``pm.vbat``, motors off) is below the fleet's ``health.battery_min``, or its
  power state (``pm.state``) is low power or shut down;
* its supervisor cannot fly (``supervisor.info`` bit 3 clear) or is locked (bit 6: an emergency stop,
  a watchdog cut; the firmware needs a restart);
* its link answers less than ``health.link_min`` of the echo requests (pings) the plant sent it, ten a
  second while the estimator converges (at least a second; an answer up to 2 s late counts);
* its estimator has not converged: a position variance (``kalman.varPX/PY/PZ``) above
  ``health.variance_max`` once ``health.settle_timeout`` has passed since the estimator was reset;
* its estimate puts it more than ``tether.fleet.PLACE_TOLERANCE`` (0.3 m) from where the fleet file says it stands
  (plausible but false: two rigid bodies or two radio addresses swapped, a vehicle put down on the
  wrong spot).

In flight, :func:`down` reads the same supervisor bits for the one thing a plant cannot mend: the
firmware has taken the vehicle out of the air (tumbled, crashed, or locked after a watchdog cut its
motors), and it will not fly again until it restarts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from tether.fleet import PLACE_TOLERANCE

BIT_CAN_FLY, BIT_TUMBLED, BIT_LOCKED, BIT_CRASHED = 3, 5, 6, 7
"""Supervisor bitfield bits (firmware ``supervisor.c`` ``supervisor.info``; cflib ``supervisor.py``)."""
PM_LOW_POWER, PM_SHUTDOWN = 3, 4
"""``pm.state`` values that forbid a take-off (firmware ``pm.h``)."""


class PreflightRefused(RuntimeError):
    """A vehicle failed its pre-flight checks; the message names the vehicle and every reason."""


@dataclass(frozen=True)
class Readings:
    """What the plant read from the vehicle just before take-off."""

    vbat: float
    """Battery voltage [V]."""
    pm_state: int
    """Power state (0 battery, 1 charging, 2 charged, 3 low power, 4 shut down)."""
    supervisor: int
    """Supervisor bitfield."""
    variance: tuple[float, float, float]
    """Position variance per axis [m^2]."""
    link: float
    """Fraction of the plant's pings the vehicle answered [0..1]."""
    position: tuple[float, float, float] | None = None
    """The state estimate's position [m; world frame], if one came."""


@dataclass(frozen=True)
class Limits:
    battery_min: float = 3.7
    """[V]."""
    variance_max: float = 0.001
    """[m^2]."""
    link_min: float = 0.9
    """[0..1]."""


def down(supervisor: int) -> str | None:
    """Why a flying vehicle's firmware has cut its motors, from its supervisor bitfield; None while
    it may fly. Tumbled (upside down: the firmware stops the motors), crashed (tumbled while flying),
    locked (an emergency stop, or the commander watchdog's cut after 2 s without a setpoint): in each
    the motors are off until the vehicle restarts, whatever it is sent."""
    why = [what for bit, what in ((BIT_CRASHED, "crashed"), (BIT_TUMBLED, "tumbled"), (BIT_LOCKED, "locked"))
           if supervisor >> bit & 1]
    return None if not why else f"its firmware has cut the motors ({', '.join(why)}; restart the vehicle)"


def converged(variance: tuple[float, float, float], lim: Limits) -> bool:
    """The estimator is sure enough of the position to fly."""
    return all(math.isfinite(v) and v <= lim.variance_max for v in variance)


def refusals(r: Readings, lim: Limits, place: tuple[float, float, float] | None = None) -> list[str]:
    """Every reason the vehicle must not take off, each ``"<what>; <fix>"``; empty: it may.
    ``place``: where the fleet file says the vehicle stands [m], if it says."""
    out: list[str] = []
    if not (math.isfinite(r.vbat) and r.vbat >= lim.battery_min):
        out.append(f"battery {r.vbat:.2f} V is below {lim.battery_min:.2f} V; charge or swap the battery")
    if r.pm_state in (PM_LOW_POWER, PM_SHUTDOWN):
        out.append(f"power state {r.pm_state} ({'low power' if r.pm_state == PM_LOW_POWER else 'shut down'}); "
                   "charge or swap the battery")
    if r.supervisor >> BIT_LOCKED & 1:
        out.append("the supervisor is locked (an emergency stop or a watchdog cut); restart the vehicle")
    elif not r.supervisor >> BIT_CAN_FLY & 1:
        out.append("the supervisor says it cannot fly (not armed?); arm it or check its deck and sensors")
    if not (math.isfinite(r.link) and r.link >= lim.link_min):
        out.append(f"the link answers {100 * r.link:.0f} % of the pings (needs {100 * lim.link_min:.0f} "
                   "%); move the Crazyradio closer, change channel, or fly fewer vehicles per radio")
    if not converged(r.variance, lim):
        worst = max(r.variance) if all(math.isfinite(v) for v in r.variance) else math.nan
        out.append(f"the position estimate has not converged (variance {worst:.2g} m^2 > {lim.variance_max:g}); "
                   "check the positioning system sees the vehicle (motion-capture rigid body, base stations, "
                   "anchors)")
    elif place is not None:
        p = r.position
        d = math.dist(p, place) if p is not None and all(math.isfinite(c) for c in p) else math.inf
        if not d <= PLACE_TOLERANCE:
            where = "nowhere" if p is None or math.isinf(d) else "[" + ", ".join(f"{c:.2f}" for c in p) + "]"
            out.append(f"its estimate puts it at {where}, {d:.2f} m from its place in the fleet file "
                       f"[{', '.join(f'{c:.2f}' for c in place)}]; check the rigid body's name, the radio address "
                       "and where the vehicle was put down")
    return out
