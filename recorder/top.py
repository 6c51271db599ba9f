"""``tether top``: a live terminal monitor of a running swarm, one row per vehicle.

It is a plain Zenoh client that hears the telemetry the agents already publish
(``tether/<ns>/agent/<i>/telemetry``, :class:`tether.wire.Telemetry`) and the swarm's liveliness
tokens, and draws with ``rich`` in an ordinary terminal (over SSH too): per vehicle its safety mode,
‖ξ_i‖, the law's state by the names the law gives it (Eq. 17's gains ``kp kv``, the integral
law's ``kp kv s``; per axis), ‖u_i‖, the worst link's delivery ratio and age p99, the
clock-offset estimate of its most offset input link (``Telemetry.clock``, :mod:`tether.skew`;
``!`` and red when the agent flagged it, as the run's warning does), and the last event: its supervisor's
newest mode change, or its plant's watchdog's newest event when that came later (``plant t=…``, from
``tether/<ns>/plant/<i>/state``, :attr:`tether.wire.PlantState.events`). Trouble is coloured: a mode other than FLYING, an agent whose token is gone or whose
telemetry stopped, ‖ξ_i‖ beyond ``xi_warn``, a link delivering less than 90 % or older than
``age_warn``, a clock offset outside :func:`tether.skew.bounds`, a non-finite value. ``q`` or Ctrl-C quits.

:class:`Board` is the monitor's state, fed sample by sample (no I/O; malformed samples are dropped and
counted, never raised); :func:`run` is the terminal loop around it.
"""

from __future__ import annotations

import asyncio
import math
import os
import re
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import msgspec

from tether import wire

if TYPE_CHECKING:
    from rich.table import Table

STALE = 1.0
"""An agent whose newest telemetry is this old [s, wall] is shown STALE."""
XI_WARN = 0.5
"""‖ξ_i‖ shown red beyond this [m] (``--xi-warn``)."""
AGE_WARN = 0.1
"""A link's age p99 shown amber beyond this [s] (``--age-warn``)."""
DELIVERY_WARN = 0.9
"""A link's delivery ratio shown amber below this."""
REFRESH = 0.25
"""Seconds between redraws."""


@dataclass
class Row:
    """What the monitor knows of one vehicle."""

    vehicle: int
    msg: wire.Telemetry | None = None
    heard: float | None = None
    """When its newest telemetry came [s, monotonic]."""
    alive: bool | None = None
    """Its agent's liveliness token: present, gone, or never seen (None)."""
    last_event: wire.SafetyEvent | None = None
    last_plant_event: wire.SafetyEvent | None = None
    """The newest event its plant's watchdog reported (a mode change, a rejected or clamped command)."""
    plant: wire.PlantState | None = None
    """Its plant's newest sample (the watchdog's mode)."""


@dataclass
class Board:
    """The monitor's state: a row per vehicle, the drops, the newest mission time."""

    ns: str
    xi_warn: float = XI_WARN
    age_warn: float = AGE_WARN
    rows: dict[int, Row] = field(default_factory=dict)
    drops: dict[str, int] = field(default_factory=dict)
    t: float | None = None
    """The newest mission time heard [s]."""

    def _drop(self, reason: str) -> None:
        self.drops[reason] = self.drops.get(reason, 0) + 1

    def _row(self, vehicle: int) -> Row:
        if vehicle not in self.rows:
            self.rows[vehicle] = Row(vehicle)
        return self.rows[vehicle]

    def _decode(self, key: str, payload: bytes, role: str, topic: str, kind: type) -> Any:
        """The message on ``key`` when it is a ``kind`` on ``tether/<ns>/<role>/<i>/<topic>`` from
        sender i, of this wire version, with a finite time; else None, dropped and counted by reason."""
        try:
            got_role, vehicle, got_topic = wire.Keys.parse(key)
        except ValueError:
            self._drop("key")
            return None
        if got_role != role or got_topic != topic:
            self._drop("key")
            return None
        try:
            msg = wire.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, RecursionError):
            self._drop("malformed")
            return None
        if not isinstance(msg, kind):
            self._drop("type")
            return None
        if msg.v != wire.WIRE_VERSION:
            self._drop("version")
            return None
        if msg.sender != vehicle:
            self._drop("sender")
            return None
        if not math.isfinite(msg.t):
            self._drop("nonfinite")
            return None
        return msg

    def plant(self, key: str, payload: bytes) -> None:
        """One sample on ``tether/<ns>/plant/<i>/state``: its watchdog's newest event is kept for
        vehicle i (an older one than held is ignored); a bad sample is dropped and counted by reason."""
        msg = self._decode(key, payload, "plant", "state", wire.PlantState)
        if msg is None:
            return
        row = self._row(msg.sender)
        if row.plant is None or msg.k > row.plant.k:
            row.plant = msg
        if not msg.events:
            return
        newest = max(msg.events, key=lambda e: (e.k, e.t))
        if row.last_plant_event is None or (newest.k, newest.t) >= (row.last_plant_event.k, row.last_plant_event.t):
            row.last_plant_event = newest

    def telemetry(self, key: str, payload: bytes, now: float) -> None:
        """One sample on ``tether/<ns>/agent/<i>/telemetry``: kept when it is agent i's, newer
        than the one held, and well formed; else dropped and counted by reason."""
        msg = self._decode(key, payload, "agent", "telemetry", wire.Telemetry)
        if msg is None:
            return
        vehicle = msg.sender
        row = self._row(vehicle)
        if row.msg is not None and msg.k <= row.msg.k:
            self._drop("stale")
            return
        row.msg, row.heard = msg, now
        if msg.events:
            row.last_event = max(msg.events, key=lambda e: (e.k, e.t))
        self.t = msg.t if self.t is None else max(self.t, msg.t)

    def token(self, key: str, alive: bool) -> None:
        """A liveliness change; only agents' tokens make rows."""
        try:
            role, vehicle = wire.Keys.parse_token(key)
        except ValueError:
            return
        if role == "agent":
            self._row(vehicle).alive = alive

    def state_heading(self) -> str:
        """The law state column's heading: the names the law gives its state variables, as the
        agents' telemetry says them (``kp  kv  s (per axis)``); ``Kp  Kv`` before any says them."""
        named = [law_state(r.msg)[0] for r in self.rows.values() if r.msg is not None and r.msg.x_names]
        names = max(named, key=len, default=["Kp", "Kv"])
        return "  ".join(names) + " (per axis)"

    def cells(self, row: Row, now: float) -> tuple[list[str], list[str]]:
        """The row's cells as text, and a style per cell ("" for none)."""
        msg = row.msg
        plant, pstyle = self._plant(row)
        if msg is None:
            state = "GONE" if row.alive is False else "no telemetry"
            return ([str(row.vehicle), state, plant] + ["-"] * 7,
                    ["bold", "red" if row.alive is False else "dim", pstyle] + [""] * 7)
        mode = wire.MODES[msg.mode] if 0 <= msg.mode < len(wire.MODES) else f"mode {msg.mode}"
        styles = ["bold"]
        age = now - row.heard if row.heard is not None else math.inf
        if row.alive is False:
            mode, mstyle = f"GONE ({mode})", "bold red"
        elif age > STALE:
            mode, mstyle = f"STALE {age:.0f}s ({mode})", "bold red"
        else:
            mstyle = {"FLYING": "green", "HOLD": "yellow", "LAND": "dark_orange", "LANDED": "dim",
                      "ESTOP": "bold red"}.get(mode, "red")
        styles.append(mstyle)
        styles.append(pstyle)
        xi = _norm(msg.xi)
        styles.append("red" if not xi <= self.xi_warn else "")
        _, values = law_state(msg)
        gains = "  ".join("/".join(_num(x) for x in v) for v in values)
        styles.append("red" if not all(math.isfinite(x) for v in values for x in v) else "")
        u = _norm(msg.u)
        styles.append("red" if not math.isfinite(u) else "")
        links = msg.links
        delivery = min((s.delivery for s in links), default=math.nan)
        p99 = max((s.age_p99 for s in links), default=math.nan)
        silent = any(s.silent for s in links)
        styles.append("yellow" if silent or (math.isfinite(delivery) and delivery < DELIVERY_WARN) else "")
        styles.append("yellow" if silent or (math.isfinite(p99) and p99 > self.age_warn) else "")
        clock, cstyle = _clock(msg.clock)
        styles.append(cstyle)
        event, ev = "-", row.last_event
        if ev is not None:
            event = f"t={ev.t:.1f}s {_mode(ev.src)}->{_mode(ev.dst)} {_reason(ev.reason)}"
        pev = row.last_plant_event
        if pev is not None and (ev is None or pev.t > ev.t):  # the plant's watchdog spoke last
            change = _mode(pev.dst) if pev.src == pev.dst else f"{_mode(pev.src)}->{_mode(pev.dst)}"
            event = f"plant t={pev.t:.1f}s {change} {_reason(pev.reason)}"
        styles.append("yellow" if event != "-" else "")
        link_delivery = "-" if not links else f"{delivery:.0%}" + (" silent" if silent else "")
        link_age = "-" if not math.isfinite(p99) else f"{p99 * 1000:.0f} ms"
        return ([str(row.vehicle), mode, plant, _num(xi, 3), gains, _num(u, 2), link_delivery, link_age, clock,
                 event], styles)

    def _plant(self, row: Row) -> tuple[str, str]:
        """The plant watchdog's mode cell: its mode (``STALE`` when its samples stopped), and a style."""
        if row.plant is None:
            return "-", "dim"
        mode = _mode(row.plant.mode)
        return mode, {"FLYING": "green", "HOLD": "yellow", "LAND": "dark_orange", "LANDED": "dim",
                      "ESTOP": "bold red"}.get(mode, "red")

    def table(self, now: float, where: str = "") -> Table:
        """The monitor as a ``rich`` renderable."""
        from rich.table import Table

        heading = f"tether top: namespace {self.ns!r}"
        if where:
            heading += f" via {where}"
        heading += f", t = {self.t:.2f} s" if self.t is not None else ", waiting for telemetry"
        dropped = sum(self.drops.values())
        caption = "q: quit" + (f"   dropped {dropped} sample(s): " + ", ".join(
            f"{n} {why}" for why, n in sorted(self.drops.items())) if dropped else "")
        t = Table(title=heading, caption=caption, expand=False)
        for name, justify in (("vehicle", "right"), ("mode", "left"), ("plant", "left"), ("|xi| [m]", "right"),
                              (self.state_heading(), "left"), ("|u| [m/s2]", "right"), ("link delivery", "right"),
                              ("age p99", "right"), ("clock", "right"), ("last event", "left")):
            t.add_column(name, justify=justify)  # type: ignore[arg-type]
        for vehicle in sorted(self.rows):
            cells, styles = self.cells(self.rows[vehicle], now)
            t.add_row(*[f"[{s}]{_escape(c)}[/]" if s else _escape(c) for c, s in zip(cells, styles)])
        return t


def law_state(msg: wire.Telemetry) -> tuple[list[str], list[list[float]]]:
    """The law's state variables of ``msg``: their names and per-axis values (``Telemetry.x`` with
    ``x_names``); the first two, ``kp`` and ``kv``, from a telemetry that does not name them."""
    if msg.x_names:
        d = len(msg.x) // len(msg.x_names)
        return list(msg.x_names), [msg.x[s * d:(s + 1) * d] for s in range(len(msg.x_names))]
    return ["Kp", "Kv"], [msg.kp, msg.kv]


def _clock(links: list[wire.ClockLink]) -> tuple[str, str]:
    """The clock cell: the input link whose offset bound is largest in size (a flagged one first),
    as ``agent/1 +31.2 ms``, ``!`` and red when its agent flagged it; ``-`` before any estimate."""
    finite = [c for c in links if math.isfinite(c.offset)]
    if not finite:
        return "-", ""
    worst = max(finite, key=lambda c: (c.warn, abs(c.offset)))
    text = f"{worst.role}/{worst.src} {1000 * worst.offset:+.1f} ms"
    return (text + " !", "bold red") if worst.warn else (text, "")


_NO_ID = re.compile(r"\b(neighbours?)(?=\s*$|\s{2}|\s(?:lost|back|holding|no longer)\b)")


def _reason(text: str) -> str:
    """An event's reason for the table: a role named without its id (``neighbour  lost``, as an
    empty list of ids reads) says ``(no id)`` instead of showing a blank where an id belongs."""
    return re.sub(r"\s{2,}", " ", _NO_ID.sub(r"\1 (no id)", text))


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text)


def _norm(v: list[float]) -> float:
    return math.sqrt(sum(x * x for x in v))


def _num(x: float, digits: int = 2) -> str:
    return f"{x:.{digits}f}" if math.isfinite(x) else str(x)


def _mode(code: int) -> str:
    return wire.MODES[code] if 0 <= code < len(wire.MODES) else str(code)


class _Keys:
    """``q`` on a terminal's stdin, read without echo or line buffering (restored on exit)."""

    def __init__(self, on_quit: Callable[[], None]):
        self.on_quit = on_quit
        self.saved: list | None = None
        self.fd = sys.stdin.fileno() if sys.stdin is not None and sys.stdin.isatty() else None

    def __enter__(self) -> _Keys:
        if self.fd is not None:
            import termios
            import tty

            self.saved = termios.tcgetattr(self.fd)
            tty.setcbreak(self.fd)
            asyncio.get_running_loop().add_reader(self.fd, self._read)
        return self

    def _read(self) -> None:
        assert self.fd is not None
        data = os.read(self.fd, 64)
        if not data or b"q" in data or b"Q" in data:
            self.on_quit()

    def __exit__(self, *exc: object) -> None:
        if self.fd is not None:
            import termios

            asyncio.get_running_loop().remove_reader(self.fd)
            if self.saved is not None:
                termios.tcsetattr(self.fd, termios.TCSADRAIN, self.saved)


RETRY = 0.5
"""How often to try the swarm's router again while it does not answer [s] (as ``tether record``)."""


class NoSwarm(Exception):
    """The swarm's router did not answer within the wait (``--wait``)."""


async def run(settings: object, ns: str, where: str, xi_warn: float = XI_WARN, age_warn: float = AGE_WARN,
              wait: float = math.inf, say: Callable[[str], None] = lambda line: print(line, file=sys.stderr)) -> int:
    """Open a session with ``settings`` (a :class:`tether.transport.ZenohSettings`), trying the
    swarm's router every :data:`RETRY` s for up to ``wait`` s while it does not answer (``say``-ing
    once that it waits), then show the monitor until ``q``, Ctrl-C or SIGTERM; returns 0. Raises
    :class:`NoSwarm` when the router never answered within ``wait``. Blocks until then."""
    from tether import transport as tp

    if not isinstance(settings, tp.ZenohSettings):
        raise TypeError("settings: a tether.transport.ZenohSettings")
    quit_ = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, quit_.set)
    try:
        deadline = time.monotonic() + wait
        told = False
        while not quit_.is_set():
            opened = False
            try:
                async with tp.open_session(settings) as session:
                    opened = True
                    await _monitor(session, ns, where, Board(ns, xi_warn=xi_warn, age_warn=age_warn), quit_)
                    return 0
            except tp.TransportError as exc:
                if opened:
                    raise
                left = deadline - time.monotonic()
                if left <= 0:
                    raise NoSwarm(f"no answer from the swarm's router at {where} within {wait:g} s "
                                  f"({str(exc).splitlines()[0]})") from None
                if not told:
                    say(f"tether top: waiting for the swarm's router at {where} "
                        f"(trying every {RETRY:g} s{'' if math.isinf(wait) else f' for up to {wait:g} s'}; "
                        "Ctrl-C stops)")
                    told = True
            try:
                async with asyncio.timeout(min(RETRY, max(left, 0.0))):
                    await quit_.wait()
            except TimeoutError:
                pass
        return 0
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


async def _monitor(session: Any, ns: str, where: str, board: Board, quit_: asyncio.Event) -> None:
    """The monitor on an open session until ``quit_`` is set (``q`` sets it)."""
    from rich.console import Console
    from rich.live import Live

    from tether import handoff
    from tether import transport as tp

    keys = wire.Keys(ns)
    samples: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(4096)
    plants: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(4096)
    tokens: handoff.BoundedFifo[tp.TokenEvent] = handoff.BoundedFifo(1024)
    console = Console()
    declared = [tp.declare_subscriber(session, f"tether/{ns}/agent/*/telemetry", samples),
                tp.declare_subscriber(session, f"tether/{ns}/plant/*/state", plants),
                tp.watch_tokens(session, keys.tokens, tokens)]
    try:
        with _Keys(quit_.set), Live(board.table(time.monotonic(), where), console=console, screen=True,
                                    auto_refresh=False) as live:
            while not quit_.is_set():
                try:  # a redraw every REFRESH s, however many samples come
                    async with asyncio.timeout(REFRESH):
                        await quit_.wait()
                except TimeoutError:
                    pass
                now = time.monotonic()
                for rec in samples.drain():
                    board.telemetry(rec.key, rec.payload, now)
                for rec in plants.drain():
                    board.plant(rec.key, rec.payload)
                for ev in tokens.drain():
                    board.token(ev.key, ev.alive)
                if samples.dropped or plants.dropped:
                    board.drops["overflow"] = samples.dropped + plants.dropped
                live.update(board.table(now, where), refresh=True)
    finally:
        for d in declared:
            d.undeclare()
