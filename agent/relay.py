"""Real time: agent i relays its plant's measurement as its own state on Zenoh's callback thread,
the moment it arrives, without waiting for the event loop. No Zenoh here: the caller gives the
publish function.

Its out-neighbours use agent i's state, so every hop of it is a delay in their loops: through the
event loop it waited for a wake-up (and for the tick, when the sample came during one), and cost
the agent a loop iteration per sample. :class:`Relay` is called by the plant input's tap
(:meth:`tether.node.Node.source`) with each sample as received and stamped, and decides alone:

* nothing before the process's start (a restarted agent learns the run's start from these samples
  first: :mod:`tether.rejoin`);
* a sample that does not decode, or not as its plant's :class:`~tether.wire.PlantState`: not
  relayed (the tick's own drain counts it);
* its own plausibility gate (:mod:`tether.gate`), judging each sample at its stamped arrival, as
  the tick's gate does: what it rejects is not relayed;
* a sample not newer (by sequence number) than the newest relayed, a replay or a duplicate: not
  relayed, counted as ``stale_relay``;
* a sample that arrives more than :data:`STALL` periods after the agent's loop last ticked
  (:attr:`Relay.alive_at`): not relayed, counted as ``relay_stalled``. An agent whose loop is
  stuck must fall silent to its out-neighbours, as it did when the loop relayed: they then count
  it out, instead of flying beside a vehicle whose controller no longer runs.

Everything it keeps is its own: it runs beside the event loop, on one callback thread. What it
reads of the agent (the supervisor's mode, the shared acceleration) are single references that
the tick replaces whole.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from tether import wire
from tether.gate import Gate

if TYPE_CHECKING:  # the type only: this module does not load Zenoh
    from tether.transport import Received

STALL = 4
"""Periods after its loop's last tick that the relay still relays (the tick comes half a period
after its plant's sample; a loaded machine makes it late by a period or two)."""


class Relay:
    """The relay of agent ``aid``'s plant samples (module docstring)."""

    def __init__(self, aid: int, dim: int, period: float, gate: Gate, origin: Callable[[], float | None],
                 publish: Callable[[wire.PlantState], None], count: Callable[[str], None]):
        """``gate``: this relay's own (its ``now`` is set from each sample's stamp); ``origin``: the
        run's tick 0 on the monotonic clock, None before the start; ``publish``: sends the state;
        ``count``: counts a dropped sample by reason."""
        self.aid = aid
        self.period = period
        self.alive_at = -math.inf
        """When the agent's loop last ticked [s, monotonic] (or its first tick's instant, set at the
        start): the agent's loop sets it, the relay reads it."""
        self.receiver = wire.Receiver(dim)
        self.gate = gate
        self._at = 0.0
        gate.now = lambda: self._at
        self.origin = origin
        self.publish = publish
        self.count = count
        self.newest: int | None = None
        """Sequence number of the newest sample relayed."""

    def __call__(self, rec: Received) -> None:
        origin = self.origin()
        if origin is None:
            return  # before this process's start
        if not rec.at <= self.alive_at + STALL * self.period:
            self.count("relay_stalled")  # the agent's loop is stuck: it falls silent
            return
        msg = self.receiver.accept(rec.payload, wire.PlantState, self.aid)
        if msg is None:
            return
        self._at = rec.at - origin
        if self.gate.check(msg) is not None:
            return
        if self.newest is not None and msg.seq <= self.newest:
            self.count("stale_relay")  # not newer than the last: never re-published as fresh
            return
        self.newest = msg.seq
        self.publish(msg)
