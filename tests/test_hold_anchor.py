"""Where HOLD and LAND anchor a vehicle: where the brake brings it to rest, never behind it.

* pure: the agent's supervisor and the plant's watchdog anchor a vehicle that begins HOLD or LAND at
  speed at :func:`tether.failsafe.hold_point` (ahead of it), and agree for the same measurement; a
  formation braking from 9 m/s comes to rest without a vehicle turning back;
* real processes (slow): ``section4`` in real time, the operator's ``tether land`` at 18 s with the
  vehicles at about 8 m/s: the plants' own positions never come within 0.1 m of each other.
"""

from __future__ import annotations

import math
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from agent.safety import Status, Supervisor, anchor
from plant.watchdog import Watchdog
from tests.factories import build
from tests.support import wait_until
from tests.test_runtime import REPO, STARTUP, PlainClient, launch, tether_cmd, wait_for_realtime_start
from tether import failsafe
from tether import mission as ms
from tether import transport as tp
from tether import wire
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run
from tether.wire import FLYING, HOLD, LAND, LANDED

H = 0.01


def section4() -> ms.Mission:
    return load_mission(builtin_path("section4"), 30.0)


def boxed(dim: int) -> ms.Mission:
    """One vehicle, a 4 m geofence box."""
    z = [1.0] if dim == 3 else []
    return build({
        "version": 1, "name": "boxed", "dim": dim, "rate": 1 / H, "duration": 10.0,
        "law": {"kind": "benchmark", "kp0": 1.0, "kv0": 1.0, "gamma_p": 0.05, "gamma_v": 0.05},
        "leader": {"id": 2, "p0": [0.0, 0.0, *z]},
        "agents": [{"id": 1, "p0": [0.0, 0.0, *z], "offset": [0.0] * dim}],
        "edges": [{"from": 2, "to": 1, "weight": 1.0}],
        "safety": {"geofence": {"min": [-4.0] * dim, "max": [4.0] * dim}}})


def command(sup: Supervisor, k: int, p: list[float], v: list[float], status: Status = Status(),
            leader_silent: bool = False) -> list[float]:
    d = len(p)
    return sup.command(k, k * H, p, v, [0.0] * d, [0.0] * d, [1.0] * d, [1.0] * d, True, leader_silent, status)


# --------------------------------------------------------------------------- pure
@pytest.mark.parametrize("why", ["leader", "operator", "plant"])
def test_the_supervisor_anchors_a_vehicle_at_speed_ahead_where_it_comes_to_rest(why: str) -> None:
    m = section4()
    sup = Supervisor(m, 1, (m.leader.id, 4))
    p, v = [12.0, -0.5], [9.0, 0.4]
    command(sup, 0, p, v)
    status = Status(operator="land") if why == "operator" else Status(plant_silent=why == "plant")
    command(sup, 1, p, v, status, leader_silent=why == "leader")
    assert sup.mode == (LAND if why == "operator" else HOLD)
    s = m.safety
    assert sup.p_hold == failsafe.hold_point(p, v, s.hold_kp, s.max_accel)
    ahead = np.subtract(sup.p_hold, p)
    assert float(ahead @ v) > 0 and np.linalg.norm(ahead) == pytest.approx(
        failsafe.stopping_distance(math.hypot(*v), s.hold_kp, s.max_accel), rel=1e-12)
    held = list(sup.p_hold)
    command(sup, 2, [13.0, -0.4], [8.0, 0.3], status, leader_silent=why == "leader")
    assert sup.p_hold == held  # set once, where HOLD or LAND began


def test_the_first_finite_position_is_anchored_with_its_velocity() -> None:
    m = section4()
    sup = Supervisor(m, 1, (m.leader.id, 4))
    u = command(sup, 0, [math.nan, 0.0], [9.0, 0.0], Status(operator="land"))
    assert sup.mode == LAND and sup.p_hold is None and u == [0.0, 0.0]
    command(sup, 1, [3.0, 0.0], [9.0, 0.0], Status(operator="land"))
    assert sup.p_hold == failsafe.hold_point([3.0, 0.0], [9.0, 0.0], m.safety.hold_kp, m.safety.max_accel)


def test_the_watchdog_anchors_where_the_supervisor_does() -> None:
    """Same measurement, same anchor: 2D, 3D (never below the ground), and with a geofence (a
    point beyond the box falls back to the position brought into it)."""
    rng = np.random.default_rng(42)
    for m in (section4(), boxed(2), boxed(3)):
        dog = Watchdog(m.safety, m.dim, H)
        for _ in range(300):
            p = rng.uniform(-6.0, 6.0, m.dim).tolist()
            v = (rng.standard_normal(m.dim) * rng.choice([0.1, 3.0, 25.0])).tolist()
            assert dog.anchor(p, v) == anchor(m.safety, p, v)
            if m.safety.geofence is not None:
                lo, hi = m.safety.geofence.min, m.safety.geofence.max
                inside = all(a <= x <= b for x, a, b in zip(p, lo, hi))
                assert not inside or all(a <= x <= b for x, a, b in zip(dog.anchor(p, v), lo, hi))
        assert dog.anchor([1.0] * m.dim, [0.0] * m.dim) == [1.0] * m.dim
    three = boxed(3).safety
    assert anchor(three, [0.0, 0.0, 1.0], [0.0, 0.0, -3.0])[2] == three.ground  # a dive: held at the ground


@pytest.mark.parametrize("how", ["silent agent", "operator land", "speed"])
def test_the_watchdog_anchors_a_vehicle_at_speed_ahead(how: str) -> None:
    m = section4()
    s = m.safety
    dog = Watchdog(s, 2, H)
    v = [35.0, 0.0] if how == "speed" else [9.0, 1.0]
    p = [0.0, 0.0]
    for k in range(1, 10):  # an agent flying it: valid commands
        dog.offer([0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, p, [9.0, 1.0])
        assert d.mode == FLYING
    k = 10
    if how == "silent agent":
        k = 10 + round(s.cmd_timeout / H) + 1
        d = dog.step(k * H, p, v)
    elif how == "operator land":
        dog.offer([0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, p, v, operator="land")
    else:
        dog.offer([0.0, 0.0], (k - 1) * H, k - 1, k)
        d = dog.step(k * H, p, v)
    assert d.mode == (LAND if how == "operator land" else HOLD)
    assert dog.p_hold == failsafe.hold_point(p, v, s.hold_kp, s.max_accel)
    assert dog.p_hold[0] > 8.0


def test_a_formation_braking_from_9_m_per_s_comes_to_rest_without_turning_back() -> None:
    """Two vehicles 2 m apart along their 9 m/s track (section4's 1 and 3), their plants' watchdogs
    taking the operator's land a tick apart: each brakes monotonically to its anchor, and the gap
    only closes towards its final value (2 m less what the later one flew in that tick). An anchor
    where LAND began left each 3.3 m ahead of it at the turn and flying back."""
    s = section4().safety
    dogs = [Watchdog(s, 2, H), Watchdog(s, 2, H)]
    p = np.array([[2.0, 0.0], [0.0, 0.0]])
    v = np.array([[9.0, 0.0], [9.0, 0.0]])
    gaps, vx = [], []
    for k in range(1, 900):
        for i, dog in enumerate(dogs):
            order = "land" if k >= 100 + i else None  # vehicle 3 (behind) hears it one tick later
            if k < 100 + i:
                dog.offer([0.0, 0.0], (k - 1) * H, k - 1, k)
            d = dog.step(k * H, p[i].tolist(), v[i].tolist(), operator=order)
            u = np.array(d.u) if d.mode != LANDED else np.zeros(2)
            if d.mode == LANDED:
                v[i] = 0.0
            else:
                p[i] += H * v[i] + 0.5 * H * H * u
                v[i] += H * u
        gaps.append(p[0, 0] - p[1, 0])
        vx.append(v[:, 0].copy())
    assert all(dog.mode == LANDED for dog in dogs)
    assert (np.array(vx) >= -1e-9).all()  # never back
    final = 2.0 - 9.0 * H
    assert min(gaps) >= final - 0.01 and abs(gaps[-1] - final) < 0.05


# --------------------------------------------------------------------------- real processes
LAND_AT = 18.0
"""Mission time of the operator's land [s]: section4's vehicles at about 8 m/s."""
SEPARATION = 0.1
"""The separation a swarm that lands must keep [m] (section4 has no [safety.avoid])."""


@pytest.mark.slow
def test_an_operator_land_at_speed_in_real_time_keeps_every_pair_apart(tmp_path: Path) -> None:
    ns = f"anchor-{os.getpid()}"
    port = tp.free_tcp_port()
    attach = tp.loopback_endpoint(port)
    duration = LAND_AT + 10.0
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", f"{duration:g}", "--listen", attach,
                "--insecure") as run:
        wait_for_realtime_start(run)
        client = PlainClient(attach)
        try:
            client.subscribe(f"tether/{ns}/plant/1/state")
            client.next_matching(lambda key, msg: isinstance(msg, wire.PlantState) and msg.t >= LAND_AT,
                                 LAND_AT + STARTUP, f"plant 1 at t = {LAND_AT:g} s")
        finally:
            client.close()
        land = subprocess.run(tether_cmd("land", "--ns", ns, "--connect", attach, "--reason", "test"),
                              cwd=REPO, capture_output=True, text=True, timeout=60)
        assert land.returncode == 0, land.stderr
        wait_until(lambda: run.proc.poll() is not None, duration + STARTUP, "the run to end")
    rec = Run.load(run.out)
    pp = rec.runtime.plant_p if rec.runtime is not None else rec.p
    pv = rec.runtime.plant_v if rec.runtime is not None else rec.v
    k_land = int(np.argmax(rec.t >= LAND_AT - 1.0))
    gaps = [np.linalg.norm(pp[:, i] - pp[:, j], axis=-1) for i in range(pp.shape[1]) for j in range(i + 1, pp.shape[1])]
    gap = np.nanmin(np.array(gaps), axis=0)  # (T,) the closest pair at each tick
    during = gap[k_land:]
    assert np.isfinite(during).sum() > 100, run.launcher_log
    lowest = float(np.nanmin(during))
    speed = float(np.nanmax(np.linalg.norm(pv[k_land], axis=-1)))
    print(f"\nland at {LAND_AT:g} s, vehicles at {speed:.1f} m/s: closest pair {lowest:.3f} m from 1 s before it"
          f" (over the whole run {float(np.nanmin(gap)):.3f} m)")
    assert any(e.dst in (LAND, LANDED) for e in rec.safety.events), run.launcher_log
    assert lowest > SEPARATION, run.launcher_log
