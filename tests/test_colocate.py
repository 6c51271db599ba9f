"""Lockstep with each simulated plant computed inside its agent's process (``plant/onboard.py``), and
the recorder's samples batched in ``wire.Record`` messages: ``tether run``'s default in lockstep
where every plant is simulated (``deploy.options.resolve``), ``--colocate-plants`` to insist on it,
``--separate-plants`` for one process per plant.

The run must be the one the separate plant processes give, byte for byte in every array of the run
file, and so the reference simulator's; a co-located plant flies only what its command watchdog
lets through (saturated, finite); a malformed, forged, replayed or lost record is dropped and
counted, and the run file says which ticks lack samples. Real processes, real Zenoh sessions on
loopback ports picked free at run time, one key namespace per run.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from plant.onboard import Onboard, problem
from sim import refsim
from tests.factories import build, one_agent, random_mission
from tests.support import read
from tests.test_runtime import ATOL, LEADER, REPO, SECTION4, STARTUP, WAIT, differing_arrays, launch, stop, tether_cmd
from tether import handoff
from tether import transport as tp
from tether import wire
from tether.catalog import builtin_path
from tether.mission import Mission
from tether.node import load_mission
from tether.runfile import SERIES, Run

AGENTS = (1, 2, 3, 4)


# =========================================================================== the same run, fewer processes
@pytest.fixture(scope="module")
def section4_runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str, str]:
    """Section 4 over 5 s in lockstep, twice at the same time: as ``tether run`` does by default
    (plants co-located, window 32, 16 ticks per record: 501 ticks end on a record of five), and with
    ``--separate-plants``, one process per plant."""
    base = tmp_path_factory.mktemp("colocate")
    ns = f"colocate-{os.getpid()}"
    with launch(base / "co", f"{ns}-co", "--duration", "5") as co, \
            launch(base / "sep", f"{ns}-sep", "--duration", "5", "--separate-plants") as sep:
        for run in (co, sep):
            run.wait(STARTUP + 60)
            assert run.status == 0, run.launcher_log
        return co.out, sep.out, co.launcher_log, sep.launcher_log


def test_colocated_run_starts_no_plant_process_and_is_complete(section4_runs: tuple[Path, Path, str, str]) -> None:
    co, _, log, sep_log = section4_runs
    assert "plants computed inside their agents" in log and "window 32, records of 16 ticks" in log, log
    assert "all 6 processes are up" in log, log
    assert "all 10 processes are up" in sep_log and "plants computed inside" not in sep_log, sep_log
    assert sorted(p.name for p in (co / "logs").iterdir()) == sorted(
        ["gateway.log", "leader-5.log", "recorder-0.log", *[f"agent-{i}.log" for i in AGENTS]])
    rec = Run.load(co)
    assert rec.meta.complete is True
    assert rec.meta.samples_recorded == rec.meta.samples_expected == (1 + 2 * len(AGENTS)) * 501
    # nothing lost or refused; a peer's lockstep resend on a busy host reaches the recorder as a copy of a
    # sample it has (counted apart, "copy", and never recorded twice), so copies are no loss
    drops = rec.meta.recorder_drops
    assert drops.total() - drops.other.get("copy", 0) == 0, drops
    assert np.all(rec.safety.plant_mode == wire.FLYING) and np.all(rec.safety.safety_mode == wire.FLYING)


def test_the_recorder_acknowledges_the_ticks_a_record_completes_at_once(
        section4_runs: tuple[Path, Path, str, str]) -> None:
    """One acknowledgement stands for every tick before it (``wire.Ack``): with records of 16 ticks
    the recorder completes ticks by sixteens (or more, records arriving together) and says so once
    for each group, not once a tick; never more than the window of 32 at once (nothing beyond the
    grant can be complete)."""
    co, sep, _, _ = section4_runs
    said = {}
    for name, out in (("co", co), ("sep", sep)):
        line = re.search(r"lockstep: (\d+) acknowledgements for (\d+) ticks", (out / "logs" / "recorder-0.log").read_text())
        assert line is not None, name
        said[name] = int(line[1]), int(line[2])
    acks, ticks = said["co"]
    # (a leader sample late beside the records completes a tick alone: a margin of twice that)
    assert ticks == 501 and math.ceil(ticks / 32) <= acks <= ticks // 2, said
    acks, ticks = said["sep"]
    assert ticks == 501 and 1 <= acks <= ticks, said  # one process per plant: ticks complete one by one, mostly


def test_colocated_run_file_equals_the_plant_processes_run_file_in_every_array(
        section4_runs: tuple[Path, Path, str, str]) -> None:
    co, sep, _, _ = section4_runs
    assert differing_arrays(co, sep) == []


def test_colocated_run_equals_the_reference_simulator(section4_runs: tuple[Path, Path, str, str]) -> None:
    run = Run.load(section4_runs[0])
    ref = refsim.simulate(load_mission(SECTION4, 5.0))
    pairs = {name: (getattr(run, name), getattr(ref, name)) for name in SERIES}
    for name in ("p", "v", "a"):
        pairs[f"plant_{name}"] = (getattr(run.runtime, f"plant_{name}"), getattr(ref, name))
    for name, (got, want) in pairs.items():
        assert np.isfinite(got).all(), name
        np.testing.assert_allclose(got, want, rtol=0, atol=ATOL, err_msg=name)
    assert not np.allclose(run.kp[-1], run.kp[0])


def test_the_default_mesh_run_equals_a_star_run_and_each_peer_is_linked_to_all_before_its_token(
        section4_runs: tuple[Path, Path, str, str], tmp_path: Path) -> None:
    """The co-located default is a peer mesh (faster in lockstep: no router hop between the agents):
    ``--network star`` gives the same run file, and in the mesh every peer declared its token only
    once linked to the five others, so that the launcher's start reached a complete mesh (a ring of
    32 once stalled at tick 0 without that wait)."""
    co, _, co_log, _ = section4_runs
    assert "network mesh" in co_log, co_log
    with launch(tmp_path, f"colocate-{os.getpid()}-star", "--duration", "5", "--network", "star") as run:
        run.wait(STARTUP + 60)
    assert run.status == 0, run.launcher_log
    assert differing_arrays(co, run.out) == []
    for name in ("leader-5", "recorder-0", *(f"agent-{i}" for i in AGENTS)):
        assert "mesh: linked to 5 other peers" in read(co / "logs" / f"{name}.log"), name
        assert "mesh: linked" not in run.child_log(name), name


def test_a_run_with_collision_avoidance_is_authenticated_and_equals_the_in_process_engine(tmp_path: Path) -> None:
    """``swap`` (``[safety.avoid]``: every agent hears every other vehicle's state) as ``tether run``
    flies it by default (mTLS with the run's access rules, plants co-located, a mesh): the access
    rules let each agent hear the others (they once did not, and the run stalled at tick 0), the
    vehicles keep apart through the crossing, and the run equals the in-process engine's bit for bit."""
    from sim import lockstep

    with launch(tmp_path, f"swap-{os.getpid()}", "--duration", "4", mission="swap") as run:
        run.wait(STARTUP + 60)
    assert run.status == 0, run.launcher_log
    got = Run.load(run.out)
    assert got.meta.complete
    m = load_mission(builtin_path("swap"), 4.0)
    want = lockstep.simulate(m)
    for name in ("p", "v", "u", "xi", "kp", "kv"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    p = got.p
    closest = min(float(np.linalg.norm(p[:, i] - p[:, j], axis=-1).min()) for i in range(4) for j in range(i + 1, 4))
    assert m.safety.avoid is not None and closest >= 0.95 * m.safety.avoid.radius, closest


def test_a_peer_of_a_mesh_that_cannot_link_to_every_other_fails_naming_the_count(tmp_path: Path) -> None:
    """A peer that should link to one other and finds none: exit 1 after ``--connect-timeout``, saying how many
    it had, never declaring the token on which the launcher would start the run."""
    r = subprocess.run(tether_cmd("leader", "--mission", "section4", "--clock", "lockstep", "--ns",
                                  f"lonely-{os.getpid()}", "--zenoh-mode", "peer", "--listen",
                                  tp.loopback_endpoint(tp.free_tcp_port()), "--mesh-peers", "1",
                                  "--connect-timeout", "1", "--start-timeout", "30"),
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stdout + r.stderr
    said = r.stdout + r.stderr
    assert "linked to 0 of the mesh's 1 other peers after 1 s" in said and "Traceback" not in said, said


def test_colocated_quadrotors_equal_their_plant_processes_bit_for_bit(tmp_path: Path) -> None:
    """Experiment 1's quadrotors (their 500 Hz inner loop, with mass and attitude), 1 s."""
    ns = f"colocate-q-{os.getpid()}"
    outs = []
    for tag, extra in (("co", ("--colocate-plants", "--record-batch", "3")), ("sep", ("--separate-plants",))):
        out = tmp_path / tag
        r = subprocess.run(tether_cmd("run", "exp1", "--out", str(out), "--ns", f"{ns}-{tag}", "--duration", "1",
                                      "--quiet", *extra), cwd=REPO, capture_output=True, text=True,
                           timeout=STARTUP + 60)
        assert r.returncode == 0, r.stderr
        outs.append(out)
    assert Run.load(outs[0]).meta.complete is True
    assert differing_arrays(outs[0], outs[1]) == []


# =========================================================================== refused before anything starts
@pytest.mark.parametrize("mission, args, names, fix", [
    ("section4", ["--clock", "realtime"], "--colocate-plants", "--clock lockstep"),
    ("section4", ["--record-batch", "33"], "--record-batch", "smaller --record-batch or a larger --window"),
    ("section4", ["--window", "4", "--record-batch", "5"], "--record-batch", "between 1 and the window (4)"),
    ("section4", ["--window", "600", "--record-batch", "300"], "--record-batch", "at most 256 (the recorder drops"),
    ("exp2", [], "--colocate-plants", "[payload] world"),
    ("exp1_cf", [], "--colocate-plants", "crazyflie"),
])
def test_colocate_plants_refuses_what_it_cannot_run_with_exit_2(tmp_path: Path, mission: str, args: list[str],
                                                                names: str, fix: str) -> None:
    r = subprocess.run(tether_cmd("run", mission, "--out", str(tmp_path / "out"), "--quiet", "--colocate-plants",
                                  *args), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    line = next(x for x in r.stderr.splitlines() if names in x)
    assert fix in line, r.stderr
    assert names == "--record-batch" or "drop --colocate-plants" in line, r.stderr
    assert not (tmp_path / "out" / "logs").exists() or not any((tmp_path / "out" / "logs").iterdir())


@pytest.mark.parametrize("args, why", [
    (["--separate-plants"], "--separate-plants was given"),
    (["--clock", "realtime"], "real time"),
    (["--listen", "tls/127.0.0.1:9"], "--listen was given"),
])
def test_record_batch_with_plant_processes_exits_2(tmp_path: Path, args: list[str], why: str) -> None:
    r = subprocess.run(tether_cmd("run", "section4", "--out", str(tmp_path / "out"), "--record-batch", "2", *args),
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    line = next(x for x in r.stderr.splitlines() if "--record-batch" in x)
    assert "plant processes" in line and why in line, r.stderr


def test_colocate_and_separate_plants_together_exit_2(tmp_path: Path) -> None:
    r = subprocess.run(tether_cmd("run", "section4", "--out", str(tmp_path / "out"), "--colocate-plants",
                                  "--separate-plants"), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--separate-plants" in r.stderr and "give one of them" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_lockstep_co_locates_by_default_where_nothing_needs_plant_processes() -> None:
    """``deploy.options.resolve``: co-located in lockstep with simulated plants and nothing that acts on
    the plant processes; else one process per plant, and why; the window follows the structure."""
    from deploy import faults
    from deploy import options
    from deploy.options import COLOCATED_WINDOW, MESH_MAX_AGENTS, WINDOW, LaunchOptions
    from deploy.supervise import pace

    def resolve(m: Mission, o: LaunchOptions) -> LaunchOptions:  # at the pace the launcher chooses for o
        return options.resolve(m, o, pace(o.clock))

    def separate_plants_needed(m: Mission, o: LaunchOptions) -> str | None:
        return options.separate_plants_needed(m, o, pace(o.clock))


    m, out = load_mission(SECTION4), Path("out")
    assert separate_plants_needed(m, LaunchOptions(out=out)) is None
    got = resolve(m, LaunchOptions(out=out))
    assert got.colocate_plants is True and got.window == COLOCATED_WINDOW and got.network == "mesh"
    cases = {
        "real time": LaunchOptions(out=out, clock="realtime"),
        "--fault": LaunchOptions(out=out, faults=(faults.parse("kill:plant/2@1"),)),
        "--wrap": LaunchOptions(out=out, wrap={2: ("nice",)}),
        "--listen": LaunchOptions(out=out, listen=("tls/127.0.0.1:9",)),
        "--shared-plants": LaunchOptions(out=out, shared_plants=True),
        "--sitl": LaunchOptions(out=out, sitl=()),
    }
    for name, o in cases.items():
        why = separate_plants_needed(m, o)
        assert why is not None and name in why, (name, why)
        got = resolve(m, o)
        assert got.colocate_plants is False and got.window == WINDOW and got.network == "star", name
        # plants co-located on demand where the default would not: the star still
        forced = resolve(m, dataclasses.replace(o, colocate_plants=True))
        assert forced.network == "star", name
    assert "[payload] world" in (separate_plants_needed(load_mission(builtin_path("exp2")), LaunchOptions(out=out)) or "")
    # what is given is kept
    assert resolve(m, LaunchOptions(out=out, colocate_plants=False)).colocate_plants is False
    assert resolve(m, LaunchOptions(out=out, colocate_plants=False)).network == "star"
    assert resolve(m, LaunchOptions(out=out, network="star")).network == "star"
    assert resolve(m, LaunchOptions(out=out, network="mesh", clock="realtime")).network == "mesh"
    # a mesh up to MESH_MAX_AGENTS agents, the star beyond (N^2/2 links to set up)
    for n, want in ((MESH_MAX_AGENTS, "mesh"), (MESH_MAX_AGENTS + 1, "star")):
        big = random_mission(np.random.default_rng(n), n)
        assert resolve(big, LaunchOptions(out=out)).network == want, n
    # and `tether run --help` says the defaults these are
    from cli.main import build_parser

    run = build_parser()._subparsers._group_actions[0].choices["run"]  # type: ignore[union-attr]
    said = next(a.help for a in run._actions if "--window" in a.option_strings)
    assert f"default: {COLOCATED_WINDOW} with the plants co-located, else {WINDOW}" in (said or ""), said
    said = next(a.help for a in run._actions if "--network" in a.option_strings)
    assert f"at most {MESH_MAX_AGENTS} agents" in (said or ""), said
    assert resolve(m, LaunchOptions(out=out, window=4)).window == 4
    assert resolve(m, LaunchOptions(out=out, clock="realtime", colocate_plants=True)).colocate_plants is True


def test_problem_names_the_plants_that_cannot_be_co_located() -> None:
    assert problem(load_mission(builtin_path("section4")), 1) is None
    assert problem(load_mission(builtin_path("exp1")), 1) is None
    assert "crazyflie" in (problem(load_mission(builtin_path("exp1_cf")), 1) or "")
    assert "payload" in (problem(load_mission(builtin_path("exp2")), 1) or "")
    with pytest.raises(ValueError, match="cannot be co-located"):
        Onboard(load_mission(builtin_path("exp2")), 1)


# =========================================================================== the co-located plant's safety
def _cmd(k: int, u: list[float]) -> wire.Command:
    return wire.Command(sender=1, seq=k, k=k, t=k * 0.01, u=u)


def test_a_co_located_plant_never_flies_a_non_finite_or_over_limit_command() -> None:
    """The plant process's command watchdog, in front of the model: a command over ``max_accel``
    is saturated to it, a non-finite or absurd one is rejected (counted) and the last valid one
    flies on; the model's state stays finite throughout."""
    m = one_agent()
    limit = m.safety.max_accel
    plant = Onboard(m, 1)
    s0 = plant.advance(0, None, None)
    assert s0.p == [0.0, 0.0] and s0.mode == wire.FLYING
    s1 = plant.advance(1, _cmd(0, [3 * limit, 0.0]), None)  # over the limit, under the absurd bound
    assert math.isclose(math.hypot(*s1.a), limit, rel_tol=1e-12), s1.a
    s2 = plant.advance(2, _cmd(1, [math.nan, 0.0]), None)
    s3 = plant.advance(3, _cmd(2, [1e9, 0.0]), None)
    s4 = plant.advance(4, _cmd(3, [0.0, math.inf]), None)
    assert plant.dog.invalid == {"nonfinite": 2, "absurd": 1}
    for s in (s2, s3, s4):
        assert all(map(math.isfinite, [*s.p, *s.vel, *s.a])), s
        assert math.hypot(*s.a) <= limit * (1 + 1e-12)
    # the operator's e-stop reaches the co-located plant too
    s5 = plant.advance(5, _cmd(4, [1.0, 0.0]), "estop")
    assert s5.mode == wire.ESTOP


def _flyer(dim: int) -> Any:
    """One agent with a disturbance of every kind at once (a sum), 2D or 3D (ground at 0)."""
    z = [1.0] if dim == 3 else []
    dist = {"kind": "sum", "terms": [
        {"kind": "sinusoid", "amplitude": [0.3, 0.2, 0.1][:dim], "omega": [1.0, 2.0, 3.0][:dim],
         "phase": [0.1, 0.2, 0.3][:dim]},
        {"kind": "constant", "value": [0.05, -0.02, 0.01][:dim]},
        {"kind": "bounded_random", "bound": 0.1, "hold": 0.05}]}
    return build({
        "version": 1, "name": f"flyer{dim}", "dim": dim, "rate": 100.0, "duration": 20.0,
        "law": {"kind": "sigma", "kp0": 1.0, "kv0": 1.0, "gamma_p": 0.05, "gamma_v": 0.05, "sigma": 1.0},
        "leader": {"id": 2, "p0": [0.0, 0.0, *z]},
        "agents": [{"id": 1, "p0": [0.3, -0.2, *z], "v0": [0.1, 0.0, *([0.0] if z else [])], "offset": [1.0, 0.0, *([0.0] if z else [])],
                    "disturbance": dist}],
        "edges": [{"from": 2, "to": 1, "weight": 1.0}],
    })


@pytest.mark.parametrize("dim, script", [
    (2, "fly"), (3, "fly"), (3, "dive"), (2, "land"), (3, "land"), (2, "estop"), (3, "estop"), (3, "silent")],
    ids=["2d fly", "3d fly", "3d through the ground", "2d land", "3d land", "2d estop", "3d estop", "3d silent"])
def test_the_plain_float_plant_equals_the_general_path_bit_for_bit(dim: int, script: str) -> None:
    """A co-located double integrator flies on plain floats while it flies nominally, and hands over
    to the general path (ground contact, motors-off) at the first tick that is not: the operator's
    land or e-stop, its watchdog landing it when its commands stop, or a dive into the floor with
    the watchdog still FLYING. Every sample equals the general path's in every bit, before, at and
    after the hand-over."""
    m = _flyer(dim)
    lean, ref = Onboard(m, 1), Onboard(m, 1, lean=False)
    assert lean.lean and not ref.lean
    rng = np.random.default_rng(dim)
    cmd = None
    went = None
    # silent: 30 ticks of commands, cmd_cutoff without, then the landing
    for k in range(30 + round(m.safety.cmd_cutoff / m.dt) + 470 if script == "silent" else 120):
        operator = script if script in ("land", "estop") and k >= 20 else None
        got, want = lean.advance(k, cmd, operator), ref.advance(k, cmd, operator)
        assert msgspec.structs.asdict(got) == msgspec.structs.asdict(want), (k, got, want)
        assert wire.encode(got) == wire.encode(want)  # plain floats on the wire, as the general path's
        if went is None and not lean.lean:
            went = got
        u = rng.normal(0.0, 0.5, dim).tolist()
        if script == "dive" and k >= 10:
            u = [0.0] * (dim - 1) + [-3.0]  # flown into the floor with the watchdog still FLYING
        if script != "silent" or k < 30:  # silent: its commands stop; the watchdog holds, then lands it
            cmd = _cmd(k, u)
    if script == "fly":
        assert went is None
    elif script == "dive":
        assert went is not None and went.mode == wire.FLYING and went.p[-1] == 0.0 and went.vel[-1] == 0.0
    else:
        assert went is not None and went.mode == {"land": wire.LAND, "estop": wire.ESTOP, "silent": wire.LAND}[script]
        assert script == "silent" or went.k == 20  # the operator's order at tick 20


def test_a_co_located_plant_holds_when_its_commands_stop() -> None:
    m = one_agent()
    plant = Onboard(m, 1)
    plant.advance(0, None, None)
    ticks = math.ceil(m.safety.cmd_timeout * m.rate) + 2
    modes = [plant.advance(k, _cmd(0, [1.0, 0.0]) if k == 1 else None, None).mode for k in range(1, ticks + 1)]
    assert modes[0] == wire.FLYING and modes[-1] == wire.HOLD


# =========================================================================== records on the wire
def _record(k0: int, n: int, sender: int = 1, dim: int = 2, p: list[float] | None = None) -> wire.Record:
    """Ticks ``k0 .. k0 + n - 1`` of a vehicle at rest at ``p``."""
    z = [0.0] * dim
    p = p or z
    plant = [wire.PlantState(sender=sender, seq=k, k=k, t=k / 100, p=p, vel=z, a=z, d=z) for k in range(k0, k0 + n)]
    tele = [wire.Telemetry(sender=sender, seq=k, k=k, t=k / 100, meas_t=k / 100, p=p, vel=z, a=z, u=z, xi=z, zeta=z,
                           kp=z, kv=z, links=[], drops={}) for k in range(k0, k0 + n)]
    return wire.Record(sender=sender, seq=k0, k=k0 + n - 1, t=(k0 + n - 1) / 100, plant=plant, telemetry=tele)


def _with(rec: wire.Record, **changes: object) -> bytes:
    return wire.encode(msgspec.structs.replace(rec, **changes))


def test_a_record_is_checked_item_by_item_and_dropped_whole_for_one_bad_item() -> None:
    good = _record(4, 3)
    rx = wire.Receiver(2)
    assert rx.accept(wire.encode(good), wire.Record, 1) == good
    nan_item = msgspec.structs.replace(good.plant[1], p=[math.nan, 0.0])
    other_sender = msgspec.structs.replace(good.telemetry[2], sender=2)
    wrong_size = msgspec.structs.replace(good.telemetry[0], u=[0.0, 0.0, 0.0])
    bad_meas_t = msgspec.structs.replace(good.telemetry[0], meas_t=math.inf)
    cases = [
        (_with(good, plant=[good.plant[0], nan_item, good.plant[2]]), "nonfinite"),
        (_with(good, telemetry=[*good.telemetry[:2], other_sender]), "sender"),
        (_with(good, telemetry=[wrong_size, *good.telemetry[1:]]), "size"),
        (_with(good, telemetry=[bad_meas_t, *good.telemetry[1:]]), "nonfinite"),
        (_with(good, plant=good.plant[:2]), "size"),  # one stream short
        (_with(good, plant=[], telemetry=[]), "size"),  # empty
        (_with(good, k=9), "record"),  # items do not end at k
        (_with(good, plant=[good.plant[0], good.plant[0], good.plant[2]]), "record"),  # a tick twice
        (wire.encode(_record(0, wire.RECORD_MAX + 1)), "size"),
        (wire.encode(good)[:-7], "malformed"),
    ]
    for payload, reason in cases:
        before = dict(rx.drops)
        assert rx.accept(payload, wire.Record, 1) is None, reason
        assert rx.drops.get(reason, 0) == before.get(reason, 0) + 1, (reason, rx.drops)
    assert rx.accept(wire.encode(good), wire.Record, 2) is None and rx.drops["sender"] == 2  # on agent 2's key


def _leader_record(k0: int, n: int, sender: int = 5, dim: int = 2) -> wire.Record:
    """The leader's states of ticks ``k0 .. k0 + n - 1``, at rest at the origin."""
    z = [0.0] * dim
    states = [wire.State(sender=sender, seq=k, k=k, t=k / 100, p=z, vel=z, a=z) for k in range(k0, k0 + n)]
    return wire.Record(sender=sender, seq=k0, k=k0 + n - 1, t=(k0 + n - 1) / 100, leader=states)


def test_a_leaders_record_carries_its_states_alone_each_checked() -> None:
    """The leader's record (lockstep, plants co-located): its states alone, one a tick for
    consecutive ticks ending at ``k``, each checked as if it had come alone."""
    good = _leader_record(16, 4)
    rx = wire.Receiver(2)
    assert rx.accept(wire.encode(good), wire.Record, 5) == good
    s = good.leader
    cases = [
        (_with(good, leader=[s[0], msgspec.structs.replace(s[1], vel=[0.0, math.inf]), *s[2:]]), "nonfinite"),
        (_with(good, leader=[*s[:3], msgspec.structs.replace(s[3], a=[0.0])]), "size"),
        (_with(good, leader=[*s[:3], msgspec.structs.replace(s[3], sender=1)]), "sender"),
        (_with(good, leader=[s[0], s[0], *s[2:]]), "record"),  # a tick twice
        (_with(good, k=21), "record"),  # the states do not end at k
        (_with(good, plant=_record(16, 4).plant), "size"),  # an agent's streams beside the leader's
        (wire.encode(_leader_record(0, wire.RECORD_MAX + 1)), "size"),
    ]
    for payload, reason in cases:
        before = dict(rx.drops)
        assert rx.accept(payload, wire.Record, 5) is None, reason
        assert rx.drops.get(reason, 0) == before.get(reason, 0) + 1, (reason, rx.drops)


def _busy_record(k0: int, n: int, sender: int, rng: np.random.Generator, dim: int = 2) -> wire.Record:
    """Ticks ``k0 .. k0 + n - 1`` of agent ``sender`` with every recorded field distinct."""
    def v() -> list[float]:
        return [float(x) for x in rng.normal(size=dim)]

    plant = [wire.PlantState(sender=sender, seq=k, k=k, t=k / 100, p=v(), vel=v(), a=v(), d=v(),
                             mode=int(rng.integers(0, 5))) for k in range(k0, k0 + n)]
    tele = []
    for k in range(k0, k0 + n):
        links = [wire.LinkStats(src=j, received=int(rng.integers(0, 99)), used=int(rng.integers(0, 99)),
                                stale=int(rng.integers(0, 9)), age=float(rng.random()), silent=bool(rng.random() < 0.5),
                                duplicates=int(rng.integers(0, 9)), reordered=int(rng.integers(0, 9)),
                                corrupt=int(rng.integers(0, 9)), delivery=float(rng.random()),
                                age_p50=float(rng.random()), age_p99=float(rng.random())) for j in (0, sender % 4 + 1)]
        events = [wire.SafetyEvent(k=k, t=k / 100, vehicle=sender, src=0, dst=1, reason="test")] if k % 7 == 0 else []
        netem = [wire.LinkDecision(src=0, seq=k, now=k / 100, event="deliver", at=k / 100)] if k % 5 == 0 else []
        tele.append(wire.Telemetry(sender=sender, seq=k, k=k, t=k / 100, meas_t=k / 100 - 0.001 * (k % 3), p=v(),
                                   vel=v(), a=v(), u=v(), xi=v(), zeta=v(), kp=v(), kv=v(), links=links,
                                   drops={"malformed": k % 4, "size": 1}, late=k % 2, mode=int(rng.integers(0, 5)),
                                   events=events, netem=netem, gate={"jump": k}))
    return wire.Record(sender=sender, seq=k0, k=k0 + n - 1, t=(k0 + n - 1) / 100, plant=plant, telemetry=tele)


def test_the_recorder_writes_a_record_at_once_as_it_would_sample_by_sample() -> None:
    """``Recording.plants`` / ``telemetries`` (one assignment per series for a record's ticks) fill
    every array of the run as ``plant`` / ``telemetry`` called for each sample do, and fall back to
    them, counting alike, for what a block cannot take: a tick already recorded (a replay), ticks
    not consecutive (a plant sample the gate rejected), another sender among the items, ticks beyond
    the run, links that change in number."""
    from types import SimpleNamespace

    from recorder.recording import Recording

    m = load_mission(SECTION4)
    # the recorder's bookkeeping asks its node for these alone
    node = SimpleNamespace(mission=m, clock=SimpleNamespace(kind="lockstep"), keys=wire.Keys("test"),
                           args=SimpleNamespace(mission_path=SECTION4), arrived_ago=lambda: 0.0)
    rng = np.random.default_rng(5)
    one, block = Recording(node, Path("unused")), Recording(node, Path("unused"))  # type: ignore[arg-type]
    one.first = block.first = 0.0
    last = m.steps
    records = [_busy_record(k0, 16, aid, rng) for aid in AGENTS for k0 in range(0, 64, 16)]
    replayed = _busy_record(16, 16, 2, rng)
    gapped = _busy_record(64, 16, 3, rng)
    mixed = _busy_record(80, 4, 1, rng)
    mixed_items = [mixed.telemetry[0], msgspec.structs.replace(mixed.telemetry[1], sender=2), *mixed.telemetry[2:]]
    links = _busy_record(96, 4, 4, rng)
    fewer = [*links.telemetry[:2], msgspec.structs.replace(links.telemetry[2], links=links.telemetry[2].links[:1]),
             links.telemetry[3]]
    beyond = _busy_record(last - 2, 5, 1, rng)
    cases = [(r.plant, r.telemetry) for r in records] + [
        (replayed.plant, replayed.telemetry),
        ([*gapped.plant[:3], *gapped.plant[4:]], gapped.telemetry),
        (mixed.plant, mixed_items),
        (links.plant, fewer),
        (beyond.plant, beyond.telemetry),
    ]
    singly = {"plant": 0, "telemetry": 0}

    def counted(name: str) -> Any:
        method = getattr(block, name)

        def call(msg: Any) -> None:
            singly[name] += 1
            method(msg)

        return call

    block.plant, block.telemetry = counted("plant"), counted("telemetry")  # type: ignore[method-assign]
    for plants, tele in cases:
        for p in plants:
            one.plant(p)
        for t in tele:
            one.telemetry(t)
        block.plants(plants)
        block.telemetries(tele)
    # the records in blocks; one by one: the replay, the gapped plant samples, the mixed senders'
    # telemetry, the links that changed in number, the ticks beyond the run
    assert singly == {"plant": 16 + 15 + 5, "telemetry": 16 + 4 + 4 + 5}
    assert one.duplicates == block.duplicates == 32
    assert np.array_equal(one.count, block.count) and np.array_equal(one.have, block.have)
    assert (one.oldest, one.newest) == (block.oldest, block.newest) == (0, last)
    assert one.events == block.events and one.netem == block.netem and one.gate == block.gate
    want, got = one.run.arrays(), block.run.arrays()
    assert want.keys() == got.keys()
    differ = [name for name in want
              if not np.array_equal(want[name], got[name], equal_nan=want[name].dtype.kind == "f")]
    assert not differ, differ
    assert one.count[:64].tolist() == [8] * 64  # the blocks were recorded: 4 plants and 4 telemetries a tick


# =========================================================================== the recorder, fed by hand
@pytest.mark.asyncio
@pytest.mark.parametrize("lost", ["agent 3", "leader"])
async def test_the_recorder_drops_and_counts_bad_records_and_its_file_says_which_ticks_lack_samples(
        tmp_path: Path, lost: str) -> None:
    """The recorder alone (``--colocate-plant``, lockstep), around this test's router session: the
    test plays the leader (its records) and the four agents. Junk, a record with a non-finite item, one
    forged on another agent's key and a replayed one are dropped and counted, and so is a leader's
    state the plausibility gate rejects (a far-off one, for a tick whose own comes after). The last
    record of agent 3, or of the leader, never comes (lost, and not sent again), so the recorder stalls
    on its first tick, says whose samples it lacks, acknowledges up to the tick before it, and writes a
    file that is marked incomplete and holds every other sample."""
    ns = f"recorder-alone-{os.getpid()}-{lost.split()[0]}"
    keys = wire.Keys(ns)
    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    steps, batch = 9, 4  # ticks 0..9: records of 0-3, 4-7, 8-9
    m = load_mission(SECTION4)
    p0 = {a.id: list(a.p0) for a in m.agents}  # where the plausibility gate expects each vehicle
    out = tmp_path / "out"
    log = tmp_path / "recorder.log"
    async with tp.open_session(tp.ZenohSettings(mode="router", listen=(endpoint,), scouting_delay=0.0)) as session:
        wakeup = handoff.Wakeup()
        acks: handoff.BoundedFifo[tp.Received] = handoff.BoundedFifo(4096, wakeup)
        sub = tp.declare_subscriber(session, keys.acks, acks)
        with open(log, "wb") as fh:
            proc = subprocess.Popen(
                tether_cmd("recorder", "--mission", "section4", "--clock", "lockstep", "--ns", ns, "--out", str(out),
                           "--colocate-plant", "--no-mcap", "--duration", str(steps / 100), "--stall-timeout", "3",
                           "--zenoh-mode", "client", "--connect", endpoint),
                cwd=REPO, stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            await tp.wait_for_tokens(session, [keys.token("recorder", 0)], STARTUP)
            pubs = {key: tp.declare_publisher(session, key, tp.SYNC) for key in
                    (keys.start, keys.topic("leader", LEADER, "record"),
                     *(keys.topic("agent", i, "record") for i in AGENTS))}
            for pub in pubs.values():
                await tp.wait_for_subscribers(pub, WAIT)
            pubs[keys.start].put(wire.encode(wire.Start(sender=0, seq=0, k=0, t=0.0, epoch=time.time())))
            zero = [0.0, 0.0]
            leader = keys.topic("leader", LEADER, "record")
            far = wire.State(sender=LEADER, seq=0, k=0, t=0.0, p=[1e4, 0.0], vel=zero, a=zero)
            pubs[leader].put(wire.encode(wire.Record(sender=LEADER, seq=0, k=0, t=0.0, leader=[far])))  # gated
            for seq, k0 in enumerate(range(0, steps + 1, batch), start=1):
                if lost == "leader" and k0 == 8:
                    continue  # lost
                states = _leader_record(k0, min(batch, steps + 1 - k0), sender=LEADER)
                pubs[leader].put(wire.encode(msgspec.structs.replace(states, seq=seq)))
            rec1 = keys.topic("agent", 1, "record")
            pubs[rec1].put(b"\x93\x01\x02")  # junk
            nan = _record(0, batch, p=p0[1])
            pubs[rec1].put(_with(nan, plant=[*nan.plant[:3], msgspec.structs.replace(nan.plant[3], vel=[math.inf, 0])]))
            pubs[rec1].put(wire.encode(_record(0, batch, sender=2, p=p0[2])))  # agent 2's, forged on agent 1's key
            for i in AGENTS:
                for seq, k0 in enumerate(range(0, steps + 1, batch)):
                    if lost == "agent 3" and i == 3 and k0 == 8:
                        continue  # lost
                    r = msgspec.structs.replace(_record(k0, min(batch, steps + 1 - k0), sender=i, p=p0[i]), seq=seq)
                    pubs[keys.topic("agent", i, "record")].put(wire.encode(r))
                    if i == 1 and seq == 1:
                        pubs[rec1].put(wire.encode(r))  # replayed: in lockstep, what a resend after a stall sends
            status = await asyncio.to_thread(proc.wait, WAIT + 30)
            acked = set()
            for rec in acks.drain():
                msg = wire.Receiver(2).accept(rec.payload, wire.Ack, 0)
                if msg is not None:
                    acked.add(msg.k)
        finally:
            stop(proc)
            sub.undeclare()
    text = read(log)
    assert status == 1 and "stalled" in text and "tick 8" in text, text
    lacks = "have 7 of 9; missing: plant 3, telemetry of agent 3" if lost == "agent 3" else \
        "have 8 of 9; missing: leader 5"
    assert f"({lacks})" in text, text  # what it lacks at the stall
    assert max(acked) == 7, (acked, text)  # an acknowledgement stands for every tick up to its own
    run = Run.load(out)
    assert run.meta.complete is False
    assert run.meta.samples_expected == 9 * (steps + 1)
    # agent 3's plant and telemetry of ticks 8 and 9, or the leader's states of those ticks
    assert run.meta.samples_recorded == 9 * (steps + 1) - (2 * 2 if lost == "agent 3" else 2)
    drops = run.meta.recorder_drops
    assert (drops.malformed, drops.nonfinite, drops.sender, drops.other) == (1, 1, 1, {"copy": 1, "gate": 1}), drops
    assert "record of the leader: state of tick 0 rejected" in text, text
    assert (run.leader_p[:8, 0] == 0.0).all()  # the far-off state did not take tick 0's place
    if lost == "agent 3":
        col = run.agent_ids.tolist().index(3)
        assert np.isnan(run.p[8:, col]).all() and np.isnan(run.runtime.plant_p[8:, col]).all()
        assert np.isfinite(np.delete(run.p, col, axis=1)).all() and np.isfinite(run.p[:8]).all()
        assert (run.leader_p[:, 0] == 0.0).all()
    else:
        assert np.isnan(run.leader_p[8:]).all() and np.isfinite(run.leader_p[:8]).all()
        assert np.isfinite(run.p).all() and np.isfinite(run.runtime.plant_p).all()
    assert "Traceback" not in text


@pytest.mark.slow  # real processes
def test_a_window_of_hundreds_of_ticks_sends_records_the_recorder_accepts(tmp_path: Path) -> None:
    """Records of half the window by default, at most tether.wire.RECORD_MAX ticks: with --window 600 they
    were records of 300 ticks, each dropped by the recorder as malformed ("size"), and the run stalled."""
    from tether.runfile import Run

    out = tmp_path / "out"
    r = subprocess.run(tether_cmd("run", "section4", "--out", str(out), "--duration", "4", "--window", "600",
                                  "--no-mcap"), cwd=REPO, capture_output=True, text=True, timeout=STARTUP + 60)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "window 600, records of 256 ticks" in r.stderr, r.stderr[-3000:]
    got = Run.load(out)
    assert got.meta.complete is True
    assert "size" not in read(out / "logs" / "recorder-0.log")
