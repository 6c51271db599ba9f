"""The red-team suite's short form: two forged inputs against one real ``section4`` run in real time.

The attacker is ``bench/redteam.py``'s (a plain Zenoh client of the run's router, ``--insecure``), the
figures its analysis (the true formation error from the plants' own samples and the leader's analytic
profile, the envelope, the reactions): one absurdly stamped command on ``agent/2/cmd`` at 4 s, then
one ``plant/2/state`` saying ESTOP at 10 s. The full table is ``python bench/redteam.py``
(``docs/results/redteam.md``).

The defended behaviour: the plant drops a command whose stamp is not its tick's and says so; an agent
never e-stops its real plant because of a report it heard; no vehicle leaves its envelope; both
forgeries are detected within DETECT_WITHIN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from bench import redteam
from tether import catalog
from tether.node import load_mission

DURATION = 20.0
"""Mission length [s] of the run."""
STAMP_AT, ESTOP_AT = 4.0, 10.0
"""When each forgery is sent [s of mission time]."""
DETECT_WITHIN = 2.0
"""A defended swarm reacts to a forgery within this [s] (an event that is not the harm itself, a
gate rejection, a watchdog rejection)."""
ERR_LAST10 = 5.0
"""Largest true formation error over the last 10 s of a defended run [m]: an undisturbed run on a
host loaded by other work reached 3.0 m (vehicles held for late ticks and caught up; the ``none``
row of ``docs/results/redteam.md``), a vehicle that flies away reaches tens of metres."""


@dataclass(frozen=True)
class Attacked:
    out: Path
    status: int
    res: dict[str, Any]
    stderr: list[str]


@pytest.fixture(scope="module")
def attacked(tmp_path_factory: pytest.TempPathFactory) -> Attacked:
    """One real run (ten processes) under both attacks, analysed; bounded by ``redteam.launch``."""
    m = load_mission(catalog.resolve(redteam.MISSION), None)
    out = tmp_path_factory.mktemp("redteam") / "run"
    plans = {"stamp": redteam.Plan(at=STAMP_AT), "estop": redteam.Plan(at=ESTOP_AT)}
    launched = redteam.launch(out, plans, m, DURATION, grace=60.0)
    (out / "redteam.json").write_text(f'{{"duration": {DURATION}}}\n')
    res = redteam.analyse(out, "stamp", plans["stamp"], status=launched.status)
    return Attacked(out, launched.status, res, launched.stderr)


def reactions(res: dict[str, Any], since: float, vehicle: int) -> list[str]:
    """What the swarm did about a forgery on ``vehicle`` sent at ``since`` within DETECT_WITHIN: its
    agent's or plant's events (but an ESTOP, which is the harm, not a detection), and gate rises."""
    found = [f"{e['who']} {e['from']}->{e['to']}: {e['why']}" for e in res["events"]
             if since - 0.01 <= e["t"] <= since + DETECT_WITHIN and e["who"] in (f"a{vehicle}", f"p{vehicle}")
             and e["to"] != "ESTOP"]
    found += [f"a{i} gate at {t:.2f} s" for t, i in res["gate_rises"] if since - 0.01 <= t <= since + DETECT_WITHIN]
    return found


@pytest.mark.slow
def test_the_attack_was_made_and_the_truth_heard(attacked: Attacked) -> None:
    """The harness itself: both forgeries left, the run ended by itself, and the plants' genuine samples
    (the truth every other figure is computed from) were heard for most ticks."""
    res = attacked.res
    assert attacked.status >= 0 and not any("outlived" in line for line in attacked.stderr), attacked.stderr[-10:]
    assert set(res["sent"]) == {"stamp", "estop"}, res["sent"]
    assert STAMP_AT <= res["sent"]["stamp"] < STAMP_AT + 1.0
    assert ESTOP_AT <= res["sent"]["estop"] < ESTOP_AT + 1.0
    assert res["heard_plant_ticks"] > 0.8 * res["ticks"], (res["heard_plant_ticks"], res["ticks"])
    assert (attacked.out / "run.npz").exists()


@pytest.mark.slow
def test_no_vehicle_leaves_its_envelope(attacked: Attacked) -> None:
    assert attacked.res["left"] == {}, attacked.res["left"]
    assert attacked.res["speed_max"] <= 30.0


@pytest.mark.slow
def test_a_forged_estop_report_stops_no_motor(attacked: Attacked) -> None:
    """Only the operator's e-stop and the agent's own supervisor may stop a vehicle's motors."""
    stopped = [e for e in attacked.res["events"] if e["to"] == "ESTOP"]
    assert not stopped, stopped
    assert not any(s.startswith("E") for s in attacked.res["end"].values()), attacked.res["end"]


@pytest.mark.slow
def test_formation_error_stays_bounded(attacked: Attacked) -> None:
    res = attacked.res
    assert math.isfinite(res["err_last10"]) and res["err_last10"] <= ERR_LAST10, res["err_last10"]


@pytest.mark.slow
def test_each_forgery_is_detected(attacked: Attacked) -> None:
    res = attacked.res
    stamp = reactions(res, res["sent"]["stamp"], 2)
    assert stamp or res["watchdog"], "the absurdly stamped command went unnoticed"
    assert reactions(res, res["sent"]["estop"], 2), "the forged ESTOP report went unnoticed"
