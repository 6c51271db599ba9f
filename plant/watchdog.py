"""A plant's command watchdog: what a vehicle flies when its agent's commands stop, lie, or would
take it out of its envelope. Pure (no I/O, no clock: the caller gives the time).

One :class:`Watchdog` per vehicle, stepped once per control tick with the plant's tick time, the
newest command its agent sent (and that command's stamp), the operator's last
:class:`~tether.wire.SafetyCommand` action, and the vehicle's own measurement. It answers with a
:class:`Decision`: the mode, the command to fly, and the events it noted (each with a reason).
It mirrors the Crazyflie firmware's supervisor (0.5 s: level out; 2 s: motors off), except that
after the cut-off a vehicle lands instead of falling, and it enforces the mission's envelope
(``safety.geofence``, ``max_speed``, ``max_accel``) whatever its agent says (``docs/watchdog.md``)::

    FLYING --no valid command for cmd_timeout--> HOLD --none for cmd_cutoff--> LAND --on the ground--> LANDED
      ^                                          |  (3D: touched down; 2D: still, or land_settle in LAND)
      +--------- a valid command comes back -----+
    envelope (FLYING, measured):
      speed beyond max_speed                           -> HOLD (brakes; FLYING again below 0.8 max_speed)
      would leave the geofence braking from here (the agent's command says FLYING)
                                                       -> HOLD, latched (LAND after land_after)
      outside the geofence (FLYING or HOLD)            -> 3D: LAND at the fence (about the nearest point
                                                          of the box); 2D: HOLD there, latched (LAND after
                                                          land_after); ESTOP if the fence's action is estop
    operator "land":  FLYING/HOLD -> LAND at once, never back to FLYING
    operator "estop": any mode -> ESTOP at once (motors off), terminal
    the vehicle itself says it is down (a Crazyflie's firmware has cut its motors: tumbled, crashed,
      locked): any mode -> ESTOP at once, terminal, so that its agent lands and its neighbours drop it
    the agent's own command says LANDED (its supervisor has landed it) -> LANDED (rest, disarmed);
      ESTOP -> ESTOP (motors off)
    no own measurement (a real vehicle's link is down, or its estimate is not finite): FLYING -> HOLD;
      once it is back, -> FLYING if a valid command is fresh (the agent has resumed), else -> LAND at once

* FLYING flies the agent's command, saturated to ``safety.max_accel`` (:func:`tether.failsafe.saturate`);
* HOLD flies :func:`tether.failsafe.hold` about its anchor (brake to zero velocity; a quadrotor
  levels and hovers, its inner loop flying the acceleration command): where that brake brings the
  vehicle to rest from the position and velocity HOLD began with (:meth:`Watchdog.anchor`, the
  agent supervisor's :func:`agent.safety.anchor`), so that it never turns back through the vehicle
  behind it; a landing at the geofence keeps the fence's nearest point instead;
* LAND flies :class:`tether.failsafe.Landing` down to ``safety.ground`` (about the same anchor);
* LANDED and ESTOP command zero: what the vehicle then does (rest where it touched down; motors
  off) is the plant's to model (:mod:`plant.rest`, :class:`plant.crazyflie.CrazyfliePlant`).

A command is *valid* when it has ``dim`` components, finite, of norm at most :data:`ABSURD` times
``max_accel`` (beyond that it is a corrupted number, not a strong command), its stamp is its
tick's (``|t - k h| <= h/2``, as every sender stamps ``t = k h``), its tick is no later than the
plant's own (so its stamp is at most ``h/2`` ahead of the plant's clock), it is not older than
``cmd_timeout`` (it could not keep a vehicle flying anyway), and it is newer than the last valid
one. Its *age* is the plant's tick time minus its stamp; the watchdog acts on the age of the newest
valid command, which no input can make more than ``h/2`` negative: nothing, however stamped, stops
the watchdog from firing. Every command that leaves the watchdog is finite and within ``max_accel``.

Events: every mode change; every rejected command (by reason: the first, then at most one a
second per reason, with the count since); a command at ``max_accel`` (saturated or at the limit)
for more than :data:`SATURATED_FOR` seconds, and its end; ground contact while FLYING or HOLD
(3D: the measured height at or below ``ground``, once per contact) unless the agent's own
supervisor is landing the vehicle. An event that is not a mode change has ``src == dst``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from tether import failsafe
from tether import mission as ms
from tether.vec import floats, norm
from tether.wire import ESTOP, FLYING, HOLD, LAND, LANDED, MODES, SafetyEvent

SPEED_RELEASE = 0.8
"""A vehicle held for being beyond ``max_speed`` flies its agent again once it has braked below this
share of it (and a valid command is fresh): the plant keeps the speed limit as a brake, so that an agent
catching up with its slot at full acceleration (after a partition) is slowed, not grounded; a push that
goes on is braked again each time, and the vehicle never goes beyond the limit by more than a tick of
``max_accel``."""
ABSURD = 10.0
"""A command of norm above ``ABSURD * max_accel`` is not valid (ignored, counted), not saturated."""

SATURATED_FOR = 0.1
"""A command at ``max_accel`` for longer than this [s], continuously, is an event. The law's command
reaches the limit only in a strong transient (a start far from the formation: about 0.05 s on
``exp1``'s first ticks is a few periods); five periods at 50 Hz is no longer a moment, and at
``max_accel`` = 20 m/s^2 a vehicle has then gone 10 cm further than it would at rest."""

NOTE_EVERY = 1.0
"""Rejected commands of one reason are an event at most once per this long [s] (a flood of
forgeries is one event a second, with its count, not one a sample)."""

WHY = {
    "size": "not a vector of the mission's dimension",
    "nonfinite": "not finite",
    "absurd": f"norm beyond {ABSURD:g} max_accel",
    "stamp": "its stamp is not its tick's",
    "future": "for a tick beyond the plant's own and its clock's",
    "stale": "older than cmd_timeout",
}
"""What each reason of :attr:`Watchdog.invalid` means (for the events)."""


@dataclass(frozen=True)
class Event:
    """One mode change, or (``src == dst``) one thing the watchdog noticed without changing mode."""

    t: float
    """Plant tick time of the change [s; mission time]."""
    src: int
    """Mode before (a code of :data:`tether.wire.MODES`)."""
    dst: int
    """Mode after."""
    reason: str

    def __str__(self) -> str:
        if self.src == self.dst:
            return f"{MODES[self.src]} at {self.t:.2f} s: {self.reason}"
        return f"{MODES[self.src]} -> {MODES[self.dst]} at {self.t:.2f} s: {self.reason}"

    def wire(self, k: int, vehicle: int) -> SafetyEvent:
        """As the run file keeps it: tick ``k``, reason prefixed ``plant:`` (a reader tells it from
        the agent supervisor's events)."""
        return SafetyEvent(k=k, t=self.t, vehicle=vehicle, src=self.src, dst=self.dst, reason=f"plant: {self.reason}")


@dataclass(frozen=True)
class Decision:
    """What one vehicle does over the coming period."""

    mode: int
    u: list[float]
    """The acceleration command to fly, ``d`` floats [m/s^2; world frame]: finite, norm <= max_accel
    (zero in LANDED and ESTOP)."""
    events: tuple[Event, ...] = ()
    landing: bool = False
    """The agent's own supervisor is landing the vehicle (its newest valid command says LAND) while
    the watchdog flies it: the ground ends that landing (:class:`plant.rest.Resting` rests it)."""

    @property
    def rest(self) -> int:
        """The mode the ground and the motors act on (:meth:`plant.rest.Resting.step`): LAND while
        the agent lands the vehicle, else :attr:`mode`."""
        return LAND if self.landing and self.mode == FLYING else self.mode


@dataclass
class Watchdog:
    """The command watchdog of one vehicle (see the module docstring). ``period`` [s]: the control
    period ``h`` (a command's stamp must be its tick's). ``t0`` [s]: the mission's start, which
    counts as a zero command's stamp, so that a plant flies zero for at most ``cmd_timeout`` before
    its agent's first command and then holds."""

    safety: ms.Safety
    dim: int
    period: float
    t0: float = 0.0
    mode: int = FLYING
    p_hold: list[float] | None = None
    """Where HOLD (or LAND) keeps the vehicle [m]: :meth:`anchor` of the measurement it began on, or
    the geofence's nearest point for a vehicle outside the box."""
    invalid: dict[str, int] = field(default_factory=dict)
    """Commands rejected, by reason (the keys of :data:`WHY`)."""
    garbled: int = 0
    """Ticks whose own measurement was not finite (each flown as no measurement at all)."""
    latched: str = ""
    """Why an envelope HOLD holds (``speed``, ``geofence``): no command takes it back to FLYING."""
    _u: list[float] | None = None
    _t: float = -math.inf
    _clock_t: float = -math.inf
    """Real time: the plant's clock at the newest offer [s] (how far ahead of its tick a command may be)."""
    _seq: tuple[int, float] | None = None
    _operator_land: bool = False
    _agent_mode: int = FLYING
    """The mode the newest valid command carries (its agent's supervisor's)."""
    _blind: bool = False
    """HOLD began, or went on, without a measurement."""
    _since: float = 0.0
    """Plant tick time of the last mode change [s] (how long LAND has lasted: 2D's ``land_settle``)."""
    _landing: failsafe.Landing | None = None
    """LAND's law and its memory (made at LAND's first tick; LAND is never left but for LANDED or ESTOP)."""
    _notes: list[Event] = field(default_factory=list)
    """Events noticed since the last step (rejected commands), given out with the next decision."""
    _noted: dict[str, float] = field(default_factory=dict)
    """Reason -> when its rejections were last an event [s]."""
    _unnoted: dict[str, int] = field(default_factory=dict)
    """Reason -> rejections since then."""
    _saturated: float | None = None
    """Since when [s] the command flown has been at ``max_accel`` (None: it is not)."""
    _saturation_noted: bool = False
    _touching: bool = False
    """3D: the vehicle is on the ground (at or below it) while flying: its contact was an event."""
    _down: str | None = None
    """Why the vehicle itself said it can no longer fly (latched: ESTOP for good)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"Watchdog: period = {self.period!r} s; give the control period (1 / rate)")
        self._u = [0.0] * self.dim
        self._t = self.t0

    @property
    def terminal(self) -> bool:
        """In LANDED or ESTOP: the vehicle will not fly again in this run."""
        return self.mode in (LANDED, ESTOP)

    def age(self, t: float) -> float:
        """Age of the newest valid command at ``t`` [s]."""
        return t - self._t

    def _reject(self, reason: str, t: float) -> None:
        self.invalid[reason] = self.invalid.get(reason, 0) + 1
        self._unnoted[reason] = self._unnoted.get(reason, 0) + 1
        last = self._noted.get(reason)
        if last is not None and t - last < NOTE_EVERY:
            return
        n = self._unnoted.pop(reason)
        self._noted[reason] = t
        what = f"command rejected ({reason}: {WHY[reason]})"
        if last is not None:
            what = f"{n} command{'s' if n > 1 else ''} rejected since {last:.2f} s ({reason}: {WHY[reason]})"
        self._notes.append(Event(t, self.mode, self.mode, what))

    def offer(self, u: Sequence[float] | np.ndarray | None, stamp: float, k: int, k_now: int,
              mode: int = FLYING, k_clock: int | None = None) -> bool:
        """Consider the newest command: ``u`` [m/s^2] stamped ``stamp`` [s] for tick ``k``, seen at
        the plant's tick ``k_now``, with its agent's supervisor ``mode``. Returns whether it is
        valid (and so the newest valid one). The same command offered again is neither counted nor
        taken twice.

        ``k_clock`` (real time): the tick the plant's own clock has reached. A plant that runs late
        (catching up after a stall or a partition) is behind its clock, and its agent's newest
        commands are for ticks it has not stepped yet: those up to ``k_clock`` are not ``future``,
        and are fresh until the plant's clock has run ``cmd_timeout`` past them. A stamp is still
        never kept beyond the plant's own clock, so nothing can silence the watchdog for longer
        than the plant is late."""
        self._clock_t = -math.inf if k_clock is None else k_clock * self.period
        if u is None:
            return False
        if self._seq == (k, stamp):
            return False
        self._seq = (k, stamp)
        h = self.period
        now = k_now * h
        try:
            if isinstance(u, np.ndarray) and u.shape != (self.dim,):
                raise ValueError
            ul = [float(x) for x in u]
        except (TypeError, ValueError):  # not a vector of numbers
            ul = []
        if len(ul) != self.dim:
            self._reject("size", now)
            return False
        if not (all(map(math.isfinite, ul)) and math.isfinite(stamp)):
            self._reject("nonfinite", now)
            return False
        if norm(ul) > ABSURD * self.safety.max_accel:
            self._reject("absurd", now)
            return False
        if not abs(stamp - k * h) <= 0.5 * h:
            self._reject("stamp", now)
            return False
        if k > (k_now if k_clock is None else max(k_now, k_clock)):
            self._reject("future", now)
            return False
        if now - stamp > self.safety.cmd_timeout:
            self._reject("stale", now)
            return False
        if stamp < self._t:
            return False  # older than the newest valid command (reordered)
        self._u, self._t, self._agent_mode = ul, stamp, mode
        return True

    def step(self, t: float, p: Sequence[float] | np.ndarray | None, v: Sequence[float] | np.ndarray | None,
             operator: str | None = None, down: str | None = None) -> Decision:
        """Decide the mode and command for the period starting at the plant's tick time ``t`` [s]
        from the commands offered so far, the operator's last action (``"land"``, ``"estop"`` or
        None), the measurement ``p`` [m], ``v`` [m/s] (None: the plant has none this tick; a
        measurement with a component that is not finite counts as none, and in :attr:`garbled`) and
        ``down``: why the vehicle itself says it can no longer fly (its firmware cut the motors), or
        None; once said, ESTOP for good."""
        s = self.safety
        events: list[Event] = self._notes
        self._notes = []

        def go(dst: int, reason: str) -> None:
            if dst != self.mode:
                events.append(Event(t, self.mode, dst, reason))
                self.mode = dst
                self._since = t

        if self._t > max(t, self._clock_t) + 0.5 * self.period:
            self._t = -math.inf  # a caller that offered for a later tick than it steps or its clock allows: never fresh
        pl = list(floats(p)) if p is not None else None  # its own copy: p_hold may keep it
        vl = floats(v) if v is not None else None
        garbled = pl is not None and vl is not None and not (all(map(math.isfinite, pl)) and
                                                              all(map(math.isfinite, vl)))
        if garbled:  # a diverged estimator, a corrupted log: no measurement at all, never a place to hold
            self.garbled += 1
            pl = vl = None
        measured = pl is not None and vl is not None
        blind = "own measurement not finite" if garbled else "no own measurement"
        if down is not None and self._down is None:
            self._down = down
        if operator == "estop":
            go(ESTOP, "operator estop")
        elif self._down is not None:
            go(ESTOP, f"vehicle down: {self._down}")
        elif self._agent_mode == ESTOP:
            go(ESTOP, "agent estop")
        elif self._agent_mode == LANDED and self.mode != LANDED and self.age(t) <= s.cmd_timeout:
            go(LANDED, "agent landed")
        elif operator == "land" and not self._operator_land:
            self._operator_land = True
            if self.mode in (FLYING, HOLD):
                if self.mode == FLYING and pl is not None and vl is not None:
                    self.p_hold = self.anchor(pl, vl)
                go(LAND, "operator land")
        age = self.age(t)
        if pl is not None and vl is not None and self.mode in (FLYING, HOLD):
            self._envelope(t, pl, vl, go)
        if self.mode == FLYING:
            if pl is None or vl is None:
                self._blind = True
                go(HOLD, blind)
            elif age > s.cmd_timeout:
                self.p_hold = self.anchor(pl, vl)
                go(HOLD, f"no valid command for {age:.2f} s")
        elif self.mode == HOLD:
            if pl is None or vl is None:
                self._blind = True
            elif self.latched == "speed" and norm(vl) <= SPEED_RELEASE * s.max_speed and age <= s.cmd_timeout:
                self.latched = ""  # braked well under the limit, its agent still commanding: fly it again
                go(FLYING, f"speed {norm(vl):.3g} m/s back under {SPEED_RELEASE:g} max_speed, command fresh")
            elif self.latched:
                if t - self._since >= s.land_after:
                    go(LAND, f"held for {s.land_after:g} s ({self.latched})")
            elif age <= s.cmd_timeout:
                self._blind = False
                go(FLYING, f"command back ({age:.2f} s old)")
            elif self._blind:  # the measurement is back but the agent is not: land now
                self._blind = False
                self.p_hold = self.anchor(pl, vl)
                go(LAND, f"measurement back, no valid command for {age:.2f} s")
            elif age >= s.cmd_cutoff:
                go(LAND, f"no valid command for {age:.2f} s")
        if self.mode in (HOLD, LAND) and self.p_hold is None and pl is not None and vl is not None:
            self.p_hold = self.anchor(pl, vl)  # HOLD began without a measurement
        if self.mode == LAND and pl is not None and vl is not None and \
                failsafe.landed(pl, vl, s.ground, t - self._since, s.land_settle):
            go(LANDED, "on the ground" if self.dim == 3 else failsafe.why_landed(pl, vl, t - self._since))
        if pl is not None:
            self._ground(t, pl, events)
        u: list[float] | None
        if self.mode == FLYING:
            u = failsafe.saturate(self._u, s.max_accel) if self._u is not None else None
            u = [0.0] * self.dim if u is None else u
            self._saturation(t, u, events)
        elif self.mode in (HOLD, LAND) and pl is not None and vl is not None:
            at = self.p_hold if self.p_hold is not None else pl  # set just above when measured
            if self.mode == HOLD:
                u = failsafe.hold(pl, vl, at, s.hold_kp, s.hold_kv, s.max_accel)
            else:
                if self._landing is None:
                    self._landing = failsafe.Landing(s.hold_kp, s.hold_kv, s.max_accel, s.land_speed, s.ground)
                u = self._landing.command(t, pl, vl, at)
        else:
            u = [0.0] * self.dim
        if self.mode != FLYING:
            self._saturation(t, None, events)
        return Decision(self.mode, u, tuple(events), landing=self._agent_mode == LAND)

    def anchor(self, p: list[float], v: list[float]) -> list[float]:
        """Where HOLD and LAND keep a vehicle that begins them at ``p`` [m] moving at ``v`` [m/s]:
        where their brake brings it to rest (:func:`tether.failsafe.hold_point`; 3D: never below
        ``ground``); where that point is outside the geofence box, ``p`` brought into the box (the
        fence's prediction keeps a vehicle braking about ``p`` inside). The agent's supervisor
        computes the same point (:func:`agent.safety.anchor`)."""
        s = self.safety
        out = failsafe.hold_point(p, v, s.hold_kp, s.max_accel, s.ground if self.dim >= 3 else None)
        fence = s.geofence
        if fence is None or all(lo <= x <= hi for x, lo, hi in zip(out, fence.min, fence.max)):
            return out
        return failsafe.inside(p, fence.min, fence.max)

    def _envelope(self, t: float, p: list[float], v: list[float], go: Callable[[int, str], None]) -> None:
        """The mission's envelope, FLYING or HOLD, measured (module docstring)."""
        s = self.safety
        fence = s.geofence
        breach = None if fence is None else failsafe.fence_breach(p, v, fence.min, fence.max, s.hold_kv, s.max_accel)
        if fence is not None and breach == "outside" and (self.dim == 3 or self.latched != "geofence"):
            self.p_hold = failsafe.inside(p, fence.min, fence.max)
            where = ", ".join(f"{x:.2f}" for x in p)
            if fence.action == "estop":
                go(ESTOP, f"geofence: outside at ({where})")
            elif self.dim == 3:
                go(LAND, f"geofence: outside at ({where}), landing at the fence")
            else:  # 2D LAND ends when still, which a vehicle braking back is at its turn: hold there first
                self.latched = "geofence"
                go(HOLD, f"geofence: outside at ({where}), holding at the fence")
            return
        if self.mode != FLYING:
            return
        speed = norm(v)
        if speed > s.max_speed:
            self.p_hold, self.latched = self.anchor(p, v), "speed"
            go(HOLD, f"speed {speed:.3g} m/s beyond max_speed {s.max_speed:g} m/s")
        elif breach is not None and self._agent_mode == FLYING:
            self.p_hold, self.latched = self.anchor(p, v), "geofence"
            go(HOLD, f"geofence: {breach} ({speed:.3g} m/s)")

    def _saturation(self, t: float, u: list[float] | None, events: list[Event]) -> None:
        """Note a command flown at ``max_accel`` for more than :data:`SATURATED_FOR`, and its end
        (``u``: the command flown in FLYING; None: not FLYING)."""
        raw = norm(self._u) if self._u is not None and u is not None else 0.0
        at_limit = raw >= self.safety.max_accel * (1.0 - 1e-9)  # the agent's own saturation rounds to about it
        if at_limit:
            if self._saturated is None:
                self._saturated = t
            elif not self._saturation_noted and t - self._saturated > SATURATED_FOR + 1e-9:
                self._saturation_noted = True
                events.append(Event(t, self.mode, self.mode, f"command at max_accel {self.safety.max_accel:g} m/s^2 "
                                    f"for {t - self._saturated:.2f} s (asked {raw:.3g} m/s^2)"))
            return
        if self._saturated is not None and self._saturation_noted:
            events.append(Event(t, self.mode, self.mode,
                                f"command back under max_accel after {t - self._saturated:.2f} s at it"))
        self._saturated, self._saturation_noted = None, False

    def _ground(self, t: float, p: list[float], events: list[Event]) -> None:
        """3D: note ground contact while FLYING or HOLD, once per contact (re-armed once the vehicle
        is :data:`tether.failsafe.TOUCHDOWN` above the ground), unless its agent is landing it."""
        if self.dim < 3:
            return
        z, ground = p[-1], self.safety.ground
        if z <= ground and not self._touching:
            self._touching = True
            if self.mode in (FLYING, HOLD) and self._agent_mode not in (LAND, LANDED):
                events.append(Event(t, self.mode, self.mode,
                                    f"ground contact while {MODES[self.mode]} (z = {z:.3f} m): downward motion stopped"))
        elif z > ground + failsafe.TOUCHDOWN:
            self._touching = False
