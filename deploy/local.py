"""One command, one machine: start every process of a mission, run it, stop them all, keep the run.

``tether run MISSION --out DIR`` starts the leader, one agent and one plant per vehicle, and the
recorder, each its own process (``subprocess``: nothing is forked after Zenoh is loaded), waits
for every liveliness token, runs the mission (lockstep: this process is the clock source; real
time: it announces the common start instant), shows progress, and stops everything at the end or
on Ctrl-C. Children get their own session (process group) and stop when the launcher is gone.

Network (``--network``):

* ``star`` (default): this process opens a Zenoh **router** session on a free loopback port and
  every child connects to it as a **client**. N processes hold N links; measured here it comes up
  and holds its rate better than a mesh as N grows (``bench/runtime.py``, ``docs/zenoh.md``).
* ``mesh``: children are **peers**, each listening on its own free loopback port and meeting the
  others through the router's gossip; about N^2/2 links.

Vehicles on another network (partition studies; a companion computer's on-board link): vehicle i's
agent and plant can run under a command prefix, ``--wrap 3='ip netns exec uav3'`` (a network
namespace; or ``taskset``, ``nice``, ``chrt``), and connect to another endpoint than the launcher's
router, ``--vehicle-connect 3=tcp/127.0.0.1:7448`` (e.g. an on-board Zenoh router in that namespace,
which links to the swarm through an endpoint the launcher's router also listens on, ``--listen
tcp/10.231.0.1:7447``). Cutting that link (``ip link set ... down`` in the namespace) partitions the
vehicle while its agent and plant keep talking on board: its neighbours see its liveliness token go
after the lease (``--lease``) and come back once the on-board router has reconnected. A prefix must
*exec* the command, not fork it (``ip netns exec``, ``nice``, ``taskset``, ``chrt`` do; ``sudo`` and
``ssh`` do not): a child stops when its parent is not the launcher. (A ``[payload]`` mission's
vehicles live in one world process: there only the agent is wrapped.) Tested with the ``star``
network (``tests/test_partition.py``).

Logs: every child's stderr goes to ``DIR/logs/<role>-<id>.log``. Exit status: 0 when every process
ended well, 1 otherwise (the failing ones are named), 2 bad input, 130 interrupted.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from tether import mission as ms
from tether import transport as tp
from tether import handoff
from tether import wire
from tether.clock import ClockKind, LockstepSource
from tether.progress import Progress

log = logging.getLogger("tether")

Network = Literal["star", "mesh"]


@dataclass(frozen=True)
class LaunchOptions:
    out: Path
    clock: ClockKind = "lockstep"
    network: Network = "star"
    window: int = 8
    """Lockstep ticks in flight at once (see :class:`tether.clock.LockstepSource`)."""
    ns: str | None = None
    startup_timeout: float = 60.0
    """How long to wait for every liveliness token [s]."""
    stall_timeout: float = 30.0
    """Lockstep: fail when no tick completes for this long [s]."""
    start_lead: float = 1.0
    """Real time: seconds between the start announcement and tick 0."""
    lease: float = 2.0
    """Zenoh link lease [s]: a frozen process is seen gone after about this long."""
    log_level: str = "INFO"
    progress: bool = True
    duration: float | None = None
    """Override the mission's duration [s]."""
    failure_grace: float = 1.0
    """After a child fails, let the others run this long [s] before stopping them, so that the run
    file and their logs show how the swarm saw the failure (silence flags)."""
    listen: tuple[str, ...] = ()
    """More endpoints for the launcher's router to listen on, for tools that attach to the run
    (``tether netem-set``, a plain Zenoh client, a partition study's far side)."""
    handover_runtime: bool = True
    """Hand Zenoh's runtime threads over to one thread per child (ZENOH_RUNTIME), which measured
    here lowest CPU for many processes on few cores."""
    wrap: dict[int, tuple[str, ...]] = field(default_factory=dict)
    """Vehicle id -> command prefix under which its agent and plant run (e.g. ``("ip", "netns", "exec",
    "uav3")``). The prefix must exec the command, not fork it (see the module docstring)."""
    vehicle_connect: dict[int, str] = field(default_factory=dict)
    """Vehicle id -> the Zenoh endpoint its agent and plant connect to instead of the launcher's router
    (e.g. an on-board router that links to one of :attr:`listen`)."""


@dataclass
class Child:
    role: str
    node_id: int
    proc: subprocess.Popen
    log_path: Path
    status: int | None = None

    @property
    def name(self) -> str:
        return f"{self.role}/{self.node_id}"

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


HANDOVER = "(rx: (handover: app), acc: (handover: app), net: (handover: app), tx: (handover: app))"


@dataclass
class Launch:
    mission_path: Path
    mission: ms.Mission
    opts: LaunchOptions
    children: list[Child] = field(default_factory=list)

    @property
    def keys(self) -> wire.Keys:
        return wire.Keys(self.opts.ns or self.mission.name)

    def members(self) -> list[tuple[str, int]]:
        m = self.mission
        if m.payload is not None:  # one world hosts every vehicle and the payload
            return [("leader", m.leader.id), *[("agent", a) for a in m.agent_ids], ("world", 0), ("recorder", 0)]
        return [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]

    def spawn(self, router: str) -> None:
        o = self.opts
        logs = o.out / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        env = dict(os.environ)
        if o.handover_runtime:
            env.setdefault("ZENOH_RUNTIME", HANDOVER)
        for role, nid in self.members():
            cmd = [sys.executable, "-m", "cli", role, "--mission", str(self.mission_path),
                   "--clock", o.clock, "--ns", self.keys.ns, "--parent-pid", str(os.getpid()),
                   "--stall-timeout", str(o.stall_timeout), "--lease", str(o.lease), "--log-level", o.log_level]
            if o.duration is not None:
                cmd += ["--duration", repr(o.duration)]
            if role in ("agent", "plant"):
                cmd += ["--id", str(nid)]
            if role == "recorder":
                cmd += ["--out", str(o.out)]
            vehicle = role in ("agent", "plant")
            endpoint = o.vehicle_connect.get(nid, router) if vehicle else router
            if o.network == "star":
                cmd += ["--zenoh-mode", "client", "--connect", endpoint]
            else:
                cmd += ["--zenoh-mode", "peer", "--connect", endpoint,
                        "--listen", tp.loopback_endpoint(tp.free_tcp_port())]
            if vehicle and nid in o.wrap:
                cmd = [*o.wrap[nid], *cmd]
            path = logs / f"{role}-{nid}.log"
            with open(path, "wb") as fh:
                proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                        env=env, start_new_session=True)
            self.children.append(Child(role, nid, proc, path))

    def poll(self) -> list[Child]:
        """Children that have exited since the last poll."""
        ended = []
        for c in self.children:
            if c.status is None and (rc := c.proc.poll()) is not None:
                c.status = rc
                ended.append(c)
        return ended

    def terminate(self, grace: float = 5.0) -> None:
        """SIGTERM every live child, then SIGKILL those still alive after ``grace`` seconds."""
        live = [c for c in self.children if c.proc.poll() is None]
        for c in live:
            c.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace
        for c in live:
            try:
                c.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                c.proc.kill()
                c.proc.wait()
        self.poll()


class LaunchFailed(RuntimeError):
    pass


def check_vehicle_options(mission: ms.Mission, opts: LaunchOptions) -> list[tuple[str, str]]:
    """Every problem of the per-vehicle options (``--wrap``, ``--vehicle-connect``), as ``(option, message)``."""
    out: list[tuple[str, str]] = []
    ids = mission.agent_ids
    for name, table in (("--wrap", opts.wrap), ("--vehicle-connect", opts.vehicle_connect)):
        for nid in table:
            if nid not in ids:
                out.append((f"{name} {nid}", f"{nid} is not a vehicle (agent id) of this mission; use one of {ids}"))
    for nid, prefix in opts.wrap.items():
        if not prefix:
            out.append((f"--wrap {nid}", "the prefix is empty; give a command, e.g. 'ip netns exec uav3'"))
    for nid, endpoint in opts.vehicle_connect.items():
        problems = tp.validate_settings(tp.ZenohSettings(mode="client", connect=(endpoint,)))
        out += [(f"--vehicle-connect {nid}", msg) for _, msg in problems]
    return out


async def _watch_children(launch: Launch) -> None:
    """Raise :class:`LaunchFailed` as soon as a child ends badly. (Ending well early is normal:
    in lockstep the leader finishes up to ``window`` ticks before the others.)"""
    while True:
        for c in launch.poll():
            if c.status != 0:
                raise LaunchFailed(f"{c.name} exited with status {c.status}; its log ends:\n{c.tail()}")
        await asyncio.sleep(0.2)


async def _lockstep(launch: Launch, session, progress: Progress | None) -> None:
    m, o, keys = launch.mission, launch.opts, launch.keys
    # The recorder hears every process's output of tick k, so its acknowledgement of k stands for
    # everyone's; the leader, the only process not gated by inputs of the same tick, follows grants.
    src = LockstepSource(frozenset({("recorder", 0)}), last=m.steps, window=o.window)
    wake = handoff.Wakeup()
    acks: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(1 << 20, wake)
    sub = tp.declare_subscriber(session, keys.acks, acks)
    pub = tp.declare_publisher(session, keys.tick, tp.SYNC)
    receiver = wire.Receiver(m.dim)
    seq = 0

    def grant() -> None:
        nonlocal seq
        g = src.grant
        pub.put(wire.encode(wire.Tick(sender=0, seq=seq, k=g, t=g * m.dt, grant=g)))
        seq += 1

    start = tp.declare_publisher(session, keys.start, tp.SYNC)
    start.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=time.time())))
    start.undeclare()
    try:
        grant()
        last_progress = time.monotonic()
        while not src.finished:
            if not await wake.wait(1.0):
                if time.monotonic() - last_progress > o.stall_timeout:
                    raise LaunchFailed(f"lockstep stalled at tick {src.done + 1}: no acknowledgement from "
                                       + ", ".join(f"{r}/{i}" for r, i in src.missing()))
                continue
            moved = False
            for rec in acks.drain():
                msg = receiver.accept(rec.payload, wire.Ack, None)
                if msg is None:
                    continue
                role, nid, _ = wire.Keys.parse(rec.key)
                if nid != msg.sender:
                    continue
                moved |= src.ack(role, nid, msg.k)
            if moved:
                last_progress = time.monotonic()
                grant()
                if progress is not None:
                    progress(src.done, m.steps, f"{m.name} lockstep")
    finally:
        sub.undeclare()
        pub.undeclare()


async def _realtime(launch: Launch, session, progress: Progress | None) -> None:
    m, o, keys = launch.mission, launch.opts, launch.keys
    pub = tp.declare_publisher(session, keys.start, tp.SYNC)
    epoch = time.time() + o.start_lead
    pub.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=epoch)))
    pub.undeclare()
    end = epoch + m.duration
    while time.time() < end:
        if progress is not None:
            progress(int(max(0.0, time.time() - epoch) * m.rate), m.steps, f"{m.name} real time")
        await asyncio.sleep(min(0.5, max(0.01, end - time.time())))
    if progress is not None:
        progress(m.steps, m.steps, f"{m.name} real time")


async def run(mission_path: Path, opts: LaunchOptions) -> int:
    """Launch and run a mission; returns the exit status (see the module docstring)."""
    from tether.node import load_mission

    m = load_mission(mission_path, opts.duration)
    problems = check_vehicle_options(m, opts)
    if opts.clock == "lockstep":
        problems += [(f"agents[{k}].plant", "is a crazyflie, a real vehicle, which cannot wait for a lockstep clock; "
                                            "run with --clock realtime")
                     for k, a in enumerate(m.agents) if isinstance(a.plant, ms.CrazyfliePlant)]
    if problems:
        raise ms.MissionError(f"tether run {mission_path}", problems)
    keys = wire.Keys(opts.ns or m.name)
    opts.out.mkdir(parents=True, exist_ok=True)
    launch = Launch(mission_path.resolve(), m, opts)
    router = tp.loopback_endpoint(tp.free_tcp_port())
    settings = tp.ZenohSettings(mode="router", listen=(router, *opts.listen), lease=opts.lease)
    tp.zenoh_config(settings)  # a bad --listen endpoint: SettingsError naming it, before anything starts
    progress = Progress() if opts.progress else None
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    status = 0
    t0 = time.monotonic()
    try:
        async with tp.open_session(settings) as session:
            log.info("router listening on %s (namespace %s)", ", ".join(settings.listen), keys.ns)
            launch.spawn(router)
            watcher = asyncio.create_task(_watch_children(launch))
            stopper = asyncio.create_task(stop.wait())

            async def body() -> None:
                tokens = [keys.token(r, i) for r, i in launch.members()]
                await tp.wait_for_tokens(session, tokens, opts.startup_timeout)
                log.info("all %d processes are up after %.1f s", len(tokens), time.monotonic() - t0)
                t1 = time.monotonic()
                if opts.clock == "lockstep":
                    await _lockstep(launch, session, progress)
                else:
                    await _realtime(launch, session, progress)
                log.info("ran %g s of mission time in %.2f s of wall time", m.duration, time.monotonic() - t1)
                while any(c.proc.poll() is None for c in launch.children):
                    await asyncio.sleep(0.05)

            work = asyncio.create_task(body())
            try:
                done, _ = await asyncio.wait({work, watcher, stopper}, return_when=asyncio.FIRST_COMPLETED)
                if stopper in done:
                    log.warning("interrupted: stopping every process")
                    status = 130
                elif watcher in done:
                    watcher.result()
                else:
                    work.result()
            except LaunchFailed as exc:
                log.error("%s", exc)
                status = 1
                log.info("stopping the others in %.1f s", opts.failure_grace)
                await asyncio.sleep(opts.failure_grace)
            except tp.TokensMissing as exc:
                log.error("%s", exc)
                status = 1
            finally:
                for task in (work, watcher, stopper):
                    task.cancel()
                launch.terminate()
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    bad = [c for c in launch.children if c.status not in (0,)]
    for c in launch.children:
        log.info("%-12s exit %s", c.name, c.status)
    if status == 0 and bad:
        status = 1
        log.error("failed: %s", ", ".join(f"{c.name} ({c.status})" for c in bad))
    if status == 0:
        log.info("run recorded in %s", opts.out / "run.npz")
    return status
