"""``run.mcap`` beside a ``run.npz``, when the Foxglove SDK (the ``viz`` extra) is installed.

Every producer of a run directory (``tether simulate``, ``tether reproduce``, the recorder of
``tether run``) calls :func:`mcap_beside` right after writing ``run.npz``; the conversion itself is
:func:`recorder.viz.write_mcap`. Without ``foxglove-sdk`` the run file is written as before and a
one-line notice says why there is no ``run.mcap``.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from tether.mission import Mission
from tether.runfile import EVENT_FIELDS, EVENT_PREFIXES, Run

log = logging.getLogger("tether")
_warned = False


def mcap_beside(run: Run, mission: Mission | None, npz: str | Path, scene_rate: float | None = None) -> Path | None:
    """Write ``run.mcap`` beside ``npz`` (the same name with ``.mcap``); returns its path, or None
    when the Foxglove SDK is not installed. ``scene_rate``: the 3D scene's rate [Hz] (None: the
    default, 0: every tick)."""
    global _warned
    try:
        from recorder import viz
    except ImportError as exc:
        if not _warned:
            log.warning("no run.mcap: the Foxglove SDK is not installed (pip install 'tether[viz]'): %s", exc)
            _warned = True
        return None
    rate = viz.SCENE_RATE if scene_rate is None else scene_rate
    return viz.write_mcap(run, mission, Path(npz).with_suffix(".mcap"), scene_rate=rate)


EPOCH_NS = 1_000_000_000 * 10**9
"""Log time of tick 0 of a simulated-time run (lockstep, the simulators) [ns]: 2001-09-09T01:46:40Z,
i.e. 1e9 s after the Unix epoch. A real-time run's tick 0 is at its own Unix time,
``RunMeta.epoch_ns``."""

TICK_ARRAYS = ("t", "leader_p", "leader_v", "leader_a", "payload_p", "payload_v")
"""Arrays with one row per tick and none per agent (topic ``/run``); every other array whose first
two axes are (tick, agent) is a field of ``/agent/<id>``, except the link statistics."""
LINK_PREFIX = "link_"
EVENT_TOPICS = {"events": "/events/agent", "plant_events": "/events/plant"}
"""SafetyRecord's event lists -> their topics (structured; ``/safety`` has them as text)."""
LAUNCHER_TOPIC = "/events/launcher"
EVENTS_FILE = "events.json"
"""The launcher's events beside ``run.npz`` (``tether run``), put on :data:`LAUNCHER_TOPIC`."""


def epoch_of(run: Run) -> int:
    """The log time of ``run``'s tick 0 [ns]: its Unix time for a real-time run, else :data:`EPOCH_NS`."""
    return run.meta.epoch_ns if run.meta.epoch_ns is not None else EPOCH_NS


@dataclass(frozen=True)
class ArrayPlan:
    """Where each array of a run file goes in its MCAP file (pure: :func:`plan`)."""

    tick: tuple[str, ...]
    """(T, ...) arrays of no agent: fields of ``/run`` under their npz names."""
    agent: tuple[str, ...]
    """(T, N, ...) arrays: fields of ``/agent/<id>`` under their npz names (among them the clock
    offsets ``clock_offset``, whose slots ``clock_role`` and ``clock_src`` of ``/run/static`` name)."""
    link: tuple[str, ...]
    """(T, N, D) ``link_*`` arrays: fields of ``/link/<dst>/<src>`` without the prefix."""
    static: tuple[str, ...]
    """Arrays without a tick axis (ids, link sources, gate counts, run totals): the one ``/run/static``
    message at tick 0, under their npz names."""
    events: tuple[str, ...]
    """``event_*`` and ``plant_event_*``: one message per event on :data:`EVENT_TOPICS`."""


def plan(run: Run) -> ArrayPlan:
    """Which topic and field each array of ``run.arrays()`` goes to; an array ``Run`` gains is covered
    by its shape (a (T, N, ...) array is an agent's field, any other without a tick axis is static)."""
    T, N = len(run.t), len(run.agent_ids)
    ev = tuple(p + f for p in EVENT_PREFIXES.values() for f in EVENT_FIELDS)
    tick, agent, link, static = [], [], [], []
    for name, a in run.arrays().items():
        if name in ev:
            continue
        per_tick = a.ndim >= 1 and a.shape[0] == T and name not in ("agent_ids",)
        per_agent = per_tick and a.ndim >= 2 and a.shape[1] == N and name not in TICK_ARRAYS
        if name.startswith(LINK_PREFIX) and a.ndim == 3:
            link.append(name)
        elif per_agent:
            agent.append(name)
        elif per_tick:
            tick.append(name)
        else:
            static.append(name)
    return ArrayPlan(tuple(tick), tuple(agent), tuple(link), tuple(static), ev)


def launcher_events(npz: str | Path) -> list[dict[str, Any]]:
    """The launcher's events (``events.json`` beside ``npz``: ``t``, ``who``, ``what``, ``why``), or
    none when there is no such file. A file that does not parse is reported and skipped."""
    path = Path(npz).with_name(EVENTS_FILE)
    if not path.exists():
        return []
    try:
        raw = json.loads(path.read_text())
        return [{"t": e["t"], "who": str(e["who"]), "what": str(e["what"]), "why": str(e["why"])} for e in raw]
    except (ValueError, KeyError, TypeError) as exc:
        log.warning("%s: not the launcher's events (%s); run.mcap is written without them", path, exc)
        return []


CHUNK_VALUES = 1 << 18
"""Values a file's arrays are converted to Python lists in at once (:class:`Chunks`)."""


class Chunks:
    """Tick ``k`` of arrays as Python lists, converted a chunk of ticks at a time: as fast as
    converting the whole run at once (one ``tolist`` per array and chunk, not per tick) in memory
    bounded by :data:`CHUNK_VALUES` (converted whole, a 100 000-tick run's lists took 1.2 GB).
    ``rows(k0, k1)`` gives each array's ticks ``k0:k1`` as numpy arrays; ticks are asked for in
    increasing order."""

    def __init__(self, rows: Callable[[int, int], dict[str, np.ndarray]], ticks: int):
        self._rows, self._ticks = rows, ticks
        self._k0 = self._k1 = 0
        self._lists: dict[str, list] = {}
        self._span = max(1, CHUNK_VALUES // max(1, sum(a.size for a in rows(0, 1).values()))) if ticks else 1

    def at(self, k: int) -> dict[str, Any]:
        if not self._k0 <= k < self._k1:
            self._k0, self._k1 = k, min(k + self._span, self._ticks)
            self._lists = {n: a.tolist() for n, a in self._rows(self._k0, self._k1).items()}
        i = k - self._k0
        return {n: rows[i] for n, rows in self._lists.items()}


class Complete:
    """The channels that make an MCAP file the whole run: every array of ``run.npz`` not already on
    ``/agent/<id>`` or ``/leader`` (on ``/run``, ``/agent/<id>``, ``/link/<dst>/<src>``,
    ``/run/static``) and every event as a structured message.

    ``channel(topic, schema)`` opens a JSON channel and returns a ``log(bytes, log_time_ns)``
    callable (the Foxglove context's, given by :mod:`recorder.viz`); ``have`` names the fields the
    agent messages already carry. ``whole``: the run is complete (a file), converted a chunk of
    ticks at a time (:class:`Chunks`); else one tick at a time (live)."""

    def __init__(self, run: Run, channel: Callable[[str, dict], Callable[[bytes, int], None]],
                 have: set[str], whole: bool):
        import msgspec

        self.run, self.whole = run, whole
        self.enc = msgspec.json.Encoder()
        self.plan = p = plan(run)
        arrays = run.arrays()
        self.ids = [int(a) for a in run.agent_ids]
        self.agent_names = [n for n in p.agent if n not in have]
        self.arrays = {n: arrays[n] for n in (*p.tick, *self.agent_names, *p.link)}
        self.chunks = (Chunks(lambda k0, k1: {n: a[k0:k1] for n, a in self.arrays.items()}, len(run.t))
                       if whole else None)
        self.tick_log = channel("/run", _object("tether.Tick", p.tick))
        self.links: list[tuple[int, int, str, Callable[[bytes, int], None]]] = []  # (i, slot, topic, log)
        if p.link and run.links is not None:
            fields = [n[len(LINK_PREFIX):] for n in p.link]
            for i, aid in enumerate(self.ids):
                for slot, src in enumerate(run.links.src[i].tolist()):
                    if src != 0:
                        topic = f"/link/{aid}/{src}"
                        self.links.append((i, slot, topic, channel(topic, _object("tether.Link", fields))))
        self.static = {n: arrays[n].tolist() for n in p.static}
        self.static_log = channel("/run/static", _object("tether.RunStatic", p.static))
        event = _object("tether.SafetyEvent", [*EVENT_FIELDS, "src_name", "dst_name", "origin"])
        self.event_logs = {attr: channel(topic, event) for attr, topic in EVENT_TOPICS.items()}
        self.launcher_log = channel(LAUNCHER_TOPIC, _object("tether.LauncherEvent", ("t", "who", "what", "why")))

    def agent_schema(self) -> dict[str, dict]:
        """The JSON schema properties of the agent fields this adds."""
        return {n: {"description": f"run.npz {n}[k, i]"} for n in self.agent_names}

    def _row(self, name: str, k: int) -> Any:
        if self.chunks is not None:
            return self.chunks.at(k)[name]
        return self.arrays[name][k].tolist()

    def agent_fields(self, k: int) -> list[dict[str, Any]]:
        """Tick ``k``'s extra fields of each agent's message, in agent order."""
        rows = {name: self._row(name, k) for name in self.agent_names}
        return [{name: rows[name][i] for name in self.agent_names} for i in range(len(self.ids))]

    def tick(self, k: int, ns: int) -> None:
        """Log tick ``k`` of ``/run`` and the links at log time ``ns``."""
        enc = self.enc
        self.tick_log(enc.encode({"k": k, **{name: self._row(name, k) for name in self.plan.tick}}), ns)
        if self.links:
            rows = {name: self._row(name, k) for name in self.plan.link}
            cut = len(LINK_PREFIX)
            for i, slot, _, log_ in self.links:
                log_(enc.encode({"k": k, **{name[cut:]: r[i][slot] for name, r in rows.items()}}), ns)

    def start(self, ns: int) -> None:
        """The static arrays, once, at tick 0's log time ``ns``."""
        self.static_log(self.enc.encode(self.static), ns)

    def event(self, attr: str, e: Any, ns: int, modes: tuple[str, ...]) -> None:
        """A safety event of ``SafetyRecord.<attr>`` on its structured topic at log time ``ns``."""
        name = (lambda c: modes[c] if 0 <= c < len(modes) else str(c))
        msg = {f: getattr(e, f) for f in EVENT_FIELDS}
        msg.update(src_name=name(e.src), dst_name=name(e.dst), origin="agent" if attr == "events" else "plant")
        self.event_logs[attr](self.enc.encode(msg), ns)

    def launcher(self, event: dict[str, Any], ns: int) -> None:
        """One of the launcher's events at log time ``ns``."""
        self.launcher_log(self.enc.encode(event), ns)


def _object(title: str, fields: Any) -> dict:
    return {"title": title, "type": "object", "properties": {f: {} for f in fields}}


def app_layout(sdk_layout: dict) -> dict:
    """A layout as the Foxglove app's **Layout → Import from file…** reads it: ``configById`` (each
    panel's config under ``<panelType>!<n>``, its title as ``foxglovePanelTitle``), the mosaic tree
    ``layout`` (a panel id, or ``{direction, first, second, splitPercentage}``), ``globalVariables``,
    ``userNodes`` and ``playbackConfig``; from the Foxglove SDK's ``Layout.to_json()`` tree of splits
    (``{type: split, direction, items: [{proportion, content}]}``) and panels. Pure."""
    config: dict[str, dict] = {}

    def node(content: dict) -> Any:
        if content["type"] == "panel":
            pid = f"{content['panelType']}!{len(config) + 1}"
            config[pid] = {**content.get("config", {}),
                           **({"foxglovePanelTitle": content["title"]} if content.get("title") else {})}
            return pid
        items = content["items"]
        if len(items) == 1:
            return node(items[0]["content"])
        first, rest = items[0], items[1:]
        share = [float(i.get("proportion", 1.0)) for i in items]
        second = node({"type": "split", "direction": content["direction"], "items": rest})
        return {"direction": content["direction"], "first": node(first["content"]), "second": second,
                "splitPercentage": 100.0 * share[0] / sum(share)}

    tree = node(sdk_layout["content"])
    return {"configById": config, "globalVariables": {}, "userNodes": {}, "linkedGlobalVariables": [],
            "playbackConfig": {"speed": 1}, "layout": tree}


def parameters(mission: Mission | None) -> dict[str, Any]:
    """The run's parameters as the live view advertises them (read-only): the law's (``law.kp0``,
    ``law.gamma_p``, ``law.sigma``, a custom law's ``law.params.<name>`` ...) and the failsafes'
    (``safety.<field>``), by dotted name; None values left out. Pure."""
    if mission is None:
        return {}
    import msgspec

    out: dict[str, Any] = {}

    def flat(prefix: str, value: Any) -> None:
        if isinstance(value, dict):
            for k, v in value.items():
                flat(f"{prefix}.{k}", v)
        elif value is not None:
            out[prefix] = value

    flat("law", msgspec.to_builtins(mission.law))
    flat("safety", msgspec.to_builtins(mission.safety))
    out["mission.rate"] = mission.rate
    return out
