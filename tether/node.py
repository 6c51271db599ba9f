"""What every process shares: its session, its inputs, its clock, its publishers, its lifetime.

A role (leader, agent, plant, recorder) is an ``async def run(node)`` that declares its inputs and
publishers on a :class:`Node`, calls :meth:`Node.ready`, then loops over ticks. ``Node`` hides the
two clocks behind one code path:

* inputs are :class:`Source` objects; ``await node.aligned([src, ...], k)`` returns, in lockstep,
  the samples of tick ``k`` exactly (waiting for them), and in real time the newest samples of one
  common tick; an input that crosses an emulated link (``[netem]``) gives what the link delivered;
* ``await node.tick(k)`` gates tick ``k`` (a grant in lockstep, an instant in real time).

Zenoh callbacks only hand raw samples to one bounded FIFO (:class:`~tether.transport.BoundedFifo`,
drop-oldest, counted); decoding and checks run on the event loop (:class:`~tether.wire.Receiver`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import signal
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from netem.channel import DeliveryQueue, Link, link_rng
from netem.profile import Network, resolve, schedule, validate_network
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.clock import ClockKind, LockstepClock, RealtimeClock

log = logging.getLogger("tether")

FIFO_CAPACITY = 65536
"""Samples a process can hold between two drains before the oldest is dropped (and counted)."""


RECENT_SEQS = 256
"""Sequence numbers a source remembers to tell duplicates from reordered samples (a duplicate
arriving more than this many samples late counts as reordered)."""


class Stalled(RuntimeError):
    """A lockstep input did not arrive in time; the message names it."""


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


@dataclass
class Source:
    """One input key: the samples accepted from it, by tick and newest, and what was seen."""

    key: str
    expect: type
    sender: int | None
    by_tick: dict[int, Any] = field(default_factory=dict)
    newest: Any = None
    received: int = 0
    stale: int = 0
    """Samples not newer (by sequence number) than the newest held: reordered or duplicated."""
    duplicates: int = 0
    """Stale samples whose sequence number had already been received (a second copy)."""
    reordered: int = 0
    """Stale samples seen for the first time (overtaken by a newer one on the way)."""
    corrupt: int = 0
    """Copies an emulated link corrupted (they fail the receiver's checksum and are dropped)."""
    recent: deque = field(default_factory=lambda: deque(maxlen=RECENT_SEQS))
    """The last sequence numbers received, to tell a duplicate from a reordered sample."""
    last: int = -1
    """The producer's last tick (the mission's), when known."""
    channel: "Channel | None" = None
    """The emulated network link this input arrives through (``[netem]``), if any."""
    raw_k: int = -1
    """Newest tick offered to the channel (what the sender has sent, before the network)."""
    gone: bool = False
    """Its producer's liveliness token is absent."""
    on_message: Callable[[Any], None] | None = None
    keep: bool = True
    """Hold samples by tick for :meth:`Node.aligned`; False for inputs consumed by ``on_message``
    alone (the recorder), which would otherwise hold every sample of the run."""

    @property
    def silent(self) -> bool:
        """The producer is gone before its last tick (one that sent its last tick and left is not
        silent, whatever order its last sample and its token's end arrive in)."""
        return self.silent_at(self.last)

    def silent_at(self, k: int) -> bool:
        """Silent as far as tick ``k`` is concerned: gone without having delivered tick ``k``.
        (In lockstep a tick runs only with its samples in, so this is never true there, and the
        flag cannot depend on when the token's end happened to be seen.)"""
        return self.gone and not (self.newest is not None and self.newest.k >= min(k, self.last))

    def offer(self, msg: Any) -> None:
        self.received += 1
        if self.newest is not None and msg.seq <= self.newest.seq:
            self.stale += 1
            if msg.seq in self.recent:
                self.duplicates += 1
            else:
                self.reordered += 1
        else:
            self.newest = msg
        self.recent.append(msg.seq)
        if self.keep:
            self.by_tick.setdefault(msg.k, msg)
        if self.on_message is not None:
            self.on_message(msg)

    def received_upto(self, k: int) -> int:
        """Samples accepted whose tick is at most ``k`` (in lockstep, what tick k could have seen,
        whatever arrived early)."""
        return self.received - sum(1 for t in self.by_tick if t > k)

    def forget_before(self, k: int) -> None:
        for old in [t for t in self.by_tick if t < k]:
            del self.by_tick[old]


@dataclass
class Channel:
    """One directed link j -> i of the emulated network: the link model, its profile schedule, and
    the copies in flight. Samples enter with :meth:`send` and leave with :meth:`release`."""

    link: Link
    changes: list[tuple[float, Any]]
    queue: DeliveryQueue = field(default_factory=DeliveryQueue)
    _next: int = 1

    @classmethod
    def of(cls, m: ms.Mission, src: int, dst: int) -> "Channel":
        """Link ``src -> dst`` of mission ``m``'s ``[netem]`` section: its profile schedule and
        its generator ``link_rng(m.seed, src, dst)``."""
        changes = schedule(m.netem, src, dst)
        return cls(Link(changes[0][1], link_rng(m.seed, src, dst), log=m.netem.log), changes)

    def send(self, now: float, payload: bytes) -> None:
        while self._next < len(self.changes) and self.changes[self._next][0] <= now:
            self.link.set_profile(self.changes[self._next][1])
            self._next += 1
        self.queue.push(self.link.offer(now, payload))

    def release(self, now: float) -> list[Any]:
        return self.queue.pop_due(now)

    @property
    def last_offer(self) -> float:
        """Time of the newest offer [s] (-inf before the first)."""
        return self.link.last_offer

    def change(self, at: float, profile: Any) -> None:
        """Use ``profile`` for the offers from ``at`` on (one already past: from the next offer).
        Changes asked for the same time apply in the order they were asked for."""
        pending = self.changes[self._next:]
        pending.append((at, profile))
        pending.sort(key=lambda c: c[0])  # stable
        self.changes[self._next:] = pending


class Publisher:
    """A publisher that stamps sender, sequence number, tick and sample time on every message."""

    def __init__(self, pub: zenoh.Publisher, sender: int):
        self._pub = pub
        self._sender = sender
        self.seq = 0

    def send(self, cls: type, k: int, t: float, **fields: Any) -> None:
        msg = cls(sender=self._sender, seq=self.seq, k=k, t=t, **fields)
        self.seq += 1
        self._pub.put(wire.encode(msg))


class Node:
    """A process's session, inputs, clock and lifetime; :func:`serve` makes one per process."""

    def __init__(self, args: NodeArgs, mission: ms.Mission, session: zenoh.Session):
        self.args = args
        self.mission = mission
        self.session = session
        self.keys = wire.Keys(args.ns or mission.name)
        self.receiver = wire.Receiver(mission.dim)
        self.wakeup = tp.Wakeup()
        self.fifo: tp.BoundedFifo[tp.Received] = tp.BoundedFifo(FIFO_CAPACITY, self.wakeup)
        self.tokens: tp.BoundedFifo[tp.TokenEvent] = tp.BoundedFifo(4096, self.wakeup)
        self.queries: tp.BoundedFifo[zenoh.Query] = tp.BoundedFifo(64, self.wakeup)
        self.sources: dict[str, Source] = {}
        self._watched: dict[str, list[Source]] = {}
        self._declared: list[Any] = []
        self._token: Any = None
        self.lockstep = LockstepClock()
        self.clock: LockstepClock | RealtimeClock = self.lockstep
        self._start: Source | None = None
        self._paced = False
        self._pump: asyncio.Task | None = None
        self._epoch_mono: float | None = None
        """Real time: tick 0's instant on this host's monotonic clock."""
        self.stop = asyncio.Event()
        self.token_log: list[tuple[str, bool]] = []

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
        if self.args.clock == "lockstep":
            qos = tp.SYNC
        pub = tp.declare_publisher(self.session, key, qos or tp.STATE)
        self._declared.append(pub)
        return Publisher(pub, self.args.node_id if sender is None else sender)

    def subscribe(self, pattern: str) -> None:
        """One subscription (one callback thread) for many inputs: samples on keys matching
        ``pattern`` reach the sources declared with ``subscribe=False``; others are ignored."""
        self._declared.append(tp.declare_subscriber(self.session, pattern, self.fifo))

    def source(self, key: str, expect: type, sender: int | None,
               on_message: Callable[[Any], None] | None = None, link: bool = False,
               subscribe: bool = True, keep: bool = True) -> Source:
        """Subscribe to ``key``; samples are checked as ``expect`` from ``sender``. ``link``: the
        samples cross the network from ``sender`` to this node, through the mission's emulated
        link ``sender -> node`` when it has a ``[netem]`` section (an ideal link delivers every sample
        at its own time: the run is then the same as without the section, bit for bit)."""
        src = Source(key, expect, sender, last=self.mission.steps, on_message=on_message, keep=keep)
        if link and self.mission.netem is not None and sender is not None:
            src.channel = Channel.of(self.mission, sender, self.args.node_id)
        self.sources[key] = src
        if subscribe:
            self._declared.append(tp.declare_subscriber(self.session, key, self.fifo))
        return src

    def netem_control(self) -> None:
        """Serve ``tether netem-set``: a query on ``tether/<ns>/<role>/<id>/netem`` carrying a
        :class:`~tether.wire.NetemSet` changes this node's emulated in-links at run time, and is
        answered with what changed (or why nothing did: a malformed message, invalid rules, or a
        mission without a ``[netem]`` section, whose links bypass the emulator; those are also
        counted as ``netem_invalid``)."""
        key = self.keys.topic(self.args.role, self.args.node_id, "netem")
        self._declared.append(self.session.declare_queryable(key, self.queries.put))

    def _serve_queries(self) -> None:
        for query in self.queries.drain():
            try:
                payload = query.payload
                msg = self.receiver.accept(payload.to_bytes() if payload is not None else b"", wire.NetemSet, 0)
                if msg is None:
                    query.reply_err("not a valid NetemSet message (see tether.wire); nothing changed")
                    continue
                try:
                    done = self._apply_netem(msg)
                except ValueError as exc:
                    self.receiver.drops["netem_invalid"] = self.receiver.drops.get("netem_invalid", 0) + 1
                    log.error("netem change refused: %s", exc)
                    query.reply_err(f"{self.args.role} {self.args.node_id}: refused: {exc}")
                    continue
                query.reply(query.key_expr, json.dumps({"node": self.args.node_id, "changed": done}))
            except zenoh.ZError as exc:  # the asker is gone: nothing to answer
                log.warning("netem change: could not answer: %s", exc)
            finally:
                query.drop()

    def _apply_netem(self, msg: wire.NetemSet) -> list[dict]:
        """Apply a change to the matching in-links; returns ``[{src, dst, at}]``. Raises ValueError."""
        me = self.args.node_id
        ids = [*self.mission.agent_ids, self.mission.leader.id]
        problems = validate_network(Network(rules=tuple(msg.rules)), ids, path="rules")
        if msg.at is not None and not (math.isfinite(msg.at) and msg.at >= 0):
            problems.append(("at", f"is {msg.at}; give a mission time >= 0 [s], or none for 'now'"))
        if self.mission.netem is None:
            problems.append(("netem", "the mission has no [netem] section, so its links bypass the emulator; "
                                      'add `[netem]` with `default = "ideal"` to change links at run time'))
        if problems:
            raise ValueError("; ".join(f"{f} {m}" for f, m in problems))
        channels = {s.sender: s.channel for s in self.sources.values() if s.channel is not None}
        done = []
        for rule in msg.rules:
            if rule.dst not in (None, me):
                continue
            prof = resolve(rule.profile)
            for src, ch in sorted(channels.items()):
                if rule.src not in (None, src):
                    continue
                now = max(ch.last_offer, 0.0)  # before the first offer: from tick 0
                at = msg.at if msg.at is not None else (
                    self.mission_time() if isinstance(self.clock, RealtimeClock) else now)
                if at < now:
                    log.warning("netem change of link %d -> %d for t = %.3f s arrived at t = %.3f s: "
                                "applied from the next sample", src, me, at, now)
                ch.change(at, prof)
                done.append({"src": src, "dst": me, "at": max(at, now)})
                log.info("link %d -> %d: profile changed from t = %.3f s", src, me, max(at, now))
        return done

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

    async def ready(self, paced: bool = False, phase: float = 0.0) -> None:
        """Declare liveliness (after every subscription, so a launcher that sees the token knows
        this process hears everything it needs), then wait for the start.

        In lockstep, only a ``paced`` role (the leader, whose inputs do not depend on the tick)
        follows the clock's grants; every other role is gated by its inputs of tick k, which is
        what makes the run deterministic, and needs only the start. In real time, tick k starts at
        ``epoch + (k + phase) h``."""
        if self._watched:
            self._declared.append(tp.watch_tokens(self.session, self.keys.tokens, self.tokens))
        self._paced = paced and self.args.clock == "lockstep"
        if self._paced:
            self.source(self.keys.tick, wire.Tick, 0, on_message=lambda m: self.lockstep.grant(m.grant), keep=False)
        start = self._start = self.source(self.keys.start, wire.Start, 0, keep=False)
        self._token = tp.declare_token(self.session, self.keys.token(self.args.role, self.args.node_id))
        await self.until(lambda: start.newest is not None, None, "the launcher's start message")
        if self.args.clock == "realtime":
            epoch = start.newest.epoch
            mono = time.monotonic
            if abs(epoch - time.time()) > 3600:
                raise Stalled(f"the start instant {epoch} is more than an hour from this host's clock; "
                              "check the clocks (NTP) of the launcher and this host")
            h = self.mission.dt
            self._epoch_mono = mono() + (epoch - time.time())
            self.clock = RealtimeClock(h, self._epoch_mono + phase * h, mono)
            self._pump = asyncio.create_task(self.pump())
            log.info("real time: tick 0 at %.3f (in %.3f s), phase %.2f", epoch, epoch - time.time(), phase)

    # ------------------------------------------------------------------ inputs
    def mission_time(self) -> float:
        """Real time: seconds since tick 0 on this host's monotonic clock (the emulated network's
        time base). Lockstep: the emulated network runs on sample times instead."""
        return time.monotonic() - self._epoch_mono if self._epoch_mono is not None else 0.0

    def drain(self) -> None:
        """Decode every pending sample and token event (on the event loop). A sample that crosses
        an emulated link is offered to it (at its sample time in lockstep, at the current mission
        time in real time) and reaches its source when the link delivers it (:meth:`release`)."""
        realtime = isinstance(self.clock, RealtimeClock)
        for rec in self.fifo.drain():
            src = self.sources.get(rec.key)
            if src is None:
                continue
            msg = self.receiver.accept(rec.payload, src.expect, src.sender)
            if msg is None:
                continue
            if src.channel is None:
                src.offer(msg)
                continue
            src.raw_k = max(src.raw_k, msg.k)
            src.channel.send(self.mission_time() if realtime else msg.t, rec.payload)
        if realtime:
            self.release(self.mission_time())
        self._serve_queries()
        for ev in self.tokens.drain():
            self.token_log.append((ev.key, ev.alive))
            for src in self._watched.get(ev.key, ()):
                was_gone, src.gone = src.gone, not ev.alive
                if ev.alive and was_gone:
                    log.warning("%s is back", ev.key)
                elif not ev.alive and src.silent:
                    log.warning("%s went silent (liveliness token gone)", ev.key)

    def release(self, now: float, only: Source | None = None) -> None:
        """Hand the copies that emulated links deliver by ``now`` to their sources. A corrupted
        copy fails its checksum: dropped and counted as ``corrupt``."""
        for src in (only,) if only is not None else self.sources.values():
            if src.channel is None:
                continue
            for copy in src.channel.release(now):
                if copy.corrupted:
                    self.receiver.drops["corrupt"] = self.receiver.drops.get("corrupt", 0) + 1
                    src.corrupt += 1
                    continue
                msg = self.receiver.accept(copy.payload, src.expect, src.sender)
                if msg is not None:
                    src.offer(msg)

    def next_delivery(self) -> float | None:
        """The earliest time [s, mission time] an emulated link will deliver a copy, if any."""
        times = [s.channel.queue.next_at for s in self.sources.values() if s.channel is not None]
        times = [t for t in times if t is not None]
        return min(times) if times else None

    async def until(self, ready: Callable[[], bool], timeout: float | None, what: str) -> None:
        """Wait (draining inputs) until ``ready()``; :class:`Stalled` naming ``what`` after ``timeout``."""
        self.drain()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not ready():
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise Stalled(f"waited {timeout:g} s for {what}")
            await self.wakeup.wait(left)
            self.drain()

    async def sample(self, src: Source, k: int) -> Any:
        """Lockstep: the sample of tick ``k`` (waits). Real time: the newest held (may be None)."""
        return (await self.aligned([src], k))[0]

    async def aligned(self, sources: list[Source], k: int, max_lag: int = 8) -> list[Any]:
        """One sample per source, all of the same tick where possible.

        Lockstep: the samples of tick ``k`` (waits for each). Real time: among the sources whose
        newest sample is at most ``max_lag`` ticks old, the newest tick ``c <= k`` that all of them
        hold, so that a tick never mixes, say, an own measurement of k-1 with neighbours' of k
        (which would show as a spurious formation error of about one period of motion); a source
        older than that (silent, or not started) gives its newest sample, or None."""
        if self.args.clock == "lockstep":
            out = []
            for src in sources:
                if src.channel is None:
                    await self.until(lambda: k in src.by_tick, self.args.stall_timeout, f"tick {k} on {src.key}")
                    out.append(src.by_tick[k])
                    src.forget_before(k)
                    continue
                # through an emulated link: once the sender's tick k has entered the link, what the
                # link has delivered by t_k is known; use the newest of it (possibly older, or none)
                await self.until(lambda: src.raw_k >= k, self.args.stall_timeout, f"tick {k} sent on {src.key}")
                self.release(k * self.mission.dt, only=src)
                held = [t for t in src.by_tick if t <= k]
                out.append(src.by_tick[max(held)] if held else None)
                src.forget_before(max(held) if held else 0)
            return out
        self.drain()
        newest = [max((t for t in s.by_tick if t <= k), default=-1) for s in sources]
        # align the on-board and ideal inputs; an emulated link's delay is what is being studied,
        # so its input is the newest it has delivered
        live = [t for s, t in zip(sources, newest) if t >= k - max_lag and s.channel is None]
        common = min(live) if live else -1
        out = []
        for src, t in zip(sources, newest):
            if src.channel is not None:
                msg = src.by_tick.get(t)
            else:
                msg = src.by_tick.get(common) if t >= k - max_lag else None
            out.append(msg if msg is not None else src.newest)
            src.forget_before(k - max_lag)
        return out

    async def tick(self, k: int) -> float:
        """Wait until tick ``k`` may run (draining inputs meanwhile); returns its lateness [s]."""
        if self.args.clock == "lockstep":
            if self._paced:
                await self.until(lambda: self.lockstep.granted >= k, self.args.stall_timeout,
                                 f"the clock's grant of tick {k}")
            return 0.0
        late = await self.clock.wait_for(k)
        self.drain()
        return late

    def close(self) -> None:
        if self._pump is not None:
            self._pump.cancel()
        for obj in reversed(self._declared):
            try:
                obj.undeclare()
            except zenoh.ZError:
                pass
        self._declared.clear()
        if self._token is not None:
            self._token.undeclare()
            self._token = None


def load_mission(path: Path, duration: float | None = None) -> ms.Mission:
    """Load a mission, with its duration overridden when ``duration`` is given (then re-validated)."""
    m = ms.load(path)
    if duration is None:
        return m
    m = msgspec.structs.replace(m, duration=float(duration))
    problems = ms.validate(m)
    if problems:
        raise ms.MissionError(f"{path} with --duration {duration}", problems)
    return m


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


async def serve(args: NodeArgs, role: Callable[[Node], Awaitable[None]],
                on_stop: Callable[[Node], None] | None = None) -> int:
    """Run one role until it finishes, fails, or is told to stop (SIGTERM/SIGINT, launcher gone).

    Returns the exit status: 0 finished, 1 failed (logged), 2 bad mission, 143 stopped by a
    signal. ``on_stop`` runs after a stop too (the recorder writes its file there). The session is
    always closed.
    """
    try:
        mission = load_mission(args.mission_path, args.duration)
    except ms.MissionError as exc:
        log.error("%s", exc)
        return EXIT_BAD_INPUT
    loop = asyncio.get_running_loop()
    status = EXIT_OK
    async with tp.open_session(args.zenoh) as session:
        node = Node(args, mission, session)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, node.stop.set)
        watcher = asyncio.create_task(_watch_parent(args.parent_pid, node.stop)) if args.parent_pid else None
        work = asyncio.create_task(role(node))
        stopper = asyncio.create_task(node.stop.wait())
        try:
            await asyncio.wait({work, stopper}, return_when=asyncio.FIRST_COMPLETED)
            if not work.done():
                work.cancel()
                status = EXIT_STOPPED
            try:
                await work
            except asyncio.CancelledError:
                pass
            except Stalled as exc:
                log.error("stalled: %s", exc)
                status = EXIT_FAILED
            except Exception:
                log.exception("failed")
                status = EXIT_FAILED
            if on_stop is not None:
                on_stop(node)
        finally:
            stopper.cancel()
            if watcher is not None:
                watcher.cancel()
            node.close()
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)
    return status


def setup_logging(role: str, node_id: int, level: str = "INFO") -> None:
    """Plain one-line records on stderr: ISO time, level, role/id, message."""
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format=f"%(asctime)s %(levelname)s {role}/{node_id}: %(message)s",
    )
