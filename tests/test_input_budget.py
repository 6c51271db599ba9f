"""The per-input decoding budget of a real-time recorder (``tether/ingress.py``): a token bucket per key.

A real :class:`~tether.node.Node` on a real Zenoh session (isolated: no endpoint, no scouting), its
real per-key queues (:class:`~tether.handoff.InputQueue`, the ones Zenoh's callback thread fills)
and a real-time clock on a time source the test moves, so that periods pass exactly when the
test says. What is asserted:

* a stream's backlog (what a healed link or a stalled loop delivers at once: two seconds of samples
  arriving together) is decoded whole, in order, none dropped: its budget was saved while the
  stream used one sample per period;
* a flood on one key costs at most :data:`~tether.ingress.INPUT_BUDGET` decodes per period once its
  budget is spent (and one bucket's worth once); the key is muted meanwhile; the other keys keep
  theirs and every one of their samples;
* what a key's queue cannot hold is dropped oldest first and counted (``Node.overflow``); the
  recorder also counts it as ``overflow`` in its drop counts (its run file's ``recorder_drops``), a
  role that flies does not (it keeps the newest few by design);
* what the FIFO of the other subscriptions cannot hold is counted as ``overflow`` in every role.
"""

from __future__ import annotations

import pytest

from tether import ingress as ig
from tether import node as nd
from tether import transport as tp
from tether import wire
from tether.catalog import builtin_path
from tether.clock import RealtimeClock

pytestmark = pytest.mark.asyncio


class Time:
    """The clock's time source [s], moved by the test a whole period at a time (read mid-period, so
    that no rounding puts it in the neighbouring one)."""

    def __init__(self, h: float) -> None:
        self.h, self.period = h, 100_000

    def advance(self, periods: int = 1) -> None:
        self.period += periods

    def __call__(self) -> float:
        return (self.period + 0.5) * self.h


def state(sender: int, k: int, h: float) -> bytes:
    return wire.encode(wire.State(sender=sender, seq=k, k=k, t=k * h, p=[0.0, 0.0], vel=[0.0, 0.0],
                                  a=[0.0, 0.0]))


async def test_a_backlog_is_taken_whole_and_a_flood_is_held_to_the_budget() -> None:
    args = nd.NodeArgs(mission_path=builtin_path("section4"), role="recorder", node_id=0, clock="realtime",
                       zenoh=tp.ZenohSettings(mode="peer", scouting_delay=0.0,
                                             listen=(tp.loopback_endpoint(tp.free_tcp_port()),)))
    m = nd.load_mission(args.mission_path)
    h = m.dt
    t = Time(h)
    clock = RealtimeClock(h, monotonic=t)
    async with tp.open_session(args.zenoh) as session:
        node = nd.Node(args, m, session, clock)
        try:
            keys = node.keys
            stream, flooded = keys.topic("agent", 1, "state"), keys.topic("leader", m.leader.id, "state")
            src = node.source(stream, wire.State, 1)
            lead = node.source(flooded, wire.State, m.leader.id)
            cap = ig.input_capacity(m.rate)
            assert cap == round(ig.BACKLOG * m.rate) == 200 == node.ingress._capacity
            flying = nd.Node(nd.NodeArgs(mission_path=args.mission_path, role="agent", node_id=2, clock="realtime",
                                         zenoh=args.zenoh), m, session, clock)
            assert flying.ingress._capacity == ig.INPUT_BUDGET  # a role that flies keeps the newest few

            # one sample per period for a second: the stream's budget stays full
            k = 0
            for _ in range(100):
                node.inputs[stream].put(tp.Received(stream, state(1, k, h)))
                node.ingress._drain_inputs()
                k += 1
                t.advance()
            assert src.received == 100 and not node.overflow

            # a healed link: 1.5 s of backlog at once (150 samples), then the stream goes on
            for _ in range(150):
                node.inputs[stream].put(tp.Received(stream, state(1, k, h)))
                k += 1
            node.ingress._drain_inputs()
            assert src.received == 250 and src.stale == 0 and src.newest.k == 249  # whole, in order
            assert not node.overflow

            # a flood on another key: 1000 junk-free, well-formed samples per period for 10 periods
            decoded = []
            for period in range(10):
                for j in range(1000):
                    node.inputs[flooded].put(tp.Received(flooded, state(m.leader.id, 10_000 * period + j, h)))
                before = lead.received + lead.rejected
                node.ingress._drain_inputs()
                decoded.append(lead.received + lead.rejected - before)
                assert node.inputs[flooded].muted == (period > 0)  # period 0 took all the queue held
                node.inputs[stream].put(tp.Received(stream, state(1, k, h)))  # the stream goes on
                k += 1
                node.ingress._drain_inputs()
                t.advance()
            assert decoded[0] == cap  # the bucket's worth once ...
            assert decoded[1:] == [ig.INPUT_BUDGET] * 9  # ... then the budget per period
            assert node.overflow[flooded] == 10 * 1000 - cap - 9 * ig.INPUT_BUDGET - len(node.inputs[flooded])
            assert stream not in node.overflow and src.received == 260  # the other key lost nothing
            # the recorder lost samples it should have recorded: its drop counts (its run file's
            # recorder_drops) say how many, as 'overflow'
            assert node.receiver.drops == {"overflow": node.overflow[flooded]}

            # a role that flies keeps the newest few by design: what it lets go is no lost record
            own = flying.source(stream, wire.State, 1)
            for j in range(ig.INPUT_BUDGET + 5):
                flying.inputs[stream].put(tp.Received(stream, state(1, j, h)))
            flying.ingress._drain_inputs()
            assert flying.overflow[stream] == 5 and own.newest.k == ig.INPUT_BUDGET + 4
            assert flying.receiver.drops == {}

            # after the flood the flooded key's budget refills at INPUT_BUDGET per period
            node.inputs[flooded].take(10_000)
            t.advance(3)  # four periods after the last drain
            node.ingress._drain_inputs()
            assert node.ingress._budget[flooded] == 4 * ig.INPUT_BUDGET

            # the FIFO of every other subscription, flooded beyond its capacity between two drains:
            # the oldest go, counted as 'overflow' in any role
            lost = node.receiver.drops["overflow"]
            for _ in range(ig.FIFO_CAPACITY + 7):
                node.fifo.put(tp.Received("elsewhere", b""))
            flying.fifo.put(tp.Received("elsewhere", b""))
            node.drain()
            flying.drain()
            assert node.receiver.drops["overflow"] == lost + 7 and flying.receiver.drops == {}
            for _ in range(ig.FIFO_CAPACITY + 3):
                flying.fifo.put(tp.Received("elsewhere", b""))
            flying.drain()
            assert flying.receiver.drops == {"overflow": 3}
        finally:
            node.close()
