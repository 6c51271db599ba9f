"""Small helpers shared by the tests that drive real processes."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest


def wait_until(ready: Callable[[], Any], timeout: float, what: str, poll: float = 0.05) -> Any:
    """Poll ``ready()`` until it returns something truthy (returned); fail naming ``what`` after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = ready()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"waited {timeout:g} s for {what}")
        time.sleep(poll)


def rt_permitted(priority: int = 10) -> bool:
    """Whether a process of this user may take ``SCHED_RR`` ``priority`` (root, CAP_SYS_NICE or an
    rtprio limit): tried in a child, which changes nothing here."""
    code = f"import os; os.sched_setscheduler(0, os.SCHED_RR, os.sched_param({priority}))"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60).returncode == 0


def read(path: Path) -> str:
    """A log file's text so far ('' while it does not exist)."""
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


@dataclass
class SoftwareCrazyflies:
    """A running ``python -m plant.cfsim``: its process, the URIs it serves by instance, and its stderr."""

    proc: subprocess.Popen[str]
    uris: dict[int, str]
    stderr: list[str] = field(default_factory=list)


@contextlib.contextmanager
def software_crazyflies(args: list[str], startup: float = 30.0) -> Iterator[SoftwareCrazyflies]:
    """Start ``python -m plant.cfsim *args`` and wait, with a real deadline, for ``cfsim ready``.
    Both output streams are drained by threads (a full pipe would block the simulator). On exit
    the simulator gets SIGTERM, then SIGKILL after 10 s."""
    proc = subprocess.Popen([sys.executable, "-m", "plant.cfsim", *args], stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    lines: queue.Queue[str | None] = queue.Queue()
    sim = SoftwareCrazyflies(proc, {})

    def pump(stream: Any, sink: Callable[[str], None]) -> None:
        for line in stream:
            sink(line.rstrip("\n"))
        if stream is proc.stdout:
            lines.put(None)

    for stream, sink in ((proc.stdout, lines.put), (proc.stderr, sim.stderr.append)):
        threading.Thread(target=pump, args=(stream, sink), daemon=True).start()
    try:
        deadline = time.monotonic() + startup
        while True:
            try:
                line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                pytest.fail(f"software Crazyflie not ready within {startup:g} s; stderr: {sim.stderr[-20:]}")
            if line is None:
                pytest.fail(f"software Crazyflie exited with {proc.wait()}; stderr: {sim.stderr[-20:]}")
            if line == "cfsim ready":
                break
            _, i, uri = line.split()
            sim.uris[int(i)] = uri
        yield sim
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
