"""Real-time priority of the control processes (``tether run --rt-priority``, ``tether/sched.py``).

Real processes: a Section 4 run in real time beside as many CPU-bound processes as the machine has
CPUs, and the launcher refused before anything starts where the system does not permit the policy.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from sim import refsim
from tests.support import rt_permitted, wait_until
from tests.test_runtime import (AGENTS, CHILDREN, SECTION4, STARTUP, WAIT, Launched, cmdline, envelope,
                                fresh_ticks, launch, physical_envelope, tether_cmd, wait_for_realtime_start)
from tether.node import load_mission
from tether.runfile import Run

PRIORITY = 10
HOG_SECONDS = STARTUP + 120
"""The longest a CPU-bound process of the fixture runs (start-up, the 20 s run, its end)."""
SCHED_OTHER, SCHED_RR = 0, 2  # the policy numbers /proc/<pid>/task/<tid>/stat gives (field 41)


def thread_policies(pid: int) -> dict[int, int]:
    """Each thread of ``pid`` -> its scheduling policy (field 41 of its ``stat``, counted after the
    command name, which may hold spaces and parentheses)."""
    out = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            stat = (task / "stat").read_text()
        except OSError:
            continue  # a thread that ended meanwhile
        out[int(task.name)] = int(stat.rsplit(")", 1)[1].split()[38])
    return out


def gateway_of(launcher: int) -> int | None:
    """The operator gateway the launcher started (``deploy.router --priority P --watch-pid <launcher>``)."""
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            argv = cmdline(int(entry.name))
            if "deploy.router" in argv and "--watch-pid" in argv and argv[argv.index("--watch-pid") + 1] == str(launcher):
                return int(entry.name)
    return None


@dataclass
class Loaded:
    run: Launched
    policies: dict[str, dict[int, int]]
    """Per child (and ``launcher``, ``gateway``), each thread's policy, read while the run flew."""
    hogs: int


@pytest.fixture(scope="module")
def loaded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Loaded]:
    """A 20 s real-time run at ``--rt-priority 10`` beside one CPU-bound process per CPU, started
    before the swarm and kept running to its end."""
    if not rt_permitted(PRIORITY):
        pytest.skip("this user may not use real-time scheduling (root, CAP_SYS_NICE or `ulimit -r` >= 10)")
    n = os.cpu_count() or 2
    # each ends by itself after HOG_SECONDS, should this test process die before it kills them
    burn = f"import time\nend = time.monotonic() + {HOG_SECONDS}\nwhile time.monotonic() < end: pass"
    hogs = [subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.DEVNULL) for _ in range(n)]
    try:
        ns = f"rtprio-{os.getpid()}"
        with launch(tmp_path_factory.mktemp("rtprio"), ns, "--clock", "realtime", "--duration", "20",
                    "--rt-priority", str(PRIORITY)) as run:
            wait_for_realtime_start(run)
            policies = {name: thread_policies(pid) for name, pid in run.children.items()}
            policies["launcher"] = thread_policies(run.proc.pid)
            found: dict[str, int] = {}

            def gateway_up() -> bool:
                pid = gateway_of(run.proc.pid)
                if pid is not None:
                    found["gateway"] = pid
                return pid is not None

            wait_until(gateway_up, WAIT, "the operator gateway")
            policies["gateway"] = thread_policies(found["gateway"])
            assert all(h.poll() is None for h in hogs), "a CPU-bound process ended early"
            run.wait(STARTUP + 60)
            yield Loaded(run, policies, n)
    finally:
        for h in hogs:
            h.kill()
            h.wait()


@pytest.mark.slow
def test_every_thread_of_the_control_processes_runs_at_the_real_time_priority(loaded: Loaded) -> None:
    """Leader, agents, plants: every thread (Zenoh's included, started after the policy was set).
    The launcher: its router's threads (one idle BLAS thread numpy started before may stay
    normal). The recorder keeps the normal policy; the operator gateway runs at SCHED_RR one step below."""
    pol = loaded.policies
    for name in CHILDREN:
        want = SCHED_OTHER if name == "recorder/0" else SCHED_RR
        assert set(pol[name].values()) == {want}, (name, pol[name])
    launcher = list(pol["launcher"].values())
    assert launcher.count(SCHED_RR) >= len(launcher) - 1 and len(launcher) > 4, launcher
    assert set(pol["gateway"].values()) == {SCHED_RR}, pol["gateway"]


@pytest.mark.slow
def test_beside_cpu_bound_work_the_swarm_keeps_its_ticks_and_its_formation(loaded: Loaded) -> None:
    """Without the priority, the same run beside two such processes had inputs older than a period
    at 30-63 % of the agents' ticks and fired failsafes (measured, ``docs/runtime.md``)."""
    run = loaded.run
    assert run.status in (0, 5), run.launcher_log  # 5: recorded, a sample lost at the end
    assert "CPU scheduling of the control processes: SCHED_RR 10" in run.launcher_log
    rt = Run.load(run.out)
    assert rt.runtime is not None
    recent = rt.t >= 10.0 - 1e-9
    share = float(fresh_ticks(rt)[recent].mean())
    assert share >= 0.95, f"only {100 * share:.1f} % of the agents' ticks had inputs at most one period old"
    late = rt.runtime.late[-1]
    assert np.all(late <= 0.02 * len(rt.t)), f"late ticks per agent: {late}"
    ref = refsim.simulate(load_mission(SECTION4, 20.0))
    phys, want = physical_envelope(rt, 10.0), physical_envelope(ref, 10.0)
    assert abs(phys / want - 1) <= 0.10, f"real time {phys:.4f} m vs lockstep {want:.4f} m"
    assert abs(envelope(rt, 10.0) / envelope(ref, 10.0) - 1) <= 0.10
    assert all(run.child_log(f"agent/{i}").count("CPU scheduling: SCHED_RR 10") == 1 for i in AGENTS)


@pytest.mark.slow
@pytest.mark.skipif(os.geteuid() == 0 and shutil.which("setpriv") is None,
                    reason="root needs setpriv (util-linux) to drop CAP_SYS_NICE")
def test_a_launcher_not_permitted_real_time_scheduling_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """Without CAP_SYS_NICE and with an rtprio limit of 0 (root with the capability dropped)."""
    drop = ["setpriv", "--bounding-set=-sys_nice", "--inh-caps=-sys_nice"] if os.geteuid() == 0 else []
    out = tmp_path / "o"
    r = subprocess.run([*drop, "prlimit", "--rtprio=0", *tether_cmd("run", "section4", "--out", str(out),
                                                                    "--clock", "realtime", "--duration", "1",
                                                                    "--rt-priority", "10")],
                       capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 2, r.stderr
    assert "--rt-priority" in r.stderr and "not permitted" in r.stderr and "ulimit -r" in r.stderr, r.stderr
    assert not (out / "logs").exists() and not (out / "run.npz").exists(), "something started"


@pytest.mark.slow
def test_a_process_not_permitted_real_time_scheduling_exits_2_naming_the_option(tmp_path: Path) -> None:
    drop = ["setpriv", "--bounding-set=-sys_nice", "--inh-caps=-sys_nice"] if os.geteuid() == 0 else []
    if drop and shutil.which("setpriv") is None:
        pytest.skip("root needs setpriv (util-linux) to drop CAP_SYS_NICE")
    r = subprocess.run([*drop, "prlimit", "--rtprio=0", *tether_cmd("agent", "--mission", "section4", "--id", "1",
                                                                    "--rt-priority", "10", "--zenoh-mode", "client",
                                                                    "--connect", "tcp/127.0.0.1:9")],
                       capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 2, r.stderr
    assert "--rt-priority" in r.stderr and "not permitted" in r.stderr, r.stderr


# --------------------------------------------------------------------------- what the launcher says at the end
def test_late_ticks_beyond_one_percent_are_reported_with_the_remedy() -> None:
    from deploy.outcome import late_report

    late = np.full((2001, 4), np.nan)
    late[:, :] = np.linspace(0, 1, 2001)[:, None] * np.array([99, 154, 102, 118])
    late[-1, 2] = np.nan  # an agent's last sample lost: its last recorded count stands
    said = late_report(late, 2001, None)
    assert said is not None and "99-154 of each agent's 2001 ticks" in said and "--rt-priority 10" in said, said
    assert "short of CPU" in (late_report(late, 2001, 10) or "")
    assert late_report(np.zeros((2001, 4)), 2001, None) is None
    assert late_report(np.full((2001, 4), 20.0), 2001, None) is None  # 1 % and below: nothing to say
    assert late_report(np.full((2001, 4), np.nan), 2001, None) is None  # nothing recorded
    assert late_report(np.full(2001, 500.0), 2001, None) is None  # not a (T, N) array: no report, no crash
