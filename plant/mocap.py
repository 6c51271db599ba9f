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
pre-flight check (:mod:`plant.preflight`) notices. In flight, :func:`fix_lost` says when a body's
positions stopped coming (for :data:`LOST_AFTER`, or the feed ended): the plant then lands the vehicle
as for a failed link. :class:`MocapFeed` is the thin
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


LOST_AFTER = 0.5
"""A vehicle whose rigid body has had no position sent for this long [s] (occluded, out of the
arena, the capture system or its network gone) has lost its fix: its onboard estimator dead-reckons
on the IMU and drifts, so the plant lands it (:func:`fix_lost`). A few frames' occlusion (tens of
milliseconds) is ridden out."""


def fix_lost(stats: "FeedStats", name: str, now: float, since: float, error: str | None,
             lost_after: float = LOST_AFTER) -> str | None:
    """Why the positions of rigid body ``name`` no longer come, or None while they do: the feed's
    thread ended (``error``), or the last position sent (else ``since``, when the feed started) is
    more than ``lost_after`` [s] before ``now`` (both ``time.monotonic()``). Pure."""
    if error is not None:
        return f"motion capture lost: {error}"
    last = stats.last_sent.get(name, since)
    if now - last > lost_after:
        refused = stats.refused.get(name, 0)
        return (f"motion capture lost: no position of rigid body {name} for {now - last:.2f} s "
                f"({refused} frame(s) without it, out of bounds or not finite)")
    return None


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
        self.started = time.monotonic()
        """When the feed started (``time.monotonic()``): the reference of :func:`fix_lost` before a first send."""
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
        else:
            if self.error is None:
                self.error = "the feed was stopped"

    def lost(self, name: str, now: float) -> str | None:
        """Why rigid body ``name``'s positions no longer come (:func:`fix_lost`), or None."""
        return fix_lost(self.stats, name, now, self.started, self.error)
