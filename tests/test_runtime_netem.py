"""The emulated network inside the runtime: identity, determinism, outages, and the agents' policy
for old neighbour data. Real processes, real Zenoh on loopback, lockstep."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.law import neighbour_sample
from sim import refsim
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run

pytestmark = pytest.mark.slow  # every role its own process over an emulated network

SERIES = ("p", "v", "a", "u", "xi", "zeta", "kp", "kv")


def run(mission: Path, out: Path, duration: float = 3.0) -> Run:
    r = subprocess.run([sys.executable, "-m", "cli", "run", str(mission), "--out", str(out),
                        "--duration", str(duration), "--quiet"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    return Run.load(out)


def with_netem(tmp: Path, name: str, section: str) -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(builtin_path("section4").read_text() + "\n" + section)
    load_mission(path)  # valid
    return path


def test_an_ideal_network_changes_nothing_bit_for_bit(tmp_path: Path) -> None:
    mission = with_netem(tmp_path, "ideal", '[netem]\ndefault = "ideal"\n')
    got = run(mission, tmp_path / "ideal")
    ref = refsim.simulate(load_mission(builtin_path("section4"), 3.0))
    for name in SERIES:
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)


def test_a_degraded_network_is_deterministic_for_a_seed_and_changes_the_run(tmp_path: Path) -> None:
    mission = with_netem(tmp_path, "lossy", '[netem]\ndefault = "lossy-burst"\nlog = true\n')
    a = run(mission, tmp_path / "a")
    b = run(mission, tmp_path / "b")
    # the decision log is written, identical across runs, and agrees with what the agents received
    log_a = (tmp_path / "a" / "netem.jsonl").read_text()
    assert log_a == (tmp_path / "b" / "netem.jsonl").read_text()
    decisions = [json.loads(line) for line in log_a.splitlines()]
    events = {d["event"] for d in decisions}
    assert "deliver" in events and "drop:loss" in events
    end = a.t[-1]
    for i, aid in enumerate(a.agent_ids):
        for n, src in enumerate(a.links.src[i]):
            if src == 0:
                continue
            due = [d for d in decisions if d["dst"] == aid and d["src"] == src and d["at"] is not None
                   and d["at"] <= end + 1e-9 and "corrupt" not in d["event"]]
            assert a.links.received[-1, i, n] == len(due), (aid, src)
    for name in (*SERIES, "law_state", "link_age", "link_received", "link_stale"):
        x = a.arrays()[name] if name.startswith("link_") else getattr(a, name)
        y = b.arrays()[name] if name.startswith("link_") else getattr(b, name)
        np.testing.assert_array_equal(x, y, err_msg=name)
    ref = refsim.simulate(load_mission(builtin_path("section4"), 3.0))
    assert np.abs(a.p - ref.p).max() > 1e-6  # the network did something
    age = a.links.age[np.isfinite(a.links.age)]
    assert age.max() >= 0.01  # delayed and lost samples are older than a period
    # received samples per link are fewer than the ticks sent (about 9 % of them are lost in bursts)
    received = a.links.received[-1]
    assert np.nanmax(received) < len(a.t)


def test_an_outage_makes_an_agent_treat_its_neighbour_as_in_formation(tmp_path: Path) -> None:
    # agent 3 hears only agent 2; it hears nothing in [1.0, 2.0) s; max_age 0.2 s
    mission = with_netem(tmp_path, "outage",
                         '[links]\nmax_age = 0.2\n[netem]\nrules = [{ to = 3, profile = { outages = [[1.0, 2.0]] } }]\n')
    r = run(mission, tmp_path / "outage")
    i = list(r.agent_ids).index(3)
    age = r.links.age[:, i, 0]
    t = r.t
    assert np.all(age[t < 1.0] == 0.0)
    inside = (t >= 1.3) & (t < 2.0)
    assert np.all(age[inside] > 0.2)  # the newest sample held is older than max_age...
    # ... so agent 3 counts agent 2 as in formation: its xi is kappa (p_3 - h_3) - (p_3 - delta_32 - h_2) = 0
    np.testing.assert_allclose(r.xi[inside, i], 0.0, atol=1e-12)
    used = r.links.received[:, i, 0]
    assert np.all(np.diff(used[inside]) == 0)  # nothing arrives during the outage
    assert np.all(age[t >= 2.05] == 0.0)  # and it is back after it


def test_neighbour_sample_policy() -> None:
    p, v, a, delta = np.array([1.0, 2.0]), np.array([0.5, 0.0]), np.array([0.1, 0.2]), np.array([1.0, -1.0])
    sample = (np.array([3.0, 3.0]), np.array([1.0, 2.0]), np.array([0.5, -0.5]))
    pj, vj, aj, used = neighbour_sample(p, v, a, delta, sample, 0.1, 0.5, False)
    assert used and np.array_equal(pj, sample[0]) and np.array_equal(vj, sample[1])
    pj, vj, aj, used = neighbour_sample(p, v, a, delta, sample, 0.1, 0.5, True)
    np.testing.assert_allclose(pj, [3.0 + 0.1 + 0.5 * 0.01 * 0.5, 3.0 + 0.2 - 0.5 * 0.01 * 0.5], atol=1e-15)
    np.testing.assert_allclose(vj, [1.05, 1.95], atol=1e-15)
    for stale in (None, 0.6, float("nan")):
        smp = None if stale is None else sample
        pj, vj, aj, used = neighbour_sample(p, v, a, delta, smp, 0.6 if stale is None else stale, 0.5, True)
        assert not used
        np.testing.assert_array_equal(pj, p - delta)
        np.testing.assert_array_equal(vj, v)
        np.testing.assert_array_equal(aj, np.zeros_like(a))  # never the agent's own acceleration


@pytest.mark.parametrize("bad, field", [
    ('[netem]\ndefault = "wifi-lossyy"\n', "netem.default"),
    ('[netem]\nrules = [{ to = 42, profile = "wifi" }]\n', "netem.rules[0].to"),
    ('[links]\nmax_age = 0.0\n', "links.max_age"),
])
def test_bad_network_sections_name_the_field(tmp_path: Path, bad: str, field: str) -> None:
    from tether import mission as ms

    path = tmp_path / "bad.toml"
    path.write_text(builtin_path("section4").read_text() + "\n" + bad)
    with pytest.raises(ms.MissionError) as info:
        ms.load(path)
    assert field in [f for f, _ in info.value.problems], info.value.problems
