"""One command, one machine: start every process of a mission, run it, stop them all, keep the run.

``tether run MISSION --out DIR`` starts the leader, one agent and one plant per vehicle, and the
recorder, each its own process (``subprocess``: nothing is forked after Zenoh is loaded); in
lockstep, where every plant is simulated and nothing given acts on the plant processes, each plant
is computed inside its agent instead (the same run bit for bit, 2-3 times faster: :func:`resolve`;
``--separate-plants`` keeps one process per plant). It waits
for every liveliness token, runs the mission (lockstep: this process is the clock source; real
time: it announces the common start instant), shows progress, and stops everything at the end or
on Ctrl-C. Children get their own session (process group) and stop when the launcher is gone.

Authentication (default): every process gets its own certificate of a CA made for this run, every
link is TLS 1.3 with client certificates, and the router (and, in a mesh, every peer) enforces the
deployment's deny-by-default access rules (``deploy/localtls.py``, ``deploy/acl.py``): a session
without a certificate of the run gets no link, and one with a certificate may do only what its
role does. Tools attach through ``--listen tls/...`` with the operator identity
``DIR/tls/control-0.json5`` (``--zenoh-config``); those endpoints belong to the operator gateway, a
second router process one ``SCHED_RR`` step below the control processes (``tether/sched.py``), linked
to the launcher's, so that an order gets through a busy host and a tool's flood costs the control
traffic's router nothing but the gateway's limited output (``deploy/localtls.py``). ``--insecure`` turns all this off (plain TCP, no
rules: anyone who reaches the router can move the formation), with a warning. Under TLS,
``--vehicle-connect`` is refused (an endpoint of your own holds no certificate of the run) and
``--listen`` takes ``tls/`` endpoints only; ``openssl`` must be on PATH (exit 2 otherwise).

Network (``--network``):

* ``star``: this process opens a Zenoh **router** session on a free loopback port and every child
  connects to it as a **client**. N processes hold N links; measured here it comes up and holds its
  rate better than a mesh as N grows (``bench/runtime.py``, ``docs/zenoh.md``).
* ``mesh``: children are **peers**, each listening on its own free loopback port and meeting the
  others through the router's gossip; about N^2/2 links. Faster in lockstep (no router hop between
  the agents: Section 4 17.2x real time against 12.8x). The run starts once every token is in, so
  each peer declares its token only once linked to every other member (``--mesh-peers``): without
  that wait a lockstep ring of 32 stalled at tick 0.

By default (:func:`resolve`) a lockstep run whose plants are co-located by default is a mesh up to
:data:`MESH_MAX_AGENTS` agents, and every other run a star: real time, one process per plant, and
whatever acts on the processes or their links (faults, ``--wrap``, ``--vehicle-connect``,
``--listen``, ``--sitl``, ``--shared-plants``).

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

Failures (real time): a process that dies, or freezes (its liveliness token vanishes while its
process still exists), is reported once (who, when, what) and the others keep running: the recording
goes on until every surviving vehicle reports LANDED or ESTOP (``Telemetry.mode``,
``PlantState.mode``) or the mission ends (``LaunchOptions.settle_timeout`` can bound it further). In lockstep a dead process stalls the tick clock: the run is stopped then, naming it.
The first Ctrl-C of a real-time run publishes ``land`` on the control key
(``tether/<ns>/control/0/safety``), waits for every vehicle to report LANDED (bounded by the descent
+ 3 s; 2 s when no vehicle leaves FLYING at all), then stops everything; a second Ctrl-C stops
everything at once. Faults can be injected (``--fault``; ``deploy/faults.py``, ``deploy/inject.py``);
``DIR/faults.json`` records when each fired and ``DIR/events.json`` every event reported.

Logs: every child's stderr goes to ``DIR/logs/<role>-<id>.log``. At the end one line is logged per
event (who, when, what, why). Exit status (:data:`EXIT_OK` ...):

* 0 — clean: every process ran to the end, no failsafe fired, nothing diverged;
* 1 — the run failed: a process did not come up, a lockstep run stalled or lost a process, or a
  process ended badly where no failure was reported (the failing ones are named);
* 2 — bad input (mission, options, ``--fault``), before anything starts;
* 3 — a failsafe fired (a mode other than FLYING in an agent's telemetry or a plant's state) or a
  value diverged (``|xi|`` beyond ``safety.max_formation_error``, a gain beyond ``safety.gain_cap``),
  every process still running;
* 4 — in real time, a process died, froze (or was cut off) or never started; the others ran on
  (takes precedence over 3);
* 5 — recorded but incomplete: nothing else went wrong, but the run file lacks samples
  (``complete: false`` in its metadata; real-time DROP streams under load); the counts are logged;
* 130 — interrupted by Ctrl-C (SIGINT), whatever else happened;
* 143 — terminated (SIGTERM to the launcher), whatever else happened.

Inputs never crash the launcher: a message on a key it does not expect (a lockstep acknowledgement
with a non-numeric id, say) is dropped and counted, and the count is logged at the end.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import subprocess
import sys
import time
import shutil
import dataclasses
from dataclasses import dataclass, field
from typing import BinaryIO, Callable
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np
import zenoh

from deploy import faults as faults_mod
from deploy import inject
from deploy import localtls
from deploy import pki
from deploy import sitl
from deploy.faults import Fault
from deploy.inject import describe_exit
from deploy.relay import Relay
from tether import mission as ms
from tether import transport as tp
from tether import handoff, jsonout, safefs, sched
from tether import wire
from tether.clock import ClockKind, LockstepSource
from tether.ingress import FIFO_CAPACITY
from tether.progress import Progress

log = logging.getLogger("tether")

Network = Literal["star", "mesh"]


@dataclass(frozen=True)
class LaunchOptions:
    out: Path
    clock: ClockKind = "lockstep"
    network: Network | None = None
    """None: :func:`resolve` decides (a mesh where the plants are co-located by default and at most
    :data:`MESH_MAX_AGENTS` agents fly, else the star)."""
    window: int | None = None
    """Lockstep ticks in flight at once (see :class:`tether.clock.LockstepSource`); None:
    :data:`COLOCATED_WINDOW` with the plants co-located, else :data:`WINDOW` (:func:`resolve`)."""
    ns: str | None = None
    startup_timeout: float = 60.0
    """How long to wait for every liveliness token [s]."""
    start_timeout: float = 120.0
    """Each child's ``--start-timeout``: a child that has not heard the start this long after it
    declared its token fails (exit 1) instead of waiting for ever [s]. Longer than
    ``startup_timeout``, so that only a launcher that is gone or stuck triggers it."""
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
    faults: tuple[Fault, ...] = ()
    """Faults to inject (``--fault``; ``deploy/faults.py``, ``deploy/inject.py``)."""
    sitl: tuple[str, ...] | None = None
    """Start the software Crazyflies the mission's ``udp://`` Crazyflies need, with these extra
    simulator options, and stop them at the end (``--sitl``; ``deploy/sitl.py``); None: do not."""
    settle_timeout: float | None = None
    """Real time: after the first failure, how long the survivors get before they are stopped [s];
    None: until every vehicle has landed or the mission ends (a failsafe that recovers, e.g. an
    agent starved of CPU for half a second, does not cut the run short)."""
    land_timeout: float | None = None
    """Real time: after the first Ctrl-C's land order, how long to wait for LANDED [s]; None: the
    descent from the highest start at ``safety.land_speed`` (2D: ``safety.land_settle``) + 3 s."""
    insecure: bool = False
    """No certificates and no access rules (plain TCP; see the module docstring)."""
    live: int | None = None
    """Serve the run over the Foxglove WebSocket protocol on this port, from the recorder (``--live``)."""
    mcap: bool = True
    """The recorder writes ``run.mcap`` beside ``run.npz`` (``--no-mcap``: not)."""
    colocate_plants: bool | None = None
    """Lockstep, simulated plants: each agent computes its own plant (``plant/onboard.py``) and no
    plant process runs; agents send the recorder one record per :attr:`record_batch` ticks
    (``--colocate-plants``: True; ``--separate-plants``: False). None: co-located wherever
    :func:`separate_plants_needed` finds nothing against it (:func:`resolve`)."""
    record_batch: int | None = None
    """With :attr:`colocate_plants`: ticks per record, at most :attr:`window`; None: :func:`record_batch`."""
    shared_plants: bool = False
    """Simulated plants: one world process steps every vehicle (:class:`plant.base.Fleet`, each
    vehicle with its own watchdog) instead of one plant process per vehicle (``--shared-plants``)."""
    rt_priority: int | None = None
    """Run the launcher (its router), the leader, agents, plants or world and ``--sitl``'s
    simulators at this ``SCHED_RR`` priority, the recorder at the normal policy (``--rt-priority``;
    :mod:`tether.sched`); None: every process keeps the launcher's policy."""


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

    def error(self) -> str | None:
        """The last error line of its log (``... ERROR role/id: failed: ...``), if any."""
        try:
            lines = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return None
        for line in reversed(lines):
            if " ERROR " in line:
                return line.split(": ", 1)[-1]
        return None

    def tail(self, lines: int = 15) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"


LOG_RESERVE = 4 * 2**20
"""Free space [bytes] a run's ``--out`` must have beyond the run file's estimate, for its logs."""

HANDOVER = "(rx: (handover: app), acc: (handover: app), net: (handover: app), tx: (handover: app))"


@dataclass
class Launch:
    mission_path: Path
    mission: ms.Mission
    opts: LaunchOptions
    children: list[Child] = field(default_factory=list)
    relays: dict[tuple[str, int], Relay] = field(default_factory=dict)
    """Processes whose link to the router goes through a relay (partition faults)."""
    logs: dict[tuple[str, int], BinaryIO] = field(default_factory=dict)
    """Every child's log file, opened by :meth:`open_logs` before any process starts."""

    def open_logs(self) -> None:
        """Check that ``--out`` can hold the run, then create ``logs/`` and every child's log file,
        before any process starts. Raises :class:`~tether.mission.MissionError` naming ``--out``
        (exit status 2): the file that could not be made and why (ENOSPC, EACCES, EROFS...), or
        the free space against the run file's estimate (:func:`tether.checks.run_bytes`)."""
        from tether import checks
        from tether.node import os_error

        out = self.opts.out
        try:
            free = shutil.disk_usage(out).free
        except OSError as exc:
            raise ms.MissionError("tether run", [("--out", f"cannot use {out}: {os_error(exc)}")]) from None
        need = checks.run_bytes(self.mission) + LOG_RESERVE
        if free < need:
            raise ms.MissionError("tether run", [("--out", (
                f"{out} has {free / 2**20:.3g} MiB free, but the run needs about {need / 2**20:.3g} MiB "
                f"(the run file's arrays and {LOG_RESERVE // 2**20} MiB of logs); free space on its file "
                "system, give another --out, or shorten the run (--duration)"))])
        try:
            with safefs.Dir.open(out) as top, top.sub("logs") as logs:
                for role, nid in self.members():
                    self.logs[role, nid] = logs.open_log(f"{role}-{nid}.log")
        except OSError as exc:
            self.close_logs(remove=True)
            raise ms.MissionError("tether run", [("--out", f"cannot create the run's logs: {os_error(exc)}; "
                                                           "nothing was started")]) from None

    def close_logs(self, remove: bool = False) -> None:
        """Close the log files not handed to a process (and ``remove`` them: none was used)."""
        for fh in self.logs.values():
            fh.close()
            if remove:
                Path(fh.name).unlink(missing_ok=True)
        self.logs.clear()

    @property
    def keys(self) -> wire.Keys:
        return wire.Keys(self.opts.ns or self.mission.name)

    def members(self) -> list[tuple[str, int]]:
        m = self.mission
        if self.opts.colocate_plants:  # each plant inside its agent
            return [("leader", m.leader.id), *[("agent", a) for a in m.agent_ids], ("recorder", 0)]
        if m.payload is not None or self.opts.shared_plants:  # one world hosts every vehicle (and the payload)
            return [("leader", m.leader.id), *[("agent", a) for a in m.agent_ids], ("world", 0), ("recorder", 0)]
        return [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]

    def spawn(self, router: str, sec: localtls.Security | None = None) -> None:
        o = self.opts
        if not self.logs:
            self.open_logs()
        env = dict(os.environ)
        # numpy works on 2- and 3-vectors in every role: one BLAS thread each (a pool of idle
        # OpenBLAS threads per process costs memory and wake-ups, never speed, on these sizes)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")
        if o.handover_runtime:
            env.setdefault("ZENOH_RUNTIME", HANDOVER)
        for role, nid in self.members():
            cmd = [sys.executable, "-m", "cli", role, "--mission", str(self.mission_path),
                   "--clock", o.clock, "--ns", self.keys.ns, "--parent-pid", str(os.getpid()),
                   "--stall-timeout", str(o.stall_timeout), "--start-timeout", repr(o.start_timeout),
                   "--lease", str(o.lease), "--log-level", o.log_level]
            if o.duration is not None:
                cmd += ["--duration", repr(o.duration)]
            if o.clock == "lockstep":  # what each stream keeps to send again after a stall (tether/node.py RESEND)
                cmd += ["--window", str(window(o))]
            if o.rt_priority is not None:  # the recorder is no control loop: normal policy (it writes the run at the end)
                cmd += ["--rt-priority", str(0 if role == "recorder" else o.rt_priority)]
            if role in ("agent", "plant"):
                cmd += ["--id", str(nid)]
            if o.colocate_plants and role in ("agent", "recorder"):
                cmd += ["--colocate-plant"]
            if o.colocate_plants and role in ("agent", "leader"):  # the recorder hears records alone
                cmd += ["--record-batch", str(record_batch(o))]
            if role == "recorder":
                cmd += ["--out", str(o.out)]
                if o.live is not None:
                    cmd += ["--live", str(o.live)]
                if not o.mcap:
                    cmd += ["--no-mcap"]
            skew = sum(f.skew for f in o.faults if f.kind == "skew" and f.member(self.mission) == (role, nid))
            if skew:
                cmd += ["--clock-skew", repr(skew)]
            vehicle = role in ("agent", "plant")
            endpoint = o.vehicle_connect.get(nid, router) if vehicle else router
            if (role, nid) in self.relays:
                endpoint = self.relays[role, nid].endpoint
                if sec is not None:  # the relay forwards bytes: TLS passes through it end to end
                    endpoint = "tls/" + endpoint.split("/", 1)[1]
            if sec is not None:
                listen = None if o.network == "star" else f"tls/127.0.0.1:{tp.free_tcp_port()}"
                cmd += ["--zenoh-config", str(sec.child(role, nid, endpoint, listen))]
            elif o.network == "star":
                cmd += ["--zenoh-mode", "client", "--connect", endpoint]
            else:
                cmd += ["--zenoh-mode", "peer", "--connect", endpoint,
                        "--listen", tp.loopback_endpoint(tp.free_tcp_port())]
            if o.network == "mesh":  # its token once linked to every other member (tether/node.py)
                others = len(self.members()) - 1
                cmd += ["--mesh-peers", str(others), "--connect-timeout", repr(max(10.0, MESH_LINK_TIME * others))]
            if vehicle and nid in o.wrap:
                cmd = [*o.wrap[nid], *cmd]
            fh = self.logs.pop((role, nid))
            path = Path(fh.name)
            with fh:
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

    def terminate(self, grace: float = 5.0, recorder_grace: float | None = None) -> None:
        """SIGTERM every live child but the recorder, SIGKILL those still alive after ``grace`` seconds;
        then the recorder, which writes ``run.npz`` and ``run.mcap`` when stopped, within
        ``recorder_grace`` (default: :func:`write_grace` of the whole mission). The recorder goes last,
        once the others have gone: what they sent before (a vehicle's LANDED, the moment before a run
        ends) has reached it, and it decodes what waits in its queues before writing."""
        if recorder_grace is None:
            recorder_grace = write_grace(self.mission, self.mission.steps)
        live = [c for c in self.children if c.proc.poll() is None]
        for group, bound in (([c for c in live if c.role != "recorder"], grace),
                             ([c for c in live if c.role == "recorder"], max(grace, recorder_grace))):
            for c in group:
                c.proc.send_signal(signal.SIGTERM)
                c.proc.send_signal(signal.SIGCONT)  # a frozen process must run to handle its SIGTERM
            t0 = time.monotonic()
            for c in group:
                try:
                    c.proc.wait(max(0.0, t0 + bound - time.monotonic()))
                except subprocess.TimeoutExpired:
                    if c.role == "recorder":
                        log.error("the recorder did not finish writing the run files within %.0f s of the stop: "
                                  "killed (run.npz is written first; run.mcap may be missing)", bound)
                    c.proc.kill()
                    c.proc.wait()
        self.poll()


class LaunchFailed(RuntimeError):
    pass


WRITE_GRACE = 10.0
"""The least time the recorder gets to write its files after the last tick or a stop [s]."""
WRITE_PER_SAMPLE = 1e-4
"""Time allowed per agent-tick recorded to write ``run.npz`` and ``run.mcap`` [s]: five times the
measured cost (1000 s of Section 4, 4 agents at 100 Hz, converts in 7.6 s on a loaded 2-core
machine, ``docs/foxglove.md``), for slower machines and heavier load."""


NPZ_PER_SAMPLE = 2.5e-5
"""Time allowed per agent-tick of the mission for ``run.npz``, which holds every tick (recorded or not)
[s]: five times the measured (a 1000 s Section 4 run stopped early: its 168 MB in 2.2 s under load)."""


def write_grace(m: ms.Mission, ticks: int) -> float:
    """How long the recorder may take to write the files of ``ticks`` recorded ticks [s]."""
    return WRITE_GRACE + (WRITE_PER_SAMPLE * max(0, ticks) + NPZ_PER_SAMPLE * (m.steps + 1)) * m.n


EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_FAILSAFE, EXIT_LOST, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130
EXIT_INCOMPLETE, EXIT_TERMINATED = 5, 143
"""Exit statuses of ``tether run`` (see the module docstring)."""


WINDOW = 8
"""Lockstep ticks in flight by default with one process per plant."""

MESH_LINK_TIME = 1.0
"""In a mesh, the time a peer is given per other member to be linked to all of them before it fails
(``--connect-timeout``, at least 10 s): a ring of 32 (33 others) linked in 5-6 s on two cores."""

MESH_MAX_AGENTS = 16
"""A lockstep run whose plants are co-located by default is a mesh up to this many agents. Measured
(``bench/runtime.py --cases network``, ``docs/benchmarks.md``, sixth sitting): as a mesh rings of 4
ran 1.30x the star's speed, rings of 8 and 16 1.17x and 1.16x, for up to 0.6 s more to start;
rings of 24 and 32 only 1.03x and 1.01x, for 1.5 s and 2.6 s more (about N^2/2 TLS links to set up):
there the whole command took longer."""

COLOCATED_WINDOW = 32
"""Lockstep ticks in flight by default with the plants co-located (records of half of it). Since
an acknowledgement stands for every tick before it (one per record instead of one per tick),
section4 runs faster with 32 (records of 16) than with 16 (records of 8) in every sitting: 12.8x
against 12.1x and 12.6x against 11.9x (``bench/runtime.py --cases colocate``), its full 1000 s in
68.1 s against 70.7 s (docs/benchmarks.md). With one acknowledgement a tick, 16 had been the
better (9.4x against 9.1x)."""


def separate_plants_needed(m: ms.Mission, o: LaunchOptions) -> str | None:
    """Why a run of ``m`` keeps one process per plant by default, or None: a lockstep run whose
    plants are all simulated computes each inside its agent (the same run bit for bit, several
    times faster, ``tests/test_colocate.py``), unless something asked of the run acts on the plant
    processes themselves or on the links between them and their agents."""
    from plant import onboard

    if o.clock != "lockstep":
        return "real time: each plant is a process of its own"
    for a in m.agents:
        why = onboard.problem(m, a.id)
        if why is not None:
            return f"agent {a.id}'s plant {why}"
    for given, name in ((o.shared_plants, "--shared-plants"), (o.faults, "--fault"), (o.wrap, "--wrap"),
                        (o.vehicle_connect, "--vehicle-connect"), (o.listen, "--listen"),
                        (o.sitl is not None, "--sitl")):
        if given:
            return f"{name} was given (it acts on, or attaches beside, the plant processes)"
    return None


def window(o: LaunchOptions) -> int:
    """The window of ``o`` (:func:`resolve` decides it; :data:`WINDOW` for options not resolved)."""
    return o.window if o.window is not None else WINDOW


def resolve(m: ms.Mission, o: LaunchOptions) -> LaunchOptions:
    """``o`` with its defaults decided for ``m``: where the plants run (:attr:`LaunchOptions.colocate_plants`
    None: inside their agents unless :func:`separate_plants_needed` says why not), the window, and
    the network (:attr:`LaunchOptions.network` None: a mesh where nothing keeps the plants apart and
    at most :data:`MESH_MAX_AGENTS` agents fly; else the star, which real time, faults, vehicles
    of their own network and tools beside the plants need)."""
    free = separate_plants_needed(m, o) is None
    colocate = o.colocate_plants if o.colocate_plants is not None else free
    ticks = o.window if o.window is not None else COLOCATED_WINDOW if colocate else WINDOW
    net: Network = o.network if o.network is not None else \
        "mesh" if free and colocate and m.n <= MESH_MAX_AGENTS else "star"
    return dataclasses.replace(o, colocate_plants=colocate, window=ticks, network=net)


def record_batch(o: LaunchOptions) -> int:
    """Ticks per record with ``--colocate-plants``: :attr:`LaunchOptions.record_batch`, by default
    half the window (measured best, ``docs/benchmarks.md``), at most :data:`tether.wire.RECORD_MAX`
    (the recorder drops a larger record)."""
    return o.record_batch if o.record_batch is not None else max(1, min(window(o) // 2, wire.RECORD_MAX))


def window_max(m: ms.Mission) -> int:
    """The largest lockstep window for ``m``: a process may have to hold a window of ticks of every
    stream it hears before it drains them, and the recorder hears 1 + 2N streams a tick (the leader's,
    every plant's, every agent's telemetry); a window of them must fit in half an input queue
    (:data:`tether.ingress.FIFO_CAPACITY`), or the oldest would be dropped and the run stall."""
    return max(1, (FIFO_CAPACITY // 2) // (1 + 2 * m.n))


def check_colocate(m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
    """Why ``--colocate-plants`` (or ``--record-batch``) cannot run this mission as asked."""
    from plant import onboard

    if not o.colocate_plants:
        why = separate_plants_needed(m, o)
        return [("--record-batch", "batches the records of co-located plants, and this run has plant processes "
                                   f"({'--separate-plants was given' if why is None else why})")] \
            if o.record_batch is not None else []
    fix = "drop --colocate-plants"
    if o.clock != "lockstep":
        return [("--colocate-plants", f"is for lockstep runs (in real time each plant is a process of its own): "
                                      f"{fix}, or run with --clock lockstep")]
    out = []
    for a in m.agents:
        why = onboard.problem(m, a.id)
        if why is not None:
            out.append(("--colocate-plants", f"agent {a.id}'s plant {why}: {fix}"))
            break
    ticks = window(o)
    if ticks >= 1 and not 1 <= record_batch(o) <= ticks:
        out.append(("--record-batch", f"{record_batch(o)} ticks per record must be between 1 and the window "
                                      f"({ticks}): the clock grants a tick only once the recorder holds the "
                                      "ticks a window before it; give a smaller --record-batch or a larger --window"))
    elif record_batch(o) > wire.RECORD_MAX:
        out.append(("--record-batch", f"{record_batch(o)} ticks per record: at most {wire.RECORD_MAX} (the recorder "
                                      "drops a larger record as malformed); give a smaller --record-batch"))
    return out


def check_shared(m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
    """Why ``--shared-plants`` cannot run this mission as asked."""
    if not o.shared_plants:
        return []
    if o.colocate_plants:
        return [("--shared-plants", "and --colocate-plants both say where the plants run (one world process; "
                                    "inside each agent): give one of them")]
    if m.payload is not None:
        return [("--shared-plants", "a [payload] mission's vehicles share one world process already: drop it")]
    real = [a.id for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]
    if real:
        return [("--shared-plants", f"agent {real[0]}'s plant is a crazyflie, a real vehicle, whose own plant "
                                    "process talks to it: drop --shared-plants")]
    return []


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


def check_faults(mission: ms.Mission, opts: LaunchOptions, members: list[tuple[str, int]]) -> list[tuple[str, str]]:
    """Every problem of ``--fault`` for this launch, as ``(option, message)``."""
    out = faults_mod.check(list(opts.faults), mission, members)
    for f in opts.faults:
        if f.kind == "skew" and opts.clock != "realtime":
            out.append((f"--fault {f.text}", "a clock skew needs --clock realtime (lockstep ticks follow the "
                                             "clock source, not each process's clock)"))
        if f.kind != "partition":
            continue
        arg = f"--fault {f.text}"
        role, nid = f.member(mission)
        if opts.network != "star":
            out.append((arg, "a partition cuts a process's link to the launcher's router, and in a mesh peers "
                             "link directly: run with --network star"))
        if role in ("agent", "plant") and (nid in opts.vehicle_connect or nid in opts.wrap):
            out.append((arg, f"vehicle {nid} has --vehicle-connect/--wrap: partition it with its own network "
                             "(e.g. ip link in its namespace), or drop those options"))
    return out


def _land_bound(m: ms.Mission) -> float:
    """After an operator's land (first Ctrl-C), how long [s] to wait for every vehicle to report
    LANDED: the descent from the highest start at the landing speed (2D: ``land_settle``, the
    longest a 2D landing lasts) and 3 s to spare."""
    sf = m.safety
    descent = sf.land_settle
    if m.dim == 3:
        descent = max(a.p0[-1] - sf.ground for a in m.agents) / sf.land_speed
    return max(0.0, descent) + 3.0


class Descent:
    """How long the launcher waits for the vehicles to land after a Ctrl-C (pure): ``bound`` [s], and,
    when ``extends`` (3D, no ``--land-timeout``), as long after it as some vehicle not yet landed has
    come :data:`LAND_PROGRESS` lower within the last :data:`LAND_STALL` seconds, :data:`LAND_CAP`
    times ``bound`` at most. A vehicle held up (hovering against a push, or a supervisor that does not
    land it) stops extending it."""

    def __init__(self, extends: bool, bound: float):
        self.extends = extends
        self.bound = bound
        self.cap = bound * LAND_CAP if extends else bound
        self._lowest: dict[str, float] = {}
        self._progress_at = 0.0

    def limit(self, waited: float, heights: dict[str, float]) -> float:
        """The wait's end [s after the order], given the unsettled vehicles' newest heights ``waited``
        seconds after it."""
        if not self.extends:
            return self.bound
        for name, h in heights.items():
            low = self._lowest.get(name)
            if low is None or h <= low - LAND_PROGRESS:
                self._lowest[name] = h
                if low is not None:
                    self._progress_at = waited
        return min(self.cap, max(self.bound, self._progress_at + LAND_STALL))


LAND_PROGRESS = 0.005
"""After a Ctrl-C, a vehicle is still descending while it comes this much lower [m] ...
(pushed up by 0.5 m/s^2, the last centimetres before touchdown were seen to take 2.7 mm/s)"""
LAND_STALL = 5.0
"""... within this long [s] (:class:`Descent`)."""
LAND_CAP = 6.0
"""The longest the launcher waits for a descent still under way, in multiples of the nominal bound."""
OBEY_TIMEOUT = 2.0
"""After the launcher's land order, stop at once if no vehicle has left FLYING by then [s]."""
EXIT_GRACE = 30.0
"""Real time: how long after the last tick the children get to exit on their own [s]."""


@dataclass
class Supervision:
    """What the launcher saw during a run (filled by the loops below)."""

    monitor: inject.Monitor
    injector: inject.Injector
    stopped_by_us: bool = False
    """The launcher stopped the survivors (their 143s are not failures)."""
    epoch: float | None = None
    done_tick: int = -1
    dropped: dict[str, int] = field(default_factory=dict)
    """Messages the launcher dropped (malformed key or payload), by reason."""

    def drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1

    def mission_time(self, m: ms.Mission) -> float | None:
        if self.epoch is not None:
            return time.time() - self.epoch
        return self.done_tick * m.dt if self.done_tick >= 0 else None


def _late_within(mon: inject.Monitor, seconds: float) -> bool:
    """Whether the launcher itself ran late (:meth:`~deploy.inject.Monitor.poll`) within the last
    ``seconds``: its processes then get that long again before it judges them silent."""
    return mon.resumed is not None and time.monotonic() - mon.resumed < seconds


def _check_children(launch: Launch, sup: Supervision, lockstep: bool) -> None:
    """Report every child that ended badly (once); in lockstep that stops the run."""
    for c in launch.poll():
        if c.status is None or c.status == 0:
            continue  # ending well early is normal: in lockstep the leader finishes up to `window` ticks first
        why = describe_exit(c.status)
        fault = next((x.fault.text for x in sup.injector.firings
                      if x.fired is not None and x.fault.member(launch.mission) == (c.role, c.node_id)), None)
        if fault is not None:
            why += f" (--fault {fault})"
        sup.monitor.report(c.name, "died", why)
        if lockstep:
            raise LaunchFailed(f"{c.name} {why}: a lockstep run cannot go on without it; its log ends:\n{c.tail()}")
        log.warning("%s: the others carry on; its log ends:\n%s", c.name, c.tail())


async def _lockstep(launch: Launch, session: zenoh.Session, progress: Progress | None,
                    sup: Supervision) -> Callable[[], None]:
    """Grant ticks as the recorder acknowledges them, to the last. Returns the announcement that the
    recorder holds every sample (:class:`~tether.wire.Recorded`), made once here; the caller repeats
    it (idempotent) while it waits for the processes, which close their sessions on hearing it."""
    m, o, keys = launch.mission, launch.opts, launch.keys
    # The recorder hears every process's output of tick k, so its acknowledgement of k stands for
    # everyone's; the leader, the only process not gated by inputs of the same tick, follows grants.
    src = LockstepSource(frozenset({("recorder", 0)}), last=m.steps, window=window(o))
    wake = handoff.Wakeup()
    acks: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(1 << 20, wake)
    sub = tp.declare_subscriber(session, keys.acks, acks)
    pub = tp.declare_publisher(session, keys.tick, tp.SYNC)
    receiver = wire.Receiver(m.dim)
    seq = 0
    granted = -1

    def grant(again: bool = False) -> None:
        """Grant what may run; ``again``: repeat the current grant (idempotent), for a process that
        lost it with its link (a freeze or partition longer than the lease)."""
        nonlocal seq, granted
        g = src.grant
        hold = sup.injector.next_tick()
        if hold is not None:  # a fault at tick K: nobody runs past K until it has fired
            g = min(g, max(hold, src.done))
        if g == granted and not again:
            return
        granted = g
        pub.put(wire.encode(wire.Tick(sender=0, seq=seq, k=g, t=g * m.dt, grant=g)))
        seq += 1

    recorded = tp.declare_publisher(session, keys.recorded, tp.SYNC)
    said = 0

    def announce() -> None:
        nonlocal said
        recorded.put(wire.encode(wire.Recorded(sender=0, seq=said, k=m.steps, t=m.steps * m.dt)))
        said += 1

    start = tp.declare_publisher(session, keys.start, tp.SYNC)
    start.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=time.time())))
    start.undeclare()
    try:
        grant()
        last_progress = time.monotonic()
        while not src.finished:
            _check_children(launch, sup, lockstep=True)
            sup.monitor.poll()
            sup.done_tick = src.done
            hold = sup.injector.next_tick()
            if hold is not None and src.done >= hold:
                sup.injector.fire_due(hold * m.dt)
                grant()
            sup.injector.fire_due(-1.0)  # ends of freezes and partitions
            if not await wake.wait(0.1):
                if time.monotonic() - last_progress > 0.5:
                    grant(again=True)
                frozen = any(x.fired is not None and x.ended is None and x.fault.duration is not None
                             for x in sup.injector.firings)
                if frozen:
                    last_progress = time.monotonic()
                elif sup.monitor.resumed is not None and sup.monitor.resumed > last_progress:
                    last_progress = sup.monitor.resumed  # the launcher's own lateness is no stall of the others
                elif time.monotonic() - last_progress > o.stall_timeout:
                    raise LaunchFailed(f"lockstep stalled at tick {src.done + 1}: no acknowledgement from "
                                       + ", ".join(f"{r}/{i}" for r, i in src.missing()))
                continue
            moved = False
            for rec in acks.drain():
                msg = receiver.accept(rec.payload, wire.Ack, None)
                if msg is None:
                    sup.drop("ack_payload")
                    continue
                try:
                    role, nid, _ = wire.Keys.parse(rec.key)
                except ValueError:  # e.g. a non-numeric id: no input may crash the launcher
                    sup.drop("ack_key")
                    continue
                if nid != msg.sender:
                    sup.drop("ack_sender")
                    continue
                if msg.k > granted:  # nobody can have finished a tick not granted yet: forged or corrupt
                    sup.drop("ack_ahead")
                    continue
                moved |= src.ack(role, nid, msg.k)
            if moved:
                last_progress = time.monotonic()
                sup.done_tick = src.done
                grant()
                if progress is not None:
                    progress(src.done, m.steps, f"{m.name} lockstep")
        announce()
        return announce
    finally:
        sub.undeclare()
        pub.undeclare()


async def _realtime(launch: Launch, session: zenoh.Session, progress: Progress | None, sup: Supervision,
                    interrupted: asyncio.Event) -> bool:
    """Run a real-time mission to its end, or until the survivors of a failure have settled (or
    were given their bound), or until interrupted. Returns True when interrupted."""
    m, o, keys = launch.mission, launch.opts, launch.keys
    pub = tp.declare_publisher(session, keys.start, tp.SYNC)
    epoch = time.time() + o.start_lead
    pub.put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=epoch)))
    pub.undeclare()
    sup.epoch = epoch
    mon, inj = sup.monitor, sup.injector
    end = epoch + m.duration
    settle_by: float | None = None
    settled_at: float | None = None
    start_checked = False
    settle = o.settle_timeout

    def live() -> set[str]:
        return {c.name for c in launch.children if c.proc.poll() is None}

    while True:
        now = time.time()
        _check_children(launch, sup, lockstep=False)
        mon.poll()
        inj.fire_due(now - epoch)
        if not start_checked and now > epoch + STARTED_WITHIN and not _late_within(mon, STARTED_WITHIN):
            start_checked = True
            for c in launch.children:
                # a world is heard through the vehicles it hosts (their plant/<id>/state)
                heard = (any(f"plant/{a}" in mon.heard for a in m.agent_ids) if c.role == "world"
                         else c.name in mon.heard)
                if c.role != "recorder" and not heard and c.proc.poll() is None:
                    mon.report(c.name, "silent", f"no sample heard {STARTED_WITHIN:g} s after tick 0: "
                                                 "it did not start (see its log)")
        if interrupted.is_set():
            return True
        if all(c.status is not None for c in launch.children):
            break
        trouble = [e for e in mon.events if e.what in inject.LOST or e.what in inject.FAILSAFE]
        if trouble and settle_by is None and now < end:
            # a transient failsafe (an agent starved of CPU for half a second) must not cut the run
            # short: the survivors fly on to the mission's end unless they have all settled
            settle_by = min(now + settle, end + EXIT_GRACE) if settle is not None else end + EXIT_GRACE
            log.warning("%s: the survivors carry on; the run ends when every vehicle has landed or at the "
                        "mission's end (in %.1f s at the latest)", trouble[0].line().strip(), settle_by - now)
        if settle_by is not None and now < end and mon.vehicles_settled(live()):
            # the recorder hears the plants' final samples as the monitor does, but not at the same
            # instant: stopping at the first one heard could leave a vehicle's LANDED out of the run file
            settled_at = now if settled_at is None else settled_at
            if now - settled_at >= SETTLED_GRACE:
                log.info("every surviving vehicle has landed or stopped: ending the run")
                sup.stopped_by_us = True
                break
        else:
            settled_at = None
        if settle is not None and settle_by is not None and now >= settle_by:
            log.warning("the survivors had %.1f s after the first failure: stopping them", settle)
            sup.stopped_by_us = True
            break
        writing = now <= end + EXIT_GRACE + write_grace(m, m.steps)  # the recorder writes its files after the end
        if now > end + EXIT_GRACE and (not writing or live() - {"recorder/0"}) and not _late_within(mon, EXIT_GRACE):
            names = ", ".join(sorted(live()))
            mon.report("launcher", "silent", f"{names} still running {EXIT_GRACE:g} s after the last tick")
            sup.stopped_by_us = True
            break
        if progress is not None:
            progress(min(m.steps, int(max(0.0, now - epoch) * m.rate)), m.steps, f"{m.name} real time")
        try:
            due = inj.next_due(time.time() - epoch)
            await asyncio.wait_for(interrupted.wait(), timeout=0.05 if due is None else min(0.05, due))
        except TimeoutError:
            pass
    if progress is not None:
        progress(m.steps, m.steps, f"{m.name} real time")
    return False


STARTED_WITHIN = 5.0
"""Real time: a process not heard this long after tick 0 is reported as not started [s]."""

SETTLED_GRACE = 0.5
"""Real time: how long every surviving vehicle must have reported LANDED or ESTOP before the launcher
ends the run [s], so that their final samples reach the recorder too (a run stopped at the first
report once lost a plant's LANDED from its run file under load). Since, the recorder is also stopped
last (:meth:`Launch.terminate`) and decodes what waits in its queues before it writes; this margin
stays for what the router still forwards."""


async def _land_then_stop(launch: Launch, session: zenoh.Session, sup: Supervision) -> None:
    """First Ctrl-C in real time: order every vehicle to land, wait (bounded) for LANDED, return.
    (A second Ctrl-C stops everything at once: :func:`run` cancels this.)"""
    from deploy import operator

    m = launch.mission
    mon = sup.monitor
    given = launch.opts.land_timeout
    bound = given if given is not None else _land_bound(m)
    # 3D, no --land-timeout: a descent still under way keeps the launcher waiting (LAND_PROGRESS), so
    # that a landing slowed by a push up (a cable's pull) is not cut off at the descent's nominal time
    descent = Descent(m.dim == 3 and given is None, bound)
    log.warning("interrupted: ordering every vehicle to land (Ctrl-C again to stop at once; waiting %.1f s%s)",
                bound, ", longer while the vehicles still descend" if descent.extends else " at most")
    sender = asyncio.create_task(operator.publish(session, launch.keys.ns, operator.order("land", "launcher: Ctrl-C"),
                                                  wait=0.5))
    t0 = time.monotonic()
    try:
        while True:
            mon.poll()
            sup.injector.fire_due(time.time() - sup.epoch if sup.epoch else -1.0)
            alive = {c.name for c in launch.children if c.proc.poll() is None}
            waited = time.monotonic() - t0
            if mon.vehicles_settled(alive):
                log.info("every vehicle reports LANDED or ESTOP after %.1f s: stopping", waited)
                return
            if waited > OBEY_TIMEOUT and sender.done() and not mon.any_obeying(alive):
                log.warning("no vehicle left FLYING within %.1f s of the land order (no supervisor obeys it): "
                            "stopping", OBEY_TIMEOUT)
                return
            if waited > descent.limit(waited, mon.unsettled_heights(alive)):
                log.warning("not every vehicle landed within %.1f s%s: stopping", waited,
                            " (none descending any more)" if waited < descent.cap else "")
                return
            await asyncio.sleep(0.05)
    finally:
        if not sender.done():
            sender.cancel()


def _exit_status(events: list[inject.Event]) -> int:
    if any(e.what in inject.LOST for e in events):
        return EXIT_LOST
    if any(e.what in inject.FAILSAFE for e in events):
        return EXIT_FAILSAFE
    return EXIT_OK


async def run(mission_path: Path, opts: LaunchOptions) -> int:
    """Launch and run a mission; returns the exit status (see the module docstring)."""
    from tether.node import load_mission

    m = load_mission(mission_path, opts.duration)
    auto = opts.colocate_plants is None
    opts = resolve(m, opts)
    launch = Launch(mission_path.resolve(), m, opts)
    problems = (check_colocate(m, opts) + check_shared(m, opts) + check_vehicle_options(m, opts)
                + check_faults(m, opts, launch.members()))
    if opts.clock == "lockstep" and opts.window is not None and opts.window < 1:
        problems.append(("--window", f"is {opts.window}: lockstep ticks in flight, at least 1 (default "
                                     f"{COLOCATED_WINDOW} with the plants co-located, else {WINDOW})"))
    elif opts.clock == "lockstep" and window(opts) > window_max(m):
        problems.append(("--window", f"is {window(opts)}: at most {window_max(m)} lockstep ticks in flight for "
                                     f"{m.n} vehicles (a process may hold a window of every stream it hears, and "
                                     f"its input queue holds {FIFO_CAPACITY}); give a smaller --window (default "
                                     f"{COLOCATED_WINDOW} with the plants co-located, else {WINDOW})"))
    if opts.clock == "lockstep":
        problems += [(f"agent {a.id}.plant", "is a crazyflie, a real vehicle, which cannot wait for a lockstep clock; "
                                            "run with --clock realtime")
                     for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]
    if opts.sitl is not None:
        problems += sitl.problems(m, opts.sitl)
    if not opts.insecure:
        problems += localtls.problems(opts.listen, opts.vehicle_connect)
    problems += [(f"--listen {ep}", why) for ep in opts.listen if (why := tp.listen_problem(ep)) is not None]
    if (unsafe := safefs.out_problem(opts.out)) is not None:
        problems.append(("--out", unsafe))
    if problems:
        raise ms.MissionError(f"tether run {mission_path}", problems)
    if auto and opts.clock == "lockstep":
        if opts.colocate_plants:
            log.info("plants computed inside their agents (lockstep, simulated plants: the same run as with plant "
                     "processes, faster), window %d, records of %d ticks, network %s; --separate-plants for one "
                     "process per plant", opts.window, record_batch(opts), opts.network)
        else:
            log.info("one process per plant: %s", separate_plants_needed(m, opts))
    if opts.rt_priority is not None:  # the launcher's router first (its threads inherit it), before anything starts
        try:
            log.info("CPU scheduling of the control processes: %s", sched.apply(opts.rt_priority))
        except sched.SchedError as exc:
            raise ms.MissionError(f"tether run {mission_path}", [("--rt-priority", str(exc))]) from None
    elif opts.clock == "realtime":  # the default: SCHED_RR where permitted, one line saying why where not
        applied, line = sched.apply_best()
        (log.info if applied else log.warning)("CPU scheduling of the control processes: %s", line)
        if applied:
            opts = launch.opts = dataclasses.replace(opts, rt_priority=applied)
    keys = wire.Keys(opts.ns or m.name)
    router = tp.loopback_endpoint(tp.free_tcp_port())
    # real time: a flood on any key, from any one link, reaches no subscriber faster than a bound
    limits = localtls.run_limits(m, keys.ns, opts.clock)
    settings = tp.ZenohSettings(mode="router", listen=(router, *opts.listen), lease=opts.lease,
                                ingress_limits=limits)
    tp.zenoh_config(settings)  # a bad --listen endpoint: SettingsError naming it, before anything starts
    try:  # every file under --out is made through its real path, following no link (tether/safefs.py)
        launch.opts = opts = dataclasses.replace(opts, out=safefs.make_out(opts.out))
    except OSError as exc:
        from tether.node import os_error

        raise ms.MissionError(f"tether run {mission_path}", [("--out", f"cannot make it: {os_error(exc)}")]) from None
    launch.open_logs()  # a full or read-only --out: exit 2 naming the file, before anything starts
    sec: localtls.Security | None = None
    if opts.insecure:
        log.warning("--insecure: no certificates and no access rules; anyone who reaches the router (%s) can "
                    "publish on any key of the run (move the formation, end it, rewrite the recording)",
                    ", ".join(settings.listen))
    else:
        router = "tls/" + router.split("/", 1)[1]
        try:
            sec = localtls.prepare(m, keys.ns, opts.out, launch.members(), router, opts.listen, opts.lease,
                                   limits)
        except pki.PkiError as exc:
            log.error("cannot make this run's certificates: %s (or pass --insecure)", exc)
            return EXIT_FAILED
        except OSError as exc:  # nothing started yet: the logs made for it go too
            from tether.node import os_error

            launch.close_logs(remove=True)
            raise ms.MissionError(f"tether run {mission_path}",
                                  [("--out", f"cannot make this run's tls/: {os_error(exc)}")]) from None
        settings = tp.ZenohSettings(config_file=str(sec.configs["router"]))
        log.info("mTLS: %d identities made in %.2f s in %s; operator identity for tools (--zenoh-config): %s",
                 sec.identities, sec.seconds, sec.dir, sec.configs["control-0"])
    progress = Progress() if opts.progress else None
    sigints = 0
    first_sigint = asyncio.Event()
    terminate = asyncio.Event()
    loop = asyncio.get_running_loop()

    def on_sigint() -> None:
        nonlocal sigints
        sigints += 1
        first_sigint.set()
        if opts.clock == "lockstep" or sigints > 1:
            if sigints > 1:
                log.warning("interrupted again: stopping every process at once")
            terminate.set()

    try:
        simulators = sitl.start(m, opts.sitl, opts.out / "logs") if opts.sitl is not None else None
    except RuntimeError as exc:
        log.error("--sitl: %s", exc)
        return EXIT_FAILED
    loop.add_signal_handler(signal.SIGINT, on_sigint)
    terminated = False

    def on_sigterm() -> None:
        nonlocal terminated
        terminated = True
        terminate.set()

    loop.add_signal_handler(signal.SIGTERM, on_sigterm)
    status = EXIT_OK
    interrupted = False
    t0 = time.monotonic()
    sup: Supervision | None = None
    gateway: subprocess.Popen[bytes] | None = None
    gateway_log = opts.out / "logs" / "gateway.log"
    try:
        async with tp.open_session(settings) as session:
            listening = (router, *opts.listen) if sec is None else (router,)
            log.info("router listening on %s (namespace %s%s)", ", ".join(listening), keys.ns,
                     "" if sec is None else ", TLS with client certificates and access rules")
            if sec is not None:  # tools attach through a router of their own, one RR step below the control loops
                gw = sched.gateway_priority(opts.rt_priority or 0)
                gateway = localtls.start_gateway(sec, gateway_log, dict(os.environ), gw)
                log.info("operator gateway (%s) listening on %s", f"SCHED_RR {gw}" if gw else "normal policy",
                         ", ".join(sec.gateway_endpoints))
            if opts.live is not None:
                log.info("live view (from the recorder): ws://127.0.0.1:%d (Foxglove: Open connection, "
                         "Foxglove WebSocket; docs/foxglove.md)", opts.live)
            port = int(router.rsplit(":", 1)[1])
            for f in opts.faults:
                if f.kind == "partition" and f.member(m) not in launch.relays:
                    launch.relays[f.member(m)] = await Relay.start(("127.0.0.1", port))
            launch.spawn(router, sec)
            members = launch.members()
            monitor = inject.Monitor(session, m, keys, members, lambda: sup.mission_time(m) if sup else None,
                                     forge_agents=any(f.kind == "forge" and f.role == "agent" for f in opts.faults),
                                     # real time checks that the leader was heard at the start; lockstep
                                     # needs its samples only to forge one (a delivery a tick less)
                                     leader=opts.clock != "lockstep" or any(f.kind == "forge" and f.role == "leader"
                                                                         for f in opts.faults),
                                     lease=opts.lease)
            pids = {(c.role, c.node_id): c.proc.pid for c in launch.children}
            monitor.proc_alive = lambda name: any(c.name == name and c.proc.poll() is None for c in launch.children)
            sup = Supervision(monitor, inject.Injector(opts.faults, m, keys, session, pids, launch.relays, monitor))

            async def body() -> bool:
                tokens = [keys.token(r, i) for r, i in members]
                await tp.wait_for_tokens(session, tokens, opts.startup_timeout)
                if gateway is not None:
                    try:
                        await localtls.wait_gateway(gateway, gateway_log, opts.startup_timeout)
                    except RuntimeError as exc:
                        raise LaunchFailed(str(exc)) from None
                log.info("all %d processes are up after %.1f s", len(tokens), time.monotonic() - t0)
                t1 = time.monotonic()
                announce: Callable[[], None] | None = None
                if opts.clock == "lockstep":
                    announce = await _lockstep(launch, session, progress, sup)
                else:
                    if await _realtime(launch, session, progress, sup, first_sigint):
                        await _land_then_stop(launch, session, sup)
                        return True
                    if sup.stopped_by_us:
                        return False
                log.info("ran %g s of mission time in %.2f s of wall time", m.duration, time.monotonic() - t1)
                deadline = time.monotonic() + EXIT_GRACE
                writing = deadline + write_grace(m, m.steps)  # the recorder writes run.npz and run.mcap now
                announced = time.monotonic()
                while any(c.proc.poll() is None for c in launch.children):
                    others = any(c.proc.poll() is None for c in launch.children if c.role != "recorder")
                    if time.monotonic() > (deadline if others else writing):
                        sup.monitor.report("launcher", "silent", "some processes did not exit after the last tick")
                        break
                    if announce is not None and others and time.monotonic() - announced > 0.5:
                        announce()  # again, for a process that lost it with its link
                        announced = time.monotonic()
                    await asyncio.sleep(0.05)
                return False

            work = asyncio.create_task(body())
            stopper = asyncio.create_task(terminate.wait())
            try:
                done, _ = await asyncio.wait({work, stopper}, return_when=asyncio.FIRST_COMPLETED)
                if stopper in done:
                    log.warning("%s: stopping every process", "terminated (SIGTERM)" if terminated else "interrupted")
                    interrupted = True
                else:
                    interrupted = work.result()
            except LaunchFailed as exc:
                log.error("%s", exc)
                status = EXIT_FAILED
                log.info("stopping the others in %.1f s", opts.failure_grace)
                await asyncio.sleep(opts.failure_grace)
            except tp.TokensMissing as exc:
                log.error("%s", exc)
                status = EXIT_FAILED
            finally:
                for task in (work, stopper):
                    task.cancel()
                sup.injector.close()
                sup.monitor.close()
                t_stop = sup.mission_time(m)
                ticks = m.steps if t_stop is None else min(m.steps, int(t_stop * m.rate) + 1)
                launch.terminate(recorder_grace=write_grace(m, ticks))
                for relay in launch.relays.values():
                    await relay.close()
    finally:
        if gateway is not None:
            localtls.stop_gateway(gateway)
        loop.remove_signal_handler(signal.SIGINT)
        loop.remove_signal_handler(signal.SIGTERM)
        if simulators is not None:
            codes = simulators.stop()
            log.info("software Crazyflies stopped: %s", ", ".join(f"agent {a} exit {c}" for a, c in codes.items()))
    for c in launch.children:
        log.info("%-12s exit %s", c.name, c.status)
    events = sup.monitor.events if sup is not None else []
    if sup is not None:
        if opts.faults:
            safefs.write_file(opts.out / "faults.json", (jsonout.dumps(sup.injector.records()) + "\n").encode())
        safefs.write_file(opts.out / "events.json", (jsonout.dumps([e.to_json() for e in events]) + "\n").encode())
    if interrupted:
        status = EXIT_TERMINATED if terminated else EXIT_INTERRUPTED
    elif status == EXIT_OK:
        status = _exit_status(events)
        reported = {e.who for e in events if e.what == "died"}
        stopped = (143, -signal.SIGTERM, -signal.SIGKILL) if sup is not None and sup.stopped_by_us else ()
        bad = [c for c in launch.children if c.status not in (0, *stopped) and c.name not in reported]
        if bad:
            status = EXIT_FAILED
            log.error("failed: %s", ", ".join(f"{c.name} ({c.status})" for c in bad))
            for c in bad:
                why = c.error()
                if why:
                    log.error("  %s: %s", c.name, why)
    shown = [e for e in events if e.what != "back"]
    if shown:
        log.warning("%d event(s) in this run (who, when, what, why):", len(shown))
        for e in shown:
            log.warning("  %s", e.line())
    if sup is not None and sup.dropped:
        log.warning("the launcher dropped %d malformed message(s): %s", sum(sup.dropped.values()),
                    ", ".join(f"{n} {why}" for why, n in sorted(sup.dropped.items())))
    rebuilt = _rebuild(opts.out)
    if rebuilt or status in (EXIT_OK, EXIT_FAILSAFE, EXIT_LOST, EXIT_INTERRUPTED, EXIT_TERMINATED):
        status = _recorded(opts.out / "run.npz", status, opts)
    return status


def _rebuild(out: Path) -> bool:
    """Where the recorder died before writing ``run.npz`` (killed, its machine stopped), write it and
    ``run.mcap`` from the journal it kept as it went (``recorder/journal.py``); whether it did."""
    from recorder import journal

    if (out / "run.npz").exists() or not (out / journal.NAME).exists():
        return False
    try:
        journal.rebuild(out)
    except (OSError, ValueError) as why:
        log.error("the recorder's journal %s could not be read back (%s)", out / journal.NAME, why)
        return False
    log.warning("%s rebuilt from the recorder's journal (the recorder did not write it)", out / "run.npz")
    return True


LATE_WARN = 0.01
"""Real time: above this share of an agent's ticks started more than a period late, the launcher
says so at the end (the issue's mark for a rate that holds)."""


def late_report(late: np.ndarray, ticks: int, rt_priority: int | None) -> str | None:
    """What to say of the agents' late ticks at the end of a real-time run, or None: ``late`` is the
    run file's ``(T, N)`` running count (its last finite value per agent is the run's), ``ticks``
    the ticks run. Names the remedy where the control processes ran at the normal policy."""
    late = np.asarray(late, dtype=float)
    if late.ndim != 2:  # not a run file's (T, N): nothing to say from it
        return None
    counts = [float(c[np.isfinite(c)][-1]) for c in late.T if np.isfinite(c).any()]
    if not counts or ticks <= 0 or max(counts) <= LATE_WARN * ticks:
        return None
    lo, hi = min(counts), max(counts)
    text = (f"real time: {lo:.0f}-{hi:.0f} of each agent's {ticks} ticks started more than a period late "
            f"({100 * lo / ticks:.1f}-{100 * hi / ticks:.1f} %)")
    if rt_priority is None or rt_priority == 0:
        text += ("; if other work shares this machine, fly with --rt-priority 10 (docs/runtime.md, "
                 "Real-time priority)")
    else:
        text += f" at --rt-priority {rt_priority}: the machine is short of CPU for this swarm"
    return text


def _recorded(path: Path, status: int, opts: LaunchOptions | None = None) -> int:
    """Tell what the run file holds; a clean run whose file lacks samples is :data:`EXIT_INCOMPLETE`,
    one without a run file :data:`EXIT_FAILED`. In real time, also how many of the agents' ticks
    were late (:func:`late_report`)."""
    from tether import runfile

    try:
        with np.load(path, allow_pickle=False) as run:
            meta = runfile.decode_meta(str(run["meta"]))
            if opts is not None and opts.clock == "realtime" and "late" in run.files:
                said = late_report(run["late"], len(run["t"]), opts.rt_priority)
                if said is not None:
                    log.warning("%s", said)
    except (OSError, KeyError, ValueError, msgspec.MsgspecError) as exc:
        log.error("no readable run file at %s (%s): see logs/recorder-0.log", path, exc)
        try:  # the usual cause, which the recorder's own log (on the same disk) may not hold
            free = shutil.disk_usage(path.parent).free
        except OSError:
            free = None
        if free is not None and free < LOG_RESERVE:
            log.error("the file system of %s has %d bytes free: a full disk (free space, or give another --out)",
                      path.parent, free)
        if path.with_name(path.name + ".part").exists():
            log.error("%s.part is a run file the recorder did not finish writing", path)
        return EXIT_FAILED if status == EXIT_OK else status
    if meta.complete is False:
        got, want = meta.samples_recorded, meta.samples_expected
        counts = f"{got} of {want} samples recorded" if got is not None and want is not None else "samples missing"
        if status == EXIT_OK:
            status = EXIT_INCOMPLETE
        log.warning("run recorded INCOMPLETE in %s: %s (the others were lost on the way or the run was cut "
                    "short; see logs/recorder-0.log) (exit status %d: %s)", path, counts, status, MEANING[status])
        return status
    log.info("run recorded in %s (exit status %d: %s)", path, status, MEANING[status])
    return status


MEANING = {EXIT_OK: "clean", EXIT_FAILED: "the run failed", EXIT_BAD_INPUT: "bad input",
           EXIT_FAILSAFE: "a failsafe fired or a value diverged", EXIT_LOST: "a process died or froze",
           EXIT_INTERRUPTED: "interrupted", EXIT_INCOMPLETE: "recorded, but samples are missing",
           EXIT_TERMINATED: "terminated (SIGTERM)"}
