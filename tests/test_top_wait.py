"""``tether top`` started before the swarm: it says it is waiting, tries the router until it answers
(a real Zenoh router session opened later by the test), then shows each plant's watchdog mode from
the plants' own samples; without a router it gives up after ``--wait`` with exit 1. The table's
cells and reasons are checked on :class:`recorder.top.Board` itself."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from recorder.top import Board, _reason
from tether import transport as tp
from tether import wire

from tests.support import REPO, free_port, tether, wait_until


def plant_state(vehicle: int, k: int, mode: int) -> bytes:
    return wire.encode(wire.PlantState(sender=vehicle, seq=k, k=k, t=k * 0.01, p=[1.0, 2.0], vel=[0.0, 0.0],
                                       a=[0.0, 0.0], d=[0.0, 0.0], mode=mode))


def test_the_board_shows_the_plant_watchdog_mode_and_no_empty_id() -> None:
    keys = wire.Keys("ns")
    board = Board("ns")
    board.plant(keys.topic("plant", 2, "state"), plant_state(2, 5, wire.HOLD))
    board.plant(keys.topic("plant", 2, "state"), plant_state(2, 4, wire.FLYING))  # older: ignored
    cells, styles = board.cells(board.rows[2], time.monotonic())
    assert cells[:3] == ["2", "no telemetry", "HOLD"] and styles[2] == "yellow"
    assert _reason("neighbour  lost and the leader no longer reaches this agent") == \
        "neighbour (no id) lost and the leader no longer reaches this agent"
    assert _reason("neighbours 2, 3 lost: edge dropped") == "neighbours 2, 3 lost: edge dropped"


def test_top_without_a_router_gives_up_after_its_wait() -> None:
    port = free_port()
    t0 = time.monotonic()
    r = tether("top", "--ns", "x", "--connect", f"tcp/127.0.0.1:{port}", "--wait", "2", check=False, timeout=60)
    assert r.returncode == 1, r.stderr
    assert "waiting for the swarm's router" in r.stderr and "within 2 s" in r.stderr and "--wait" in r.stderr
    assert time.monotonic() - t0 >= 2.0


@pytest.mark.slow
def test_top_started_before_the_swarm_waits_then_shows_it(tmp_path: Path) -> None:
    if shutil.which("tmux") is None:
        pytest.skip("tmux is not installed (apt-get install tmux): tether top is tested in a real terminal")
    port = free_port()
    session = f"tether-top-wait-{os.getpid()}"
    rc = tmp_path / "rc"
    command = (f"cd {REPO} && env -u COLUMNS -u LINES PYTHONPATH={REPO} {sys.executable} -m cli top "
               f"--connect tcp/127.0.0.1:{port} --ns topwait --wait 120; echo $? > {rc}")
    tmux = ["tmux", "-L", session, "-f", "/dev/null"]
    subprocess.run([*tmux, "new-session", "-d", "-s", session, "-x", "200", "-y", "30", command], check=True)

    def pane() -> str:
        return subprocess.run([*tmux, "capture-pane", "-p", "-t", session], capture_output=True, text=True).stdout

    def plant_cell(vehicle: str) -> str:
        for line in pane().splitlines():
            cells = [c.strip() for c in line.split("│")]
            if len(cells) > 4 and cells[1] == vehicle:
                return cells[3]
        return ""

    try:
        wait_until(lambda: "waiting for the swarm's router" in pane(), 60, "top to say it waits for the router")
        router = tp.ZenohSettings(mode="router", listen=(f"tcp/127.0.0.1:{port}",))
        with tp.open_session(router) as zs:
            wait_until(lambda: "tether top: namespace 'topwait'" in pane(), 60, "top to connect once the router is up")
            key = wire.Keys("topwait").topic("plant", 3, "state")
            k = 0

            def shows_hold() -> bool:
                nonlocal k
                k += 1
                zs.put(key, plant_state(3, k, wire.HOLD))
                return plant_cell("3") == "HOLD"

            wait_until(shows_hold, 60, "vehicle 3's plant watchdog mode HOLD in the table")
            subprocess.run([*tmux, "send-keys", "-t", session, "q"], check=True)
            wait_until(lambda: rc.exists() and rc.read_text().strip() != "", 30, "tether top to quit on q")
        assert rc.read_text().strip() == "0"
    finally:
        subprocess.run([*tmux, "kill-server"], capture_output=True)
