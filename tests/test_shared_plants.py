"""``tether run --shared-plants``: one world process steps every simulated vehicle
(:class:`plant.base.Fleet`), each with its own command watchdog, instead of one plant process per
vehicle.

* the fleet (pure): stepping it equals stepping each vehicle's own plant, bit for bit, rows in
  the vehicles' order, whatever their kinds (a vehicle without attitude reads NaN there);
* lockstep: the run file equals the one the plant processes give, byte for byte in every array,
  and no plant process runs;
* real time, with agent 3 killed mid-run: the world's watchdog for vehicle 3 holds it and then
  lands it while vehicles 1 and 2 fly on; the launcher reports the kill (exit 4);
* refused before anything starts (exit 2, naming the option and the fix): with
  ``--colocate-plants``, a crazyflie, a ``[payload]`` mission, a fault aimed at a plant process;
* authenticated runs: the world's identity holds the plants' keys, nothing more.

Real processes, real Zenoh sessions on loopback ports picked free at run time, one key namespace
per run.
"""

from __future__ import annotations

import contextlib
import math
import os
import queue
import re
import subprocess
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from deploy import acl, localtls
from plant import base
from plant.build import build
from tests.factories import random_mission
from tests.support import read
from tests.support import wait_until
from tests.test_runtime import (REPO, STARTUP, PlainClient, children_of, count, differing_arrays, exit_statuses, launch,
                                raw, router_of, tether_cmd)
from tether import mission as ms
from tether import wire
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run


# =========================================================================== the fleet, pure
def _mixed_kinds(n: int) -> ms.Mission:
    """``n`` 3D agents with sinusoids, every third vehicle a point mass, the rest double integrators."""
    m = random_mission(np.random.default_rng(7), n, dim=3, disturbance="sinusoid", duration=2.0,
                       profile={"kind": "hold"})
    agents = [msgspec.structs.replace(a, plant=ms.PointMassPlant()) if k % 3 == 2 else a
              for k, a in enumerate(m.agents)]
    return msgspec.structs.replace(m, agents=agents)


def test_a_fleet_steps_each_vehicle_as_its_own_plant_does_bit_for_bit() -> None:
    m = _mixed_kinds(5)
    fleet = base.Fleet(build(m))
    alone = build(m)
    assert fleet.ids == tuple(m.agent_ids)
    rng = np.random.default_rng(1)
    for k in range(60):
        s = fleet.state()
        for r, p in enumerate(alone):
            own = p.state()
            np.testing.assert_array_equal(s.p[r], own.p[0])
            np.testing.assert_array_equal(s.v[r], own.v[0])
            np.testing.assert_array_equal(s.a[r], own.a[0])
            np.testing.assert_array_equal(s.d[r], own.d[0])
            if own.attitude is None:
                assert s.attitude is not None and np.all(np.isnan(s.attitude[r]))
            else:
                np.testing.assert_array_equal(s.attitude[r], own.attitude[0])
        np.testing.assert_array_equal(fleet.positions(), s.p)
        u = rng.normal(0.0, 1.0, (m.n, m.dim))
        fleet.step(u)
        for r, p in enumerate(alone):
            p.step(u[r:r + 1])
    assert np.any(fleet.state().p != build(m)[0].state().p[0])  # it moved


def test_a_fleet_of_double_integrators_reports_no_attitude() -> None:
    m = load_mission(builtin_path("section4"))
    fleet = base.Fleet(build(m))
    assert fleet.state().attitude is None and fleet.state().p.shape == (4, 2)
    with pytest.raises(ValueError, match="at least one plant"):
        base.Fleet([])


# =========================================================================== lockstep: the same run
@pytest.mark.slow
def test_shared_plants_lockstep_run_equals_the_plant_processes_run(tmp_path: Path) -> None:
    ns = f"shared-{os.getpid()}"
    with launch(tmp_path / "world", f"{ns}-w", "--duration", "4", "--shared-plants", "--insecure") as world, \
            launch(tmp_path / "sep", f"{ns}-s", "--duration", "4", "--insecure") as sep:
        for run in (world, sep):
            run.wait(STARTUP + 60)
            assert run.status == 0, run.launcher_log
    logs = sorted(p.name for p in (world.out / "logs").iterdir())
    assert "world-0.log" in logs and not [x for x in logs if x.startswith("plant-")], logs
    assert Run.load(world.out).meta.complete is True
    assert differing_arrays(world.out, sep.out) == []


# =========================================================================== real time: one vehicle's agent dies
@pytest.mark.slow
def test_the_world_holds_and_lands_the_vehicle_whose_agent_died_while_the_others_fly_on(tmp_path: Path) -> None:
    kill_at = 2.0
    duration = kill_at + ms.Safety().cmd_cutoff + 5.0  # the world's watchdog lands vehicle 3 after cmd_cutoff
    with launch(tmp_path, f"shared-rt-{os.getpid()}", "--clock", "realtime", "--duration", f"{duration:g}", "--insecure",
                "--shared-plants", "--fault", f"kill:agent/3@{kill_at:g}") as run:
        run.wait(STARTUP + 60)
    log = run.launcher_log
    assert run.status == 4, log  # a process was lost
    statuses = exit_statuses(log)
    assert statuses["world/0"] == 0 and "plant/1" not in statuses, statuses
    rec = Run.load(run.out)
    col = {int(aid): i for i, aid in enumerate(rec.agent_ids)}
    modes = rec.safety.plant_mode
    heard = modes[:, col[3]] >= 0
    v3 = modes[heard, col[3]]
    assert wire.HOLD in v3 and (wire.LAND in v3 or wire.LANDED in v3), np.unique(v3)
    t3 = rec.t[heard]
    assert t3[np.argmax(v3 != wire.FLYING)] > kill_at  # it flew until its agent died
    for aid in (1, 2):  # upstream of the dead agent: the leader still reaches them
        mine = modes[:, col[aid]]
        assert np.all(mine[mine >= 0] == wire.FLYING), (aid, np.unique(mine))
    world_log = read(run.out / "logs" / "world-0.log")
    assert "vehicle 3:" in world_log and "vehicle 1:" not in world_log, world_log


# =========================================================================== real time: forged commands for one vehicle
@pytest.mark.slow
def test_a_world_drops_forged_commands_and_never_flies_a_non_finite_or_over_limit_one(tmp_path: Path) -> None:
    """A third party's commands on vehicle 2's command key, while the world flies every vehicle:
    the undecodable, non-finite, wrong-sized and wrongly-signed ones are dropped and counted by the
    world's receiver; an absurd one that decodes is rejected by vehicle 2's own watchdog; the world
    says so at its end, and no vehicle ever flies a non-finite command or one beyond max_accel."""
    ns = f"shared-forged-{os.getpid()}"
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", "6", "--insecure", "--shared-plants") as run:
        wait_until(lambda: "real time: tick 0" in run.child_log("world/0") or run.proc.poll() is not None, STARTUP,
                   "the world's first tick")
        run.children = children_of(run.proc.pid)
        client = PlainClient(router_of(run.children))
        try:
            state2 = wire.Keys(ns).topic("plant", 2, "state")
            client.subscribe(state2)
            _, now = client.next_matching(lambda key, msg: key == state2 and msg.k >= 50, 30, "vehicle 2 at tick 50")
            pub = client.publisher(wire.Keys(ns).topic("agent", 2, "cmd"))
            # for a tick 1 s ahead: held until the world reads it then (in place of the agent's own)
            k = now.k + 100
            good = wire.Command(sender=2, seq=10**6, k=k, t=k / 100, u=[0.0, 0.0])

            def at(i: int) -> wire.Command:  # each forgery for a tick of its own: an input queue admits
                return msgspec.structs.replace(good, k=k + i, t=(k + i) / 100)  # two samples a tick

            forged = [
                (b"\xc1not msgpack", "malformed"),
                (raw(at(1), u=[math.nan, 0.0]), "nonfinite"),
                (raw(at(2), u=[0.0, math.inf]), "nonfinite"),
                (raw(at(3), u=[0.0, 0.0, 0.0]), "size"),
                (raw(at(4), sender=3), "sender"),
            ]
            absurd = wire.encode(msgspec.structs.replace(at(5), seq=10**6 + 1, u=[1e9, 0.0]))  # decodes
            window = 1.0 / (localtls.LIMIT_FACTOR * 100.0)
            for payload in [*(f for f, _ in forged), absurd]:
                pub.put(payload)
                sent = time.monotonic()
                # paced: the router's ingress limit on a command key passes one message per window
                # (1 / (LIMIT_FACTOR rate)) per link and drops the rest of a burst, a flood's defence;
                # and the world has ticked since
                with contextlib.suppress(queue.Empty):
                    while True:  # what came before this put
                        client.samples.get_nowait()
                client.next_matching(lambda key, msg: key == state2, 30, "vehicle 2's next tick")
                wait_until(lambda: time.monotonic() - sent > 4 * window, 1, "the ingress limit's window", poll=window)
            # the session stays open until the world has flown past the forged tick (a session
            # closed right after its puts may not have sent them)
            client.next_matching(lambda key, msg: key == state2 and msg.k >= k + 7, 30, f"vehicle 2 past tick {k + 5}")
        finally:
            client.close()
        assert run.wait(STARTUP + 60) in (0, 5), run.launcher_log  # 5: a sample lost on the way (real time)
    world = run.child_log("world/0")
    want = count([why for _, why in forged])
    said = re.search(r"inputs dropped: (.*)", world)
    assert said is not None, world
    got = {r: int(n) for r, n in (part.rsplit(" ", 1) for part in said[1].split(", "))}
    assert all(got.get(r, 0) >= n for r, n in want.items()), (got, want)
    # the absurd command, beside the agent's own of its tick: contested and flown as none, or (where it
    # came alone) rejected by the watchdog
    assert re.search(r"vehicle 2: commands rejected by its watchdog: .*absurd 1", world) or \
        re.search(r"vehicle 2: commands in conflict, and contested ones flown as none: .*contested [1-9]", world), world
    assert "Traceback" not in world
    rec = Run.load(run.out)
    flown = rec.a - rec.d  # what each vehicle's plant flew: its acceleration less its disturbance
    # where the plant's own sample was recorded (its acceleration also comes with its agent's
    # telemetry; its disturbance only with the plant's sample, lost on the way in an exit-5 run)
    seen = np.isfinite(rec.a).all(axis=-1) & np.isfinite(rec.d).all(axis=-1)
    assert seen.mean() > 0.9
    odd = seen & ~np.isfinite(flown).all(axis=-1)
    assert not odd.any(), [(rec.t[t], rec.agent_ids[i], rec.a[t, i], rec.d[t, i]) for t, i in np.argwhere(odd)[:5]]
    assert np.linalg.norm(flown[seen], axis=-1).max() <= ms.Safety().max_accel * (1 + 1e-9)


# =========================================================================== refused before anything starts
@pytest.mark.parametrize("mission, args, fix", [
    ("section4", ["--colocate-plants"], "give one of them"),
    ("exp1_cf", ["--clock", "realtime"], "drop --shared-plants"),
    ("exp2", [], "drop it"),
    ("section4", ["--fault", "kill:plant/2@1"], "world/0"),
])
def test_shared_plants_refuses_what_it_cannot_run_with_exit_2(tmp_path: Path, mission: str, args: list[str],
                                                             fix: str) -> None:
    r = subprocess.run(tether_cmd("run", mission, "--out", str(tmp_path / "out"), "--quiet", "--insecure",
                                  "--shared-plants", *args), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert fix in r.stderr, r.stderr
    assert not (tmp_path / "out" / "logs").exists() or not any((tmp_path / "out" / "logs").iterdir())


def test_a_world_process_refuses_a_crazyflie_with_exit_2() -> None:
    r = subprocess.run(tether_cmd("world", "--mission", "exp1_cf"), cwd=REPO, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "crazyflie" in r.stderr and "tether plant --id" in r.stderr, r.stderr


# =========================================================================== authenticated runs
def test_the_world_identity_holds_the_plants_keys_and_nothing_of_a_payload() -> None:
    m = load_mission(builtin_path("section4"))
    k = wire.Keys("s4")
    separate = {g.name: g for g in localtls.grants(m, "s4")}
    shared = {g.name: g for g in localtls.grants(m, "s4", world=True)}
    assert not [n for n in shared if n.startswith("plant-")] and "world-0" not in separate
    world = shared["world-0"]
    plants = [separate[f"plant-{a}"] for a in m.agent_ids]
    assert set(world.publish) == {p for g in plants for p in g.publish}
    assert set(world.subscribe) == {s for g in plants for s in g.subscribe}
    assert set(world.tokens) == {k.token("world", 0), *(t for g in plants for t in g.tokens)}
    assert k.topic("world", 0, "state") not in shared["recorder-0"].subscribe
    rules = acl.access_control(localtls.router_grants(m, "s4", world=True), "s4")
    assert {s["id"] for s in rules["subjects"]} >= {"world-0", *(f"agent-{a}" for a in m.agent_ids)}
