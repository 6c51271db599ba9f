"""A busy host degrades gracefully (``tether/sched.py``, ``deploy/router.py``).

Real processes: the default priority taken where permitted and refused with one line where not
(root with ``CAP_SYS_NICE`` dropped and an rtprio limit of 0), the operator gateway's router at
the priority it is given, and the operator's ``land``/``estop`` through that gateway reaching every
vehicle of a real-time swarm beside two busy loops. How fast they get there, and what the swarm
does beside busy loops at each policy, is measured by ``bench/loaded.py``, not here.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from deploy import operator
from tests.support import read, rt_permitted, wait_until
from tests.test_rt_priority import SCHED_OTHER, SCHED_RR, thread_policies
from tests.test_runtime import AGENTS, STARTUP, WAIT, launch, wait_for_realtime_start
from tether import sched, wire
from tether import transport as tp
from tether.runfile import Run

REPO = Path(__file__).resolve().parents[1]
DROP = ["setpriv", "--bounding-set=-sys_nice", "--inh-caps=-sys_nice"] if os.geteuid() == 0 else []
"""Root keeps real-time scheduling through CAP_SYS_NICE: drop it (with ``prlimit --rtprio=0``, the
process is then refused it like an unprivileged user)."""
needs_drop = pytest.mark.skipif(bool(DROP) and shutil.which("setpriv") is None,
                                reason="root needs setpriv (util-linux) to drop CAP_SYS_NICE")
needs_rt = pytest.mark.skipif(not rt_permitted(sched.DEFAULT_PRIORITY),
                              reason="this user may not use real-time scheduling (root, CAP_SYS_NICE or `ulimit -r`)")


# --------------------------------------------------------------------------- the pure choices
def test_the_gateway_runs_one_step_below_the_control_processes() -> None:
    assert sched.gateway_priority(10) == 9
    assert sched.gateway_priority(99) == 98
    assert sched.gateway_priority(1) == 1  # nothing lower is real-time: beside them, round robin
    assert sched.gateway_priority(0) == 0  # the control processes at the normal policy: so is the gateway
    for bad in (-1, 100):
        with pytest.raises(sched.SchedError, match="1..99"):
            sched.gateway_priority(bad)


def test_a_default_priority_out_of_range_is_an_error_not_a_fallback() -> None:
    with pytest.raises(sched.SchedError, match="1..99"):
        sched.apply_best(100)


# --------------------------------------------------------------------------- the default, applied or refused
PROBE = ("import json, os; from tether import sched; got, line = sched.apply_best(); "
         "print(json.dumps([got, line, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority]))")


def probe(*prefix: str) -> tuple[int, str, int, int]:
    r = subprocess.run([*prefix, sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 0, r.stderr
    got, line, policy, priority = json.loads(r.stdout)
    return got, line, policy, priority


@pytest.mark.slow
@needs_rt
def test_the_default_takes_real_time_priority_where_permitted() -> None:
    assert probe() == (sched.DEFAULT_PRIORITY, f"SCHED_RR {sched.DEFAULT_PRIORITY}", SCHED_RR,
                       sched.DEFAULT_PRIORITY)


@pytest.mark.slow
@needs_drop
def test_where_not_permitted_the_default_keeps_the_normal_policy_and_says_why_in_one_line() -> None:
    got, line, policy, priority = probe(*DROP, "prlimit", "--rtprio=0")
    assert (got, policy, priority) == (0, SCHED_OTHER, 0)
    assert "\n" not in line and line.startswith("SCHED_OTHER: SCHED_RR 10 is not permitted"), line
    assert "CAP_SYS_NICE" in line and "ulimit -r" in line, line


# --------------------------------------------------------------------------- the gateway's router
@pytest.fixture
def router_config(tmp_path: Path) -> Path:
    path = tmp_path / "router.json5"
    path.write_text(json.dumps({"mode": "router", "listen": {"endpoints": [f"tcp/127.0.0.1:{tp.free_tcp_port()}"]},
                                "scouting": {"multicast": {"enabled": False}}}))
    return path


def start_router(config: Path, log: Path, *args: str) -> subprocess.Popen[bytes]:
    with open(log, "wb") as fh:
        return subprocess.Popen([sys.executable, "-m", "deploy.router", "--config", str(config), *args], cwd=REPO,
                                stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)


def listening(proc: subprocess.Popen[bytes], log: Path) -> bool:
    if proc.poll() is not None:
        pytest.fail(f"the router exited with {proc.returncode}:\n{read(log)}")
    return "listening on" in read(log)


def stop_router(proc: subprocess.Popen[bytes]) -> int:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(WAIT)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.slow
@needs_rt
def test_a_router_given_a_priority_runs_every_thread_at_it(router_config: Path, tmp_path: Path) -> None:
    log = tmp_path / "router.log"
    proc = start_router(router_config, log, "--priority", "9")
    try:
        wait_until(lambda: listening(proc, log), STARTUP, "the router listening")
        assert set(thread_policies(proc.pid).values()) == {SCHED_RR}, thread_policies(proc.pid)
        assert os.sched_getparam(proc.pid).sched_priority == 9
    finally:
        assert stop_router(proc) == 0, read(log)
    assert read(log).count("CPU priority: SCHED_RR 9") == 1, read(log)


@pytest.mark.slow
@needs_drop
def test_a_router_not_permitted_its_priority_runs_at_the_normal_one_and_says_so(router_config: Path,
                                                                               tmp_path: Path) -> None:
    """The gateway carries the operator's orders: a refused priority must not stop it."""
    log = tmp_path / "router.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen([*DROP, "prlimit", "--rtprio=0", sys.executable, "-m", "deploy.router",
                                 "--config", str(router_config), "--priority", "9"], cwd=REPO,
                                stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_until(lambda: listening(proc, log), STARTUP, "the router listening")
        assert set(thread_policies(proc.pid).values()) == {SCHED_OTHER}, thread_policies(proc.pid)
    finally:
        assert stop_router(proc) == 0, read(log)
    said = [ln for ln in read(log).splitlines() if "CPU priority" in ln]
    assert len(said) == 1 and "WARNING" in said[0] and "SCHED_RR 9 is not permitted" in said[0], said


def test_a_router_priority_out_of_range_is_refused_naming_the_option(router_config: Path) -> None:
    r = subprocess.run([sys.executable, "-m", "deploy.router", "--config", str(router_config), "--priority", "100"],
                       capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.returncode == 2 and "--priority" in r.stderr and "1..99" in r.stderr, r.stderr


# --------------------------------------------------------------------------- the operator's orders on a busy host
HOGS = 2
ORDER_AT = 6.0
"""Mission time [s] after which the order is given (the swarm at about 4.5 m/s)."""


@pytest.fixture
def busy() -> Iterator[None]:
    """Two busy loops at the default policy, started before the swarm; each ends by itself."""
    burn = f"import time\nend = time.monotonic() + {STARTUP + 120}\nwhile time.monotonic() < end: pass"
    hogs = [subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.DEVNULL) for _ in range(HOGS)]
    try:
        yield
    finally:
        for h in hogs:
            h.kill()
            h.wait()


class Listener:
    """The operator's view: every plant's newest mode and state time, heard through the gateway."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.t: dict[int, float] = {}
        self.modes: dict[int, set[int]] = {}

    def on_sample(self, sample: zenoh.Sample) -> None:
        msg = wire.decode(sample.payload.to_bytes())
        if isinstance(msg, wire.PlantState):
            with self.lock:
                self.t[msg.sender] = max(msg.t, self.t.get(msg.sender, 0.0))
                self.modes.setdefault(msg.sender, set()).add(msg.mode)

    def all_past(self, t: float) -> bool:
        with self.lock:
            return len(self.t) == len(AGENTS) and min(self.t.values()) >= t

    def all_in(self, mode: int) -> bool:
        with self.lock:
            return all(mode in self.modes.get(i, set()) for i in AGENTS)


@pytest.mark.slow
@needs_rt
@pytest.mark.parametrize("action", ["land", "estop"])
def test_beside_busy_loops_the_operators_order_reaches_every_vehicle_and_nothing_fails_before(
        action: operator.Action, busy: None, tmp_path: Path) -> None:
    """``--rt-priority 10`` beside two busy loops at the default policy; the order is sent as
    ``tether land|estop --zenoh-config DIR/tls/control-0.json5`` sends it, through the gateway."""
    ns = f"busy-{action}-{os.getpid()}"
    ep = f"tls/127.0.0.1:{tp.free_tcp_port()}"
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", "30", "--listen", ep,
                "--rt-priority", str(sched.DEFAULT_PRIORITY)) as run:
        wait_for_realtime_start(run)
        conf = run.out / "tls" / "control-0.json5"
        heard = Listener()
        with tp.open_session(tp.ZenohSettings(config_file=str(conf))) as session:
            sub = session.declare_subscriber(f"tether/{ns}/plant/*/state", heard.on_sample)
            try:
                wait_until(lambda: heard.all_past(ORDER_AT), STARTUP, f"every plant's state past {ORDER_AT} s")
                asyncio.run(operator.send(tp.ZenohSettings(config_file=str(conf)), ns, action, "busy host",
                                          timeout=STARTUP))
                mode = wire.LAND if action == "land" else wire.ESTOP
                wait_until(lambda: heard.all_in(mode), STARTUP, f"every plant reporting {action}")
            finally:
                sub.undeclare()
        status = run.wait(STARTUP + 60)
    assert status in (0, 3, 5), run.launcher_log
    rt = Run.load(run.out)
    assert rt.runtime is not None
    first = min((e.t for e in rt.safety.events if e.src != e.dst), default=np.inf)
    first_plant = min((e.t for e in rt.safety.plant_events if e.src != e.dst), default=np.inf)
    assert min(first, first_plant) > ORDER_AT, [str(e) for e in (*rt.safety.events, *rt.safety.plant_events)][:8]
    flew = rt.t < ORDER_AT
    P = rt.runtime.plant_p[flew]
    d = np.linalg.norm(P[:, :, None, :] - P[:, None, :, :], axis=3)
    d[:, np.arange(len(AGENTS)), np.arange(len(AGENTS))] = np.inf
    assert np.nanmin(d) > 0.1, np.nanmin(d)
