"""Clock offsets seen on each input link, from sample times against arrival times. Pure: no I/O, no clock.

Every sample carries its tick's time ``t = k h`` on the *sender's* clock (mission time: seconds
since the run's start instant, as the sender's wall clock placed it), and it is sent at about that
instant (a plant, the leader) or relayed as soon as the plant's sample arrives (an agent's state,
which therefore leaves at its plant's time). The receiver reads its own mission time ``now`` when
the sample arrives. One way, what is observable is

    now - t = L + (c_r - c_s)

with ``L >= 0`` the transport delay (network, queues, the relay's hop) and ``c_r - c_s`` how far
the receiver's clock is ahead of the sender's. Neither term can be told apart from one link
alone, so the estimate per link is an **offset bound**:

    e = a low order statistic of (now - t) over a window  =  L_min + (c_r - c_s)

* ``e < 0`` proves the sender's clock is ahead by at least ``-e`` (no delay is negative);
* ``e > 0`` is the smallest delay plus the receiver's lead: on a link whose minimum delay is known
  (loopback, a wired LAN: well under a millisecond), ``e - L_min`` is the receiver's lead;
* with the reverse link's ``e'`` (where there is one), ``(e - e') / 2`` is ``c_r - c_s`` up to half the
  delay asymmetry, and ``(e + e') / 2`` the mean minimum delay — NTP's estimate (:func:`pair`).

The low order statistic is robust: samples are grouped in blocks of :data:`BLOCK` seconds of the
receiver's time; each block keeps its minimum, and the estimate is the median of the last :data:`BLOCKS`
blocks' minima, valid once :data:`MIN_BLOCKS` blocks are complete. A forged or replayed sample, or
a burst of queueing, moves one block's minimum at most: fewer than half the blocks being wrong
cannot move the estimate. Samples are observed *before* the plausibility gate (a sender whose
clock is ahead by more than the gate's ``future`` bound has every sample rejected, and that is
exactly what must be seen).

A link is flagged (:attr:`LinkClock.warn`) when ``e`` is outside :func:`bounds`: below minus half
a control period (the sender's clock is certainly ahead by more than that: its samples' ages read
half a period too young, and at two periods ahead the gate rejects every one of them), or above
one period (the receiver's clock is ahead, or the link is slower than a period: either way every
sample misses the tick it was meant for). The upper bound is wider because ``e > 0`` includes the
link's delay (measured 1-2 ms on loopback, 3-6 ms with TLS through network namespaces on a loaded
machine), which is no clock error.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

BLOCK = 0.25
"""Length of one block of the receiver's time [s]: the estimate is the median of per-block minima."""
BLOCKS = 8
"""Blocks in the window (2 s)."""
MIN_BLOCKS = 3
"""Complete blocks needed before a link has an estimate (0.75 s after its first sample)."""


def bounds(period: float) -> tuple[float, float]:
    """The offsets [s] outside which a link is flagged: ``(-period / 2, period)`` for the control
    period ``period`` [s] (see the module docstring)."""
    return -0.5 * period, period


def pair(e_ij: float, e_ji: float) -> tuple[float, float]:
    """From the offset bounds of both directions between two processes: ``(c_j - c_i, mean
    minimum delay)`` [s] — how far j's clock is ahead of i's (``e_ij`` is measured at j, of i's
    samples), exact when both directions have the same minimum delay."""
    return 0.5 * (e_ij - e_ji), 0.5 * (e_ij + e_ji)


@dataclass
class LinkEstimator:
    """The offset bound of one input link (see the module docstring)."""

    block: float = BLOCK
    blocks: int = BLOCKS
    min_blocks: int = MIN_BLOCKS
    minima: deque[float] = field(default_factory=deque)
    """Minima of the complete blocks, oldest first (at most ``blocks``)."""
    current: int | None = None
    """Index of the block being filled (``floor(t / block)``)."""
    current_min: float = math.inf
    samples: int = 0
    """Samples observed (finite times only)."""
    ignored: int = 0
    """Samples with a non-finite time."""
    changes: int = 0
    """Blocks completed so far (the estimate can change only then)."""

    def observe(self, t: float, now: float) -> None:
        """One sample of time ``t`` [s, sender's mission time] arrived at ``now`` [s, receiver's]."""
        if not (math.isfinite(t) and math.isfinite(now)):
            self.ignored += 1
            return
        # blocks by the receiver's clock: whatever time a sample claims (a forgery far ahead, a
        # replay far behind) it falls into the current block and moves only that block's minimum
        b = math.floor(now / self.block)
        if self.current is None:
            self.current = b
        if b > self.current:
            if math.isfinite(self.current_min):
                self.minima.append(self.current_min)
                while len(self.minima) > self.blocks:
                    self.minima.popleft()
                self.changes += 1
            self.current, self.current_min = b, math.inf
        self.samples += 1
        d = now - t
        if d < self.current_min:
            self.current_min = d

    @property
    def estimate(self) -> float | None:
        """``e`` [s]: median of the complete blocks' minima; None before :attr:`min_blocks` blocks."""
        if len(self.minima) < self.min_blocks:
            return None
        s = sorted(self.minima)
        n = len(s)
        return s[n // 2] if n % 2 else 0.5 * (s[n // 2 - 1] + s[n // 2])


@dataclass(frozen=True)
class LinkClock:
    """One link's estimate, as reported."""

    role: str
    """The sender's role: ``plant``, ``agent`` or ``leader``."""
    src: int
    offset: float
    """``e`` [s]: minimum delay plus how far the receiver's clock is ahead of the sender's."""
    warn: bool
    """``offset`` is outside :func:`bounds`."""


@dataclass
class SkewMonitor:
    """The estimators of one receiver's input links, by ``(role, id)`` of the sender."""

    period: float
    links: dict[tuple[str, int], LinkEstimator] = field(default_factory=dict)
    warned: dict[tuple[str, int], float] = field(default_factory=dict)
    """Flagged links, with the offset last said."""
    _reported: tuple[tuple[int, int], list[LinkClock]] | None = field(default=None, repr=False)

    def link(self, role: str, src: int) -> LinkEstimator:
        est = self.links.get((role, src))
        if est is None:
            est = self.links[role, src] = LinkEstimator()
        return est

    def observe(self, role: str, src: int, t: float, now: float) -> None:
        self.link(role, src).observe(t, now)

    @property
    def limits(self) -> tuple[float, float]:
        return bounds(self.period)

    def report(self) -> list[LinkClock]:
        """Every link that has an estimate, in the order the links were first seen. The same list
        (not to be changed) as at the previous call while no estimate can have changed: an
        estimate moves only when a block completes, and an agent asks every tick."""
        version = (len(self.links), sum(est.changes for est in self.links.values()))
        if self._reported is not None and self._reported[0] == version:
            return self._reported[1]
        lo, hi = self.limits
        out = []
        for (role, src), est in self.links.items():
            e = est.estimate
            if e is not None:
                out.append(LinkClock(role, src, e, not lo <= e <= hi))
        self._reported = (version, out)
        return out

    def newly_flagged(self, now: list[LinkClock]) -> list[LinkClock]:
        """Of ``now`` (:meth:`report`), the links flagged that were not at the previous call, or whose
        offset has moved by more than a period since they were last said (a slow start-up that turns
        out to be a skew): each is said once until it clears or changes."""
        new = []
        for c in now:
            key = (c.role, c.src)
            if not c.warn:
                self.warned.pop(key, None)
            elif key not in self.warned or abs(c.offset - self.warned[key]) > self.period:
                self.warned[key] = c.offset
                new.append(c)
        return new


def describe(c: LinkClock, receiver: str, limits: tuple[float, float]) -> str:
    """A warning line for a flagged link."""
    ms_ = 1000 * c.offset
    if c.offset < 0:
        why = (f"its samples arrive {-ms_:.1f} ms before their time: {c.role}/{c.src}'s clock is ahead of "
               f"{receiver}'s by at least that")
    else:
        why = (f"its samples arrive {ms_:.1f} ms after their time at the earliest: {receiver}'s clock is ahead "
               f"of {c.role}/{c.src}'s by up to that, or the link is that slow")
    return (f"clock: link {c.role}/{c.src} -> {receiver}: {why} (flagged outside {1000 * limits[0]:+.1f} .. "
            f"{1000 * limits[1]:+.1f} ms; synchronise the hosts' clocks: chrony/PTP, docs/deploy.md)")
