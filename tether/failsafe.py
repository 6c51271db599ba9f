"""The failsafe command laws every agent's supervisor and every plant's watchdog fly. Pure.

They live in the core because both sides of the command link need them: an agent in HOLD or LAND
commands them itself, and a plant whose agent has gone silent flies the very same laws on its own
measurement (``docs/safety.md``). Vectors are sequences of ``d`` floats [SI units; world frame]
(:mod:`tether.vec`), every result a list; in 3D the last axis is up.

* :func:`saturate` — the command scaled down to a norm of at most ``max_accel``; a command that is
  not finite becomes None (the caller must fail safe, never pass it on);
* :func:`hold` — brake to zero velocity and keep the position where HOLD began:
  ``u = -kv v - kp (p - p_hold)``, saturated;
* :func:`land` — hold horizontally and descend at ``land_speed`` to ``ground`` (3D; in 2D there
  is no up, so LAND is HOLD until the vehicle is still);
* :func:`landed` — on the ground (3D) or still (2D), slow enough to disarm; in 2D also a landing
  that has held for ``settle`` seconds (a disturbance HOLD cannot cancel may keep a vehicle moving).
"""

from __future__ import annotations

import math

from tether.vec import Vec, dot, floats

STILL = 0.05
"""A vehicle slower than this [m/s] counts as still (2D LAND ends, a landing has settled)."""
TOUCHDOWN = 0.02
"""A 3D vehicle within this height of the ground [m] has touched down."""


def saturate(u: Vec, max_accel: float) -> list[float] | None:
    """``u`` scaled down to norm ``max_accel`` where it exceeds it; None if ``u`` is not finite."""
    u = floats(u)
    uu = dot(u, u)  # finite only if every component is (checked one by one only where not)
    if not math.isfinite(uu) and not all(map(math.isfinite, u)):
        return None
    n = math.sqrt(uu)
    if n <= max_accel:
        return u
    scale = max_accel / n
    return [c * scale for c in u]


def hold(p: Vec, v: Vec, p_hold: Vec, kp: float, kv: float, max_accel: float) -> list[float]:
    """HOLD's command: brake to zero velocity and return to ``p_hold``, at most ``max_accel``.
    Non-finite measurements give a zero command (nothing better is known)."""
    u = saturate([-kv * vc - kp * (pc - hc) for pc, vc, hc in zip(p, v, p_hold)], max_accel)
    return [0.0] * len(p) if u is None else u


def land(p: Vec, v: Vec, p_hold: Vec, kp: float, kv: float, max_accel: float,
         land_speed: float, ground: float) -> list[float]:
    """LAND's command: HOLD horizontally; in 3D descend at ``land_speed``, slowing in the last
    ``2 land_speed / kv`` metres and touching down at :data:`STILL` (vertical velocity tracking)."""
    if len(p) < 3:
        return hold(p, v, p_hold, kp, kv, max_accel)
    u = [-kv * vc - kp * (pc - hc) for pc, vc, hc in zip(p, v, p_hold)]
    height = float(p[-1] - ground)
    # the last metres: v_want = -(kv/2) height (damping ratio 0.7 with the velocity loop), down to a
    # touch-down speed of STILL, so the vehicle reaches the ground in finite time and slowly
    v_want = -min(land_speed, max(STILL, max(height, 0.0) * 0.5 * kv))
    u[-1] = kv * (v_want - v[-1])
    out = saturate(u, max_accel)
    return [0.0] * len(p) if out is None else out


def landed(p: Vec, v: Vec, ground: float, held: float = 0.0, settle: float = math.inf) -> bool:
    """On the ground and settled (3D), or, in 2D, still or in LAND for ``held >= settle`` seconds.

    2D has no ground to end a landing, and HOLD's law (a spring and a damper about ``p_hold``) does
    not cancel a steady sway: under the cable's sinusoidal pull a holding vehicle moves at
    ``|d| w / |kp - w^2 + j kv w|`` for ever (0.1-0.3 m/s on ``section4``), never below
    :data:`STILL`. ``settle`` bounds how long a 2D landing lasts (``safety.land_settle``); in 3D
    nothing but the ground ends it (a timeout must never disarm a vehicle in the air)."""
    speed = math.sqrt(dot(v, v)) if all(map(math.isfinite, v)) else math.inf
    if len(p) < 3:
        return speed < STILL or held >= settle
    return bool(p[-1] - ground <= TOUCHDOWN) and speed < 2 * STILL


def why_landed(p: Vec, v: Vec, held: float) -> str:
    """The reason :func:`landed` gives for a vehicle that has been in LAND ``held`` seconds."""
    if len(p) >= 3:
        return "touched down"
    speed = math.sqrt(dot(v, v)) if all(map(math.isfinite, v)) else math.inf
    if speed < STILL:
        return "still"
    return f"landing held {held:.2f} s (land_settle), still moving at {speed:.2g} m/s: stopped"
