"""The in-process lockstep engine against the real runtime, the mission writer, and ``tether sweep``."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agent.law import AgentLaw
from sim import lockstep, refsim, sweep
from tests.factories import random_mission
from tether import checks
from tether import mission as ms
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run

SERIES = ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d")

# every impairment that changes what arrives and when, on every link, changing during the run
DEGRADED = """
[netem]
default = { delay = { constant = 0.03, jitter = 0.02, distribution = "pareto", correlation = 0.3 }, loss = { kind = "gilbert_elliott", p = 0.05, r = 0.3 }, duplicate = 0.05, reorder = { p = 0.2, gap = 3 }, corrupt = { p = 0.02 }, rate = { bytes_per_s = 20000, limit = 4 } }
rules = [{ from = 2, to = 3, start = 1.0, profile = { outages = [[1.2, 1.9]] } }, { to = 1, start = 2.0, profile = "wifi-lossy" }]
[links]
max_age = 0.15
compensate = true
"""


def mission_with(tmp: Path, name: str, section: str, duration: float | None = None) -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(builtin_path("section4").read_text() + section)
    load_mission(path, duration)
    return path


def test_without_a_network_it_is_the_reference_simulator_bit_for_bit() -> None:
    m = load_mission(builtin_path("section4"), 5.0)
    a, b = lockstep.simulate(m), refsim.simulate(m)
    for name in SERIES:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize("engine", ["numpy", "compiled"])
def test_every_agent_hearing_every_other_it_is_still_the_reference_bit_for_bit(engine: str) -> None:
    """In-degrees of 9 and 10 with weights whose products round: the agent's weighted sums, kappa
    and sum_wdelta are added in the reference's order (a BLAS product and a pairwise sum were not)."""
    if engine == "compiled":
        pytest.importorskip("numba")
    m = random_mission(np.random.default_rng(0), 10, disturbance="sinusoid", duration=2.0, dense=True)  # 2D: no ground
    assert min(len(AgentLaw.from_mission(m, a.id).neighbours) for a in m.agents) >= 9
    a, b = lockstep.simulate(m), refsim.simulate(m, engine=engine)
    for name in SERIES:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.slow  # real processes
def test_under_a_degraded_network_it_is_the_distributed_runtime_bit_for_bit(tmp_path: Path) -> None:
    path = mission_with(tmp_path, "degraded", DEGRADED)
    r = subprocess.run([sys.executable, "-m", "cli", "run", str(path), "--out", str(tmp_path / "run"),
                        "--duration", "3", "--quiet"], capture_output=True, text=True, timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    got = Run.load(tmp_path / "run")
    want = lockstep.simulate(load_mission(path, 3.0))
    ideal = lockstep.simulate(load_mission(builtin_path("section4"), 3.0))
    assert np.abs(want.p - ideal.p).max() > 1e-3  # the network changed the run
    for name in SERIES:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    # the same links, the same samples received and the same ages of what was used
    np.testing.assert_array_equal(got.links.src, want.links.src)
    slot = want.links.src > 0
    np.testing.assert_array_equal(got.links.received[-1][slot], want.links.received[slot])
    for name in ("stale", "duplicates", "reordered", "corrupt", "used"):
        np.testing.assert_array_equal(getattr(got.links, name)[-1][slot], getattr(want.links, name)[slot], err_msg=name)
    np.testing.assert_array_equal(want.links.duplicates + want.links.reordered, want.links.stale)
    assert want.links.duplicates.sum() > 0 and want.links.reordered.sum() > 0
    # the agents' own summaries: delivery ratio and age percentiles, consistent with the counts
    delivery = got.links.delivery[-1][slot]
    assert np.all((delivery > 0.5) & (delivery < 1.0)), delivery
    assert np.all(got.links.age_p99[-1][slot] >= got.links.age_p50[-1][slot])
    used = np.isfinite(want.links.age)
    np.testing.assert_array_equal(got.links.age[used], want.links.age[used])
    assert want.links.stale.sum() > 0 and want.links.corrupt.sum() > 0


def test_a_diverging_run_stops_and_says_when() -> None:
    base = load_mission(builtin_path("section4"), 20.0)
    # 300 ms of delay in a loop with gains of 40 that never come down (the benchmark), adapting a
    # thousand times faster than the mission's: within every [safety] limit the checks accept (the
    # saturation at max_accel keeps the error itself bounded), the gains grow until the supervisor's
    # gain_cap catches them
    law = msgspec.structs.replace(base.law, kp0=40.0, kv0=40.0, gamma_p=1000.0, gamma_v=1000.0)
    m = sweep.point_mission(msgspec.structs.replace(base, law=law), sweep.Point("benchmark", 0.0, 300.0, 1.0))
    assert not checks.validate(m)
    run = lockstep.simulate(m)
    at = run.meta.diverged_at
    assert at is not None and 0 < at < 20.0
    k = int(round(at * m.rate))
    assert np.all(np.isfinite(run.xi[: k + 1])) and np.all(np.isnan(run.xi[k + 1:]))
    assert sweep.figures_of_merit(run, m)["diverged"]
    assert [e.reason for e in run.safety.events if e.reason.startswith("divergence")] == \
        ["divergence: gain 1e+03 beyond gain_cap 1000"]


def test_saturation_keeps_the_same_unstable_loop_within_max_accel() -> None:
    base = load_mission(builtin_path("section4"), 20.0)
    law = msgspec.structs.replace(base.law, kp0=40.0, kv0=40.0)
    m = sweep.point_mission(msgspec.structs.replace(base, law=law), sweep.Point("benchmark", 0.0, 300.0, 1.0))
    run = lockstep.simulate(m)
    norms = np.linalg.norm(run.u, axis=-1)
    assert np.all(np.isfinite(run.u)) and norms.max() <= m.safety.max_accel * (1 + 1e-12)
    assert norms.max() > 0.99 * m.safety.max_accel  # it was needed


def test_the_true_formation_error_is_eq8_from_positions_and_differs_under_delay() -> None:
    from sim import metrics
    from tether import graph

    m = load_mission(builtin_path("section4"), 20.0)
    offsets = np.array([a.offset for a in m.agents], dtype=float)
    adjacency = graph.topology(m).adjacency
    ideal = lockstep.simulate(m)
    # with ideal links the agents' own xi is the true one
    np.testing.assert_allclose(metrics.formation_error(ideal, adjacency, offsets), ideal.xi, atol=1e-12)
    delayed = lockstep.simulate(sweep.point_mission(m, sweep.Point("sigma", 0.0, 200.0, 1.0)))
    true = metrics.formation_error(delayed, adjacency, offsets)
    assert np.abs(true - delayed.xi).max() > 0.1  # 200 ms old neighbour data: the agents see another xi


def test_mission_files_round_trip_through_the_writer(tmp_path: Path) -> None:
    for m in (ms.load(builtin_path("section4")), load_mission(mission_with(tmp_path, "deg", DEGRADED))):
        assert ms.loads(ms.dumps(m)) == m


def test_grid_points_have_the_asked_for_loss_and_delay() -> None:
    prof = sweep.link_profile(30.0, 50.0, 5.0)
    ge = prof.loss
    assert ge.p / (ge.p + ge.r) == pytest.approx(0.3) and 1.0 / ge.r == pytest.approx(5.0)
    assert prof.delay.constant == pytest.approx(0.05)
    assert sweep.link_profile(10.0, 0.0, 1.0).loss.p == pytest.approx(0.1)


@pytest.mark.slow  # a sweep
def test_sweep_command_writes_the_table_maps_and_every_point(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    r = subprocess.run([sys.executable, "-m", "cli", "sweep", "section4", "--out", str(out), "--loss", "0,50",
                        "--delay", "0,100", "--burst", "1,4", "--duration", "4", "--jobs", "2"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 2 * 2 * 2 * 2
    assert {row["law"] for row in rows} == {"sigma", "benchmark"}
    for name in ("heatmap-burst1.png", "heatmap-burst4.png", "sweep.md", "sweep.json"):
        assert (out / name).stat().st_size > 0
    ideal = next(row for row in rows if row["law"] == "sigma" and row["loss_pct"] == "0" and row["delay_ms"] == "0")
    assert float(ideal["delivery_ratio"]) == 1.0 and float(ideal["age_p99_ms"]) == 0.0
    lossy = next(row for row in rows if row["law"] == "sigma" and row["loss_pct"] == "50" and row["burst"] == "1"
                 and row["delay_ms"] == "0")
    assert 0.4 < float(lossy["delivery_ratio"]) < 0.6
    # a cell re-run alone from its mission file gives the same figures
    point = out / "points" / "sigma-loss50-delay0-burst1" / "mission.toml"
    again = sweep.figures_of_merit(lockstep.simulate(ms.load(point)), ms.load(point))
    assert float(lossy["ultimate_bound_m"]) == pytest.approx(again["ultimate_bound_m"], rel=1e-5)
    assert json.loads((out / "sweep.json").read_text())["meta"]["engine"] == "inprocess"


@pytest.mark.parametrize("args, message", [
    (["--loss", "0,100"], "--loss: 100 is out of range"),
    (["--delay", "5,x"], "--delay: 'x' is not a number"),
    (["--burst", "0.5"], "--burst: 0.5 is out of range"),
    (["--laws", "sigma,pid"], "--laws: 'pid' is not a law"),
    (["--loss", "10,10"], "--loss: 10,10 repeats a value"),
])
def test_bad_grids_are_refused_before_anything_runs(tmp_path: Path, args: list[str], message: str) -> None:
    r = subprocess.run([sys.executable, "-m", "cli", "sweep", "section4", "--out", str(tmp_path / "o"), *args],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow  # a sweep run by real processes
def test_the_runtime_engine_gives_the_same_map(tmp_path: Path) -> None:
    """``--engine runtime`` runs ``tether run`` for every point: the same figures as in process."""
    m = load_mission(builtin_path("section4"))
    grid = {"loss": [30.0], "delay": [0.0, 50.0], "burst": [1.0], "laws": ("sigma",), "duration": 2.0}
    fast = sweep.sweep(m, tmp_path / "fast", **grid)
    slow = sweep.sweep(m, tmp_path / "slow", engine="runtime", **grid)
    for a, b in zip(fast, slow):
        for key in ("ultimate_bound_m", "ultimate_bound_seen_m", "max_xi_true_m", "peak_gain", "final_kp_mean"):
            assert a[key] == b[key], (key, a, b)
        assert a["delivery_ratio"] == pytest.approx(b["delivery_ratio"], abs=0.02)


@pytest.mark.slow  # two 60 s runs of Section 4
def test_a_sweep_row_says_when_the_safety_layer_acted_and_how_many_it_grounded() -> None:
    base = load_mission(builtin_path("section4"), 60.0)
    calm = sweep.point_mission(base, sweep.Point("sigma", 0.0, 0.0, 1.0), compensate=True)
    row = sweep.figures_of_merit(lockstep.simulate(calm), calm)
    assert row["failsafe_at_s"] is None and row["grounded"] == 0
    # compensating 200 ms of delay oscillates (docs/netem.md): saturated, then one vehicle overspeeds,
    # holds and lands after land_after (2 s here: held for the default 10 s, its neighbours' oscillation
    # carries its |xi| to the divergence bound first, and the row says diverged)
    wild = sweep.point_mission(base, sweep.Point("sigma", 0.0, 200.0, 1.0), compensate=True)
    wild = msgspec.structs.replace(wild, safety=msgspec.structs.replace(wild.safety, land_after=2.0))
    row = sweep.figures_of_merit(lockstep.simulate(wild), wild)
    assert row["failsafe_at_s"] is not None and 0 < row["failsafe_at_s"] < 60.0
    assert row["grounded"] >= 1 and not row["diverged"]
