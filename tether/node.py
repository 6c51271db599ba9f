"""What every process shares: its session, its inputs, its clock, its publishers, its lifetime.

A role (leader, agent, plant, recorder) is an ``async def run(node)`` that declares its inputs and
publishers on a :class:`Node`, calls :meth:`Node.ready`, then loops over ticks. ``Node`` is handed
its clock (:class:`~tether.clock.Clock`, lockstep or real time) and leaves to it whatever the two
differ in; neither it nor a role asks which one it holds:

* inputs are :class:`Source` objects; ``await node.aligned([src, ...], k)`` returns, in lockstep,
  the samples of tick ``k`` exactly (waiting for them), and in real time the newest samples of one
  common tick; an input that crosses an emulated link (``[netem]``) gives what the link delivered;
* ``await node.tick(k)`` gates tick ``k`` (a grant in lockstep, an instant in real time).

The node is a facade over its jobs: its inputs (:class:`~tether.ingress.Ingress`), its publishers
(:class:`~tether.outputs.Outputs`), its pacing (the clock's, with :meth:`Node.until` to wait on inputs)
and its life (:meth:`Node.ready`, :meth:`Node.linger`, :meth:`Node.close`, :func:`serve`).
"""

from __future__ import annotations

import asyncio
import errno
import logging
import math
import os
import signal
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from tether import evloop, handoff
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.clock import Clock, ClockError, ClockKind
from tether.clock import make as make_clock
from tether.ingress import BACKLOG_ROLES, Ingress, undeclare
from tether.inputs import Link, Source
from tether.outputs import Outputs, Publisher

log = logging.getLogger("tether")

LINGER = 0.25
"""Real time: how long a process that ran to its last tick keeps its session open before closing it
[s], so that the samples of its last ticks leave before the session goes. Closed at once, it lost
them: the recorder, which waits for every producer's last tick or its token's going, then wrote an
incomplete run. Lockstep waits for the launcher's word instead (:meth:`Node.linger`): there, closed
at once, an agent's second-to-last record (plants co-located, records of 8 ticks) never reached the
recorder although its last did, and the recorder stalled for 30 s and failed the run (4 of 8 runs
of Section 4 beside three CPU-bound processes)."""

RESEND = 2.0
"""Lockstep: a tick that has waited this long for its inputs (at most a third of ``--stall-timeout``)
makes the process send its streams' kept messages again (:meth:`Node.resend`)."""


MESH_POLL = 0.02
"""How often a peer of a mesh looks at its links while it waits for all of them [s] (Zenoh gives no
event for a new link)."""

class Stalled(RuntimeError):
    """A lockstep input did not arrive in time; the message names it."""


def os_error(exc: OSError) -> str:
    """An ``OSError`` as one line for a user: the file, the cause and its errno name, what to do
    (``/out/run.npz: No space left on device (ENOSPC); free space on its file system ...``)."""
    from tether.safefs import UnsafePath

    if isinstance(exc, UnsafePath):  # its message names the path and the fix
        return str(exc.strerror)
    code = errno.errorcode.get(exc.errno or 0, f"errno {exc.errno}")
    where = f"{exc.filename}: " if exc.filename else ""
    advice = {errno.ENOSPC: "free space on its file system, or give another --out",
              errno.EDQUOT: "free space within your quota, or give another --out",
              errno.EFBIG: "the file is beyond the file-size limit (ulimit -f): raise it, or record less",
              errno.EACCES: "make the directory writable, or give another --out",
              errno.EPERM: "make the directory writable, or give another --out",
              errno.EROFS: "the file system is read-only: give another --out"}.get(exc.errno or 0,
                                                                                  "fix the path, then run again")
    return f"{where}{exc.strerror or exc} ({code}); {advice}"


@dataclass(frozen=True)
class NodeArgs:
    """Everything a process needs, as parsed from its command line."""

    mission_path: Path
    role: str
    node_id: int
    clock: ClockKind
    zenoh: tp.ZenohSettings
    ns: str | None = None
    """Key namespace; the mission name by default."""
    stall_timeout: float = 30.0
    """Lockstep: give up when an input of the current tick has not come for this long [s]."""
    parent_pid: int | None = None
    """Stop when this process (the launcher) is gone."""
    duration: float | None = None
    """Override the mission's duration [s] (a whole number of periods)."""
    start_timeout: float | None = None
    """Give up (exit 1) when the start message has not come this long after :meth:`Node.ready`
    declared liveliness [s]; None waits for ever (a service waiting for its operator's start)."""
    colocate: bool = False
    """Lockstep: an agent computes its simulated plant itself (:mod:`plant.onboard`) and sends the
    recorder :class:`~tether.wire.Record` messages; the recorder listens for them
    (``tether run --colocate-plants``)."""
    record_batch: int = 1
    """With :attr:`colocate`: ticks an agent's record carries at most (a smaller last one ends the run).
    The leader's (lockstep): ticks of its states per record for the recorder, 0 for none."""
    mesh_peers: int = 0
    """A peer of a mesh: the token is declared once the session is linked to this many other peers
    (:meth:`Node.ready`); 0: at once."""
    window: int = 0
    """Lockstep: the clock's window (``tether run --window``). Each stream keeps its messages of the
    last ``window + 1`` ticks, to send them again when a tick has waited :data:`RESEND` for its inputs
    (0: none kept)."""


class Node:
    """A process's session, inputs, clock and lifetime; :func:`serve` makes one per process.

    The node is given its :class:`~tether.clock.Clock` (lockstep or real time); it never reads the
    time itself."""

    def __init__(self, args: NodeArgs, mission: ms.Mission, session: zenoh.Session, clock: Clock):
        self.args = args
        self.mission = mission
        self.session = session
        self.clock = clock
        self._dt = mission.dt
        """The control period [s] (a property of the mission, computed once here)."""
        self.keys = wire.Keys(args.ns or mission.name)
        self.ingress = Ingress(session, self.keys, mission, clock, backlog=args.role in BACKLOG_ROLES)
        self.outputs = Outputs(session, clock, args.node_id, args.window)
        self._declared: list[Any] = []
        """What a role asked to keep (:meth:`hold`), undeclared by :meth:`close`."""
        self.closing = False
        """Set when :meth:`close` begins."""
        self._token: Any = None
        self._start: Source | None = None
        self._recorded: Source | None = None
        """Lockstep, a member of the swarm: the launcher's word that every sample is recorded."""
        self.tasks: asyncio.TaskGroup | None = None
        """The task group that owns this process's tasks (set by :func:`serve`); :meth:`ready`
        starts the real-time input pump in it, so that the pump ends with the process's work."""
        self.stop = asyncio.Event()
        self.rejoined = False
        """Real time: this process joined a run already under way (see :meth:`ready`)."""

    # the ingress's parts that roles read through the node
    @property
    def receiver(self) -> wire.Receiver:
        """The decoder, with its drop counts by reason."""
        return self.ingress.receiver

    @property
    def wakeup(self) -> handoff.Wakeup:
        return self.ingress.wakeup

    @property
    def fifo(self) -> handoff.BoundedFifo[tp.Received]:
        return self.ingress.fifo

    @property
    def deferred(self) -> handoff.BoundedFifo[tp.Received]:
        return self.ingress.deferred

    @property
    def sources(self) -> dict[str, Source]:
        return self.ingress.sources

    @property
    def inputs(self) -> dict[str, handoff.InputQueue[tp.Received]]:
        return self.ingress.inputs

    @property
    def overflow(self) -> dict[str, int]:
        """Real time: samples each input key's queue dropped (oldest first), by key."""
        return self.ingress.overflow

    @property
    def token_log(self) -> list[tuple[str, bool]]:
        return self.ingress.token_log

    @property
    def alive(self) -> dict[str, bool]:
        """Liveliness seen so far, by token key: True while present, False once gone."""
        return self.ingress.alive

    @property
    def copies(self) -> int:
        """Lockstep: copies received of samples already had (:attr:`tether.ingress.Ingress.copies`)."""
        return self.ingress.copies

    @property
    def resent(self) -> int:
        """Messages sent again so far (:meth:`resend`)."""
        return self.outputs.resent

    # ------------------------------------------------------------------ declarations
    def withdraw(self) -> None:
        """Withdraw this process's liveliness token (it is alive but out of the swarm: a plant whose
        vehicle's link is lost)."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None

    def hold(self, *declared: Any) -> None:
        """Keep Zenoh declarations (tokens, queryables) until the node closes."""
        self._declared.extend(declared)

    def publisher(self, key: str, qos: tp.StreamQos | None = None, sender: int | None = None) -> Publisher:
        """A stamped publisher on ``key`` (:meth:`tether.outputs.Outputs.publisher`)."""
        return self.outputs.publisher(key, qos, sender)

    def subscribe(self, pattern: str, wake: bool = True) -> None:
        """One subscription for many inputs (:meth:`tether.ingress.Ingress.subscribe`)."""
        self.ingress.subscribe(pattern, wake)

    def source(self, key: str, expect: type, sender: int | None,
               on_message: Callable[[Any], None] | None = None, channel: Link | None = None,
               subscribe: bool = True, keep: bool = True, wake: bool = True,
               tap: Callable[[tp.Received], None] | None = None) -> Source:
        """An input on ``key`` (:meth:`tether.ingress.Ingress.source`)."""
        return self.ingress.source(key, expect, sender, on_message, channel, subscribe, keep, wake, tap)

    def tick_source(self, grant: Callable[[int], None]) -> None:
        """Lockstep, a paced role: hear the clock source's grants."""
        self.source(self.keys.tick, wire.Tick, 0, on_message=lambda m: grant(m.grant), keep=False)

    def recorded_source(self) -> Source:
        """Lockstep, a member of the swarm: the launcher's word that every sample is recorded."""
        return self.source(self.keys.recorded, wire.Recorded, 0, keep=False)

    @property
    def stall_timeout(self) -> float:
        return self.args.stall_timeout

    def quieten(self, src: Source) -> None:
        """Real time: ``src``'s samples no longer wake the event loop (:meth:`tether.ingress.Ingress.quieten`)."""
        self.ingress.quieten(src)

    def queryable(self, key: str, handle: Callable[[zenoh.Query], None]) -> None:
        """Answer queries on ``key`` with ``handle`` (:meth:`tether.ingress.Ingress.queryable`)."""
        self.ingress.queryable(key, handle)

    def count_drop(self, reason: str) -> None:
        """Count one input dropped for ``reason`` (reported in telemetry with the decoder's drops)."""
        self.ingress.receiver.count(reason)

    def gone(self, role: str) -> frozenset[int]:
        """Ids of ``role`` whose liveliness token was seen and is gone now (:meth:`tether.ingress.Ingress.gone`)."""
        return self.ingress.gone(role)

    def watch(self, role: str, node_id: int, *sources: Source) -> None:
        """Mark ``sources`` silent while the token of ``role``/``node_id`` is absent."""
        self.ingress.watch(role, node_id, *sources)

    async def pump(self) -> None:
        """Real time: drain inputs whenever samples arrive, so that ``on_message`` hooks (an agent
        relaying its plant's measurement) run at once instead of at the next tick."""
        while True:
            due = self.ingress.next_delivery()
            await self.ingress.wakeup.wait(None if due is None else max(0.0, due - self.mission_time()))
            self.drain()

    async def pace(self) -> None:
        """Real time: once per control period, wake the loop if deferred samples wait (:meth:`subscribe`)."""
        while True:
            await asyncio.sleep(self.mission.dt)
            if len(self.ingress.deferred):
                self.ingress.wakeup.notify_here()

    async def _mesh_linked(self) -> None:
        """A peer of a mesh (``--mesh-peers N``): wait until the session is linked to N other peers.
        The launcher starts the run once it holds every token, through its router; in a mesh a
        sample goes over the link between its two peers, so a token declared before the links were
        up let the run start while some samples still had nowhere to go (a lockstep ring of 32
        stalled at tick 0, the recorder missing the samples of the peers it was not yet linked to).
        Raises :class:`Stalled` naming the count after ``--connect-timeout``."""
        want = self.args.mesh_peers
        if not want:
            return
        info = self.session.info
        limit = self.args.zenoh.connect_timeout or 10.0
        have = 0
        try:
            async with asyncio.timeout(limit):
                while (have := len(info.peers_zid())) < want:
                    await asyncio.sleep(MESH_POLL)
            log.info("mesh: linked to %d other peers", have)
        except TimeoutError:
            raise Stalled(f"linked to {have} of the mesh's {want} other peers after {limit:g} s "
                          "(--connect-timeout); a star (--network star) needs one link per process") from None

    async def ready(self, paced: bool = False, phase: float = 0.0, token: bool = True,
                    rejoin: Callable[[], float | None] | None = None) -> None:
        """Declare liveliness (after every subscription, so a launcher that sees the token knows
        this process hears everything it needs), then wait for the start. ``token=False``: a
        process outside the swarm (``tether record``) declares none, so that no launcher or
        agent counts it as a member (it joins a run under way through ``rejoin``).

        In lockstep, only a ``paced`` role (the leader, whose inputs do not depend on the tick)
        follows the clock's grants; every other role is gated by its inputs of tick k, which is
        what makes the run deterministic, and needs only the start. In real time, tick k starts at
        ``epoch + (k + phase) h``. ``rejoin`` (real time): returns the start instant of a run
        already under way, once the role can tell it (a restarted agent, from its plant's samples),
        else None; the process then joins that run (:attr:`rejoined`) instead of waiting for a start
        message that was sent before it existed."""
        self.ingress.watch_tokens()
        self._recorded = self.clock.prepare(self, paced, member=token and self.args.role not in BACKLOG_ROLES)
        start = self._start = self.source(self.keys.start, wire.Start, 0, keep=False)
        if token:
            await self._mesh_linked()
            self._token = tp.declare_token(self.session, self.keys.token(self.args.role, self.args.node_id))
        joined: list[float] = []
        rejoin = self.clock.join(rejoin)

        def started() -> bool:
            if start.newest is not None:
                return True
            if rejoin is not None and (e := rejoin()) is not None:
                joined.append(e)
                return True
            return False

        await self.until(started, self.args.start_timeout, "the launcher's start message (--start-timeout)")
        epoch = start.newest.epoch if start.newest is not None else joined[0]
        self.rejoined = start.newest is None
        if self.rejoined:
            log.info("joined a run already under way: tick 0 taken as %.3f from the samples heard", epoch)
        try:
            began = self.clock.begin(epoch, phase)
        except ClockError as exc:
            raise Stalled(str(exc)) from None
        companions = self.clock.companions(self, self.ingress.deferring)
        if companions:
            if self.tasks is None:
                for _, coro in companions:
                    coro.close()
                raise RuntimeError("Node.ready: real time needs serve()'s task group for the input pump")
            for name, coro in companions:
                self.tasks.create_task(coro, name=name)
        log.info("%s", began)

    # ------------------------------------------------------------------ inputs
    def mission_time(self) -> float:
        """Real time: seconds since tick 0 on this host's monotonic clock (the emulated network's
        time base). Lockstep: the emulated network runs on sample times instead (0 here)."""
        return self.clock.now()

    def drain(self) -> None:
        """Decode every pending sample and token event (on the event loop; :meth:`tether.ingress.Ingress.drain`)."""
        self.ingress.drain()

    def arrival(self) -> float:
        """Real time: when the sample being accepted arrived [s, mission time] (:meth:`tether.ingress.Ingress.arrival`)."""
        return self.ingress.arrival()

    def arrived_ago(self) -> float:
        """Real time: how long ago [s] the sample being accepted arrived (:meth:`tether.ingress.Ingress.arrived_ago`)."""
        return self.ingress.arrived_ago()

    def release(self, now: float, only: Source | None = None) -> None:
        """Hand the copies that emulated links deliver by ``now`` to their sources (:meth:`tether.ingress.Ingress.release`)."""
        self.ingress.release(now, only)

    async def until(self, ready: Callable[[], bool], timeout: float | None, what: str | Callable[[], str],
                    resend: bool = False) -> None:
        """Wait (draining inputs) until ``ready()``; :class:`Stalled` naming ``what`` after ``timeout``
        (a callable: asked then, so that it can say what is still missing at that moment).

        ``resend`` (a lockstep tick's wait): every :data:`RESEND` of waiting (a third of ``timeout``
        at most), the process's streams send their kept messages again (:meth:`resend`)."""
        self.drain()
        if ready():  # the common case in lockstep (a grant window ahead, a sample already in): no timer
            return
        # the bound is one timer that wakes this wait (``asyncio.timeout`` around it cost a waiting
        # agent about 8 us more of its loop's CPU a wait: a wait nearly every lockstep tick); with
        # ``resend`` it first rings at each resend instant, then at the deadline
        loop = asyncio.get_running_loop()
        began = loop.time()
        deadline = math.inf if timeout is None else began + timeout
        step = min(RESEND, timeout / 3) if timeout is not None else RESEND
        step = step if resend and self.outputs.kept else math.inf
        rang = [False]

        def alarm() -> None:
            rang[0] = True
            self.ingress.wakeup.notify_here()

        def arm() -> asyncio.TimerHandle | None:
            at = min(deadline, loop.time() + step)
            return None if at == math.inf else loop.call_at(at, alarm)

        timer = arm()
        try:
            while not ready():
                if rang[0]:
                    rang[0] = False
                    missing = what if isinstance(what, str) else what()
                    if timer is not None and timer.when() >= deadline:
                        raise Stalled(f"waited {timeout:g} s for {missing}")
                    self.resend(missing, loop.time() - began)
                    timer = arm()
                await self.ingress.wakeup.wait(None)
                self.drain()
        finally:
            if timer is not None:
                timer.cancel()

    def resend(self, waiting_for: str, waited: float = RESEND) -> int:
        """Lockstep: every stream's kept messages put again after a tick has waited ``waited``
        seconds for ``waiting_for`` (:meth:`tether.outputs.Outputs.resend`); how many."""
        return self.outputs.resend(waiting_for, waited)

    async def sample(self, src: Source, k: int, drain: bool = True) -> Any:
        """Lockstep: the sample of tick ``k`` (waits). Real time: the newest held (may be None).
        ``drain``: as :meth:`aligned`'s."""
        return (await self.aligned([src], k, drain=drain))[0]

    async def aligned(self, sources: list[Source], k: int, drain: bool = True) -> list[Any]:
        """One sample per source, all of the same tick where possible (the clock's
        :meth:`~tether.clock.Clock.align`).

        Lockstep: the samples of tick ``k`` (waits for each). Real time: among the sources whose
        newest sample is at most :data:`~tether.clock.MAX_LAG` ticks old, the newest tick ``c <= k``
        that all of them hold; a source older than that (silent, or not started) gives its newest
        sample, or None.

        ``drain=False``: the caller has just drained (a previous call at this tick, or
        :meth:`tick`, as it returns); what arrived since is taken at the next drain, or (lockstep)
        by the wait for a missing sample, which drains first. A world process reading its
        vehicles' commands one by one drained every input key once per vehicle: N² queue checks
        per tick."""
        return await self.clock.align(self, sources, k, self._dt, drain)

    async def tick(self, k: int) -> float:
        """Wait until tick ``k`` may run (draining inputs meanwhile, and once more as it returns:
        what follows at this tick may read with ``drain=False``); returns its lateness [s]."""
        return await self.clock.gate(self, k)

    async def linger(self) -> None:
        """Keep the session open after the last tick until this process's last samples have left.

        Lockstep (a member of the swarm): until the launcher says the recorder holds every sample
        of the run (:class:`~tether.wire.Recorded`), at most ``stall_timeout`` (the launcher has
        failed the run by then: no acknowledgement for that long); a deterministic end, whatever
        the load. Real time, or a lockstep process outside the swarm: :data:`LINGER` seconds."""
        got = self._recorded
        if got is None:
            await asyncio.sleep(LINGER)
            return
        last = self.mission.steps
        try:
            # a word for an earlier tick is not the end (no launcher sends one: a replay, or a bug)
            await self.until(lambda: got.newest is not None and got.newest.k >= last, self.args.stall_timeout,
                             "the launcher's word that every sample is recorded")
        except Stalled as exc:
            log.warning("%s: closing anyway", exc)

    def close(self) -> None:
        """Undeclare everything this node declared: its inputs first, once no tap runs (blocks up to
        :data:`~tether.ingress.TAP_DRAIN` [s]), then its publishers, what it held, its token."""
        self.closing = True
        self.ingress.close()
        self.outputs.close()
        undeclare(self._declared)
        if self._token is not None:
            self._token.undeclare()
            self._token = None


def load_mission(path: Path, duration: float | None = None) -> ms.Mission:
    """Load a mission, with its duration overridden when ``duration`` is given (then re-validated)."""
    return ms.with_duration(ms.load(path), duration, source=str(path))


async def _watch_parent(pid: int, stop: asyncio.Event) -> None:
    while not stop.is_set():
        if os.getppid() != pid:
            log.warning("launcher (pid %d) is gone: stopping", pid)
            stop.set()
            return
        try:
            async with asyncio.timeout(1.0):
                await stop.wait()
        except TimeoutError:
            pass


EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_STOPPED = 0, 1, 2, 143


class _Over(Exception):
    """Raised by a task of :func:`serve`'s group to end the group (the outcome is already noted)."""


async def serve(args: NodeArgs, role: Callable[[Node], Awaitable[None]],
                on_stop: Callable[[Node], None] | None = None, clock: Clock | None = None) -> int:
    """Run one role until it finishes, fails, or is told to stop (SIGTERM/SIGINT, launcher gone).

    Returns the exit status: 0 finished, 1 failed (logged), 2 bad mission, 143 stopped by a
    signal. ``on_stop`` runs after a stop too (the recorder writes its file there). The session is
    always closed. ``clock``: the process's clock (default: the one ``args.clock`` names).
    """
    try:
        mission = load_mission(args.mission_path, args.duration)
    except ms.MissionError as exc:
        log.error("%s", exc)
        return EXIT_BAD_INPUT
    loop = asyncio.get_running_loop()
    log.info("event loop: %s", evloop.running())
    async with tp.open_session(args.zenoh) as session:
        node = Node(args, mission, session, clock if clock is not None else make_clock(args.clock, mission.dt))
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, node.stop.set)
        try:
            status = await _run_tasks(node, role)
            report_drops(node.receiver.drops)
            if node.resent or node.copies:
                log.info("lockstep stalls: sent %d messages again; dropped %d copies of samples already had",
                         node.resent, node.copies)
            if on_stop is not None:
                try:
                    on_stop(node)
                except OSError as exc:
                    log.error("failed: %s", os_error(exc))
                    status = EXIT_FAILED
        finally:
            node.close()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
    return status


async def _run_tasks(node: Node, role: Callable[[Node], Awaitable[None]]) -> int:
    """The process's tasks in one :class:`asyncio.TaskGroup`: the role's work, the stop watcher,
    the launcher watcher (``parent_pid``) and, from :meth:`Node.ready` in real time, the input
    pump. The first of the work and the stop to end ends the group, cancelling the rest. Returns
    the exit status: 1 if the work (or another task) failed, else 143 if the stop came first,
    else 0."""
    failed = stopped = work_done = False

    async def work() -> None:
        nonlocal failed, work_done
        try:
            await role(node)
            work_done = True  # a stop during the linger is not a stop of the work
            if node.args.role not in BACKLOG_ROLES:
                await node.linger()  # the last samples leave first (a stop ends this at once)
        except Stalled as exc:
            log.error("stalled: %s", exc)
            failed = True
        except OSError as exc:  # a file that cannot be written (a full disk...): named, no traceback
            log.error("failed: %s", os_error(exc))
            failed = True
        except Exception:
            log.exception("failed")
            failed = True
        finally:
            work_done = True
        raise _Over

    async def watch_stop() -> None:
        nonlocal stopped
        await node.stop.wait()
        stopped = not work_done
        raise _Over

    try:
        async with asyncio.TaskGroup() as tasks:
            node.tasks = tasks
            tasks.create_task(work(), name=f"{node.args.role} {node.args.node_id}")
            tasks.create_task(watch_stop(), name="stop watcher")
            if node.args.parent_pid:
                tasks.create_task(_watch_parent(node.args.parent_pid, node.stop), name="launcher watcher")
    except* _Over:
        pass
    except* Exception as group:
        for exc in group.exceptions:
            log.error("failed", exc_info=exc)
        failed = True
    finally:
        node.tasks = None
    return EXIT_FAILED if failed else EXIT_STOPPED if stopped else EXIT_OK


def report_drops(drops: dict[str, int], what: str = "inputs dropped") -> None:
    """Log, once at the end, what a process dropped and counted, by reason (every role: a plant's
    or a world's drops reach no run file otherwise). Nothing dropped, nothing said."""
    if any(drops.values()):
        log.warning("%s: %s", what, ", ".join(f"{reason} {n}" for reason, n in sorted(drops.items()) if n))


def setup_logging(role: str, node_id: int, level: str = "INFO") -> None:
    """Plain one-line records on stderr: ISO time, level, role/id, message."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s %(levelname)s {role}/{node_id}: %(message)s",
    )
