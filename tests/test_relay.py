"""The real-time relay of an agent's plant samples (``agent/relay.py``), pure: samples as a
subscriber callback hands them off (payload bytes, arrival stamp), a recording publish function.

What it must do with each input: nothing before the start; junk and another sender's sample are
not relayed; its plausibility gate judges the stamped arrival (a sample from too far in the
future, a jump, an absurd speed: not relayed); a replay or a duplicate is not relayed and is
counted as ``stale_relay``; every newer plausible sample is relayed once, in order, as decoded.
"""

from __future__ import annotations

import math

from agent.relay import Relay
from tether import gate as gt
from tether import wire
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.transport import Received

M = load_mission(builtin_path("section4"))
AID = M.agent_ids[0]
H = M.dt
ORIGIN = 1000.0  # tick 0 on the monotonic clock
KEY = f"tether/section4/plant/{AID}/state"


def sample(k: int, seq: int | None = None, p: list[float] | None = None, vel: list[float] | None = None,
           t: float | None = None, sender: int = AID) -> bytes:
    p0 = gt.initial_positions(M)[AID]
    return wire.encode(wire.PlantState(sender=sender, seq=k if seq is None else seq, k=k, t=k * H if t is None else t,
                                       p=p if p is not None else list(p0), vel=vel or [0.0] * M.dim,
                                       a=[0.1] * M.dim, d=[0.0] * M.dim, mode=wire.FLYING))


def arrived(payload: bytes, k: int, late: float = 0.001) -> Received:
    """Received ``late`` seconds after tick k's instant."""
    return Received(KEY, payload, ORIGIN + k * H + late)


class Setup:
    def __init__(self) -> None:
        self.origin: float | None = None
        self.sent: list[wire.PlantState] = []
        self.drops: dict[str, int] = {}
        self.relay = Relay(AID, M.dim, H, gt.for_sender(M, AID, None), lambda: self.origin, self.sent.append,
                           lambda why: self.drops.__setitem__(why, self.drops.get(why, 0) + 1))
        self.relay.alive_at = math.inf  # the agent's loop ticks (see the stall test)


def test_nothing_is_relayed_before_the_start_then_each_newer_sample_once_in_order() -> None:
    s = Setup()
    s.relay(arrived(sample(0), 0))
    assert s.sent == []
    s.origin = ORIGIN
    for k in range(5):
        s.relay(arrived(sample(k), k))
    assert [m.k for m in s.sent] == [0, 1, 2, 3, 4] and s.relay.newest == 4
    assert s.sent[2] == wire.decode(sample(2))  # the sample itself, decoded
    assert s.drops == {}


def test_replays_and_duplicates_are_counted_not_relayed() -> None:
    s = Setup()
    s.origin = ORIGIN
    for k in range(3):
        s.relay(arrived(sample(k), k))
    s.relay(arrived(sample(2), 3))  # a duplicate
    s.relay(arrived(sample(1), 3))  # a replay of an older one
    s.relay(arrived(sample(3), 3))
    assert [m.k for m in s.sent] == [0, 1, 2, 3]
    assert s.drops == {"stale_relay": 2}


def test_junk_another_senders_and_implausible_samples_are_not_relayed() -> None:
    s = Setup()
    s.origin = ORIGIN
    s.relay(arrived(sample(0), 0))
    s.relay(Received(KEY, b"\x93\x01\x02", ORIGIN + H))  # junk
    s.relay(arrived(sample(1, sender=AID + 1), 1))  # another agent's plant on this key
    far = [c + 50.0 for c in gt.initial_positions(M)[AID]]
    s.relay(arrived(sample(1, p=far), 1))  # a jump of 50 m in one period
    s.relay(arrived(sample(1, vel=[1e3] + [0.0] * (M.dim - 1)), 1))  # an absurd speed
    s.relay(arrived(sample(1, p=[math.nan] * M.dim), 1))  # non-finite
    assert [m.k for m in s.sent] == [0]
    assert s.relay.receiver.drops == {"malformed": 1, "sender": 1, "nonfinite": 1}
    assert s.relay.gate.rejected == {"jump": 1, "speed": 1}
    s.relay(arrived(sample(1), 1))  # the real one still goes
    assert [m.k for m in s.sent] == [0, 1]


def test_its_gate_judges_the_stamped_arrival_not_the_call() -> None:
    """A sample stamped long before its tick (from far in the future, as the receiver's clock
    says) is rejected; the same sample stamped at its tick is relayed, whenever the call comes."""
    s = Setup()
    s.origin = ORIGIN
    ahead = M.safety.future_window + 5
    s.relay(arrived(sample(ahead), 0))
    assert s.sent == [] and s.relay.gate.rejected == {"future": 1}
    s.relay(arrived(sample(ahead), ahead))
    assert [m.k for m in s.sent] == [ahead]


def test_a_stuck_agent_loop_silences_the_relay_until_it_ticks_again() -> None:
    """The relay goes on only while the agent's loop ticks: samples arriving more than STALL
    periods after its last tick are counted (``relay_stalled``), not relayed; the next tick
    resumes it with the newest sample."""
    from agent.relay import STALL

    s = Setup()
    s.origin = ORIGIN
    s.relay.alive_at = ORIGIN + 0.5 * H  # the loop's last tick: tick 0
    for k in range(10):
        s.relay(arrived(sample(k), k))
    relayed = [m.k for m in s.sent]
    assert relayed == list(range(STALL + 1)), relayed
    assert s.drops == {"relay_stalled": 10 - (STALL + 1)}
    s.relay.alive_at = ORIGIN + 10.5 * H  # the loop ticks again
    s.relay(arrived(sample(11), 11))
    assert [m.k for m in s.sent][-1] == 11
