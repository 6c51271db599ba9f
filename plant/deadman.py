"""A ground-side dead-man for Crazyflies: a vehicle whose plant process dies is landed, not dropped.

A plant streams low-level setpoints; if its process is killed outright (SIGKILL, the out-of-memory
killer, a crash in native code) nothing reaches the vehicle any more, and the firmware's watchdog
levels it out after 0.5 s and stops its motors after 2 s, in the air (``docs/lab.md``). The stock
firmware has nothing that would land it on its own. So the process that holds the links starts a
small guardian process beside it (:class:`Guardian`), joined to it by a pipe and by nothing else:
no Zenoh, no shared state, its own session (a signal to the plant's process group does not reach
it). The plant tells it which vehicles are in the air (``arm URI``, ``disarm URI``) and lets it go
(``bye``) once none is: it lives while a vehicle of that process flies. When the pipe closes without ``bye`` the plant's process is gone, and with
it its hold on the radio: the guardian opens each armed vehicle's link itself, hands the commander
to the high-level planner (``send_notify_setpoint_stop``) and orders a landing (``land`` to 0 m
over ``land_time``), a few times over (a radio link may lose a packet), then exits. Measured on the
software Crazyflie: ``pytest -s tests/test_lab_deadman.py``.

What it cannot cover: a ground computer that loses power or its radio (the guardian dies with it),
and a plant process that is frozen rather than dead (its pipe stays open and, on a real radio, it
still holds the dongle): there the firmware's watchdog acts as before. The guardian ignores SIGTERM,
SIGINT and SIGHUP (a service stop signals the plant's whole control group at once): it ends with its
pipe, at most about a second after the plant.

    python -m plant.deadman --land-time SECONDS      # the guardian; reads its orders on stdin

Each order is one line: ``arm URI``, ``disarm URI``, ``bye``. An order it does not understand is
logged and ignored.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from typing import IO, Any

log = logging.getLogger("tether.deadman")

REPEATS = 3
"""How many times the guardian sends each vehicle its landing order (a radio link may lose one)."""
REPEAT_GAP = 0.05
"""Seconds between those repeats."""


def parse(line: str) -> tuple[str, str] | None:
    """An order line as ``(verb, uri)`` (``uri`` empty for ``bye``); None if it is not an order. Pure."""
    words = line.split()
    if words == ["bye"]:
        return ("bye", "")
    if len(words) == 2 and words[0] in ("arm", "disarm"):
        return (words[0], words[1])
    return None


def listen(orders: Iterable[str]) -> tuple[set[str], bool]:
    """Follow the orders until they end: the URIs armed at the end, and whether ``bye`` came. Pure
    but for logging (an order it does not understand is logged and skipped)."""
    armed: set[str] = set()
    for line in orders:
        order = parse(line)
        if order is None:
            if line.strip():
                log.warning("deadman: not an order, ignored: %r", line.strip()[:80])
            continue
        verb, uri = order
        if verb == "bye":
            return armed, True
        if verb == "arm":
            armed.add(uri)
        else:
            armed.discard(uri)
    return armed, False


class _Link:
    """What cflib's commanders need of a Crazyflie (``send_packet``), over a bare link driver: no
    table of contents, no log blocks, nothing to wait for."""

    def __init__(self, driver: Any):
        self._driver = driver

    def send_packet(self, pk: Any) -> None:
        self._driver.send_packet(pk)


def land(uri: str, land_time: float) -> None:
    """Open ``uri``'s link and order the vehicle down: the commander to the high-level planner,
    then ``land`` to 0 m over ``land_time`` [s], :data:`REPEATS` times. Raises what cflib raises."""
    import cflib.crtp
    from cflib.crazyflie.commander import Commander
    from cflib.crazyflie.high_level_commander import HighLevelCommander

    cflib.crtp.init_drivers()
    driver = cflib.crtp.get_link_driver(uri)
    if driver is None:
        raise ConnectionError(f"no link driver for {uri}")
    try:
        link = _Link(driver)
        cmd, hl = Commander(link), HighLevelCommander(link)
        for _ in range(REPEATS):
            cmd.send_notify_setpoint_stop()
            hl.land(0.0, land_time)
            time.sleep(REPEAT_GAP)
        time.sleep(0.2)  # let the driver's queue drain before the link closes
    finally:
        driver.close()


def guard(orders: IO[str], land_time: float) -> int:
    """The guardian's life: follow ``orders``; if they end without ``bye``, land every armed vehicle
    (all at once, one thread each: the firmware cuts the motors 2 s after the last setpoint).
    Returns the exit status: 0, or 1 if a landing order could not be sent."""
    armed, bye = listen(orders)
    if bye or not armed:
        return 0
    log.error("deadman: the plant process is gone; landing %s", ", ".join(sorted(armed)))
    failed: list[str] = []

    def one(uri: str) -> None:
        try:
            land(uri, land_time)
            log.error("deadman: %s ordered to land over %g s", uri, land_time)
        except Exception as exc:  # every vehicle is tried; the failure is said
            failed.append(uri)
            log.error("deadman: %s could not be ordered to land: %s", uri, exc)

    threads = [threading.Thread(target=one, args=(uri,), daemon=True) for uri in sorted(armed)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=10.0)
    return 1 if failed or any(th.is_alive() for th in threads) else 0


class Guardian:
    """The plant side: starts the guardian process when a vehicle is armed and none was, tells it
    what is in the air, and lets it go (``bye``) once nothing is: no guardian idles beside a process
    whose vehicles are all down. Thread-safe (plants of one radio host arm and disarm from their own
    threads). A process that dies while a vehicle is armed leaves the guardian to land it."""

    def __init__(self, land_time: float):
        self.land_time = land_time
        self._proc: subprocess.Popen[str] | None = None
        self._armed: set[str] = set()
        self._lock = threading.RLock()
        """Held across each order and the state it changes (an arm never lands between a disarm and its bye)."""

    def _say(self, line: str) -> None:
        with self._lock:
            if self._proc is None:
                if line.startswith("disarm") or line == "bye":
                    return
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", "plant.deadman", "--land-time", f"{self.land_time:g}"],
                    stdin=subprocess.PIPE, text=True, start_new_session=True,
                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
            assert self._proc.stdin is not None
            try:
                self._proc.stdin.write(line + "\n")
                self._proc.stdin.flush()
            except (BrokenPipeError, ValueError):  # the guardian is gone: nothing to tell it
                log.error("deadman: the guardian process is gone (exit %s); a killed plant will not land its "
                          "vehicles", self._proc.poll())

    @property
    def pid(self) -> int | None:
        """The guardian process's id, once started."""
        return None if self._proc is None else self._proc.pid

    def arm(self, uri: str) -> None:
        """``uri``'s vehicle is in the air: land it if this process dies."""
        with self._lock:
            self._armed.add(uri)
            self._say(f"arm {uri}")

    def disarm(self, uri: str) -> None:
        """``uri``'s vehicle is on the ground or its motors are off: leave it alone."""
        with self._lock:
            self._armed.discard(uri)
            self._say(f"disarm {uri}")
            if not self._armed:
                self.close()

    def close(self) -> None:
        """The guardian exits without acting (this process ends well, or nothing is in the air); a
        later :meth:`arm` starts another. Idempotent."""
        with self._lock:
            self._say("bye")
            proc, self._proc = self._proc, None
            self._armed.clear()
            if proc is None:
                return
            assert proc.stdin is not None
            try:
                proc.stdin.close()
            except BrokenPipeError:
                pass
            try:
                proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


_GUARDIAN: Guardian | None = None
_GUARDIAN_LOCK = threading.Lock()


def guardian(land_time: float) -> Guardian:
    """This process's one :class:`Guardian` (made at the first call; ``land_time`` of that call)."""
    global _GUARDIAN
    with _GUARDIAN_LOCK:
        if _GUARDIAN is None:
            _GUARDIAN = Guardian(land_time)
        return _GUARDIAN


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m plant.deadman", description=__doc__.split("\n\n")[0])
    p.add_argument("--land-time", type=float, required=True, help="seconds the landing takes (> 0)")
    a = p.parse_args(argv)
    if not (math.isfinite(a.land_time) and a.land_time > 0):
        p.error("--land-time: must be a positive, finite number of seconds, e.g. 3")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s", stream=sys.stderr)
    # a stop of the plant's service (SIGTERM to its whole control group), a hang-up or Ctrl-C must not
    # take the guardian first: its life is the plant's (the pipe) and, after it, at most a second
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    return guard(sys.stdin, a.land_time)


if __name__ == "__main__":
    sys.exit(main())
