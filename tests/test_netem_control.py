"""Changing emulated links of a running swarm by control message (``tether netem-set``): real
launcher, real processes, real Zenoh on loopback."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tether import transport as tp
from tether.catalog import builtin_path
from tether.runfile import Run

pytestmark = pytest.mark.slow  # real-time runs of every process, changed by control messages

NETEM = '\n[netem]\ndefault = "ideal"\n'


def start_run(tmp: Path, section: str, duration: float) -> tuple[subprocess.Popen, str]:
    mission = tmp / "m.toml"
    mission.write_text(builtin_path("section4").read_text() + section)
    # authenticated (the default): the tool attaches with the operator identity the launcher writes
    endpoint = f"tls/127.0.0.1:{tp.free_tcp_port()}"
    proc = subprocess.Popen([sys.executable, "-m", "cli", "run", str(mission), "--out", str(tmp / "run"),
                             "--duration", str(duration), "--listen", endpoint, "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    for line in proc.stderr:  # every process up: the agents answer from now on
        if "processes are up" in line:
            break
        assert time.monotonic() < deadline, "the run did not come up"
    else:
        raise AssertionError(f"the run ended before coming up (status {proc.wait()})")
    return proc, str(tmp / "run" / "tls" / "control-0.json5")


def netem_set(endpoint: str, *args: str, timeout: float = 20.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "cli", "netem-set", *args, "--ns", "section4",
                           *(["--zenoh-config", endpoint] if endpoint.endswith(".json5") else ["--connect", endpoint]),
                           "--timeout", str(timeout)], capture_output=True, text=True,
                          timeout=60)


def finish(proc: subprocess.Popen, status: int = 0) -> str:
    try:
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == status, err[-3000:]
    return err


def test_a_link_cut_by_control_message_takes_effect_at_the_asked_time(tmp_path: Path) -> None:
    proc, endpoint = start_run(tmp_path, NETEM + "[links]\nmax_age = 0.2\n", duration=30.0)
    try:
        r = netem_set(endpoint, "{ outages = [[0.0, inf]] }", "--from", "2", "--to", "3", "--at", "20")
        assert r.returncode == 0, r.stdout + r.stderr
        assert "agent 3: 2 -> 3 from t = 20.000 s" in r.stdout, r.stdout
    finally:
        # agent 3 hears only agent 2: cut off for good, it holds once 2 is lost (1 s) and then lands,
        # so a failsafe fired (status 3)
        err = finish(proc, status=3)
    assert re.search(r"agent/3 +failsafe: mode FLYING -> HOLD \(neighbour 2 lost", err), err[-3000:]
    run = Run.load(tmp_path / "run")
    i = list(run.agent_ids).index(3)
    received = run.links.received[:, i, 0]
    t = run.t
    # every sample of 2 up to t = 20 s arrived (ideal link), none after
    assert received[np.searchsorted(t, 19.99)] == np.searchsorted(t, 19.99) + 1
    assert np.all(received[t >= 20.0] == received[np.searchsorted(t, 20.0) - 1])
    # agent 3 then counts agent 2 as in formation (its only in-neighbour): xi_3 = 0 once the data is too old
    np.testing.assert_allclose(run.xi[t >= 20.25, i], 0.0, atol=1e-12)
    assert np.all(np.abs(run.xi[(t > 19.0) & (t < 20.0), i]).max() > 1e-6)
    # the other agents' links are untouched
    j = list(run.agent_ids).index(2)
    assert run.links.received[-1, j, 0] == len(t)


def test_invalid_changes_are_refused_by_the_agents_and_change_nothing(tmp_path: Path) -> None:
    proc, endpoint = start_run(tmp_path, NETEM, duration=30.0)
    try:
        r = netem_set(endpoint, "wifi", "--to", "42", timeout=2.0)
        assert r.returncode == 1 and "agent 42 is not up in namespace 'section4'" in r.stderr, r.stderr
        assert "(agents up: 1, 2, 3, 4)" in r.stderr, r.stderr
        bad = netem_set(endpoint, "wifi", "--from", "99", "--to", "3")
        assert bad.returncode == 1 and "rules[0].from" in bad.stdout and "99" in bad.stdout, bad.stdout + bad.stderr
        unknown = netem_set(endpoint, "wify")
        assert unknown.returncode == 1 and "did you mean `wifi`" in unknown.stdout, unknown.stdout
    finally:
        finish(proc)
    run = Run.load(tmp_path / "run")
    src = run.links.src
    received = run.links.received[-1]
    np.testing.assert_array_equal(received[src > 0], len(run.t))  # nothing changed


def test_a_mission_without_netem_says_how_to_enable_changes(tmp_path: Path) -> None:
    proc, endpoint = start_run(tmp_path, "", duration=30.0)
    try:
        r = netem_set(endpoint, "wifi-lossy", "--to", "1")
        assert r.returncode == 1 and "add `[netem]`" in r.stdout, r.stdout + r.stderr
    finally:
        finish(proc)


def test_a_bad_profile_is_refused_before_connecting() -> None:
    t0 = time.monotonic()
    r = netem_set("tcp/127.0.0.1:9", "{ delay = { constant = -1 } }")
    assert r.returncode == 2 and "delay.constant" in r.stderr, r.stderr
    assert time.monotonic() - t0 < 30
