"""Fault injection (``tether run --fault``), the launcher's failure reports, and ``tether land``.

The parser is pure and tested on its own. The rest are real processes on loopback (multicast
scouting off, explicit ``tcp/127.0.0.1`` ports picked free, one namespace per run), waited on by
condition with a timeout:

* ``faulted`` — a real-time Section 4 run with ``--fault kill:agent/2@3 --fault freeze:agent/4@3+4``
  that a test process joins: once the faults have fired it subscribes to the control key and runs
  ``tether land`` (the order arrives, decoded with the schema alone); the launcher reports the kill and
  the freeze, keeps the others running, records when each fault fired, and exits 4;
* lockstep, an agent frozen longer than a resend: the run file equals the unfaulted run's (its
  peers' resent copies are counted apart, not as link duplicates);
* bad ``--fault`` values exit 2 before anything starts: no process, no file.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from deploy import faults
from tests.support import wait_until
from tests.test_runtime import (REPO, STARTUP, WAIT, Launched, PlainClient, differing_arrays, exit_statuses, launch,
                                processes_naming, tether_cmd, wait_for_realtime_start)
from tether import transport as tp
from tether import wire
from tether.wire import FLYING, LAND, LANDED
from tether.node import load_mission
from tether.runfile import Run

pytestmark = pytest.mark.slow  # real-time runs of every process with injected faults

SECTION4 = "section4"


# =========================================================================== the parser (pure)
@pytest.mark.parametrize("text, kind, target, at, duration", [
    ("kill:agent/2@10", "kill", "agent/2", 10.0, None),
    ("freeze:leader@5+3", "freeze", "leader", 5.0, 3.0),
    ("partition:agent/3@8+2", "partition", "agent/3", 8.0, 2.0),
    ("forge:leader@12", "forge", "leader", 12.0, None),
    ("forge:plant/1@0.5", "forge", "plant/1", 0.5, None),
    ("kill:recorder@0", "kill", "recorder", 0.0, None),
])
def test_parse_reads_every_kind(text: str, kind: str, target: str, at: float, duration: float | None) -> None:
    f = faults.parse(text)
    assert (f.kind, f.target, f.at, f.duration, f.text) == (kind, target, at, duration, text)


@pytest.mark.parametrize("text, says", [
    ("explode:agent/2@1", "unknown kind 'explode'"),
    ("kill agent/2", "KIND:TARGET@T"),
    ("kill:agent/2", "has no time"),
    ("kill:robot/2@1", "unknown process 'robot/2'"),
    ("kill:agent@1", "agent/<id>"),
    ("kill:agent/x@1", "no integer id"),
    ("kill:agent/2@-1", "finite number of seconds >= 0"),
    ("kill:agent/2@nan", "finite number of seconds >= 0"),
    ("kill:agent/2@inf", "finite number of seconds >= 0"),
    ("kill:agent/2@soon", "not a number of seconds"),
    ("freeze:leader@5", "needs a duration"),
    ("partition:agent/3@8+0", "duration is 0"),
    ("kill:agent/2@1+2", "takes no duration"),
    ("forge:recorder@1", "publishes no state"),
])
def test_parse_errors_name_the_argument_and_the_fix(text: str, says: str) -> None:
    with pytest.raises(faults.FaultError) as err:
        faults.parse(text)
    assert f"--fault {text!r}" in str(err.value) and says in str(err.value)


def test_check_names_unknown_processes_and_times_beyond_the_run() -> None:
    m = load_mission(Path(__file__).resolve().parents[1] / "tether" / "missions" / "section4.toml", 10.0)
    members = [("leader", 5), *[(r, a) for a in (1, 2, 3, 4) for r in ("agent", "plant")], ("recorder", 0)]
    problems = faults.check([faults.parse("kill:agent/9@1"), faults.parse("kill:leader@11"),
                             faults.parse("freeze:leader/5@2+1")], m, members)
    assert [arg for arg, _ in problems] == ["--fault kill:agent/9@1", "--fault kill:leader@11"]
    assert "no process agent/9" in problems[0][1] and "agent/1" in problems[0][1]
    assert "after the run's end (10 s)" in problems[1][1]


# =========================================================================== bad input: nothing starts
@pytest.mark.parametrize("fault, says", [
    ("explode:agent/2@1", "unknown kind"),
    ("kill:agent/9@1", "no process agent/9"),
    ("kill:agent/2@-3", ">= 0"),
    ("kill:agent/2@nan", ">= 0"),
    ("kill:agent/2@99", "after the run's end"),
    ("partition:agent/2@1+1", "--network star"),  # with --network mesh below
])
def test_bad_faults_exit_2_before_anything_starts(tmp_path: Path, fault: str, says: str) -> None:
    ns = f"badfault-{os.getpid()}"
    out = tmp_path / "out"
    extra = ["--network", "mesh"] if "partition" in fault else []
    r = subprocess.run(tether_cmd("run", SECTION4, "--out", str(out), "--ns", ns, "--clock", "realtime",
                                  "--duration", "5", "--quiet", "--fault", fault, *extra),
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "--fault" in r.stderr and says in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    assert not out.exists() or not any(out.iterdir())  # no run directory content
    assert processes_naming(ns) == []  # and no process was started
    assert "router listening" not in r.stderr


# =========================================================================== a run with faults, and tether land
@dataclass
class Faulted:
    run: Launched
    land: subprocess.CompletedProcess
    order: wire.SafetyCommand
    launcher_alive_at_land: bool
    modes_after_land: set[int]


KILL_AT, FREEZE_AT, FREEZE_FOR = 3.0, 3.0, 4.0


@pytest.fixture(scope="module")
def faulted(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Faulted]:
    ns = f"faulted-{os.getpid()}"
    port = tp.free_tcp_port()
    attach = tp.loopback_endpoint(port)
    with launch(tmp_path_factory.mktemp("faulted"), ns, "--clock", "realtime", "--duration", "40",
                "--listen", attach, "--insecure", "--fault", f"kill:agent/2@{KILL_AT:g}",  # a plain client attaches
                "--fault", f"freeze:agent/4@{FREEZE_AT:g}+{FREEZE_FOR:g}") as run:
        wait_for_realtime_start(run)
        client = PlainClient(attach)
        try:
            keys = wire.Keys(ns)
            client.subscribe(keys.safety)
            client.subscribe(f"tether/{ns}/plant/*/state")
            wait_until(lambda: _matched(client, keys.safety), WAIT, "the test's subscriber to reach the router")
            # order the land once both faults have fired: a swarm whose supervisors obey it must not
            # have landed (and ended the run) before them
            wait_until(lambda: run.launcher_log.count(" fired at t = ") >= 2, STARTUP, "both faults to fire")
            land = subprocess.run(tether_cmd("land", "--ns", ns, "--connect", attach, "--reason", "test"),
                                  cwd=REPO, capture_output=True, text=True, timeout=60)
            _, order = client.next_matching(lambda k, m: k == keys.safety, WAIT, "the land order")
            alive = run.proc.poll() is None
            modes: set[int] = set()
            deadline = time.monotonic() + 1.0
            while time.monotonic() < deadline:  # what the plants report just after the order
                _, msg = client.next_matching(lambda k, m: isinstance(m, wire.PlantState), WAIT, "a plant state")
                modes.add(msg.mode)
        finally:
            client.close()
        run.wait(STARTUP + 60)
        yield Faulted(run, land, order, alive, modes)


def _matched(client: PlainClient, key: str) -> bool:
    pub = client.session.declare_publisher(key)
    try:
        return bool(pub.matching_status.matching)
    finally:
        pub.undeclare()


def test_tether_land_reaches_a_running_swarm(faulted: Faulted) -> None:
    assert faulted.land.returncode == 0, faulted.land.stderr
    assert "sent land" in faulted.land.stdout
    order = faulted.order
    assert isinstance(order, wire.SafetyCommand)
    assert (order.action, order.reason, order.sender) == ("land", "test", 0)
    assert faulted.launcher_alive_at_land


def test_tether_land_lands_every_survivor_and_ends_the_run(faulted: Faulted) -> None:
    """section4 is 2D and its disturbances sway the vehicles for ever: before ``land_settle``, a 2D
    LAND never saw a vehicle still, so the swarm held until the mission's end (40 s here) and the
    launcher called the landing agents "diverged" as the leader flew on."""
    run = faulted.run
    assert "every surviving vehicle has landed or stopped: ending the run" in run.launcher_log, run.launcher_log
    assert " diverged" not in run.launcher_log, run.launcher_log
    rec = Run.load(run.out)
    heard = np.isfinite(rec.p).all(axis=-1).any(axis=-1)
    assert rec.t[heard][-1] < 25.0  # the order came at about 3 s; 40 s is the mission's end
    for i, aid in enumerate(rec.agent_ids):
        modes = rec.safety.plant_mode[heard, i]
        modes = modes[modes >= 0]
        assert modes[-1] == LANDED, (aid, modes[-1])
    reasons = [e.reason for e in rec.safety.events if e.dst == LANDED]
    assert reasons and all("still" in r or "land_settle" in r or "agent landed" in r for r in reasons), reasons


def test_a_killed_agent_is_reported_and_the_run_exits_4(faulted: Faulted) -> None:
    run = faulted.run
    assert run.status == 4, run.launcher_log
    assert re.search(r"agent/2 +died: killed by SIGKILL \(--fault kill:agent/2@3\)", run.launcher_log), run.launcher_log
    assert exit_statuses(run.launcher_log)["agent/2"] == -9
    assert "exit status 4: a process died or froze" in run.launcher_log


def test_faults_json_says_when_each_fault_fired_within_a_tick(faulted: Faulted) -> None:
    records = {r["fault"]: r for r in json.loads((faulted.run.out / "faults.json").read_text())}
    assert set(records) == {f"kill:agent/2@{KILL_AT:g}", f"freeze:agent/4@{FREEZE_AT:g}+{FREEZE_FOR:g}"}
    for r in records.values():
        print(f"\n{r['fault']}: asked {r['at']} s, fired {r['fired']:.4f} s")
        assert 0.0 <= r["fired"] - r["at"] <= 0.01 + 1e-9, r  # one tick of the 100 Hz mission
    freeze = records[f"freeze:agent/4@{FREEZE_AT:g}+{FREEZE_FOR:g}"]
    assert freeze["kind"] == "freeze" and freeze["target"] == "agent/4"
    assert freeze["ended"] - freeze["fired"] == pytest.approx(FREEZE_FOR, abs=0.1)


def test_a_frozen_agent_is_reported_as_a_freeze(faulted: Faulted) -> None:
    log = faulted.run.launcher_log
    line = re.search(r"t = +([0-9.]+) s +agent/4 +froze: its liveliness token is gone", log)
    assert line, log
    assert FREEZE_AT < float(line[1]) < FREEZE_AT + FREEZE_FOR
    events = json.loads((faulted.run.out / "events.json").read_text())
    assert {(e["who"], e["what"]) for e in events} >= {("agent/2", "died"), ("agent/4", "froze"),
                                                        ("agent/2", "fault"), ("agent/4", "fault")}


def test_the_others_ran_on_after_the_kill(faulted: Faulted) -> None:
    run = faulted.run
    statuses = exit_statuses(run.launcher_log)
    assert set(statuses) == {"leader/5", "recorder/0", *[f"{r}/{i}" for i in (1, 2, 3, 4) for r in ("agent", "plant")]}
    assert all(s in (0, 143) for n, s in statuses.items() if n != "agent/2"), statuses
    rec = Run.load(run.out)
    col = {int(a): i for i, a in enumerate(rec.agent_ids)}
    after = rec.t >= KILL_AT + 2.0
    for aid in (1, 3):  # recorded on, well after the kill
        assert np.isfinite(rec.xi[after, col[aid]]).all(axis=-1).sum() >= 150, aid
    assert not np.isfinite(rec.xi[rec.t >= KILL_AT + 0.5, col[2]]).any()  # and agent 2 did not
    assert math.isfinite(rec.leader_p[after][0, 0])


# =========================================================================== lockstep: a freeze longer than a resend
def test_a_lockstep_freeze_long_enough_to_make_peers_resend_leaves_the_run_as_without_it(tmp_path: Path) -> None:
    """Lockstep, agent 2 frozen for 3 s (longer than ``RESEND``): its peers wait, send their last
    messages again, and receive copies of samples they have. The freeze is reported (exit 4), and
    the run file equals a run without the fault in every array: the copies are counted apart (logged),
    never as a link's duplicates or drops. (A clean-clone CI run once failed this equality, two
    lockstep runs at once on a busy machine, through a resend its load caused.)"""
    ns = f"lockstep-freeze-{os.getpid()}"
    with launch(tmp_path / "frozen", f"{ns}-f", "--duration", "4", "--insecure",
                "--fault", "freeze:agent/2@1+3") as frozen:
        frozen.wait(STARTUP + 60)
    with launch(tmp_path / "plain", f"{ns}-p", "--duration", "4", "--insecure", "--separate-plants") as plain:
        plain.wait(STARTUP + 60)
    assert frozen.status == 4 and plain.status == 0, frozen.launcher_log + plain.launcher_log
    assert re.search(r"agent/2 +froze", frozen.launcher_log), frozen.launcher_log
    stalls = [re.search(r"lockstep stalls: sent (\d+) messages again; dropped (\d+) copies", frozen.child_log(f"agent/{i}"))
              for i in (1, 3, 4)]
    assert any(m and int(m[1]) > 0 for m in stalls), [frozen.child_log(f"agent/{i}") for i in (1, 3, 4)]
    assert any(m and int(m[2]) > 0 for m in stalls), stalls
    assert differing_arrays(frozen.out, plain.out) == []


# =========================================================================== tether land / estop: errors
def test_tether_estop_without_a_router_exits_1_saying_so() -> None:
    nowhere = tp.loopback_endpoint(tp.free_tcp_port())
    r = subprocess.run(tether_cmd("estop", "--ns", "nobody", "--connect", nowhere, "--connect-timeout", "1"),
                       cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    assert "error:" in r.stderr and nowhere in r.stderr and "Traceback" not in r.stderr


@pytest.mark.parametrize("args, names", [
    (["--ns", "a/b", "--connect", "tcp/127.0.0.1:7447"], "--ns"),
    (["--ns", "x"], "--connect"),
    (["--ns", "x", "--connect", "tcp/127.0.0.1:7447", "--timeout", "0"], "--timeout"),
    (["--ns", "x", "--connect", "127.0.0.1:7447"], "connect"),
])
def test_tether_land_bad_input_exits_2_naming_the_argument(args: list[str], names: str) -> None:
    r = subprocess.run(tether_cmd("land", *args), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert names in r.stderr and "Traceback" not in r.stderr


def test_the_monitor_judges_divergence_only_of_a_vehicle_that_was_flying_or_holding() -> None:
    """A landing (or landed) agent has left the formation on purpose: its ‖ξ‖ against a leader that
    flies on grows past ``max_formation_error`` and must not be reported as a divergence (it was, on
    ``section4`` after ``tether land``: 'agent/1 diverged, |xi| = 50 m'). The tick a divergence sends
    an agent from FLYING to LAND is still judged, as its supervisor judges it."""
    import asyncio

    from deploy import inject

    m = load_mission(REPO / "tether" / "missions" / "failsafe.toml", None)
    keys = wire.Keys("judged")
    members = [("leader", 5), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]
    far = m.safety.max_formation_error * 2

    def telemetry(agent: int, k: int, mode: int, xi: float) -> tp.Received:
        z = [0.0] * m.dim
        msg = wire.Telemetry(sender=agent, seq=k, k=k, t=k / m.rate, meas_t=k / m.rate, p=z, vel=z, a=z, u=z,
                             xi=[xi, *z[1:]], zeta=z, kp=[1.0] * m.dim, kv=[1.0] * m.dim, links=[], drops={},
                             mode=mode)
        return tp.Received(keys.topic("agent", agent, "telemetry"), wire.encode(msg))

    async def main() -> None:
        with tp.open_session(tp.ZenohSettings(listen=(tp.loopback_endpoint(tp.free_tcp_port()),))) as session:
            mon = inject.Monitor(session, m, keys, members, lambda: 1.0)
            try:
                a, b = m.agent_ids[0], m.agent_ids[1]
                # agent a lands (operator), then its xi grows as the leader flies on: not a divergence
                for k, mode, xi in [(1, FLYING, 0.1), (2, LAND, 0.2), (3, LAND, far), (4, LANDED, far)]:
                    mon.fifo.put(telemetry(a, k, mode, xi))
                # agent b diverges while flying: its supervisor lands it at that very tick
                for k, mode, xi in [(1, FLYING, 0.1), (2, LAND, far), (3, LAND, far)]:
                    mon.fifo.put(telemetry(b, k, mode, xi))
                mon.poll()
                diverged = [e.who for e in mon.events if e.what == "diverged"]
                assert diverged == [f"agent/{b}"], mon.events
                assert mon.modes[f"agent/{a}"] == LANDED
            finally:
                mon.close()

    asyncio.run(main())


def test_what_the_monitor_reads_is_a_part_of_the_wire_messages_and_decodes_them() -> None:
    """The monitor decodes only the fields it judges (``deploy/inject.py``): each of its structs
    has a wire message's tag and a subset of its fields, with the same defaults, so that every
    message the swarm sends decodes, and a changed wire message fails here, not in a run."""
    import msgspec

    from deploy import inject

    pairs = [(inject._Telemetry, wire.Telemetry), (inject._PlantState, wire.PlantState), (inject._State, wire.State),
             (inject._Record, wire.Record)]
    for mine, theirs in pairs:
        assert mine.__struct_config__.tag == theirs.__struct_config__.tag
        fields = {f.name: f for f in msgspec.structs.fields(theirs)}
        for f in msgspec.structs.fields(mine):
            assert f.name in fields, (mine, f.name)
            assert (f.default, f.default_factory) == (fields[f.name].default, fields[f.name].default_factory) \
                or (f.default_factory is list and fields[f.name].default == []), (mine, f.name)
    z = [0.0, 0.0]
    tele = wire.Telemetry(sender=2, seq=3, k=3, t=0.03, meas_t=0.03, p=z, vel=z, a=z, u=z, xi=[0.5, 0.0], zeta=z,
                          kp=[1.0, 2.0], kv=z, links=[], drops={"malformed": 1}, mode=wire.LAND)
    plant = wire.PlantState(sender=2, seq=3, k=3, t=0.03, p=[0.0, 1.5], vel=z, a=z, d=z)
    decoder = msgspec.msgpack.Decoder(inject._Heard)
    got = decoder.decode(wire.encode(wire.Record(sender=2, seq=0, k=3, t=0.03, plant=[plant], telemetry=[tele])))
    assert isinstance(got, inject._Record)
    assert (got.telemetry[0].mode, got.telemetry[0].xi, got.telemetry[0].kp) == (wire.LAND, [0.5, 0.0], [1.0, 2.0])
    assert got.plant[0].p == [0.0, 1.5]


def test_a_token_back_within_the_confirmation_delay_is_still_reported_as_a_freeze() -> None:
    """A freeze (or cut-off) about as long as the lease: the token goes and comes back within
    Monitor.CONFIRM while the process ran on. Measured before the fix (bench/faults.py,
    freeze:agent/1@8+3 with the 2 s lease): no 'froze' event, exit status 3 instead of 4."""
    from deploy import inject

    m = load_mission(REPO / "tether" / "missions" / "failsafe.toml", None)
    keys = wire.Keys("failsafe")
    members = [("leader", 5), *[(r, a) for a in m.agent_ids for r in ("agent", "plant")], ("recorder", 0)]
    clock = [9.0]
    import asyncio

    async def main() -> None:
        with tp.open_session(tp.ZenohSettings(listen=(tp.loopback_endpoint(tp.free_tcp_port()),))) as session:
            mon = inject.Monitor(session, m, keys, members, lambda: clock[0])
            try:
                mon.proc_alive = lambda name: True
                mon.token_events.put(tp.TokenEvent(keys.token("agent", 1), True))
                mon.poll()
                mon.token_events.put(tp.TokenEvent(keys.token("agent", 1), False))
                mon.poll()
                clock[0] = 9.5
                mon.token_events.put(tp.TokenEvent(keys.token("agent", 1), True))
                mon.poll()
                got = [(e.who, e.what, e.t) for e in mon.events]
                assert ("agent/1", "froze", 9.0) in got and ("agent/1", "back", 9.5) in got
                # a process that ends withdraws its token for good: not a freeze
                mon.proc_alive = lambda name: name != "agent/2"
                mon.token_events.put(tp.TokenEvent(keys.token("agent", 2), True))
                mon.token_events.put(tp.TokenEvent(keys.token("agent", 2), False))
                mon.poll()
                assert not [e for e in mon.events if e.who == "agent/2"]
            finally:
                mon.close()

    asyncio.run(main())


# =========================================================================== a silent plant: no stale command
SILENT_AT, SILENT_FOR = 4.0, 1.5


def test_an_agent_sends_no_command_while_its_plant_is_silent(tmp_path: Path) -> None:
    """Plant 2 frozen for 1.5 s: its agent, hearing nothing from it, sends no command at all from
    the moment it calls the plant silent until it hears it again (a command computed from its last
    measurement would be flown on the vehicle as it is now), says so once each way, and flies on;
    the plant's watchdog, back, holds on its own measurement until a fresh command comes."""
    ns = f"silentplant-{os.getpid()}"
    attach = tp.loopback_endpoint(tp.free_tcp_port())
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", "12", "--listen", attach, "--insecure",
                "--fault", f"freeze:plant/2@{SILENT_AT:g}+{SILENT_FOR:g}") as run:
        wait_for_realtime_start(run)
        client = PlainClient(attach)
        sent: list[float] = []
        try:
            client.subscribe(f"tether/{ns}/agent/2/cmd")
            while not sent or sent[-1] < SILENT_AT + SILENT_FOR + 3.0:
                _, msg = client.next_matching(lambda k, m: isinstance(m, wire.Command), STARTUP, "agent 2's commands")
                sent.append(msg.t)
        finally:
            client.close()
        run.wait(STARTUP + 30)
    log = run.child_log("agent/2")
    assert log.count("no command sent until it is back") == 1, log
    assert log.count("plant back: commands sent again") == 1, log
    rec = Run.load(run.out)
    said = [e for e in rec.safety.events if e.vehicle == 2 and e.src == e.dst and e.reason.startswith("plant ")]
    assert [e.reason.split(" ")[1] for e in said] == ["silent", "back:"], said
    quiet, back = said[0].t, said[1].t
    assert SILENT_AT < quiet < back and back - quiet >= SILENT_FOR - 0.6
    assert not [t for t in sent if quiet <= t < back], (quiet, back)  # nothing while silent
    assert [t for t in sent if t >= back]  # and commands again once it is back
    plant = run.child_log("plant/2")  # back, its watchdog held until a fresh command came
    assert re.search(r"FLYING -> HOLD at [0-9.]+ s: no valid command for", plant), plant
    assert "command back" in plant, plant
