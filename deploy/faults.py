"""Fault injection for ``tether run --fault``: what a fault is, and its parser. Pure.

A fault is written ``KIND:TARGET@T[+D]``:

* ``kill:agent/2@10`` — SIGKILL agent 2's process at mission time 10 s;
* ``freeze:leader@5+3`` — SIGSTOP the leader at 5 s, SIGCONT it 3 s later;
* ``partition:agent/3@8+2`` — cut agent 3's process off the network for 2 s from 8 s
  (``deploy/inject.py`` says exactly what that emulates);
* ``forge:leader@12`` — publish one well-formed but far-off sample on the leader's state key at
  12 s, with the leader's sender id and its next sequence number;
* ``skew:agent/2=+0.05`` — agent 2's clock reads 0.05 s ahead (negative: behind) for the whole run
  (real time only): the process gets ``--clock-skew``, which offsets the wall clock injected into
  its :class:`~tether.clock.RealtimeClock`, so it places the run's start instant, every tick and
  every sample time it stamps that much early, as an unsynchronised host would. No ``@T``.

``TARGET`` is ``leader`` (or ``leader/<id>``), ``agent/<id>``, ``plant/<id>``, ``world`` or
``recorder``. ``T`` and ``D`` are seconds of mission time (real time: since tick 0; lockstep: the
tick clock, the fault fires when the run reaches tick ``round(T / h)``; a freeze or partition then
lasts ``D`` seconds of wall time, during which the lockstep clock cannot advance).

:func:`parse` checks the text alone; :func:`check` checks parsed faults against a mission (the
target exists, the times are within the run). Both name the ``--fault`` argument and the fix.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from tether import mission as ms

Kind = Literal["kill", "freeze", "partition", "forge", "skew"]
KINDS: tuple[Kind, ...] = ("kill", "freeze", "partition", "forge", "skew")
NEEDS_DURATION = frozenset({"freeze", "partition"})
ROLES = ("leader", "agent", "plant", "world", "recorder")
FORGE_OFFSET = 1.0e6
"""How far a forged sample's position is from the victim's newest real one [m, every axis]."""


class FaultError(ValueError):
    """A ``--fault`` value that cannot be used; the message names it and says how to fix it."""


@dataclass(frozen=True)
class Fault:
    """One fault to inject."""

    kind: Kind
    role: str
    """``leader``, ``agent``, ``plant``, ``world`` or ``recorder``."""
    node_id: int | None
    """The process's id; None for ``leader`` written without one (the mission's leader)."""
    at: float
    """When it fires [s; mission time]."""
    duration: float | None = None
    """How long a freeze or partition lasts [s]; None for kill and forge."""
    text: str = ""
    """The argument as given (for messages)."""
    skew: float = 0.0
    """A skew's clock offset [s] (the process's clock is ahead by this much); 0 for other kinds."""

    @property
    def target(self) -> str:
        """``agent/2``; ``leader`` when the id was left out."""
        return self.role if self.node_id is None else f"{self.role}/{self.node_id}"

    def member(self, mission: ms.Mission) -> tuple[str, int]:
        """The ``(role, id)`` of the launched process this fault hits."""
        if self.node_id is not None:
            return self.role, self.node_id
        return self.role, mission.leader.id if self.role == "leader" else 0


def _seconds(text: str, what: str, arg: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FaultError(f"--fault {arg!r}: {what} {text!r} is not a number of seconds; "
                         "write e.g. kill:agent/2@10 or freeze:leader@5+3") from None
    if not math.isfinite(value) or value < 0:
        raise FaultError(f"--fault {arg!r}: {what} is {text}; give a finite number of seconds >= 0")
    return value


def _target(arg: str, target: str) -> tuple[str, int | None]:
    role, slash, nid = target.partition("/")
    if role not in ROLES:
        raise FaultError(f"--fault {arg!r}: unknown process {target!r}; use leader, agent/<id>, plant/<id>, "
                         "world or recorder")
    node_id: int | None = None
    if slash:
        try:
            node_id = int(nid)
        except ValueError:
            raise FaultError(f"--fault {arg!r}: {target!r} has no integer id; write e.g. {role}/2") from None
    elif role in ("agent", "plant"):
        raise FaultError(f"--fault {arg!r}: which {role}? write {role}/<id>, e.g. {role}/2")
    return role, node_id


def _skew(arg: str, rest: str) -> Fault:
    """``skew:TARGET=S``: a clock offset for the whole run."""
    from tether.clock import check_skew

    target, sep, value = rest.partition("=")
    if not sep or "@" in rest:
        raise FaultError(f"--fault {arg!r}: a skew is skew:TARGET=S (seconds ahead, for the whole run), "
                         "e.g. skew:agent/2=+0.05; it takes no @T")
    role, node_id = _target(arg, target)
    try:
        offset = float(value)
    except ValueError:
        raise FaultError(f"--fault {arg!r}: the skew {value!r} is not a number of seconds; write e.g. "
                         f"skew:{target}=+0.05") from None
    if (why := check_skew(offset, "the skew")) is not None:
        raise FaultError(f"--fault {arg!r}: {why}")
    if offset == 0:
        raise FaultError(f"--fault {arg!r}: the skew is 0; give a non-zero offset in seconds, e.g. +0.05")
    return Fault("skew", role, node_id, 0.0, None, arg, skew=offset)


def parse(text: str) -> Fault:
    """``KIND:TARGET@T[+D]`` -> :class:`Fault`. Raises :class:`FaultError` naming the argument."""
    arg = text
    kind, sep, rest = text.strip().partition(":")
    if not sep:
        raise FaultError(f"--fault {arg!r} is not KIND:TARGET@T[+D]; write e.g. kill:agent/2@10, "
                         "freeze:leader@5+3, partition:agent/3@8+2 or forge:leader@12")
    if kind not in KINDS:
        raise FaultError(f"--fault {arg!r}: unknown kind {kind!r}; use one of {', '.join(KINDS)}")
    if kind == "skew":
        return _skew(arg, rest)
    target, sep, when = rest.partition("@")
    if not sep:
        raise FaultError(f"--fault {arg!r} has no time; add @T (mission time [s]), e.g. {kind}:{target}@10")
    role, node_id = _target(arg, target)
    at_text, plus, dur_text = when.partition("+")
    at = _seconds(at_text, "the time", arg)
    duration: float | None = None
    if kind in NEEDS_DURATION:
        if not plus:
            raise FaultError(f"--fault {arg!r}: a {kind} needs a duration; write {kind}:{target}@{at_text}+D "
                             "(D seconds)")
        duration = _seconds(dur_text, "the duration", arg)
        if duration == 0:
            raise FaultError(f"--fault {arg!r}: the duration is 0; give D > 0 seconds")
    elif plus:
        raise FaultError(f"--fault {arg!r}: a {kind} takes no duration; drop '+{dur_text}'")
    if kind == "forge" and role not in ("leader", "agent", "plant"):
        raise FaultError(f"--fault {arg!r}: a {role} publishes no state to forge; forge leader, agent/<id> "
                         "or plant/<id>")
    return Fault(kind, role, node_id, at, duration, arg)


def check(faults: list[Fault], mission: ms.Mission, members: list[tuple[str, int]]) -> list[tuple[str, str]]:
    """Every problem of ``faults`` for this mission and launch (``members``: the processes it
    starts), as ``(argument, message)``."""
    out: list[tuple[str, str]] = []
    names = sorted({f"{r}/{i}" for r, i in members})
    skewed: dict[tuple[str, int], str] = {}
    for f in faults:
        arg = f"--fault {f.text}"
        if f.member(mission) not in members:
            out.append((arg, f"this mission has no process {f.target}; use one of {', '.join(names)}"))
        if f.kind == "skew":
            if f.member(mission) in skewed:
                out.append((arg, f"{f.target} already has a skew ({skewed[f.member(mission)]}); give one per process"))
            skewed.setdefault(f.member(mission), f.text)
        if f.at > mission.duration:
            out.append((arg, f"fires at {f.at:g} s, after the run's end ({mission.duration:g} s); give a time "
                             "within the mission's duration (or a longer --duration)"))
        if f.duration is not None and f.duration > mission.duration:
            out.append((arg, f"lasts {f.duration:g} s, longer than the whole run ({mission.duration:g} s); give "
                             f"at most {mission.duration:g} s (the run's end also ends a {f.kind})"))
    return out
