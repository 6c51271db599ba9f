"""``tether run MISSION --sitl``: the launcher starts the software Crazyflies the mission needs and
stops them at the end, on Ctrl-C and when it is killed outright: no simulator outlives a run.
Missions that cannot be simulated, and bad simulator options, are refused (exit 2) before anything
starts. Real launcher, real simulators, real cflib in the plants, on four free UDP ports."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path

import pytest

from tests.support import free_port, tether_popen, wait_until
from tether import catalog

pytest.importorskip("cflib")

_BASE = free_port(4, udp=True)
PORTS = range(_BASE, _BASE + 4)
"""This test process's four simulator ports (each parallel test process has its own)."""


def mission(tmp: Path, *, uri0: str | None = None) -> Path:
    text = catalog.builtin_path("exp1_cf").read_text()
    for k, port in enumerate(PORTS):
        shipped = f"udp://127.0.0.1:{19970 + k}"
        assert shipped in text, f"exp1_cf no longer uses {shipped}: update this test"
        text = text.replace(shipped, f"udp://127.0.0.1:{port}")
    if uri0 is not None:
        text = text.replace(f"udp://127.0.0.1:{PORTS[0]}", uri0)
    path = tmp / "exp1_cf_test.toml"
    path.write_text(text)
    return path


def simulators() -> list[int]:
    """Pids of live ``plant.cfsim`` processes serving this test's ports."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            argv = (d / "cmdline").read_bytes().split(b"\0")
            state = (d / "stat").read_text().rpartition(")")[2].split()[0]
        except OSError:
            continue
        if b"plant.cfsim" in argv and state != "Z" and any(str(p).encode() in argv for p in PORTS):
            out.append(int(d.name))
    return out


def test_refused_before_anything_starts(tmp_path: Path) -> None:
    bad = mission(tmp_path, uri0="radio://0/80/2M/E7E7E7E701")
    p = tether_popen("run", str(bad), "--sitl", "--out", str(tmp_path / "a"))
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 2, out
    assert "agent 1.plant.uri" in out and "udp://127.0.0.1:PORT" in out
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--sitl-args", "--noise -3", "--out", str(tmp_path / "b"))
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 2, out
    assert "--sitl-args" in out
    p = tether_popen("run", "exp1", "--sitl", "--out", str(tmp_path / "c"))
    out, _ = p.communicate(timeout=60)
    assert p.returncode == 2 and "no crazyflie agent" in out, out
    assert not simulators()


@pytest.mark.slow  # real launchers, refused before any simulator starts
def test_an_unsafe_out_or_a_linked_simulator_log_is_refused_before_any_simulator_starts(tmp_path: Path) -> None:
    """``--out`` another user could write is refused (exit 2) before anything starts; so is a
    simulator's log (``logs/cfsim-<id>.log``, by its first vehicle) that is a link to a root-only file, which is named,
    never followed, and its target left untouched."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--duration", "2", "--out", str(shared))
    out, _ = p.communicate(timeout=240)
    assert p.returncode == 2, out
    assert "--out" in out and "can be written by other users" in out and "Traceback" not in out
    assert list(shared.iterdir()) == []

    secret = tmp_path / "secret"
    secret.write_text("root only\n")
    secret.chmod(0o600)
    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)
    (run / "logs" / "cfsim-1.log").symlink_to(secret)
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--duration", "2", "--out", str(run))
    out, _ = p.communicate(timeout=240)
    assert p.returncode == 2, out
    assert "--out" in out and "cfsim-1.log is a symbolic link" in out and "Traceback" not in out, out
    assert "software Crazyflies ready" not in out and "router listening" not in out
    assert secret.read_text() == "root only\n" and (run / "logs" / "cfsim-1.log").is_symlink()
    assert not (run / "run.npz").exists()
    assert not simulators()


@pytest.mark.slow
def test_sitl_run_flies_and_stops_its_simulators(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--duration", "2", "--out", str(out_dir))
    out, _ = p.communicate(timeout=240)
    # 0, or on a loaded machine 3 (a plant's failsafe briefly held a vehicle) or 5 (a sample lost on
    # the way to the recorder, in real time): the run happened either way, which is what this checks
    assert p.returncode in (0, 3, 5), out
    assert "software Crazyflies ready" in out and "software Crazyflies stopped" in out
    assert (out_dir / "run.npz").is_file()
    # four vehicles on one simulated dongle: one simulator, one radio host
    assert sorted(f.name for f in (out_dir / "logs").glob("cfsim-*.log")) == ["cfsim-1.log"]
    assert " radio 0: up " in (out_dir / "logs" / "cfsim-1.log").read_text()
    assert not simulators()


@pytest.mark.slow
@pytest.mark.parametrize("how", ["sigint", "sigkill"])
def test_no_simulator_outlives_an_interrupted_or_killed_launcher(tmp_path: Path, how: str) -> None:
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--duration", "60", "--out", str(tmp_path / "run"))
    try:
        wait_until(lambda: len(simulators()) == 1, 60.0, "the simulated radio's simulator")
        time.sleep(1.0)
        if how == "sigint":
            p.send_signal(signal.SIGINT)  # Ctrl-C: the launcher lands the vehicles and stops everything
            p.communicate(timeout=120)
        else:
            # no chance to clean up: SIGKILL to the launcher's process group (its agents and plants);
            # the simulators are in sessions of their own, and their parent-death signal stops them
            os.killpg(p.pid, signal.SIGKILL)
            p.communicate(timeout=30)
        wait_until(lambda: not simulators(), 20.0, "every simulator to exit")
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL)  # whatever of the run is left in its group
        for pid in simulators():  # only ours: they serve this test's ports
            os.kill(pid, signal.SIGKILL)
