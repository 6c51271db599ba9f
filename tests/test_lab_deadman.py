"""What a vehicle does when its plant process is killed outright mid-flight, measured on the
software Crazyflie (whose supervisor follows the firmware's ``supervisor.c``).

* The plant's guardian (:mod:`plant.deadman`) survives it and lands the vehicle: a controlled
  descent, never a motor cut in the air.
* With the guardian killed too (the ground computer lost), the firmware's setpoint watchdog acts
  alone: it levels the vehicle out after 0.5 s and cuts its motors after 2 s, in the air, and it
  falls (docs/lab.md, *If the ground side dies*); pinned down so that the manual's account stays true.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import REPO, cli_env, free_port, software_crazyflies, wait_until

pytest.importorskip("cflib")

LAND_TIME = 2.0
"""The plant's ``land_time`` [s] in these flights (the plant table's default)."""
WEIGHT = 0.029 * 9.81
"""A Crazyflie 2.1's weight [N]."""

HOVER = """
import sys, time
import msgspec, numpy as np
from plant import deadman
from plant.crazyflie import CrazyfliePlant
from tether import mission as ms
from tether.catalog import builtin_path

m = ms.load(builtin_path("exp1"))
spec = ms.CrazyfliePlant(uri=sys.argv[1], takeoff_height=1.0)
m = msgspec.structs.replace(m, agents=[msgspec.structs.replace(a, plant=spec) for a in m.agents])
plant = CrazyfliePlant(m, [1]).open()
print("airborne", deadman.guardian(spec.land_time).pid, spec.land_time, flush=True)
while True:  # hold: brake the vertical velocity, as the plant process would with its agent's u
    s = plant.state()
    plant.step(np.array([[0.0, 0.0, -2.0 * float(s.v[0, 2])]]))
    time.sleep(0.01)
"""


def _trace(path: Path) -> list[tuple[int, float, float, float, str]]:
    """``(tick, z [m], vz [m/s], thrust [N], supervisor state)`` per tick of vehicle 0."""
    rows = []
    for line in path.read_text().splitlines():
        f = line.split()
        if len(f) == 10 and f[1] == "0":
            rows.append((int(f[0]), float(f[4]), float(f[7]), float(f[8]), f[9]))
    return rows


def _kill_hovering_plant(tmp_path: Path, kill_guardian: bool) -> tuple[list[tuple[int, float, float, float, str]], str]:
    """Fly one software Crazyflie at 1 m from a plant process, SIGKILL it (and its guardian too if
    ``kill_guardian``), and return the simulator's trace once the vehicle is down, and the plant's stderr."""
    port = free_port(udp=True)
    trace = tmp_path / "trace.txt"
    err = tmp_path / "plant.err"
    with software_crazyflies(["--count", "1", "--base-port", str(port), "--trace", str(trace)]) as sim, \
            err.open("w") as err_file:
        plant = subprocess.Popen([sys.executable, "-c", HOVER, sim.uris[0]], cwd=REPO, env=cli_env(),
                                 stdout=subprocess.PIPE, stderr=err_file, text=True)
        guardian = None
        try:
            assert plant.stdout is not None
            said = plant.stdout.readline().split()
            assert said[:1] == ["airborne"] and float(said[2]) == LAND_TIME, (said, err.read_text()[-2000:])
            guardian = int(said[1])
            wait_until(lambda: any(s == "flying" and z > 0.9 for _, z, _, _, s in _trace(trace)[-20:]), 10.0,
                       "a steady hover at 1 m", plant)
            plant.send_signal(signal.SIGKILL)  # no handler runs: the plant lands nothing
            if kill_guardian:
                os.kill(guardian, signal.SIGKILL)
        finally:
            if plant.poll() is None:
                plant.kill()
            plant.wait()
        rows = wait_until(lambda: (r := _trace(trace)) and r[-1][1] < 0.005 and r[-1][3] < 0.01 * WEIGHT
                          and r[-1][4] not in ("flying", "level_out") and r, 20.0, "the vehicle on the floor, motors off")
    if not kill_guardian:  # its own session: wait for it to finish its orders and go
        wait_until(lambda: not Path(f"/proc/{guardian}").exists() or "Z" in Path(f"/proc/{guardian}/stat").read_text().split()[2],
                   10.0, "the guardian's exit")
    return rows, err.read_text()


@pytest.mark.slow
def test_a_killed_plant_process_has_its_vehicle_landed_by_its_guardian(tmp_path: Path) -> None:
    rows, err = _kill_hovering_plant(tmp_path, kill_guardian=False)
    assert "ordered to land" in err, err[-3000:]
    airborne = [r for r in rows if r[1] > 0.1]
    states = {s for _, _, _, _, s in airborne}
    fastest = -min(vz for _, _, vz, _, _ in rows)
    top = max(range(len(rows)), key=lambda i: rows[i][1])
    touchdown = -next(vz for _, z, vz, _, _ in rows[top:] if z < 0.02)  # descending through 2 cm
    weight = WEIGHT
    thrust_air = min(th for _, z, _, th, _ in airborne[-200:])
    print(f"\nkilled at 1 m, landed by the guardian: supervisor states in the air {sorted(states)}, fastest descent "
          f"{fastest:.2f} m/s, {touchdown:.2f} m/s at 2 cm, least thrust in the air's last 2 s "
          f"{thrust_air / weight:.2f} of the weight")
    assert "locked" not in states  # never a motor cut in the air
    assert thrust_air > 0.3 * weight, "motors (nearly) off in the air"
    # land() to 0 m over 2 s from about 1 m: a planned descent averaging 0.5 m/s, peaking near 1.1 m/s
    # (the planner's polynomial) and slowing to touch down; a free fall from 1 m hits at 4.4 m/s
    assert fastest < 2.0 and touchdown < 0.5, (fastest, touchdown)
    assert rows[-1][4] != "locked" or rows[-1][1] < 0.005


@pytest.mark.slow
def test_without_its_guardian_a_killed_plant_leaves_the_vehicle_to_the_firmware_watchdog(tmp_path: Path) -> None:
    rows, _ = _kill_hovering_plant(tmp_path, kill_guardian=True)
    level = next(k for k, _, _, _, s in rows if s == "level_out")
    locked = next(k for k, _, _, _, s in rows if s == "locked")
    z_cut = next(z for k, z, _, _, _ in rows if k == locked)
    impact = -min(vz for k, _, vz, _, _ in rows if k >= locked)
    assert 145 <= locked - level <= 155, (level, locked)  # 0.5 s -> 2 s of setpoint age, in 10 ms ticks
    z_level = next(z for k, z, _, _, _ in rows if k == level)
    print(f"\nkilled at 1 m, and its guardian: levelled out at z = {z_level:.2f} m, motors cut at z = {z_cut:.2f} m, "
          f"{locked - level} ticks later; hit the floor at {impact:.2f} m/s")
    assert z_cut > 0.1, z_cut  # the motors stop in the air ...
    assert impact > 0.8 * math.sqrt(2 * 9.81 * z_cut), (impact, z_cut)  # ... and it falls freely
