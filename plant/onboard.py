"""A simulated plant computed inside its agent's process (``tether run --colocate-plants``, lockstep
only). Pure: no I/O.

The same pieces as a plant process (``plant/node.py``), composed the same way: the mission's plant
model and disturbance bank (:func:`plant.base.build`: a double integrator, a point mass or a
quadrotor), ground contact and motors-off (:class:`plant.rest.Resting`), and the command watchdog
(:class:`plant.watchdog.Watchdog`), which saturates every command to ``safety.max_accel`` and
replaces a non-finite or missing one by its failsafe before the model sees it. Tick k: the
watchdog takes the agent's command of tick k-1 (the one a plant process would have received), the
model advances ``[t_{k-1}, t_k]`` with what the watchdog decided, and :meth:`Onboard.advance`
returns the measurement of tick k as the :class:`~tether.wire.PlantState` a plant process would
have published, so that the run is the same bit for bit.
"""

from __future__ import annotations

import logging

import numpy as np

from plant import base
from plant.rest import Resting
from plant.watchdog import Watchdog
from tether import mission as ms
from tether import wire

log = logging.getLogger("tether")


def problem(m: ms.Mission, aid: int) -> str | None:
    """Why agent ``aid``'s plant cannot run inside its agent, or None."""
    if m.payload is not None:
        return "is in a [payload] world, which hosts every vehicle and the payload in one process"
    spec = m.agent(aid).plant
    if isinstance(spec, ms.CrazyfliePlant):
        return "is a crazyflie, a real vehicle: its plant process talks to it"
    return None


class Onboard:
    """Agent ``aid``'s simulated plant, stepped by its agent (module docstring)."""

    def __init__(self, m: ms.Mission, aid: int):
        why = problem(m, aid)
        if why is not None:
            raise ValueError(f"agent {aid}'s plant cannot be co-located: {why}")
        (inner,) = base.build(m, [aid], live=False)
        self.plant = Resting(inner, m.dim, m.safety.ground)
        self.dog = Watchdog(m.safety, m.dim)
        self.aid = aid
        self.h = m.dt
        self.seq = 0
        self._p: np.ndarray | None = None
        self._v: np.ndarray | None = None

    @property
    def mode(self) -> int:
        """The watchdog's mode (what ``PlantState.mode`` carries)."""
        return self.dog.mode

    def advance(self, k: int, cmd: wire.Command | None, operator: str | None) -> wire.PlantState:
        """The measurement of tick ``k``; for ``k > 0`` first one period with ``cmd``, the agent's
        command of tick k-1 (None: there was none; the watchdog's failsafe then flies), and the
        operator's standing order (``land``, ``estop``)."""
        t = k * self.h
        if k > 0:
            dog = self.dog
            if cmd is not None:
                dog.offer(cmd.u, cmd.t, cmd.k, k, cmd.mode)
            d = dog.step(t, self._p, self._v, operator)
            for ev in d.events:
                log.warning("vehicle %d: %s", self.aid, ev)
            self.plant.step(np.array([d.u]), [d.mode])
        s = self.plant.state()
        self._p, self._v = s.p[0], s.v[0]
        msg = wire.PlantState(sender=self.aid, seq=self.seq, k=k, t=t, p=s.p[0].tolist(), vel=s.v[0].tolist(),
                              a=s.a[0].tolist(), d=s.d[0].tolist(), mode=self.dog.mode)
        self.seq += 1
        return msg

    def close(self) -> None:
        self.plant.close()
