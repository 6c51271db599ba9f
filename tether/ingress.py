"""A process's inputs: what Zenoh's callbacks hand off, decoded and checked on the event loop.

Zenoh callbacks only hand raw samples to bounded queues (:class:`~tether.handoff.BoundedFifo`,
drop-oldest, counted; real time: one :class:`~tether.handoff.InputQueue` per input key, with a
decode budget); :meth:`Ingress.drain` decodes and checks them on the event loop
(:class:`~tether.wire.Receiver`) and offers each to its :class:`~tether.inputs.Source` the way the
process's clock says (:meth:`tether.clock.Clock.offer`). Liveliness events and queries are drained
with them.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from typing import Any

import zenoh

from tether import evloop, handoff
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.clock import Clock
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
    are dropped (oldest first), counted per key in :attr:`Ingress.overflow` and logged once; in the
    recorder also as ``overflow`` in its drop counts (the run file's ``recorder_drops``), where each
    of them is a sample the run file lacks."""
    return max(INPUT_BUDGET, math.ceil(BACKLOG * rate))


TAP_DRAIN = 1.0
"""How long :meth:`Ingress.close` waits for a running tap [s]: a tap is one relay put (microseconds),
so a second only passes on a machine that gives the process no CPU."""


class _Tapped:
    """A sink that queues each sample, then hands it to ``tap`` on the same (Zenoh's) thread."""

    def __init__(self, queue: handoff.InputQueue[tp.Received], tap: Callable[[tp.Received], None],
                 ingress: Ingress):
        self.queue, self.tap, self.ingress = queue, tap, ingress

    def put(self, item: tp.Received, /) -> None:
        self.queue.put(item)
        if not self.ingress.taps.enter():
            return  # the node is closing: its publishers are going (a relay would put on an undeclared one)
        try:
            self.tap(item)
        except Exception:  # noqa: BLE001 - no input may crash Zenoh's thread; said and counted
            drops = self.ingress.receiver.drops  # this key is written by taps only
            n = drops["tap_error"] = drops.get("tap_error", 0) + 1
            if n in (1, 10, 100, 1000):
                log.exception("input %s: its tap failed (%d so far)", item.key, n)
        finally:
            self.ingress.taps.leave()


class Ingress:
    """A process's input side: its hand-off queues, its sources, their budgets, liveliness and
    queries. Everything but the callbacks' puts runs on the event loop.

    ``backlog``: the role takes a :data:`BACKLOG` of each input (:data:`BACKLOG_ROLES`)."""

    def __init__(self, session: zenoh.Session, keys: wire.Keys, mission: ms.Mission, clock: Clock,
                 backlog: bool) -> None:
        self.session = session
        self.keys = keys
        self.clock = clock
        self.steps = mission.steps
        self.dt = mission.dt
        self.backlog = backlog
        self.receiver = wire.Receiver(mission.dim)
        self.wakeup = handoff.Wakeup()
        self.fifo: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(FIFO_CAPACITY, self.wakeup)
        self.deferred: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(FIFO_CAPACITY)
        """Real time: samples of :meth:`subscribe` ``(wake=False)`` subscriptions, which wake nobody;
        drained with the rest, at the latest one control period after they arrive
        (:meth:`tether.node.Node.pace`)."""
        self.tokens: handoff.BoundedFifo[tp.TokenEvent] = handoff.BoundedFifo(4096, self.wakeup)
        self.queries: handoff.BoundedFifo[tuple[Callable[[zenoh.Query], None], zenoh.Query]] = \
            handoff.BoundedFifo(64, self.wakeup)
        self.sources: dict[str, Source] = {}
        self.inputs: dict[str, handoff.InputQueue[tp.Received]] = {}
        """Real time: one bounded queue per subscribed input key (see :data:`INPUT_BUDGET`)."""
        self._budget: dict[str, float] = {}
        """Real time: decodes each input key has left (:data:`INPUT_BUDGET`)."""
        self._capacity = input_capacity(mission.rate) if backlog else INPUT_BUDGET
        self._overflow: dict[str, int] = {}
        self._excess: dict[str, int] = {}
        """Real time: samples each input key's queue dropped as a tick's excess, by key (counted as
        ``excess`` in the receiver's drops)."""
        self.overflow = self._overflow
        """Real time: samples each input key's queue dropped (oldest first), by key."""
        self._period = -1
        self._rearm: asyncio.Handle | None = None
        self._watched: dict[str, list[Source]] = {}
        self.deferring = False
        """Some subscription's samples wake nobody (:meth:`subscribe` ``wake=False``, real time)."""
        self._fifo_lost = {"inputs": 0, "deferred inputs": 0}
        """Samples each FIFO had dropped at the last drain (the rest are new, counted as ``overflow``)."""
        self.taps = handoff.TapGuard()
        """Taps (relays published from Zenoh's thread) run inside it; :meth:`close` waits for them."""
        self._gone: dict[str, frozenset[int]] = {}
        """:meth:`gone`'s answers since the last token event."""
        self._linked: list[Source] = []
        """The sources behind an emulated link (:meth:`release` looks at these only, every drain)."""
        self.declared: list[Any] = []
        """The subscriptions and queryables declared, undeclared by :meth:`close`."""
        self.copies = 0
        """Lockstep: copies received of samples already had, sent again by a peer after a stall
        (:meth:`tether.node.Node.resend`). Dropped, counted here and logged at the end; kept out of
        the link statistics and the drop counts, which a run records and which must not depend on
        the machine's load."""
        self.token_log: list[tuple[str, bool]] = []
        self.alive: dict[str, bool] = {}
        """Liveliness seen so far, by token key: True while present, False once gone."""
        self._arrival = math.nan
        """The callback's stamp of the sample being accepted (:meth:`arrival`); NaN otherwise."""

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
        self.deferring |= sink is self.deferred
        self.declared.append(tp.declare_subscriber(self.session, pattern, sink, stamp))

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
        src = Source(key, expect, sender, last=self.steps, on_message=on_message, keep=keep,
                     channel=channel)
        self.sources[key] = src
        if channel is not None:
            self._linked.append(src)
        if subscribe:
            quiet = not wake and on_message is None and channel is None
            sink, stamp = self.clock.input_sink(self, key, expect, quiet, tap)
            self.declared.append(tp.declare_subscriber(self.session, key, sink, stamp))
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
        self.declared.append(self.session.declare_queryable(key, lambda q: self.queries.put((handle, q))))

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

    def watch_tokens(self) -> None:
        """Hear liveliness tokens, once something is :meth:`watch` ed (before the token is declared)."""
        if self._watched:
            self.declared.append(tp.watch_tokens(self.session, self.keys.tokens, self.tokens))

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
        stamp, for an input that does not wake the loop), else now (the clock's :meth:`~tether.clock.Clock.now`)."""
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
        h = self.dt
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
                            "(counted in Ingress.overflow%s)", key, cap,
                            " and as 'overflow'" if self.backlog else "")
            if q.dropped:
                lost = q.dropped - self._overflow.get(key, 0)
                if lost and self.backlog:  # a sample to record lost: the run file says why
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

    def close(self) -> None:
        """Undeclare every subscription, once no tap runs (blocks up to :data:`TAP_DRAIN` [s] for
        one running on Zenoh's thread: see :class:`~tether.handoff.TapGuard`): a tap publishes, so
        this goes before the publishers."""
        if not self.taps.close(TAP_DRAIN):
            log.warning("a tap still runs %.1f s after the close began: undeclaring anyway", TAP_DRAIN)
        if self._rearm is not None:
            self._rearm.cancel()
        undeclare(self.declared)


def undeclare(declared: list[Any]) -> None:
    """Undeclare Zenoh declarations, newest first (one already gone is skipped)."""
    for obj in reversed(declared):
        try:
            obj.undeclare()
        except zenoh.ZError:
            pass
        except RuntimeError as exc:  # still borrowed by a tap past TAP_DRAIN: the session's close frees it
            log.warning("undeclaring %s: %s", type(obj).__name__, exc)
    declared.clear()
