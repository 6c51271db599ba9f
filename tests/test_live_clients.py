"""The live view for every Foxglove client: a real WebSocket client (``websockets``) offering only
``foxglove.websocket.v1`` (Lichtblick before Dec 2025, older libraries) and one offering only
``foxglove.sdk.v1`` (current apps) each get the channels of a ``tether simulate --live``; the scene
comes at 25 Hz by default. The handshake's renaming is checked on its own (pure)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("foxglove")
ws_client = pytest.importorskip("websockets.sync.client")

from recorder import wscompat  # noqa: E402
from tether import catalog  # noqa: E402
from tether import mission as ms  # noqa: E402

from tests.foxglove_live import listen  # noqa: E402
from tests.support import REPO, free_port  # noqa: E402

REQUEST = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
           b"Sec-WebSocket-Protocol: %s\r\n\r\n")


def test_only_a_legacy_only_handshake_is_renamed() -> None:
    legacy, renamed = wscompat.rename_request(REQUEST % b"foxglove.websocket.v1")
    assert renamed and wscompat.offered(legacy) == ["foxglove.sdk.v1"]
    for offer in (b"foxglove.sdk.v1", b"foxglove.websocket.v1, foxglove.sdk.v1", b"other"):
        head, renamed = wscompat.rename_request(REQUEST % offer)
        assert not renamed and head == REQUEST % offer
    answer = b"HTTP/1.1 101 Switching Protocols\r\nsec-websocket-protocol: foxglove.sdk.v1\r\n\r\n"
    assert wscompat.offered(wscompat.rename_response(answer)) == ["foxglove.websocket.v1"]


@pytest.mark.slow  # a real simulation serving its live view
def test_both_subprotocols_get_the_live_view_and_the_scene_at_25_hz(tmp_path: Path) -> None:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "cli", "simulate", "section4", "--out", str(tmp_path / "live"),
                             "--duration", "60", "--live", str(port), "--speed", "1", "--no-figures", "--no-mcap"],
                            cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        for offer in (["foxglove.websocket.v1"], ["foxglove.sdk.v1"]):
            live = listen(port, {"/agent/1": 20, "/scene": 5, "/tf": 2}, timeout=90,
                          alive=lambda: proc.poll() is None, subprotocols=offer)
            assert live.subprotocol == offer[0]
            assert live.channels["/scene"]["schemaName"] == "foxglove.SceneUpdate"
            ticks = [json.loads(data)["k"] for _, data in live.got["/agent/1"]]
            assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
            # the scene at 25 Hz of a 100 Hz run: every 4th tick's stamp
            stamps = [t for t, _ in live.got["/scene"]]
            steps = {round((b - a) / 1e7) for a, b in zip(stamps, stamps[1:])}
            assert steps == {4}, (offer, steps)
            assert "parameters" in (live.info or {})["capabilities"]
        read_only_parameters(port)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)


def request(ws: object, op: dict, want: str) -> dict:
    """Send ``op`` and return the first reply of op ``want`` with its id."""
    ws.send(json.dumps(op))  # type: ignore[attr-defined]
    while True:
        frame = ws.recv(timeout=30)  # type: ignore[attr-defined]
        if isinstance(frame, str):
            reply = json.loads(frame)
            if reply["op"] == want and reply.get("id") == op["id"]:
                return reply


def read_only_parameters(port: int) -> None:
    """The law's and the failsafes' parameters are advertised, and a client's set changes none."""
    law = ms.load(catalog.resolve("section4")).law
    with ws_client.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"],  # type: ignore[list-item]
                           open_timeout=10) as ws:
        got = request(ws, {"op": "getParameters", "parameterNames": [], "id": "all"}, "parameterValues")
        values = {p["name"]: p["value"] for p in got["parameters"]}
        assert values["law.sigma"] == law.sigma and values["law.kind"] == law.kind
        assert "safety.land_after" in values and "mission.rate" in values
        got = request(ws, {"op": "setParameters", "parameters": [{"name": "law.sigma", "value": 99.0}], "id": "set"},
                      "parameterValues")
        assert [(p["name"], p["value"]) for p in got["parameters"]] == [("law.sigma", law.sigma)]
        again = request(ws, {"op": "getParameters", "parameterNames": ["law.sigma"], "id": "again"}, "parameterValues")
        assert [p["value"] for p in again["parameters"]] == [law.sigma]
