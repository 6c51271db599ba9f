"""One emulated link ``j -> i`` as a process's input sees it: the link model, its profile
schedule, and the copies in flight (the :class:`tether.inputs.Link` the core's inputs sit behind).

Used by the agent process and by the in-process engine alike, so both emulate the same link.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from netem.channel import Delivery, DeliveryQueue, Link, batchable, link_rng
from tether import mission as ms
from tether.netprofile import schedule


@dataclass
class Channel:
    """One directed link j -> i of the emulated network. Samples enter with :meth:`send` and leave
    with :meth:`release`."""

    link: Link
    changes: list[tuple[float, Any]]
    queue: DeliveryQueue = field(default_factory=DeliveryQueue)
    _next: int = 1

    @classmethod
    def of(cls, m: ms.Mission, src: int, dst: int) -> "Channel":
        """Link ``src -> dst`` of mission ``m``'s ``[netem]`` section: its profile schedule and
        its generator ``link_rng(m.seed, src, dst)``."""
        assert m.netem is not None, "Channel.of needs a mission with a [netem] section"
        changes = schedule(m.netem, src, dst)
        return cls(Link(changes[0][1], link_rng(m.seed, src, dst), log=m.netem.log), changes)

    def send(self, now: float, payload: bytes) -> None:
        while self._next < len(self.changes) and self.changes[self._next][0] <= now:
            self.link.set_profile(self.changes[self._next][1])
            self._next += 1
        self.queue.push(self.link.offer(now, payload))

    def decide(self, now: np.ndarray) -> np.ndarray:
        """What :meth:`send` decides for one message at each time of ``now`` (non-decreasing), the
        profile schedule followed as it follows it, for a link whose profiles are all batchable
        (:func:`netem.channel.batchable`: loss and delay only): each message's delivery time [s], NaN
        where it was lost. The copies are not queued: the caller holds the times. Raises
        ``ValueError`` (nothing changed) when a profile the times reach is not batchable, or for times
        :meth:`send` would refuse (not finite, decreasing, or before the last offer)."""
        now = np.asarray(now, dtype=float)
        if len(now) and (not np.all(np.isfinite(now)) or bool(np.any(np.diff(now) < 0.0))
                         or not float(now[0]) >= self.link.last_offer):
            raise ValueError(f"offer times must be finite and non-decreasing from the previous offer "
                             f"({self.link.last_offer}); first {float(now[0])}")
        starts = [at for at, _ in self.changes[self._next:]]
        reached = self.changes[self._next:self._next + int(np.searchsorted(starts, now[-1], side="right"))] \
            if len(now) else []
        if not all(batchable(prof) for prof in [self.link.profile, *(p for _, p in reached)]):
            raise ValueError("decide takes a link whose profiles are all batchable (loss and delay only)")
        out = np.empty(len(now))
        lo = 0
        while lo < len(now):
            while self._next < len(self.changes) and self.changes[self._next][0] <= now[lo]:
                self.link.set_profile(self.changes[self._next][1])
                self._next += 1
            hi = len(now)
            if self._next < len(self.changes):  # the offers before the next change
                hi = lo + int(np.searchsorted(now[lo:], self.changes[self._next][0], side="left"))
            out[lo:hi] = self.link.offer_times(now[lo:hi])
            lo = hi
        return out

    def release(self, now: float) -> list[Delivery]:
        return self.queue.pop_due(now)

    @property
    def next_at(self) -> float | None:
        return self.queue.next_at

    @property
    def last_offer(self) -> float:
        """Time of the newest offer [s] (-inf before the first)."""
        return self.link.last_offer

    def change(self, at: float, profile: Any) -> None:
        """Use ``profile`` for the offers from ``at`` on (one already past: from the next offer).
        Changes asked for the same time apply in the order they were asked for."""
        pending = self.changes[self._next:]
        pending.append((at, profile))
        pending.sort(key=lambda c: c[0])  # stable
        self.changes[self._next:] = pending
