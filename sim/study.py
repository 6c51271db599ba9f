"""Studies: many independent cells (one mission run each) through any ``concurrent.futures`` executor,
kept as they finish, resumable, with Monte Carlo replicates and their statistics.

* **Cells.** A cell is the TOML text of one mission plus the engine that runs it
  (the ``point`` a study is given, :func:`sim.sweep.run_point`): a pure function of its text. Everything random in a run (random
  disturbances, network models, a Monte Carlo replicate's draws) is seeded from the text, never
  from the worker, the submission order or the clock, so a cell gives the same row wherever it
  runs: inline, in a local process pool or on a Dask cluster.
* **Executors** (:func:`open_executor`): one process at a time inline (``jobs = 1``), a local pool
  of spawned processes (``jobs > 1``; spawned because a Zenoh session or a native library does not
  survive a fork), or ``tcp://HOST:PORT``: a running Dask scheduler, through
  ``distributed.Client(...).get_executor()`` (the optional ``cluster`` extra). Dask re-runs the
  cells of a worker that dies on the workers left.
* **The results file** (:class:`StudyFile`, ``study.jsonl``): a header line with the study key (a
  hash of every cell's text, the engine, the format and numpy's version) and one JSON line per
  finished cell, appended and flushed to disk as each completes. Rerunning the same command skips
  the cells already there; another study in the same directory is refused. A kill mid-write loses
  at most the line being written: a truncated last line is dropped (and cut off) on resume, while
  damage anywhere else is an error naming the line.
* **Monte Carlo** (:func:`replicate`): replicate ``r`` of a mission draws, from
  ``numpy.random.default_rng([seed, r, MC_KEY])``, a new mission seed (every random disturbance
  and network link), a uniform jitter of every agent's start position, and a uniform phase of
  every sinusoidal disturbance; the same replicate of every grid cell uses the same draws
  (common random numbers). :func:`summarise` gives each metric's mean, standard deviation and a
  95 % Student-t confidence interval per cell.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import signal
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, BrokenExecutor, Executor, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from tether import mission as ms

FORMAT = 1
"""Version of the results file's layout (part of the study key)."""

MC_KEY = 0x6D6F6E74
"""Last word of every Monte Carlo replicate's seed (``"mont"``): keeps its draws apart from the
run's own generators (``[seed, agent_id]``, ``[seed, src, dst, "nete"]``)."""

MAX_SEEDS = 10_000
"""Most Monte Carlo replicates of one study."""

MAX_CELLS = 200_000
"""Most cells of one study (grid points times replicates)."""

CONNECT_TIMEOUT_S = 10.0
"""How long ``--executor`` waits for a Dask scheduler to answer and for its first worker."""

US_PER_AGENT_TICK = 85.0
"""Rough cost of one agent's tick in the in-process engine [us] (``bench/sweep_engine.py``: about
335 us per tick of Section 4's four agents): only for the estimates of work in messages."""


class StudyError(ValueError):
    """A study that cannot start or resume: names the option or file and the fix (exit 2)."""


class StudyBroken(RuntimeError):
    """The executor itself failed (a local worker process died, so the pool is unusable): the
    finished cells are kept; rerunning the same command resumes."""


class StudyInterrupted(Exception):
    """Ctrl-C during a study: ``done`` of ``total`` cells are kept in ``path``."""

    def __init__(self, done: int, total: int, path: Path) -> None:
        super().__init__(f"{done} of {total} cells done")
        self.done, self.total, self.path = done, total, path


# --------------------------------------------------------------------------- cells
@dataclass(frozen=True)
class Cell:
    """One run of a study: ``name`` (unique in the study), the mission's TOML ``text``, the engine,
    and ``code``: the version of whatever turns a run into its row (``sim.sweep.METRICS_VERSION``)."""

    name: str
    text: str
    engine: str
    code: str = ""

    @property
    def digest(self) -> str:
        """The cell's identity: a hash of its engine, code version and mission text (its row depends
        on nothing else)."""
        return hashlib.sha256(f"{self.engine}\n{self.code}\n{self.text}".encode()).hexdigest()[:20]


def study_key(cells: Sequence[Cell]) -> str:
    """The key of a study: its cells' identities (in any order), the file format and numpy's version
    (numpy does not promise the same random streams across versions)."""
    h = hashlib.sha256(f"tether-study {FORMAT} numpy {np.__version__}\n".encode())
    for d in sorted(c.digest for c in cells):
        h.update(d.encode() + b"\n")
    return h.hexdigest()[:20]


def worker_id() -> str:
    """Where a cell ran: ``host:pid``."""
    return f"{socket.gethostname()}:{os.getpid()}"


Point = Callable[..., dict]
"""What runs one cell: ``point(text, engine, workdir) -> row``, a module-level function (the
executors pickle it by name), e.g. :func:`sim.sweep.run_point`."""


def run_cell(point: Point, text: str, engine: str, workdir: str | None) -> dict:
    """Run one cell with ``point`` (in whichever process the executor chose): ``{"row", "worker", "wall_s"}``."""
    t0 = time.perf_counter()
    row = point(text, engine, workdir)
    row.pop("wall_s", None)
    return {"row": row, "worker": worker_id(), "wall_s": time.perf_counter() - t0}


# --------------------------------------------------------------------------- Monte Carlo
def replicate(m: ms.Mission, rep: int, p0_jitter: float) -> ms.Mission:
    """Replicate ``rep`` (``>= 0``) of ``m``: a new seed, start positions moved by up to ``p0_jitter``
    [m] per horizontal axis (x, y; the height of a 3D start is kept: vehicles start on the ground),
    and a uniform phase on every sinusoidal disturbance (same amplitude and frequency, so the same
    bound). Draws, in order: the seed, then per agent in file order 3 jitter values and 3 phases
    (always drawn, whatever the dimension and the disturbance, so one agent's draws never shift
    another's)."""
    rng = np.random.default_rng([m.seed, rep, MC_KEY])
    seed = int(rng.integers(0, 2**31 - 1))
    agents = []
    for a in m.agents:
        shift = rng.uniform(-1.0, 1.0, size=3) * p0_jitter
        phase = rng.uniform(0.0, 2.0 * math.pi, size=3)
        p0 = [float(x) for x in a.p0]
        for k in range(min(2, m.dim)):
            p0[k] = float(p0[k] + shift[k])
        dist = a.disturbance
        if isinstance(dist, ms.Sinusoid):
            dist = msgspec.structs.replace(dist, phase=[float(x) for x in phase[: m.dim]])
        agents.append(msgspec.structs.replace(a, p0=p0, disturbance=dist))
    return msgspec.structs.replace(m, seed=seed, agents=agents)


_T975 = (12.706204736, 4.302652730, 3.182446305, 2.776445105, 2.570581836, 2.446911851, 2.364624252,
         2.306004135, 2.262157163, 2.228138852, 2.200985160, 2.178812830, 2.160368656, 2.144786688,
         2.131449546, 2.119905299, 2.109815578, 2.100922040, 2.093024054, 2.085963447, 2.079613845,
         2.073873068, 2.068657610, 2.063898562, 2.059538553, 2.055529439, 2.051830516, 2.048407142,
         2.045229642, 2.042272456)


def t975(df: int) -> float:
    """The 97.5 % quantile of Student's t with ``df`` degrees of freedom (a table to 30, then the
    Cornish-Fisher expansion around the normal quantile, within 1e-6 there)."""
    if df < 1:
        return math.nan
    if df <= len(_T975):
        return _T975[df - 1]
    z, v = 1.959963984540054, float(df)
    return (z + (z**3 + z) / (4 * v) + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * v**2)
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * v**3)
            + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / (92160 * v**4))


def stats(values: Sequence[float | None]) -> dict[str, float | int]:
    """Mean, sample standard deviation and the 95 % Student-t interval of the mean of the finite
    ``values`` (``n`` of them; the interval is NaN below 2)."""
    x = np.array([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    n = int(x.size)
    if n == 0:
        return {"n": 0, "mean": math.nan, "std": math.nan, "ci_lo": math.nan, "ci_hi": math.nan}
    mean = float(x.mean())
    std = float(x.std(ddof=1)) if n > 1 else math.nan
    half = t975(n - 1) * std / math.sqrt(n) if n > 1 else math.nan
    return {"n": n, "mean": mean, "std": std, "ci_lo": mean - half, "ci_hi": mean + half}


def summarise(rows: Sequence[dict], by: Sequence[str], metrics: Sequence[str]) -> list[dict]:
    """One row per distinct value of the ``by`` columns (first-seen order): ``replicates``,
    ``diverged`` (how many), and per metric ``<m>_mean``, ``<m>_std``, ``<m>_ci_lo``, ``<m>_ci_hi``,
    ``<m>_n`` over the replicates that did not diverge."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in by), []).append(r)
    out = []
    for key, members in groups.items():
        row: dict[str, Any] = dict(zip(by, key))
        row["replicates"] = len(members)
        row["diverged"] = sum(bool(r.get("diverged")) for r in members)
        kept = [r for r in members if not r.get("diverged")]
        for m in metrics:
            for k, v in stats([r.get(m) for r in kept]).items():
                row[f"{m}_{k}"] = v
        out.append(row)
    return out


# --------------------------------------------------------------------------- the results file
class StudyFile:
    """``study.jsonl`` of one study (see the module docstring). :meth:`open` checks or writes the
    header and returns the finished cells; :meth:`append` adds one, on disk before it returns."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd: int | None = None

    def check(self, key: str) -> None:
        """Raise :class:`StudyError` when the file exists and belongs to another study (reads its header)."""
        if self.path.exists() and self.path.stat().st_size > 0:
            with open(self.path, "rb") as f:
                first = f.readline()
            self._check_header(first, key)

    def _check_header(self, first: bytes, key: str) -> None:
        try:
            head = json.loads(first) if first.endswith(b"\n") else None
        except ValueError:
            head = None
        if not isinstance(head, dict) or "study" not in head:
            raise StudyError(f"{self.path}: not a study results file (its first line is no study header); "
                             "remove it or give another --out")
        if head["study"] != key:
            raise StudyError(f"--out: {self.path.parent} holds another study (key {head['study']}, mission "
                             f"{head.get('meta', {}).get('mission')!r}); this command is study {key}. Give a new "
                             "--out, or remove that directory's study.jsonl to start over")

    def open(self, key: str, meta: dict) -> dict[str, dict]:
        """Start or resume the study ``key``: the records of its finished cells by digest. Raises
        :class:`StudyError` for another study's file or a damaged one."""
        done: dict[str, dict] = {}
        if not self.path.exists() or self.path.stat().st_size == 0:
            tmp = self.path.with_name(self.path.name + ".tmp")
            tmp.write_text(json.dumps({"study": key, "format": FORMAT, "meta": meta}) + "\n")
            os.replace(tmp, self.path)
        else:
            data = self.path.read_bytes()
            lines = data.split(b"\n")
            tail = lines.pop()  # b"" when the file ends with a newline, else a line cut short
            good = len(data) - len(tail)
            self._check_header(lines[0] + b"\n" if lines else tail, key)
            for no, line in enumerate(lines[1:], start=2):
                try:
                    rec = json.loads(line)
                    done[rec["digest"]] = rec
                except (ValueError, KeyError, TypeError):
                    if no == len(lines) and not tail:  # the last complete line is damaged: a cut-off write
                        good -= len(line) + 1
                        break
                    raise StudyError(f"{self.path}: line {no} is damaged (not a cell record); remove that line "
                                     "or the file (its cells are then run again)") from None
            if good < len(data):  # a write cut short by a kill: dropped, and cut off before appending
                with open(self.path, "r+b") as f:
                    f.truncate(good)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND)
        return done

    def append(self, record: dict) -> None:
        """One finished cell, as one line written at once and synced to disk."""
        if self._fd is None:
            raise RuntimeError("StudyFile.append before open")
        os.write(self._fd, (json.dumps(record, allow_nan=True) + "\n").encode())
        os.fsync(self._fd)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


# --------------------------------------------------------------------------- executors
def _worker_init(pid: int) -> None:
    """In a local pool's worker: leave Ctrl-C to the study (which keeps what is done and stops the
    pool), and exit as soon as the study that started it is gone."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == pid:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="follow-parent").start()


class InlineExecutor(Executor):
    """Runs each cell when it is submitted, in this process (``jobs = 1``)."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except Exception as exc:  # a cell's failure is its future's, as in any executor
            fut.set_exception(exc)
        return fut


def check_address(address: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` -> ``(HOST, PORT)``; raises :class:`StudyError` naming ``--executor``."""
    fix = "give the scheduler's address as tcp://HOST:PORT (e.g. tcp://127.0.0.1:8786), or leave --executor out"
    if not address.startswith("tcp://"):
        raise StudyError(f"--executor: {address!r} is not a Dask scheduler address; {fix}")
    host, _, port = address[len("tcp://"):].rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise StudyError(f"--executor: {address!r} has no HOST:PORT with a port 1-65535; {fix}")
    return host, int(port)


@dataclass
class Engine:
    """An open executor and what to say about it."""

    executor: Executor
    kind: str
    """``inline``, ``local`` or ``dask``."""
    workers: int
    client: Any = None


@contextmanager
def open_executor(address: str | None, jobs: int, timeout: float = CONNECT_TIMEOUT_S) -> Iterator[Engine]:
    """The executor of a study: inline (``jobs = 1``), a spawned local pool of ``jobs`` processes, or
    the Dask scheduler at ``address`` (``tcp://HOST:PORT``). Raises :class:`StudyError` when the
    address is malformed, ``distributed`` is not installed, or no scheduler (or no worker) answers
    within ``timeout`` seconds."""
    if address is None:
        if jobs <= 1:
            yield Engine(InlineExecutor(), "inline", 1)
            return
        pool = ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"), initializer=_worker_init,
                                   initargs=(os.getpid(),))
        try:
            yield Engine(pool, "local", jobs)
        finally:
            procs = list(getattr(pool, "_processes", {}).values())  # the pool's own workers
            pool.shutdown(wait=False, cancel_futures=True)
            for p in procs:
                if p.is_alive():
                    p.terminate()
            for p in procs:
                p.join(timeout=5.0)
        return
    check_address(address)
    try:
        from distributed import Client
    except ImportError:
        raise StudyError("--executor: Dask's distributed is not installed; pip install 'tether[cluster]' "
                         "(or leave --executor out to use local processes)") from None
    try:
        client = Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as exc:
        raise StudyError(f"--executor: no Dask scheduler answered at {address} within {timeout:g} s "
                         f"({type(exc).__name__}); start one (dask scheduler --port PORT, then dask worker "
                         f"{address}) or leave --executor out to use local processes") from None
    try:
        try:
            client.wait_for_workers(1, timeout=timeout)
        except (OSError, TimeoutError):
            raise StudyError(f"--executor: the Dask scheduler at {address} has no worker after {timeout:g} s; "
                             f"start some (dask worker {address}) and run again") from None
        n = len(client.scheduler_info(n_workers=-1).get("workers", {}))
        yield Engine(client.get_executor(), "dask", n, client)
    finally:
        client.close()


# --------------------------------------------------------------------------- running a study
Progress = Callable[..., None]


class _HeldInterrupt:
    """Ctrl-C held off while a finished cell is written and counted, then raised: the file and the
    count a study reports on interrupt always agree. Elsewhere (waiting on the workers) Ctrl-C
    raises at once. Only where Python's own Ctrl-C handler is in place, on the main thread; anywhere
    else the handler is left alone and nothing is held."""

    def __init__(self) -> None:
        self._held = False
        self._pending = False
        self._old: Any = None

    def __enter__(self) -> _HeldInterrupt:
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._old = signal.signal(signal.SIGINT, self._on_sigint)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None

    def _on_sigint(self, signum: int, frame: object) -> None:
        if self._held:
            self._pending = True
        else:
            raise KeyboardInterrupt

    def hold(self) -> None:
        self._held = True

    def release(self) -> None:
        """End the hold; a Ctrl-C that came during it is raised now."""
        self._held = False
        if self._pending:
            self._pending = False
            raise KeyboardInterrupt


@dataclass
class Outcome:
    """A study's result: ``records`` by digest (every finished cell, resumed ones included), the
    ``failed`` cells (name -> error), how many cells this invocation ran, and per-worker counts."""

    records: dict[str, dict]
    failed: dict[str, str]
    ran: int
    resumed: int
    per_worker: Counter
    wall_s: float


def run(cells: Sequence[Cell], results: StudyFile, engine: Engine, point: Point, *, meta: dict,
        workdir: Callable[[Cell], str | None] = lambda c: None, progress: Progress | None = None,
        stop_after: int | None = None) -> Outcome:
    """Run every cell of ``cells`` not already in ``results`` through ``engine`` with ``point``, appending each as it
    finishes. ``progress(done, total, label, note=...)`` is told after each. Ctrl-C (or
    ``stop_after`` cells run, for measurements) raises :class:`StudyInterrupted` with what is kept."""
    key = study_key(cells)
    done = results.open(key, meta)
    by_digest = {c.digest: c for c in cells}
    done = {d: r for d, r in done.items() if d in by_digest}
    total, resumed = len(cells), len(done)
    failed: dict[str, str] = {}
    per_worker: Counter = Counter()
    ran = 0
    t0 = time.perf_counter()

    def tell() -> None:
        if progress is not None:
            note = f"{engine.workers} worker{'s' if engine.workers != 1 else ''}, {len(failed)} failed"
            if per_worker:
                note += " (" + ", ".join(f"{w.rsplit(':', 1)[-1]}: {k}" for w, k in sorted(per_worker.items())) + ")"
            progress(len(done), total, "study", note=note)

    todo = [c for c in cells if c.digest not in done]
    pending: dict[Future, Cell] = {}
    tell()
    with _HeldInterrupt() as sigint:
        try:
            it = iter(todo)
            # keep a bounded queue in flight: twice the workers, so an interrupt loses little and a
            # long study does not hold every future at once
            window = max(2 * engine.workers, 2) if engine.kind != "inline" else 1
            while True:
                while len(pending) < window:
                    c = next(it, None)
                    if c is None:
                        break
                    pending[engine.executor.submit(run_cell, point, c.text, c.engine, workdir(c))] = c
                if not pending:
                    break
                finished, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                for fut in finished:
                    c = pending.pop(fut)
                    try:
                        res = fut.result()
                    except BrokenExecutor:
                        raise
                    except Exception as exc:  # the cell raised, or the engine gave up on it (a KilledWorker)
                        failed[c.name] = f"{type(exc).__name__}: {exc}"
                        continue
                    rec = {"digest": c.digest, "cell": c.name, "row": res["row"], "worker": res["worker"],
                           "wall_s": res["wall_s"]}
                    sigint.hold()  # written and counted together, or neither
                    results.append(rec)
                    done[c.digest] = rec
                    per_worker[res["worker"]] += 1
                    ran += 1
                    sigint.release()
                    tell()
                    if stop_after is not None and ran >= stop_after:
                        raise KeyboardInterrupt
        except KeyboardInterrupt:
            for fut in pending:
                fut.cancel()
            results.close()
            raise StudyInterrupted(len(done), total, results.path) from None
        except BrokenExecutor as exc:
            results.close()
            raise StudyBroken(f"the {engine.kind} executor broke ({exc}); {len(done)} of {total} cells done and kept "
                              f"in {results.path}; run the same command again to resume") from None
    results.close()
    return Outcome(done, failed, ran, resumed, per_worker, time.perf_counter() - t0)


def estimate(m: ms.Mission, cells: int) -> str:
    """A rough cost of ``cells`` runs of ``m`` on one core, for messages."""
    s = cells * m.steps * m.n * US_PER_AGENT_TICK * 1e-6
    return f"about {s / 3600:.3g} CPU-hours" if s >= 3600 else f"about {s:.3g} CPU-seconds"
