"""Process statistics for the benchmarks, read from ``/proc``: a process's CPU (whole and by
thread kind), memory and threads, the whole machine's load, and the measured window of one run
(:class:`Window` around :class:`Proc` snapshots, into a :class:`Result`). Linux only.

CPU is read from ``/proc/<pid>/stat`` in clock ticks (:data:`CLK_TCK`, 10 ms on most systems), so
a figure over a window of a few seconds is good to about a percent of one core.
"""

from __future__ import annotations

import os
import queue
import re
import statistics
import subprocess
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_times(pid: int) -> tuple[float, float] | None:
    """(utime, stime) of ``pid`` [s] (``/proc/<pid>/stat`` fields 14, 15), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            rest = fh.read().rpartition(")")[2].split()
        return int(rest[11]) / CLK_TCK, int(rest[12]) / CLK_TCK
    except (OSError, IndexError, ValueError):
        return None


def thread_cpu(pid: int) -> dict[int, tuple[str, float]] | None:
    """CPU time [s] of every thread of ``pid``: tid -> (kind, seconds), kind ``main`` (the asyncio
    thread), ``zenoh`` (Zenoh's runtime threads: ``app-*``, ``rx-*``, ``tx-*``, ``net-*``, ``acc-*``)
    or ``callback`` (the other Python threads: zenoh-python runs one per subscriber callback)."""
    out = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as fh:
                comm = fh.read().strip()
            with open(f"/proc/{pid}/task/{tid}/stat") as fh:
                rest = fh.read().rpartition(")")[2].split()
        except OSError:
            continue
        if int(tid) == pid:
            kind = "main"
        elif re.match(r"(app|rx|tx|net|acc)-\d+$", comm):
            kind = "zenoh"
        else:
            kind = "callback"
        out[int(tid)] = (kind, (int(rest[11]) + int(rest[12])) / CLK_TCK)
    return out


def memory_kib(pid: int) -> dict[str, int] | None:
    """Rss, Pss (shared pages divided among their users) and USS (private pages) of ``pid`` [KiB],
    from ``/proc/<pid>/smaps_rollup``."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            f = {line.split(":")[0]: int(line.split()[1]) for line in fh if line.split(":")[0] in
                 ("Rss", "Pss", "Private_Clean", "Private_Dirty")}
    except (OSError, ValueError, IndexError):
        return None
    return {"rss": f["Rss"], "pss": f["Pss"], "uss": f["Private_Clean"] + f["Private_Dirty"]}


def threads(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return None


def machine_jiffies() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine since boot (``/proc/stat``, first line)."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    idle = f[3] + (f[4] if len(f) > 4 else 0)  # idle + iowait
    return sum(f) - idle, sum(f)


def busy_cores(seconds: float = 1.0) -> float:
    """Cores' worth of CPU the whole machine used over the next ``seconds`` (blocks that long)."""
    b0, _ = machine_jiffies()
    time.sleep(seconds)
    b1, _ = machine_jiffies()
    return (b1 - b0) / CLK_TCK / seconds


def wait_quiet(limit: float, timeout: float) -> float:
    """Wait (up to ``timeout`` s) until the machine uses less than ``limit`` cores with none of our runs
    going, so that another user's burst does not land in a measurement; returns the last reading."""
    deadline = time.monotonic() + timeout
    busy = busy_cores()
    while busy > limit and time.monotonic() < deadline:
        busy = busy_cores(2.0)
    return busy


def rss_kib(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def children_of(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    if int(fh.read().rpartition(")")[2].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, IndexError, ValueError):
                pass
    return out


def reap(proc: subprocess.Popen[str], timeout: float) -> None:
    """Wait up to ``timeout`` [s] for ``proc`` to end by itself, then kill it."""
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return [a.decode() for a in fh.read().split(b"\0") if a]
    except OSError:
        return []


@dataclass
class Proc:
    """One measured process: its role and id, CPU [s] and RSS [KiB] at the two snapshots."""

    pid: int
    role: str
    nid: int
    cpu0: tuple[float, float] | None = None
    cpu1: tuple[float, float] | None = None
    rss: int | None = None
    threads: int | None = None

    th0: dict[int, tuple[str, float]] | None = None
    th1: dict[int, tuple[str, float]] | None = None
    mem: dict[str, int] | None = None
    """Rss/Pss/USS [KiB], read now and then during the window (the last reading kept)."""

    def snap_mem(self) -> None:
        mem = memory_kib(self.pid)
        if mem is not None:
            self.mem = mem

    def snap0(self) -> None:
        self.cpu0 = cpu_times(self.pid)
        self.th0 = thread_cpu(self.pid)

    def snap1(self) -> None:
        """Read the end of the window; a process already gone keeps its last sampled values."""
        cpu, rss, nth = cpu_times(self.pid), rss_kib(self.pid), threads(self.pid)
        th = thread_cpu(self.pid)
        if cpu is not None and rss is not None and nth is not None and th is not None:
            self.cpu1, self.rss, self.threads = cpu, rss, nth
            self.th1 = {**(self.th1 or {}), **th}  # threads that ended keep their last reading

    def by_thread(self) -> dict[str, float]:
        """CPU over the window [s] by thread kind (see :func:`thread_cpu`)."""
        out = {"main": 0.0, "callback": 0.0, "zenoh": 0.0}
        if self.th0 is None or self.th1 is None:
            return {k: float("nan") for k in out}
        for tid, (kind, sec) in self.th1.items():
            out[kind] += sec - self.th0.get(tid, (kind, 0.0))[1]
        return out

    @property
    def cpu(self) -> float:
        """CPU time over the window [s]."""
        return self.user + self.system

    @property
    def user(self) -> float:
        if self.cpu0 is None or self.cpu1 is None:
            return float("nan")
        return self.cpu1[0] - self.cpu0[0]

    @property
    def system(self) -> float:
        if self.cpu0 is None or self.cpu1 is None:
            return float("nan")
        return self.cpu1[1] - self.cpu0[1]


class Sampler:
    """Samples every process's end-of-window figures every ``period`` s while the window is open, so
    that a process that exits just before the window closes (its last tick done) is still counted."""

    def __init__(self, procs: list[Proc], period: float = 0.1) -> None:
        self.procs, self.period = procs, period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        n = 0
        while not self._stop.wait(self.period):
            n += 1
            for p in self.procs:
                p.snap1()
                if n % 10 == 1:
                    p.snap_mem()

    def stop(self) -> None:
        """Close the window: one last reading of every live process."""
        self._stop.set()
        self._thread.join()
        for p in self.procs:
            p.snap1()
            p.snap_mem()


class Window:
    """The measured window of one run: every process's CPU, and the whole machine's."""

    def __init__(self, procs: list[Proc]) -> None:
        self.procs = procs
        self.sampler = Sampler(procs)

    def open(self) -> None:
        self.t0 = time.monotonic()
        self.m0 = machine_jiffies()[0]
        for p in self.procs:
            p.snap0()
        self.sampler.start()

    def close(self, res: "Result") -> None:
        self.sampler.stop()
        res.window_s = time.monotonic() - self.t0
        machine = 100 * (machine_jiffies()[0] - self.m0) / CLK_TCK / res.window_s
        mine = sum(100 * p.cpu / res.window_s for p in self.procs if p.cpu == p.cpu)
        res.foreign_pct = max(0.0, machine - mine)  # both are read at 10 ms granularity


@dataclass
class Result:
    """One run (tether or baseline)."""

    kind: str
    n: int
    clock: str
    rate: float
    ok: bool = True
    why: str = ""
    status: int = 0
    """tether run's exit status (5: recorded, but samples are missing; the run itself went to its end)."""
    mission_s: float = float("nan")
    wall_s: float = float("nan")
    startup_s: float = float("nan")
    window_s: float = float("nan")
    """Wall time between the two CPU snapshots [s]."""
    foreign_pct: float = float("nan")
    """CPU used by everything else on the machine during the window [% of one core]: noise."""
    procs: list[Proc] = field(default_factory=list)
    late: float = float("nan")
    """Late ticks / agent ticks (real time)."""
    late_max: float = float("nan")
    link_age: np.ndarray | None = None
    meas_age: np.ndarray | None = None
    probe: dict[str, Any] | None = None
    complete: str = ""
    command_s: float = float("nan")
    """The whole ``tether run`` command's wall time [s], start-up and end included."""
    end_s: float = float("nan")
    """Wall time from the launcher's "ran ..." line (the last tick) to the command's exit [s]: the
    files' end (``run.npz``, ``run.mcap``) and the processes' exits."""
    cwds: set[str] = field(default_factory=set)
    """The working directories of tether's processes (which checkout they import: ``run_tether``)."""

    @property
    def ran_to_end(self) -> bool:
        """The run went to its end: clean, or recorded with samples lost on the way (exit 5)."""
        return self.ok or self.status == 5

    @property
    def speed(self) -> float:
        return self.mission_s / self.wall_s

    def cpu_pct(self, role: str | None = None) -> list[float]:
        """CPU per process over the window [% of one core]; every measured role but the probe by default."""
        return [100 * p.cpu / self.window_s for p in self.procs
                if (role is None and p.role != "probe") or p.role == role]

    def thread_pct(self, role: str) -> dict[str, float]:
        """Median over the role's processes of CPU by thread kind [% of one core]."""
        rows = [p.by_thread() for p in self.procs if p.role == role]
        return {k: med([100 * r[k] / self.window_s for r in rows]) for k in ("main", "callback", "zenoh")}

    def total_cpu_pct(self) -> float:
        return float(sum(x for x in self.cpu_pct() if x == x))

    def mem_mib(self, role: str, kind: str) -> list[float]:
        """``kind``: rss, pss or uss of the role's processes [MiB]."""
        return [p.mem[kind] / 1024 for p in self.procs if p.role == role and p.mem is not None]


# =========================================================================== helpers
def read_lines(stream: Iterable[str], q: queue.Queue[str | None]) -> None:
    """Thread body: put every line of a child's ``stream`` on ``q``, then None when it closes."""
    for line in stream:
        q.put(line)
    q.put(None)


def med(xs: list[float]) -> float:
    xs = [x for x in xs if x == x]
    return statistics.median(xs) if xs else float("nan")


def pct(xs: Sequence[float] | np.ndarray, q: float) -> float:
    arr = np.asarray(xs, dtype=float)
    return float(np.percentile(arr, q)) if arr.size else float("nan")


def ratio(a: float, b: float) -> float:
    return a / b if b else float("nan")
