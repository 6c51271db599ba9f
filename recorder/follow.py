"""``run.mcap`` written as the run is recorded, by a helper process at the lowest CPU priority.

The recorder keeps its run (every array of :class:`~tether.runfile.Run`, and its count of samples
per tick) in one block of memory shared with one helper process, ``python -m recorder.follow``: an
anonymous ``memfd`` that only the two of them map. As ticks complete, the recorder tells the helper
how far the run is whole and hands it the safety events heard since; the helper converts those ticks
into ``run.mcap.part`` (:class:`recorder.viz.McapFile`). It runs at ``SCHED_IDLE``
(:func:`tether.sched.lower_priority`): it converts with the CPU no other process wants, so that it
does not slow the run. A lockstep run is bound by the CPU of its processes, yet leaves part of the two
cores idle between its ticks (``docs/foxglove.md``, *Cost*); a real-time run leaves most of them idle.

When the recorder has saved ``run.npz`` it sends the rest: the final metadata, the gate counts, the
events not sent yet. The helper writes the ticks heard that it has not written (a stopped run's,
complete or not; a tick of which nothing was heard is left out), ends the file, renames it
``run.mcap`` and exits 0. The recorder raises its priority back to normal where it may (the run is
over) and waits for it as long as it writes ticks (:data:`STALL`); if the helper failed or stalled,
the recorder stops it and converts the whole run itself (:func:`recorder.export.mcap_beside`). Either way the file is the one :func:`recorder.viz.write_mcap`
makes of the run, message for message.

The helper's standard input carries JSON lines: first ``{"manifest": [[name, dtype, shape,
offset], ...], "size": bytes, "fd": n, "meta": ..., "mission": ..., "out": path}``; then lines of
:class:`_Line`: any number of ``{"upto": k, "events": [...]}`` (every tick up to ``k`` is whole),
then one with ``"close": true``, the final metadata and gate counts. Its input ending
without a close (the recorder died or gave up) makes it remove its unfinished file and exit 3. The
shared block also holds ``written``, the ticks the helper has written, which the recorder logs.
"""

from __future__ import annotations

import dataclasses
import fcntl
import gc
import logging
import math
import mmap
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from tether import mission as ms
from tether.runfile import Run, RunMeta
from tether.wire import SafetyEvent

log = logging.getLogger("tether")

ALIGN = 64
"""Each array of the shared block starts on a multiple of this many bytes."""

PIPE_SIZE = 1 << 20
"""The helper's input pipe is asked to hold this much (Linux's default limit for a user): the
recorder never blocks on it while the run goes on, whatever the helper's pace."""

STALL = 5.0
"""Once the run is saved, the recorder waits for the helper as long as it writes ticks: after this
long [s] without one written (still at the lowest priority while other work takes every core: raising
a lowered priority needs a privilege), it stops waiting and writes the file itself."""



class _Line(msgspec.Struct, kw_only=True):
    """One line of the helper's input after the first."""

    upto: int = -1
    """Every tick up to this one is whole (-1: none said)."""
    events: list[SafetyEvent] = []
    """Safety events heard since the previous line."""
    close: bool = False
    """The run is saved: write the rest and end the file."""
    meta: str = ""
    """With ``close``: the run's final metadata (JSON)."""
    gate_reasons: list[str] = []
    gate_counts: list[list[int]] = []


_LINE = msgspec.json.Decoder(_Line)


def _layout(arrays: dict[str, np.ndarray]) -> tuple[list[tuple[str, str, tuple[int, ...], int]], int]:
    manifest, size = [], 0
    for name, arr in arrays.items():
        if arr.dtype.hasobject:
            raise TypeError(f"array {name} holds Python objects: it cannot be shared")
        size = -(-size // ALIGN) * ALIGN
        manifest.append((name, arr.dtype.str, tuple(arr.shape), size))
        size += arr.nbytes
    return manifest, max(size, 1)


def _views(buf: mmap.mmap, manifest: list[Any]) -> dict[str, np.ndarray]:
    return {name: np.ndarray(tuple(shape), dtype=np.dtype(dtype), buffer=buf, offset=offset)
            for name, dtype, shape, offset in manifest}


class Follower:
    """The recorder's side: the shared run, the helper process and what it has been told.

    :meth:`start` moves the run into shared memory (the recorder then fills :attr:`run` and
    :attr:`count`, which replace its own) and starts the helper; :meth:`upto` never blocks;
    :meth:`close` ends the file; :meth:`abandon` stops the helper and removes its unfinished file."""

    def __init__(self, run: Run, count: np.ndarray, proc: subprocess.Popen[bytes], buf: mmap.mmap,
                 written: np.ndarray, out: Path):
        self.run, self.count, self.proc, self.buf, self.written, self.out = run, count, proc, buf, written, out
        self.told = -1
        """The newest tick the helper knows to be whole."""
        self.events = 0
        """How many of the recorder's events it has been given."""
        self.failed = False
        """The helper is gone, or its input could not be written: the recorder writes the file itself."""
        self.cpu = math.nan
        """The helper's CPU time [s], once it has exited."""
        self._pending = bytearray()

    @classmethod
    def start(cls, run: Run, count: np.ndarray, mission: ms.Mission, out: Path) -> "Follower":
        """Share ``run`` and ``count`` and start the helper writing ``out`` (``run.mcap``)."""
        arrays = {name: arr for name, arr in run.arrays().items() if not name.startswith("event_")}
        arrays["count"] = count
        arrays["written"] = np.zeros(1, dtype=np.int64)
        manifest, size = _layout(arrays)
        fd = os.memfd_create("tether-run")
        try:
            os.ftruncate(fd, size)
            buf = mmap.mmap(fd, size)
            views = _views(buf, manifest)
            for name, arr in arrays.items():
                views[name][...] = arr
            count_view, written = views.pop("count"), views.pop("written")
            shared = Run.from_arrays(run.meta, views)
            shared.safety.events = run.safety.events
            head = {"manifest": manifest, "size": size, "fd": fd, "out": str(out),
                    "meta": msgspec.json.encode(run.meta).decode(), "mission": msgspec.json.encode(mission).decode()}
            proc = subprocess.Popen([sys.executable, "-m", "recorder.follow"], stdin=subprocess.PIPE,
                                    stdout=subprocess.DEVNULL, pass_fds=(fd,))
        finally:
            os.close(fd)  # the mapping and the helper keep the memory
        assert proc.stdin is not None  # a pipe
        try:  # room for the whole run's messages: never a blocked recorder
            fcntl.fcntl(proc.stdin.fileno(), fcntl.F_SETPIPE_SZ, PIPE_SIZE)
        except OSError:
            pass
        os.set_blocking(proc.stdin.fileno(), False)
        self = cls(shared, count_view, proc, buf, written, out)
        self._send(head)
        return self

    def _send(self, msg: Any) -> None:
        self._pending += msgspec.json.encode(msg) + b"\n"
        self._flush()

    def _flush(self) -> None:
        if self.failed or not self._pending:
            return
        assert self.proc.stdin is not None
        try:
            n = os.write(self.proc.stdin.fileno(), self._pending)
        except BlockingIOError:
            return  # the helper is behind: said with the next message
        except OSError as exc:  # it is gone (a broken pipe)
            self._fail(f"its input: {exc}")
            return
        del self._pending[:n]

    def _fail(self, why: str) -> None:
        if not self.failed:
            log.warning("run.mcap: its writer (pid %d) failed (%s); the recorder writes it at the end",
                        self.proc.pid, why)
        self.failed = True

    def _new_events(self, events: list[SafetyEvent]) -> list[SafetyEvent]:
        new = events[self.events:]
        self.events = len(events)
        return new

    def upto(self, k: int, events: list[SafetyEvent]) -> None:
        """Every tick up to ``k`` is whole; ``events``: the recorder's (a list that only grows)."""
        if self.failed or k <= self.told:
            return
        if self.proc.poll() is not None:
            self._fail(f"exit {self.proc.returncode}")
            return
        self.told = k
        self._send(_Line(upto=k, events=self._new_events(events)))

    def close(self, run: Run, events: list[SafetyEvent]) -> bool:
        """The run is saved (``run``: its final metadata and gate counts): the helper writes the rest
        and ends the file. True once ``run.mcap`` is complete; False if the helper failed (it is
        stopped, its file removed)."""
        if not self.failed:
            s = run.safety
            self._send(_Line(close=True, meta=msgspec.json.encode(run.meta).decode(),
                             gate_reasons=[] if s.gate_reasons is None else s.gate_reasons.tolist(),
                             gate_counts=[] if s.gate_counts is None else s.gate_counts.tolist(),
                             events=self._new_events(events)))
        assert self.proc.stdin is not None
        if not self.failed:
            os.set_blocking(self.proc.stdin.fileno(), True)
            try:
                self.proc.stdin.write(bytes(self._pending))
                self._pending.clear()
                self.proc.stdin.close()
            except OSError as exc:
                self._fail(f"its input: {exc}")
        if not self.failed:
            try:  # the run is over: it may have the CPU now (a user may raise a priority it lowered)
                os.sched_setscheduler(self.proc.pid, os.SCHED_OTHER, os.sched_param(0))
            except (AttributeError, OSError):
                pass
            code = self._wait(STALL)
            if code is None:
                self._fail(f"no tick written for {STALL:g} s, at {self.ticks_written}")
            elif code != 0 or not self.out.exists():
                self._fail(f"exit {code}")
        if self.failed:
            self.abandon()
            return False
        return True  # the shared memory stays mapped: it holds the recorder's run (closing it under
        # the arrays would leave them pointing at nothing)

    def _wait(self, stall: float) -> int | None:
        """The helper's exit code once it has exited (its CPU time in :attr:`cpu`); None once it has
        written no tick for ``stall`` [s]."""
        seen, since = self.ticks_written, time.monotonic()
        while self.proc.returncode is None:
            pid, status, usage = os.wait4(self.proc.pid, os.WNOHANG)
            if pid:
                self.cpu = usage.ru_utime + usage.ru_stime
                self.proc.returncode = os.waitstatus_to_exitcode(status)
                break
            now, written = time.monotonic(), self.ticks_written
            if written != seen:
                seen, since = written, now
            elif now - since > stall:
                return None
            time.sleep(0.005)
        return self.proc.returncode

    def abandon(self) -> None:
        """Stop the helper; remove its unfinished file."""
        self.failed = True
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdin is not None:
            try:
                self.proc.stdin.close()
            except OSError:
                pass
        self.out.with_name(self.out.name + ".part").unlink(missing_ok=True)

    @property
    def ticks_written(self) -> int:
        """The ticks the helper has written so far."""
        return int(self.written[0])


# =========================================================================== the helper
def main() -> int:
    """The helper: see the module's docstring. Exit 0: ``run.mcap`` written; 3: its input ended
    first (its unfinished file removed); 1: it failed (said on standard error)."""
    from recorder import viz
    from tether.sched import lower_priority

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C reaches the recorder, which says when to end
    lower_priority()
    gc.disable()  # millions of short-lived lists and dicts, no cycles: the collector would cost a third
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s run.mcap writer: %(message)s")
    lines = sys.stdin.buffer
    head = msgspec.json.decode(lines.readline())
    buf = mmap.mmap(head["fd"], head["size"])
    views = _views(buf, head["manifest"])
    count, written = views.pop("count"), views.pop("written")
    run = Run.from_arrays(msgspec.json.decode(head["meta"], type=RunMeta), views)
    mission = msgspec.json.decode(head["mission"], type=ms.Mission)
    out = viz.McapFile(Path(head["out"]), mission)
    events: list[SafetyEvent] = []
    nxt = 0
    try:
        for line in lines:
            msg = _LINE.decode(line)
            events.extend(msg.events)
            for k in range(nxt, msg.upto + 1):
                out.tick(run, k, events)
                written[0] = k + 1
            nxt = max(nxt, msg.upto + 1)
            if msg.close:
                run.meta = msgspec.json.decode(msg.meta, type=RunMeta)
                run.safety.gate_reasons = np.array(msg.gate_reasons, dtype=str)
                run.safety.gate_counts = np.array(msg.gate_counts, dtype=np.int64).reshape(
                    len(run.agent_ids), len(msg.gate_reasons))
                run.safety.events = events
                for k in np.flatnonzero(count[nxt:] > 0).tolist():
                    out.tick(run, nxt + k, events)
                    written[0] = nxt + k + 1
                out.close(dataclasses.replace(run, t=np.where(count > 0, run.t, np.nan)), events)
                return 0
    except Exception:  # noqa: BLE001 - said, and the recorder writes the file itself
        log.exception("failed at tick %d", nxt)
        out.abandon()
        return 1
    out.abandon()
    return 3


if __name__ == "__main__":
    sys.exit(main())
