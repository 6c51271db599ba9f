"""The ``tether`` command as a user runs it: real subprocesses, exit codes, files on disk."""

import json
from pathlib import Path

import numpy as np
import pytest

from tests.support import tether
from tether.runfile import FORMAT_VERSION, Links, Run, RunMeta

BAD = """version = 1
name = "bad"
dim = 2
rate = 100.0
duration = 1.0
edges = [{ from = 1, to = 2 }]
[law]
kind = "sigma"
kp0 = 0.5
kv0 = 1.0
gamma_p = 0.1
gamma_v = 0.1
sigma = 0.1
[leader]
id = 9
p0 = [0.0, 0.0]
[[agents]]
id = 1
p0 = [0.0, 0.0]
offset = [1.0, 0.0]
[[agents]]
id = 2
p0 = [0.0, 0.0]
offset = [0.0, 1.0]
"""


def test_check_prints_a_summary() -> None:
    r = tether("check", "section4")
    assert r.returncode == 0, r.stderr
    assert "4 agents" in r.stdout and "Assumption 1 holds" in r.stdout
    lines = [ln.split() for ln in r.stdout.splitlines() if ln.strip()[:1].isdigit()]
    by_id = {ln[0]: ln for ln in lines}
    assert by_id["1"][1:3] == ["2", "yes"] and by_id["2"][1:3] == ["1", "no"]  # kappa, hears leader


def test_check_rejects_a_bad_mission_with_status_2_naming_the_fields(tmp_path: Path) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(BAD)
    r = tether("check", str(f))
    assert r.returncode == 2
    assert "law.kp0" in r.stderr and ">= 1" in r.stderr
    assert "Assumption 1" in r.stderr and "agents 1 and 2" in r.stderr  # names both unreachable agents
    assert r.stdout == ""


def test_check_missing_file_is_status_2(tmp_path: Path) -> None:
    r = tether("check", str(tmp_path / "nope.toml"))
    assert r.returncode == 2 and "cannot be read" in r.stderr


SWAP = Path(__file__).resolve().parents[1] / "tether" / "missions" / "swap.toml"


def test_check_warns_of_vehicles_that_start_on_or_below_the_ground(tmp_path: Path) -> None:
    r = tether("check", str(SWAP))  # every vehicle starts at z = 1 m above the ground at 0
    assert r.returncode == 0 and "warning" not in r.stderr, r.stderr
    text = SWAP.read_text()
    low = tmp_path / "low.toml"
    low.write_text(text.replace("p0 = [-2.0, 0.03, 1.0]", "p0 = [-2.0, 0.03, 0.0]")
                   .replace("p0 = [2.0, -0.03, 1.0]", "p0 = [2.0, -0.03, -0.5]")
                   .replace("p0 = [0.0, 0.0, 1.0]", "p0 = [0.0, 0.0, -1.0]"))
    r = tether("check", str(low))
    assert r.returncode == 0, r.stderr  # a warning: a vehicle may take off from its pad
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ")]
    assert len(lines) == 2, r.stderr
    below, on = lines
    assert "below the ground" in below and "agent 3" in below and "the leader" in below and "-0.5" in below
    assert "agent 1" not in below and "agent 2" not in below
    assert "on the ground" in on and "agent 1" in on and "agent 3" not in on
    assert "4 agents" in r.stdout


def test_simulate_writes_a_run_metrics_and_figures(tmp_path: Path) -> None:
    r = tether("simulate", "section4", "--out", str(tmp_path), "--duration", "5")
    assert r.returncode == 0, r.stderr
    run = Run.load(tmp_path / "run.npz")
    assert run.p.shape == (501, 4, 2) and run.meta.source == "reference-discrete"
    assert np.all(np.isfinite(run.kp))
    assert json.loads((tmp_path / "metrics.json").read_text())["peak_kp"] >= 1.0
    for name in ("errors_gains.png", "velocities.png", "xy.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    r2 = tether("plot", str(tmp_path), "--out", str(tmp_path / "again"))
    assert r2.returncode == 0, r2.stderr
    assert (tmp_path / "again" / "xy.png").exists()


def test_simulate_says_it_does_not_fly_collision_avoidance(tmp_path: Path) -> None:
    """The reference simulator computes the law alone: for a mission with ``[safety.avoid]`` it says
    so (and names the command that flies it), where it once flew the swap through a collision silently;
    a mission without it gets no such word."""
    r = tether("simulate", "swap", "--out", str(tmp_path / "swap"), "--duration", "1", "--no-figures", "--no-mcap")
    assert r.returncode == 0, r.stderr
    assert "[safety.avoid]" in r.stderr and "tether run swap" in r.stderr, r.stderr
    r = tether("simulate", "section4", "--out", str(tmp_path / "s4"), "--duration", "1", "--no-figures", "--no-mcap")
    assert r.returncode == 0 and "safety.avoid" not in r.stderr, r.stderr


def test_simulate_engines_write_the_same_run(tmp_path: Path) -> None:
    pytest.importorskip("numba")
    runs = {}
    for engine in ("numpy", "compiled"):
        r = tether("simulate", "section4", "--out", str(tmp_path / engine), "--duration", "3", "--engine", engine,
                   "--no-figures", "--no-mcap")
        assert r.returncode == 0, r.stderr
        runs[engine] = Run.load(tmp_path / engine / "run.npz")
    for f in ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d"):
        np.testing.assert_array_equal(getattr(runs["compiled"], f), getattr(runs["numpy"], f), err_msg=f)


def test_reproduce_section4_short(tmp_path: Path) -> None:
    r = tether("reproduce", "section4", "--out", str(tmp_path), "--duration", "20")
    assert r.returncode == 0, r.stderr
    table = json.loads((tmp_path / "metrics.json").read_text())
    assert set(table) == {"sigma-discrete", "benchmark-discrete"}
    assert (tmp_path / "fig4.png").stat().st_size > 20_000
    bench = Run.load(tmp_path / "benchmark-discrete")
    assert np.all(np.diff(bench.kp, axis=0) >= 0)
    assert "benchmark gains never decrease: yes" in (tmp_path / "metrics.md").read_text()


def test_run_file_round_trip(tmp_path: Path) -> None:
    run = Run.empty(3, [4, 7], 3, RunMeta(mission="x", source="reference-discrete", law="sigma", rate=10.0, steps=2))
    run.t[:] = [0.0, 0.1, 0.2]
    run.p[:] = np.arange(18.0).reshape(3, 2, 3)
    run.links = Links.empty(3, 2, 1)
    run.links.delivery[:] = 1.0
    run.save(tmp_path / "r" / "run.npz")
    back = Run.load(tmp_path / "r")
    np.testing.assert_array_equal(back.p, run.p)
    np.testing.assert_array_equal(back.agent_ids, [4, 7])
    assert back.meta.mission == "x" and back.meta.format_version == FORMAT_VERSION
    np.testing.assert_array_equal(back.links.delivery, 1.0)


def test_netem_set_without_a_reachable_router_says_so_in_one_line() -> None:
    from tether import transport as tp

    port = tp.free_tcp_port()  # nothing listens there
    r = tether("netem-set", "--ns", "nobody", "--connect", f"tcp/127.0.0.1:{port}", "--connect-timeout", "1", "wifi")
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "--connect" in lines[0], r.stderr
    assert f"127.0.0.1:{port}" in lines[0]
