"""Helpers shared by the tests that drive real processes: the ``tether`` runners, the one port
allocator, the condition waits, and the software Crazyflie process. Plain functions, imported by name
(``from tests.support import tether``); ``tests/conftest.py`` holds only what pytest itself must see."""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tether import transport as tp

REPO = Path(__file__).resolve().parent.parent
"""The checkout under test: every ``tether`` subprocess runs from it and imports it first."""


# =========================================================================== the tether command
def cli_env(extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """The environment of a ``tether`` subprocess: this test's (``tests/conftest.py`` sets one BLAS thread
    and no display there) with this checkout first on the import path, the code under test whatever is
    installed, and ``extra``."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return {**os.environ, "PYTHONPATH": path, **(extra or {})}


def tether(*args: str, timeout: float = 600.0, cwd: Path | None = None, env: Mapping[str, str] | None = None,
           **run: Any) -> subprocess.CompletedProcess[str]:
    """Run ``tether ARGS`` (``python -m cli``) to its end and return it with its output captured as text.
    Blocks for up to ``timeout`` [s], generous because a short simulation has taken 103 s on a loaded
    two-core machine. ``env`` is added to :func:`cli_env`; ``run`` goes to :func:`subprocess.run`."""
    return subprocess.run([sys.executable, "-m", "cli", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=cwd or REPO, env=cli_env(env), stdin=subprocess.DEVNULL, **run)


def tether_popen(*args: str, log: Path | None = None, cwd: Path | None = None,
                 env: Mapping[str, str] | None = None) -> subprocess.Popen[str]:
    """Start ``tether ARGS`` in a session of its own (so that :func:`kill` reaches everything it started),
    stdout and stderr merged, piped or written to ``log``. Returns at once."""
    if log is None:
        return subprocess.Popen([sys.executable, "-m", "cli", *args], cwd=cwd or REPO, env=cli_env(env),
                                stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, start_new_session=True)
    with open(log, "w") as fh:
        return subprocess.Popen([sys.executable, "-m", "cli", *args], cwd=cwd or REPO, env=cli_env(env),
                                stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)


def finish(proc: subprocess.Popen[str], timeout: float = 120.0) -> tuple[int, str]:
    """Wait up to ``timeout`` [s] for a piped :func:`tether_popen` to end: its status and output. Past the
    timeout its whole session is killed and the test fails with the output's tail."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate(timeout=30)
        pytest.fail(f"still running after {timeout:g} s:\n{(out or '')[-3000:]}")
    return proc.returncode, out or ""


def kill(proc: subprocess.Popen[str]) -> None:
    """SIGKILL a :func:`tether_popen`'s whole session if it still runs, and reap it (a cleanup step)."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)


# =========================================================================== ports
def free_port(span: int = 1, *, udp: bool = False) -> int:
    """The one port allocator of the tests: a port on 127.0.0.1 (with ``span`` > 1 the first of that many
    consecutive ones) that nothing binds now, for TCP and, with ``udp``, for UDP as well (the software
    Crazyflies listen on UDP). Never the same twice in one process: it is the launcher's own
    :func:`tether.transport.free_tcp_port`, whose ports lie below the kernel's ephemeral range so that
    no outgoing connection takes one before the test's process binds it. Parallel test processes pick at
    random among some 20 000 ports and check by binding, so two of them meeting is very unlikely."""
    for _ in range(100):
        port = tp.free_tcp_port(span=span)
        if not udp or _udp_free(range(port, port + span)):
            return port
    raise OSError(f"no {span} consecutive UDP and TCP port(s) free on 127.0.0.1")


def _udp_free(ports: range) -> bool:
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


# =========================================================================== waits
def wait_until(ready: Callable[[], Any], timeout: float, what: str, proc: subprocess.Popen[str] | None = None,
               *, poll: float = 0.05) -> Any:
    """Poll ``ready()`` until it returns something truthy (returned); fail naming ``what`` after ``timeout``
    [s], or as soon as ``proc`` (a piped :func:`tether_popen` the condition depends on) has ended."""
    deadline = time.monotonic() + timeout
    while True:
        value = ready()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"waited {timeout:g} s for {what}")
        if proc is not None and proc.poll() is not None:
            out = proc.communicate()[0] or ""
            pytest.fail(f"process ended ({proc.returncode}) while waiting for {what}:\n{out[-3000:]}")
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


# =========================================================================== software Crazyflies
@dataclass
class SoftwareCrazyflies:
    """A running ``python -m plant.cfsim``: its process, the URIs it serves by instance, and its stderr."""

    proc: subprocess.Popen[str]
    uris: dict[int, str]
    stderr: list[str] = field(default_factory=list)


@contextlib.contextmanager
def software_crazyflies(args: list[str], startup: float = 30.0, wrap: Sequence[str] = ()) -> Iterator[SoftwareCrazyflies]:
    """Start ``python -m plant.cfsim *args`` (after ``wrap``: ``chrt --rr 10``) and wait, with a real
    deadline, for ``cfsim ready``. Both output streams are drained by threads (a full pipe would block
    the simulator). On exit the simulator gets SIGTERM, then SIGKILL after 10 s."""
    proc = subprocess.Popen([*wrap, sys.executable, "-m", "plant.cfsim", *args], stdin=subprocess.DEVNULL,
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


def log_time(line: str) -> float:
    """Unix time of a log record (``%(asctime)s``: local time, milliseconds after the comma)."""
    stamp, ms = line[:23].split(",")
    return time.mktime(time.strptime(stamp, "%Y-%m-%d %H:%M:%S")) + int(ms) / 1000
