"""What each site wrote down itself: the safety events in its processes' logs, merged into a run
file that missed them, and the events a rehearsal's exit status follows. Pure (text and arrays in,
events and a run out; the caller reads and writes the files).

A recorder hears a vehicle's mode changes only in its telemetry (agents) and state samples
(plants). While a site is cut off from the recorder (a partition of two sites' routers, a router
restart) those samples are lost, and with them the events they carried: the field side's HOLD and
LAND after a partition. Every agent and plant also logs each event as it happens, on its own
host, with its mission time (``agent/node.py``: ``safety: t = 3.50 s: FLYING -> HOLD: why``;
``plant/node.py``: ``vehicle 2: FLYING -> HOLD at 3.50 s: why``). :func:`merge` adds the logged
events the run file lacks, so the run file holds every process's events.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Iterable

import msgspec
import numpy as np

from deploy import inject
from tether.runfile import Run
from tether.wire import FLYING, HOLD, MODES, SafetyEvent

_MODE = "|".join(MODES)
_AGENT = re.compile(rf"safety: t = (-?[0-9.]+) s: ({_MODE}) -> ({_MODE}): (.*)$")
_PLANT = re.compile(rf"vehicle (\d+): ({_MODE})(?: -> ({_MODE}))? at (-?[0-9.]+) s: (.*)$")
SAME_WITHIN = 0.006
"""A logged event and a recorded one of the same vehicle and modes are one event when their times
differ by at most this [s] (the logs print t to 0.01 s)."""


def agent_events(text: str, vehicle: int, h: float) -> list[SafetyEvent]:
    """The supervisor's mode changes agent ``vehicle`` logged (its unit's log ``text``); ``h`` is the
    control period [s] (an event's tick is its time over ``h``, rounded)."""
    out = []
    for line in text.splitlines():
        mt = _AGENT.search(line)
        if mt is not None:
            t = float(mt.group(1))
            out.append(SafetyEvent(k=round(t / h), t=t, vehicle=vehicle, src=MODES.index(mt.group(2)),
                                   dst=MODES.index(mt.group(3)), reason=mt.group(4)))
    return out


def plant_events(text: str, h: float) -> list[SafetyEvent]:
    """The watchdog events a plant process logged (its unit's log ``text``), reasons prefixed
    ``plant:`` as the run file keeps them (:meth:`plant.watchdog.Event.wire`)."""
    out = []
    for line in text.splitlines():
        mt = _PLANT.search(line)
        if mt is not None:
            src = MODES.index(mt.group(2))
            dst = src if mt.group(3) is None else MODES.index(mt.group(3))
            t = float(mt.group(4))
            out.append(SafetyEvent(k=round(t / h), t=t, vehicle=int(mt.group(1)), src=src, dst=dst,
                                   reason=f"plant: {mt.group(5)}"))
    return out


def _missing(have: list[SafetyEvent], logged: Iterable[SafetyEvent]) -> list[SafetyEvent]:
    """The events of ``logged`` with no event of the same vehicle, modes and time in ``have``."""
    keys: dict[tuple[int, int, int], list[float]] = {}
    for e in have:
        keys.setdefault((e.vehicle, e.src, e.dst), []).append(e.t)
    out = []
    for e in logged:
        times = keys.setdefault((e.vehicle, e.src, e.dst), [])
        if not any(abs(e.t - t) <= SAME_WITHIN for t in times):
            out.append(e)
            times.append(e.t)
    return out


def merge(run: Run, agents: Iterable[SafetyEvent], plants: Iterable[SafetyEvent]) -> tuple[Run, int]:
    """``run`` with the logged events it lacks added (in order of tick and vehicle), and how many
    were added. Events of vehicles the run does not hold are ignored."""
    ids = {int(a) for a in run.agent_ids}
    add_a = _missing(run.safety.events, (e for e in agents if e.vehicle in ids))
    add_p = _missing(run.safety.plant_events, (e for e in plants if e.vehicle in ids))
    if not add_a and not add_p:
        return run, 0
    order = lambda e: (e.k, e.vehicle, e.t)  # noqa: E731
    safety = msgspec.structs.replace(run.safety, events=sorted([*run.safety.events, *add_a], key=order),
                                     plant_events=sorted([*run.safety.plant_events, *add_p], key=order))
    return dataclasses.replace(run, safety=safety), len(add_a) + len(add_p)


def run_events(run: Run, max_formation_error: float) -> list[inject.Event]:
    """What the launcher's monitor (:class:`deploy.inject.Monitor`) would have reported of a run it
    heard all of: ``failsafe`` for every vehicle's first mode change away from FLYING (supervisor or
    watchdog), ``diverged`` for a formation error beyond the bound while FLYING or HOLD."""
    out: list[inject.Event] = []
    seen: set[str] = set()
    for role, events in (("agent", run.safety.events), ("plant", run.safety.plant_events)):
        for e in events:
            who = f"{role}/{e.vehicle}"
            if e.dst != FLYING and e.src != e.dst and who not in seen:
                seen.add(who)
                out.append(inject.Event(e.t, who, "failsafe", f"mode {MODES[e.src]} -> {MODES[e.dst]} ({e.reason})"))
    norm = np.linalg.norm(run.xi, axis=-1)
    judged = np.isin(run.safety.safety_mode, (FLYING, HOLD))
    for i, aid in enumerate(run.agent_ids):
        over = np.flatnonzero(judged[:, i] & (norm[:, i] > max_formation_error))
        if over.size:
            k = int(over[0])
            out.append(inject.Event(float(run.t[k]), f"agent/{int(aid)}", "diverged",
                                    f"|xi| = {norm[k, i]:.3g} m (limit {max_formation_error:g})"))
    return out
