"""The schema kit: the one reader of msgspec's error messages, fed real errors of every kind.

:func:`tether.schema.read_issue` is the only code that depends on how msgspec words a
``ValidationError``; every file format's fix hints stand on what it returns. These tests produce
each kind of error with ``msgspec.convert`` on small structs and check what is read, so that a
msgspec release that rewords its messages fails here, by name, rather than as vaguer hints in every
format.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec
import pytest

from deploy import hosts
from tether import mission, netprofile, schema, transport

TESTED_MSGSPEC = {"0.23.0"}
"""msgspec releases whose error wording these tests were checked against."""


def test_msgspec_is_a_tested_release() -> None:
    assert msgspec.__version__ in TESTED_MSGSPEC, (
        f"msgspec {msgspec.__version__} is installed but tether.schema.read_issue was written against "
        f"{sorted(TESTED_MSGSPEC)}: run this file's other tests; if they pass, add the version to "
        "TESTED_MSGSPEC; if not, adapt read_issue's patterns to the new wording (nothing else in the "
        "project reads msgspec's messages)"
    )


class Inner(schema.Strict):
    n: Annotated[int, msgspec.Meta(ge=0)] = 0
    pair: tuple[float, float] = (0.0, 0.0)


class One(schema.Kind, tag="one"):
    x: int = 0


class Two(schema.Kind, tag="two"):
    y: int = 0


class Doc(schema.Strict):
    a: int
    b: float = 0.0
    mode: Literal["fast", "slow"] = "fast"
    items: list[Inner] = []
    maybe: int | None = None
    choice: One | Two = One()
    table: dict[str, Inner] = {}
    src: int = msgspec.field(default=0, name="from")


def _issue(raw: object) -> schema.Issue:
    with pytest.raises(msgspec.ValidationError) as info:
        msgspec.convert(raw, type=Doc)
    return schema.read_issue(info.value)


CASES = [
    # raw document, kind, path, where, name, expected, got, value, constraint
    ({"a": 1, "zz": 2}, "unknown_field", (), "", "zz", (), None, None, None),
    ({"a": 1, "items": [{}, {"nn": 1}]}, "unknown_field", ("items", 1), "items[1]", "nn", (), None, None, None),
    ({}, "missing_field", (), "", "a", (), None, None, None),
    ({"a": 1, "choice": {}}, "missing_field", ("choice",), "choice", "kind", (), None, None, None),
    ({"a": "1"}, "wrong_type", ("a",), "a", None, ("int",), "str", None, None),
    ({"a": 1.5}, "wrong_type", ("a",), "a", None, ("int",), "float", None, None),
    ({"a": True}, "wrong_type", ("a",), "a", None, ("int",), "bool", None, None),
    ({"a": 1, "maybe": "x"}, "wrong_type", ("maybe",), "maybe", None, ("int", "null"), "str", None, None),
    ({"a": 1, "items": [{}, {"n": "x"}]}, "wrong_type", ("items", 1, "n"), "items[1].n", None, ("int",), "str",
     None, None),
    ({"a": 1, "items": 3}, "wrong_type", ("items",), "items", None, ("array",), "int", None, None),
    ({"a": 1, "choice": 5}, "wrong_type", ("choice",), "choice", None, ("object",), "int", None, None),
    ({"a": 1, "table": {"k": {"n": "x"}}}, "wrong_type", ("table", "[...]", "n"), "table[...].n", None,
     ("int",), "str", None, None),
    (5, "wrong_type", (), "", None, ("object",), "int", None, None),
    ({"a": 1, "mode": "medium"}, "invalid_value", ("mode",), "mode", None, (), None, "'medium'", None),
    ({"a": 1, "choice": {"kind": "three"}}, "invalid_value", ("choice", "kind"), "choice.kind", None, (), None,
     "'three'", None),
    ({"a": 1, "items": [{"n": -1}]}, "invalid_value", ("items", 0, "n"), "items[0].n", None, ("int",), None,
     None, ">= 0"),
    ({"a": 1, "items": [{"pair": [1.0]}]}, "invalid_value", ("items", 0, "pair"), "items[0].pair", None,
     ("array",), None, None, "of length 2, got 1"),
]


@pytest.mark.parametrize(("raw", "kind", "path", "where", "name", "expected", "got", "value", "constraint"), CASES,
                         ids=[f"{c[1]}:{c[3] or '$'}" for c in CASES])
def test_every_kind_of_validation_error_is_read(raw: object, kind: str, path: tuple[object, ...], where: str,
                                                name: str | None, expected: tuple[str, ...], got: str | None,
                                                value: str | None, constraint: str | None) -> None:
    issue = _issue(raw)
    assert (issue.kind, issue.path, issue.where, issue.name) == (kind, path, where, name), issue
    assert (issue.expected, issue.got, issue.value, issue.constraint) == (expected, got, value, constraint), issue
    assert issue.field == (schema.join(where, name) if name else where)
    assert " - at `$" not in issue.text and issue.text in issue.raw
    assert issue.sentence[:1].islower() and issue.sentence[1:] == issue.text[1:]


def test_a_field_is_named_as_in_the_file() -> None:
    issue = _issue({"a": 1, "from": "x"})
    assert issue.where == "from" and issue.kind == "wrong_type"


def test_text_it_does_not_know_is_kept_as_other() -> None:
    issue = schema.read_issue("Something new happened - at `$.agents[2].p0`")
    assert (issue.kind, issue.path, issue.where, issue.text) == ("other", ("agents", 2, "p0"), "agents[2].p0",
                                                                 "Something new happened")
    bare = schema.read_issue("Something new happened")
    assert (bare.kind, bare.path, bare.where, bare.field) == ("other", (), "", "")


def test_a_value_that_looks_like_a_location_is_not_one() -> None:
    issue = _issue({"a": 1, "mode": "x - at `$.b`"})
    assert issue.kind == "invalid_value" and issue.where == "mode" and issue.value == "'x - at `$.b`'"


def test_tokens_and_join() -> None:
    assert schema.tokens("agents[0].p0") == ("agents", 0, "p0")
    assert schema.tokens("[3]") == (3,)
    assert schema.tokens("") == ()
    assert schema.join("", "a") == "a" and schema.join("a[0]", "b") == "a[0].b"


def test_strict_bases() -> None:
    """Subclasses inherit strictness, immutability and the tag field (msgspec does not pass kw_only
    on to a subclass's own fields)."""
    for cls in (Inner, Doc, One):
        config = cls.__struct_config__
        assert config.forbid_unknown_fields and config.frozen, cls
    with pytest.raises(AttributeError):
        Inner().n = 1  # type: ignore[misc]
    assert One.__struct_config__.tag_field == "kind" and Two.__struct_config__.tag == "two"
    assert msgspec.convert({"kind": "two", "y": 2}, type=One | Two) == Two(y=2)


def test_every_format_error_is_a_schema_error_with_the_same_message() -> None:
    problems = [("a.b", "is 1; use 2"), ("c", "is missing; add it")]
    expected = "src: 2 problem(s)\n  a.b: is 1; use 2\n  c: is missing; add it"
    for cls in (schema.SchemaError, mission.MissionError, netprofile.ProfileError, hosts.HostsError):
        err = cls("src", problems)
        assert isinstance(err, schema.SchemaError) and isinstance(err, ValueError)
        assert (str(err), err.source, err.problems) == (expected, "src", problems)
    settings = transport.SettingsError(problems)
    assert isinstance(settings, schema.SchemaError) and settings.problems == problems
    assert str(settings) == expected.replace("src:", "zenoh settings:")
