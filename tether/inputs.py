"""A process's inputs, without Zenoh: the samples accepted from one key, and what was seen of them.

A :class:`Source` is fed decoded, checked messages (:meth:`Source.offer`); it keeps them by tick
and the newest, and counts what arrived stale (duplicated or reordered) and what an emulated link
corrupted. When the mission emulates the network, a source sits behind a :class:`Link` (the
receive side of one directed link ``j -> i``, implemented by :class:`netem.link.Channel`); the
core knows only this protocol, so a process without ``[netem]`` never loads the emulator.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from tether.gate import Health

RECENT_SEQS = 256
"""How far behind the newest sequence number a source tells duplicates from reordered samples:
it remembers every sequence number received in that window. A sample further behind is too old
to be a reordering and counts as a duplicate (a replay, or a copy too late to matter), so that
``received - duplicates`` never exceeds the samples sent."""
_WINDOW = (1 << (RECENT_SEQS + 1)) - 1
"""The bits of :attr:`Source.recent`: the newest and the :data:`RECENT_SEQS` before it."""
_FRESH = RECENT_SEQS + 1
"""A shift that starts :attr:`Source.recent` afresh."""
_CONTENTS = ("seq", "t", "p", "vel", "a", "u", "mode")
"""What two samples of one tick from one sender must agree on (a state's ``p``, ``vel``, ``a``, a
command's ``u``, and the mode either carries). The sequence number too: a sender sends one sample a
tick, so a second one for a held tick under another number, even with the same contents, was put on
the key by someone else (a copy a network or a resend delivers twice keeps its number)."""
CONTESTED_KEPT = 4 * RECENT_SEQS
"""Most contested ticks a source remembers (the oldest forgotten first), beyond its consumer's
:meth:`Source.forget_before`."""


class Copy(Protocol):
    """One copy a link delivers: its bytes, and whether the link corrupted it (read-only)."""

    @property
    def payload(self) -> bytes: ...

    @property
    def corrupted(self) -> bool: ...


class Link(Protocol):
    """The receive side of one emulated link: copies enter with :meth:`send` at the current
    network time [s] and leave with :meth:`release` when due."""

    def send(self, now: float, payload: bytes) -> None: ...

    def release(self, now: float) -> Sequence[Copy]: ...

    @property
    def next_at(self) -> float | None:
        """When the next copy is due [s], if any is in flight."""
        ...

    @property
    def last_offer(self) -> float:
        """Time of the newest offer [s] (-inf before the first)."""
        ...


@dataclass
class Source:
    """One input key: the samples accepted from it, by tick and newest, and what was seen."""

    key: str
    expect: type
    sender: int | None
    by_tick: dict[int, Any] = field(default_factory=dict)
    newest: Any = None
    received: int = 0
    stale: int = 0
    """Samples not newer (by sequence number) than the newest held: reordered or duplicated."""
    duplicates: int = 0
    """Stale samples whose sequence number had already been received (a second copy, a replay), or
    more than :data:`RECENT_SEQS` behind the newest."""
    reordered: int = 0
    """Stale samples seen for the first time, within :data:`RECENT_SEQS` of the newest
    (overtaken by a newer one on the way)."""
    corrupt: int = 0
    """Copies an emulated link corrupted (they fail the receiver's checksum and are dropped)."""
    recent: int = 0
    """Which sequence numbers within :data:`RECENT_SEQS` of the newest were received, to tell a
    duplicate from a reordered sample: bit ``i`` stands for ``newest.seq - i`` (a few machine words
    however many samples come; a set of the numbers themselves held 30-50 kB per input)."""
    last: int = -1
    """The producer's last tick (the mission's), when known."""
    channel: Link | None = None
    """The emulated network link this input arrives through (``[netem]``), if any."""
    raw_k: int = -1
    """Newest tick offered to the channel (what the sender has sent, before the network)."""
    gone: bool = False
    """Its producer's liveliness token is absent."""
    on_message: Callable[[Any], None] | None = None
    admit: Callable[[Any], str | None] | None = None
    """The plausibility gate: returns why a decoded sample cannot be true (it is then dropped
    before it is stored or counted as received), or None to accept it."""
    rejected: int = 0
    """Samples the gate rejected."""
    conflicts: int = 0
    """Samples that passed the gate but conflict with what the sender already said: another sample
    of the same tick with other contents (:meth:`offer` drops it: two truths for one tick mean one
    of them is forged), one that :attr:`corroborate` refuses (dropped), or one that
    :attr:`consistent` refuses (kept)."""
    consistent: Callable[[Any], bool] | None = None
    """A check of a sample against what its sender said before (a plant's modes,
    :class:`tether.gate.PlantModes`): False counts a conflict."""
    corroborate: Callable[[Any], bool] | None = None
    """A check of a sample against another source that says the same thing (a neighbour's state
    against its own plant's measurement of that tick): False counts a conflict and drops it."""
    health: Health | None = None
    """The stream's sliding-window judge (:class:`tether.gate.Health`), told every sample's verdict
    (but that of a copy of a sample already had);
    with one, a second sample of a held tick with other contents is a conflict (an agent's inputs and
    a plant's commands, whose senders send one sample a tick), and the tick is *contested*: the
    first conflict of a tick is two bad verdicts, the held sample's and the new one's (neither can
    be trusted: the first to arrive is not the more likely true), so that a forger sending one copy
    per genuine sample makes two thirds of the window bad, not a half."""
    contested: dict[int, int] = field(default_factory=dict)
    """Tick -> conflicting samples of it seen (beyond the held one), for the ticks still held; a
    consumer that must not act on a contested tick (a plant's command) asks :meth:`is_contested`."""
    keep: bool = True
    """Hold samples by tick for :meth:`tether.node.Node.aligned`; False for inputs consumed by
    ``on_message`` alone (the recorder), which would otherwise hold every sample of the run."""

    @property
    def silent(self) -> bool:
        """The producer is gone before its last tick (one that sent its last tick and left is not
        silent, whatever order its last sample and its token's end arrive in)."""
        return self.silent_at(self.last)

    def silent_at(self, k: int) -> bool:
        """Silent as far as tick ``k`` is concerned: gone without having delivered tick ``k``.
        (In lockstep a tick runs only with its samples in, so this is never true there, and the
        flag cannot depend on when the token's end happened to be seen.)"""
        return self.gone and not (self.newest is not None and self.newest.k >= min(k, self.last))

    def had(self, msg: Any) -> bool:
        """Whether a sample with ``msg``'s sequence number is known to have been accepted already.
        One more than :data:`RECENT_SEQS` behind the newest is too old to tell: not known (a caller
        that drops what was had must not drop a sample it may still need)."""
        newest = self.newest
        if newest is None or msg.seq > newest.seq:
            return False
        behind = newest.seq - msg.seq
        return behind <= RECENT_SEQS and bool(self.recent >> behind & 1)

    def offer(self, msg: Any, missed: bool = False) -> None:
        """Take one decoded sample: the gate may reject it; otherwise it is counted, held by tick,
        becomes the newest if its sequence number is, and goes to ``on_message`` (which can tell a
        stale one: it is then not :attr:`newest`).

        ``missed``: lockstep, where a stream arrives in order and an older sample not yet had can
        only be one missed and sent again after a stall (:meth:`tether.node.Node.resend`): it is
        taken as if it had come in its turn (not counted stale), so that a run's link statistics
        do not depend on whether the machine's load made a peer resend."""
        health = self.health
        if self.admit is not None and self.admit(msg) is not None:
            self.rejected += 1
            if health is not None:
                health.note(True)
            return
        if health is not None and self.keep and self._conflicts(msg):
            self.conflicts += 1
            contested = self.contested
            n = contested.get(msg.k, 0)
            if n == 0:
                health.note(True)  # the held sample's verdict: contested, no longer to be believed
                if len(contested) >= CONTESTED_KEPT:
                    del contested[min(contested)]
            contested[msg.k] = n + 1
            health.note(True)
            return
        if self.corroborate is not None and not self.corroborate(msg):
            self.conflicts += 1
            if health is not None:
                health.note(True)
            return
        if self.consistent is not None and not self.consistent(msg):
            self.conflicts += 1
            if health is not None:
                health.note(True)
        elif health is not None and not self.had(msg):
            # a copy of a sample already had is no evidence either way (else replays of genuine
            # samples would dilute a forgery's share of the window)
            health.note(False)
        self.received += 1
        newest = self.newest
        if missed and newest is not None and msg.seq < newest.seq and newest.seq - msg.seq <= RECENT_SEQS:
            self.recent |= 1 << (newest.seq - msg.seq)
        elif newest is not None and msg.seq <= newest.seq:
            self.stale += 1
            behind = newest.seq - msg.seq
            if behind > RECENT_SEQS or self.recent >> behind & 1:
                self.duplicates += 1
            else:
                self.reordered += 1
                self.recent |= 1 << behind
        else:
            # a jump beyond the window (a first sample, a forged sequence number) starts it afresh:
            # never a shift by an absurd count
            ahead = msg.seq - newest.seq if newest is not None else _FRESH
            self.recent = (self.recent << ahead | 1) & _WINDOW if ahead <= RECENT_SEQS else 1
            self.newest = msg
        if self.keep:
            self.by_tick.setdefault(msg.k, msg)
        if self.on_message is not None:
            self.on_message(msg)

    def _conflicts(self, msg: Any) -> bool:
        """Whether a sample of ``msg``'s tick is held with another sequence number or other contents
        (time, position, velocity, acceleration or mode): a copy, a resend or a replay of the same
        sample is no conflict."""
        held = self.by_tick.get(msg.k)
        if held is None or held is msg:
            return False
        return any(getattr(held, f, None) != getattr(msg, f, None) for f in _CONTENTS)

    def received_upto(self, k: int) -> int:
        """Samples accepted whose tick is at most ``k`` (in lockstep, what tick k could have seen,
        whatever arrived early)."""
        return self.received - sum(1 for t in self.by_tick if t > k)

    def is_contested(self, msg: Any) -> bool:
        """Whether another sample of ``msg``'s tick, with other contents, has come (:attr:`contested`)."""
        return msg.k in self.contested

    def forget_before(self, k: int) -> None:
        for old in [t for t in self.by_tick if t < k]:
            del self.by_tick[old]
        if self.contested:
            for old in [t for t in self.contested if t < k]:
                del self.contested[old]

    def deliver(self, now: float, decode: Callable[[bytes], Any | None]) -> int:
        """Hand the copies this source's link delivers by ``now`` to it; a corrupted copy fails its
        checksum at the receiver and is counted, not decoded. ``decode`` returns None for a copy
        the receiver rejects. Returns the number of corrupted copies."""
        if self.channel is None:
            return 0
        bad = 0
        for copy in self.channel.release(now):
            if copy.corrupted:
                self.corrupt += 1
                bad += 1
                continue
            msg = decode(copy.payload)
            if msg is not None:
                self.offer(msg)
        return bad
