"""The operator's stop commands: ``tether land`` and ``tether estop``.

Each publishes one :class:`~tether.wire.SafetyCommand` on ``tether/<ns>/control/0/safety`` (the
control key; under the generated access rules only the operator identity, ``control-0``, may
publish there, and every agent and plant subscribes to it), then exits::

    tether land --ns section4 --connect tcp/127.0.0.1:7447 --reason "wind"
    tether estop --ns trio --zenoh-config /etc/tether/control-0.json5

The order is sent :data:`REPEATS` times over :data:`SPREAD` seconds, byte for byte the same
message (same ``seq``, ``k`` and ``t``), so that a subscriber that joins late or loses a sample
still gets it; a receiver treats the copies as one order. ``seq`` is the order's creation time in
milliseconds since the Unix epoch, so that two orders given one after the other differ, and grow.

Exit status: 0 sent (to at least one subscriber), 1 no Zenoh router or peer reachable within the
timeout, or no process subscribes to the control key (nothing heard the order), 2 bad input.
The launcher's first Ctrl-C sends ``land`` through :func:`publish` on its own session.

Before its session opens, the command takes the operator gateway's CPU priority
(:func:`take_priority`: ``SCHED_RR`` one step below the control processes' default, where this
user is permitted it, else the normal policy and one line saying why), so that on a busy host the
order is not starved by the work beside it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Literal

import zenoh

from tether import sched
from tether import transport as tp
from tether import wire

log = logging.getLogger("tether")

Action = Literal["land", "estop"]
REPEATS = 6
"""Copies of one order."""
SPREAD = 0.5
"""Seconds over which the copies are spread."""


class Unreachable(TimeoutError):
    """No Zenoh router or peer answered within the timeout; the message says where it looked."""


class NobodyListens(TimeoutError):
    """No process subscribes to the control key: the order reached nobody."""


def take_priority() -> tuple[int, str]:
    """Put this process (and the threads it starts from now on: its Zenoh session's) at the
    operator gateway's priority, :func:`tether.sched.gateway_priority` of
    :data:`tether.sched.DEFAULT_PRIORITY`, or at the normal policy where that is not permitted.
    Returns the priority applied (0: the normal policy) and the line for the log
    (:func:`tether.sched.apply_best`). Call it before the session opens. Never raises for want
    of privilege."""
    return sched.apply_best(sched.gateway_priority(sched.DEFAULT_PRIORITY))


def order(action: Action, reason: str = "", seq: int | None = None) -> wire.SafetyCommand:
    """The :class:`~tether.wire.SafetyCommand` of the operator (sender 0)."""
    if action not in ("land", "estop"):
        raise ValueError(f"action {action!r}: use land or estop")
    return wire.SafetyCommand(sender=0, seq=int(time.time() * 1000) if seq is None else seq, k=0, t=0.0,
                              action=action, reason=reason)


async def publish(session: zenoh.Session, ns: str, msg: wire.SafetyCommand, wait: float = 0.0,
                  repeats: int = REPEATS, spread: float = SPREAD) -> bool:
    """Send ``msg`` on ``ns``'s control key ``repeats`` times over ``spread`` seconds, after waiting
    up to ``wait`` [s] for a subscriber. Returns whether any subscriber matched. Blocks about
    ``wait + spread`` seconds at most (awaits; the event loop keeps running)."""
    pub = tp.declare_publisher(session, wire.Keys(ns).safety, tp.SYNC)
    try:
        try:
            await tp.wait_for_subscribers(pub, wait)
        except TimeoutError:
            pass
        matched = tp.has_subscribers(pub)
        payload = wire.encode(msg)
        gap = spread / max(1, repeats - 1)
        for n in range(repeats):
            pub.put(payload)
            if n < repeats - 1:
                await asyncio.sleep(gap)
        matched |= tp.has_subscribers(pub)
        await asyncio.sleep(0.1)  # let the last copy leave before the publisher goes
    finally:
        pub.undeclare()
    return matched


async def _connected(session: zenoh.Session, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while True:
        if list(session.info.routers_zid()) or list(session.info.peers_zid()):
            return True
        if time.monotonic() >= deadline:
            return False
        await asyncio.sleep(0.05)


async def send(settings: tp.ZenohSettings, ns: str, action: Action, reason: str = "",
               timeout: float = 5.0) -> wire.SafetyCommand:
    """Open a session with ``settings``, send one ``action`` order to namespace ``ns`` and close.

    Raises :class:`Unreachable` when no router or peer is linked within ``timeout`` [s],
    :class:`NobodyListens` when none subscribes to the control key within ``timeout`` (the copies
    are sent anyway), :class:`~tether.transport.TransportError` when Zenoh cannot open at all."""
    msg = order(action, reason)
    wire.Keys(ns)  # a bad namespace: ValueError naming it, before anything opens
    async with tp.open_session(settings) as session:
        if not await _connected(session, timeout):
            where = settings.config_file or ", ".join(settings.connect) or "(no endpoint)"
            raise Unreachable(f"no Zenoh router or peer reachable at {where} within {timeout:g} s; "
                              "check --connect (the run's router, e.g. tether run --listen) or --zenoh-config")
        if not await publish(session, ns, msg, wait=timeout):
            raise NobodyListens(f"no process of namespace {ns!r} subscribes to {wire.Keys(ns).safety} "
                                f"within {timeout:g} s: the {action} order reached nobody; check --ns")
    return msg
