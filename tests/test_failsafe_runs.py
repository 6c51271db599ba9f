"""The swarm fails safe, with real processes in real time: ``tether run failsafe --fault ...``.

The failsafe mission (``tether/missions/failsafe.toml``): leader 5 -> 1, 5 -> 3 and the ring
1 -> 2 -> 3 -> 4 -> 1. Killing agent 2 leaves agent 3 hearing the leader (its edge from 2 is
dropped and kappa re-normalised, it flies on); killing agent 1 leaves agent 2 with no path from
the leader (it holds, then lands). The killed agent's own plant holds on its command watchdog and
lands. A forged leader sample 10^6 m away is rejected by the gate and changes nothing.
Every outcome is read from the run file (modes and events per tick and vehicle), not from logs.
"""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from tether.runfile import Run
from tether.wire import FLYING, HOLD, LAND, LANDED

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parent.parent
DURATION = 14.0
FAULT_AT = 4.0


def fly(tmp: Path, *faults: str, duration: float = DURATION) -> tuple[subprocess.CompletedProcess[str], Run, Path]:
    out = tmp / "run"
    cmd = [sys.executable, "-m", "cli", "run", "failsafe", "--clock", "realtime", "--duration", str(duration),
           "--out", str(out), "--ns", f"fs{uuid.uuid4().hex[:8]}", "--quiet"]
    for f in faults:
        cmd += ["--fault", f]
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=180)
    assert (out / "run.npz").exists(), r.stdout[-3000:] + r.stderr[-3000:]
    return r, Run.load(out), out


def column(run: Run, vehicle: int) -> int:
    return int(np.nonzero(run.agent_ids == vehicle)[0][0])


def first_tick(modes: np.ndarray, wanted: set[int], after: int = 0) -> int | None:
    hits = [k for k in range(after, len(modes)) if int(modes[k]) in wanted]
    return hits[0] if hits else None


def min_separation(run: Run, rows: slice) -> float:
    """From the plants' own states (an agent's telemetry ends with the agent)."""
    assert run.runtime is not None
    p = run.runtime.plant_p
    n = p.shape[1]
    return min(float(np.nanmin(np.linalg.norm(p[rows, i] - p[rows, j], axis=-1)))
               for i, j in itertools.combinations(range(n), 2))


def test_killing_an_agent_others_need_drops_its_edge_and_its_plant_lands(tmp_path: Path) -> None:
    r, run, out = fly(tmp_path, f"kill:agent/2@{FAULT_AT}")
    assert r.returncode == 4, r.stderr[-3000:]  # a process died: the documented status
    fired = json.loads((out / "faults.json").read_text())[0]["fired"]
    h = 1.0 / run.meta.rate
    k0 = int(round(fired / h))
    # agent 3 hears the leader too: the edge from 2 is dropped, kappa re-normalised, it flies on
    drops = [e for e in run.safety.events if e.vehicle == 3 and "edge dropped" in e.reason]
    assert drops and drops[0].t - fired < 1.0 + m_timeout(run), drops
    c3 = column(run, 3)
    survivors = [column(run, i) for i in (1, 3, 4)]
    assert all(int(x) == FLYING for x in run.safety.safety_mode[k0:, c3] if x >= 0)
    # the killed agent's plant: HOLD within cmd_timeout (+ a tick and the measurement's delay), then down
    c2 = column(run, 2)
    hold = first_tick(run.safety.plant_mode[:, c2], {HOLD, LAND, LANDED}, k0)
    assert hold is not None and (hold - k0) * h <= 0.5 + 3 * h, (hold, k0)
    landed = first_tick(run.safety.plant_mode[:, c2], {LANDED}, k0)
    assert landed is not None, "the orphaned vehicle never landed"
    # it braked: no open-loop flight beyond cmd_timeout (its speed falls once it holds)
    assert run.runtime is not None  # the plants' own states (agent 2's telemetry ended with it)
    v2 = np.linalg.norm(run.runtime.plant_v[:, c2, :2], axis=-1)  # horizontal: it descends at land_speed
    assert np.nanmax(v2[hold + int(1.5 / h):]) < 0.2
    # the survivors' formation stays bounded and nobody comes close to anybody
    xi = np.linalg.norm(run.xi[k0:, survivors], axis=-1)
    assert np.nanmax(xi) < 1.0
    assert min_separation(run, slice(k0, None)) > 0.3


def m_timeout(run: Run) -> float:
    return 1.0  # safety.neighbour_timeout of the failsafe mission (the default)


def test_killing_the_only_path_from_the_leader_holds_then_lands_the_orphan(tmp_path: Path) -> None:
    r, run, out = fly(tmp_path, f"kill:agent/1@{FAULT_AT}")
    assert r.returncode == 4, r.stderr[-3000:]
    fired = json.loads((out / "faults.json").read_text())[0]["fired"]
    h = 1.0 / run.meta.rate
    k0 = int(round(fired / h))
    c2 = column(run, 2)
    hold = first_tick(run.safety.safety_mode[:, c2], {HOLD}, k0)
    assert hold is not None and (hold - k0) * h < 1.0 + 0.2, "detection took longer than the neighbour timeout"
    why = [e.reason for e in run.safety.events if e.vehicle == 2 and e.dst == HOLD]
    assert why and "no longer reaches" in why[0]
    land = first_tick(run.safety.safety_mode[:, c2], {LAND, LANDED}, hold)
    assert land is not None and abs((land - hold) * h - 2.0) < 0.2  # land_after
    assert first_tick(run.safety.safety_mode[:, c2], {LANDED}, land) is not None
    z2 = run.p[land:, c2, 2]
    assert np.nanmin(z2) > -0.05  # down to the ground, not through it


def test_a_forged_far_leader_sample_is_rejected_and_changes_no_command(tmp_path: Path) -> None:
    r, run, out = fly(tmp_path, f"forge:leader@{FAULT_AT}", duration=8.0)
    assert r.returncode in (0, 5), r.stdout[-2000:] + r.stderr[-3000:]  # nothing failed (5: a sample lost on the way)
    reasons = list(run.safety.gate_reasons) if run.safety.gate_reasons is not None else []
    assert "jump" in reasons, reasons
    hears_leader = [column(run, 1), column(run, 3)]
    jumps = run.safety.gate_counts[hears_leader, reasons.index("jump")]
    assert np.all(jumps >= 1), jumps
    assert not run.safety.events
    assert np.nanmax(np.abs(run.u)) < 5.0 and np.nanmax(np.linalg.norm(run.xi, axis=-1)) < 2.0
    # and the record itself is clean: the recorder passes the same gate
    assert np.nanmax(np.abs(run.leader_p)) < 100.0


def test_a_frozen_leader_holds_those_that_hear_it_and_they_fly_on_when_it_is_back(tmp_path: Path) -> None:
    r, run, out = fly(tmp_path, f"freeze:leader@{FAULT_AT}+1.5")
    # failsafes fired (3); a freeze shorter than the Zenoh lease is not seen as a lost token (else 4)
    assert r.returncode in (3, 4), r.stderr[-3000:]
    fired = json.loads((out / "faults.json").read_text())[0]["fired"]
    h = 1.0 / run.meta.rate
    k0 = int(round(fired / h))
    for vehicle in (1, 3):  # they hear the leader
        c = column(run, vehicle)
        hold = first_tick(run.safety.safety_mode[:, c], {HOLD}, k0)
        assert hold is not None and (hold - k0) * h < 0.5 + 0.2, (vehicle, hold, k0)  # leader_timeout
        back = first_tick(run.safety.safety_mode[:, c], {FLYING}, hold)
        assert back is not None, f"agent {vehicle} did not fly on after the leader came back"
        assert not any(e.vehicle == vehicle and e.dst in (LAND, LANDED) for e in run.safety.events)
    # nobody strayed while the leader was away
    assert run.runtime is not None
    xi = np.linalg.norm(run.xi[k0:], axis=-1)
    assert np.nanmax(xi) < 1.0


def test_a_partitioned_agent_is_dropped_by_those_who_can_do_without_and_its_plant_lands(tmp_path: Path) -> None:
    r, run, out = fly(tmp_path, f"partition:agent/2@{FAULT_AT}+3")
    assert r.returncode == 4, r.stderr[-3000:]  # a process was cut off
    fired = json.loads((out / "faults.json").read_text())[0]["fired"]
    h = 1.0 / run.meta.rate
    k0 = int(round(fired / h))
    drops = [e for e in run.safety.events if e.vehicle == 3 and "edge dropped" in e.reason]
    assert drops and drops[0].t - fired < 1.0 + 1.5, drops  # neighbour_timeout (or the lease)
    c2 = column(run, 2)
    hold = first_tick(run.safety.plant_mode[:, c2], {HOLD, LAND, LANDED}, k0)
    assert hold is not None and (hold - k0) * h <= 0.5 + 3 * h  # cmd_timeout: its agent's commands stopped
    assert first_tick(run.safety.plant_mode[:, c2], {LAND, LANDED}, hold) is not None  # cut beyond cmd_cutoff
    assert min_separation(run, slice(k0, None)) > 0.3


# =========================================================================== Ctrl-C, a slow descent
def test_after_ctrl_c_the_launcher_waits_while_a_pushed_vehicle_still_descends(tmp_path: Path) -> None:
    """3D, every vehicle pushed up by 0.5 m/s^2 (a cable's steady pull): Ctrl-C orders them to land, and
    a landing against that push takes longer than the nominal bound (the descent from the highest
    start at ``land_speed``, plus 3 s: 6.7 s here; 17 s were measured). The launcher waits as long
    as they still come down, and every vehicle's last recorded mode is LANDED. Before, it stopped them
    at the nominal bound, in the air."""
    import signal
    import time

    from deploy import supervise
    from tests.support import wait_until
    from tether import mission as ms

    text = (REPO / "tether" / "missions" / "failsafe.toml").read_text()
    text = text.replace('offset = [', 'disturbance = { kind = "constant", value = [0.0, 0.0, 0.5] }\noffset = [')
    mission = tmp_path / "pushed.toml"
    mission.write_text(text)
    m = ms.load(mission)
    bound = supervise.land_bound(m)
    out = tmp_path / "run"
    log = tmp_path / "launcher.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "cli", "run", str(mission), "--clock", "realtime",
                                 "--duration", "60", "--out", str(out), "--ns", f"push{uuid.uuid4().hex[:8]}",
                                 "--insecure"], cwd=REPO, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        def flying() -> bool:
            assert proc.poll() is None, log.read_text()[-3000:]
            logs = out / "logs"
            return all("real time: tick 0" in (logs / f"plant-{a}.log").read_text()
                       for a in m.agent_ids if (logs / f"plant-{a}.log").exists()) and \
                len(list(logs.glob("plant-*.log"))) == m.n
        wait_until(flying, 90, "every plant's start")
        # tick 0's wall-clock instant, as the plants logged it: the formation flies 2 s before the order
        epoch = float((out / "logs" / f"plant-{m.agent_ids[0]}.log").read_text().split("real time: tick 0 at ")[1]
                      .split(",")[0])
        wait_until(lambda: time.time() > epoch + 2.0, 30, "2 s of flight")
        proc.send_signal(signal.SIGINT)
        proc.wait(90)
    finally:
        if proc.poll() is None:
            proc.kill()
    said = log.read_text()
    assert "every vehicle reports LANDED or ESTOP after" in said, said[-3000:]
    waited = float(said.split("every vehicle reports LANDED or ESTOP after ")[1].split(" s")[0])
    print(f"\nlanded {waited:.1f} s after Ctrl-C; nominal bound {bound:.1f} s")
    assert waited > bound  # what the nominal bound would have cut off
    rec = Run.load(out)
    for i, aid in enumerate(rec.agent_ids):
        modes = rec.safety.plant_mode[:, i]
        modes = modes[modes >= 0]
        assert modes[-1] == LANDED, (aid, modes[-1])
