"""``tether run MISSION --sitl``: start the software Crazyflies a Crazyflie mission needs, stop them
at the end.

Every agent whose plant is ``crazyflie`` with a ``udp://HOST:PORT`` URI on this machine gets a
software Crazyflie on that port, standing at its agent's ``p0`` and as heavy as the lab weighed it
(the fleet's mass for its URI where the mission names a fleet, else the plant table's ``mass``; a
``--mass`` in ``--sitl-args`` overrides both, for every vehicle). The vehicles are grouped by simulated
dongle as ``tether run`` groups real ones (:func:`plant.radio.dongles`: four to a dongle, in port
order), and each group is one ``python -m plant.cfsim --radio --count N --port P... --p0 X,Y,Z...``
process: its vehicles share the dongle's airtime over a Crazyradio-like link (retries, in order),
and the radio host that flies them is one process too. The launcher waits, with a deadline,
for each to print ``cfsim ready``; then the run proceeds as against real vehicles. The simulators are
stopped (SIGTERM, then SIGKILL after a grace) whatever ends the run: its end, a failure, Ctrl-C or
SIGTERM. Each is started in its own session (a terminal's Ctrl-C reaches the launcher only, which
stops them in order) and, on Linux, with the launcher as its parent-death signal, so that a launcher
killed outright does not leave them running either.

A mission whose Crazyflies are not all ``udp://`` on a loopback or local address cannot be run with
``--sitl`` (a real vehicle cannot be simulated into existence): :func:`problems` names each such
agent's ``uri``. Extra simulator options (``--sitl-args "--noise 0.1 --seed 2"``: estimator noise,
battery, link latency and loss; ``docs/cfsim.md``) are checked by the simulator's own parser before
anything starts.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import shlex
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO
from urllib.parse import urlsplit

from tether import mission as ms
from tether import safefs

log = logging.getLogger("tether.sitl")

LOCAL_HOSTS = ("127.0.0.1", "localhost", "0.0.0.0")
STARTUP_TIMEOUT = 30.0
"""How long [s] a simulator may take to print ``cfsim ready`` (numpy's import on a loaded machine)."""
STOP_GRACE = 5.0


def groups(m: ms.Mission) -> list[list["SitlVehicle"]]:
    """The software Crazyflies of ``m`` by simulated dongle (:func:`plant.radio.dongles`)."""
    from plant import radio

    by_id = {v.agent_id: v for v in vehicles(m)}
    uris = [(v.agent_id, f"udp://{v.host}:{v.port}") for v in by_id.values()]
    return [[by_id[a] for a in d.agents] for d in radio.dongles(uris)]


@dataclass(frozen=True)
class SitlVehicle:
    agent_id: int
    host: str
    port: int
    p0: tuple[float, float, float]
    mass: float
    """The simulated vehicle's mass [kg]: the fleet's for its URI where the mission names a fleet
    (what the lab weighed), else the plant table's ``mass``."""


def vehicles(m: ms.Mission) -> list[SitlVehicle]:
    """The software Crazyflies ``m`` needs (its ``crazyflie`` agents with a local ``udp://`` URI)."""
    fleet = None
    if m.fleet is not None:
        from tether import fleet as fl

        fleet = fl.load(m.fleet)
    out = []
    for a in m.agents:
        if isinstance(a.plant, ms.CrazyfliePlant):
            u = urlsplit(a.plant.uri)
            if u.scheme == "udp" and u.hostname in LOCAL_HOSTS and u.port is not None:
                p0 = (list(a.p0) + [0.0, 0.0, 0.0])[:3]
                listed = None if fleet is None else fleet.by_uri(a.plant.uri)
                mass = a.plant.mass if fleet is None or listed is None else float(fleet.mass_of(listed))
                out.append(SitlVehicle(a.id, u.hostname, u.port, (float(p0[0]), float(p0[1]), float(p0[2])), mass))
    return out


def problems(m: ms.Mission, extra: tuple[str, ...]) -> list[tuple[str, str]]:
    """Why ``m`` cannot run with ``--sitl`` (and these ``extra`` simulator options); empty if it can."""
    from plant.cfsim.__main__ import parse_args

    out: list[tuple[str, str]] = []
    cf = [(k, a) for k, a in enumerate(m.agents) if isinstance(a.plant, ms.CrazyfliePlant)]
    if not cf:
        out.append(("--sitl", f"mission {m.name} has no crazyflie agent to simulate; drop --sitl"))
    ports: dict[int, int] = {}
    for k, a in cf:
        assert isinstance(a.plant, ms.CrazyfliePlant)
        u = urlsplit(a.plant.uri)
        try:
            port = u.port
        except ValueError:
            port = None
        if u.scheme != "udp" or u.hostname not in LOCAL_HOSTS or port is None:
            out.append((f"agent {a.id}.plant.uri", f"is {a.plant.uri!r}, not a software Crazyflie on this machine; "
                                                  "with --sitl give udp://127.0.0.1:PORT (e.g. udp://127.0.0.1:19850)"))
            continue
        if port in ports:
            out.append((f"agent {a.id}.plant.uri", f"uses port {port} like agent {ports[port]}; give each vehicle "
                                                  "its own port"))
        ports[port] = a.id
    try:
        _quiet_parse(parse_args, ["--count", "1", *extra])
    except SystemExit:
        out.append(("--sitl-args", f"{shlex.join(extra)!r} is not accepted by python -m plant.cfsim; "
                                   "see python -m plant.cfsim --help (e.g. --sitl-args '--noise 0.1 --seed 2')"))
    return out


def _quiet_parse(parse: object, argv: list[str]) -> None:
    import io

    with contextlib.redirect_stderr(io.StringIO()):
        parse(argv)  # type: ignore[operator]


def _set_pdeathsig() -> None:  # runs in the child between fork and exec
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    os.setsid()


@dataclass
class Sitl:
    """The running simulators."""

    procs: dict[int, subprocess.Popen[str]] = field(default_factory=dict)
    stderr: dict[int, list[str]] = field(default_factory=dict)

    def stop(self, grace: float = STOP_GRACE) -> dict[int, int]:
        """SIGTERM every simulator, SIGKILL what is left after ``grace``; returns exit codes by agent."""
        for p in self.procs.values():
            if p.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    p.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        codes = {}
        for aid, p in self.procs.items():
            try:
                codes[aid] = p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                codes[aid] = p.wait()
        return codes


def start(m: ms.Mission, extra: tuple[str, ...], logs: Path, timeout: float = STARTUP_TIMEOUT,
          wrap: tuple[str, ...] = ()) -> Sitl:
    """Start one simulator per vehicle of ``m`` and wait until each is ready; on any failure the ones
    started are stopped and ``RuntimeError`` says which failed and why (its stderr's tail). ``wrap``
    is put before each simulator's command (``ip netns exec NS``: the radio host of a rehearsal).

    ``logs`` (``--out``'s ``logs``, under a real path: ``tether.safefs.make_out``) gets each
    simulator's stderr as ``cfsim-<id>.log``, made first and following no link: a log that is a
    symbolic link, or not this user's plain file, is :class:`~tether.mission.MissionError` naming
    ``--out`` and the file, before any simulator starts (and its target is left untouched).

    Call it from the thread that lives as long as the run (the main thread): the parent-death signal
    fires when the thread that started a child ends."""
    files: dict[int, BinaryIO] = {}
    try:
        with safefs.Dir.open(logs.parent) as top, top.sub(logs.name) as d:
            for g in groups(m):
                files[g[0].agent_id] = d.open_log(f"cfsim-{g[0].agent_id}.log")
    except OSError as exc:
        from tether.node import os_error

        for fh in files.values():
            fh.close()
        raise ms.MissionError("tether run --sitl", [("--out", f"cannot create the simulators' logs: "
                                                              f"{os_error(exc)}; nothing was started")]) from None
    sitl = Sitl()
    ready: queue.Queue[tuple[int, str | None]] = queue.Queue()
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        for g in groups(m):
            v, aid = g[0], g[0].agent_id
            cmd = [sys.executable, "-m", "plant.cfsim", "--radio", "--count", str(len(g)),
                   "--host", v.host if v.host != "localhost" else "127.0.0.1", "--instance", str(aid),
                   *(a for w in g for a in ("--port", str(w.port))), *("--p0=" + ",".join(repr(c) for c in w.p0) for w in g),
                   *(() if "--mass" in extra else (a for w in g for a in ("--mass", repr(w.mass)))),
                   "--log-level", "INFO", *extra]
            p = subprocess.Popen([*wrap, *cmd], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                 text=True, env=env, preexec_fn=_set_pdeathsig)  # noqa: PLW1509 (setsid + prctl only)
            sitl.procs[aid] = p
            sitl.stderr[aid] = []
            _pump(aid, p, sitl.stderr[aid], ready, files.pop(aid))
        waiting = set(sitl.procs)
        deadline = time.monotonic() + timeout
        while waiting:
            try:
                aid, line = ready.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise RuntimeError(f"software Crazyflie(s) of agent(s) {sorted(waiting)} not ready within "
                                   f"{timeout:g} s") from None
            if line is None:
                tail = " | ".join(sitl.stderr[aid][-5:])
                raise RuntimeError(f"software Crazyflie of agent {aid} exited with {sitl.procs[aid].wait()}: {tail}")
            if line == "cfsim ready":
                waiting.discard(aid)
        log.info("software Crazyflies ready: %s", ", ".join(f"agent {v.agent_id} udp://{v.host}:{v.port}"
                                                            for v in vehicles(m)))
        return sitl
    except BaseException:
        sitl.stop()
        raise
    finally:
        for fh in files.values():  # those no simulator was started for
            fh.close()


def _pump(aid: int, p: subprocess.Popen[str], stderr: list[str], ready: queue.Queue[tuple[int, str | None]],
          logfile: BinaryIO) -> None:
    """Threads that hand ``p``'s stdout lines to ``ready`` and copy its stderr to ``stderr`` and
    ``logfile`` (closed when the simulator's stderr ends)."""
    def out() -> None:
        assert p.stdout is not None
        for line in p.stdout:
            ready.put((aid, line.strip()))
        ready.put((aid, None))

    def err() -> None:
        assert p.stderr is not None
        with logfile as fh:
            for line in p.stderr:
                stderr.append(line.rstrip("\n"))
                fh.write(line.encode())
                fh.flush()

    for fn in (out, err):
        threading.Thread(target=fn, daemon=True, name=f"cfsim-{aid}").start()


@contextlib.contextmanager
def running(m: ms.Mission, extra: tuple[str, ...], logs: Path) -> Iterator[Sitl]:
    sitl = start(m, extra, logs)
    try:
        yield sitl
    finally:
        codes = sitl.stop()
        log.info("software Crazyflies stopped: %s", ", ".join(f"agent {a} exit {c}" for a, c in codes.items()))
