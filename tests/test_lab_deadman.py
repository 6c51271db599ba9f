"""What a vehicle does when its plant process is killed outright mid-flight, measured on the
software Crazyflie (whose supervisor follows the firmware's ``supervisor.c``): the firmware's
setpoint watchdog levels it out after 0.5 s and cuts its motors after 2 s, in the air. The stock
firmware offers no landing dead-man for a low-level setpoint stream (docs/lab.md, *If the ground
side dies*); this test pins that behaviour down so that the manual's account stays true."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support import REPO, cli_env, free_port, software_crazyflies, wait_until

pytest.importorskip("cflib")

HOVER = """
import sys, time
import msgspec, numpy as np
from plant.crazyflie import CrazyfliePlant
from tether import mission as ms
from tether.catalog import builtin_path

m = ms.load(builtin_path("exp1"))
spec = ms.CrazyfliePlant(uri=sys.argv[1], takeoff_height=1.0)
m = msgspec.structs.replace(m, agents=[msgspec.structs.replace(a, plant=spec) for a in m.agents])
plant = CrazyfliePlant(m, [1]).open()
print("airborne", flush=True)
while True:  # hold: brake the vertical velocity, as the plant process would with its agent's u
    s = plant.state()
    plant.step(np.array([[0.0, 0.0, -2.0 * float(s.v[0, 2])]]))
    time.sleep(0.01)
"""


def _trace(path: Path) -> list[tuple[int, float, float, str]]:
    """``(tick, z [m], vz [m/s], supervisor state)`` per tick of vehicle 0."""
    rows = []
    for line in path.read_text().splitlines():
        f = line.split()
        if len(f) == 10 and f[1] == "0":
            rows.append((int(f[0]), float(f[4]), float(f[7]), f[9]))
    return rows


@pytest.mark.slow
def test_a_killed_plant_process_leaves_the_vehicle_to_the_firmware_watchdog(tmp_path: Path) -> None:
    port = free_port(udp=True)
    trace = tmp_path / "trace.txt"
    with software_crazyflies(["--count", "1", "--base-port", str(port), "--trace", str(trace)]) as sim:
        plant = subprocess.Popen([sys.executable, "-c", HOVER, sim.uris[0]], cwd=REPO, env=cli_env(),
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        try:
            assert plant.stdout is not None
            assert plant.stdout.readline().strip() == "airborne"
            wait_until(lambda: any(s == "flying" and z > 0.9 for _, z, _, s in _trace(trace)[-20:]), 10.0,
                       "a steady hover at 1 m", plant)
            plant.send_signal(signal.SIGKILL)  # no handler runs: nothing lands it
        finally:
            if plant.poll() is None:
                plant.kill()
            plant.wait()
        rows = wait_until(lambda: (r := _trace(trace)) and r[-1][3] == "locked" and r[-1][1] < 0.005 and r,
                          20.0, "the vehicle locked and on the floor")
    level = next(k for k, _, _, s in rows if s == "level_out")
    locked = next(k for k, _, _, s in rows if s == "locked")
    z_cut = next(z for k, z, _, _ in rows if k == locked)
    impact = -min(vz for k, _, vz, _ in rows if k >= locked)
    assert 145 <= locked - level <= 155, (level, locked)  # 0.5 s -> 2 s of setpoint age, in 10 ms ticks
    z_level = next(z for k, z, _, _ in rows if k == level)
    print(f"\nkilled at 1 m: levelled out at z = {z_level:.2f} m, motors cut at z = {z_cut:.2f} m, "
          f"{locked - level} ticks later; hit the floor at {impact:.2f} m/s")
    assert z_cut > 0.1, z_cut  # the motors stop in the air ...
    assert impact > 0.8 * math.sqrt(2 * 9.81 * z_cut), (impact, z_cut)  # ... and it falls freely
