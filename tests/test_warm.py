"""sim.warm: processes that start cold at once compile the engines once, and get the same runs.

Real processes, each with the same private compile caches (``NUMBA_CACHE_DIR``, ``TETHER_CACHE``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support import wait_until

ROOT = Path(__file__).resolve().parents[1]

# holds the lock: its compile_ says it started, then waits for the test's "go" file
LOCKER = """
import json, sys, time
from pathlib import Path
from agent import laws
from sim import warm
from tether import catalog, mission as ms
box = Path(sys.argv[1])
law = laws.of_mission(ms.load(catalog.builtin_path("section4"))).law
calls = []
def compile_():
    calls.append(1)
    (box / f"started-{sys.argv[2]}").write_text("")
    deadline = time.monotonic() + 120
    while not (box / "go").exists():  # the test's condition, bounded
        if time.monotonic() > deadline:
            raise SystemExit("no go")
        time.sleep(0.02)
compiled = warm.ensure("lockstep", law, compile_)
print(json.dumps({"compiled": compiled, "calls": len(calls)}))
"""

# a cold lockstep run: whether this process compiled, the kernel's cache misses, the run's bytes
RUNNER = """
import hashlib, json
from tether import catalog, mission as ms
from sim import lockstep, lockstep_kernel, warm
m = ms.load(catalog.builtin_path("section4"))
compiled = warm.warm_lockstep(m)
run = lockstep.simulate(m, duration=2.0)
misses = sum(lockstep_kernel._ticks.stats.cache_misses.values())
digest = hashlib.sha256(b"".join(x.tobytes() for x in (run.p, run.v, run.u, run.xi, run.zeta))).hexdigest()
print(json.dumps({"compiled": compiled, "misses": misses, "digest": digest}))
"""


def _env(cache: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(ROOT), NUMBA_CACHE_DIR=str(cache / "numba"),
                TETHER_CACHE=str(cache / "tether"))


def _start(code: str, cache: Path, *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=ROOT, env=_env(cache),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _result(p: subprocess.Popen[str], timeout: float) -> dict:
    out, err = p.communicate(timeout=timeout)
    assert p.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def test_a_second_process_waits_for_the_first_ones_compile(tmp_path: Path) -> None:
    """B starts while A holds the lock (A's compile is under way): B must not compile, whatever the
    timing, because the mark appears only after A is told to go."""
    pytest.importorskip("numba")

    a = _start(LOCKER, tmp_path, str(tmp_path), "a")
    wait_until(lambda: (tmp_path / "started-a").exists() or a.poll() is not None, 300, "A to take the lock")
    assert a.poll() is None, a.communicate()[1][-3000:]
    b = _start(LOCKER, tmp_path, str(tmp_path), "b")
    (tmp_path / "go").write_text("")
    ra, rb = _result(a, 300), _result(b, 300)
    assert ra == {"compiled": True, "calls": 1}
    assert rb == {"compiled": False, "calls": 0}
    assert not (tmp_path / "started-b").exists()


@pytest.mark.slow
def test_two_cold_processes_compile_once_and_agree(tmp_path: Path) -> None:
    """Two cold lockstep runs at once on one cache: one compiles (numba cache misses), the other
    loads the kernels from the cache (no misses); both runs are the same bit for bit."""
    pytest.importorskip("numba")
    procs = [_start(RUNNER, tmp_path) for _ in range(2)]
    results = [_result(p, 900) for p in procs]
    assert sorted(r["compiled"] for r in results) == [False, True]
    loaded = next(r for r in results if not r["compiled"])
    assert loaded["misses"] == 0
    assert results[0]["digest"] == results[1]["digest"]


# a short cold discrete run: which path it took and the run's bytes
SHORT = """
import hashlib, json
from tether import catalog, mission as ms
from sim import kernel, refsim
m = ms.load(catalog.builtin_path("section4"))
run = refsim.simulate(m, "discrete", duration=20.0, ENGINE)
misses = sum(kernel.discrete.stats.cache_misses.values())
hits = sum(kernel.discrete.stats.cache_hits.values())
digest = hashlib.sha256(b"".join(x.tobytes() for x in (run.p, run.v, run.u, run.xi, run.zeta))).hexdigest()
print(json.dumps({"calls": misses + hits, "misses": misses, "digest": digest}))
"""


@pytest.mark.slow
def test_a_short_cold_run_takes_numpy_and_the_next_one_the_cache(tmp_path: Path) -> None:
    """A short discrete run with cold caches runs on the numpy path (no kernel call) and starts the
    compile in the background; once its mark is written a run loads the kernel from the cache. All
    three runs (cold auto, numpy, warm auto) are the same bit for bit."""
    pytest.importorskip("numba")
    cold = _result(_start(SHORT.replace("ENGINE", "engine='auto'"), tmp_path), 600)
    assert cold["calls"] == 0
    marks = tmp_path / "tether" / "warm"
    wait_until(lambda: any(marks.glob("refsim-discrete-*.done")), 900, "the background compile's mark")
    warm = _result(_start(SHORT.replace("ENGINE", "engine='auto'"), tmp_path), 600)
    assert warm["calls"] > 0 and warm["misses"] == 0
    ref = _result(_start(SHORT.replace("ENGINE", "engine='numpy'"), tmp_path), 600)
    assert cold["digest"] == warm["digest"] == ref["digest"]
    assert not list(marks.glob("*.toml"))  # the background compile removed its mission file


@pytest.mark.slow  # a real background compile of two parts (tens of seconds of CPU)
def test_a_first_command_compiles_the_first_studys_kernels_in_the_background(tmp_path: Path) -> None:
    """``tether check`` on a machine with empty caches starts one detached compile at idle priority
    and returns at once; once its stamp is there the marks of a first study's parts are too (a
    ``tether sweep`` would find them compiled), and a second command starts nothing."""
    env = dict(_env(tmp_path), TETHER_PREWARM="1")
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "cli", "check", "section4"], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)
    took = time.monotonic() - t0
    assert done.returncode == 0, done.stderr[-2000:]
    code = ("import json, os; from sim import warm; print(json.dumps({'stamp': str(warm.prewarm_stamp()), "
            "'marks': str(warm.marks_dir())}))")
    where = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                                      timeout=60, check=True).stdout)
    stamp, marks = Path(where["stamp"]), Path(where["marks"])
    wait_until(stamp.exists, 300.0, "the background compile's stamp")
    names = sorted(f.name for f in marks.glob("*.done") if not f.name.startswith("prewarm-"))
    print(f"\ntether check returned in {took:.2f} s; compiled in the background: {names}")
    assert any(n.startswith("lockstep-") for n in names), names
    assert any(n.startswith("refsim-discrete-") and "parallel" not in n for n in names), names
    # a second first command: the stamp is there, nothing is started
    again = subprocess.run([sys.executable, "-c", "from sim import warm; print(warm.prewarm())"], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=60, check=True)
    assert again.stdout.strip() == "False"
