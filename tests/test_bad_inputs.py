"""Every bad input is a clear error before anything starts: the ``tether`` command as a subprocess.

Two catalogues, both run as real processes under a memory limit (``RLIMIT_AS``, :data:`MEMORY`) and
a timeout (:data:`TIMEOUT`):

- every mission of ``tests/missions_bad/`` (the catalogue ``tests/test_mission.py`` checks in
  process, with its ``# expect:`` lines) through ``tether check``, and the ones whose harm was in
  a later command (a run-sized allocation, a key namespace, a diverging run) through that command
  too (:data:`ALSO`);
- :data:`ARGUMENTS`: bad command-line arguments (``--duration``, ``--out``, ``plot``'s run file...).

Each must exit with status 2, name its field or argument on stderr, print no traceback, start no
process and write no run.
"""

from __future__ import annotations

import os
import re
import resource
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests import support
from tether.runfile import Run, RunMeta

BAD = Path(__file__).parent / "missions_bad"
BAD_FILES = sorted(BAD.glob("*.toml"))
REPO = Path(__file__).parent.parent

MEMORY = 1 << 30
"""Address-space limit of every command here [bytes]: 1 GiB, a hundredth of what the unchecked
inputs tried to allocate."""
TIMEOUT = 60.0
"""Every command must answer within this long [s] (each takes about a second; the machine is shared)."""

_EXPECT = re.compile(r"^# expect: (?P<field>.+?) \| (?P<text>.+)$")

ALSO = {
    "duration_agent_ticks": "simulate",
    "duration_run_too_big": "simulate",
    "rate_giga": "simulate",
    "rate_tiny_duration_huge": "simulate",
    "kp0_huge": "simulate",
    "offset_huge": "simulate",
    "waypoints_too_fast": "simulate",
    "weight_subnormal": "simulate",
    "name_with_slash": "run",
    "name_with_space": "run",
    "name_with_star": "run",
    "name_empty": "run",
    "crazyflie_udp_port_out_of_range": "run",
}
"""Catalogue missions that are also given to the command where they used to do harm."""


def _limit() -> None:  # runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY, MEMORY))


def tether(*args: str, cwd: Path | None = None) -> tuple[subprocess.CompletedProcess[str], float]:
    """Run ``python -m cli ARGS`` under :data:`MEMORY` and :data:`TIMEOUT`; the result and its wall time [s]."""
    start = time.monotonic()
    r = support.tether(*args, timeout=TIMEOUT, cwd=cwd, preexec_fn=_limit)
    return r, time.monotonic() - start


def _assert_refused(r: subprocess.CompletedProcess[str], names: list[str]) -> None:
    assert "Traceback" not in r.stderr, r.stderr
    assert r.returncode == 2, f"status {r.returncode}\n{r.stderr}"
    for name in names:
        assert name in r.stderr, f"{name!r} not named in\n{r.stderr}"


def _expected(path: Path) -> list[tuple[str, str]]:
    text = path.read_bytes().decode("utf-8", errors="replace")
    found = [_EXPECT.match(line) for line in text.splitlines()]
    return [(m["field"], m["text"]) for m in found if m]


# --------------------------------------------------------------------------- missions
def test_catalogue_covers_the_commands() -> None:
    stems = {p.stem for p in BAD_FILES}
    assert set(ALSO) <= stems, set(ALSO) - stems
    assert len(BAD_FILES) + len(ALSO) + len(ARGUMENTS) >= 150


@pytest.mark.slow  # one subprocess per case: the in-process catalogue runs in the fast lane (test_mission)
@pytest.mark.parametrize("path", BAD_FILES, ids=[p.stem for p in BAD_FILES])
def test_check_refuses_every_bad_mission(path: Path) -> None:
    r, _ = tether("check", str(path))
    _assert_refused(r, [f"  {field}: " for field, _ in _expected(path)])
    for _, text in _expected(path):
        assert text in r.stderr, r.stderr
    assert r.stdout == ""


@pytest.mark.slow  # one subprocess per case: the in-process catalogue runs in the fast lane (test_mission)
@pytest.mark.parametrize("stem", sorted(ALSO), ids=sorted(ALSO))
def test_the_command_it_harmed_refuses_it_before_starting(stem: str, tmp_path: Path) -> None:
    path = BAD / f"{stem}.toml"
    command = ALSO[stem]
    out = tmp_path / "out"
    extra = ["--no-figures"] if command == "simulate" else ["--quiet"]
    r, _ = tether(command, str(path), "--out", str(out), *extra)
    _assert_refused(r, [f"  {field}: " for field, _ in _expected(path)])
    assert not (out / "run.npz").exists() and not (out / "logs").exists(), "something ran"


# --------------------------------------------------------------------------- arguments
@dataclass(frozen=True)
class Bad:
    """A bad command line: ``args`` (``{tmp}`` is a fresh directory, ``{file}`` a file in it,
    ``{npzdir}`` a directory whose run.npz is a directory, ``{junk}`` a directory whose run.npz is
    not a zip, ``{trunc}`` one whose run.npz is a truncated zip, ``{good}`` one with a valid run), the words stderr must hold."""

    name: str
    args: tuple[str, ...]
    names: tuple[str, ...]


ARGUMENTS = [
    Bad("simulate-duration-negative", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "-5"),
        ("--duration", "> 0")),
    Bad("simulate-duration-zero", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "0"), ("--duration",)),
    Bad("simulate-duration-nan", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "nan"), ("--duration",)),
    Bad("simulate-duration-inf", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "inf"), ("--duration",)),
    Bad("simulate-duration-text", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "ten"),
        ("--duration", "not a number")),
    Bad("simulate-duration-below-a-period", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "0.001"),
        ("--duration", "whole number of control periods", "--duration 0.01")),
    Bad("simulate-duration-huge", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "1e12"),
        ("--duration", "agent-ticks")),
    Bad("simulate-duration-run-too-big", ("simulate", "section4", "--out", "{tmp}/o", "--duration", "1e5"),
        ("--duration", "GiB", "4 GiB limit")),
    Bad("simulate-substeps-zero", ("simulate", "section4", "--out", "{tmp}/o", "--substeps", "0"), ("--substeps",)),
    Bad("simulate-out-is-a-file", ("simulate", "section4", "--out", "{file}", "--duration", "1"),
        ("--out", "existing file")),
    Bad("simulate-out-below-a-file", ("simulate", "section4", "--out", "{file}/sub", "--duration", "1"),
        ("--out", "is a file, so")),
    Bad("simulate-out-unwritable", ("simulate", "section4", "--out", "/proc/self/tether-out", "--duration", "1"),
        ("--out", "cannot write", "ENOENT")),
    Bad("sweep-out-is-a-file", ("sweep", "section4", "--out", "{file}", "--duration", "1"), ("--out", "existing file")),
    Bad("simulate-out-sysfs", ("simulate", "section4", "--out", "/sys/tether-out", "--duration", "1"),
        ("--out", "cannot write")),
    Bad("simulate-out-run-npz-is-a-directory", ("simulate", "section4", "--out", "{npzdir}", "--duration", "1"),
        ("--out", "run.npz is a directory")),
    Bad("simulate-missing-mission", ("simulate", "{tmp}/none.toml", "--out", "{tmp}/o"), ("<file>", "cannot be read")),
    Bad("check-a-directory", ("check", "{tmp}"), ("<file>", "is a directory")),
    Bad("reproduce-duration-negative", ("reproduce", "section4", "--out", "{tmp}/o", "--duration", "-1"),
        ("--duration",)),
    Bad("reproduce-duration-below-a-period", ("reproduce", "section4", "--out", "{tmp}/o", "--duration", "0.001"),
        ("--duration", "whole number of control periods")),
    Bad("reproduce-exp1-duration-huge", ("reproduce", "exp1", "--out", "{tmp}/o", "--duration", "1e15"),
        ("--duration", "agent-ticks")),
    Bad("reproduce-out-is-a-file", ("reproduce", "section4", "--out", "{file}", "--duration", "1"),
        ("--out", "existing file")),
    Bad("run-duration-below-a-period", ("run", "section4", "--out", "{tmp}/o", "--duration", "0.001"),
        ("--duration", "whole number of control periods")),
    Bad("run-duration-negative", ("run", "section4", "--out", "{tmp}/o", "--duration", "-5"), ("--duration",)),
    Bad("run-duration-huge", ("run", "section4", "--out", "{tmp}/o", "--duration", "1e12"),
        ("--duration", "agent-ticks")),
    Bad("run-out-is-a-file", ("run", "section4", "--out", "{file}", "--duration", "1"), ("--out", "existing file")),
    Bad("run-out-run-npz-is-a-directory", ("run", "section4", "--out", "{npzdir}", "--duration", "1"),
        ("--out", "run.npz is a directory")),
    Bad("run-out-unwritable", ("run", "section4", "--out", "/sys/tether-out", "--duration", "1"),
        ("--out", "cannot write")),
    Bad("run-rt-priority-too-high", ("run", "section4", "--out", "{tmp}/o", "--duration", "1", "--rt-priority", "100"),
        ("--rt-priority", "1..99")),
    Bad("run-rt-priority-negative", ("run", "section4", "--out", "{tmp}/o", "--duration", "1", "--rt-priority", "-1"),
        ("--rt-priority", "1..99")),
    Bad("run-rt-priority-text", ("run", "section4", "--out", "{tmp}/o", "--duration", "1", "--rt-priority", "high"),
        ("--rt-priority", "not an integer")),
    Bad("agent-rt-priority-too-high", ("agent", "--mission", "section4", "--id", "1", "--rt-priority", "200"),
        ("--rt-priority", "1..99")),
    Bad("leader-record-batch-too-large", ("leader", "--mission", "section4", "--clock", "lockstep",
                                          "--record-batch", "300"), ("--record-batch", "at most 256")),
    Bad("leader-record-batch-realtime", ("leader", "--mission", "section4", "--record-batch", "16"),
        ("--record-batch", "lockstep")),
    Bad("agent-record-batch-zero", ("agent", "--mission", "section4", "--id", "1", "--record-batch", "0"),
        ("--record-batch", "not >= 1")),
    Bad("leader-mesh-peers-negative", ("leader", "--mission", "section4", "--mesh-peers", "-1"),
        ("--mesh-peers", "not >= 0")),
    Bad("agent-mesh-peers-text", ("agent", "--mission", "section4", "--id", "1", "--mesh-peers", "all"),
        ("--mesh-peers", "not an integer")),
    Bad("run-ns-with-slash", ("run", "section4", "--out", "{tmp}/o", "--duration", "1", "--ns", "a/b"),
        ("--ns", "key chunk")),
    Bad("demo-duration-negative", ("demo", "--out", "{tmp}/o", "--duration", "-1"), ("--duration",)),
    Bad("sweep-duration-below-a-period", ("sweep", "section4", "--out", "{tmp}/o", "--duration", "0.001"),
        ("--duration", "whole number of control periods")),
    Bad("plot-missing-directory", ("plot", "{tmp}/nowhere"), ("run:", "does not exist")),
    Bad("plot-directory-without-run", ("plot", "{tmp}"), ("run:", "is not a file")),
    Bad("plot-not-a-zip", ("plot", "{junk}"), ("run:", "not a run file", "zip archive")),
    Bad("plot-truncated-zip", ("plot", "{trunc}"), ("run:", "not a readable run file")),
    Bad("plot-out-unwritable", ("plot", "{good}", "--out", "/sys/tether-plots"), ("--out", "cannot write")),
    Bad("plot-out-is-a-file", ("plot", "{good}", "--out", "{file}"), ("--out", "existing file")),
    Bad("land-ns-with-star", ("land", "--ns", "swarm*", "--connect", "tcp/127.0.0.1:1"), ("--ns",)),
    # the same --duration check for every command (a 0-step run once wrote NaN into metrics.json)
    Bad("run-duration-zero", ("run", "section4", "--out", "{tmp}/o", "--duration", "0"), ("--duration", "> 0")),
    Bad("run-duration-nan", ("run", "section4", "--out", "{tmp}/o", "--duration", "nan"), ("--duration",)),
    Bad("reproduce-duration-zero", ("reproduce", "section4", "--out", "{tmp}/o", "--duration", "0"),
        ("--duration", "> 0")),
    Bad("reproduce-duration-text", ("reproduce", "section4", "--out", "{tmp}/o", "--duration", "ten"),
        ("--duration", "not a number")),
    Bad("sweep-duration-negative", ("sweep", "section4", "--out", "{tmp}/o", "--duration", "-5"), ("--duration",)),
    Bad("run-out-proc", ("run", "section4", "--out", "/proc/self/tether-out", "--duration", "1"),
        ("--out", "cannot write")),
    Bad("simulate-continuous-substeps-huge", ("simulate", "section4", "--out", "{tmp}/o", "--mode", "continuous",
                                              "--substeps", "1000000000"), ("--substeps", "agent-substeps")),
    Bad("simulate-scene-rate-negative", ("simulate", "section4", "--out", "{tmp}/o", "--scene-rate", "-1"),
        ("--scene-rate", ">= 0")),
    Bad("run-window-zero", ("run", "section4", "--out", "{tmp}/o", "--window", "0"), ("--window", "at least 1")),
    # a window the input queues cannot hold: once, its records of window/2 ticks were dropped as too large and the
    # run stalled for 30 s (exit 1)
    Bad("run-window-huge", ("run", "section4", "--out", "{tmp}/o", "--window", "100000"),
        ("--window", "at most 3640 lockstep ticks in flight for 4 vehicles")),
    Bad("run-window-negative-separate", ("run", "section4", "--out", "{tmp}/o", "--window", "-3", "--separate-plants"),
        ("--window", "at least 1")),
    Bad("run-stall-timeout-nan", ("run", "section4", "--out", "{tmp}/o", "--stall-timeout", "nan"),
        ("--stall-timeout", "seconds > 0")),
    Bad("run-lease-huge", ("run", "section4", "--out", "{tmp}/o", "--lease", "1e300"), ("--lease", "an hour")),
    Bad("run-lease-negative", ("run", "section4", "--out", "{tmp}/o", "--lease", "-1"), ("--lease",)),
    Bad("reproduce-duration-inf", ("reproduce", "section4", "--out", "{tmp}/o", "--duration", "inf"), ("--duration",)),
    Bad("run-fault-freeze-forever", ("run", "section4", "--out", "{tmp}/o", "--fault", "freeze:leader@1+1e308"),
        ("--fault freeze:leader@1+1e308", "longer than the whole run")),
    Bad("run-listen-not-a-host", ("run", "section4", "--out", "{tmp}/o", "--listen", "tls/not-a-host:7447"),
        ("--listen tls/not-a-host:7447", "cannot resolve 'not-a-host'", "give an address of this machine")),
    Bad("run-listen-not-this-machine", ("run", "section4", "--out", "{tmp}/o", "--insecure", "--listen",
                                        "tcp/192.0.2.1:7447"),
        ("--listen tcp/192.0.2.1:7447", "not an address of this machine")),
]
"""Bad command lines (58; beside them 43 of the 105 catalogue missions are new with this file)."""


def _fill(text: str, tmp: Path) -> str:
    file = tmp / "a-file"
    file.write_text("not a directory\n")
    npzdir = tmp / "npzdir"
    (npzdir / "run.npz").mkdir(parents=True, exist_ok=True)
    junk = tmp / "junk"
    junk.mkdir(exist_ok=True)
    (junk / "run.npz").write_bytes(b"\x80\x04garbage, not a zip")
    trunc = tmp / "trunc"
    trunc.mkdir(exist_ok=True)
    (trunc / "run.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 40)
    good = tmp / "good"
    if not (good / "run.npz").exists():
        run = Run.empty(3, [4, 7], 2, RunMeta(mission="x", source="reference-discrete", law="sigma", rate=10.0, steps=2))
        run.save(good / "run.npz")
    return text.format(tmp=tmp, file=file, npzdir=npzdir, junk=junk, trunc=trunc, good=good)


@pytest.mark.slow  # one subprocess per case: the in-process catalogue runs in the fast lane (test_mission)
@pytest.mark.parametrize("bad", ARGUMENTS, ids=[b.name for b in ARGUMENTS])
def test_bad_argument_is_refused_before_anything_starts(bad: Bad, tmp_path: Path) -> None:
    args = [_fill(a, tmp_path) for a in bad.args]
    r, _ = tether(*args)
    _assert_refused(r, list(bad.names))
    assert not (tmp_path / "o" / "run.npz").exists() and not (tmp_path / "o" / "logs").exists(), "something ran"
    assert not (tmp_path / "o" / "metrics.json").exists()


# --------------------------------------------------------------------------- scale and writes
def _chain(n: int) -> str:
    """A mission of ``n`` agents in a chain behind the leader (sparse: n edges)."""
    lines = ['version = 1', 'name = "chain"', 'dim = 2', 'rate = 10.0', 'duration = 1.0',
             '[law]', 'kind = "sigma"', 'kp0 = 2.0', 'kv0 = 2.0', 'gamma_p = 0.05', 'gamma_v = 0.05', 'sigma = 1.0',
             '[leader]', f'id = {n + 1}', 'p0 = [0.0, 0.0]']
    for i in range(1, n + 1):
        lines += ['[[agents]]', f'id = {i}', f'p0 = [{float(i)}, 0.0]', f'offset = [{float(i)}, 0.0]']
    lines += ['[[edges]]', f'from = {n + 1}', 'to = 1']
    for i in range(1, n):
        lines += ['[[edges]]', f'from = {i}', f'to = {i + 1}']
    return "\n".join(lines) + "\n"


def measured(*args: str) -> tuple[int, str, str, float, int]:
    """Run ``python -m cli ARGS`` like :func:`tether`; its status, stdout, stderr, wall time [s] and
    peak resident set [bytes], the last read from the kernel's accounting of that one child (``wait4``)."""
    import tempfile

    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", MPLBACKEND="Agg")
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        start = time.monotonic()
        p = subprocess.Popen([sys.executable, "-m", "cli", *args], stdout=out, stderr=err, text=True,
                             preexec_fn=_limit, env=env, cwd=REPO)
        deadline = start + TIMEOUT
        while True:
            pid, status, usage = os.wait4(p.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                p.kill()
                p.wait()
                raise AssertionError(f"tether {' '.join(args)} did not finish within {TIMEOUT} s")
            time.sleep(0.05)
        seconds = time.monotonic() - start
        p.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return p.returncode, out.read(), err.read(), seconds, usage.ru_maxrss * 1024  # Linux: KiB


BIG_CHAIN = 10_000
CHAIN_SECONDS = 30.0
"""Bound on ``check`` and ``simulate`` of the :data:`BIG_CHAIN` chain [s]: measured about 1 s
(``check``) and 9 s (``simulate``, most of it the run.mcap scene of 10 000 vehicles) on an idle machine."""
CHAIN_RSS = 500 * 2**20
"""Bound on their peak resident set [bytes]: measured 57 MB (``check``) and 390 MB (``simulate``: 265 MB
without run.mcap);
a single dense (N+1) x (N+1) matrix of the chain is 800 MB (the ``check`` of old took 2.4 GB)."""


def test_check_of_a_10000_agent_chain_is_fast_and_small(tmp_path: Path) -> None:
    """Once 92 s and 2.4 GB (a dense 10 001 x 10 001 matrix and a solve); now O(N + edges)."""
    path = tmp_path / "chain.toml"
    path.write_text(_chain(BIG_CHAIN))
    status, out, err, seconds, rss = measured("check", str(path))
    assert status == 0 and "Traceback" not in err, err
    assert f"{BIG_CHAIN} agents" in out and "Lemma 3 follows from Assumption 1" in out
    assert seconds < CHAIN_SECONDS, seconds
    assert rss < CHAIN_RSS, f"peak RSS {rss / 2**20:.0f} MiB"


@pytest.mark.slow  # about 10 s of one core
def test_simulate_of_a_10000_agent_chain_is_fast_and_small(tmp_path: Path) -> None:
    """Once 924 MB (the offsets summed through the dense adjacency) and O(N^2) agent look-ups; now the
    engine is O(N + edges) per tick. The continuous mode's compiled kernel solves the chain agent by
    agent (no N x N matrix); its numpy path, which inverts L1, and a graph whose strongly connected
    block is too large to invert are refused up front."""
    path = tmp_path / "chain.toml"
    path.write_text(_chain(BIG_CHAIN))
    out = tmp_path / "o"
    status, _, err, seconds, rss = measured("simulate", str(path), "--out", str(out), "--no-figures")
    assert status == 0 and "Traceback" not in err, err
    assert (out / "run.npz").is_file() and (out / "run.mcap").is_file()
    assert seconds < CHAIN_SECONDS, seconds
    assert rss < CHAIN_RSS, f"peak RSS {rss / 2**20:.0f} MiB"
    status, _, err, seconds, rss = measured("simulate", str(path), "--out", str(tmp_path / "c"), "--mode", "continuous",
                                            "--no-figures", "--no-mcap")
    assert status == 0 and "Traceback" not in err, err
    assert seconds < CHAIN_SECONDS, seconds
    assert rss < CHAIN_RSS, f"peak RSS {rss / 2**20:.0f} MiB"  # one dense N x N matrix is 800 MB
    status, _, err, seconds, rss = measured("simulate", str(path), "--out", str(tmp_path / "n"), "--mode", "continuous",
                                            "--engine", "numpy")
    _assert_refused(subprocess.CompletedProcess([], status, "", err), ["--mode", "GiB", "--mode discrete"])
    assert not (tmp_path / "n").exists()
    ring = tmp_path / "ring.toml"  # the chain closed: one strongly connected block of every agent
    ring.write_text(_chain(BIG_CHAIN) + f"\n[[edges]]\nfrom = {BIG_CHAIN}\nto = 1\n")
    status, _, err, seconds, rss = measured("simulate", str(ring), "--out", str(tmp_path / "r"), "--mode", "continuous")
    _assert_refused(subprocess.CompletedProcess([], status, "", err),
                    ["--mode", f"strongly connected block of the agents' graph, {BIG_CHAIN} agents", "--mode discrete"])
    assert not (tmp_path / "r").exists()


def test_a_run_too_big_for_its_agents_is_refused_with_the_estimate(tmp_path: Path) -> None:
    """Steps x agents and the memory estimate are checked before anything is allocated."""
    path = tmp_path / "chain.toml"
    path.write_text(_chain(BIG_CHAIN).replace("duration = 1.0", "duration = 20000.0"))
    status, _, err, seconds, rss = measured("simulate", str(path), "--out", str(tmp_path / "o"))
    _assert_refused(subprocess.CompletedProcess([], status, "", err), ["  duration: ", "agent-ticks", "2e+09", "1e+09"])
    path.write_text(_chain(BIG_CHAIN).replace("duration = 1.0", "duration = 1000.0"))
    status, _, err, seconds, rss = measured("check", str(path))
    _assert_refused(subprocess.CompletedProcess([], status, "", err), ["  duration: ", "GiB of arrays", "4 GiB limit"])
    assert rss < CHAIN_RSS and seconds < CHAIN_SECONDS
    assert not (tmp_path / "o").exists()


def _no_caches(tmp_path: Path) -> dict[str, str]:
    """The environment of a child run under a file-size limit: a short write is not an error for
    Python's bytecode cache or numba's kernel cache, so a truncated ``.pyc`` or kernel would be left
    for every later process to load; neither cache is written to the source tree from such a child."""
    return {**os.environ, "PYTHONDONTWRITEBYTECODE": "1", "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}


def test_a_write_that_fails_part_way_names_the_path_and_errno(tmp_path: Path) -> None:
    """A full disk, emulated by a file-size limit: status 1, the path and the errno named, no ``.part`` left."""
    import signal

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # the write then fails with EFBIG instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))
        _limit()

    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-m", "cli", "simulate", "section4", "--duration", "20", "--out", str(out),
                        "--no-figures"], capture_output=True, text=True, timeout=TIMEOUT, preexec_fn=small_files,
                       cwd=REPO, env=_no_caches(tmp_path))
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert f"{out / 'run.npz'}:" in r.stderr and "EFBIG" in r.stderr
    assert not list(out.glob("*.part"))


@pytest.fixture
def small_disk(tmp_path: Path):  # type: ignore[no-untyped-def]
    """``mount(size, inodes)``: a real tmpfs of that size and inode count under ``tmp_path`` (root
    only; skipped otherwise), unmounted at the end."""
    mounted: list[Path] = []

    def mount(size: str, inodes: int) -> Path:
        if os.geteuid() != 0:
            pytest.skip("mounting a small tmpfs needs root")
        where = tmp_path / f"disk{len(mounted)}"
        where.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},nr_inodes={inodes}", "tmpfs", str(where)],
                           capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
        mounted.append(where)
        return where

    yield mount
    for where in mounted:
        subprocess.run(["umount", "-l", str(where)], check=False)


def test_a_run_whose_logs_cannot_be_made_is_refused_before_anything_starts(tmp_path: Path, small_disk) -> None:  # type: ignore[no-untyped-def]
    """``logs/`` in the way, a file system out of inodes, one without room for the run: exit 2, the
    file and the cause named, what to do, no process started (no log left behind)."""
    out = tmp_path / "in-the-way"
    out.mkdir()
    (out / "logs").write_text("a file where the launcher makes a directory\n")
    r, _ = tether("run", "section4", "--out", str(out), "--duration", "1", "--insecure", "--quiet")
    _assert_refused(r, ["--out", f"{out / 'logs'} is a file", "give another --out"])
    assert "router listening" not in r.stderr

    inodes = small_disk("16m", 5) / "o"  # the root, o, logs and two files: the third log fails
    inodes.mkdir()
    r, _ = tether("run", "section4", "--out", str(inodes), "--duration", "1", "--insecure", "--quiet")
    _assert_refused(r, ["--out", "cannot create the run's logs", "ENOSPC", "free space on its file system"])
    assert "router listening" not in r.stderr and list((inodes / "logs").iterdir()) == []

    full = small_disk("64k", 100) / "o"
    r, _ = tether("run", "section4", "--out", str(full), "--duration", "1", "--insecure", "--quiet")
    _assert_refused(r, ["--out", "MiB free, but the run needs about", "give another --out"])
    assert not (full / "logs").exists()


@pytest.mark.slow  # a 3 s lockstep run of every process
def test_a_run_file_that_cannot_be_written_is_named_by_the_recorder_and_the_launcher(tmp_path: Path) -> None:
    """A disk that fills up during the run, made real by a file-size limit on the launcher and every
    process it starts (the write then fails with EFBIG): the recorder logs the path and the cause and
    exits 1, no traceback; the launcher names the recorder's cause and exits 1; no ``.part`` is left."""
    import signal

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # inherited: the write fails instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    out = tmp_path / "o"
    r = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--out", str(out), "--duration", "3",
                        "--insecure", "--quiet"], capture_output=True, text=True, timeout=120, preexec_fn=small_files,
                       cwd=REPO, env=_no_caches(tmp_path))
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    assert f"recorder/0: failed: {out / 'run.npz'}: " in r.stderr and "(EFBIG)" in r.stderr, r.stderr
    recorder = (out / "logs" / "recorder-0.log").read_text()
    assert "Traceback" not in recorder and f"failed: {out / 'run.npz'}: File too large" in recorder, recorder
    assert not (out / "run.npz").exists() and not list(out.glob("*.part"))


def test_a_velocity_schedule_of_100000_segments_is_sampled_by_bisection() -> None:
    """Once O(segments) per sample (about 0.1 s each at 100 000 segments); now O(log segments)."""
    import numpy as np

    from leader.profile import PiecewiseLinearVelocity

    segs = [(float(k), np.array([float(k % 3), 0.0])) for k in range(100_000)]
    ref = PiecewiseLinearVelocity.from_schedule(np.zeros(2), segs, 0.1)
    start = time.process_time()
    for k in range(200):
        ref(k * 37.3)
    assert time.process_time() - start < 2.0
    small = PiecewiseLinearVelocity.from_schedule(np.zeros(2), segs[:5], 0.1)
    p, v, a = small(2.05)  # mid-ramp from segment 1 (v = 1) to 2 (v = 2): v = 1.5, a = 10
    np.testing.assert_allclose(v, [1.5, 0.0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(a, [10.0, 0.0], rtol=0, atol=1e-9)
