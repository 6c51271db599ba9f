"""Positions from a motion-capture system, sent to a Crazyflie as external position (``extpos``), so
that its onboard Kalman estimator fuses them and ``stateEstimate.*`` carries the result.

The motion-capture system is reached through the `motioncapture` package (libmotioncapture:
``vicon``, ``optitrack``, ``qualisys``, ``vrpn``, ``motionanalysis``, and ``mock`` for tests and
dry runs): ``motioncapture.connect(backend, {"hostname": ...})`` and ``waitForNextFrame()``, which
blocks until the next frame; each frame has ``rigidBodies``, a mapping from a rigid body's name to
its position [m; the capture system's world frame, z up] and attitude.

:func:`checked_position` (pure) decides whether a rigid body's position may be sent: a body missing
from the frame, a non-finite position, or one outside the arena's bounds is not sent (counted by
the feed), so a vehicle never fuses a wild measurement; its estimator's variance then grows and the
pre-flight check (:mod:`plant.preflight`) or the link watchdog notices. :class:`MocapFeed` is the thin
adapter: one daemon thread reads frames and hands each vehicle's position to a ``send`` callable
(``cf.extpos.send_extpos(x, y, z)``: the unpacked form, one vehicle per link; the packed form, several vehicles
in one broadcast packet, needs a broadcast link the plant does not own).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tether.fleet import BACKENDS

log = logging.getLogger("tether")

@dataclass(frozen=True)
class Bounds:
    """The arena: positions outside are not sent [m; world frame]."""

    lo: tuple[float, float, float] = (-10.0, -10.0, -0.5)
    hi: tuple[float, float, float] = (10.0, 10.0, 5.0)


def checked_position(bodies: Mapping[str, Any], name: str, bounds: Bounds) -> np.ndarray | None:
    """The position [m] of rigid body ``name`` in a frame's ``bodies`` (values with a ``position``
    of three numbers), or None if it is missing, non-finite or outside ``bounds``. Pure."""
    body = bodies.get(name)
    if body is None:
        return None
    p = np.asarray(body.position, dtype=float).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        return None
    if np.any(p < np.asarray(bounds.lo)) or np.any(p > np.asarray(bounds.hi)):
        return None
    return p


@dataclass
class FeedStats:
    """What a feed did, per rigid body name (read from other threads: plain counters, monotonic)."""

    sent: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)
    """Frames in which the body was missing, non-finite or out of bounds."""
    last_sent: dict[str, float] = field(default_factory=dict)
    """``time.monotonic()`` of the last position sent."""


class MocapFeed:
    """One motion-capture connection feeding positions to vehicles. ``with MocapFeed(...) as feed``
    starts its thread on entry and stops it on exit (the thread ends after the frame it waits for).

    ``bindings``: ``(rigid body name, send)`` pairs, ``send`` taking a position [m] (3,); it is called
    from the feed's thread and must only hand off (cflib's ``send_extpos`` queues a packet).
    ``period``: the smallest time [s] between two sends to one body (a 300 Hz system need not fill a
    100 Hz radio link).
    """

    def __init__(self, backend: str, hostname: str, bindings: Sequence[tuple[str, Callable[[np.ndarray], None]]],
                 bounds: Bounds | None = None, period: float = 0.01, options: Mapping[str, str] | None = None) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"backend {backend!r}: give one of {', '.join(BACKENDS)}")
        if not (math.isfinite(period) and period >= 0.0):
            raise ValueError(f"period {period!r}: give a number of seconds >= 0")
        self.backend, self.hostname = backend, hostname
        self.bindings = tuple(bindings)
        self.bounds = bounds if bounds is not None else Bounds()
        self.period = period
        self.options = dict(options or {})
        self.stats = FeedStats()
        self.error: str | None = None
        """Why the feed's thread ended early (the connection failed or broke), if it did."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> "MocapFeed":
        import motioncapture

        opts = {"hostname": self.hostname, **self.options}
        mc = motioncapture.connect(self.backend, opts)  # blocks while connecting
        self._thread = threading.Thread(target=self._run, args=(mc,), name="tether-mocap", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(1.0)

    def _run(self, mc: Any) -> None:
        stats = self.stats
        try:
            while not self._stop.is_set():
                mc.waitForNextFrame()
                bodies = mc.rigidBodies
                now = time.monotonic()
                for name, send in self.bindings:
                    p = checked_position(bodies, name, self.bounds)
                    if p is None:
                        stats.refused[name] = stats.refused.get(name, 0) + 1
                        continue
                    if now - stats.last_sent.get(name, -math.inf) < self.period:
                        continue
                    send(p)
                    stats.sent[name] = stats.sent.get(name, 0) + 1
                    stats.last_sent[name] = now
        except Exception as exc:  # a broken connection or link: recorded, the plant's checks see it
            self.error = f"{type(exc).__name__}: {exc}"
            log.error("motion capture (%s %s): %s", self.backend, self.hostname, self.error)
