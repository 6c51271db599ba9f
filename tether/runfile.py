"""Run files: one ``run.npz`` per run, written by the reference simulator, the in-process engine and
the runtime's recorder. The layout is documented in ``docs/runfile.md``; in short (float64 unless
said; T samples, N agents, d dimensions; SI units, world frame):

=================  ===========  ====================================================================
``t``              (T,)         sample time t_k = k h [s]
``agent_ids``      (N,) int64   agent ids, in the order of the agent axis
``p`` ``v``        (T, N, d)    position [m], velocity [m/s] at t_k
``a``              (T, N, d)    measured acceleration shared with neighbours at t_k [m/s^2]
``u``              (T, N, d)    command computed at t_k and held over [t_k, t_k+h) [m/s^2]
``xi`` ``zeta``    (T, N, d)    formation error [m] (Eq. 8), velocity error [m/s] (Eq. 9) at t_k
``law_state``      (S, T, N, d) the law's S state variables at t_k (its gains, integrators ...),
                               named by ``meta.law_state``, units ``meta.law_units``
``kp`` ``kv``      (T, N, d)    the first two state variables (views of ``law_state``; stored
                               only where the law has fewer, as zeros)
``d``              (T, N, d)    disturbance d(t_k) [m/s^2] (NaN where the recorder cannot know it)
``leader_p/v/a``   (T, d)       the virtual leader's state at t_k
``safety_mode``    (T, N) int   the agent's safety supervisor mode at t_k (code of ``meta.modes``; -1: no sample)
``plant_mode``     (T, N) int   the plant's command watchdog mode at t_k (same codes; -1: no sample)
``meta``           () str       JSON of :class:`RunMeta` (``format_version`` 5)
=================  ===========  ====================================================================

The optional groups are typed containers, each with the arrays of its npz names: :class:`Links`
(``link_*``), :class:`RuntimeRecord` (``plant_p`` ... ``late``), :class:`PlantRecord` (``payload_p``,
``tension``, ``attitude`` ...) and :class:`SafetyRecord` (the mode columns, ``event_*``,
``gate_*``) and :class:`ClockRecord` (``clock_*``, real time: per-link clock-offset bounds). A run
file opens with nothing but numpy: ``numpy.load("run.npz")``. Files of format version 1 (before
the safety record) still load: their modes read -1 (no sample), with no events; files of version 2
(before the clock record) load with ``clock`` None; files of version 3 (before the plants' own
events) load with no plant events; files of version 4 and older (before the law's named state)
load with ``law_state`` their ``kp`` and ``kv``, named so. :func:`gaps` says which samples a run
lacks (a run stopped early, a recorder frozen or killed: ``recorder/journal.py`` rebuilds a run
from what a killed recorder wrote as it went).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Mapping

import msgspec
import numpy as np

from tether.wire import MODES, SafetyEvent

FORMAT_VERSION = 5
READS = (1, 2, 3, 4, 5)
"""Format versions :meth:`Run.load` reads (a version-1 file is upgraded on load)."""
SERIES = ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d")
BASE = ("t", "agent_ids", *SERIES, "leader_p", "leader_v", "leader_a")
SHOWN = ("kp", "kv")
"""The columns of the law's first two state variables (:meth:`agent.laws.Bound.shown`)."""
NO_SAMPLE = -1
"""The mode code of a (tick, vehicle) with no sample."""

Source = Literal["reference-discrete", "reference-continuous", "lockstep-inprocess", "runtime-lockstep",
                 "runtime-realtime"]


class DropCounts(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """Messages a process dropped, by reason (:class:`tether.wire.Receiver`'s reasons, then the node's)."""

    malformed: int = 0
    """Not msgpack, or not a known message."""
    version: int = 0
    """Another wire version."""
    type: int = 0
    """A message of the wrong type for its key."""
    sender: int = 0
    """Sender id differs from the key's."""
    size: int = 0
    """A vector of the wrong dimension."""
    nonfinite: int = 0
    """NaN or Inf where a number must be finite."""
    corrupt: int = 0
    """Copies an emulated link corrupted (checksum failures)."""
    netem_invalid: int = 0
    """Invalid netem control messages."""
    other: dict[str, int] = {}
    """Reasons this version does not name, kept rather than lost."""

    @classmethod
    def of(cls, counts: Mapping[str, int]) -> "DropCounts":
        """From a ``reason -> count`` mapping (``Receiver.drops``)."""
        named = {f for f in cls.__struct_fields__ if f != "other"}
        return cls(**{r: int(c) for r, c in counts.items() if r in named},
                   other={r: int(c) for r, c in counts.items() if r not in named})

    def total(self) -> int:
        return sum(getattr(self, f) for f in self.__struct_fields__ if f != "other") + sum(self.other.values())


class RunMeta(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """A run's metadata (the ``meta`` JSON string of ``run.npz``)."""

    mission: str
    """The mission's name."""
    source: Source
    """Which engine wrote the run."""
    law: str
    """The law's name: ``sigma``, ``benchmark``, or a law of one's own by its ``name`` (``integral``, ``pd``)."""
    rate: float
    """Control rate [Hz]."""
    steps: int
    """Ticks after tick 0 (T = steps + 1 when every tick is recorded)."""
    seed: int = 0
    """The mission's seed."""
    format_version: int = FORMAT_VERSION
    law_state: tuple[str, ...] = ()
    """The names of the law's state variables (``FormationLaw.state``), in the order of the first
    axis of ``Run.law_state``."""
    law_units: tuple[str, ...] = ()
    """Their units, in the same order (``''``: the law does not say); empty when none is known."""
    modes: tuple[str, ...] = MODES
    """Safety mode names by integer code (``safety_mode``, ``plant_mode``, ``event_src/dst``)."""
    mission_text: str | None = None
    """The mission file's text (TOML)."""
    substeps: int | None = None
    """``reference-continuous``: RK4 substeps per control period."""
    diverged_at: float | None = None
    """In-process engine: when the run diverged and was stopped [s]; None if it did not."""
    namespace: str | None = None
    """Runtime: the run's Zenoh namespace."""
    complete: bool | None = None
    """Runtime: every sample of every tick was recorded."""
    samples_recorded: int | None = None
    samples_expected: int | None = None
    recorder_drops: DropCounts | None = None
    """Runtime: messages the recorder dropped."""
    recovered: str | None = None
    """Runtime: set when the run was rebuilt from the recorder's journal (its recorder did not finish:
    killed, or its machine stopped); says up to which tick and time the journal holds samples."""
    epoch_ns: int | None = None
    """Real time: the Unix time of tick 0 [ns] on the recorder's clock (``t_k`` is then at
    ``epoch_ns + t_k``); None for simulated time (lockstep, the simulators)."""


class Links(msgspec.Struct, kw_only=True):
    """Per-agent in-link statistics (npz ``link_<field>``); D = largest in-degree.

    The recorder stores per-tick counts ``(T, N, D)``; the in-process engine run totals ``(N, D)``
    int64 for the counts (``age`` is per tick in both). :meth:`final` gives the totals of either."""

    src: np.ndarray
    """``(N, D)`` int64: agent i's in-neighbours in link order (0 = unused slot)."""
    age: np.ndarray
    """``(T, N, D)``: age of j's sample when used at t_k [s] (NaN: none usable)."""
    received: np.ndarray
    """Samples accepted from j so far."""
    used: np.ndarray
    """Ticks so far at which j's sample was used."""
    stale: np.ndarray
    """Samples not newer than the newest held (= duplicates + reordered)."""
    duplicates: np.ndarray
    reordered: np.ndarray
    corrupt: np.ndarray
    """Copies the emulated link corrupted, dropped."""
    silent: np.ndarray | None = None
    """Recorder ``(T, N, D)``: 1 while j's liveliness token is gone."""
    delivery: np.ndarray | None = None
    """Recorder ``(T, N, D)``: distinct samples received over samples j sent up to its newest received."""
    age_p50: np.ndarray | None = None
    """Recorder ``(T, N, D)``: median age of the samples used over the last 500 ticks [s]."""
    age_p99: np.ndarray | None = None
    """Recorder ``(T, N, D)``: 99th percentile of the same [s]."""

    @staticmethod
    def final(counts: np.ndarray) -> np.ndarray:
        """Run totals ``(N, D)`` of a count: the last tick's of a per-tick one, else itself."""
        return counts[-1] if counts.ndim == 3 else counts

    @classmethod
    def empty(cls, samples: int, n: int, width: int) -> "Links":
        """The recorder's per-tick statistics, NaN (``src`` 0) until filled."""
        per_tick = {f: np.full((samples, n, width), np.nan) for f in cls.__struct_fields__ if f != "src"}
        return cls(src=np.zeros((n, width), dtype=np.int64), **per_tick)


class RuntimeRecord(msgspec.Struct, kw_only=True):
    """What only the runtime's recorder hears (npz names = field names)."""

    plant_p: np.ndarray
    """``(T, N, d)`` each plant's own position measurement of tick k [m]."""
    plant_v: np.ndarray
    """``(T, N, d)`` [m/s]."""
    plant_a: np.ndarray
    """``(T, N, d)`` [m/s^2]."""
    drops: np.ndarray
    """``(T, N)`` messages agent i dropped so far (all reasons)."""
    meas_age: np.ndarray
    """``(T, N)`` age of agent i's own measurement when used at t_k [s]."""
    late: np.ndarray
    """``(T, N)`` real time: ticks of agent i that started more than a period late, so far."""

    @classmethod
    def empty(cls, samples: int, n: int, dim: int) -> "RuntimeRecord":
        return cls(**{f: np.full((samples, n, dim), np.nan) for f in ("plant_p", "plant_v", "plant_a")},
                   **{f: np.full((samples, n), np.nan) for f in ("drops", "meas_age", "late")})


class PlantRecord(msgspec.Struct, kw_only=True):
    """The plants' own records, each present only where the plant makes it (npz names = field names)."""

    attitude: np.ndarray | None = None
    """``(T, N, 3)`` roll, pitch, yaw [rad] of vehicles with mass (NaN for a vehicle without)."""
    payload_p: np.ndarray | None = None
    """``(T, 3)`` payload position [m]."""
    payload_v: np.ndarray | None = None
    """``(T, 3)`` payload velocity [m/s]."""
    tension: np.ndarray | None = None
    """``(T, N)`` cable tension per vehicle [N]."""
    slack_events: np.ndarray | None = None
    """``(T, N)`` taut -> slack transitions per cable since the start (float, NaN where missing)."""


class ClockRecord(msgspec.Struct, kw_only=True):
    """Real time: each agent's per-link clock-offset bounds (:mod:`tether.skew`; npz ``clock_<field>``).
    S slots per agent: its plant and its in-neighbours, in the order their estimates first came."""

    role: np.ndarray
    """``(N, S)`` str: the sender's role of each slot (``plant``, ``agent``, ``leader``; '' unused)."""
    src: np.ndarray
    """``(N, S)`` int64: the sender's id (0 unused)."""
    offset: np.ndarray
    """``(T, N, S)``: the estimate at t_k [s]: minimum delay + how far agent i's clock is ahead of the
    sender's (NaN: none yet)."""

    @classmethod
    def empty(cls, samples: int, n: int, width: int) -> "ClockRecord":
        return cls(role=np.full((n, width), "", dtype="<U8"), src=np.zeros((n, width), dtype=np.int64),
                   offset=np.full((samples, n, width), np.nan))


EVENT_FIELDS = ("k", "t", "vehicle", "src", "dst", "reason")
""":class:`~tether.wire.SafetyEvent`'s fields, stored as arrays ``event_<field>`` of length E (the
agents' supervisors) and ``plant_event_<field>`` of length P (the plants' watchdogs)."""
EVENT_PREFIXES = {"events": "event_", "plant_events": "plant_event_"}
""":class:`SafetyRecord`'s event lists -> npz prefix of their arrays."""


class SafetyRecord(msgspec.Struct, kw_only=True):
    """Safety modes, mode changes and plausibility-gate rejections."""

    safety_mode: np.ndarray
    """``(T, N)`` int64: agent i's supervisor mode at t_k (code of ``RunMeta.modes``; -1: no sample)."""
    plant_mode: np.ndarray
    """``(T, N)`` int64: agent i's plant's command watchdog mode at t_k (-1: no sample)."""
    events: list[SafetyEvent] = []
    """The agents' supervisors' mode changes, in order of (k, vehicle) (npz ``event_k`` ... ``event_reason``)."""
    plant_events: list[SafetyEvent] = []
    """The plants' watchdogs' events, in order of (k, vehicle) (npz ``plant_event_k`` ...): their mode
    changes and the commands they rejected or clamped (``src == dst`` when the mode did not change)."""
    gate_reasons: np.ndarray | None = None
    """``(R,)`` str: the gate's rejection reasons."""
    gate_counts: np.ndarray | None = None
    """``(N, R)`` int64: samples agent i's gate rejected over the run, by reason."""

    @classmethod
    def empty(cls, samples: int, n: int, mode: int = NO_SAMPLE) -> "SafetyRecord":
        return cls(safety_mode=np.full((samples, n), mode, dtype=np.int64),
                   plant_mode=np.full((samples, n), mode, dtype=np.int64))


def _arrays_of(group: msgspec.Struct | None, prefix: str = "") -> dict[str, np.ndarray]:
    if group is None:
        return {}
    return {prefix + f: getattr(group, f) for f in group.__struct_fields__
            if f not in EVENT_PREFIXES and getattr(group, f) is not None}


_GROUPS: dict[str, tuple[type[msgspec.Struct], str]] = {"links": (Links, "link_"), "runtime": (RuntimeRecord, ""),
                                        "plant": (PlantRecord, ""), "safety": (SafetyRecord, ""),
                                        "clock": (ClockRecord, "clock_")}
"""Run attribute -> (container, npz prefix of its fields)."""


class _Version(msgspec.Struct):
    format_version: int = 1


@dataclass
class Run:
    t: np.ndarray
    agent_ids: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    xi: np.ndarray
    zeta: np.ndarray
    kp: np.ndarray
    kv: np.ndarray
    d: np.ndarray
    leader_p: np.ndarray
    leader_v: np.ndarray
    leader_a: np.ndarray
    meta: RunMeta
    safety: SafetyRecord
    links: Links | None = None
    runtime: RuntimeRecord | None = None
    plant: PlantRecord = field(default_factory=PlantRecord)
    clock: ClockRecord | None = None
    law_state: np.ndarray = field(default_factory=lambda: np.empty((0, 0, 0, 0)))
    """``(S, T, N, d)``: the law's state variable ``s`` at t_k in ``law_state[s]`` (named by
    ``meta.law_state[s]``; :meth:`state` by name). Variable first, so that each one is a contiguous
    ``(T, N, d)`` block: ``kp`` and ``kv`` are views of the first two."""

    @classmethod
    def empty(cls, samples: int, agent_ids: list[int], dim: int, meta: RunMeta, mode: int = NO_SAMPLE) -> "Run":
        """NaN series, with one ``law_state`` block per name of ``meta.law_state``; both mode columns
        filled with ``mode`` (an engine without a supervisor passes FLYING)."""
        n = len(agent_ids)

        def series() -> np.ndarray:  # one of SERIES
            return np.full((samples, n, dim), np.nan)

        law_state = np.full((len(meta.law_state), samples, n, dim), np.nan)
        kp, kv = (law_state[s] if s < len(law_state) else series() for s in range(len(SHOWN)))
        return cls(
            t=np.full(samples, np.nan),
            agent_ids=np.array(agent_ids, dtype=np.int64),
            p=series(), v=series(), a=series(), u=series(), xi=series(), zeta=series(), kp=kp, kv=kv,
            d=series(), law_state=law_state,
            leader_p=np.full((samples, dim), np.nan),
            leader_v=np.full((samples, dim), np.nan),
            leader_a=np.full((samples, dim), np.nan),
            meta=msgspec.structs.replace(meta),
            safety=SafetyRecord.empty(samples, n, mode),
        )

    def state(self, name: str) -> np.ndarray:
        """The law's state variable ``name``, ``(T, N, d)`` (a view of :attr:`law_state`). Raises
        KeyError naming the law's state variables when it has none of that name."""
        names = self.meta.law_state
        if name not in names:
            raise KeyError(f"{name!r}: the law {self.meta.law!r} of this run has state "
                           f"{', '.join(names) if names else 'none'}")
        return self.law_state[names.index(name)]

    def zero_absent_shown(self) -> None:
        """Zeros in ``kp``/``kv`` where the law has no such state variable (fewer than two), at the
        ticks that hold a sample (``xi`` recorded): what :meth:`agent.laws.Bound.shown` gives."""
        for s in range(len(self.law_state), len(SHOWN)):
            column = getattr(self, SHOWN[s])
            column[~np.isnan(self.xi)] = 0.0

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array of the run under its npz name (as :meth:`save` writes them): ``kp``/``kv``
        only where the law has fewer state variables (else they are ``law_state``'s first two)."""
        out = {name: getattr(self, name) for name in BASE if name not in SHOWN[:len(self.law_state)]}
        out["law_state"] = self.law_state
        for attr, (_, prefix) in _GROUPS.items():
            out.update(_arrays_of(getattr(self, attr), prefix))
        for attr, prefix in EVENT_PREFIXES.items():
            ev = getattr(self.safety, attr)
            for f in EVENT_FIELDS:
                values = [getattr(e, f) for e in ev]
                out[prefix + f] = (np.array(values, dtype=str) if f == "reason" else
                                   np.array(values, dtype=float if f == "t" else np.int64))
        return out

    def save(self, path: str | Path, sync: bool = False) -> Path:
        """Write ``path`` (a ``.npz``, uncompressed) atomically; returns it. ``sync``: ``fsync`` it
        before it takes its name (it then survives the machine stopping once this returns).

        Uncompressed on purpose: for Section 4's 1000 s run, compression saved 24 % of the bytes
        (53 MB against 70 MB) for 40 times the time (5.9 s against 0.15 s, medians of 3 on a loaded
        2-core machine); a user waits for the file at the end of every run. On a failed write (a full
        disk) the partial ``.part`` file is removed and the ``OSError`` re-raised naming ``path``."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = msgspec.json.encode(msgspec.structs.replace(self.meta, format_version=FORMAT_VERSION)).decode()
        tmp = path.with_name(path.name + ".part")
        try:
            with open(tmp, "wb") as fh:
                # numpy's stub lets ** reach the keyword allow_pickle; no array is named so
                np.savez(fh, meta=np.array(meta), **self.arrays())  # type: ignore[arg-type]
                if sync:
                    fh.flush()
                    os.fsync(fh.fileno())
            tmp.replace(path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise OSError(exc.errno, f"{exc.strerror or exc} while writing the run file", str(path)) from exc
        return path

    @classmethod
    def load(cls, path: str | Path) -> "Run":
        """Read a run file (``path`` or ``path/run.npz``) of a version in :data:`READS`.

        Raises ValueError naming the version for another one, and naming any array or metadata
        field this version does not know."""
        path = Path(path)
        if path.is_dir():
            path = path / "run.npz"
        with np.load(path, allow_pickle=False) as z:
            text = str(z["meta"])
            version = msgspec.json.decode(text, type=_Version).format_version
            if version not in READS:
                raise ValueError(f"{path}: run file format version {version}; this tether reads versions "
                                 f"{', '.join(map(str, READS))}")
            try:
                meta = decode_meta(text)
            except msgspec.ValidationError as exc:
                raise ValueError(f"{path}: run file metadata (format version {version}): {exc}") from None
            arrays = {k: z[k] for k in z.files if k != "meta"}
        stray = {}
        if version < 5:  # the two columns were the law's state as the file knew it
            if "law_state" in arrays:
                stray["law_state"] = arrays.pop("law_state")
            meta = msgspec.structs.replace(meta, law_state=SHOWN, law_units=())
            if all(k in arrays for k in SHOWN):
                arrays["law_state"] = np.stack([arrays.pop(k) for k in SHOWN])
        law_state = arrays.pop("law_state", None)
        if law_state is None or law_state.ndim != 4 or len(law_state) != len(meta.law_state) \
                or ("xi" in arrays and law_state.shape[1:] != arrays["xi"].shape) \
                or len(meta.law_units) not in (0, len(meta.law_state)):
            raise ValueError(f"{path}: law_state does not match the metadata's law_state "
                             f"{list(meta.law_state)} and law_units {list(meta.law_units)}")
        for s, name in enumerate(SHOWN[:len(law_state)]):
            arrays[name] = law_state[s]
        missing = [k for k in BASE if k not in arrays]
        if missing:
            raise ValueError(f"{path}: run file (format version {version}) lacks {', '.join(missing)}")
        base = {k: arrays.pop(k) for k in BASE}
        kinds = EVENT_PREFIXES if version >= 4 else {"events": "event_"}  # the plants' events since 4
        events = {attr: _events({f: arrays.pop(prefix + f) for f in EVENT_FIELDS if prefix + f in arrays})
                  for attr, prefix in kinds.items()}
        groups: dict[str, Any] = {}  # each built and checked by its own kind(**fields)
        for attr, (kind, prefix) in _GROUPS.items():
            fields = {f: arrays.pop(prefix + f) for f in kind.__struct_fields__ if prefix + f in arrays}
            if attr == "safety" and version == 1:
                samples, n = len(base["t"]), len(base["agent_ids"])
                fields = {"safety_mode": np.full((samples, n), NO_SAMPLE, dtype=np.int64),
                          "plant_mode": np.full((samples, n), NO_SAMPLE, dtype=np.int64)}
            if attr == "safety":
                fields.update(events)
            if fields or attr == "plant":
                try:
                    groups[attr] = kind(**fields)
                except TypeError as exc:
                    raise ValueError(f"{path}: incomplete {kind.__name__} arrays: {exc}") from None
        arrays.update(stray)
        if arrays:
            raise ValueError(f"{path}: arrays unknown to run file format version {version}: {', '.join(sorted(arrays))}")
        return cls(meta=meta, law_state=law_state, **groups, **base)


def decode_meta(text: str) -> RunMeta:
    """A run file's ``meta`` string as :class:`RunMeta`, for a file of any version in :data:`READS`."""
    version = msgspec.json.decode(text, type=_Version).format_version
    if version == 1:  # recorder_drops was a plain reason -> count object
        raw = json.loads(text)
        drops = raw.pop("recorder_drops", None)
        if drops is not None:
            raw["recorder_drops"] = msgspec.to_builtins(DropCounts.of(drops))
        return msgspec.convert(raw, RunMeta)
    return msgspec.json.decode(text, type=RunMeta)


def _events(cols: dict[str, np.ndarray]) -> list[SafetyEvent]:
    if not cols:
        return []
    return [SafetyEvent(k=int(k), t=float(t), vehicle=int(veh), src=int(s), dst=int(d), reason=str(why))
            for k, t, veh, s, d, why in zip(*(cols[f] for f in EVENT_FIELDS))]


@dataclass(frozen=True)
class Gap:
    """One stream's missing samples in a run (:func:`gaps`)."""

    stream: str
    """``leader``, ``plant <id>``, ``telemetry of agent <id>`` or ``payload``."""
    missing: int
    """Ticks without its sample."""
    spans: tuple[tuple[int, int], ...]
    """The missing ticks as inclusive ranges ``(first, last)``, in order."""
    last: int
    """Its newest tick recorded (-1: none)."""

    def describe(self, dt: float, limit: int = 3) -> str:
        """One line: ``plant 2: 3000 of 4001 ticks missing: 1001-4000 (t 10.01-40.00 s); newest t 10.00 s``."""
        shown = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in self.spans[:limit])
        more = f" and {len(self.spans) - limit} more spans" if len(self.spans) > limit else ""
        a, b = self.spans[0][0], self.spans[-1][1]
        newest = f"newest t {self.last * dt:.2f} s" if self.last >= 0 else "nothing recorded"
        return (f"{self.stream}: {self.missing} ticks missing: {shown}{more} "
                f"(t {a * dt:.2f}-{b * dt:.2f} s); {newest}")


def _spans(missing: np.ndarray) -> tuple[tuple[int, int], ...]:
    """The True runs of a (T,) bool array as inclusive (first, last) ranges."""
    edges = np.diff(np.concatenate(([0], missing.astype(np.int8), [0])))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1
    return tuple(zip(starts.tolist(), stops.tolist()))


def gaps(run: Run) -> list[Gap]:
    """Which samples ``run`` lacks, per stream (pure; empty when every tick holds every sample).

    A tick lacks the leader's sample where ``leader_p`` is NaN, an agent's telemetry where its
    ``safety_mode`` is −1 (no sample), a plant's sample where its ``plant_mode`` is −1, and the
    payload's where ``payload_p`` is NaN. The engines without a recorder (modes never −1, no
    runtime record) have no gaps."""
    out: list[Gap] = []

    def add(stream: str, missing: np.ndarray) -> None:
        if missing.any():
            heard = np.flatnonzero(~missing)
            out.append(Gap(stream, int(missing.sum()), _spans(missing), int(heard[-1]) if len(heard) else -1))

    add("leader", np.isnan(run.leader_p).any(axis=1))
    ids = [int(i) for i in run.agent_ids]
    if run.runtime is not None:
        for n, aid in enumerate(ids):
            add(f"plant {aid}", run.safety.plant_mode[:, n] == NO_SAMPLE)
    for n, aid in enumerate(ids):
        add(f"telemetry of agent {aid}", run.safety.safety_mode[:, n] == NO_SAMPLE)
    if run.plant.payload_p is not None:
        add("payload", np.isnan(run.plant.payload_p).any(axis=1))
    return out


def missing_report(run: Run, limit: int = 12) -> list[str]:
    """What ``run`` lacks, as lines for a person (empty when it lacks nothing): whether it was rebuilt
    from a journal and up to when, then one line per stream with missing ticks (:meth:`Gap.describe`)."""
    lines = []
    if run.meta.recovered:
        lines.append(f"recovered: {run.meta.recovered}")
    dt = 1.0 / run.meta.rate
    found = gaps(run)
    lines += [g.describe(dt) for g in found[:limit]]
    if len(found) > limit:
        lines.append(f"and {len(found) - limit} more streams with missing ticks")
    return lines
