"""The recorder's journal: every sample it records, written as it goes, so that a recorder killed
mid-run (``kill -9``, its launcher killed, its machine stopped) leaves a run that can be read.

``journal.mcap`` in the run directory is an MCAP file (the format Foxglove and ``mcap`` read, made
for recording as you go): zstd-compressed chunks, one closed and handed to the operating system at
least every :data:`FLUSH_PERIOD` of wall time and of mission time (a lockstep run goes faster than
the wall clock), and everything handed over ``fsync``-ed every :data:`FLUSH_PERIOD` of wall time
from a worker thread (the event loop never waits for the disk). A chunk is whole or absent: a file
cut anywhere reads up to its last whole chunk, i.e. everything recorded up to one flush period
before the cut, on either clock (:func:`read`); a machine that stops loses what was not yet synced.

Each message is one wire message exactly as the recorder took it, after its plausibility gate
(``tether.wire.encode``: msgpack, message encoding ``msgpack``, a JSON schema per type): the
leader's, plants' and agents' samples in real time, the agents' and the leader's records in
lockstep, on channels ``/<role>/<id>/<kind>`` (``/plant/2/state``, ``/agent/2/record``). Log time:
when the recorder took it [ns, Unix]; publish time: its sample time ``t`` [ns, mission time].
The first record is the metadata ``tether.journal`` (:class:`Header`: the mission's text, the
clock, the namespace); ``tether.drops`` metadata records carry the recorder's drop counts when
they change; ``tether.end`` closes a journal whose recorder finished.

:func:`recover` replays a journal through the recorder's own bookkeeping
(:class:`recorder.recording.Recording`) into a :class:`~tether.runfile.Run`, the same run the recorder
would have written, marked incomplete and ``recovered``; :func:`load` reads a run directory either
way, and :func:`rebuild` writes the rebuilt run as ``run.npz`` and ``run.mcap``. A recorder that
finishes writes ``run.npz`` (and ``run.mcap``), ``fsync``-s it and removes its journal.
"""

from __future__ import annotations

import logging
import math
import os
import struct
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, IndexType, Writer

from tether import wire
from tether.runfile import Run, missing_report

log = logging.getLogger("tether")

NAME = "journal.mcap"
"""The journal's name in a run directory."""
VERSION = 1
"""The journal's layout version (:class:`Header`)."""
FLUSH_PERIOD = 1.0
"""At most this long between two flushes [s], of wall time and of mission time (the sample time of
the messages taken): what a killed recorder can lose (plus what its input queues held)."""
CHUNK_BYTES = 4 << 20
"""A chunk is closed at this size even within a flush period (lockstep runs fast) [bytes]."""
MESSAGE_ENCODING = "msgpack"


class Header(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """The journal's first record (metadata ``tether.journal``, each field a string)."""

    journal_version: int = VERSION
    mission: str
    mission_text: str
    namespace: str
    duration: float
    """The run's duration [s] (the mission's, or ``--duration``'s)."""
    lockstep: bool
    started_ns: int
    """When the recorder opened it [ns, Unix]."""


class Journal:
    """The journal being written (the recorder's event loop alone calls it, except :meth:`sync`).

    Create with :meth:`create`; :meth:`add` each message taken, :meth:`flush` at least every
    :data:`FLUSH_PERIOD`, :meth:`sync` (blocking: from a worker thread) after a flush, then
    :meth:`finish` or :meth:`discard`."""

    def __init__(self, path: Path, fh: IO[bytes], writer: Writer, now_ns: Callable[[], int]):
        self.path, self._fh, self._writer, self._now_ns = path, fh, writer, now_ns
        self._schemas: dict[type, int] = {}
        self._channels: dict[tuple[str, int, str], int] = {}
        self._drops: dict[str, int] = {}
        self.messages = 0
        self.flushes = 0
        self.syncs = 0
        self.sync_seconds = 0.0
        """Wall time spent in ``fsync`` [s] (on a worker thread)."""
        self.sync_max = 0.0
        self._flush_at = FLUSH_PERIOD
        """The next multiple of :data:`FLUSH_PERIOD` of mission time: a message at or past it flushes."""
        self.closed = False
        self.error: OSError | None = None
        """Why the journal stopped before its end (a failed write), if it did."""

    @classmethod
    def create(cls, directory: Path, header: Header, now_ns: Callable[[], int] = time.time_ns) -> "Journal":
        """Open ``directory/journal.mcap`` (a new file; an existing one is replaced, a symlink in its
        place refused with ``OSError``), write its header and flush it."""
        path = directory / NAME
        path.unlink(missing_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o644)
        fh = os.fdopen(fd, "wb")
        # no message indexes: a journal is read front to back (measured: 10 % fewer bytes, and a little
        # less CPU per message than with every index); chunk CRCs kept: a torn chunk is told from a whole one
        writer = Writer(fh, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD, index_types=IndexType.NONE)
        writer.start(profile="", library="tether journal")
        writer.add_metadata("tether.journal", {f: str(getattr(header, f)) for f in header.__struct_fields__})
        journal = cls(path, fh, writer, now_ns)
        journal.flush()
        return journal

    def _channel(self, msg: wire.Message) -> int:
        role, kind = _TOPICS[type(msg)]
        if isinstance(msg, wire.Record) and msg.leader:
            role = "leader"
        key = (role, msg.sender, kind)
        cid = self._channels.get(key)
        if cid is None:
            sid = self._schemas.get(type(msg))
            if sid is None:
                sid = self._schemas[type(msg)] = self._writer.register_schema(
                    name=f"tether.wire.{type(msg).__name__}", encoding="jsonschema",
                    data=msgspec.json.encode(msgspec.json.schema(type(msg))))
            cid = self._channels[key] = self._writer.register_channel(
                topic=f"/{role}/{msg.sender}/{kind}", message_encoding=MESSAGE_ENCODING, schema_id=sid)
        return cid

    def add(self, msg: wire.Message) -> None:
        """Journal one message the recorder took (buffered until the next :meth:`flush`, which the
        first message at or past each :data:`FLUSH_PERIOD` of mission time makes itself)."""
        if self.closed:
            return
        t_ns = int(msg.t * 1e9) if 0.0 <= msg.t < 1.8e10 else 0
        try:  # a full chunk is written here
            self._writer.add_message(self._channel(msg), log_time=self._now_ns(), data=wire.encode(msg),
                                     publish_time=t_ns, sequence=self.messages & 0xFFFFFFFF)
        except OSError as exc:
            self._fail(exc)
            return
        self.messages += 1
        if math.isfinite(msg.t) and msg.t >= self._flush_at:  # (a non-finite t: the wall-time flush)
            self.flush()
            self._flush_at = (math.floor(msg.t / FLUSH_PERIOD) + 1) * FLUSH_PERIOD

    def drops(self, counts: dict[str, int]) -> None:
        """Note the recorder's drop counts (a metadata record, only when they changed)."""
        if not self.closed and counts != self._drops:
            self._drops = dict(counts)
            try:
                self._writer.add_metadata("tether.drops", {r: str(c) for r, c in counts.items()})
            except OSError as exc:
                self._fail(exc)

    def flush(self) -> None:
        """Close the chunk in progress and hand everything to the operating system (survives the
        process, not the machine: :meth:`sync`). Non-blocking in practice: a write to the page cache.
        A failed write (a full disk) closes the journal, keeping what was written before, and is
        noted in :attr:`error` (the caller logs it): the recording goes on without it."""
        if self.closed:
            return
        try:
            self._writer.flush()
        except OSError as exc:
            self._fail(exc)
            return
        self.flushes += 1

    def _fail(self, exc: OSError) -> None:
        """Stop journaling after a failed write (what was written before stays readable)."""
        self.error = exc
        self.closed = True
        try:
            self._fh.close()
        except OSError:
            pass

    def sync(self) -> None:
        """``fsync`` what was flushed (blocks until the disk has it: call from a worker thread)."""
        if self.closed:
            return
        t0 = time.perf_counter()
        try:
            os.fsync(self._fh.fileno())
        except (OSError, ValueError):  # closed meanwhile: nothing left to keep
            return
        spent = time.perf_counter() - t0
        self.syncs += 1
        self.sync_seconds += spent
        self.sync_max = max(self.sync_max, spent)

    def size(self) -> int:
        """Bytes handed to the operating system so far."""
        return self._fh.tell()

    def finish(self) -> None:
        """Close the journal as finished (``tether.end``, the MCAP summary)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.add_metadata("tether.end", {"messages": str(self.messages)})
            self._writer.finish()
        except OSError as exc:
            self.error = exc
        finally:
            try:
                self._fh.close()
            except OSError as exc:
                self.error = self.error or exc

    def discard(self) -> None:
        """Close and remove the journal (the run file it stood in for is written and synced)."""
        if not self.closed:
            self.finish()
        self.path.unlink(missing_ok=True)


_TOPICS: dict[type, tuple[str, str]] = {
    wire.State: ("leader", "state"), wire.PlantState: ("plant", "state"), wire.Telemetry: ("agent", "telemetry"),
    wire.WorldState: ("world", "state"), wire.Record: ("agent", "record"),
}
"""Message type -> the role and kind of its journal channel (a record with leader states is the leader's)."""


@dataclass
class Contents:
    """What a journal holds (:func:`read`)."""

    header: Header
    messages: list[wire.Message] = field(default_factory=list)
    finished: bool = False
    """The recorder closed it (``tether.end``); else it was cut short."""
    cut: str | None = None
    """Where and why reading stopped before the end of a journal that was cut short."""
    drops: dict[str, int] = field(default_factory=dict)
    """The recorder's newest drop counts."""
    undecodable: int = 0
    """Messages that did not decode (skipped)."""


def read(path: str | Path) -> Contents:
    """Read a journal (``path`` or ``path/journal.mcap``), whole or cut anywhere: every message up to
    the last whole chunk. Raises ValueError when it has no header (not a tether journal, or cut before
    its first flush)."""
    path = Path(path)
    if path.is_dir():
        path = path / NAME
    header: Header | None = None
    out: Contents | None = None
    channels: dict[int, Channel] = {}
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh, validate_crcs=True).records:
                if isinstance(record, Metadata):
                    if record.name == "tether.journal":
                        header = msgspec.convert(dict(record.metadata), Header, strict=False)
                        out = Contents(header)
                    elif out is not None and record.name == "tether.drops":
                        out.drops = {r: int(c) for r, c in record.metadata.items()}
                    elif out is not None and record.name == "tether.end":
                        out.finished = True
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and out is not None:
                    try:
                        out.messages.append(wire.decode(record.data))
                    except (msgspec.DecodeError, msgspec.ValidationError):
                        out.undecodable += 1
        except (McapError, EOFError, struct.error, ValueError, OSError) as exc:
            if out is not None and not out.finished:
                out.cut = f"cut at byte {fh.tell()} ({type(exc).__name__}: {str(exc) or 'end of file'})"
            elif out is None:
                raise ValueError(f"{path}: not a readable tether journal ({type(exc).__name__}: {exc})") from None
    if out is None:
        raise ValueError(f"{path}: no tether.journal header: not a tether journal, or cut before its first flush")
    if not out.finished and out.cut is None:
        out.cut = "ends without its closing record"
    return out


def replay(contents: Contents) -> Any:
    """The recorder's bookkeeping (:class:`recorder.recording.Recording`) filled with the journal's
    messages, in the order it took them (pure: nothing is written)."""
    from recorder.recording import Recording, RecordingContext
    from tether import mission as ms

    h = contents.header
    source = f"the journal's mission ({h.mission})"
    mission = ms.with_duration(ms.loads(h.mission_text, source=source), h.duration, source=source)
    rec = Recording(RecordingContext(mission=mission, lockstep=h.lockstep, namespace=h.namespace,
                                     mission_text=h.mission_text), Path("."), mcap=False)
    rec.first = 0.0  # the epoch hint matters only to a recorder attaching live
    for msg in contents.messages:
        rec.take(msg)
    return rec


def recover(path: str | Path) -> Run:
    """The run a killed recorder would have written, rebuilt from its journal (``path`` or
    ``path/journal.mcap``): every sample it took up to its last flush; ``meta.complete`` false and
    ``meta.recovered`` saying how far it goes. Raises ValueError for a file that is no journal."""
    contents = read(path)
    rec = replay(contents)
    newest = int(rec.newest)
    drops = {**contents.drops, **({"undecodable_journal": contents.undecodable} if contents.undecodable else {})}
    run: Run = rec.finalise(complete=False, drops=drops)
    upto = f"tick {newest} (t = {newest * rec.mission.dt:.2f} s)" if newest >= 0 else "no tick"
    how = "closed by its recorder" if contents.finished else f"{contents.cut}"
    run.meta.recovered = (f"from the recorder's journal ({len(contents.messages)} messages, {how}): "
                          f"samples up to {upto} of {rec.mission.steps}")
    return run


def rebuild(directory: str | Path, mcap: bool = True) -> Path:
    """Write ``directory/run.npz`` (synced) from its journal (:func:`recover`), and ``run.mcap``
    beside it when ``mcap`` and the Foxglove SDK is installed; then remove the journal. Returns the
    run file's path. Raises ValueError for a file that is no journal, OSError for a failed write
    (the journal then stays)."""
    from recorder.export import mcap_beside

    directory = Path(directory)
    run = recover(directory)
    path = run.save(directory / "run.npz", sync=True)
    if mcap:
        mcap_beside(run, None, path)
    (directory / NAME).unlink(missing_ok=True)
    return path


def load(path: str | Path, report: Callable[[str], None] | None = None) -> Run:
    """A run directory's run: its ``run.npz`` when there is one (or ``path`` is one), else the run
    rebuilt from its journal (:func:`recover`). What the run lacks (:func:`tether.runfile.missing_report`)
    goes to ``report`` line by line (default: the log, as warnings). Raises FileNotFoundError when
    there is neither, ValueError for a file that is neither."""
    path = Path(path)
    say = report if report is not None else log.warning
    if path.is_dir() and not (path / "run.npz").exists() and (path / NAME).exists():
        run = recover(path)
    elif path.is_file() and path.suffix == ".mcap" and path.name == NAME:
        run = recover(path)
    elif path.is_dir() and not (path / "run.npz").exists():
        raise FileNotFoundError(f"{path}: no run.npz and no {NAME}: not a run directory (tether simulate/run "
                                "--out DIR writes DIR/run.npz)")
    else:
        run = Run.load(path)
    for line in missing_report(run):
        say(line)
    return run


__all__ = ["FLUSH_PERIOD", "NAME", "Contents", "Header", "Journal", "load", "read", "rebuild", "recover", "replay"]
