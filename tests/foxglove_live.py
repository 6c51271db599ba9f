"""A real Foxglove WebSocket client for the live-view tests: connect, subscribe once the topics are
advertised, collect messageData and time frames until enough have come or the deadline passes."""

from __future__ import annotations

import json
import struct
import time
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import pytest

ws_client = pytest.importorskip("websockets.sync.client")

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
"""The Foxglove WebSocket protocol's names: current clients offer the first, older ones (Lichtblick
before Dec 2025, ``foxglove.websocket.v1`` libraries) only the second; the live view accepts either."""


@dataclass
class Live:
    """What a live server sent: its serverInfo, the advertised channels by topic, per topic the
    (stamp [ns], payload) of each messageData frame, and the stamps of its time frames."""

    info: dict[str, Any] | None = None
    channels: dict[str, dict[str, Any]] = field(default_factory=dict)
    got: dict[str, list[tuple[int, bytes]]] = field(default_factory=lambda: defaultdict(list))
    clock: list[int] = field(default_factory=list)
    subprotocol: str | None = None
    """The subprotocol the server chose."""


def listen(port: int, want: Mapping[str, int], timeout: float,
           alive: Callable[[], bool] = lambda: True, subprotocols: list[str] | None = None) -> Live:
    """Subscribe to every topic of ``want`` and collect until each has at least ``want[topic]``
    messages (0: subscribe, wait for none) or ``timeout`` s have passed. ``alive`` is polled while
    connecting: a server process that ended fails the test at once instead of at the deadline.
    ``subprotocols``: what the client offers (default: both names)."""
    offer = list(SUBPROTOCOLS if subprotocols is None else subprotocols)
    deadline = time.monotonic() + timeout
    topics = list(want)
    ws = None
    while ws is None:
        try:
            ws = ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=offer,  # type: ignore[arg-type]
                                   open_timeout=5)
        except OSError:
            if time.monotonic() > deadline or not alive():
                pytest.fail(f"no live server on port {port}")
            time.sleep(0.2)
    live = Live()
    subscribed = False
    with ws:
        assert ws.subprotocol in offer
        live.subprotocol = ws.subprotocol
        while time.monotonic() < deadline and not (
                subscribed and all(len(live.got[t]) >= n for t, n in want.items())):
            try:
                frame = ws.recv(timeout=2)
            except TimeoutError:
                continue
            if isinstance(frame, str):
                op = json.loads(frame)
                if op["op"] == "serverInfo":
                    live.info = op
                elif op["op"] == "advertise":
                    live.channels.update({c["topic"]: c for c in op["channels"]})
                if not subscribed and all(t in live.channels for t in topics):
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                        {"id": n, "channelId": live.channels[t]["id"]} for n, t in enumerate(topics)]}))
                    subscribed = True
                continue
            if frame[0] == 0x02:  # time (the Time capability): the run's clock
                live.clock.append(struct.unpack_from("<Q", frame, 1)[0])
                continue
            assert frame[0] == 0x01, frame[:1]  # message data
            sub, stamp_ns = struct.unpack_from("<IQ", frame, 1)
            live.got[topics[sub]].append((stamp_ns, bytes(frame[13:])))
    assert live.info is not None and live.info["name"] == "tether", live.info
    for t, n in want.items():
        assert len(live.got[t]) >= n, f"{len(live.got[t])} messages on {t} (advertised: {sorted(live.channels)})"
    return live
