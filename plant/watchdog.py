"""A plant's command watchdog: what a vehicle flies when its agent's commands stop. Pure (no I/O,
no clock: the caller gives the time).

One :class:`Watchdog` per vehicle, stepped once per control tick with the plant's tick time, the
newest command its agent sent (and that command's stamp), the operator's last
:class:`~tether.wire.SafetyCommand` action, and the vehicle's own measurement. It answers with a
:class:`Decision`: the mode, the command to fly, and the mode changes it made (each with a reason).
It mirrors the Crazyflie firmware's supervisor (0.5 s: level out; 2 s: motors off), except that
after the cut-off a vehicle lands instead of falling (``docs/watchdog.md``)::

    FLYING --no valid command for cmd_timeout--> HOLD --none for cmd_cutoff--> LAND --on the ground--> LANDED
      ^                                          |  (3D: touched down; 2D: still, or land_settle in LAND)
      +--------- a valid command comes back -----+
    operator "land":  FLYING/HOLD -> LAND at once, never back to FLYING
    operator "estop": any mode -> ESTOP at once (motors off), terminal
    the agent's own command says LANDED (its supervisor has landed it) -> LANDED (rest, disarmed);
      ESTOP -> ESTOP (motors off)
    no own measurement (a real vehicle's link is down, or its estimate is not finite): FLYING -> HOLD;
      once it is back, -> FLYING if a valid command is fresh (the agent has resumed), else -> LAND at once

* FLYING flies the agent's command, saturated to ``safety.max_accel`` (:func:`tether.failsafe.saturate`);
* HOLD flies :func:`tether.failsafe.hold` about the position where HOLD began (brake to zero
  velocity; a quadrotor levels and hovers, its inner loop flying the acceleration command);
* LAND flies :class:`tether.failsafe.Landing` down to ``safety.ground`` (about the same horizontal position);
* LANDED and ESTOP command zero: what the vehicle then does (rest where it touched down; motors
  off) is the plant's to model (:mod:`plant.rest`, :class:`plant.crazyflie.CrazyfliePlant`).

A command is *valid* when it is finite, its norm is at most :data:`ABSURD` times ``max_accel``
(beyond that it is a corrupted number, not a strong command), it is for a tick no later than the
plant's own, and it is newer than the last valid one. Its *age* is the plant's tick time minus
the command's stamp; the watchdog acts on the age of the newest valid command. Every command that
leaves the watchdog is finite and within ``max_accel``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from tether import failsafe
from tether import mission as ms
from tether.vec import floats, norm
from tether.wire import ESTOP, FLYING, HOLD, LAND, LANDED, MODES

ABSURD = 10.0
"""A command of norm above ``ABSURD * max_accel`` is not valid (ignored, counted), not saturated."""


@dataclass(frozen=True)
class Event:
    """One mode change."""

    t: float
    """Plant tick time of the change [s; mission time]."""
    src: int
    """Mode before (a code of :data:`tether.wire.MODES`)."""
    dst: int
    """Mode after."""
    reason: str

    def __str__(self) -> str:
        return f"{MODES[self.src]} -> {MODES[self.dst]} at {self.t:.2f} s: {self.reason}"


@dataclass(frozen=True)
class Decision:
    """What one vehicle does over the coming period."""

    mode: int
    u: list[float]
    """The acceleration command to fly, ``d`` floats [m/s^2; world frame]: finite, norm <= max_accel
    (zero in LANDED and ESTOP)."""
    events: tuple[Event, ...] = ()


@dataclass
class Watchdog:
    """The command watchdog of one vehicle (see the module docstring). ``t0`` [s]: the mission's
    start, which counts as a zero command's stamp, so that a plant flies zero for at most
    ``cmd_timeout`` before its agent's first command and then holds."""

    safety: ms.Safety
    dim: int
    t0: float = 0.0
    mode: int = FLYING
    p_hold: list[float] | None = None
    """Where HOLD (or LAND) began [m], the position it keeps."""
    invalid: dict[str, int] = field(default_factory=dict)
    """Commands rejected, by reason (``nonfinite``, ``absurd``, ``future``, ``size``)."""
    garbled: int = 0
    """Ticks whose own measurement was not finite (each flown as no measurement at all)."""
    _u: list[float] | None = None
    _t: float = -math.inf
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

    def __post_init__(self) -> None:
        self._u = [0.0] * self.dim
        self._t = self.t0

    @property
    def terminal(self) -> bool:
        """In LANDED or ESTOP: the vehicle will not fly again in this run."""
        return self.mode in (LANDED, ESTOP)

    def age(self, t: float) -> float:
        """Age of the newest valid command at ``t`` [s]."""
        return t - self._t

    def _reject(self, reason: str) -> None:
        self.invalid[reason] = self.invalid.get(reason, 0) + 1

    def offer(self, u: Sequence[float] | np.ndarray | None, stamp: float, k: int, k_now: int,
              mode: int = FLYING) -> bool:
        """Consider the newest command: ``u`` [m/s^2] stamped ``stamp`` [s] for tick ``k``, seen at
        the plant's tick ``k_now``, with its agent's supervisor ``mode``. Returns whether it is valid (and so the newest valid one). The
        same command offered again is neither counted nor taken twice."""
        if u is None:
            return False
        if self._seq == (k, stamp):
            return False
        self._seq = (k, stamp)
        try:
            if isinstance(u, np.ndarray) and u.shape != (self.dim,):
                raise ValueError
            ul = [float(x) for x in u]
        except (TypeError, ValueError):  # not a vector of numbers
            ul = []
        if len(ul) != self.dim:
            self._reject("size")
            return False
        if not (all(map(math.isfinite, ul)) and math.isfinite(stamp)):
            self._reject("nonfinite")
            return False
        if norm(ul) > ABSURD * self.safety.max_accel:
            self._reject("absurd")
            return False
        if k > k_now:
            self._reject("future")
            return False
        if stamp < self._t:
            return False  # older than the newest valid command (reordered)
        self._u, self._t, self._agent_mode = ul, stamp, mode
        return True

    def step(self, t: float, p: Sequence[float] | np.ndarray | None, v: Sequence[float] | np.ndarray | None,
             operator: str | None = None) -> Decision:
        """Decide the mode and command for the period starting at the plant's tick time ``t`` [s]
        from the commands offered so far, the operator's last action (``"land"``, ``"estop"`` or
        None) and the measurement ``p`` [m], ``v`` [m/s] (None: the plant has none this tick; a
        measurement with a component that is not finite counts as none, and in :attr:`garbled`)."""
        s = self.safety
        events: list[Event] = []

        def go(dst: int, reason: str) -> None:
            if dst != self.mode:
                events.append(Event(t, self.mode, dst, reason))
                self.mode = dst
                self._since = t

        pl = list(floats(p)) if p is not None else None  # its own copy: p_hold may keep it
        vl = floats(v) if v is not None else None
        garbled = pl is not None and vl is not None and not (all(map(math.isfinite, pl)) and
                                                              all(map(math.isfinite, vl)))
        if garbled:  # a diverged estimator, a corrupted log: no measurement at all, never a place to hold
            self.garbled += 1
            pl = vl = None
        measured = pl is not None and vl is not None
        blind = "own measurement not finite" if garbled else "no own measurement"
        if operator == "estop":
            go(ESTOP, "operator estop")
        elif self._agent_mode == ESTOP:
            go(ESTOP, "agent estop")
        elif self._agent_mode == LANDED and self.mode != LANDED and self.age(t) <= s.cmd_timeout:
            go(LANDED, "agent landed")
        elif operator == "land" and not self._operator_land:
            self._operator_land = True
            if self.mode in (FLYING, HOLD):
                if self.mode == FLYING and measured:
                    self.p_hold = pl
                go(LAND, "operator land")
        age = self.age(t)
        if self.mode == FLYING:
            if not measured:
                self._blind = True
                go(HOLD, blind)
            elif age > s.cmd_timeout:
                self.p_hold = pl
                go(HOLD, f"no valid command for {age:.2f} s")
        elif self.mode == HOLD:
            if not measured:
                self._blind = True
            elif age <= s.cmd_timeout:
                self._blind = False
                go(FLYING, f"command back ({age:.2f} s old)")
            elif self._blind:  # the measurement is back but the agent is not: land now
                self._blind = False
                self.p_hold = pl
                go(LAND, f"measurement back, no valid command for {age:.2f} s")
            elif age >= s.cmd_cutoff:
                go(LAND, f"no valid command for {age:.2f} s")
        if self.mode in (HOLD, LAND) and self.p_hold is None and measured:
            self.p_hold = pl  # HOLD began without a measurement
        if self.mode == LAND and pl is not None and vl is not None and \
                failsafe.landed(pl, vl, s.ground, t - self._since, s.land_settle):
            go(LANDED, "on the ground" if self.dim == 3 else failsafe.why_landed(pl, vl, t - self._since))
        u: list[float] | None
        if self.mode == FLYING:
            u = failsafe.saturate(self._u, s.max_accel) if self._u is not None else None
            u = [0.0] * self.dim if u is None else u
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
        return Decision(self.mode, u, tuple(events))

