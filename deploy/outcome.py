"""How a launch ended: its exit status, the events it saw, and what its run file holds.

Exit statuses of ``tether run`` (``docs/launch.md``): :data:`EXIT_OK` clean, :data:`EXIT_FAILED`
the run failed, :data:`EXIT_BAD_INPUT` bad input, :data:`EXIT_FAILSAFE` a failsafe fired or a value
diverged, :data:`EXIT_LOST` a process died or froze (real time), :data:`EXIT_INCOMPLETE` recorded
with samples missing, :data:`EXIT_INTERRUPTED` Ctrl-C, :data:`EXIT_TERMINATED` SIGTERM.
"""

from __future__ import annotations

import logging
import shutil
import signal
from pathlib import Path

import msgspec
import numpy as np

from deploy import inject
from deploy.children import LOG_RESERVE, Launch
from deploy.supervise import Supervision
from tether import jsonout, safefs

log = logging.getLogger("tether")

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_FAILSAFE, EXIT_LOST, EXIT_INTERRUPTED = 0, 1, 2, 3, 4, 130
EXIT_INCOMPLETE, EXIT_TERMINATED = 5, 143

MEANING = {EXIT_OK: "clean", EXIT_FAILED: "the run failed", EXIT_BAD_INPUT: "bad input",
           EXIT_FAILSAFE: "a failsafe fired or a value diverged", EXIT_LOST: "a process died or froze",
           EXIT_INTERRUPTED: "interrupted", EXIT_INCOMPLETE: "recorded, but samples are missing",
           EXIT_TERMINATED: "terminated (SIGTERM)"}


def from_events(events: list[inject.Event]) -> int:
    """The exit status the events reported call for: a process lost outweighs a failsafe."""
    if any(e.what in inject.LOST for e in events):
        return EXIT_LOST
    if any(e.what in inject.FAILSAFE for e in events):
        return EXIT_FAILSAFE
    return EXIT_OK


def before_first_tick(sup: Supervision | None) -> bool:
    """Whether the run ended before its first tick was recorded (lockstep) or its clock started
    (real time): still starting up."""
    return sup is None or (sup.done_tick < 0 and sup.epoch is None)


STALL_FAULTS = frozenset({"kill", "freeze", "partition"})
"""Injected faults that make a process's loss the run's subject, never a stall of its host."""


def host_stall(clock: str, events: list[inject.Event], faults: list[str]) -> bool:
    """Whether the processes lost in a run were only a stall of its host: a lockstep run (which waits
    for every input, so a stall delays it and changes nothing in it), every loss a freeze (a token gone
    for a while, or the launcher not running: never a death or a silence) and no kill, freeze or
    partition injected. Such a run whose record is complete (:func:`complete`) is clean."""
    lost = [e for e in events if e.what in inject.LOST]
    return (clock == "lockstep" and bool(lost) and all(e.what == "froze" for e in lost)
            and not STALL_FAULTS.intersection(faults))


def complete(path: Path) -> bool:
    """Whether the run file at ``path`` reads and holds every tick (its ``complete`` flag)."""
    from tether import runfile

    try:
        with np.load(path, allow_pickle=False) as run:
            return runfile.decode_meta(str(run["meta"])).complete is not False
    except (OSError, KeyError, ValueError, msgspec.MsgspecError):
        return False


def rebuild(out: Path) -> bool:
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


def with_events(out: Path) -> None:
    """Rewrite ``run.mcap`` with the launcher's events (``events.json``, known only once every process
    has stopped, after the recorder wrote the file; ``recorder/export.py`` puts them on
    ``/events/launcher``). A run file that cannot be read leaves the recorder's ``run.mcap`` as it is."""
    from recorder.export import mcap_beside
    from tether.runfile import Run

    try:
        mcap_beside(Run.load(out), None, out / "run.npz")
    except (OSError, ValueError) as why:
        log.error("run.mcap is kept without the launcher's events: %s", why)


LATE_WARN = 0.01
"""Above this share of an agent's ticks started more than a period late, the launcher says so at the
end (the mark of a rate that holds; lockstep ticks are never late)."""


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


def recorded(path: Path, status: int, rt_priority: int | None) -> int:
    """Tell what the run file holds; a clean run whose file lacks samples is :data:`EXIT_INCOMPLETE`,
    one without a run file :data:`EXIT_FAILED`. Also how many of the agents' ticks were late
    (:func:`late_report`; ``rt_priority``: the control processes' ``--rt-priority``)."""
    from tether import runfile

    try:
        with np.load(path, allow_pickle=False) as run:
            meta = runfile.decode_meta(str(run["meta"]))
            if "late" in run.files:
                said = late_report(run["late"], len(run["t"]), rt_priority)
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


def conclude(launch: Launch, sup: Supervision | None, status: int) -> int:
    """Once every process has stopped: log how each ended and every event, write ``faults.json`` and
    ``events.json``, rebuild a run file the recorder did not write, and decide the exit status from
    ``status`` so far (what the events call for where it is :data:`EXIT_OK`, :data:`EXIT_FAILED`
    for a process that ended badly unreported)."""
    o = launch.opts
    for c in launch.children:
        log.info("%-12s exit %s", c.name, c.status)
    events = sup.monitor.events if sup is not None else []
    if sup is not None:
        if o.faults:
            safefs.write_file(o.out / "faults.json", (jsonout.dumps(sup.injector.records()) + "\n").encode())
        safefs.write_file(o.out / "events.json", (jsonout.dumps([e.to_json() for e in events]) + "\n").encode())
        if events and o.mcap and (o.out / "run.mcap").exists():
            with_events(o.out)
    if status == EXIT_OK:
        status = from_events(events)
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
    if status in (EXIT_INTERRUPTED, EXIT_TERMINATED) and before_first_tick(sup) and not rebuild(o.out) \
            and not (o.out / "run.npz").exists():
        log.warning("%s before the first tick: nothing was recorded (exit status %d)",
                    "terminated" if status == EXIT_TERMINATED else "interrupted", status)
        write_outcome(o.out, status)
        return status
    stalled = status == EXIT_LOST and host_stall(o.clock, events, [f.kind for f in o.faults])
    if rebuild(o.out) or status in (EXIT_OK, EXIT_FAILSAFE, EXIT_LOST, EXIT_INTERRUPTED, EXIT_TERMINATED):
        if stalled and complete(o.out / "run.npz"):
            log.warning("the host stalled (%s), but a lockstep run waits for every input: every tick was "
                        "recorded, and the data are those of a run without the stall; clean, with this warning",
                        "; ".join(e.line() for e in events if e.what in inject.LOST))
            status = from_events([e for e in events if e.what not in inject.LOST])
        status = recorded(o.out / "run.npz", status, o.rt_priority)
    write_outcome(o.out, status)
    return status


OUTCOME = "outcome.json"
"""The exit status of the run in its ``--out`` and what it means (``tether report`` shows it)."""


def write_outcome(out: Path, status: int) -> None:
    """Leave ``status`` and its meaning in ``out``/:data:`OUTCOME` (a full disk is logged, not raised:
    the status stands)."""
    doc = {"exit_status": status, "meaning": MEANING.get(status, "unknown")}
    try:
        safefs.write_file(out / OUTCOME, (jsonout.dumps(doc) + "\n").encode())
    except OSError as exc:
        log.error("could not write %s (%s)", out / OUTCOME, exc)
