"""A process's output side: stamped publishers, and in lockstep the messages they keep to send again.

Every message leaves through a :class:`Publisher`, which stamps sender, sequence number, tick and
sample time on it. The process's clock says how a stream is published
(:meth:`tether.clock.Clock.stream`): real time DROP (the newest supersedes), lockstep BLOCK with
its last ticks kept, which :meth:`Outputs.resend` puts again after a tick has waited long.
"""

from __future__ import annotations

import collections
import logging
from typing import Any

import zenoh

from tether import transport as tp
from tether import wire
from tether.clock import Clock
from tether.ingress import undeclare

log = logging.getLogger("tether")

class Publisher:
    """A publisher that stamps sender, sequence number, tick and sample time on every message.

    ``keep`` (lockstep): the payloads of its messages of the last ``keep`` ticks, which
    :meth:`resend` puts again (:meth:`tether.node.Node.until`, after :data:`tether.node.RESEND` of waiting)."""

    def __init__(self, pub: zenoh.Publisher, sender: int, keep: int = 0):
        self._pub = pub
        self._sender = sender
        self.seq = 0
        self.keep = keep
        self.kept: collections.deque[tuple[int, bytes]] | None = collections.deque() if keep else None
        """``(tick, payload)`` of the messages kept, oldest first."""

    def send(self, cls: type, k: int, t: float, **fields: Any) -> None:
        self.put(cls(sender=self._sender, seq=self.seq, k=k, t=t, **fields))

    def put(self, msg: wire.Message) -> None:
        """Publish a message built by the caller (its sender and sequence number are the caller's)."""
        self.seq += 1
        payload = wire.encode(msg)
        self._pub.put(payload)
        if self.kept is not None:
            self._keep(msg.k, payload)

    def _keep(self, k: int, payload: bytes) -> None:
        kept = self.kept
        assert kept is not None
        kept.append((k, payload))
        while kept[0][0] <= k - self.keep:  # a record carries many ticks: kept by its last, as many as it takes
            kept.popleft()

    def resend(self) -> int:
        """Put the kept messages again, oldest first (the same bytes: a receiver that has one keeps
        the first copy and counts the other as a duplicate). Returns how many."""
        kept = list(self.kept or ())
        for _, payload in kept:
            self._pub.put(payload)
        return len(kept)


class Outputs:
    """A process's publishers. ``sender``: the id stamped by default; ``window``: the lockstep
    clock's (each stream keeps its messages of the last ``window + 1`` ticks, 0: none)."""

    def __init__(self, session: zenoh.Session, clock: Clock, sender: int, window: int) -> None:
        self.session = session
        self.clock = clock
        self.sender = sender
        self.window = window
        self.declared: list[Any] = []
        """The publishers declared, undeclared by :meth:`close`."""
        self.kept: list[Publisher] = []
        """Lockstep publishers that keep their last messages (:meth:`resend`)."""
        self.resent = 0
        """Messages sent again so far (:meth:`resend`)."""

    def publisher(self, key: str, qos: tp.StreamQos | None = None, sender: int | None = None) -> Publisher:
        """A stamped publisher on ``key``. Real time: ``qos`` (default :data:`~tether.transport.STATE`,
        DROP: the newest supersedes). Lockstep: always :data:`~tether.transport.SYNC` (BLOCK),
        because a lost sample would stall the run: measured here, DROP state streams lost samples
        under load and stalled lockstep runs."""
        qos, keep = self.clock.stream(qos, self.window)
        pub = tp.declare_publisher(self.session, key, qos)
        self.declared.append(pub)
        out = Publisher(pub, self.sender if sender is None else sender, keep=keep)
        if out.kept is not None:
            self.kept.append(out)
        return out

    def resend(self, waiting_for: str, waited: float) -> int:
        """Lockstep: put every stream's kept messages (those of its last ``window + 1`` ticks) again,
        after a tick has waited ``waited`` seconds for ``waiting_for``. A peer of a mesh can miss a
        stream's first samples for good: the run starts once every peer is linked to every other and
        its token is in, but a peer's subscriptions reach each other peer over their own link, and a
        sample put before they arrive goes nowhere (a lockstep run stalled at tick 0, an agent waiting
        for its in-neighbour's state of tick 0 while that neighbour waited further on). Sent again,
        the sample reaches the peer that waits for it. A receiver that has it keeps the first copy; the
        other is dropped and counted apart (:attr:`tether.ingress.Ingress.copies`, not a link's ``duplicates``), and one it
        missed is taken as if it had come in its turn: a run's arrays stay those of a run without
        the stall. Returns the number of messages sent again."""
        n = sum(pub.resend() for pub in self.kept)
        self.resent += n
        log.warning("waited %.1f s for %s: sent the last %d messages of my %d streams again (%d so far)",
                    waited, waiting_for, n, len(self.kept), self.resent)
        return n

    def close(self) -> None:
        """Undeclare every publisher."""
        undeclare(self.declared)
