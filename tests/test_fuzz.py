"""Property-based fuzzing of the two doors bad bytes come in by: the mission loader and the wire decoder.

- :func:`tether.mission.loads` on generated TOML-ish text (random lines of keys, tables and
  values) and on generated structures (a shipped mission with a leaf replaced, a key dropped or
  added, written back as TOML): it returns a :class:`~tether.mission.Mission` or raises a
  :class:`~tether.mission.MissionError` whose every problem names a field and says how to fix it;
  nothing else, ever.
- :meth:`tether.wire.Receiver.accept` on arbitrary bytes, on valid messages with their bytes
  mutated, and on valid messages with a field replaced by any msgpack value: it returns a message
  that passes its checks or None with exactly one drop counted; it never raises.

Example counts are modest (:data:`EXAMPLES`) and the examples the same on every run, so the file
runs in seconds; hunt with ``TETHER_FUZZ_EXAMPLES=5000 TETHER_FUZZ_RANDOM=1`` in the environment.
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tether
from tether import mission as ms
from tether import wire

EXAMPLES = int(os.environ.get("TETHER_FUZZ_EXAMPLES") or 150)
FUZZ = settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow],
                derandomize=not os.environ.get("TETHER_FUZZ_RANDOM"), database=None)
"""Deterministic (the same examples on every run) and quick."""

SHIPPED = Path(tether.__file__).parent / "missions"
SECTION4 = (SHIPPED / "section4.toml").read_text(encoding="utf-8")


def _assert_clear(exc: ms.MissionError) -> None:
    assert exc.problems
    for field, message in exc.problems:
        assert field and isinstance(field, str)
        what, sep, fix = message.partition("; ")
        assert sep and what.strip() and fix.strip(), f"{field}: {message!r} says no fix"
    assert "Traceback" not in str(exc)


def _load_or_refuse(text: str | bytes) -> None:
    try:
        m = ms.loads(text, source="fuzz.toml")
    except ms.MissionError as exc:
        _assert_clear(exc)
    else:
        assert isinstance(m, ms.Mission) and ms.validate(m) == []


# --------------------------------------------------------------------------- TOML-ish text
KEYS = ["version", "name", "dim", "rate", "duration", "seed", "edges", "agents", "law", "leader", "links",
        "safety", "kind", "kp0", "kv0", "gamma_p", "gamma_v", "sigma", "id", "p0", "offset", "from", "to",
        "weight", "profile", "max_age", "gain_cap", "uri", "plant", "disturbance", "a0", "decay", "points", "t",
        "p", "v", "segments", "ramp", "x", "[", "]"]
NUMBERS = st.one_of(st.integers(-2**70, 2**70), st.floats(allow_nan=True, allow_infinity=True),
                    st.sampled_from([0.0, -0.0, 5e-324, 1e-300, 1e300, 1e308, 2**63, -1]))


def _toml_scalar(x: object) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if isinstance(x, float):
        return "nan" if x != x else "inf" if x == math.inf else "-inf" if x == -math.inf else repr(x)
    if isinstance(x, int):
        return str(x)
    return json.dumps(x)


VALUES = st.recursive(
    st.one_of(NUMBERS.map(_toml_scalar), st.booleans().map(_toml_scalar), st.text(max_size=12).map(_toml_scalar),
              st.sampled_from(['"sigma"', '"benchmark"', '"exp_accel"', '"waypoints"', '"crazyflie"',
                               '"udp://127.0.0.1:99999"', "1979-05-27", "[", "{", '"a/b"'])),
    lambda inner: st.one_of(st.lists(inner, max_size=4).map(lambda xs: "[" + ", ".join(xs) + "]"),
                            st.lists(st.tuples(st.sampled_from(KEYS), inner), max_size=3).map(
                                lambda kv: "{ " + ", ".join(f"{json.dumps(k)} = {v}" for k, v in kv) + " }")),
    max_leaves=8)
LINES = st.one_of(
    st.tuples(st.sampled_from(KEYS), VALUES).map(lambda kv: f"{kv[0]} = {kv[1]}"),
    st.sampled_from(KEYS).map(lambda k: f"[{k}]"),
    st.sampled_from(KEYS).map(lambda k: f"[[{k}]]"),
    st.text(max_size=20),
)


@FUZZ
@given(st.lists(LINES, max_size=12), st.booleans())
def test_loads_on_toml_ish_text_is_a_mission_or_a_clear_error(lines: list[str], versioned: bool) -> None:
    _load_or_refuse(("version = 1\n" if versioned else "") + "\n".join(lines))


@FUZZ
@given(st.binary(max_size=200))
def test_loads_on_arbitrary_bytes_is_a_clear_error(data: bytes) -> None:
    _load_or_refuse(data)


@FUZZ
@given(st.integers(0, len(SECTION4)), st.integers(0, 40), st.text(max_size=8))
def test_loads_on_spliced_shipped_text(at: int, cut: int, insert: str) -> None:
    _load_or_refuse(SECTION4[:at] + insert + SECTION4[at + cut:])


# --------------------------------------------------------------------------- generated structures
LEAVES = st.one_of(NUMBERS, st.booleans(), st.text(max_size=10), st.just([]), st.just({}),
                   st.lists(NUMBERS, max_size=4), st.sampled_from(["sigma", "hold", "waypoints", "a/b", ""]))


def _paths(obj: object, prefix: tuple = ()) -> list[tuple]:
    """Every path to a node of a plain-data document."""
    out = [prefix]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(obj, list):
        for k, v in enumerate(obj):
            out += _paths(v, (*prefix, k))
    return out


def _set(doc: object, path: tuple, value: object) -> object:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(doc, dict):
        return {**doc, head: _set(doc[head], rest, value)}
    copy = list(doc)  # a list
    copy[head] = _set(copy[head], rest, value)
    return copy


def _drop(doc: object, path: tuple) -> object:
    if len(path) == 1:
        if isinstance(doc, dict):
            return {k: v for k, v in doc.items() if k != path[0]}
        return [v for k, v in enumerate(doc) if k != path[0]]
    head = path[0]
    if isinstance(doc, dict):
        return {**doc, head: _drop(doc[head], path[1:])}
    copy = list(doc)
    copy[head] = _drop(copy[head], path[1:])
    return copy


def _inline(v: object) -> str:
    """A TOML value (inline tables and arrays; every key quoted)."""
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_inline(x)}" for k, x in v.items()) + " }"
    if isinstance(v, list):
        return "[" + ", ".join(_inline(x) for x in v) + "]"
    return _toml_scalar(v)


def _toml(doc: dict) -> str:
    return "\n".join(f"{json.dumps(k)} = {_inline(v)}" for k, v in doc.items()) + "\n"


BASES = [tomllib.loads((SHIPPED / f"{name}.toml").read_text(encoding="utf-8")) for name in ("section4", "exp1", "swap")]


@st.composite
def mutated_missions(draw: st.DrawFn) -> dict:
    doc = draw(st.sampled_from(BASES))
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(doc)[1:]
        path = draw(st.sampled_from(paths))
        action = draw(st.sampled_from(["replace", "replace", "drop", "add"]))
        if action == "replace":
            doc = _set(doc, path, draw(LEAVES))
        elif action == "drop":
            doc = _drop(doc, path)
        else:
            doc = {**doc, draw(st.sampled_from(KEYS)): draw(LEAVES)}
    return doc


def test_the_structure_writer_round_trips_a_shipped_mission() -> None:
    for doc in BASES:
        assert ms.loads(_toml(doc)) is not None


@FUZZ
@given(mutated_missions())
def test_loads_on_mutated_structures_is_a_mission_or_a_clear_error(doc: dict) -> None:
    _load_or_refuse(_toml(doc))


# --------------------------------------------------------------------------- the wire
DIM = 2
VALID = [
    wire.State(sender=3, seq=0, k=1, t=0.01, p=[1.0, 2.0], vel=[0.0, 0.0], a=[0.0, 0.0]),
    wire.PlantState(sender=3, seq=1, k=1, t=0.01, p=[1.0, 2.0], vel=[0.0, 0.0], a=[0.0, 0.0], d=[0.0, 0.0]),
    wire.Command(sender=3, seq=2, k=1, t=0.01, u=[0.5, -0.5], mode=wire.HOLD),
    wire.Tick(sender=0, seq=0, k=0, t=0.0, grant=8),
    wire.Ack(sender=3, seq=0, k=0, t=0.0, role="agent"),
    wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=1.7e9),
    wire.Recorded(sender=0, seq=0, k=8, t=0.08),
    wire.SafetyCommand(sender=0, seq=0, k=0, t=0.0, action="land", reason="fuzz"),
    wire.Telemetry(sender=3, seq=0, k=1, t=0.01, meas_t=0.01, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0],
                   u=[0.0, 0.0], xi=[0.0, 0.0], zeta=[0.0, 0.0], kp=[1.0, 1.0], kv=[1.0, 1.0],
                   links=[wire.LinkStats(src=5, received=1, used=1, stale=0, age=0.0, silent=False)],
                   drops={"malformed": 1}),
]
TYPES = [type(m) for m in VALID]
PAYLOADS = [wire.encode(m) for m in VALID]


def _accept(payload: bytes, expect: type, sender: int | None) -> None:
    """``accept`` never raises; it returns a checked message or None with one drop counted."""
    rx = wire.Receiver(DIM)
    msg = rx.accept(payload, expect, sender)
    dropped = sum(rx.drops.values())
    if msg is None:
        assert dropped == 1, rx.drops
        assert set(rx.drops) <= {"malformed", "version", "type", "sender", "size", "nonfinite"}
    else:
        assert dropped == 0 and isinstance(msg, expect) and msg.v == wire.WIRE_VERSION
        assert sender is None or msg.sender == sender
        assert math.isfinite(msg.t)


def test_every_valid_message_is_accepted() -> None:
    for msg, payload in zip(VALID, PAYLOADS):
        assert wire.Receiver(DIM).accept(payload, type(msg), msg.sender) == msg


@pytest.mark.parametrize("payload", [b"\x91" * 100_000, b"\x81\xa1a" * 100_000, b"\xdd\xff\xff\xff\xff", b""],
                         ids=["deep-array", "deep-map", "huge-array-header", "empty"])
def test_pathological_payloads_are_counted_drops(payload: bytes) -> None:
    _accept(payload, wire.State, 3)


@FUZZ
@given(st.binary(max_size=300), st.sampled_from(TYPES), st.one_of(st.none(), st.integers(0, 5)))
def test_accept_on_arbitrary_bytes(payload: bytes, expect: type, sender: int | None) -> None:
    _accept(payload, expect, sender)


@st.composite
def mutated_bytes(draw: st.DrawFn) -> tuple[bytes, type]:
    k = draw(st.integers(0, len(VALID) - 1))
    data = bytearray(PAYLOADS[k])
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        at = draw(st.integers(0, max(0, len(data) - 1)))
        if op == "flip" and data:
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif op == "set" and data:
            data[at] = draw(st.integers(0, 255))
        elif op == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete" and data:
            del data[at:at + draw(st.integers(1, 8))]
        elif op == "truncate":
            del data[at:]
    return bytes(data), TYPES[k]


@FUZZ
@given(mutated_bytes(), st.one_of(st.none(), st.just(3)))
def test_accept_on_mutated_valid_bytes(case: tuple[bytes, type], sender: int | None) -> None:
    payload, expect = case
    _accept(payload, expect, sender)


MSGPACK_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=8),
              st.binary(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=4), inner, max_size=3)),
    max_leaves=6)


@FUZZ
@given(st.integers(0, len(VALID) - 1), st.data())
def test_accept_on_valid_messages_with_a_field_replaced(k: int, data: st.DataObject) -> None:
    fields = msgspec.to_builtins(VALID[k])
    name = data.draw(st.sampled_from(sorted(fields) + ["extra"]))
    fields[name] = data.draw(MSGPACK_VALUES)
    _accept(msgspec.msgpack.encode(fields), TYPES[k], VALID[k].sender)
