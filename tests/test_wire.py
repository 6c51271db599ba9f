"""tether.wire: the schema every process speaks, the checked receive path, and the key scheme.

Pure: no Zenoh, no I/O. Every message type is built once in :data:`SAMPLES` and every test that
needs "one of each" iterates over it, so a new message type that is not added here fails
:func:`test_samples_cover_every_message_type`.
"""

from __future__ import annotations

import math
import typing

import msgspec
import pytest

from tether.netprofile import LinkRule
from tether import wire
from tether.wire import Keys, Receiver

DIM = 2

LINKS = [
    wire.LinkStats(src=5, received=10, used=9, stale=1, age=0.01, silent=False),
    wire.LinkStats(src=4, received=0, used=0, stale=0, age=math.nan, silent=True),
]

SAMPLES: dict[type, wire.Message] = {
    wire.State: wire.State(sender=3, seq=7, k=7, t=0.07, p=[1.0, -2.0], vel=[0.5, 0.25], a=[0.0, -9.5]),
    wire.PlantState: wire.PlantState(sender=2, seq=1, k=1, t=0.01, p=[0.1, 0.2], vel=[0.3, 0.4], a=[0.5, 0.6],
                                     d=[math.nan, 0.125]),
    wire.Command: wire.Command(sender=4, seq=99, k=99, t=0.99, u=[-1.5, 3.0]),
    wire.Telemetry: wire.Telemetry(sender=1, seq=12, k=12, t=0.12, meas_t=0.12, p=[1.0, 2.0], vel=[3.0, 4.0], a=[5.0, 6.0],
                                   u=[7.0, 8.0], xi=[0.1, -0.1], zeta=[0.2, -0.2], kp=[1.5, 1.25], kv=[2.0, 1.0],
                                   links=LINKS, drops={"malformed": 2, "sender": 1}, late=3, mode=wire.HOLD,
                                   events=[wire.SafetyEvent(k=11, t=0.11, vehicle=1, src=wire.FLYING, dst=wire.HOLD,
                                                            reason="leader silent")], gate={"jump": 1}),
    wire.Tick: wire.Tick(sender=0, seq=4, k=40, t=0.4, grant=40),
    wire.Ack: wire.Ack(sender=0, seq=40, k=40, t=0.4, role="recorder"),
    wire.Start: wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=1.7e9),
    wire.Recorded: wire.Recorded(sender=0, seq=1, k=2000, t=20.0),
    wire.NetemSet: wire.NetemSet(sender=0, seq=0, k=0, t=0.0, at=12.5,
                                 rules=[LinkRule(profile="wifi-lossy", src=2, dst=3)]),
    wire.WorldState: wire.WorldState(sender=0, seq=7, k=7, t=0.07, p=[0.0, 0.1], vel=[0.0, 0.0],
                                     tension=[0.05, 0.05, 0.0, 0.05], slack_events=[0, 1, 2, 0]),
    wire.SafetyCommand: wire.SafetyCommand(sender=0, seq=2, k=0, t=0.0, action="land", reason="test"),
}
_TELE = SAMPLES[wire.Telemetry]
_PLANT = SAMPLES[wire.PlantState]
SAMPLES[wire.Record] = wire.Record(
    sender=1, seq=3, k=12, t=0.12,
    plant=[msgspec.structs.replace(_PLANT, sender=1, seq=k, k=k, t=k / 100) for k in (11, 12)],
    telemetry=[msgspec.structs.replace(_TELE, seq=k, k=k, t=k / 100, meas_t=k / 100) for k in (11, 12)])
"""One message of every type, with the sender id its key would carry."""

EXPECTED_TAGS = {wire.State: "state", wire.PlantState: "plant_state", wire.Command: "cmd",
                 wire.Telemetry: "telemetry", wire.Tick: "tick", wire.Ack: "ack", wire.Start: "start",
                 wire.NetemSet: "netem_set", wire.WorldState: "world_state", wire.SafetyCommand: "safety",
                 wire.Record: "record", wire.Recorded: "recorded"}


def same(a: wire.Message, b: wire.Message) -> bool:
    """Equal type and equal encoding, field for field (NaN fields make ``==`` on Structs useless)."""
    return type(a) is type(b) and wire.encode(a) == wire.encode(b)


def as_raw(msg: wire.Message, **changes: object) -> bytes:
    """``msg`` msgpack-encoded with some fields replaced or added, bypassing the Struct's types."""
    raw = msgspec.msgpack.decode(wire.encode(msg))
    raw.update(changes)
    return msgspec.msgpack.encode(raw)


# --------------------------------------------------------------------------- schema
def test_samples_cover_every_message_type() -> None:
    assert set(SAMPLES) == set(typing.get_args(wire.Message))
    assert {cls: cls.__struct_config__.tag for cls in SAMPLES} == EXPECTED_TAGS


@pytest.mark.parametrize("cls", list(SAMPLES), ids=lambda c: c.__name__)
def test_every_message_round_trips(cls: type) -> None:
    msg = SAMPLES[cls]
    payload = wire.encode(msg)
    back = wire.decode(payload)
    assert type(back) is cls
    assert same(back, msg)
    assert back.v == wire.WIRE_VERSION
    assert wire.encode(back) == payload  # re-encoding is stable byte for byte


@pytest.mark.parametrize("cls", list(SAMPLES), ids=lambda c: c.__name__)
def test_a_plain_client_decodes_with_nothing_but_the_schema(cls: type) -> None:
    """What the wire docstring promises a third-party client: one call, the union type, no helper."""
    payload = wire.encode(SAMPLES[cls])
    back = msgspec.msgpack.decode(payload, type=wire.Message)
    assert type(back) is cls and same(back, SAMPLES[cls])
    # and without the schema at all it is an ordinary msgpack map carrying its tag and version
    raw = msgspec.msgpack.decode(payload)
    assert raw["type"] == EXPECTED_TAGS[cls] and raw["v"] == wire.WIRE_VERSION


def test_messages_are_immutable_and_strict() -> None:
    with pytest.raises(AttributeError):
        SAMPLES[wire.Command].u = [0.0, 0.0]  # type: ignore[misc]
    with pytest.raises(msgspec.ValidationError, match="unknown field `spare`"):
        wire.decode(as_raw(SAMPLES[wire.Command], spare=1))
    with pytest.raises(msgspec.ValidationError, match="missing required field `u`"):
        raw = msgspec.msgpack.decode(wire.encode(SAMPLES[wire.Command]))
        del raw["u"]
        wire.decode(msgspec.msgpack.encode(raw))


# --------------------------------------------------------------------------- Receiver
@pytest.mark.parametrize("cls", list(SAMPLES), ids=lambda c: c.__name__)
def test_receiver_accepts_every_valid_message(cls: type) -> None:
    rx = Receiver(DIM)
    msg = SAMPLES[cls]
    got = rx.accept(wire.encode(msg), cls, msg.sender)
    assert got is not None and same(got, msg)
    assert rx.accept(wire.encode(msg), cls, None) is not None  # no sender expectation
    assert rx.drops == {}


STATE = SAMPLES[wire.State]
TELE = SAMPLES[wire.Telemetry]

BAD: list[tuple[str, bytes, type, str]] = [
    ("garbage bytes", b"\x00\xffnot msgpack at all", wire.State, "malformed"),
    ("empty payload (a Zenoh DELETE)", b"", wire.State, "malformed"),
    ("msgpack but not a map", msgspec.msgpack.encode([1, 2, 3]), wire.State, "malformed"),
    ("truncated", wire.encode(STATE)[:-3], wire.State, "malformed"),
    ("unknown type tag", as_raw(STATE, type="teleport"), wire.State, "malformed"),
    ("no type tag", msgspec.msgpack.encode({k: v for k, v in msgspec.msgpack.decode(wire.encode(STATE)).items()
                                            if k != "type"}), wire.State, "malformed"),
    ("field of the wrong type", as_raw(STATE, p="north"), wire.State, "malformed"),
    ("another wire version", as_raw(STATE, v=wire.WIRE_VERSION + 1), wire.State, "version"),
    ("version 0", as_raw(STATE, v=0), wire.State, "version"),
    ("wrong message type for the key", wire.encode(SAMPLES[wire.Command]), wire.State, "type"),
    ("wrong sender", as_raw(STATE, sender=STATE.sender + 1), wire.State, "sender"),
    ("vector too short", as_raw(STATE, p=[1.0]), wire.State, "size"),
    ("vector too long", as_raw(STATE, a=[0.0, 0.0, 0.0]), wire.State, "size"),
    ("telemetry gain of the wrong size", as_raw(TELE, kv=[1.0]), wire.Telemetry, "size"),
    ("NaN position", as_raw(STATE, p=[math.nan, 0.0]), wire.State, "nonfinite"),
    ("+Inf velocity", as_raw(STATE, vel=[0.0, math.inf]), wire.State, "nonfinite"),
    ("-Inf acceleration", as_raw(STATE, a=[-math.inf, 0.0]), wire.State, "nonfinite"),
    ("NaN sample time", as_raw(STATE, t=math.nan), wire.State, "nonfinite"),
    ("NaN command", as_raw(SAMPLES[wire.Command], u=[0.0, math.nan]), wire.Command, "nonfinite"),
    ("Inf in telemetry xi", as_raw(TELE, xi=[math.inf, 0.0]), wire.Telemetry, "nonfinite"),
]


@pytest.mark.parametrize(("payload", "expect", "reason"), [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_receiver_drops_and_counts_by_reason(payload: bytes, expect: type, reason: str) -> None:
    sender = {wire.State: STATE.sender, wire.Telemetry: TELE.sender, wire.Command: SAMPLES[wire.Command].sender}[expect]
    rx = Receiver(DIM)
    assert rx.accept(payload, expect, sender) is None
    assert rx.drops == {reason: 1}


def test_receiver_counts_accumulate_and_valid_messages_still_pass() -> None:
    rx = Receiver(DIM)
    for _, payload, expect, _ in BAD:
        sender = TELE.sender if expect is wire.Telemetry else (4 if expect is wire.Command else STATE.sender)
        assert rx.accept(payload, expect, sender) is None
    expected: dict[str, int] = {}
    for *_, reason in BAD:
        expected[reason] = expected.get(reason, 0) + 1
    assert rx.drops == expected
    assert sum(rx.drops.values()) == len(BAD)
    assert rx.accept(wire.encode(STATE), wire.State, STATE.sender) is not None  # nothing is poisoned
    assert sum(rx.drops.values()) == len(BAD)


def test_receiver_never_raises_on_random_bytes() -> None:
    import random

    rng = random.Random(20230601)
    rx = Receiver(DIM)
    valid = [wire.encode(m) for m in SAMPLES.values()]
    n = 3000
    for i in range(n):
        if i % 2:
            payload = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 64)))
        else:  # flip bytes of a valid message: mostly still msgpack, often still decodable
            buf = bytearray(rng.choice(valid))
            for _ in range(rng.randrange(1, 4)):
                buf[rng.randrange(len(buf))] = rng.randrange(256)
            payload = bytes(buf)
        for cls in SAMPLES:
            rx.accept(payload, cls, rng.choice([None, 0, 1, 2, 3, 4, 5]))
    assert set(rx.drops) <= {"malformed", "version", "type", "sender", "size", "nonfinite", "record"}
    assert sum(rx.drops.values()) <= n * len(SAMPLES)
    assert rx.drops["malformed"] > 0


@pytest.mark.parametrize("epoch", [math.nan, math.inf], ids=["nan", "inf"])
def test_receiver_drops_a_start_with_a_nonfinite_epoch(epoch: float) -> None:
    rx = Receiver(DIM)
    bad = wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=epoch)
    assert rx.accept(wire.encode(bad), wire.Start, 0) is None
    assert rx.drops == {"nonfinite": 1}


def test_receiver_counts_a_next_version_message_with_a_new_field_as_version() -> None:
    rx = Receiver(DIM)
    future = as_raw(STATE, v=wire.WIRE_VERSION + 1, frame="enu")
    assert rx.accept(future, wire.State, STATE.sender) is None
    assert rx.drops == {"version": 1}


# --------------------------------------------------------------------------- keys
def test_keys_build_the_documented_scheme() -> None:
    k = Keys("section4")
    assert k.topic("agent", 3, "state") == "tether/section4/agent/3/state"
    assert k.topic("leader", 5, "state") == "tether/section4/leader/5/state"
    assert k.token("plant", 2) == "@tether/section4/plant/2"
    assert k.tokens == "@tether/section4/**"
    assert k.everything == "tether/section4/**"
    assert k.tick == "tether/section4/clock/0/tick"
    assert k.start == "tether/section4/control/0/start"
    assert k.recorded == "tether/section4/control/0/recorded"
    assert k.acks == "tether/section4/*/*/ack"


@pytest.mark.parametrize(("role", "node", "topic"),
                         [("agent", 1, "state"), ("agent", 12, "cmd"), ("agent", 3, "telemetry"),
                          ("plant", 4, "state"), ("leader", 5, "state"), ("clock", 0, "tick"),
                          ("recorder", 0, "ack"), ("control", 0, "start"), ("control", 0, "recorded")])
def test_keys_parse_what_they_build(role: str, node: int, topic: str) -> None:
    k = Keys("run-7_b")
    assert Keys.parse(k.topic(role, node, topic)) == (role, node, topic)
    assert Keys.parse_token(k.token(role, node)) == (role, node)


@pytest.mark.parametrize("key", ["tether/ns/agent/1", "tether/ns/agent/1/state/extra", "other/ns/agent/1/state",
                                 "tether/ns/agent/one/state", "@tether/ns/agent/1", ""])
def test_keys_parse_rejects_what_is_not_a_tether_key(key: str) -> None:
    with pytest.raises(ValueError):
        Keys.parse(key)


@pytest.mark.parametrize("key", ["tether/ns/agent/1", "@tether/ns/agent", "@tether/ns/agent/x", "@other/ns/agent/1"])
def test_keys_parse_token_rejects_what_is_not_a_token(key: str) -> None:
    with pytest.raises(ValueError):
        Keys.parse_token(key)


@pytest.mark.parametrize("ns", ["", "a/b", "a*", "**", "a$b", "a#b", "a?b", "@ns", "two words"])
def test_keys_reject_bad_namespaces(ns: str) -> None:
    with pytest.raises(ValueError, match="namespace"):
        Keys(ns)


@pytest.mark.parametrize("ns", ["section4", "run-7_b", "Ω"])
def test_keys_accept_good_namespaces(ns: str) -> None:
    assert Keys(ns).ns == ns
