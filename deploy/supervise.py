"""Supervision of a running launch: the clock it keeps, what it sees fail, and how it ends.

How a run keeps time is a pace chosen once from ``--clock`` (:func:`pace`): :class:`Lockstep` grants
the ticks as the recorder acknowledges them and stops the run when a process is lost;
:class:`Realtime` announces the start instant, lets the survivors of a failure fly on, and lands
every vehicle on the first Ctrl-C. The user's manual: ``docs/launch.md``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from deploy import inject, localtls
from deploy.children import Launch, LaunchFailed
from deploy.inject import describe_exit
from deploy.options import LaunchOptions, check_lockstep, window, write_grace
from tether import handoff, sched
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.clock import ClockKind, LockstepSource
from tether.progress import Progress

log = logging.getLogger("tether")


def land_bound(m: ms.Mission) -> float:
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
    when ``extends`` (3D, no :attr:`~deploy.options.LaunchOptions.land_timeout`), as long after it as
    some vehicle not yet landed has come :data:`LAND_PROGRESS` lower within the last
    :data:`LAND_STALL` seconds, :data:`LAND_CAP` times ``bound`` at most. A vehicle held up (hovering
    against a push, or a supervisor that does not land it) stops extending it."""

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


def _check_children(launch: Launch, sup: Supervision, fatal: bool) -> None:
    """Report every child that ended badly (once); ``fatal`` (lockstep: the clock cannot go on
    without it): stop the run, raising :class:`LaunchFailed`."""
    for c in launch.poll():
        if c.status is None or c.status == 0:
            continue  # ending well early is normal: in lockstep the leader finishes up to `window` ticks first
        why = describe_exit(c.status)
        fault = next((x.fault.text for x in sup.injector.firings
                      if x.fired is not None and x.fault.member(launch.mission) == (c.role, c.node_id)), None)
        if fault is not None:
            why += f" (--fault {fault})"
        sup.monitor.report(c.name, "died", why)
        if fatal:
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
            _check_children(launch, sup, fatal=True)
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
                last_progress = _stall_clock(sup, last_progress)
                if time.monotonic() - last_progress > o.stall_timeout:
                    raise LaunchFailed(f"lockstep stalled at tick {src.done + 1}: no acknowledgement from "
                                       + ", ".join(f"{r}/{i}" for r, i in src.missing()))
                continue
            if _take_acks(acks.drain(), receiver, src, granted, sup):
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


def _stall_clock(sup: Supervision, last_progress: float) -> float:
    """The instant a lockstep stall is timed from, given the last progress: a freeze or partition
    under way holds it at now, and the launcher's own lateness is no stall of the others."""
    if any(x.fired is not None and x.ended is None and x.fault.duration is not None for x in sup.injector.firings):
        return time.monotonic()
    if sup.monitor.resumed is not None and sup.monitor.resumed > last_progress:
        return sup.monitor.resumed
    return last_progress


def _take_acks(received: list[tp.Received], receiver: wire.Receiver, src: LockstepSource, granted: int,
               sup: Supervision) -> bool:
    """Hand the acknowledgements ``received`` to the clock source, dropping (and counting) any that is
    malformed or ahead of the ``granted`` tick; whether the clock moved."""
    moved = False
    for rec in received:
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
    return moved


async def _realtime(launch: Launch, session: zenoh.Session, progress: Progress | None, sup: Supervision,
                    interrupted: asyncio.Event) -> bool:
    """Run a real-time mission to its end, or until the survivors of a failure have settled (or
    were given their bound), or until interrupted. Returns True when interrupted."""
    m, o, keys = launch.mission, launch.opts, launch.keys
    pub = tp.declare_publisher(session, keys.start, tp.SYNC)
    epoch = time.time() + ms.start_lead(m, o.start_lead)  # a Crazyflie takes off in it
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
        _check_children(launch, sup, fatal=False)
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
ends the run [s], so that their final samples reach the recorder too (stopping at the first report
can leave a plant's LANDED out of the run file under load). The recorder is also stopped last
(:meth:`Launch.terminate`) and decodes what waits in its queues before it writes; this margin is for
what the router still forwards."""


async def _land_then_stop(launch: Launch, session: zenoh.Session, sup: Supervision) -> None:
    """First Ctrl-C in real time: order every vehicle to land, wait (bounded) for LANDED, return.
    (A second Ctrl-C stops everything at once: :func:`deploy.local.run` cancels this.)"""
    from deploy import operator

    m = launch.mission
    mon = sup.monitor
    given = launch.opts.land_timeout
    bound = given if given is not None else land_bound(m)
    # 3D, no land_timeout given: a descent still under way keeps the launcher waiting (LAND_PROGRESS), so
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


async def _finish(launch: Launch, sup: Supervision, since: float, announce: Callable[[], None] | None) -> None:
    """After the last tick: let the children exit on their own (the recorder once it has written the
    run files), repeating ``announce`` for a process that lost it with its link; report those that
    do not. ``since``: when the run started [s, monotonic]."""
    m = launch.mission
    log.info("ran %g s of mission time in %.2f s of wall time", m.duration, time.monotonic() - since)
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


class Lockstep:
    """Lockstep: the launcher is the tick clock's source (:func:`_lockstep`); a process lost stalls the
    clock, so the run stops, and so does the first Ctrl-C."""

    kind: ClockKind = "lockstep"
    apart: str | None = None
    interrupts_to_stop = 1
    """Ctrl-Cs after which every process is stopped at once."""
    hears_leader = False
    """The monitor needs the leader's samples only to forge one (a delivery a tick less)."""

    def problems(self, m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
        return check_lockstep(m, o)

    def child_args(self, o: LaunchOptions) -> list[str]:
        # the window is what each stream keeps to send again after a stall (tether/node.py RESEND)
        return ["--clock", self.kind, "--window", str(window(o))]

    def limits(self, m: ms.Mission, ns: str) -> tuple[tuple[str, float], ...]:
        """The launcher's router's ingress limits: none, since lockstep ticks go out in bursts."""
        return ()

    def schedule(self) -> int | None:
        """CPU scheduling when no ``--rt-priority`` is given: the launcher's policy, kept."""
        return None

    async def drive(self, launch: Launch, session: zenoh.Session, progress: Progress | None, sup: Supervision,
                    interrupted: asyncio.Event) -> bool:
        """Run the mission to its last tick and let the children exit; returns False (the first
        Ctrl-C stops the run from outside: :attr:`interrupts_to_stop`)."""
        since = time.monotonic()
        announce = await _lockstep(launch, session, progress, sup)
        await _finish(launch, sup, since, announce)
        return False


class Realtime:
    """Real time: every process ticks on its own clock from the start instant announced here
    (:func:`_realtime`); the survivors of a failure fly on, and the first Ctrl-C lands them."""

    kind: ClockKind = "realtime"
    apart: str | None = "real time: each plant is a process of its own"
    interrupts_to_stop = 2
    """Ctrl-Cs after which every process is stopped at once (the first orders a landing)."""
    hears_leader = True
    """The monitor checks that the leader was heard at the start."""

    def problems(self, m: ms.Mission, o: LaunchOptions) -> list[tuple[str, str]]:
        return []

    def child_args(self, o: LaunchOptions) -> list[str]:
        return ["--clock", self.kind]

    def limits(self, m: ms.Mission, ns: str) -> tuple[tuple[str, float], ...]:
        """The launcher's router's ingress limits: a flood on any key, from any one link, reaches no
        subscriber faster than a bound (:func:`deploy.localtls.ingress_limits`)."""
        return localtls.ingress_limits(m, ns)

    def schedule(self) -> int | None:
        """CPU scheduling when no ``--rt-priority`` is given: ``SCHED_RR`` where permitted, one line
        saying why where not; the priority applied, or None."""
        applied, line = sched.apply_best()
        (log.info if applied else log.warning)("CPU scheduling of the control processes: %s", line)
        return applied or None

    async def drive(self, launch: Launch, session: zenoh.Session, progress: Progress | None, sup: Supervision,
                    interrupted: asyncio.Event) -> bool:
        """Run the mission to its end (or until the survivors of a failure have settled) and let the
        children exit; on ``interrupted``, order every vehicle to land first. Whether interrupted."""
        since = time.monotonic()
        if await _realtime(launch, session, progress, sup, interrupted):
            await _land_then_stop(launch, session, sup)
            return True
        if not sup.stopped_by_us:
            await _finish(launch, sup, since, None)
        return False


def pace(kind: ClockKind) -> Lockstep | Realtime:
    """The launcher's pace for ``--clock kind``: the one place it reads the clock's name."""
    return Lockstep() if kind == "lockstep" else Realtime()
