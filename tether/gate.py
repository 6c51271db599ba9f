"""The plausibility gate in front of the law. Pure: no I/O, no clock.

Every sample an agent takes in (its plant's, each in-neighbour's, the leader's) has already been
decoded and checked by :class:`tether.wire.Receiver` (version, type, sender id, sizes, finite
numbers). The gate then asks whether it could be true, and rejects, with a counted reason:

* ``stamp`` — its time is not its tick's (``|t - k h| > h/2``): every sender stamps ``t = k h``;
* ``future`` — (real time only) its time is more than ``future_window`` periods ahead of the
  receiver's clock (mission time), so it cannot have been measured yet. The receiver's clock, not
  its loop's progress, is the reference: a receiver that runs late must not reject what is on
  time. (In lockstep the clock source lets senders run up to its window ahead, so there is no such
  bound; the jump rule still holds);
* ``jump`` — its position is further from the sender's last accepted sample than the sender could
  have moved since: ``|p - p_ref| > max_speed |t - t_ref| + jump_margin``; before any accepted
  sample the reference is the sender's initial position from the mission at t = 0;
* ``speed`` — its velocity is beyond ``max_speed``.

Only an accepted sample newer than the last accepted one (a later ``t``) moves the reference: a
replayed old sample, which may well pass (it was true once), must not take the reference back in
time, where a forgery could then be measured against an old position with a long time to reach it.

A rejected sample is never stored, so a forged sample for an upcoming tick cannot shadow the real
one (a :class:`tether.inputs.Source` keeps the first sample of each tick): to be stored it must be
where the sender really could be. A forgery that passes is, by construction, within reach of the
truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from collections.abc import Callable
from typing import Any

from tether.mission import CrazyfliePlant, Mission, Waypoints

REASONS = ("stamp", "future", "jump", "speed")


def initial_positions(m: Mission) -> dict[int, list[float]]:
    """Where each sender is at t = 0, a gate's first reference [m]: an agent's ``p0`` (raised by
    its take-off height for a Crazyflie, which takes off before tick 0), the leader's profile at 0
    (its first waypoint when it has waypoints, else its ``p0``)."""
    prof = m.leader.profile
    out = {m.leader.id: list(prof.points[0].p) if isinstance(prof, Waypoints) else list(m.leader.p0)}
    for a in m.agents:
        p = list(a.p0)
        if isinstance(a.plant, CrazyfliePlant):
            p[-1] += a.plant.takeoff_height
        out[a.id] = p
    return out


def for_sender(m: Mission, sender: int, now: Callable[[], float] | None) -> Gate:
    """The gate of ``sender``'s samples in mission ``m``; ``now``: the receiver's mission time in
    real time (None in lockstep)."""
    sf = m.safety
    return Gate(m.dt, sf.max_speed, sf.jump_margin, initial_positions(m)[sender],
                future_window=sf.future_window, now=now)


@dataclass
class Gate:
    """The gate of one input (one sender). ``check(msg)`` returns a reason to reject, or None and
    takes ``msg`` as the new reference."""

    period: float
    max_speed: float
    margin: float
    p_ref: list[float]
    """The sender's last accepted position [m] (its mission p0 until one is accepted)."""
    t_ref: float = 0.0
    future_window: int | None = None
    """Real time: the most periods a sample may be ahead of ``now()``; None: no such bound (lockstep)."""
    now: Callable[[], float] | None = None
    """Real time: the receiver's mission time [s] (its clock)."""
    rejected: dict[str, int] = field(default_factory=dict)
    accepted: int = 0
    """Samples accepted (each newer one moved the reference)."""

    def check(self, msg: Any) -> str | None:
        reason = self._reason(msg)
        if reason is None:
            if self.accepted == 0 or msg.t > self.t_ref:  # never back in time (a replay)
                self.p_ref, self.t_ref = list(msg.p), msg.t
            self.accepted += 1
        else:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1
        return reason

    def _reason(self, msg: Any) -> str | None:
        h = self.period
        if not abs(msg.t - msg.k * h) <= 0.5 * h:
            return "stamp"
        if self.now is not None and self.future_window is not None \
                and msg.t > self.now() + self.future_window * h:
            return "future"
        reach = self.max_speed * abs(msg.t - self.t_ref) + self.margin
        if not math.dist(msg.p, self.p_ref) <= reach:
            return "jump"
        if not math.hypot(*msg.vel) <= self.max_speed:
            return "speed"
        return None


def merged(gates: list[Gate]) -> dict[str, int]:
    """Rejections of several gates, summed by reason."""
    out: dict[str, int] = {}
    for g in gates:
        for reason, n in g.rejected.items():
            out[reason] = out.get(reason, 0) + n
    return out
