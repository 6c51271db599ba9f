"""The options of ``tether run``, their defaults decided for a mission, and their checks (pure).

Nothing here starts a process: :func:`problems` says everything wrong with a launch before anything
starts (exit status 2), :func:`resolve` decides what was left to the launcher. How a run keeps time
is a :class:`Pace`, chosen once from ``--clock`` and handed in. The user's manual: ``docs/launch.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Protocol

from deploy import faults as faults_mod
from deploy import localtls, sitl
from deploy.faults import Fault
from tether import mission as ms
from tether import safefs
from tether import transport as tp
from tether import wire
from tether.clock import ClockKind
from tether.ingress import FIFO_CAPACITY

Network = Literal["star", "mesh"]


@dataclass(frozen=True)
class LaunchOptions:
    """What ``tether run`` was asked; :func:`resolve` decides the defaults left None."""

    out: Path
    clock: ClockKind = "lockstep"
    """The children's ``--clock``; the launcher's own pacing is the :class:`Pace` chosen from it."""
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
    """Real time: seconds between the start announcement and tick 0 (longer where a Crazyflie takes
    off in it: :func:`tether.mission.start_lead`)."""
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
    "uav3")``). The prefix must exec the command, not fork it (``docs/launch.md``)."""
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
    """No certificates and no access rules (plain TCP; ``docs/launch.md``)."""
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


class Pace(Protocol):
    """How a run keeps time, as far as its options go: lockstep (the launcher is the tick clock's
    source) or real time (every process on its own clock). Chosen once from ``--clock``
    (:func:`deploy.supervise.pace`) and handed in; what differs between the two is said by each
    implementation, never by asking which one is held."""

    @property
    def apart(self) -> str | None:
        """Why this pace keeps each plant a process of its own, or None (co-located plants may run)."""
        ...

    def problems(self, m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
        """What this pace cannot run as asked, as ``(option, message)``."""
        ...

    def child_args(self, o: LaunchOptions) -> list[str]:
        """What every child's command line says of the clock (``--clock`` and what goes with it)."""
        ...


WINDOW = 8
"""Lockstep ticks in flight by default with one process per plant."""

MESH_LINK_TIME = 1.0
"""In a mesh, the time a peer is given per other member to be linked to all of them before it fails
(``--connect-timeout``, at least 10 s): a ring of 32 (33 others) linked in 5-6 s on two cores."""

MESH_MAX_AGENTS = 16
"""A lockstep run whose plants are co-located by default is a mesh up to this many agents. Measured
(``bench/runtime.py --cases network``, ``docs/benchmarks.md``): as a mesh rings of 4
ran 1.30x the star's speed, rings of 8 and 16 1.17x and 1.16x, for up to 0.6 s more to start;
rings of 24 and 32 only 1.03x and 1.01x, for 1.5 s and 2.6 s more (about N^2/2 TLS links to set up):
there the whole command took longer."""

COLOCATED_WINDOW = 32
"""Lockstep ticks in flight by default with the plants co-located (records of half of it). Since
an acknowledgement stands for every tick before it (one per record instead of one per tick),
section4 runs faster with 32 (records of 16) than with 16 (records of 8): 12.8x against 12.1x and
12.6x against 11.9x (``bench/runtime.py --cases colocate``), its full 1000 s in 68.1 s against
70.7 s (docs/benchmarks.md)."""


def separate_plants_needed(m: ms.Mission, o: LaunchOptions, pace: Pace) -> str | None:
    """Why a run of ``m`` keeps one process per plant by default, or None: a lockstep run whose
    plants are all simulated computes each inside its agent (the same run bit for bit, several
    times faster, ``tests/test_colocate.py``), unless something asked of the run acts on the plant
    processes themselves or on the links between them and their agents."""
    from plant import onboard

    if pace.apart is not None:
        return pace.apart
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


def resolve(m: ms.Mission, o: LaunchOptions, pace: Pace) -> LaunchOptions:
    """``o`` with its defaults decided for ``m``: where the plants run (:attr:`LaunchOptions.colocate_plants`
    None: inside their agents unless :func:`separate_plants_needed` says why not), the window, and
    the network (:attr:`LaunchOptions.network` None: a mesh where nothing keeps the plants apart and
    at most :data:`MESH_MAX_AGENTS` agents fly; else the star, which real time, faults, vehicles
    of their own network and tools beside the plants need)."""
    free = separate_plants_needed(m, o, pace) is None
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


def check_colocate(m: ms.Mission, o: LaunchOptions, pace: Pace) -> list[tuple[str, str]]:
    """Why ``--colocate-plants`` (or ``--record-batch``) cannot run this mission as asked."""
    from plant import onboard

    if not o.colocate_plants:
        why = separate_plants_needed(m, o, pace)
        return [("--record-batch", "batches the records of co-located plants, and this run has plant processes "
                                   f"({'--separate-plants was given' if why is None else why})")] \
            if o.record_batch is not None else []
    fix = "drop --colocate-plants"
    if pace.apart is not None:
        return [("--colocate-plants", f"is for lockstep runs ({pace.apart}): {fix}, or run with --clock lockstep")]
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


def check_lockstep(m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
    """What a lockstep run of ``m`` cannot do as asked: a window out of range, a real vehicle, a
    clock skew, as ``(option, message)``."""
    out: list[tuple[str, str]] = []
    defaults = f"default {COLOCATED_WINDOW} with the plants co-located, else {WINDOW}"
    if o.window is not None and o.window < 1:
        out.append(("--window", f"is {o.window}: lockstep ticks in flight, at least 1 ({defaults})"))
    elif window(o) > window_max(m):
        out.append(("--window", f"is {window(o)}: at most {window_max(m)} lockstep ticks in flight for "
                                f"{m.n} vehicles (a process may hold a window of every stream it hears, and "
                                f"its input queue holds {FIFO_CAPACITY}); give a smaller --window ({defaults})"))
    out += [(f"agent {a.id}.plant", "is a crazyflie, a real vehicle, which cannot wait for a lockstep clock; "
                                    "run with --clock realtime")
            for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]
    out += [(f"--fault {f.text}", "a clock skew needs --clock realtime (lockstep ticks follow the clock source, "
                                  "not each process's clock)")
            for f in o.faults if f.kind == "skew"]
    return out


def problems(m: ms.Mission, o: LaunchOptions, pace: Pace, members: list[tuple[str, int]]) -> list[tuple[str, str]]:
    """Everything wrong with launching ``m`` with the resolved options ``o`` and the processes
    ``members``, as ``(option, message)``; none: the launch may start."""
    out = (check_colocate(m, o, pace) + check_shared(m, o) + check_vehicle_options(m, o)
           + check_faults(m, o, members) + pace.problems(m, o))
    if o.sitl is not None:
        out += sitl.problems(m, o.sitl)
    if not o.insecure:
        out += localtls.problems(o.listen, o.vehicle_connect)
    out += [(f"--listen {ep}", why) for ep in o.listen if (why := tp.listen_problem(ep)) is not None]
    if (unsafe := safefs.out_problem(o.out)) is not None:
        out.append(("--out", unsafe))
    return out


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
