"""What every process shares: its session, its inputs, its clock, its publishers, its lifetime.

A role (leader, agent, plant, recorder) is an ``async def run(node)`` that declares its inputs and
publishers on a :class:`Node`, calls :meth:`Node.ready`, then loops over ticks. ``Node`` is handed
its clock (:class:`~tether.clock.Clock`, lockstep or real time) and leaves to it whatever the two
differ in; neither it nor a role asks which one it holds:

* inputs are :class:`Source` objects; ``await node.aligned([src, ...], k)`` returns, in lockstep,
  the samples of tick ``k`` exactly (waiting for them), and in real time the newest samples of one
  common tick; an input that crosses an emulated link (``[netem]``) gives what the link delivered;
* ``await node.tick(k)`` gates tick ``k`` (a grant in lockstep, an instant in real time).

Zenoh callbacks only hand raw samples to one bounded FIFO (:class:`~tether.transport.BoundedFifo`,
drop-oldest, counted); decoding and checks run on the event loop (:class:`~tether.wire.Receiver`).
"""

from __future__ import annotations

import asyncio
import collections
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
from tether.inputs import Link, Source

log = logging.getLogger("tether")

FIFO_CAPACITY = 65536
"""Samples a process can hold between two drains before the oldest is dropped (and counted)."""
INPUT_BUDGET = 8
"""Real time: samples of one input key decoded per control period, on average: each key has a
budget (a token bucket) that gains this many per period, up to :func:`input_capacity`; a key whose
budget is spent waits, muted (its queue overwritten by newer samples), until the next period. A
flood on one key then costs the event loop at most this many decodes per period once the bucket
is empty (and one bucket's worth once), and wakes it at most once per period."""
BACKLOG = 2.0
"""Real time: seconds of one stream's samples that an input key holds and may decode at once: the
backlog a healed link (a partition shorter than the lease, 2 s by default) or a stalled loop
delivers in a burst. A stream brings one sample per period and uses one of its :data:`INPUT_BUDGET`,
so its bucket is full when the burst comes, and the burst is taken whole, not cut to the newest few."""


TICKED = frozenset({wire.State, wire.PlantState, wire.Command, wire.Telemetry, wire.WorldState})
"""Real time: the inputs whose sender sends one sample a tick, whose queue admits only the first
:data:`tether.handoff.PER_TICK` of each tick (:class:`tether.handoff.InputQueue`). Orders and control
messages (``SafetyCommand``, ``Start``, ...) are not: one may be said again for the same tick."""


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

BACKLOG_ROLES = frozenset({"recorder"})
"""The roles whose inputs hold and take a :data:`BACKLOG`: the recorder, which wants every sample
and runs no control loop. A role that flies (agent, plant, leader, world) holds the newest
:data:`INPUT_BUDGET` per key and decodes at most that many per period: it acts on the newest sample
only, and a burst of old ones decoded at once costs its loop time when it is already late (measured:
a 20 s authenticated real-time run of Section 4 with the 2 s backlog in every process had an RMS
formation error of 17 m against 0.44-0.70 m without it, on a loaded machine)."""


def input_capacity(rate: float) -> int:
    """Samples one input key's queue holds between two drains, and the most its budget saves up:
    :data:`BACKLOG` seconds of a stream at ``rate`` [Hz], at least :data:`INPUT_BUDGET`. Older ones
    are dropped (oldest first), counted per key in :attr:`Node.overflow` and logged once; in the
    recorder also as ``overflow`` in its drop counts (the run file's ``recorder_drops``), where each
    of them is a sample the run file lacks."""
    return max(INPUT_BUDGET, math.ceil(BACKLOG * rate))


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


TAP_DRAIN = 1.0
"""How long :meth:`Node.close` waits for a running tap [s]: a tap is one relay put (microseconds),
so a second only passes on a machine that gives the process no CPU."""


class _Tapped:
    """A sink that queues each sample, then hands it to ``tap`` on the same (Zenoh's) thread."""

    def __init__(self, queue: handoff.InputQueue[tp.Received], tap: Callable[[tp.Received], None], node: "Node"):
        self.queue, self.tap, self.node = queue, tap, node

    def put(self, item: tp.Received, /) -> None:
        self.queue.put(item)
        if not self.node.taps.enter():
            return  # the node is closing: its publishers are going (a relay would put on an undeclared one)
        try:
            self.tap(item)
        except Exception:  # noqa: BLE001 - no input may crash Zenoh's thread; said and counted
            drops = self.node.receiver.drops  # this key is written by taps only
            n = drops["tap_error"] = drops.get("tap_error", 0) + 1
            if n in (1, 10, 100, 1000):
                log.exception("input %s: its tap failed (%d so far)", item.key, n)
        finally:
            self.node.taps.leave()


class Publisher:
    """A publisher that stamps sender, sequence number, tick and sample time on every message.

    ``keep`` (lockstep): the payloads of its messages of the last ``keep`` ticks, which
    :meth:`resend` puts again (:meth:`Node.until`, after :data:`RESEND` of waiting)."""

    def __init__(self, pub: zenoh.Publisher, sender: int, keep: int = 0):
        self._pub = pub
        self._sender = sender
        self.seq = 0
        self.keep = keep
        self.kept: collections.deque[tuple[int, bytes]] | None = collections.deque() if keep else None
        """``(tick, payload)`` of the messages kept, oldest first."""

    def send(self, cls: type, k: int, t: float, **fields: Any) -> None:
        self.put(cls(sender=self._sender, seq=self.seq, k=k, t=t, **fields))

    def put(self, msg: wire.Message) -> None:
        """Publish a message built by the caller (its sender and sequence number are the caller's)."""
        self.seq += 1
        payload = wire.encode(msg)
        self._pub.put(payload)
        if self.kept is not None:
            self._keep(msg.k, payload)

    def _keep(self, k: int, payload: bytes) -> None:
        kept = self.kept
        assert kept is not None
        kept.append((k, payload))
        while kept[0][0] <= k - self.keep:  # a record carries many ticks: kept by its last, as many as it takes
            kept.popleft()

    def resend(self) -> int:
        """Put the kept messages again, oldest first (the same bytes: a receiver that has one keeps
        the first copy and counts the other as a duplicate). Returns how many."""
        kept = list(self.kept or ())
        for _, payload in kept:
            self._pub.put(payload)
        return len(kept)


class Node:
    """A process's session, inputs, clock and lifetime; :func:`serve` makes one per process.

    The node is given its :class:`~tether.clock.Clock` (lockstep or real time); it never reads the
    time itself."""

    def __init__(self, args: NodeArgs, mission: ms.Mission, session: zenoh.Session, clock: Clock):
        self.args = args
        self.mission = mission
        self.session = session
        self.keys = wire.Keys(args.ns or mission.name)
        self.receiver = wire.Receiver(mission.dim)
        self.wakeup = handoff.Wakeup()
        self.fifo: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(FIFO_CAPACITY, self.wakeup)
        self.deferred: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(FIFO_CAPACITY)
        """Real time: samples of :meth:`subscribe` ``(wake=False)`` subscriptions, which wake nobody;
        drained with the rest, at the latest one control period after they arrive (:meth:`pace`)."""
        self.tokens: handoff.BoundedFifo[tp.TokenEvent] = handoff.BoundedFifo(4096, self.wakeup)
        self.queries: handoff.BoundedFifo[tuple[Callable[[zenoh.Query], None], zenoh.Query]] = \
            handoff.BoundedFifo(64, self.wakeup)
        self.sources: dict[str, Source] = {}
        self.inputs: dict[str, handoff.InputQueue[tp.Received]] = {}
        """Real time: one bounded queue per subscribed input key (see :data:`INPUT_BUDGET`)."""
        self._budget: dict[str, float] = {}
        """Real time: decodes each input key has left (:data:`INPUT_BUDGET`)."""
        self._capacity = input_capacity(mission.rate) if args.role in BACKLOG_ROLES else INPUT_BUDGET
        self._overflow: dict[str, int] = {}
        self._excess: dict[str, int] = {}
        """Real time: samples each input key's queue dropped as a tick's excess, by key (counted as
        ``excess`` in the receiver's drops)."""
        self.overflow = self._overflow
        """Real time: samples each input key's queue dropped (oldest first), by key."""
        self._period = -1
        self._rearm: asyncio.Handle | None = None
        self._watched: dict[str, list[Source]] = {}
        self._deferring = False
        self._fifo_lost = {"inputs": 0, "deferred inputs": 0}
        """Samples each FIFO had dropped at the last drain (the rest are new, counted as ``overflow``)."""
        self.closing = False
        """Set when :meth:`close` begins."""
        self.taps = handoff.TapGuard()
        """Taps (relays published from Zenoh's thread) run inside it; :meth:`close` waits for them."""
        self._gone: dict[str, frozenset[int]] = {}
        """:meth:`gone`'s answers since the last token event."""
        self._linked: list[Source] = []
        """The sources behind an emulated link (:meth:`release` looks at these only, every drain)."""
        self._declared: list[Any] = []
        self._kept: list[Publisher] = []
        """Lockstep publishers that keep their last messages (:meth:`resend`)."""
        self.resent = 0
        """Messages sent again so far (:meth:`resend`)."""
        self.copies = 0
        """Lockstep: copies received of samples already had, sent again by a peer after a stall
        (:meth:`resend`). Dropped, counted here and logged at the end; kept out of the link statistics
        and the drop counts, which a run records and which must not depend on the machine's load."""
        self._token: Any = None
        self.clock = clock
        self._start: Source | None = None
        self._recorded: Source | None = None
        """Lockstep, a member of the swarm: the launcher's word that every sample is recorded."""
        self.tasks: asyncio.TaskGroup | None = None
        """The task group that owns this process's tasks (set by :func:`serve`); :meth:`ready`
        starts the real-time input pump in it, so that the pump ends with the process's work."""
        self.stop = asyncio.Event()
        self.token_log: list[tuple[str, bool]] = []
        self.alive: dict[str, bool] = {}
        """Liveliness seen so far, by token key: True while present, False once gone."""
        self.rejoined = False
        """Real time: this process joined a run already under way (see :meth:`ready`)."""
        self._arrival = math.nan
        """The callback's stamp of the sample being accepted (:meth:`arrival`); NaN otherwise."""

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
        """A stamped publisher on ``key``. Real time: ``qos`` (default :data:`~tether.transport.STATE`,
        DROP: the newest supersedes). Lockstep: always :data:`~tether.transport.SYNC` (BLOCK),
        because a lost sample would stall the run: measured here, DROP state streams lost samples
        under load and stalled lockstep runs."""
        qos, keep = self.clock.stream(qos, self.args.window)
        pub = tp.declare_publisher(self.session, key, qos)
        self._declared.append(pub)
        out = Publisher(pub, self.args.node_id if sender is None else sender, keep=keep)
        if out.kept is not None:
            self._kept.append(out)
        return out

    def subscribe(self, pattern: str, wake: bool = True) -> None:
        """One subscription (one callback thread) for many inputs: samples on keys matching
        ``pattern`` reach the sources declared with ``subscribe=False``; others are ignored.

        ``wake=False`` (real time; lockstep ignores it, a tick waits for its inputs): its samples do
        not wake the event loop as they arrive; each is stamped with its arrival time in the
        callback (what a source's plausibility gate sees through :meth:`arrival`) and decoded at
        the next drain, which comes at the latest one control period later (:meth:`pace`). For a
        role that reacts to no single sample (the recorder): a burst of a tick's samples then
        costs one wake-up instead of one per sample."""
        sink, stamp = self.clock.subscription(self, wake)
        self._deferring |= sink is self.deferred
        self._declared.append(tp.declare_subscriber(self.session, pattern, sink, stamp))

    def source(self, key: str, expect: type, sender: int | None,
               on_message: Callable[[Any], None] | None = None, channel: Link | None = None,
               subscribe: bool = True, keep: bool = True, wake: bool = True,
               tap: Callable[[tp.Received], None] | None = None) -> Source:
        """Subscribe to ``key``; samples are checked as ``expect`` from ``sender``. ``channel``: the
        emulated link the samples cross from ``sender`` to this node (``[netem]``; built by the role
        with :class:`netem.link.Channel`, so that only a mission with a ``[netem]`` section loads
        the emulator; an ideal link delivers every sample at its own time: the run is then the
        same as without the section, bit for bit).

        ``wake=False`` (real time; an input read only at the tick, without ``on_message`` or
        ``channel``): its samples do not wake the event loop as they arrive; they are decoded at
        the next drain (the tick's), and each is stamped with its arrival time in the callback,
        which is what the plausibility gate and the clock-offset monitor see (:meth:`arrival`).
        Lockstep ignores it: a tick waits for its inputs.

        ``tap`` (real time): also called with each sample, stamped, on Zenoh's callback thread right
        after it is queued, for work that must not wait for the event loop (an agent relaying its
        plant's measurement: :mod:`agent.relay`). It runs beside the loop: it may touch only what
        it owns. An exception in it is logged and counted (``tap_error``), never raised into Zenoh."""
        src = Source(key, expect, sender, last=self.mission.steps, on_message=on_message, keep=keep,
                     channel=channel)
        self.sources[key] = src
        if channel is not None:
            self._linked.append(src)
        if subscribe:
            quiet = not wake and on_message is None and channel is None
            sink, stamp = self.clock.input_sink(self, key, expect, quiet, tap)
            self._declared.append(tp.declare_subscriber(self.session, key, sink, stamp))
        return src

    def bounded(self, key: str, expect: type, quiet: bool,
                tap: Callable[[tp.Received], None] | None) -> handoff.Sink[tp.Received]:
        """Real time: one bounded queue for input ``key`` (:data:`INPUT_BUDGET`), which wakes the
        loop unless ``quiet``, its samples also handed to ``tap`` on Zenoh's thread."""
        # a stream's sender sends one sample a tick (its excess is a flood); an order or a control
        # message may be repeated for one tick (the operator's land, said again)
        tick_of = tp.tick_of if expect in TICKED else None
        queue = self.inputs[key] = handoff.InputQueue(self._capacity, None if quiet else self.wakeup, tick_of=tick_of)
        return queue if tap is None else _Tapped(queue, tap, self)

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
        """Real time: ``src``'s samples no longer wake the event loop; they are decoded at the next
        drain (for an input that must wake the loop only for a while: a plant's commands, until
        its start). Lockstep: nothing changes."""
        q = self.inputs.get(src.key)
        if q is not None:
            q.quieten()

    def queryable(self, key: str, handle: Callable[[zenoh.Query], None]) -> None:
        """Answer queries on ``key`` with ``handle`` (called on the event loop, from :meth:`drain`;
        Zenoh's thread only queues the query, at most 64 waiting: more are dropped, and their askers
        time out). The query is released after ``handle`` returns; an asker that went away is
        logged, not raised."""
        self._declared.append(self.session.declare_queryable(key, lambda q: self.queries.put((handle, q))))

    def _serve_queries(self) -> None:
        for handle, query in self.queries.drain():
            try:
                handle(query)
            except zenoh.ZError as exc:  # the asker is gone: nothing to answer
                log.warning("query on %s: could not answer: %s", query.key_expr, exc)
            finally:
                query.drop()

    def count_drop(self, reason: str) -> None:
        """Count one input dropped for ``reason`` (reported in telemetry with the decoder's drops)."""
        self.receiver.count(reason)

    def gone(self, role: str) -> frozenset[int]:
        """Ids of ``role`` whose liveliness token was seen and is gone now (kept between token
        events: an agent asks every tick)."""
        cached = self._gone.get(role)
        if cached is None:
            cached = self._gone[role] = frozenset(self._gone_now(role))
        return cached

    def _gone_now(self, role: str) -> set[int]:
        out = set()
        for key, up in self.alive.items():
            if not up:
                try:
                    r, nid = wire.Keys.parse_token(key)
                except ValueError:  # a token on a malformed key (a non-numeric id): no input may crash
                    continue
                if r == role:
                    out.add(nid)
        return out

    def watch(self, role: str, node_id: int, *sources: Source) -> None:
        """Mark ``sources`` silent while the token of ``role``/``node_id`` is absent."""
        key = self.keys.token(role, node_id)
        self._watched.setdefault(key, []).extend(sources)

    async def pump(self) -> None:
        """Real time: drain inputs whenever samples arrive, so that ``on_message`` hooks (an agent
        relaying its plant's measurement) run at once instead of at the next tick."""
        while True:
            due = self.next_delivery()
            await self.wakeup.wait(None if due is None else max(0.0, due - self.mission_time()))
            self.drain()

    async def pace(self) -> None:
        """Real time: once per control period, wake the loop if deferred samples wait (:meth:`subscribe`)."""
        while True:
            await asyncio.sleep(self.mission.dt)
            if len(self.deferred):
                self.wakeup.notify_here()

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
        if self._watched:
            self._declared.append(tp.watch_tokens(self.session, self.keys.tokens, self.tokens))
        self._recorded = self.clock.prepare(self, paced, member=token and self.args.role not in BACKLOG_ROLES)
        start = self._start = self.source(self.keys.start, wire.Start, 0, keep=False)
        if token:
            await self._mesh_linked()
            self._token = tp.declare_token(self.session, self.keys.token(self.args.role, self.args.node_id))
        joined: list[float] = []

        def started() -> bool:
            if start.newest is not None:
                return True
            if rejoin is not None and (e := rejoin()) is not None:  # never in lockstep: nothing to join
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
        companions = self.clock.companions(self, self._deferring)
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
        """Decode every pending sample and token event (on the event loop). A sample that crosses
        an emulated link is offered to it (at its sample time in lockstep, at the current mission
        time in real time) and reaches its source when the link delivers it (:meth:`release`)."""
        for rec in self.fifo.drain():
            self._accept(rec)
        for rec in self.deferred.drain():
            self._accept(rec)
        for name, fifo in (("inputs", self.fifo), ("deferred inputs", self.deferred)):
            lost = fifo.dropped - self._fifo_lost[name]
            if lost:  # more than FIFO_CAPACITY samples between two drains (a flood, or a stalled loop)
                if not self._fifo_lost[name]:
                    log.warning("%s: more than %d samples between two drains; the oldest are dropped "
                                "(counted as 'overflow')", name, fifo.capacity)
                self._fifo_lost[name] += lost
                self.receiver.count("overflow", lost)
        if self.inputs:
            self._drain_inputs()
        self.clock.deliver(self)
        self._serve_queries()
        for ev in self.tokens.drain():
            self.token_log.append((ev.key, ev.alive))
            self.alive[ev.key] = ev.alive
            self._gone.clear()
            for src in self._watched.get(ev.key, ()):
                was_gone, src.gone = src.gone, not ev.alive
                if ev.alive and was_gone:
                    log.warning("%s is back", ev.key)
                elif not ev.alive and src.silent:
                    log.warning("%s went silent (liveliness token gone)", ev.key)

    def arrival(self) -> float:
        """Real time: when the sample being accepted arrived [s, mission time] (its callback's
        stamp, for an input that does not wake the loop), else now (:meth:`mission_time`)."""
        return self.clock.arrival(self._arrival)

    def arrived_ago(self) -> float:
        """Real time: how long ago [s] the sample being accepted arrived (its callback's stamp), for
        one drained later than it arrived; else 0."""
        return self.clock.ago(self._arrival)

    def _accept(self, rec: tp.Received) -> None:
        src = self.sources.get(rec.key)
        if src is None:
            return
        msg = self.receiver.accept(rec.payload, src.expect, src.sender)
        if msg is None:
            return
        self.clock.offer(self, src, msg, rec)

    def offer(self, src: Source, msg: Any, at: float, missed: bool) -> None:
        """Hand ``msg`` to ``src``, its arrival stamp ``at`` what :meth:`arrival` says meanwhile
        (``missed``: as :meth:`tether.inputs.Source.offer`'s)."""
        self._arrival = at
        try:
            src.offer(msg, missed=missed)
        finally:
            self._arrival = math.nan

    def _drain_inputs(self) -> None:
        """Decode what each input key's budget allows (:data:`INPUT_BUDGET` more per control period,
        saved up to :func:`input_capacity`); a key whose budget is spent is muted until the next
        period, when a timer wakes the loop to go on."""
        h = self.mission.dt
        cap = self._capacity
        reading = self.clock.reading
        period = int(reading() // h)
        if period != self._period:
            gained = INPUT_BUDGET * (period - self._period if self._period >= 0 else 1)
            self._period = period
            for key in self._budget:
                self._budget[key] = min(cap, self._budget[key] + gained)
            for q in self.inputs.values():
                q.muted = False
        waiting = False
        for key, q in self.inputs.items():
            if q.excess != self._excess.get(key, 0):  # a tick's samples beyond the first two: a flood
                if key not in self._excess:
                    log.warning("input %s: more than %d samples of one tick; the later ones are dropped as they "
                                "come (counted as 'excess')", key, handoff.PER_TICK)
                self.receiver.count("excess", q.excess - self._excess.get(key, 0))
                self._excess[key] = q.excess
            if not len(q):  # nothing since the last drain (nor dropped: a drop leaves the queue full)
                continue
            left = self._budget.get(key, cap)  # a new key starts with a full budget
            items = q.take(int(left))
            self._budget[key] = left - len(items)
            for rec in items:
                self._accept(rec)
            if len(q) and self._budget[key] < 1:
                q.muted = True
                waiting = True
            if q.dropped and key not in self._overflow:  # once per key: a flood, or this loop stalled
                log.warning("input %s: more than %d samples between two drains; the oldest are dropped "
                            "(counted in Node.overflow%s)", key, cap,
                            " and as 'overflow'" if self.args.role in BACKLOG_ROLES else "")
            if q.dropped:
                lost = q.dropped - self._overflow.get(key, 0)
                if lost and self.args.role in BACKLOG_ROLES:  # a sample to record lost: the run file says why
                    self.receiver.count("overflow", lost)
                self._overflow[key] = q.dropped
        if waiting and self._rearm is None:
            delay = (period + 1) * h - reading()
            self._rearm = asyncio.get_running_loop().call_later(max(evloop.TIMER_GRAIN, delay), self._next_period)

    def _next_period(self) -> None:
        self._rearm = None
        self.wakeup.notify()

    def release(self, now: float, only: Source | None = None) -> None:
        """Hand the copies that emulated links deliver by ``now`` to their sources. A corrupted
        copy fails its checksum: dropped and counted as ``corrupt``."""
        for src in (only,) if only is not None else self._linked:
            if src.channel is None:
                continue
            bad = src.deliver(now, lambda payload: self.receiver.accept(payload, src.expect, src.sender))
            if bad:
                self.receiver.count("corrupt", bad)

    def next_delivery(self) -> float | None:
        """The earliest time [s, mission time] an emulated link will deliver a copy, if any."""
        times = [t for s in self._linked if s.channel is not None and (t := s.channel.next_at) is not None]
        return min(times) if times else None

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
        step = step if resend and self._kept else math.inf
        rang = [False]

        def alarm() -> None:
            rang[0] = True
            self.wakeup.notify_here()

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
                await self.wakeup.wait(None)
                self.drain()
        finally:
            if timer is not None:
                timer.cancel()

    def resend(self, waiting_for: str, waited: float = RESEND) -> int:
        """Lockstep: put every stream's kept messages (those of its last ``window + 1`` ticks) again,
        after a tick has waited ``waited`` seconds for ``waiting_for``. A peer of a mesh can miss a
        stream's first samples for good: the run starts once every peer is linked to every other and
        its token is in, but a peer's subscriptions reach each other peer over their own link, and a
        sample put before they arrive goes nowhere (a lockstep run stalled at tick 0, an agent waiting
        for its in-neighbour's state of tick 0 while that neighbour waited further on). Sent again,
        the sample reaches the peer that waits for it. A receiver that has it keeps the first copy; the
        other is dropped and counted apart (:attr:`copies`, not a link's ``duplicates``), and one it
        missed is taken as if it had come in its turn: a run's arrays stay those of a run without
        the stall. Returns the number of messages sent again."""
        n = sum(pub.resend() for pub in self._kept)
        self.resent += n
        log.warning("waited %.1f s for %s: sent the last %d messages of my %d streams again (%d so far)",
                    waited, waiting_for, n, len(self._kept), self.resent)
        return n

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
        return await self.clock.align(self, sources, k, self.mission.dt, drain)

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
        """Undeclare everything this node declared, once no tap runs (blocks up to
        :data:`TAP_DRAIN` [s] for one running on Zenoh's thread: see :class:`~tether.handoff.TapGuard`)."""
        self.closing = True
        if not self.taps.close(TAP_DRAIN):
            log.warning("a tap still runs %.1f s after the close began: undeclaring anyway", TAP_DRAIN)
        if self._rearm is not None:
            self._rearm.cancel()
        for obj in reversed(self._declared):
            try:
                obj.undeclare()
            except zenoh.ZError:
                pass
            except RuntimeError as exc:  # still borrowed by a tap past TAP_DRAIN: the session's close frees it
                log.warning("undeclaring %s: %s", type(obj).__name__, exc)
        self._declared.clear()
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
