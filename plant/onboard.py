"""A simulated plant computed inside its agent's process (``tether run --colocate-plants``, lockstep
only). Pure: no I/O.

The same pieces as a plant process (``plant/node.py``), composed the same way: the mission's plant
model and disturbance bank (:func:`plant.build.build`: a double integrator, a point mass or a
quadrotor), ground contact and motors-off (:class:`plant.rest.Resting`), and the command watchdog
(:class:`plant.watchdog.Watchdog`), which saturates every command to ``safety.max_accel`` and
replaces a non-finite or missing one by its failsafe before the model sees it. Tick k: the
watchdog takes the agent's command of tick k-1 (the one a plant process would have received), the
model advances ``[t_{k-1}, t_k]`` with what the watchdog decided, and :meth:`Onboard.advance`
returns the measurement of tick k as the :class:`~tether.wire.PlantState` a plant process would
have published, so that the run is the same bit for bit.

A double integrator in nominal flight is stepped on plain floats, axis by axis through the same
:func:`plant.double_integrator.step` (numpy's element-wise arithmetic on one vehicle's rows costs
more than the arithmetic: a quarter of a co-located agent's tick). The first tick that is not
nominal flight (LAND, LANDED or ESTOP, or a step through the ground in 3D) hands the state over to
the general path (:meth:`plant.base.DoubleIntegratorPlant.take_over`), which flies the rest of
the run: ground contact and motors-off are :class:`plant.rest.Resting`'s alone.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from plant import base, double_integrator

from plant.build import build
from plant.rest import Resting
from plant.watchdog import NOTE_EVERY, Event, Watchdog
from tether import mission as ms
from tether import wire

log = logging.getLogger("tether")

LEAN_BLOCK = 256
"""Ticks of disturbance taken from the bank at once, as plain floats, by the plain-float path."""


def problem(m: ms.Mission, aid: int) -> str | None:
    """Why agent ``aid``'s plant cannot run inside its agent, or None."""
    if m.payload is not None:
        return "is in a [payload] world, which hosts every vehicle and the payload in one process"
    spec = m.agent(aid).plant
    if isinstance(spec, ms.CrazyfliePlant):
        return "is a crazyflie, a real vehicle: its plant process talks to it"
    return None


@dataclass
class Trust:
    """Which of one vehicle's commands its plant flies, by its command stream's conflict rule
    (:meth:`tether.inputs.Source.offer` with a :class:`tether.gate.Health`). Pure.

    * A command whose tick another, different command contests (two commands for one tick: one is
      forged, and the first to arrive is not the more likely true) is flown as **no command**: the
      watchdog goes on with the last valid one and holds after ``cmd_timeout`` if that goes on.
      Counted in :attr:`contested`; an event at the first, then at most one every
      :data:`plant.watchdog.NOTE_EVERY` with the count since.
    * While the stream is **suspect** (most of its recent commands in conflict), no command is
      trusted: the watchdog holds after ``cmd_timeout`` and lands after ``cmd_cutoff``, as if the
      agent were silent. Its start and end are events.

    A stream without conflicts (every lockstep run, every undisturbed real-time one) is flown as
    it comes."""

    contested: int = 0
    """Commands flown as none because their tick was contested."""
    suspect: bool = False
    _k: int = -1
    """Tick of the last command judged contested (one flown as none again is not counted again)."""
    _noted: float = -math.inf
    _unnoted: int = 0

    def judge(self, cmd: wire.Command | None, contested: bool, suspect: bool, t: float,
              mode: int) -> tuple[wire.Command | None, list[Event]]:
        """The command to offer the watchdog at plant tick time ``t`` [s] (None: none), and the
        events of this judgement; ``contested``: ``cmd``'s tick is (:meth:`tether.inputs.Source.is_contested`);
        ``suspect``: the stream is (:attr:`tether.gate.Health.suspect`); ``mode``: the watchdog's."""
        events: list[Event] = []
        if suspect != self.suspect:
            self.suspect = suspect
            events.append(Event(t, mode, mode, "commands mostly contested (a second sender on the key): none trusted"
                                if suspect else "commands trusted again"))
        if cmd is None:
            return None, events
        if contested:
            if cmd.k != self._k:
                self._k = cmd.k
                self.contested += 1
                self._unnoted += 1
                if t - self._noted >= NOTE_EVERY - 1e-9:
                    n, self._unnoted = self._unnoted, 0
                    what = f"command of tick {cmd.k} contested (two different commands for one tick): flown as none" \
                        if self._noted == -math.inf else \
                        f"{n} contested command{'s' if n > 1 else ''} since {self._noted:.2f} s: flown as none"
                    self._noted = t
                    events.append(Event(t, mode, mode, what))
            return None, events
        return (None if self.suspect else cmd), events


class Onboard:
    """Agent ``aid``'s simulated plant, stepped by its agent (module docstring). ``lean=False``:
    the general path from the start (the plain-float path's reference in tests)."""

    def __init__(self, m: ms.Mission, aid: int, lean: bool = True):
        why = problem(m, aid)
        if why is not None:
            raise ValueError(f"agent {aid}'s plant cannot be co-located: {why}")
        (inner,) = build(m, [aid], live=False)
        self.plant = Resting(inner, m.dim, m.safety.ground)
        self.dog = Watchdog(m.safety, m.dim, m.dt)
        self.trust = Trust()
        self.aid = aid
        self.h = m.dt
        self.seq = 0
        self._p: np.ndarray | list[float] | None = None
        self._v: np.ndarray | list[float] | None = None
        self._dim = m.dim
        self._ground = m.safety.ground
        self._last = m.steps
        self._inner = inner if lean and isinstance(inner, base.DoubleIntegratorPlant) else None
        """The double integrator while it flies on plain floats (module docstring); None after the
        hand-over, or for another model."""
        if self._inner is not None:
            s = inner.state()
            self._lean = (s.p[0].tolist(), s.v[0].tolist(), s.a[0].tolist())
            self._first = 0
            self._block: tuple[list[list[float]], ...] = ([], [], [])

    @property
    def lean(self) -> bool:
        """Whether the vehicle is stepped on plain floats (module docstring)."""
        return self._inner is not None

    @property
    def mode(self) -> int:
        """The watchdog's mode (what ``PlantState.mode`` carries)."""
        return self.dog.mode

    def advance(self, k: int, cmd: wire.Command | None, operator: str | None, contested: bool = False,
                suspect: bool = False) -> wire.PlantState:
        """The measurement of tick ``k``; for ``k > 0`` first one period with ``cmd``, the agent's
        command of tick k-1 (None: there was none; the watchdog's failsafe then flies), and the
        operator's standing order (``land``, ``estop``). ``contested``, ``suspect``: what the
        command's stream says of it, as a plant process's (:class:`Trust`; a co-located agent hands
        its command over in-process, where neither can happen). It carries the watchdog's events of
        this tick, as a plant process's would."""
        t = k * self.h
        events: list[wire.SafetyEvent] = []
        if k > 0:
            dog = self.dog
            cmd, noted = self.trust.judge(cmd, contested, suspect, t, dog.mode)
            if cmd is not None:
                dog.offer(cmd.u, cmd.t, cmd.k, k, cmd.mode)
            d = dog.step(t, self._p, self._v, operator)
            for ev in (*noted, *d.events):
                log.warning("vehicle %d: %s", self.aid, ev)
            events = [ev.wire(k, self.aid) for ev in (*noted, *d.events)]
            if self._inner is None or not self._fly(k, d.u, d.rest):
                self.plant.step(np.array([d.u]), [d.rest])
        if self._inner is not None:
            p, v, a = self._lean
            msg = wire.PlantState(sender=self.aid, seq=self.seq, k=k, t=t, p=p, vel=v, a=a, d=self._rows(k)[0],
                                  mode=self.dog.mode, events=events)
            self._p, self._v = p, v
        else:
            s = self.plant.state()
            self._p, self._v = s.p[0], s.v[0]
            msg = wire.PlantState(sender=self.aid, seq=self.seq, k=k, t=t, p=s.p[0].tolist(), vel=s.v[0].tolist(),
                                  a=s.a[0].tolist(), d=s.d[0].tolist(), mode=self.dog.mode, events=events)
        self.seq += 1
        return msg

    def _fly(self, k: int, u: list[float], mode: int) -> bool:
        """Step ``[t_{k-1}, t_k]`` on plain floats in nominal flight. Anything else (the modes that
        :class:`~plant.rest.Resting` acts on, a step that would go through the ground): hands the
        state over to the general path and returns False, nothing stepped."""
        inner = self._inner
        assert inner is not None
        p, v, a = self._lean
        if mode not in (wire.LAND, wire.LANDED, wire.ESTOP):
            _, dv, dp = self._rows(k - 1)
            h = self.h
            axes = [double_integrator.step(p[c], v[c], u[c], dv[c], dp[c], h) for c in range(self._dim)]
            if self._dim < 3 or axes[-1][0] >= self._ground:
                self._lean = ([x[0] for x in axes], [x[1] for x in axes], [x[2] for x in axes])
                return True
        inner.take_over(k - 1, [p], [v], [a])
        self._inner = None
        return False

    def _rows(self, k: int) -> tuple[list[float], list[float], list[float]]:
        """The disturbance's value at ``t_k`` and its increments over tick k, as plain floats."""
        inner = self._inner
        assert inner is not None
        r = k - self._first
        if not 0 <= r < len(self._block[0]):
            value, dv, dp = inner.bank.span(k, min(k + LEAN_BLOCK, self._last + 1))
            self._first, self._block, r = k, (value[:, 0].tolist(), dv[:, 0].tolist(), dp[:, 0].tolist()), 0
        return self._block[0][r], self._block[1][r], self._block[2][r]

    def close(self) -> None:
        self.plant.close()
