"""The failsafe command laws every agent's supervisor and every plant's watchdog fly. Pure.

They live in the core because both sides of the command link need them: an agent in HOLD or LAND
commands them itself, and a plant whose agent has gone silent flies the very same laws on its own
measurement (``docs/safety.md``). Vectors are sequences of ``d`` floats [SI units; world frame]
(:mod:`tether.vec`), every result a list; in 3D the last axis is up.

* :func:`saturate` — the command scaled down to a norm of at most ``max_accel``; a command that is
  not finite becomes None (the caller must fail safe, never pass it on);
* :func:`hold` — brake to zero velocity and keep the anchor ``p_hold`` (:func:`hold_point`):
  ``u = -kv v - kp (p - p_hold)``, saturated;
* :func:`land` — hold horizontally and descend at ``land_speed`` to ``ground`` (3D; in 2D there
  is no up, so LAND is HOLD until the vehicle is still); :class:`Landing` flies it with the
  memory that a steady push up needs;
* :func:`landed` — on the ground (3D) or still (2D), slow enough to disarm; in 2D also a landing
  that has held for ``settle`` seconds (a disturbance HOLD cannot cancel may keep a vehicle moving);
* :func:`hold_point` — where HOLD (and LAND) anchors a vehicle: where its brake brings it to
  rest, ahead of where HOLD began, so that a formation that brakes together stops together and no
  vehicle turns back through the one behind it;
* :func:`braking_distance`, :func:`fence_breach` — how far a vehicle travels once HOLD brakes, and
  whether it is outside a geofence box or would leave it braking from here;
* :func:`inside` — a position brought into a box (where a vehicle outside a geofence lands).

Each law's arithmetic is a function of scalars (:func:`saturation`, :func:`hold_axis`,
:func:`hold_reach`, :func:`anchor_axis`, :func:`floored`, :func:`settled`) that the law calls on
every axis and the in-process engine (``sim/lockstep_kernel.py``) compiles, so both run one
definition, operation for operation.
"""

from __future__ import annotations

import math

from tether.vec import Vec, dot, floats, norm

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
    scale = saturation(uu, max_accel)
    if scale == 1.0:
        return u
    return [c * scale for c in u]


def saturation(uu: float, max_accel: float) -> float:
    """The factor :func:`saturate` scales a command of squared norm ``uu`` by: 1.0 where its norm is
    at most ``max_accel``, else ``max_accel`` over the norm (NaN where ``uu`` is). Scalars: the
    in-process engine compiles this very function."""
    n = math.sqrt(uu)
    if n <= max_accel:
        return 1.0
    return max_accel / n


def hold(p: Vec, v: Vec, p_hold: Vec, kp: float, kv: float, max_accel: float) -> list[float]:
    """HOLD's command: brake to zero velocity and return to ``p_hold``, at most ``max_accel``.
    Non-finite measurements give a zero command (nothing better is known)."""
    u = saturate([hold_axis(pc, vc, hc, kp, kv) for pc, vc, hc in zip(p, v, p_hold)], max_accel)
    return [0.0] * len(p) if u is None else u


def hold_axis(p: float, v: float, p_hold: float, kp: float, kv: float) -> float:
    """:func:`hold`'s command on one axis, before saturation: ``-kv v - kp (p - p_hold)``. Scalars:
    the in-process engine compiles this very function."""
    return -kv * v - kp * (p - p_hold)


def descent_rate(p: Vec, kv: float, land_speed: float, ground: float) -> float:
    """The vertical velocity LAND wants at ``p`` (3D) [m/s, negative: down]: ``land_speed``, and in
    the last metres ``(kv/2) height`` (damping ratio 0.7 with the velocity loop), down to a
    touch-down speed of :data:`STILL`, so the vehicle reaches the ground in finite time and slowly."""
    height = float(p[-1] - ground)
    return -min(land_speed, max(STILL, max(height, 0.0) * 0.5 * kv))


def land(p: Vec, v: Vec, p_hold: Vec, kp: float, kv: float, max_accel: float,
         land_speed: float, ground: float, bias: float = 0.0) -> list[float]:
    """LAND's command: HOLD horizontally; in 3D descend at :func:`descent_rate` (vertical velocity
    tracking, plus ``bias`` [m/s^2], the integral term :class:`Landing` keeps)."""
    if len(p) < 3:
        return hold(p, v, p_hold, kp, kv, max_accel)
    u = [hold_axis(pc, vc, hc, kp, kv) for pc, vc, hc in zip(p, v, p_hold)]
    u[-1] = kv * (descent_rate(p, kv, land_speed, ground) - v[-1]) + bias
    out = saturate(u, max_accel)
    return [0.0] * len(p) if out is None else out


MAX_STEP = 0.1
"""The longest interval [s] :class:`Landing` integrates over at once (a vehicle that missed ticks)."""


class Landing:
    """LAND's law with its memory, for one vehicle: :func:`land` plus an integral term on the
    descent rate's error (3D), so that a steady push up cannot stall a landing.

    :func:`land`'s vertical loop alone is proportional: against a steady upward disturbance ``d`` it
    descends ``d / kv`` slower than wanted, and near the ground, where it wants :data:`STILL`, any
    ``d > kv STILL`` (0.1 m/s^2 with the defaults: 1 % of g, a 1 % thrust or mass error) left the
    vehicle hovering above the ground for ever (measured: 2.4 cm up at 0.1 m/s^2, 25 cm at 0.5,
    ``tests/test_safety.py``). The integral ``bias += (kv^2 / 16) (v_want - v_z) dt``, bounded by
    ``max_accel``, removes that error; its gain puts the velocity loop's slow pole next to the zero
    the integral adds, so a descent begun at rest overshoots ``land_speed`` by under 5 %.
    2D: :func:`land` (HOLD), no memory. Make one when LAND begins; ``t`` is the caller's tick time."""

    def __init__(self, kp: float, kv: float, max_accel: float, land_speed: float, ground: float):
        self.kp, self.kv, self.max_accel, self.land_speed, self.ground = kp, kv, max_accel, land_speed, ground
        self.bias = 0.0
        """The integral term [m/s^2] added to the vertical command (finite, at most ``max_accel``)."""
        self._t: float | None = None

    def command(self, t: float, p: Vec, v: Vec, p_hold: Vec) -> list[float]:
        """LAND's command at tick time ``t`` [s] (finite, norm at most ``max_accel``)."""
        if len(p) >= 3:
            dt = 0.0 if self._t is None else min(max(t - self._t, 0.0), MAX_STEP)
            self._t = t
            err = descent_rate(p, self.kv, self.land_speed, self.ground) - float(v[-1])
            bias = self.bias + (self.kv * self.kv / 16.0) * err * dt
            if math.isfinite(bias):  # a non-finite measurement leaves the memory as it was
                self.bias = min(self.max_accel, max(-self.max_accel, bias))
        return land(p, v, p_hold, self.kp, self.kv, self.max_accel, self.land_speed, self.ground, self.bias)


def landed(p: Vec, v: Vec, ground: float, held: float = 0.0, settle: float = math.inf) -> bool:
    """On the ground and settled (3D), or, in 2D, still or in LAND for ``held >= settle`` seconds.

    2D has no ground to end a landing, and HOLD's law (a spring and a damper about ``p_hold``) does
    not cancel a steady sway: under the cable's sinusoidal pull a holding vehicle moves at
    ``|d| w / |kp - w^2 + j kv w|`` for ever (0.1-0.3 m/s on ``section4``), never below
    :data:`STILL`. ``settle`` bounds how long a 2D landing lasts (``safety.land_settle``); in 3D
    nothing but the ground ends it (a timeout must never disarm a vehicle in the air)."""
    three = len(p) >= 3
    return settled(norm(v), float(p[-1] - ground) if three else 0.0, held, settle, three)


def settled(speed: float, height: float, held: float, settle: float, three: bool) -> bool:
    """:func:`landed` of a vehicle at ``speed`` [m/s] (infinite if not finite), ``height`` [m] above
    the ground (3D; unused in 2D), in LAND for ``held`` [s]. Scalars: the in-process engine
    compiles this very function."""
    if not three:
        return speed < STILL or held >= settle
    return height <= TOUCHDOWN and speed < 2 * STILL


def why_landed(p: Vec, v: Vec, held: float) -> str:
    """The reason :func:`landed` gives for a vehicle that has been in LAND ``held`` seconds."""
    return why_settled(norm(v), held, len(p) >= 3)


def why_settled(speed: float, held: float, three: bool) -> str:
    """:func:`why_landed` of a vehicle at ``speed`` [m/s] (infinite if not finite), in LAND for ``held`` [s]."""
    if three:
        return "touched down"
    if speed < STILL:
        return "still"
    return f"landing held {held:.2f} s (land_settle), still moving at {speed:.2g} m/s: stopped"


def stopping_distance(speed: float, kp: float, max_accel: float) -> float:
    """How far ahead [m] of a vehicle at ``speed`` [m/s] HOLD's law must anchor it for the vehicle to
    come to rest there without turning back. For the linear law ``u = -kv v - kp e`` with the
    default, critically damped gains (``kv^2 = 4 kp``, natural frequency ``wn = sqrt(kp)``), the
    error ``e(t) = -(speed/wn) e^(-wn t)`` from ``e0 = -speed/wn`` decays without a sign change, at
    an initial deceleration of ``wn speed``; above ``max_accel / wn`` the brake is saturated at
    ``max_accel`` until the speed falls to it. Other gains keep ``wn = sqrt(kp)`` (an
    under-damped HOLD overshoots whatever its anchor)."""
    wn = math.sqrt(kp)
    knee = max_accel / wn
    if speed <= knee:
        return speed / wn
    return (speed * speed - knee * knee) / (2.0 * max_accel) + knee / wn


def hold_point(p: Vec, v: Vec, kp: float, max_accel: float, floor: float | None = None) -> list[float]:
    """Where HOLD anchors a vehicle at ``p`` [m] moving at ``v`` [m/s]: ``p`` plus
    :func:`stopping_distance` along ``v``; 3D (``floor`` given): never below ``floor`` [m]. A
    vehicle at rest, or a velocity that is not finite, anchors where it is."""
    p = floats(p)
    speed = norm(v)
    scale = hold_reach(speed, stopping_distance(speed, kp, max_accel))
    if scale != scale:
        return list(p)
    out = [anchor_axis(pc, vc, scale) for pc, vc in zip(p, v)]
    if floor is not None:
        out[-1] = floored(p[-1], out[-1], floor)
    return out


def hold_reach(speed: float, stop: float) -> float:
    """How far ahead :func:`hold_point` anchors a vehicle at ``speed`` [m/s], per m/s of its
    velocity [s]: its :func:`stopping_distance` ``stop`` [m] over ``speed``; NaN where it anchors
    where it is (at rest, or a speed not finite). Scalars: the in-process engine compiles this very
    function (and :func:`stopping_distance`)."""
    if not (speed > 0.0 and math.isfinite(speed)):
        return math.nan
    return stop / speed


def anchor_axis(p: float, v: float, scale: float) -> float:
    """:func:`hold_point` on one axis: ``p + v scale`` [m] (``scale`` from :func:`hold_reach`)."""
    return p + v * scale


def floored(p: float, out: float, floor: float) -> float:
    """:func:`hold_point`'s last axis (3D, up), ``out`` [m], kept at or above ``floor`` [m]: a
    vehicle at ``p`` above the floor anchors no lower than it, one already below where it is."""
    if out < floor:
        return floor if p >= floor else p
    return out


def braking_distance(speed: float, kv: float, max_accel: float) -> float:
    """How far [m] a vehicle at ``speed`` [m/s] travels once HOLD brakes: HOLD's brake settles
    within about ``1/kv`` seconds of travel at the current speed, more when it is saturated at
    ``max_accel``: ``speed / kv + speed^2 / (2 max_accel)``."""
    return speed / kv + speed * speed / (2.0 * max_accel)


def fence_breach(p: Vec, v: Vec, lo: Vec, hi: Vec, kv: float, max_accel: float) -> str | None:
    """Why ``p`` [m] moving at ``v`` [m/s] breaches the box ``[lo, hi]`` [m]: ``"outside"`` (the
    position is not in it: a non-finite position is not), ``"would leave the box braking from
    here"`` (the position plus :func:`braking_distance` along the velocity is not), else None."""
    speed = norm(v)
    reach = braking_distance(speed, kv, max_accel)
    ahead = [pc + (vc / speed) * reach for pc, vc in zip(p, v)] if speed > 0 and math.isfinite(reach) else None
    if not all(a <= x <= b for x, a, b in zip(p, lo, hi)):
        return "outside"
    if ahead is not None and not all(a <= x <= b for x, a, b in zip(ahead, lo, hi)):
        return "would leave the box braking from here"
    return None


def inside(p: Vec, lo: Vec, hi: Vec) -> list[float]:
    """``p`` [m] brought into the box ``[lo, hi]`` (each axis clamped): the nearest point of it."""
    return [min(max(float(x), a), b) for x, a, b in zip(p, lo, hi)]
