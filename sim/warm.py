"""Compile once per machine: the compiled engines' first use, serialised by a lock file.

numba compiles a kernel at its first call in a process and writes it to its cache (``cache=True``);
a later process loads it from there. Processes that start before the cache is written (a study's
workers, several Dask workers on one host, two commands at once) each compiled the same kernels,
each paying the whole compile on a shared CPU. Here the first compile of each part (:data:`PARTS`:
a run compiles only its own) happens under a lock file beside the compile cache, and a mark says
when it is done; a part already marked costs a ``stat``:

* the in-process lockstep engine (:func:`first_run`): a cold run is itself the compile, under the
  lock; the other processes wait for it and load the kernels from the cache;
* the reference simulator, discrete mode, a short run (:func:`compiled_or_background`): it runs on
  the numpy path (the same run bit for bit) while a detached ``python -m sim.warm`` compiles the
  part for the next run;
* the reference simulator otherwise (:func:`warm_refsim`): a few ticks of the caller's own run
  compile the part under the lock (the run's own argument types), then the run goes on.

    python -m sim.warm [MISSION] [--parts refsim-discrete refsim-continuous lockstep]

compiles the parts ahead of any run (at install, on a CI runner, on each host of a Dask cluster
before its first study): blocks until they are in the cache. :func:`prewarm` does it in the
background, once per machine, from the first commands a new user runs (``tether demo`` among them).

The mark is keyed on the kernels' sources, the law's source, numba's and Python's versions and
the cache location; if numba's cache is removed while the mark stays, a run compiles as it would
without this module.
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import inspect
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from sim import jitcache, lawkernels

PARTS = ("refsim-discrete", "refsim-discrete-parallel", "refsim-continuous", "lockstep")
"""The compiled pieces a run may need, each warmed on its own (a run compiles only its own)."""

_TEMPLATE = {"refsim-discrete": "sim.kernel", "refsim-discrete-parallel": "sim.kernel",
             "refsim-continuous": "sim.kernel", "lockstep": "sim.lockstep_kernel"}

WARMUP_TICKS = 5
"""Ticks of the caller's run that the compiling process runs (enough to call every kernel once)."""

T = TypeVar("T")

_DONE: set[str] = set()  # keys marked in this process: a sweep worker's later cells skip the stat


def marks_dir() -> Path:
    """Where the marks and lock files go: beside the generated law modules (``$TETHER_CACHE/warm``)."""
    return lawkernels.cache_dir().parent / "warm"


_KEYS: dict[tuple[str, type, str], str] = {}  # hashing the sources once per process, not per sweep cell


def key(part: str, law: Any) -> str:
    """The mark's name for ``part`` compiled for ``law`` (a :class:`agent.laws.FormationLaw`)."""
    memo = (part, type(law), os.environ.get("NUMBA_CACHE_DIR", ""))
    if memo not in _KEYS:
        _KEYS[memo] = _key(part, law)
    return _KEYS[memo]


def _key(part: str, law: Any) -> str:
    import numba

    template = sys.modules.get(_TEMPLATE[part]) or __import__(_TEMPLATE[part], fromlist=["_"])
    h = hashlib.sha256()
    for text in (part, numba.__version__, sys.version, os.environ.get("NUMBA_CACHE_DIR", ""),
                 str(inspect.getsourcefile(template)), inspect.getsource(template), jitcache.digest(),
                 inspect.getsource(sys.modules[type(law).__module__])):
        h.update(text.encode())
        h.update(b"\0")
    return f"{part}-{h.hexdigest()[:20]}"


def is_warm(part: str, law: Any) -> bool:
    """Whether ``part``'s kernels for ``law`` are marked compiled on this machine (does not block)."""
    k = key(part, law)
    return k in _DONE or (marks_dir() / f"{k}.done").exists()


def first_run(part: str, law: Any, run: Callable[[], T]) -> T:
    """``run()``, the caller's run on ``part``'s kernels for ``law``; where they are not marked
    compiled on this machine, under the lock (**blocks** while another process compiles them), so
    that its first call compiles them for every process and no warm-up run is needed (its own
    argument types, its own ticks). A process that waited loads them from the cache."""
    box: list[T] = []
    ensure(part, law, lambda: box.append(run()))
    return box[0] if box else run()


def ensure(part: str, law: Any, compile_: Callable[[], object]) -> bool:
    """Make sure ``part``'s kernels for ``law`` are in the compile cache, compiling them here (by
    calling ``compile_``, a few ticks of the caller's run) only if no other process has: **blocks**
    while another process holds the lock (it is compiling them). Returns True if this process
    compiled them. Where the lock file cannot be made (a read-only cache), returns False at once
    and the caller's own first call compiles, as without this module."""
    k = key(part, law)
    if k in _DONE:
        return False
    folder = marks_dir()
    mark = folder / f"{k}.done"
    if mark.exists():
        _DONE.add(k)
        return False
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"{k}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # the lock goes with the process: a killed compiler frees it
        if mark.exists():  # another process compiled them while this one waited
            _DONE.add(k)
            return False
        compile_()
        tmp = folder / f"{k}.{os.getpid()}.tmp"
        tmp.write_text(f"{part}\n", encoding="utf-8")
        os.replace(tmp, mark)
        _DONE.add(k)
        return True
    finally:
        os.close(fd)  # closing the descriptor releases the lock


NUMPY_WHILE_COLD = (30_000, 50)
"""The largest discrete run (ticks, agents) that ``engine="auto"`` runs on the numpy path while its
kernels are not compiled yet. The numpy loop's cost is mostly a fixed cost per tick up to tens of
agents, about 70 us of CPU; the discrete kernel's compile costs about 9 s of CPU, some 120 000
ticks (bench/coldstart.py). 30 000 ticks keep a cold run within about 2 s of CPU of a warm one;
a longer run waits for the compile."""


def compiled_or_background(s: Any, mode: str, threads: int, steps: int) -> bool:
    """For ``engine="auto"``: whether a reference-simulator run takes the compiled kernels now.
    False for a short discrete run whose kernels are not compiled on this machine yet: the numpy
    path (the same run bit for bit) runs it, and a detached ``python -m sim.warm`` compiles them
    for the next run, unless another process already is. Does not block."""
    if mode != "discrete" or steps > NUMPY_WHILE_COLD[0] or s.mission.n > NUMPY_WHILE_COLD[1]:
        return True
    part = refsim_part(mode, threads)
    k = key(part, s.bound.law)
    if k in _DONE or (marks_dir() / f"{k}.done").exists():
        return True
    try:
        folder = marks_dir()
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(folder / f"{k}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return True  # no cache to coordinate in: compile here, as without this module
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False  # being compiled by another process
    finally:
        os.close(fd)  # free it for the compiler (two started at once: the second finds the mark)
    from tether import mission as ms

    text = folder / f"{k}.{os.getpid()}.toml"
    try:
        text.write_text(ms.dumps(s.mission), encoding="utf-8")
        subprocess.Popen([sys.executable, "-m", "sim.warm", str(text), "--parts", part, "--remove-mission"],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True)  # outlives this command: the compile is for the next run
    except OSError:
        return True  # no background compile to be had: compile here
    return False


PREWARM = ("lockstep", "refsim-discrete")
"""The parts :func:`prewarm` compiles: what a first ``tether simulate``, ``sweep`` and ``montecarlo``
of a shipped mission take (Section 4's law)."""
PREWARM_MISSION = "section4"


def prewarm_stamp() -> Path:
    """The file :func:`prewarm` leaves once this machine's compile cache holds :data:`PREWARM`:
    named by the kernels' sources (:func:`sim.jitcache.digest`: no import of numba), the Python
    version and the cache location, so that an edit or another cache compiles again."""
    h = hashlib.sha256()
    h.update(f"{jitcache.digest()}\0{sys.version}\0{os.environ.get('NUMBA_CACHE_DIR', '')}\0"
             f"{lawkernels.cache_dir()}".encode())
    return marks_dir() / f"prewarm-{h.hexdigest()[:20]}.done"


def prewarm(idle: bool = False) -> bool:
    """Compile :data:`PREWARM` for this machine in the background, once: unless the stamp says it is
    done (a ``stat``), start a detached ``python -m sim.warm`` that outlives the command and leaves the
    stamp, at ``nice`` 10, or with ``idle`` at idle CPU priority (``SCHED_IDLE``: it takes only what
    nothing else wants, so that a real-time swarm beside it is not disturbed). Called by the commands
    a new user runs first (``tether demo``, ``simulate``, ``run``, ``check``): the first study then
    finds its kernels compiled. ``TETHER_PREWARM=0`` turns it off. Returns whether a compile was
    started. Does not block."""
    if os.environ.get("TETHER_PREWARM", "1") == "0":
        return False
    try:
        stamp = prewarm_stamp()
        if stamp.exists():
            return False
        stamp.parent.mkdir(parents=True, exist_ok=True)
        subprocess.Popen([sys.executable, "-m", "sim.warm", PREWARM_MISSION, "--parts", *PREWARM, "--stamp", str(stamp)],
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True, preexec_fn=_idle if idle else _nice)  # noqa: PLW1509
    except OSError:
        return False  # no cache to write or no process to start: the first study compiles, as before
    return True


def _nice() -> None:  # runs in the child between fork and exec: a scheduler call only
    os.nice(10)


def _idle() -> None:  # runs in the child between fork and exec: a scheduler call only
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (OSError, AttributeError):
        os.nice(19)


def refsim_part(mode: str, threads: int) -> str:
    """The part a reference-simulator run in ``mode`` with ``threads`` takes."""
    if mode == "continuous":
        return "refsim-continuous"
    return "refsim-discrete" if threads <= 1 else "refsim-discrete-parallel"


def warm_refsim(s: Any, mode: str, threads: int, meta: Any) -> bool:
    """:func:`ensure` for a reference-simulator run of setup ``s`` (:class:`sim.setup.Setup`):
    compiles with a few of its ticks. **Blocks** while another process compiles."""
    from sim import fast

    def compile_() -> object:
        if mode == "continuous":
            return fast.continuous(s, WARMUP_TICKS, 1, False, None, meta)
        return fast.discrete(s, WARMUP_TICKS, False, None, meta, threads)

    return ensure(refsim_part(mode, threads), s.bound.law, compile_)


def warm_lockstep(m: Any) -> bool:
    """:func:`ensure` for an in-process lockstep run of mission ``m``: compiles with a whole run of
    ``m`` (a few ticks may stop before a delayed link's first message; nothing where the compiled twin
    cannot run ``m``). **Blocks** while another process compiles."""
    from agent import laws
    from sim import lockstep_kernel

    if lockstep_kernel.unsupported(m) is not None:
        return False
    return ensure("lockstep", laws.of_mission(m).law, lambda: lockstep_kernel.simulate(m, record=False))


def warm(m: Any, parts: tuple[str, ...] = ("refsim-discrete", "refsim-continuous", "lockstep")) -> dict[str, bool]:
    """Compile ``parts`` for mission ``m`` (its law) ahead of any run; **blocks** until they are in the
    cache. Returns, per part, whether this process compiled it."""
    from sim import kernel
    from sim.setup import Setup, check_continuous
    from tether.runfile import RunMeta

    done: dict[str, bool] = {}
    if not kernel.AVAILABLE:
        return done
    for part in parts:
        if part == "lockstep":
            done[part] = warm_lockstep(m)
            continue
        mode = "continuous" if part == "refsim-continuous" else "discrete"
        if mode == "continuous":
            try:
                check_continuous(m)
            except ValueError:
                continue
        setup = Setup.of(m)
        meta = RunMeta(mission=m.name, source="reference-continuous" if mode == "continuous" else "reference-discrete",
                       law=setup.bound.law.name, rate=m.rate, steps=WARMUP_TICKS, seed=m.seed,
                       law_state=setup.bound.law.state, law_units=setup.bound.units)
        done[part] = warm_refsim(setup, mode, 2 if part.endswith("parallel") else 1, meta)
    return done


def main(argv: list[str] | None = None) -> None:
    """``python -m sim.warm``: compile the kernels a mission's runs take; blocks until done."""
    from tether import catalog
    from tether import mission as ms

    ap = argparse.ArgumentParser(prog="python -m sim.warm", description=__doc__.splitlines()[0])
    ap.add_argument("mission", nargs="?", default="section4", help="a mission file or built-in name")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=["refsim-discrete", "refsim-continuous", "lockstep"])
    ap.add_argument("--remove-mission", action="store_true", help="remove the mission file once read")
    ap.add_argument("--stamp", default=None, help="a file to create once every part is compiled (prewarm)")
    a = ap.parse_args(argv)
    path = catalog.resolve(a.mission)
    m = ms.load(path)
    if a.remove_mission:
        path.unlink(missing_ok=True)
    for part, compiled in warm(m, tuple(a.parts)).items():
        print(f"{part}: {'compiled' if compiled else 'already in the cache'}")
    if a.stamp is not None:
        Path(a.stamp).touch()


if __name__ == "__main__":
    main()
