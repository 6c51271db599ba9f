"""``tether run``: one command, one machine: start every process of a mission, run it, stop them all.

:func:`run` puts the launch together: its options resolved and checked (``deploy/options.py``), the
launcher's router and the run's identities, its processes (``deploy/children.py``), their
supervision at the pace ``--clock`` chose (``deploy/supervise.py``) and the exit status
(``deploy/outcome.py``). The user's manual: ``docs/launch.md``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import signal
import subprocess
import time
from pathlib import Path

import zenoh

from deploy import inject, localtls, options, outcome, pki, sitl
from deploy.children import Launch, LaunchFailed
from deploy.options import LaunchOptions, record_batch, resolve, separate_plants_needed
from deploy.relay import Relay
from deploy.supervise import Lockstep, Realtime, Supervision, pace
from tether import mission as ms
from tether import safefs, sched
from tether import transport as tp
from tether.progress import Progress

log = logging.getLogger("tether")


async def run(mission_path: Path, opts: LaunchOptions) -> int:
    """Launch and run a mission; returns the exit status (:mod:`deploy.outcome`). Raises
    :class:`~tether.mission.MissionError` (exit status 2) for bad input, before anything starts."""
    chosen = pace(opts.clock)
    launch, router, settings, held = _prepare(mission_path, opts, chosen)
    try:
        return await _run(launch, router, settings, chosen)
    finally:
        os.close(held)  # the claim on --out (:func:`claim_out`) ends with the run


LIVE = "holds a run that is going on now (another tether run writes there)"


def claim_out(out: Path) -> int:
    """Claim the run directory ``out`` for this run: an exclusive lock on the directory itself,
    held until the returned descriptor is closed (and by the kernel no longer than the process).
    Raises :class:`BlockingIOError` when another run holds it: two runs never write one
    ``--out``."""
    import fcntl

    fd = os.open(out, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise
    return fd


async def _run(launch: Launch, router: str, settings: tp.ZenohSettings, chosen: Lockstep | Realtime) -> int:
    """:func:`run` once ``--out`` is claimed."""
    o = launch.opts
    try:
        router, settings, sec = _secure(launch, router, settings)
    except LaunchFailed as exc:
        log.error("%s", exc)
        return outcome.EXIT_FAILED
    try:
        simulators = sitl.start(launch.mission, o.sitl, o.out / "logs") if o.sitl is not None else None
    except RuntimeError as exc:
        log.error("--sitl: %s", exc)
        return outcome.EXIT_FAILED
    signals = Interrupts(chosen.interrupts_to_stop)
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGINT, signals.sigint)
    loop.add_signal_handler(signal.SIGTERM, signals.sigterm)
    try:
        status, interrupted, sup = await _fly(launch, chosen, router, settings, sec, signals)
    finally:
        loop.remove_signal_handler(signal.SIGINT)
        loop.remove_signal_handler(signal.SIGTERM)
        if simulators is not None:
            codes = simulators.stop()
            log.info("software Crazyflies stopped: %s", ", ".join(f"agent {a} exit {c}" for a, c in codes.items()))
    if interrupted:
        status = outcome.EXIT_TERMINATED if signals.terminated else outcome.EXIT_INTERRUPTED
    return outcome.conclude(launch, sup, status)


def _prepare(mission_path: Path, opts: LaunchOptions,
             chosen: Lockstep | Realtime) -> tuple[Launch, str, tp.ZenohSettings, int]:
    """The launch of ``mission_path``, its options resolved and checked, the launcher's CPU scheduling
    applied, ``--out`` made and claimed (:func:`claim_out`) and every child's log opened; with the
    launcher's router endpoint and settings and the claim's descriptor. Raises
    :class:`~tether.mission.MissionError` (exit status 2) before anything starts."""
    from tether.node import load_mission, os_error

    m = load_mission(mission_path, opts.duration)
    auto = opts.colocate_plants is None
    opts = resolve(m, opts, chosen)
    launch = Launch(mission_path.resolve(), m, opts, chosen)
    problems = options.problems(m, opts, chosen, launch.members())
    if problems:
        raise ms.MissionError(f"tether run {mission_path}", problems)
    if auto and opts.colocate_plants:
        log.info("plants computed inside their agents (lockstep, simulated plants: the same run as with plant "
                 "processes, faster), window %d, records of %d ticks, network %s; --separate-plants for one "
                 "process per plant", opts.window, record_batch(opts), opts.network)
    elif auto:
        log.info("one process per plant: %s", separate_plants_needed(m, opts, chosen))
    if opts.rt_priority is not None:  # the launcher's router first (its threads inherit it), before anything starts
        try:
            log.info("CPU scheduling of the control processes: %s", sched.apply(opts.rt_priority))
        except sched.SchedError as exc:
            raise ms.MissionError(f"tether run {mission_path}", [("--rt-priority", str(exc))]) from None
    elif (applied := chosen.schedule()) is not None:
        opts = dataclasses.replace(opts, rt_priority=applied)
    tp.reserve_ports((*opts.listen, *opts.vehicle_connect.values()))  # free until bound: never ours to pick
    router = tp.loopback_endpoint(tp.free_tcp_port())
    settings = tp.ZenohSettings(mode="router", listen=(router, *opts.listen), lease=opts.lease,
                                ingress_limits=chosen.limits(m, launch.keys.ns))
    tp.zenoh_config(settings)  # a bad --listen endpoint: SettingsError naming it, before anything starts
    try:  # every file under --out is made through its real path, following no link (tether/safefs.py)
        launch.opts = dataclasses.replace(opts, out=safefs.make_out(opts.out))
    except OSError as exc:
        raise ms.MissionError(f"tether run {mission_path}", [("--out", f"cannot make it: {os_error(exc)}")]) from None
    try:
        held = claim_out(launch.opts.out)
    except BlockingIOError:
        raise ms.MissionError(f"tether run {mission_path}", [("--out", f"{opts.out} {LIVE}; give another --out, "
                                                              "or wait for that run to end")]) from None
    try:
        launch.open_logs()  # a full or read-only --out: exit 2 naming the file, before anything starts
    except BaseException:
        os.close(held)
        raise
    return launch, router, settings, held


def _secure(launch: Launch, router: str,
            settings: tp.ZenohSettings) -> tuple[str, tp.ZenohSettings, localtls.Security | None]:
    """Make the run's certificates and access rules (none with ``--insecure``, said with a warning);
    the router's endpoint and settings under them, and the identities. :class:`LaunchFailed` if the
    certificates cannot be made; :class:`~tether.mission.MissionError` if ``--out`` cannot hold them."""
    o, m = launch.opts, launch.mission
    if o.insecure:
        log.warning("--insecure: no certificates and no access rules; anyone who reaches the router (%s) can "
                    "publish on any key of the run (move the formation, end it, rewrite the recording)",
                    ", ".join(settings.listen))
        return router, settings, None
    router = "tls/" + router.split("/", 1)[1]
    try:
        sec = localtls.prepare(m, launch.keys.ns, o.out, launch.members(), router, o.listen, o.lease,
                               settings.ingress_limits)
    except pki.PkiError as exc:
        raise LaunchFailed(f"cannot make this run's certificates: {exc} (or pass --insecure)") from None
    except OSError as exc:  # nothing started yet: the logs made for it go too
        from tether.node import os_error

        launch.close_logs(remove=True)
        raise ms.MissionError(f"tether run {launch.mission_path}",
                              [("--out", f"cannot make this run's tls/: {os_error(exc)}")]) from None
    log.info("mTLS: %d identities made in %.2f s in %s; operator identity for tools (--zenoh-config): %s",
             sec.identities, sec.seconds, sec.dir, sec.configs["control-0"])
    return router, tp.ZenohSettings(config_file=str(sec.configs["router"])), sec


class Interrupts:
    """Ctrl-C and SIGTERM as the launcher hears them: every Ctrl-C sets :attr:`first`; the pace's
    number of them (:attr:`~deploy.supervise.Lockstep.interrupts_to_stop`), or a SIGTERM, sets
    :attr:`stop`: every process is stopped at once. Handlers of the event loop (they only hand off)."""

    def __init__(self, to_stop: int) -> None:
        self.to_stop = to_stop
        self.count = 0
        self.first = asyncio.Event()
        self.stop = asyncio.Event()
        self.terminated = False
        """SIGTERM was heard (exit status 143 rather than 130)."""

    def sigint(self) -> None:
        self.count += 1
        self.first.set()
        if self.count >= self.to_stop:
            if self.count > 1:
                log.warning("interrupted again: stopping every process at once")
            self.stop.set()

    def sigterm(self) -> None:
        self.terminated = True
        self.stop.set()


async def _fly(launch: Launch, chosen: Lockstep | Realtime, router: str, settings: tp.ZenohSettings,
               sec: localtls.Security | None, signals: Interrupts) -> tuple[int, bool, Supervision | None]:
    """Open the launcher's router, start every process, supervise the run at its pace until it ends
    or :attr:`Interrupts.stop`, then stop every process. Returns the exit status so far, whether it
    was interrupted, and what the supervision saw (None: nothing started)."""
    o = launch.opts
    progress = Progress() if o.progress else None
    status, interrupted = outcome.EXIT_OK, False
    sup: Supervision | None = None
    gateway: subprocess.Popen[bytes] | None = None
    gateway_log = o.out / "logs" / "gateway.log"
    t0 = time.monotonic()
    try:
        async with tp.open_session(settings) as session:
            listening = (router, *o.listen) if sec is None else (router,)
            log.info("router listening on %s (namespace %s%s)", ", ".join(listening), launch.keys.ns,
                     "" if sec is None else ", TLS with client certificates and access rules")
            if sec is not None:  # tools attach through a router of their own, one RR step below the control loops
                gw = sched.gateway_priority(o.rt_priority or 0)
                gateway = localtls.start_gateway(sec, gateway_log, dict(os.environ), gw)
                log.info("operator gateway (%s) listening on %s", f"SCHED_RR {gw}" if gw else "normal policy",
                         ", ".join(sec.gateway_endpoints))
            if o.live is not None:
                log.info("live view (from the recorder): ws://127.0.0.1:%d (Foxglove: Open connection, "
                         "Foxglove WebSocket; docs/foxglove.md)", o.live)
            for f in o.faults:
                if f.kind == "partition" and f.member(launch.mission) not in launch.relays:
                    port = int(router.rsplit(":", 1)[1])
                    launch.relays[f.member(launch.mission)] = await Relay.start(("127.0.0.1", port))
            launch.spawn(router, sec)
            sup = watch = _supervision(launch, chosen, session)

            async def body() -> bool:
                await _all_up(launch, session, gateway, gateway_log, t0)
                return await chosen.drive(launch, session, progress, watch, signals.first)

            work = asyncio.create_task(body())
            stopper = asyncio.create_task(signals.stop.wait())
            try:
                done, _ = await asyncio.wait({work, stopper}, return_when=asyncio.FIRST_COMPLETED)
                if stopper in done:
                    log.warning("%s: stopping every process",
                                "terminated (SIGTERM)" if signals.terminated else "interrupted")
                    interrupted = True
                else:
                    interrupted = work.result()
            except LaunchFailed as exc:
                log.error("%s", exc)
                status = outcome.EXIT_FAILED
                log.info("stopping the others in %.1f s", o.failure_grace)
                await asyncio.sleep(o.failure_grace)
            except tp.TokensMissing as exc:
                log.error("%s", exc)
                status = outcome.EXIT_FAILED
            finally:
                for task in (work, stopper):
                    task.cancel()
                await _stop(launch, watch)
    finally:
        if gateway is not None:
            localtls.stop_gateway(gateway)
    return status, interrupted, sup


def _supervision(launch: Launch, chosen: Lockstep | Realtime, session: zenoh.Session) -> Supervision:
    """What watches the started processes (:class:`~deploy.inject.Monitor`) and fires the faults
    (:class:`~deploy.inject.Injector`)."""
    m, o = launch.mission, launch.opts
    sup: Supervision | None = None
    monitor = inject.Monitor(session, m, launch.keys, launch.members(), lambda: sup.mission_time(m) if sup else None,
                             forge_agents=any(f.kind == "forge" and f.role == "agent" for f in o.faults),
                             leader=chosen.hears_leader or any(f.kind == "forge" and f.role == "leader"
                                                               for f in o.faults),
                             lease=o.lease)
    pids = {(c.role, c.node_id): c.proc.pid for c in launch.children}
    monitor.proc_alive = lambda name: any(c.name == name and c.proc.poll() is None for c in launch.children)
    sup = Supervision(monitor, inject.Injector(o.faults, m, launch.keys, session, pids, launch.relays, monitor))
    return sup


async def _all_up(launch: Launch, session: zenoh.Session, gateway: subprocess.Popen[bytes] | None,
                  gateway_log: Path, t0: float) -> None:
    """Wait for every member's liveliness token and the operator gateway (``tp.TokensMissing``,
    :class:`LaunchFailed` when they do not come within ``--startup-timeout``)."""
    o = launch.opts
    tokens = [launch.keys.token(r, i) for r, i in launch.members()]
    await tp.wait_for_tokens(session, tokens, o.startup_timeout)
    if gateway is not None:
        try:
            await localtls.wait_gateway(gateway, gateway_log, o.startup_timeout)
        except RuntimeError as exc:
            raise LaunchFailed(str(exc)) from None
    log.info("all %d processes are up after %.1f s", len(tokens), time.monotonic() - t0)


async def _stop(launch: Launch, sup: Supervision) -> None:
    """Stop watching, stop every process (the recorder last, given the time to write what it holds)
    and close the relays."""
    m = launch.mission
    sup.injector.close()
    sup.monitor.close()
    t_stop = sup.mission_time(m)
    ticks = m.steps if t_stop is None else min(m.steps, int(t_stop * m.rate) + 1)
    launch.terminate(recorder_grace=options.write_grace(m, ticks))
    for relay in launch.relays.values():
        await relay.close()
