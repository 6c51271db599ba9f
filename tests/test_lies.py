"""Plausible lies against a real swarm: forged mode reports and a drifting leader.

Each case is a real-time ``tether run section4 --insecure`` that a plain Zenoh client joins on
loopback; it forges samples on a victim's key (copies of the genuine ones it hears, changed) for a
stretch of the run, then the run file is read back. What is asserted:

* ``agent/1/state`` says HOLD (a copy of each genuine sample, same tick, mode HOLD) for 5 s: no
  vehicle is e-stopped, the mode changes are few (the forged stream is judged suspect, not followed
  sample by sample) and no two vehicles come within 0.3 m;
* one ``plant/2/state`` says ESTOP (the next tick's sample, mode ESTOP): agent 2 and plant 2 never
  leave FLYING, and the agent counts the contradiction;
* the leader drifts at 0.5 m/s (each forged sample the next tick's, a plausible step ahead of the
  genuine one): agent 1 rejects it as ``profile``, judges the leader's stream suspect, holds, and no
  vehicle is steered more than 2 m sideways from where the true leader's formation wants it;
* ``agent/2/cmd`` carries, for 1 s, a copy of each genuine command with u = (20, 0): plant 2 flies
  neither command of a contested tick, says so, holds while no command is trusted, and vehicle 2
  stays within 4 m more than before of its slot (it holds while the formation flies on).

The forger forges only from genuine samples it heard: it hears its own forgeries too, and one that
forged from those would flood the key.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np
import pytest

from leader import profile
from tests.test_runtime import PlainClient, launch, wait_for_realtime_start, STARTUP
from tests.support import wait_until
from tether import transport as tp
from tether import wire
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run

pytestmark = pytest.mark.slow

AT, FOR, DURATION = 6.0, 5.0, 20.0
"""The forgery starts at AT [s of mission time] and lasts FOR [s]; the run lasts DURATION [s]."""

Sample = wire.State | wire.PlantState | wire.Command
Forge = Callable[[Sample, float], Sample]
"""A forged sample from a genuine one and the attack's age [s]."""


def hold(msg, age):  # type: ignore[no-untyped-def]
    return msgspec.structs.replace(msg, seq=msg.seq + 1, mode=wire.HOLD)


def estop(msg, age):  # type: ignore[no-untyped-def]
    return msgspec.structs.replace(msg, seq=msg.seq + 1, k=msg.k + 1, t=(msg.k + 1) * 0.01, mode=wire.ESTOP)


def drift(msg, age):  # type: ignore[no-untyped-def]
    h = 0.01
    p = [x + v * h for x, v in zip(msg.p, msg.vel)]
    p[1] += 0.5 * age  # 0.5 m/s sideways, each sample a plausible step ahead of the genuine one
    return msgspec.structs.replace(msg, seq=msg.seq + 1, k=msg.k + 1, t=(msg.k + 1) * h, p=p)


def push(msg, age):  # type: ignore[no-untyped-def]
    return msgspec.structs.replace(msg, u=[20.0, 0.0])  # the genuine command of that tick, u replaced


CASES = {
    "agent-hold": ("agent/1/state", hold, FOR),
    "plant-estop": ("plant/2/state", estop, 0.0),  # one sample
    "leader-drift": ("leader/5/state", drift, FOR),
    "cmd-push": ("agent/2/cmd", push, 1.0),
}


def attack(tmp: Path, case: str) -> tuple[Run, str, int]:
    """The run file, plant 2's log and the number of samples forged."""
    key, forge, span = CASES[case]
    ns = f"lies-{case}-{os.getpid()}"
    attach = tp.loopback_endpoint(tp.free_tcp_port())
    with launch(tmp, ns, "--clock", "realtime", "--duration", f"{DURATION:g}", "--listen", attach,
                "--insecure") as run:
        wait_for_realtime_start(run)
        client = PlainClient(attach)
        try:
            full = f"tether/{ns}/{key}"
            client.subscribe(full)
            pub = client.publisher(full)
            _, first = client.next_matching(lambda k, m: k == full, STARTUP, f"a sample on {key}")
            forged = 0
            start: float | None = None
            mine: dict[tuple[int, int], Sample] = {}
            """Every sample this forger published, by (k, seq): it hears them too, and forges only
            from genuine samples (a forgery of a forgery would flood the key, one more a tick). The
            contents tell them apart too: a forgery of the next tick takes the number the genuine
            sample of that tick will have."""
            while True:  # forge from each genuine sample heard, from mission time AT for span seconds
                _, msg = client.next_matching(lambda k, m: k == full and m.sender == first.sender, STARTUP, key)
                if msg.t < AT or mine.get((msg.k, msg.seq)) == msg:
                    continue
                start = msg.t if start is None else start
                age = msg.t - start
                if age > span:
                    break
                lie = forge(msg, age)
                mine[(lie.k, lie.seq)] = lie
                pub.put(wire.encode(lie))
                forged += 1
            assert forged >= 1
        finally:
            client.close()
        run.wait(STARTUP + 2 * DURATION)
        return Run.load(run.out), run.child_log("plant/2"), forged


def true_error(rec: Run, m) -> np.ndarray:  # type: ignore[no-untyped-def]
    """Per tick and vehicle, the distance [m] from the slot the true leader's profile gives it."""
    ref = profile.build(m.leader, m.dim)
    lp, _, _ = ref(rec.t)
    offsets = np.array([a.offset for a in m.agents])
    return np.linalg.norm(rec.p - (np.asarray(lp)[:, None, :] + offsets[None]), axis=-1)


def mode_changes(rec: Run) -> int:
    return len([e for e in rec.safety.events if e.src != e.dst])


SEPARATION, SEPARATION_LOADED = 0.3, 0.1
"""Least distance between two vehicles [m]: while an attack lasts and for :data:`SETTLE` after it,
and over the whole run. A busy host stalls every process at once now and then (every agent says
"plant silent" at the same instant: the machine, not the attack; measured 0.19-0.28 m with a load
average of 13 on 2 cores, the attack long over); the issue's floor for load is 0.1 m."""
SETTLE = 3.0
"""Seconds after an attack ends that its consequences are judged over."""


def min_separation(rec: Run, since: float = 0.0, until: float = math.inf) -> float:
    span = (rec.t >= since) & (rec.t <= until)
    p = rec.p[span]
    n = p.shape[1]
    return min(float(np.nanmin(np.linalg.norm(p[:, i] - p[:, j], axis=-1))) for i in range(n) for j in range(i + 1, n))


@pytest.mark.parametrize("case", [
    "agent-hold", "plant-estop", "leader-drift", "cmd-push"])
def test_a_plausible_lie_is_caught_or_bounded(tmp_path: Path, case: str) -> None:
    m = load_mission(builtin_path("section4"))
    rec, plant_log, forged = attack(tmp_path, case)
    err = true_error(rec, m)
    modes = rec.safety.safety_mode
    _, _, span = CASES[case]
    near = min_separation(rec, AT, AT + span + SETTLE)
    print(f"{case}: {forged} forged; true error max {np.nanmax(err):.3f} m, mode changes {mode_changes(rec)}, "
          f"min separation {near:.3f} m during the attack and {SETTLE:g} s after, {min_separation(rec):.3f} m "
          f"overall, events {[(e.vehicle, round(e.t, 2), e.reason) for e in rec.safety.events]}")
    assert not (modes == wire.ESTOP).any() and "ESTOP" not in plant_log  # the real plant 2's own log
    assert near > SEPARATION and min_separation(rec) > SEPARATION_LOADED
    if case == "plant-estop":
        # agent 2 (row 1) never leaves FLYING because of the report (a host stall may hold it for a while)
        assert not any("ESTOP" in e.reason or "plant reports" in e.reason for e in rec.safety.events)
    elif case == "agent-hold":
        assert mode_changes(rec) <= 3 * len(m.agents)
        # agent 2 (row 1) hears agent 1: most forged copies were caught as conflicts (a copy more than
        # a few ticks late, or one whose genuine sample a loaded agent never decoded, may pass)
        assert rec.safety.gate_counts is not None and rec.safety.gate_reasons is not None
        reasons = [str(r) for r in rec.safety.gate_reasons]
        conflicts = int(rec.safety.gate_counts[1, reasons.index("conflict")]) if "conflict" in reasons else 0
        print(f"agent-hold: {forged} forged, {conflicts} conflicts at agent 2")
        assert conflicts >= forged // 2
        # judged suspect (agent 2 holds, its followers follow it), or the forgery never moved a mode
        suspect = any("neighbour 1 mostly rejected" in e.reason for e in rec.safety.events if e.vehicle == 2)
        assert suspect or (modes[:, 1:] == wire.FLYING).all()
    elif case == "cmd-push":
        # plant 2 flies neither command of a contested tick, says so and holds while it goes on;
        # vehicle 2 is never pushed out of the formation
        said = [e for e in rec.safety.plant_events if e.vehicle == 2 and e.reason.startswith("plant: ")]
        print(f"cmd-push: plant 2 said {[(round(e.t, 2), e.reason) for e in said]}")
        assert any("contested" in e.reason for e in said), said
        assert "contested" in plant_log
        during = (rec.t >= AT) & (rec.t <= AT + span + SETTLE)
        print(f"cmd-push: vehicle 2's true error during the attack: max {np.nanmax(err[during, 1]):.3f} m, "
              f"before it {np.nanmax(err[rec.t < AT, 1]):.3f} m")
        # it holds (no command trusted) for about 0.8 s while the formation flies on: measured 3.4 m
        # against 1.2 m before; the forged 20 m/s^2 flown for 1 s pushed it 9-11 m out
        assert float(np.nanmax(err[during, 1])) < np.nanmax(err[rec.t < AT, 1]) + 4.0
    else:
        reasons = [e.reason for e in rec.safety.events if e.vehicle == 1]
        assert any("leader mostly rejected" in r for r in reasons)
        assert rec.safety.gate_counts is not None
        # steered off: each vehicle's true error sideways (the forged drift's direction; the true
        # leader never moves sideways) while the attack lasts and SETTLE after it. Followed, the
        # forgery would carry the formation 2.5 m; measured 1.1 m, the disturbances' own swing
        # (1.0 m before the attack). Vehicles rejoin afterwards, so their later swing is not judged.
        window = (rec.t >= AT) & (rec.t <= AT + span + SETTLE)
        lp, _, _ = profile.build(m.leader, m.dim)(rec.t[window])
        slots = np.asarray(lp)[:, None, :] + np.array([a.offset for a in m.agents])[None]
        side = np.abs(rec.p[window][:, :, 1] - slots[:, :, 1])
        print(f"leader-drift: sideways true error max {np.nanmax(side):.3f} m")
        assert float(np.nanmax(side)) < 2.0
