"""A deployment rehearsal on one machine (deploy/rehearse.py), and clock skew detected in real runs.

* The unit reader and the rehearsal's plan (fast): what is read from a generated deployment, and
  what is refused before anything starts (addresses a namespace cannot take, non-root).
* A rehearsal of a generated Section 4 deployment (4 vehicles, each on a host of its own, router,
  leader and recorder on a ground station): every host in its own network namespace on a bridge,
  every unit's command line as written; it flies, and its formation-error envelope equals a
  loopback ``tether run`` of the same mission within the real-time tolerance of
  ``tests/test_runtime.py`` (10 %); nothing is left behind, at the end or after Ctrl-C.
* An injected skew (``--fault skew:...``) is detected within seconds, by the right agents, with
  the right sign and size (``tether run``, real time).

Needs root and iproute2 for the namespaces (skipped otherwise, with the reason). Namespaces are
``tether-rh<pid>-...`` (tests/test_partition.py uses ``tether-pt-<pid>``); host addresses are in
10.77.0.0/24, inside those namespaces only; every loopback port is picked free at run time.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
import pytest

from deploy import gen, rehearse
from sim import refsim
from tests.support import log_time, read, wait_until
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run

REPO = Path(__file__).resolve().parents[1]
SECTION4 = builtin_path("section4")
DURATION = 20.0
"""Mission time of the compared runs [s] (as tests/test_runtime.py's real-time run)."""
TOLERANCE = 0.10
"""Formation-error envelopes over the last half agree within this (tests/test_runtime.py)."""
RUN_WITHIN = 85.0
"""Upper bound on one real-time run of 20 s with its start-up and teardown [s] (two loaded cores)."""
HOSTS = """\
version = 1
config_dir = {config}
tether = "/opt/tether/venv/bin/tether"
python = "/opt/tether/venv/bin/python"
[router]
address = "10.77.0.1"
[leader]
address = "10.77.0.1"
[recorder]
address = "10.77.0.1"
out = {out}
[[agents]]
id = 1
address = "10.77.0.11"
[[agents]]
id = 2
address = "10.77.0.12"
[[agents]]
id = 3
address = "10.77.0.13"
[[agents]]
id = 4
address = "10.77.0.14"
"""


def generate(tmp: Path, hosts: str = HOSTS) -> gen.Deployment:
    out = tmp / "deploy"
    path = tmp / "hosts.toml"
    path.write_text(hosts.format(config=json.dumps(str(out / "hosts" / "{host}")),
                                 out=json.dumps(str(tmp / "recorder-out"))))
    return gen.generate(SECTION4, out, hosts=path)


def needs_namespaces() -> None:
    why = rehearse.unavailable()
    if why is None:
        from tests import netns

        why = netns.unavailable()
    if why is not None:
        pytest.skip(f"a rehearsal {why}")


def cli(*args: str, **kw: object) -> subprocess.Popen[bytes]:
    return subprocess.Popen([sys.executable, "-m", "cli", *args], cwd=REPO, stdin=subprocess.DEVNULL,
                            env=dict(os.environ, PYTHONPATH=str(REPO)), **kw)  # type: ignore[call-overload]


def run_rehearsal(log: Path, *args: str, timeout: float = RUN_WITHIN + 20) -> tuple[int, str]:
    """``tether rehearse ARGS`` to its end; past ``timeout`` it is interrupted (SIGINT: it tears
    everything down) and the test fails. Returns its exit status and output."""
    with open(log, "wb") as fh:
        proc = cli("rehearse", *args, stdout=fh, stderr=subprocess.STDOUT)
        try:
            status = proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
            proc.wait(30)
            pytest.fail(f"the rehearsal did not end within {timeout:g} s:\n{read(log)[-3000:]}")
    return status, read(log)


def envelope(run: Run, since: float) -> float:
    """max over agents and ticks t_k >= ``since`` of ||xi_i(t_k)|| [m], as the agents computed it."""
    return float(np.nanmax(np.linalg.norm(run.xi[run.t >= since - 1e-9], axis=-1)))


def left_behind(record: dict) -> tuple[list[str], list[int]]:
    """The rehearsal's namespaces that still exist, and its processes that still run."""
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    names = {ln.split()[0] for ln in listed.splitlines() if ln.split()}
    spaces = [ns for ns in record["namespaces"] if ns in names]
    alive = []
    for unit in record["units"].values():
        for pid in unit["pids"]:
            try:
                os.kill(pid, 0)
                alive.append(pid)
            except ProcessLookupError:
                pass
    return spaces, alive


# =========================================================================== fast: reading a deployment
def test_units_are_read_as_systemd_reads_them(tmp_path: Path) -> None:
    dep = generate(tmp_path)
    pl = rehearse.plan(dep.out)
    assert pl.hosts == {"agent-1": "10.77.0.11", "agent-2": "10.77.0.12", "agent-3": "10.77.0.13",
                        "agent-4": "10.77.0.14", "leader": "10.77.0.1", "recorder": "10.77.0.1", "router": "10.77.0.1"}
    assert list(pl.machines) == ["10.77.0.11", "10.77.0.12", "10.77.0.13", "10.77.0.14", "10.77.0.1"]
    units = {u.name: u for u in pl.units}
    assert sorted(units) == sorted(["tether-router", "tether-leader-5", "tether-start", "tether-recorder-0",
                                    *[f"tether-{r}-{i}" for i in (1, 2, 3, 4) for r in ("agent", "plant")]])
    a2 = units["tether-agent-2"]
    assert (a2.kind, a2.restart, a2.restart_sec, a2.host) == ("simple", "on-failure", 2.0, "agent-2")
    assert a2.argv[:2] == ["/opt/tether/venv/bin/tether", "agent"]
    assert a2.argv[a2.argv.index("--zenoh-config") + 1] == str(dep.config("agent-2"))
    assert (units["tether-router"].restart, units["tether-start"].kind) == ("always", "oneshot")
    # the control units at SCHED_RR 10, as systemd sets it at exec; the recorder and the start tool not
    assert {n: u.scheduling for n, u in units.items() if u.scheduling is not None} == {
        n: ("rr", 10) for n in units if n.startswith(("tether-agent", "tether-plant", "tether-leader", "tether-router"))}
    here = rehearse.command(a2, 5.0)
    assert here[:3] == [sys.executable, "-m", "cli"] and here[3:-2] == a2.argv[1:] and here[-2:] == ["--duration", "5.0"]
    assert rehearse.command(units["tether-router"], 5.0)[:3] == [sys.executable, "-m", "deploy.router"]
    assert rehearse.command(a2, None, 0.03)[-2:] == ["--clock-skew", "0.03"]
    assert "--clock-skew" not in rehearse.command(units["tether-router"], None, 0.03)


def test_bad_rehearsal_options_exit_2_naming_them(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cli import main as tether

    for bad, says in (("--skew=agent-2", "not HOST=S"), ("--skew=agent-2=nan", "finite"),
                      ("--kill=tether-agent-2", "not UNIT@T"), ("--duration=-1", "> 0")):
        with pytest.raises(SystemExit) as ex:
            tether.main(["rehearse", str(tmp_path), "--out", str(tmp_path / "o"), bad])
        assert ex.value.code == 2 and says in capsys.readouterr().err


def test_specifiers_are_filled_as_systemd_would(tmp_path: Path) -> None:
    unit = tmp_path / "x@7.service"
    unit.write_text("[Unit]\nDescription=x\n[Service]\nExecStart=-/bin/echo %i %% \"a b\" %n %H\nRestart=always\n")
    u = rehearse.parse_unit(unit, "host-a")
    assert u.argv == ["/bin/echo", "7", "%", "a b", "x@7.service", "host-a"] and u.restart == "always"
    unit.write_text("[Service]\nExecStart=/bin/echo %Z\n")
    with pytest.raises(rehearse.RehearseError, match="specifier %Z"):
        rehearse.parse_unit(unit, "h")
    unit.write_text("[Service]\nType=simple\n")
    with pytest.raises(rehearse.RehearseError, match="no ExecStart"):
        rehearse.parse_unit(unit, "h")
    for sched, says in (("CPUSchedulingPolicy=rt\n", "not one of"), ("CPUSchedulingPolicy=rr\n", "1..99"),
                        ("CPUSchedulingPolicy=rr\nCPUSchedulingPriority=100\n", "1..99"),
                        ("CPUSchedulingPolicy=idle\nCPUSchedulingPriority=5\n", "give 0"),
                        ("CPUSchedulingPolicy=rr\nCPUSchedulingPriority=ten\n", "not an integer"),
                        ("CPUSchedulingPriority=10\n", "without CPUSchedulingPolicy")):
        unit.write_text(f"[Service]\nExecStart=/bin/true\n{sched}")
        with pytest.raises(rehearse.RehearseError, match=says):
            rehearse.parse_unit(unit, "h")
    unit.write_text("[Service]\nExecStart=/bin/true\nCPUSchedulingPolicy=fifo\nCPUSchedulingPriority=20\n")
    assert rehearse.parse_unit(unit, "h").scheduling == ("fifo", 20)


def test_addresses_a_namespace_cannot_take_are_refused(tmp_path: Path) -> None:
    dep = generate(tmp_path, HOSTS.replace('"10.77.0.11"', '"127.0.0.1"'))
    with pytest.raises(rehearse.RehearseError, match="own loopback") as err:
        rehearse.plan(dep.out)
    assert "agent-1" in str(err.value) and "hosts file" in str(err.value)
    with pytest.raises(rehearse.RehearseError, match="no hosts/ directory"):
        rehearse.plan(tmp_path)


DNS_HOSTS = (HOSTS.replace('"10.77.0.1"', '"ground.lab"').replace('"10.77.0.11"', '"uav1.lab"')
             .replace('"10.77.0.12"', '"uav2.lab"'))
"""Section 4's hosts file with the ground station and vehicles 1 and 2 named by DNS name."""


def test_hosts_named_by_dns_name_get_addresses_of_their_own(tmp_path: Path) -> None:
    """The hosts file a lab deploys, hosts named by DNS name, is rehearsed as it is: each distinct
    name is put at an address of its own (one machine per name), every namespace resolves the
    names, and hosts given by address keep theirs."""
    dep = generate(tmp_path, DNS_HOSTS)
    pl = rehearse.plan(dep.out)
    assert sorted(pl.names) == ["ground.lab", "uav1.lab", "uav2.lab"]
    assert all(ipaddress.ip_address(a) in rehearse.NAME_NET for a in pl.names.values())
    assert len(set(pl.names.values())) == 3
    assert pl.hosts["router"] == pl.hosts["leader"] == pl.hosts["recorder"] == pl.names["ground.lab"]
    assert (pl.hosts["agent-1"], pl.hosts["agent-2"]) == (pl.names["uav1.lab"], pl.names["uav2.lab"])
    assert (pl.hosts["agent-3"], pl.hosts["agent-4"]) == ("10.77.0.13", "10.77.0.14")
    assert len(pl.machines) == 5
    # the units dial the names, as the deployment would
    a1 = next(u for u in pl.units if u.name == "tether-agent-1")
    conf = Path(a1.argv[a1.argv.index("--zenoh-config") + 1]).read_text()
    assert "ground.lab:" in conf


def test_an_out_holding_an_earlier_run_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """An ``--out`` with an earlier run's files: exit 2 naming ``--out`` and the fixes (a fresh
    directory, ``--replace``), nothing read, removed or started; an empty log or an empty ``logs/``
    (a rehearsal refused before it ran) is not a run."""
    if (why := rehearse.unavailable()) is not None:
        pytest.skip(f"a rehearsal {why}")  # it says so first, exit 2
    dep = generate(tmp_path)
    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)
    (run / "logs" / "tether-agent-2.log").write_text("")
    assert rehearse.earlier_run(run) == []
    (run / "logs" / "tether-agent-2.log").write_text("real time: tick 0 at 1000.0\n")
    (run / "run.npz").write_bytes(b"an earlier run")
    assert rehearse.earlier_run(run) == ["run.npz", "logs/tether-agent-2.log"]
    done = subprocess.run([sys.executable, "-m", "cli", "rehearse", str(dep.out), "--out", str(run)], cwd=REPO,
                          capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=60)
    assert done.returncode == 2, done.stderr
    assert "--out" in done.stderr and "earlier run" in done.stderr and "--replace" in done.stderr
    assert "fresh directory" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert (run / "run.npz").read_bytes() == b"an earlier run" and not (run / "rehearsal.json").exists()
    assert not (tmp_path / "recorder-out").exists()


def test_logged_safety_events_the_run_file_lacks_are_merged() -> None:
    """What a site logs (agents: ``safety: t = ...``; plants: ``vehicle i: ... at t s: ...``) is read
    back as the run file keeps it; events the recorder heard are not added twice; the merged run's
    events give the exit status ``tether run`` would (3: a failsafe)."""
    from deploy import outcome, sitelogs

    agent = ("2026-01-01 10:00:00,000 WARNING tether: safety: t = 6.52 s: FLYING -> HOLD: agent/2 silent 1.01 s\n"
             "2026-01-01 10:00:02,000 WARNING tether: safety: t = 8.52 s: HOLD -> LAND: held 2.00 s\n"
             "2026-01-01 10:00:02,000 INFO tether: something else: t = 1.00 s\n")
    plant = ("2026-01-01 10:00:00,000 WARNING tether: vehicle 3: FLYING -> HOLD at 6.60 s: no valid command for 0.52 s\n"
             "2026-01-01 10:00:00,000 WARNING tether: vehicle 3: HOLD at 6.70 s: command rejected (stamp: x)\n")
    h = 0.01
    a = sitelogs.agent_events(agent, 3, h)
    p = sitelogs.plant_events(plant, h)
    assert [(e.k, e.vehicle, e.src, e.dst, e.reason) for e in a] == [
        (652, 3, 0, 1, "agent/2 silent 1.01 s"), (852, 3, 1, 2, "held 2.00 s")]
    assert [(e.k, e.vehicle, e.src, e.dst, e.reason) for e in p] == [
        (660, 3, 0, 1, "plant: no valid command for 0.52 s"), (670, 3, 1, 1, "plant: command rejected (stamp: x)")]
    m = load_mission(SECTION4, 10.0)
    run = refsim.simulate(m)
    assert sitelogs.run_events(run, m.safety.max_formation_error) == []
    heard = msgspec.structs.replace(a[0], t=6.5200001)  # the recorder heard the HOLD, not the LAND
    run.safety.events = [heard]
    merged, added = sitelogs.merge(run, a, p)
    assert added == 3 and [(e.k, e.dst) for e in merged.safety.events] == [(652, 1), (852, 2)]
    assert len(merged.safety.plant_events) == 2
    assert sitelogs.merge(merged, a, p)[1] == 0
    events = sitelogs.run_events(merged, m.safety.max_formation_error)
    assert {(e.who, e.what) for e in events} == {("agent/3", "failsafe"), ("plant/3", "failsafe")}
    assert outcome.from_events(events) == outcome.EXIT_FAILSAFE


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to drop to another user")
def test_without_root_it_exits_2_before_anything_starts(tmp_path: Path) -> None:
    dep = generate(tmp_path)
    done = subprocess.run(["setpriv", "--reuid", "65534", "--regid", "65534", "--clear-groups", sys.executable, "-m",
                           "cli", "rehearse", str(dep.out), "--out", str(tmp_path / "run")], cwd=REPO,
                          capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=60)
    assert done.returncode == 2, done.stderr
    assert "needs root" in done.stderr and "sudo" in done.stderr
    assert not (tmp_path / "run").exists()


def test_an_unsafe_out_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """``--out`` another user could write, or a path under a directory they could write without the
    sticky bit: exit 2 naming ``--out``, checked before the deployment is read (no namespace,
    nothing written)."""
    if (why := rehearse.unavailable()) is not None:
        pytest.skip(f"a rehearsal {why}")  # it says so first, exit 2
    dep = generate(tmp_path)
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    for out, says in ((shared, "can be written by other users"), (shared / "run", "no sticky bit")):
        done = subprocess.run([sys.executable, "-m", "cli", "rehearse", str(dep.out), "--out", str(out)], cwd=REPO,
                              capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)),
                              timeout=60)
        assert done.returncode == 2, done.stderr
        assert "--out" in done.stderr and says in done.stderr and "Traceback" not in done.stderr, done.stderr
        assert list(shared.iterdir()) == []


@pytest.mark.slow  # a real tether rehearse, refused after reading the deployment, before any namespace
def test_a_unit_log_that_is_a_link_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """A unit's log (``RUN/logs/<unit>.log``, appended to across restarts) that is a link to a
    root-only file: exit 2 naming it, never followed, before any namespace or process exists."""
    needs_namespaces()
    dep = generate(tmp_path)
    secret = tmp_path / "secret"
    secret.write_text("root only\n")
    secret.chmod(0o600)
    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)
    (run / "logs" / "tether-agent-2.log").symlink_to(secret)
    status, out = run_rehearsal(tmp_path / "rehearse.log", str(dep.out), "--out", str(run), timeout=60)
    assert status == 2, out
    assert "--out" in out and "tether-agent-2.log is a symbolic link" in out and "Traceback" not in out, out
    assert "router up" not in out and not (run / "rehearsal.json").exists()
    assert secret.read_text() == "root only\n" and (run / "logs" / "tether-agent-2.log").is_symlink()
    assert not (tmp_path / "recorder-out").exists()


# =========================================================================== a rehearsal against a loopback run
@dataclass
class Done:
    out: Path
    status: int
    log: str


@pytest.fixture(scope="module")
def rehearsal(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Done]:
    needs_namespaces()
    tmp = tmp_path_factory.mktemp("rehearsal")
    dep = generate(tmp)
    out = tmp / "run"
    with open(tmp / "rehearse.log", "wb") as fh:
        proc = cli("rehearse", str(dep.out), "--out", str(out), "--duration", repr(DURATION), stdout=fh,
                   stderr=subprocess.STDOUT)
        try:
            status = proc.wait(RUN_WITHIN)
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                proc.wait(30)
    yield Done(out, status, read(tmp / "rehearse.log"))


@pytest.fixture(scope="module")
def loopback(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Done]:
    out = tmp_path_factory.mktemp("loopback") / "run"
    done = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--clock", "realtime", "--duration",
                           repr(DURATION), "--out", str(out), "--quiet", "--ns", f"loopback-{os.getpid()}"],
                          cwd=REPO, capture_output=True, text=True, timeout=RUN_WITHIN,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    yield Done(out, done.returncode, done.stderr)


@pytest.mark.slow  # two real-time runs of 20 s: the rehearsal and tether run
def test_a_rehearsal_flies_and_equals_a_loopback_run(rehearsal: Done, loopback: Done) -> None:
    # 0, or 5 as tether run: recorded, a sample lost on the way (DROP streams)
    assert rehearsal.status in (0, 5), rehearsal.log[-4000:]
    assert json.loads((rehearsal.out / "events.json").read_text()) == []
    # 5: recorded, a sample lost (DROP streams); 3: a failsafe fired (measured under load average 13: plant
    # watchdogs on late commands), which leaves the lockstep reference below to compare with
    assert loopback.status in (0, 3, 5), loopback.log[-3000:]
    rh, lb = Run.load(rehearsal.out), Run.load(loopback.out)
    assert rh.meta.source == "runtime-realtime" and rh.meta.namespace == "section4"
    assert rh.xi.shape == lb.xi.shape and rh.clock is not None
    recorded = np.isfinite(rh.xi).all(axis=-1).mean()
    assert recorded > 0.9, f"only {recorded:.1%} of agent ticks recorded"
    ref = refsim.simulate(load_mission(SECTION4, DURATION))
    got, want, ideal = envelope(rh, DURATION / 2), envelope(lb, DURATION / 2), envelope(ref, DURATION / 2)
    print(f"\nformation-error envelope over the last {DURATION / 2:g} s: rehearsal {got:.4f} m, loopback {want:.4f} m "
          f"({100 * (got / want - 1):+.1f} %), lockstep reference {ideal:.4f} m ({100 * (got / ideal - 1):+.1f} %)")
    # a loopback real-time run is itself timing-noisy on a loaded machine (measured here: +26 % on the
    # lockstep reference at load average 9, while the rehearsal beside it was +1.3 %); the rehearsal
    # must be within the tolerance of the loopback run or of the lockstep run it stands for
    assert min(abs(got / want - 1), abs(got / ideal - 1)) <= TOLERANCE, (
        f"rehearsal {got:.4f} m vs loopback {want:.4f} m and lockstep {ideal:.4f} m")
    record = json.loads((rehearsal.out / "rehearsal.json").read_text())
    # every unit of the deployment ran once, in its host's namespace, and ended well
    hosts = {u: v["namespace"] for u, v in record["units"].items()}
    assert hosts["tether-agent-3"] != hosts["tether-agent-4"] and hosts["tether-router"] == hosts["tether-leader-5"]
    assert all(len(u["pids"]) == 1 for u in record["units"].values())
    assert all(u["exits"][-1][1] == 0 for n, u in record["units"].items() if n != "tether-router")
    # the links crossed the bridge: every agent's in-links have offset bounds, none flagged
    # (of the last half second's ticks: real time may lose the very last telemetry sample of an agent)
    assert np.isfinite(rh.clock.offset[-50:, :, 0]).any(axis=0).all(), rh.clock.offset[-50:, :, 0]
    # nothing left behind
    assert record["left_behind"] == [] and left_behind(record) == ([], [])


@pytest.mark.slow  # a rehearsal interrupted mid-run
def test_ctrl_c_tears_everything_down(tmp_path: Path) -> None:
    needs_namespaces()
    dep = generate(tmp_path)
    out = tmp_path / "run"
    with open(tmp_path / "rehearse.log", "wb") as fh:
        proc = cli("rehearse", str(dep.out), "--out", str(out), "--duration", "60", stdout=fh, stderr=subprocess.STDOUT)
        try:
            wait_until(lambda: "real time: tick 0" in read(out / "logs" / "tether-agent-2.log"), 60,
                       "agent 2 to start flying")
            time.sleep(1.0)  # mid-flight
            proc.send_signal(signal.SIGINT)
            status = proc.wait(30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert status == 130, read(tmp_path / "rehearse.log")[-3000:]
    record = json.loads((out / "rehearsal.json").read_text())
    assert len(record["namespaces"]) == 6  # 5 machines and the switch
    assert left_behind(record) == ([], [])
    assert not any(ns.startswith(f"tether-rh{proc.pid}-") for ns in
                   subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split())


# =========================================================================== skew, detected


@pytest.mark.slow  # a real-time run with vehicle 2's clock 30 ms ahead
def test_an_injected_skew_is_detected_within_seconds(tmp_path: Path) -> None:
    """Vehicle 2's host (its agent and plant) 30 ms ahead. Agent 2, which hears agent 1, sees agent
    1's samples arrive ~30 ms late; agent 3, which hears agent 2, sees agent 2's arrive ~30 ms
    before their time (the sender is ahead: certain, on an unloaded machine). One way, each is the
    link's delay plus the skew, and a loaded machine's delay can hide the negative one; the two
    directions through host 2 give the skew itself, ``(e_12 - e_23) / 2`` (agents 1 and 3 share a
    clock), which must come out within 10 ms of 30 ms within 3 s of tick 0. Agent 2 flags its link in
    its log within 3 s, the launcher reports it, and the run file keeps every estimate."""
    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--clock", "realtime", "--duration", "8",
                           "--out", str(out), "--quiet", "--ns", f"skew-{os.getpid()}",
                           "--fault", "skew:agent/2=+0.03", "--fault", "skew:plant/2=+0.03"],
                          cwd=REPO, capture_output=True, text=True, timeout=RUN_WITHIN,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert (out / "run.npz").exists(), done.stderr[-3000:]
    text = read(out / "logs" / "agent-2.log")
    epoch = float(re.search(r"real time: tick 0 at ([0-9.]+)", text).group(1))  # type: ignore[union-attr]
    line = next((ln for ln in text.splitlines() if "clock: link agent/1 -> agent/2" in ln), None)
    assert line is not None and "ms after their time" in line, text[-3000:]
    print(f"\nagent 2 flagged agent/1 {log_time(line) - epoch:.2f} s after tick 0: {line[24:]}")
    assert log_time(line) - epoch < 3.0
    events = json.loads((out / "events.json").read_text())
    assert ("agent/2", "link agent/1") in {(e["who"], e["why"].split(":")[0]) for e in events if e["what"] == "skew"}
    run = Run.load(out)
    clock = run.clock
    assert clock is not None
    col = {int(a): i for i, a in enumerate(run.agent_ids)}

    def series(agent: int, role: str, src: int) -> np.ndarray:
        i = col[agent]
        slot = next(s for s in range(clock.src.shape[1]) if clock.role[i, s] == role and clock.src[i, s] == src)
        return clock.offset[:, i, slot]

    lead = 0.5 * (series(2, "agent", 1) - series(3, "agent", 2))  # skew.pair: host 2's lead on hosts 1 and 3
    right = np.abs(lead - 0.03) <= 0.01
    assert right.any(), np.nanmedian(lead)
    first = float(run.t[np.argmax(right)])
    e23 = float(np.nanmedian(series(3, "agent", 2)[run.t >= 2.0]))
    print(f"host 2's lead estimated {1000 * float(np.nanmedian(lead[run.t >= 2.0])):.1f} ms (right from t = {first:.2f} s); "
          f"agent 3's one-way bound on agent 2 {1000 * e23:+.1f} ms")
    assert first < 3.0
    later = (run.t >= 2.0) & np.isfinite(lead)
    assert np.mean(right[later]) > 0.8, np.nanpercentile(lead[later], [5, 50, 95])
    assert abs(float(np.nanmedian(series(2, "plant", 2)[run.t >= 2.0]))) < 0.02  # one host, one clock: delay only


# =========================================================================== restart and rejoin
KILL_AT = 4.0
"""Mission time [s] the rehearsal SIGKILLs agent 2 (its unit's Restart=on-failure brings it back)."""
REJOIN_WITHIN = 20.0
"""Kill to rejoined [s]: RestartSec=2 of the unit, then a Python process importing numpy and Zenoh and
linking over TLS on two loaded cores (measured 4.3-4.8 s on a quieter minute, 12.9 s at load average 13,
15.0 s at load average 68)."""
RESTART_SAFETY = "\n[safety]\ncmd_cutoff = 30.0\nland_after = 30.0\nmax_formation_error = 500.0\n"
"""The rehearsed mission's changes to Section 4's safety layer: the plant holds (rather than lands,
after the default 2 s) while its agent restarts, the agents the lost one cuts off hold (rather than
land) until it is back, and the formation the restarted agent finds, tens of metres on at Section 4's
6 m/s after a restart of 5-15 s, is not taken for divergence (measured: 82 m after 12.7 s, which the
default 50 m bound lands): a restart takes longer than the defaults allow (docs/deploy.md)."""


def plant_earlier_run(run_dir: Path) -> None:
    """What an earlier rehearsal leaves in its ``--out``: logs with its start instant, its files."""
    (run_dir / "logs").mkdir(parents=True)
    for unit in ("tether-agent-1", "tether-agent-2", "tether-leader-5"):
        (run_dir / "logs" / f"{unit}.log").write_text("2026-01-01 10:00:00,000 INFO tether: real time: tick 0 at "
                                                      "1000.000000 (an earlier run)\n")
    for name in ("run.npz", "rehearsal.json", "events.json"):
        (run_dir / name).write_text("an earlier run\n")


@pytest.mark.slow  # a rehearsal with agent 2 killed mid-run and restarted by its unit's Restart=
def test_a_killed_agent_rejoins_and_the_survivors_stay_bounded(tmp_path: Path) -> None:
    """Section 4 with its ``[safety]`` untouched (the shipped defaults): agent 2 killed, restarted
    by its unit, takes its holding plant over and flies again; no vehicle lands, no formation error
    reaches the divergence bound. Also: hosts named by DNS name (the ground station and vehicles 1
    and 2), an ``--out`` holding an earlier run rehearsed into with ``--replace`` (its logs neither
    read nor kept), and the exit status of ``tether run`` for a process that died: 4."""
    needs_namespaces()
    mission = tmp_path / "mission.toml"
    mission.write_text(SECTION4.read_text())
    assert "[safety]" not in SECTION4.read_text()
    out = tmp_path / "deploy"
    hosts = tmp_path / "hosts.toml"
    hosts.write_text(DNS_HOSTS.format(config=json.dumps(str(out / "hosts" / "{host}")),
                                      out=json.dumps(str(tmp_path / "recorder-out"))))
    gen.generate(mission, out, hosts=hosts)
    run_dir = tmp_path / "run"
    plant_earlier_run(run_dir)
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(out), "--out", str(run_dir), "--duration",
                                   repr(DURATION), "--kill", f"tether-agent-2@{KILL_AT:g}", "--replace")
    assert status == 4, output[-4000:]  # a process died, as tether run says it
    assert "earlier run" not in "".join(read(p) for p in (run_dir / "logs").iterdir())
    events = json.loads((run_dir / "events.json").read_text())
    assert ("tether-agent-2", "died") in {(e["who"], e["what"]) for e in events}
    record = json.loads((run_dir / "rehearsal.json").read_text())
    assert record["epoch"] > 1e9
    a2 = record["units"]["tether-agent-2"]
    assert [rc for _, rc in a2["exits"]] == [-signal.SIGKILL, 0] and len(a2["pids"]) == 2
    assert [k["unit"] for k in record["kills"]] == ["tether-agent-2"]
    text = read(run_dir / "logs" / "tether-agent-2.log")
    back = re.search(r"rejoined a run under way at tick (\d+) \(t = ([0-9.]+) s\): tick 0 at ([0-9.]+)", text)
    assert back is not None, text[-3000:]
    rejoined_at = float(back.group(2))
    print(f"\nagent 2 killed at {KILL_AT:g} s, rejoined at {rejoined_at:.2f} s ({rejoined_at - KILL_AT:.2f} s); "
          f"start instant learnt {1000 * (float(back.group(3)) - record['epoch']):+.1f} ms off the operator's")
    assert rejoined_at - KILL_AT <= REJOIN_WITHIN
    assert abs(float(back.group(3)) - record["epoch"]) < 0.05  # from its plant's samples: a few ms late
    run = Run.load(run_dir)
    col = {int(a): i for i, a in enumerate(run.agent_ids)}
    # through the supervisor (its own log: the run file's events travel in telemetry, which may drop one):
    # HOLD at the first tick back, FLYING once every input is fresh
    modes = [(float(t), src, dst, why) for t, src, dst, why in
             re.findall(r"safety: t = ([0-9.]+) s: (\w+) -> (\w+): (.*)", text)]
    hold = next(e for e in modes if "restarted into a running swarm" in e[3])
    fly = next(e for e in modes if e[3] == "rejoin recovered")
    assert hold[1:3] == ("FLYING", "HOLD") and fly[1:3] == ("HOLD", "FLYING")
    assert rejoined_at - 1e-9 <= hold[0] < fly[0] <= hold[0] + 2.0
    # no jump in command: from the hold command, at most max_accel per second
    k0 = round(hold[0] / run.t[1])
    u = run.u[k0:, col[2]]
    steps = np.linalg.norm(np.diff(u[np.isfinite(u).all(axis=-1)], axis=0), axis=-1)
    assert float(np.max(steps[:50])) <= 20.0 * run.t[1] * 1.001 + 1e-9
    # no divergence, no landing, the formation error within the safety layer's bound
    norm = np.linalg.norm(run.xi, axis=-1)
    for aid in (1, 2, 3, 4):
        assert np.nanmax(norm[:, col[aid]]) < load_mission(SECTION4).safety.max_formation_error, aid
    assert not [e for e in run.safety.events if e.dst >= 2], "a vehicle landed or stopped"
    seen = run.safety.safety_mode[:, col[2]]
    assert seen[seen >= 0][-1] == 0  # flying at its last recorded tick
    around = (run.t >= KILL_AT - 1) & (run.t <= rejoined_at + 3)
    print("max ||xi|| per agent from 1 s before the kill to 3 s after the rejoin: "
          + ", ".join(f"{a}: {np.nanmax(norm[around, col[a]]):.2f} m" for a in (1, 2, 3, 4)))


# =========================================================================== router loss
ROUTER_BACK_WITHIN = 15.0
"""Router killed to its clients linked again [s]: RestartSec=2, the router's start-up, then each
client's reconnection (measured 3.0-7.5 s on two loaded cores)."""


def restart_deployment(tmp_path: Path) -> Path:
    mission = tmp_path / "mission.toml"
    mission.write_text(SECTION4.read_text() + RESTART_SAFETY)
    out = tmp_path / "deploy"
    hosts = tmp_path / "hosts.toml"
    hosts.write_text(HOSTS.format(config=json.dumps(str(out / "hosts" / "{host}")),
                                  out=json.dumps(str(tmp_path / "recorder-out"))))
    gen.generate(mission, out, hosts=hosts)
    return out


@pytest.mark.slow  # a rehearsal with the router killed mid-run and restarted by its unit's Restart=always
def test_a_router_restart_is_survived(tmp_path: Path) -> None:
    """Every client loses every link at once; the safety layer holds (agents: their plant and leader
    fall silent; plants: no commands), the router's unit brings it back, every client links again
    and the run goes on to its end: no process exits early, the recorder writes the run, marked
    incomplete, with the ticks it missed."""
    needs_namespaces()
    out = restart_deployment(tmp_path)
    run_dir = tmp_path / "run"
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(out), "--out", str(run_dir), "--duration",
                                   repr(DURATION), "--kill", f"tether-router@{KILL_AT:g}")
    assert status == 4, output[-4000:]  # a process died
    record = json.loads((run_dir / "rehearsal.json").read_text())
    router = record["units"]["tether-router"]
    assert router["exits"][0][1] == -signal.SIGKILL and len(router["pids"]) == 2
    assert all(len(u["pids"]) == 1 and u["exits"][-1][1] == 0 for n, u in record["units"].items() if n != "tether-router")
    killed = record["kills"][0]["wall"]
    for aid in (1, 2, 3, 4):
        text = read(run_dir / "logs" / f"tether-agent-{aid}.log")
        lines = [ln for ln in text.splitlines() if ln[:4].isdigit()]
        after = [ln for ln in lines if log_time(ln) >= killed - 0.01]
        # holding within 2 s of the kill: the last mode change by then is to HOLD (on a loaded machine
        # it may already have been holding, for another reason, when the router went)
        modes = [ln for ln in lines if "safety: t = " in ln and log_time(ln) <= killed + 2.0]
        back = next((ln for ln in after if f"plant/{aid} is back" in ln), None)
        last = re.search(r"safety: t = [0-9.]+ s: (\w+) -> (\w+)", modes[-1]) if modes else None
        assert last is not None and last.group(2) == "HOLD" and back is not None, text[-3000:]
        assert log_time(back) - killed < ROUTER_BACK_WITHIN
        print(f"\nagent {aid}: holding {max(0.0, log_time(modes[-1]) - killed):.2f} s after the router's kill, its "
              f"plant back {log_time(back) - killed:.2f} s after")
    run = Run.load(run_dir)
    assert run.meta.complete is False and run.meta.samples_recorded < run.meta.samples_expected  # what it missed
    recorded = np.isfinite(run.xi).all(axis=-1).all(axis=1)
    assert recorded[run.t < KILL_AT - 0.5].mean() > 0.9
    assert not recorded[(run.t > KILL_AT + 0.5) & (run.t < KILL_AT + 2.0)].any()  # nothing passed meanwhile
    assert recorded[run.t > KILL_AT + ROUTER_BACK_WITHIN].mean() > 0.8  # and the telemetry flows again
    assert not [e for e in run.safety.events if e.dst == 4], "no vehicle stopped its motors"


@pytest.mark.slow  # a rehearsal with the recorder killed mid-run and restarted by its unit's Restart=
def test_a_restarted_recorder_rejoins_and_the_run_file_says_what_it_missed(tmp_path: Path) -> None:
    needs_namespaces()
    dep = generate(tmp_path)
    run_dir = tmp_path / "run"
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(dep.out), "--out", str(run_dir), "--duration",
                                   repr(DURATION), "--kill", f"tether-recorder-0@{KILL_AT:g}")
    assert status == 4, output[-4000:]  # a process died
    record = json.loads((run_dir / "rehearsal.json").read_text())
    rec = record["units"]["tether-recorder-0"]
    assert [rc for _, rc in rec["exits"]] == [-signal.SIGKILL, 0]
    text = read(run_dir / "logs" / "tether-recorder-0.log")
    back = re.search(r"rejoined a run under way at t = ([0-9.]+) s", text)
    assert back is not None, text[-3000:]
    rejoined_at = float(back.group(1))
    assert rejoined_at - KILL_AT <= REJOIN_WITHIN
    run = Run.load(run_dir)
    recorded = np.isfinite(run.xi).all(axis=-1).all(axis=1)
    print(f"\nrecorder killed at {KILL_AT:g} s, rejoined at {rejoined_at:.2f} s; ticks recorded before "
          f"{recorded[run.t < rejoined_at].mean():.1%}, after {recorded[run.t > rejoined_at + 0.5].mean():.1%}")
    assert run.meta.complete is False and run.meta.samples_recorded < run.meta.samples_expected
    assert not recorded[run.t < KILL_AT].any()  # the first recorder's were lost with it
    assert recorded[run.t > rejoined_at + 0.5].mean() > 0.9


# =========================================================================== a restarted plant resumes
@pytest.mark.slow  # a rehearsal with plant 2 killed mid-run and restarted by its unit's Restart=
def test_a_restarted_plant_resumes_from_its_last_state(tmp_path: Path) -> None:
    """Plant 2's process SIGKILLed at KILL_AT; its unit brings it back, and the new process learns
    the start instant from agent 2's commands, asks agent 2 for its last state (the newest sample
    of plant 2 it holds) and resumes there: no teleport to the mission's initial state, no jump in
    the recorded position; agent 2 holds on its silent plant meanwhile and flies again once it is
    back; the survivors stay bounded."""
    needs_namespaces()
    out = restart_deployment(tmp_path)
    run_dir = tmp_path / "run"
    # 30 s: a restart on two loaded cores took 14 s to come up (load average 14), and the new process
    # then needs 20 of its agent's commands before it knows the start instant
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(out), "--out", str(run_dir), "--duration", "30",
                                   "--kill", f"tether-plant-2@{KILL_AT:g}", timeout=RUN_WITHIN + 40)
    assert status == 4, output[-4000:]  # a process died
    record = json.loads((run_dir / "rehearsal.json").read_text())
    p2 = record["units"]["tether-plant-2"]
    assert [rc for _, rc in p2["exits"]] == [-signal.SIGKILL, 0] and len(p2["pids"]) == 2
    text = read(run_dir / "logs" / "tether-plant-2.log")
    back = re.search(r"rejoined a run under way at tick (\d+) \(t = ([0-9.]+) s\): tick 0 at ([0-9.]+); resuming from "
                     r"the last state on the wire, tick (\d+) \(t = ([0-9.]+) s\) at p = (\[[^\]]*\])", text)
    assert back is not None, text[-3000:]
    first, rejoined_at, epoch, last_k = int(back.group(1)), float(back.group(2)), float(back.group(3)), int(back.group(4))
    print(f"\nplant 2 killed at {KILL_AT:g} s, resumed at {rejoined_at:.2f} s ({rejoined_at - KILL_AT:.2f} s) from its "
          f"state of t = {float(back.group(5)):.2f} s; start instant learnt {1000 * (epoch - record['epoch']):+.1f} ms "
          "off the operator's")
    assert rejoined_at - KILL_AT <= REJOIN_WITHIN and abs(epoch - record["epoch"]) < 0.05
    run = Run.load(run_dir)
    col = {int(a): i for i, a in enumerate(run.agent_ids)}
    assert run.runtime is not None
    p = run.runtime.plant_p[:, col[2]]
    seen = np.isfinite(p).all(axis=-1)
    before = np.flatnonzero(seen & (np.arange(len(run.t)) <= last_k))
    after = np.flatnonzero(seen & (np.arange(len(run.t)) >= first))
    assert before.size and after.size, "plant 2's states before the kill and after the restart were recorded"
    resumed = np.array(json.loads(back.group(6)))
    jump = float(np.linalg.norm(p[after[0]] - p[before[-1]]))
    mission = load_mission(SECTION4, DURATION)
    p0 = np.array(mission.agent(2).p0)
    print(f"plant 2's position: last recorded before the kill {p[before[-1]]} (tick {before[-1]}), resumed at "
          f"{resumed} (tick {last_k}'s), first recorded after the restart {p[after[0]]} (tick {after[0]}; moved "
          f"{jump:.3f} m; the initial state is {float(np.linalg.norm(p[after[0]] - p0)):.1f} m away)")
    # the state resumed from is the plant's own last sample: the very one recorded, when the recorder
    # heard it; a frozen vehicle otherwise, moved since only by the ticks the recorder missed on either
    # side (real time loses samples: a CI run's recording of plant 2 was 0.078 m away around tick 402), at most the recorded speed
    h = mission.dt
    speed = float(np.nanmax(np.linalg.norm(run.runtime.plant_v[:, col[2]], axis=-1)))
    if seen[last_k]:
        assert np.array_equal(p[last_k], resumed), (p[last_k], resumed)
    assert np.linalg.norm(resumed - p[before[-1]]) <= speed * h * (last_k - before[-1]) + 1e-9
    assert np.linalg.norm(p[after[0]] - resumed) <= speed * h * (after[0] - first + 1) + 1e-9
    assert jump < 0.05 + speed * h * (last_k - before[-1] + after[0] - first)
    assert float(np.linalg.norm(p[before[-1]] - p0)) > 1.0  # a teleport would have shown
    a2 = read(run_dir / "logs" / "tether-agent-2.log")
    modes = [(float(t), src, dst, why) for t, src, dst, why in
             re.findall(r"safety: t = ([0-9.]+) s: (\w+) -> (\w+): (.*)", a2)]
    hold = next(e for e in modes if e[0] >= KILL_AT and e[2] == "HOLD" and "plant silent" in e[3])
    fly = next(e for e in modes if e[0] >= rejoined_at - 1e-9 and e[2] == "FLYING")
    print(f"agent 2: HOLD at {hold[0]:.2f} s ({hold[3]}), FLYING at {fly[0]:.2f} s ({fly[3]})")
    assert fly[0] >= rejoined_at - 1e-9
    norm = np.linalg.norm(run.xi, axis=-1)
    assert not [e for e in run.safety.events if e.dst >= 2], "a vehicle landed or stopped"
    tail = norm[run.t >= fly[0] + 5.0]
    around = (run.t >= KILL_AT - 1) & (run.t <= fly[0] + 5.0)
    print("max ||xi|| per agent from 1 s before the kill to 5 s after agent 2 flies again: "
          + ", ".join(f"{a}: {np.nanmax(norm[around, col[a]]):.2f} m" for a in (1, 2, 3, 4))
          + (f"; after: {np.nanmax(tail):.2f} m" if tail.size else ""))
    for aid in (1, 3, 4):
        assert np.nanmax(norm[:, col[aid]]) < 500.0, aid


# =========================================================================== a partitioned site's events
PART_AT, PART_FOR, PART_DURATION = 5.0, 8.0, 18.0
"""The two sites' routers cut apart at mission time PART_AT [s] for PART_FOR [s], in a run of
PART_DURATION [s]."""
PART_SAFETY = "\n[safety]\nland_after = 3.0\n"
"""The field side holds (its only path to the leader is cut) and lands 3 s later, both while cut off."""


@pytest.mark.slow  # a real-time rehearsal of 18 s on two sites with their link cut for 8 s
def test_a_partitioned_sites_events_reach_the_run_file_and_the_exit_status(tmp_path: Path) -> None:
    """Two sites (tests/test_sites.py): the field side's agents 3 and 4 hold and land while their
    router is cut off from the ground's, where the recorder is; their telemetry, and the events it
    carried, are lost meanwhile. The run file holds those events all the same (merged from the
    field side's logs), ``events.json`` lists the failsafe, and the exit status is 3, as
    ``tether run``'s for a failsafe."""
    needs_namespaces()
    from tests.test_sites import write_hosts

    mission = tmp_path / "mission.toml"
    mission.write_text(SECTION4.read_text() + PART_SAFETY)
    path, out = write_hosts(tmp_path)
    gen.generate(mission, out, hosts=path)
    run_dir = tmp_path / "run"
    status, output = run_rehearsal(tmp_path / "rehearse.log", str(out), "--out", str(run_dir), "--duration",
                                   repr(PART_DURATION), "--partition",
                                   f"router-ground:router-field@{PART_AT:g}+{PART_FOR:g}", timeout=140)
    assert status == 3, output[-4000:]  # a failsafe fired; no process died
    merged = re.search(r"(\d+) safety event\(s\) the recorder did not hear .* merged into", output)
    assert merged is not None and int(merged.group(1)) > 0, output[-4000:]
    record = json.loads((run_dir / "rehearsal.json").read_text())
    (cut,) = record["partitions"]
    t_cut, t_heal = cut["cut_mission_time"], cut["heal_mission_time"]
    run = Run.load(run_dir)
    mode = {e.dst: e.t for e in reversed(run.safety.events) if e.vehicle == 3}
    assert 1 in mode and 2 in mode, run.safety.events  # HOLD, LAND
    print(f"\nagent 3 in the run file: HOLD at {mode[1]:.2f} s, LAND at {mode[2]:.2f} s (cut {t_cut:.2f}-{t_heal:.2f} s); "
          f"{merged.group(1)} event(s) merged from the sites' logs")
    assert t_cut <= mode[1] < mode[2] < t_heal
    # the recorder heard nothing of agent 3 at either instant: these came from its own log
    col = {int(a): i for i, a in enumerate(run.agent_ids)}
    heard = np.isfinite(run.xi[:, col[3]]).all(axis=-1)
    assert not heard[round(mode[2] / run.t[1])]
    events = json.loads((run_dir / "events.json").read_text())
    assert ("agent/3", "failsafe") in {(e["who"], e["what"]) for e in events}
    assert not [e for e in events if e["what"] == "died"]
