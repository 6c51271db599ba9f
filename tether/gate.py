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
* ``speed`` — its velocity is beyond ``max_speed``;
* ``profile`` — (the leader's samples, whose profile the mission defines) its position, velocity or
  acceleration departs from the profile at the sample's own time by more than ``profile_margin``
  (a distance in each unit: m, m/s, m/s^2). The leader publishes the profile itself, at ``t = k h``,
  and a receiver evaluates the same closed forms (:func:`leader.profile.scalar`): the genuine
  departure is rounding (0 on every shipped mission), and the network delays a sample, never changes
  it. The margin (1 cm by default) is therefore not a noise allowance: it bounds what a forgery that
  passes can move the formation by.

Beyond single samples, a stream is judged over a sliding window (:class:`Health`): a stream whose
recent samples are mostly rejected, or conflict with what the same sender said for the same tick,
is *suspect* (a forgery beside the genuine stream, or a faulty sensor), and the agent's supervisor
treats it as a lost input (``docs/safety.md``). A plant's report of its own mode is believed only as
far as its samples agree (:class:`PlantModes`).

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
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tether.mission import CrazyfliePlant, Mission, Waypoints
from tether.wire import ESTOP, FLYING, LAND, LANDED

REASONS = ("stamp", "future", "jump", "speed", "profile")

Expected = Callable[[float], tuple[Sequence[float], Sequence[float], Sequence[float]]]
"""A sender's position [m], velocity [m/s] and acceleration [m/s^2] at a time [s] (the leader's profile)."""


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


def for_sender(m: Mission, sender: int, now: Callable[[], float] | None, expect: Expected | None = None) -> Gate:
    """The gate of ``sender``'s samples in mission ``m``; ``now``: the receiver's mission time in
    real time (None in lockstep); ``expect``: what the sender publishes at a time, when that is known
    (the leader's profile, :func:`leader.profile.scalar`)."""
    sf = m.safety
    return Gate(m.dt, sf.max_speed, sf.jump_margin, initial_positions(m)[sender],
                future_window=sf.future_window, now=now, expect=expect, profile_margin=sf.profile_margin)


def health_of(m: Mission) -> Health:
    """A stream's sliding-window judge with the mission's ``[safety]`` settings."""
    return Health(m.safety.suspect_window, m.safety.suspect_share)


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
    expect: Expected | None = None
    """What the sender publishes at a time (the leader's profile); None: not known."""
    profile_margin: float = 0.0
    """The largest departure from ``expect`` accepted [m; m/s; m/s^2]."""
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
        if self.expect is not None:
            p, v, a = self.expect(msg.t)
            tol = self.profile_margin
            if not (math.dist(msg.p, p) <= tol and math.dist(msg.vel, v) <= tol and math.dist(msg.a, a) <= tol):
                return "profile"
        return None


@dataclass
class Health:
    """One stream's sliding window: of the last ``window`` verdicts (one for every sample offered
    that decoded, and one more for each contested tick), how many were bad (rejected by the gate,
    in conflict with what the sender already said, or the held sample of a tick that another sample
    contests: :attr:`tether.inputs.Source.contested`). A forger sending one copy beside each genuine
    sample thus makes two thirds of the window bad, well past ``share``; the genuine stream alone
    makes none.

    The stream becomes :attr:`suspect` when at least ``share`` of a full window is bad
    (``ceil(share window)`` samples), and clears when at most half that share is (hysteresis: a
    forgery that keeps the share near the threshold cannot make the verdict flap). Before ``window``
    samples have been offered, the count is still taken against the full window, so a stream's first
    rejected samples alone do not make it suspect."""

    window: int
    share: float
    outcomes: deque[bool] = field(default_factory=deque)
    bad: int = 0
    suspect: bool = False

    def note(self, bad: bool) -> bool:
        """Count one sample; True when :attr:`suspect` changed with it."""
        self.outcomes.append(bad)
        self.bad += bad
        if len(self.outcomes) > self.window:
            self.bad -= self.outcomes.popleft()
        was = self.suspect
        if not was and self.bad >= math.ceil(self.share * self.window):
            self.suspect = True
        elif was and self.bad <= math.floor(self.share * self.window / 2):
            self.suspect = False
        return self.suspect != was

    def reset(self) -> None:
        self.outcomes.clear()
        self.bad = 0
        self.suspect = False


TERMINAL = (LAND, LANDED, ESTOP)
"""A plant's watchdog modes it never leaves for FLYING (``plant/watchdog.py``)."""


@dataclass
class PlantModes:
    """A plant's report of its own mode, believed only as far as its samples agree: a mode other
    than FLYING is believed once ``confirm`` samples of consecutive ticks say it, and a report of
    LAND, LANDED or ESTOP followed by a FLYING one is a contradiction (the watchdog never flies
    again after those), so that report is not believed. Fed the plant's accepted samples in arrival
    order; pure."""

    confirm: int
    believed: int = FLYING
    """The mode believed (a code of :data:`tether.wire.MODES`)."""
    contradictions: int = 0
    _mode: int = FLYING
    _run: int = 0
    _k: int = -1

    def observe(self, k: int, mode: int) -> bool:
        """Take the mode of the plant's sample of tick ``k``; False if it contradicts what the plant
        said before (the caller counts it as a conflict)."""
        if k <= self._k and mode == self._mode:
            return True  # a copy, or a late sample of the same run: nothing new
        ok = not (mode == FLYING and (self._mode in TERMINAL or self.believed in TERMINAL))
        if not ok:
            self.contradictions += 1
        if self.believed in TERMINAL:
            return ok  # believed already: a vehicle that stopped flying is not flown again on a report
        if mode == self._mode and k == self._k + 1:
            self._run += 1
        elif k > self._k or mode != self._mode:
            self._mode, self._run = mode, 1
        self._k = max(self._k, k)
        if self._run >= self.confirm or mode == FLYING:
            self.believed = self._mode
        return ok


def merged(gates: list[Gate]) -> dict[str, int]:
    """Rejections of several gates, summed by reason."""
    out: dict[str, int] = {}
    for g in gates:
        for reason, n in g.rejected.items():
            out[reason] = out.get(reason, 0) + n
    return out
