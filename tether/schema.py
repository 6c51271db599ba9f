"""The strict-schema kit every file format of the project is built on: bases, the error, and msgspec's errors read once.

- :class:`Strict` and :class:`Kind` are the bases of every schema struct (mission, link profiles,
  hosts file, Zenoh settings): unknown fields are errors and instances are immutable; a
  :class:`Kind` is a member of a tagged union told apart by its ``kind`` field. (msgspec does not
  pass ``kw_only`` on to a subclass's own fields: a subclass that needs it, such as one adding a
  required field after inherited defaults, says ``kw_only=True`` itself.)
- :class:`SchemaError` is the one error a file that does not fit its schema raises: ``source``
  (the file, or what was being read) and :data:`Problems`, every one a ``(field path, message)``
  pair whose message reads ``"<what is wrong>; <how to fix it>"``. Each format subclasses it
  (``MissionError``, ``ProfileError``, ``HostsError``, ``SettingsError``).
- :func:`read_issue` turns a ``msgspec.ValidationError`` into an :class:`Issue`: what kind of
  mismatch it is, where (the ``$.a[0].b`` path as tokens and as ``a[0].b``), which field, which
  types. It is the only code in the project that depends on the wording of msgspec's messages
  (``tests/test_schema.py`` pins the msgspec versions it was checked against); each format words
  its own fix on top of the :class:`Issue`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import msgspec

__all__ = ["Issue", "IssueKind", "KeyPath", "Kind", "Problems", "SchemaError", "Strict", "join", "read_issue",
           "tokens"]

Problems = list[tuple[str, str]]
"""``(field path, "<what is wrong>; <how to fix it>")`` pairs."""

KeyPath = tuple[str | int, ...]
"""A field path split into names and indices: ``agents[0].p0`` is ``("agents", 0, "p0")``; a key of a
mapping, which msgspec does not name, is the token ``"[...]"``."""


class Strict(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Base of every schema struct: unknown fields are errors, instances are immutable (both are
    inherited; ``kw_only`` is not). Subclasses restate ``frozen=True``: msgspec inherits it, but a
    type checker reading ``dataclass_transform`` (PEP 681) does not, and would call them mutable."""


class Kind(Strict, tag_field="kind", frozen=True):
    """Base of the members of a tagged union, told apart by their ``kind`` field."""


class SchemaError(ValueError):
    """A file (or table) does not fit its schema. ``problems`` holds one ``(field, message)`` pair per
    problem; the message of the exception is ``"<source>: N problem(s)"`` followed by one
    ``"  <field>: <message>"`` line per problem."""

    def __init__(self, source: str, problems: Problems):
        self.source = source
        self.problems = problems
        lines = [f"{source}: {len(problems)} problem(s)"]
        lines += [f"  {field}: {msg}" for field, msg in problems]
        super().__init__("\n".join(lines))


# --------------------------------------------------------------------------- msgspec's errors
IssueKind = Literal["unknown_field", "missing_field", "wrong_type", "invalid_value", "other"]


@dataclass(frozen=True)
class Issue:
    """One ``msgspec.ValidationError``, read.

    ``kind`` is

    - ``unknown_field``: a table has a field the schema does not know (``name``);
    - ``missing_field``: a required field ``name`` is absent;
    - ``wrong_type``: the value at ``where`` is a ``got`` where one of ``expected`` was wanted;
    - ``invalid_value``: the value at ``where`` has the right type but is not allowed: not one of
      a literal's or tag's values (``value`` is msgspec's rendering of it, ``'gauss'``), or outside a
      constraint (``expected`` holds the type and ``constraint`` the rest, ``>= 0``,
      ``of length 2, got 1``);
    - ``other``: a message this reader does not know; ``text`` still says what is wrong.
    """

    kind: IssueKind
    text: str
    """msgspec's message without its location (``Expected `float`, got `str```)."""
    path: KeyPath
    """Where the offending value is (for a field that is unknown or missing: the table holding it)."""
    where: str
    """``path`` written as in a file (``agents[0].p0``); empty for the document itself."""
    name: str | None = None
    """The unknown or missing field's name."""
    expected: tuple[str, ...] = ()
    """msgspec's names of the types it wanted (``int``, ``float``, ``str``, ``array``, ``object``, ``null``...)."""
    got: str | None = None
    """msgspec's name of the type it found."""
    value: str | None = None
    """A rejected literal or tag value, as msgspec wrote it (``'gauss'``, ``3``)."""
    constraint: str | None = None
    """The constraint a value broke, as msgspec wrote it (``>= 0``)."""
    raw: str = ""
    """msgspec's whole message."""

    @property
    def field(self) -> str:
        """The path of the offending field: ``where``, joined with ``name`` when there is one."""
        return join(self.where, self.name) if self.name is not None else self.where

    @property
    def sentence(self) -> str:
        """``text`` starting with a lower-case letter, to go after a field name."""
        return self.text[:1].lower() + self.text[1:]


_AT = re.compile(r"^(?P<text>.*) - at `\$(?P<at>[^`]*)`$", re.DOTALL)
_UNKNOWN = re.compile(r"^Object contains unknown field `(?P<name>[^`]*)`$")
_MISSING = re.compile(r"^Object missing required field `(?P<name>[^`]*)`$")
_WRONG = re.compile(r"^Expected `(?P<want>[^`]*)`, got `(?P<got>[^`]*)`$")
_CONSTRAINT = re.compile(r"^Expected `(?P<want>[^`]*)` (?P<rest>.+)$", re.DOTALL)
_BAD_VALUE = re.compile(r"^Invalid (?:enum )?value (?P<value>.+)$", re.DOTALL)
_TOKEN = re.compile(r"\.?([^.\[\]]+)|\[(\d+)\]|\[(\.\.\.)\]")


def tokens(where: str) -> KeyPath:
    """``"agents[0].p0"`` -> ``("agents", 0, "p0")``; a mapping key ``[...]`` is the token ``"[...]"``."""
    out: list[str | int] = []
    for name, index, key in _TOKEN.findall(where):
        out.append(int(index) if index else "[...]" if key else name)
    return tuple(out)


def join(where: str, name: str) -> str:
    """The path of field ``name`` of the table at ``where`` (``where`` empty: the document)."""
    return f"{where}.{name}" if where else name


def read_issue(exc: msgspec.ValidationError | str) -> Issue:
    """Read a ``msgspec.ValidationError`` (or its text) into an :class:`Issue`. Pure; never raises.

    msgspec writes ``"<text> - at `$.a[0].b`"``, leaving the location out at the document's root.
    """
    raw = str(exc)
    at = _AT.match(raw)
    text, where = (at["text"], at["at"].removeprefix(".")) if at else (raw, "")
    path = tokens(where)

    def issue(kind: IssueKind, name: str | None = None, expected: str = "", got: str | None = None,
              value: str | None = None, constraint: str | None = None) -> Issue:
        wanted = tuple(expected.split(" | ")) if expected else ()
        return Issue(kind, text, path, where, name, wanted, got, value, constraint, raw)

    if m := _UNKNOWN.match(text):
        return issue("unknown_field", name=m["name"])
    if m := _MISSING.match(text):
        return issue("missing_field", name=m["name"])
    if m := _WRONG.match(text):
        return issue("wrong_type", expected=m["want"], got=m["got"])
    if m := _CONSTRAINT.match(text):
        return issue("invalid_value", expected=m["want"], constraint=m["rest"])
    if m := _BAD_VALUE.match(text):
        return issue("invalid_value", value=m["value"])
    return issue("other")


def close_matches(word: str, choices: list[str], n: int = 1) -> list[str]:
    """``difflib.get_close_matches``: the spelling suggestion of a message about a mistake. Imported
    here, when a mistake is being explained, not by every process that reads a mission."""
    import difflib

    return difflib.get_close_matches(word, choices, n=n)
