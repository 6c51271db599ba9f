"""``tether run`` hardened: authenticated by default, floods bounded, replays not relayed, no crash on
bad input, truthful exit statuses (``deploy/local.py``, ``deploy/localtls.py``, ``tether/node.py``).

Every run is real processes on loopback; every wait is on a condition with a timeout:

* a default run admits no session without a certificate of the run (plain TCP, TLS without a client
  certificate), while the operator identity it writes (``DIR/tls/control-0.json5``) attaches and
  lands the swarm with ``tether land --zenoh-config``;
* a flood of junk on an input of every vehicle (the order key, from the operator identity) for 8 s
  leaves the formation error
  (RMS of ||xi_i|| over the agents and the flood's ticks) within 10 % of a clean real-time run's, and so
  does a rogue plant flooding its own state key;
* a replay of agent 1's plant samples is counted and never re-published as agent 1's state, and a
  replay of a neighbour's samples does not push a link's delivery above 1;
* a lockstep acknowledgement on a key with a non-numeric id is dropped and counted, not a crash;
  SIGTERM exits 143; without ``openssl`` the launcher says so and exits 2.
"""

from __future__ import annotations

import contextlib
import os
import queue
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import NamedTuple

import msgspec
import numpy as np
import pytest

from deploy import localtls
from sim import refsim
from tests.support import read, wait_until
from tests.test_runtime import (REPO, SECTION4, STARTUP, WAIT, PlainClient, envelope, launch, tether_cmd,
                                wait_for_realtime_start)
from tether import transport as tp
from tether import wire
from tether.node import load_mission
from tether.runfile import Run

pytestmark = pytest.mark.slow  # real processes, real time

FLOOD_FROM, FLOOD_FOR = 6.0, 8.0
"""Mission time [s] the flood starts, and how long it lasts."""


def up(run) -> None:
    wait_until(lambda: "processes are up" in run.launcher_log or run.proc.poll() is not None, STARTUP,
               "every process to come up")
    assert run.proc.poll() is None, run.launcher_log


# =========================================================================== authenticated by default
def test_a_default_run_admits_only_its_own_identities_and_the_operator_lands_it(tmp_path: Path) -> None:
    ns = f"secure-{os.getpid()}"
    attach = f"tls/127.0.0.1:{tp.free_tcp_port()}"
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", "60", "--listen", attach) as run:
        wait_for_realtime_start(run)
        tls = run.out / "tls"
        assert (tls / "control-0.json5").is_file() and (tls / "ca.crt").is_file()
        assert not list(tls.glob("ca.key")) and not list(run.out.rglob("ca.key"))  # nothing more can be signed
        assert all((k.stat().st_mode & 0o077) == 0 for k in tls.glob("*.key"))
        assert "identities made in" in run.launcher_log and "--insecure" not in run.launcher_log
        port = attach.rsplit(":", 1)[1]
        router = msgspec.json.decode((tls / "router.json5").read_text().split("\n", 1)[1])["listen"]["endpoints"]
        assert attach not in router  # --listen is the operator gateway's, not the control router's
        for name in ("router", "gateway"):  # both routers queue a tick's burst (tether/transport.py), read by Zenoh
            conf = tp.zenoh_config(tp.ZenohSettings(config_file=str(tls / f"{name}.json5")))
            assert msgspec.json.decode(conf.get_json("transport/link/tx/queue/size")) == tp.ROUTER_TX_QUEUE, name
        attempts = {
            # the operator's certificate is signed by the operator CA, which the control router does not trust:
            # a tool holding it, flooding or not, reaches the run through the gateway only
            "the operator identity at the control router": tp.ZenohSettings(
                mode="client", connect=(router[0],), tls=tp.TlsFiles(
                    root_ca_certificate=str(tls / "ca.crt"), connect_certificate=str(tls / "control-0.crt"),
                    connect_private_key=str(tls / "control-0.key"), enable_mtls=True)),
            "plain TCP": tp.ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)),
            "TLS without a client certificate": tp.ZenohSettings(
                mode="client", connect=(attach,), tls=tp.TlsFiles(root_ca_certificate=str(tls / "ca.crt"))),
        }
        for what, settings in attempts.items():
            with pytest.raises(tp.TransportError, match="Unable to connect"):
                with tp.open_session(settings):
                    pytest.fail(f"{what}: a link was opened")
        # the operator identity attaches and its land order is obeyed by every vehicle
        land = subprocess.run(tether_cmd("land", "--ns", ns, "--zenoh-config", str(tls / "control-0.json5"),
                                         "--reason", "test"), cwd=REPO, capture_output=True, text=True, timeout=60)
        assert land.returncode == 0, land.stdout + land.stderr
        run.wait(STARTUP)
    assert run.status == 3, run.launcher_log  # a failsafe (LAND) fired: the vehicles obeyed
    assert "operator: land (test)" in run.child_log("agent/1")
    assert "ERROR" not in run.launcher_log


# =========================================================================== floods
FLOODER = textwrap.dedent("""
    import os, sys, time, zenoh
    os.nice(19)  # an attacker elsewhere: the flood's messages, not its CPU, are what is tested
    config, key, delay, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
    RATE = 255_000  # messages per second at most (the rate of the reported incident)
    conf = zenoh.Config.from_file(config)  # the operator identity the run wrote beside it
    with zenoh.open(conf) as s:
        pub = s.declare_publisher(key, congestion_control=zenoh.CongestionControl.DROP)
        junk = bytes(range(64))  # 64 bytes, not a message: every copy is rejected by the decoder
        time.sleep(delay)
        n, t0 = 0, time.monotonic()
        while time.monotonic() - t0 < seconds:
            for _ in range(1000):
                pub.put(junk)
            n += 1000
            ahead = n / RATE - (time.monotonic() - t0)
            if ahead > 0:
                time.sleep(ahead)
        print(n, time.monotonic() - t0, flush=True)
""")


def formation_error(run: Run, since: float, until: float) -> float:
    """The RMS over every agent and every tick ``since <= t_k <= until`` of ||xi_i(t_k)|| [m], xi as
    the agents computed it (Eq. 8). Why this statistic: it weighs every agent and every tick of the
    window alike, so that a sustained rise (the incident: 16.6 m for 4 s of 11) moves it in full, and
    a rise on one agent only counts too, while one tick this shared machine's load delayed moves it by
    a fraction of a percent; a maximum (the envelope) moved by 2x between two clean runs here, and a
    percentile of the worst agent hides what the other agents do. Ticks whose samples were lost (NaN)
    are left out."""
    window = (run.t >= since - 1e-9) & (run.t <= until + 1e-9)
    return float(np.sqrt(np.nanmean(np.linalg.norm(run.xi[window], axis=-1) ** 2)))


FLOODS = {
    "order": ("control-0.json5", lambda keys: keys.safety),
    "plant": ("plant-2.json5", lambda keys: keys.topic("plant", 2, "state")),
}
"""Who floods which key: the operator identity the order key (every agent and plant hears it), or a
rogue plant 2 its own state key (agent 2, the recorder, and whoever else hears plant 2)."""


def _flight(tmp: Path, ns: str, flood: str | None) -> tuple[Run, str]:
    """A 20 s real-time run of Section 4, authenticated (the default), flooded or not (``flood``: a
    key of :data:`FLOODS`) by a tool holding that identity: a hostile tool that may publish there."""
    attach = f"tls/127.0.0.1:{tp.free_tcp_port()}"
    report = ""
    with launch(tmp, ns, "--clock", "realtime", "--duration", "20", "--listen", attach) as run:
        wait_for_realtime_start(run)
        if flood:  # tick 0 is 1 s after the start message (start_lead): from about FLOOD_FROM s of mission time
            identity, key = FLOODS[flood]
            flooder = subprocess.run([sys.executable, "-c", FLOODER, str(run.out / "tls" / identity), key(wire.Keys(ns)),
                                      str(FLOOD_FROM - 1.0), str(FLOOD_FOR)], capture_output=True, text=True,
                                     timeout=STARTUP)
            assert flooder.returncode == 0, flooder.stderr
            sent, took = flooder.stdout.split()
            report = f"{int(sent)} junk samples in {float(took):.1f} s ({int(sent) / float(took):.0f}/s), "
        run.wait(STARTUP)
    # 5: recorded, some samples lost (DROP streams under load); 3: a transient failsafe (a process starved
    # of CPU for half a second on this shared machine): the formation error is what is asserted
    assert run.status in (0, 3, 5), run.launcher_log
    return Run.load(run.out), report + f"exit status {run.status}"


class FloodPair(NamedTuple):
    got: float
    """RMS of ||xi_i|| over the window, flooded run [m]."""
    want: float
    """The same, clean run [m]."""
    ideal: float
    """The same, reference simulator [m]."""
    drops: np.ndarray
    """Samples each agent dropped, flooded run."""
    clean_drops: np.ndarray
    """Samples each agent dropped, clean run."""
    unfit: str | None
    """Why this pair cannot measure the flood (the machine could not fly the mission), or None."""
    clean: Run
    """The clean run."""
    ideal_run: Run
    """The reference simulator's run of the same mission."""


ATTEMPTS = 3
"""Pairs flown at most, until one in which the machine could fly the mission (:func:`_unfit`)."""
BEFORE = (2.0, FLOOD_FROM - 0.5)
"""Mission time [s] before the flood (the flooder is starting up), checked in both runs of a pair."""
FIT = 0.10
"""A run is the mission as flown when its formation error is within this share of the reference
simulator's: the clean run over the flood's window and before it, the flooded run before it."""


def _unfit(clean: Run, flooded: Run, ideal: Run) -> str | None:
    """Why a pair cannot tell what the flood did, or None. A clean run the machine's load degraded by
    itself is no measure of the flood; nor is a flooded run that was already off before the flood
    began (other work on this shared machine starving its processes, not the flood)."""
    since, until = FLOOD_FROM + 1.0, FLOOD_FROM + FLOOD_FOR
    checks = (("the clean run", clean, since, until), ("the clean run, before the flood", clean, *BEFORE),
              ("the flooded run, before the flood", flooded, *BEFORE))
    for what, run, a, b in checks:
        got, want = formation_error(run, a, b), formation_error(ideal, a, b)
        if abs(got - want) > FIT * want:
            return (f"{what} is {100 * (got / want - 1):+.0f} % off the reference simulator over {a:g}..{b:g} s "
                    f"({got:.4f} m vs {want:.4f} m): the machine was too loaded for a real-time comparison")
    return None


@pytest.fixture(scope="module")
def flood_pair(tmp_path_factory: pytest.TempPathFactory) -> FloodPair:
    """The same mission twice, one after the other (two at once overload this machine, flood or not):
    clean, then flooded with junk on the order key, which every agent and plant subscribes to, from mission
    time FLOOD_FROM for FLOOD_FOR seconds. The flooder runs at the lowest priority (an attacker
    elsewhere, as far as one process on the same two cores can be: its messages are what is tested, and
    what CPU it still takes counts against the machine). Compared from the flood's second second on.
    A pair in which the machine could not fly the mission (:func:`_unfit`, checked before and apart
    from the flood's window of the flooded run) is flown again, ATTEMPTS times at most; the last pair
    is returned either way, and the tests fail on an unfit one naming why."""
    tmp_path = tmp_path_factory.mktemp("flood")
    ideal_run = refsim.simulate(load_mission(SECTION4, 20.0))
    since, until = FLOOD_FROM + 1.0, FLOOD_FROM + FLOOD_FOR
    ideal = formation_error(ideal_run, since, until)
    for attempt in range(1, ATTEMPTS + 1):
        ns = f"flood-{os.getpid()}-{attempt}"
        clean, clean_report = _flight(tmp_path / f"clean-{attempt}", f"{ns}-clean", flood=None)
        flooded, report = _flight(tmp_path / f"flooded-{attempt}", f"{ns}-flooded", flood="order")
        got, want = formation_error(flooded, since, until), formation_error(clean, since, until)
        drops = np.nanmax(flooded.runtime.drops, axis=0)  # per agent, since the start
        clean_drops = np.nanmax(clean.runtime.drops, axis=0)
        unfit = _unfit(clean, flooded, ideal_run)
        print(f"\nflood (pair {attempt}, {os.getloadavg()[0]:.1f} load average): {report} on control/0/safety; reached "
              f"and dropped by each agent: {drops.astype(int).tolist()}; formation error (RMS of ||xi_i|| over agents and "
              f"ticks, t = {since:g}..{until:g} s): flooded {got:.4f} m, clean {want:.4f} m ({clean_report}) "
              f"({100 * (got / want - 1):+.1f} %), reference simulator {ideal:.4f} m; envelopes (max): flooded "
              f"{envelope(flooded, since):.4f} m, clean {envelope(clean, since):.4f} m"
              + ("" if unfit is None else f"; unfit: {unfit}"))
        if unfit is None:
            break
    return FloodPair(got, want, ideal, drops, clean_drops, unfit, clean, ideal_run)


def _clean_is_the_mission(r: FloodPair) -> None:
    # the clean run must be the mission as flown (it is, on a machine with the CPU for 10 processes at
    # 100 Hz: within 0.1 % of the reference simulator), and the flooded one before the flood too
    assert r.unfit is None, f"in each of {ATTEMPTS} pairs, {r.unfit}"


def test_a_flood_is_kept_off_the_control_loops(flood_pair: FloodPair) -> None:
    """What the access rules and the per-link ingress limits guarantee: the flood reaches every agent
    only at the order key's limit (CONTROL_RATE a second, rejected and counted, where the incident let
    255 000 a second into the control loop), and the formation is not lost."""
    _clean_is_the_mission(flood_pair)
    drops = flood_pair.drops - flood_pair.clean_drops
    assert (flood_pair.drops > 0).all()  # the flood did reach every agent (rejected and counted)
    limit = 2 * localtls.CONTROL_RATE * FLOOD_FOR  # per agent: one flooding link, twice the limit's share
    assert (drops <= limit).all(), f"rejected per agent {drops.tolist()} > {limit:g}: the ingress limit let more in"


def test_a_flood_on_every_process_input_leaves_the_formation_error_within_10_percent(
        flood_pair: FloodPair) -> None:
    """|flooded - clean| <= 10 % of clean, RMS of ||xi_i|| over 7..14 s. The flood comes through the
    operator gateway, which runs at SCHED_IDLE (``deploy/localtls.py``): what its messages cost to
    decrypt and check is taken from idle CPU, not from the control loops (docs/deploy.md)."""
    _clean_is_the_mission(flood_pair)
    got, want = flood_pair.got, flood_pair.want
    assert abs(got - want) <= 0.10 * want, f"flooded {got:.4f} m vs clean {want:.4f} m"


def test_a_rogue_plants_flood_on_its_own_state_key_leaves_the_formation_error_within_10_percent(
        flood_pair: FloodPair, tmp_path: Path) -> None:
    """A tool holding plant 2's identity floods plant 2's state key, which agent 2 and the recorder
    hear: the router passes LIMIT_FACTOR times the rate of it per link (``deploy/localtls.py``), agent
    2 rejects and counts the junk, and the formation error stays within 10 % of the clean run of the
    pair above (measured: 0.4413 m against 0.4412 m)."""
    _clean_is_the_mission(flood_pair)
    for attempt in range(1, ATTEMPTS + 1):  # flown again while the machine could not fly it (_unfit)
        flooded, report = _flight(tmp_path / f"plant-flooded-{attempt}", f"flood-{os.getpid()}-plant-{attempt}",
                                  flood="plant")
        unfit = _unfit(flood_pair.clean, flooded, flood_pair.ideal_run)
        if unfit is None:
            break
    assert unfit is None, f"in each of {ATTEMPTS} runs, {unfit} ({report})"
    since, until = FLOOD_FROM + 1.0, FLOOD_FROM + FLOOD_FOR
    got, want = formation_error(flooded, since, until), flood_pair.want
    drops = np.nanmax(flooded.runtime.drops, axis=0) - np.nanmax(flood_pair.clean.runtime.drops, axis=0)
    print(f"\nrogue plant 2: {report}; dropped by each agent {drops.astype(int).tolist()}; formation error "
          f"{got:.4f} m, clean {want:.4f} m ({100 * (got / want - 1):+.1f} %)")
    agent2 = flooded.agent_ids.tolist().index(2)
    assert drops[agent2] > 0  # the flood reached agent 2, rejected and counted
    limit = 2 * localtls.LIMIT_FACTOR * flooded.meta.rate * FLOOD_FOR  # one flooding link, twice its share
    assert drops[agent2] <= limit, f"agent 2 rejected {drops[agent2]:g} > {limit:g}: the ingress limit let more in"
    assert abs(got - want) <= 0.10 * want, f"flooded {got:.4f} m vs clean {want:.4f} m"


# =========================================================================== replays
def test_replayed_samples_are_counted_not_relayed_and_delivery_stays_at_most_1(tmp_path: Path) -> None:
    ns = f"replay-{os.getpid()}"
    keys = wire.Keys(ns)
    attach = tp.loopback_endpoint(tp.free_tcp_port())
    plant1, agent1, agent4 = keys.topic("plant", 1, "state"), keys.topic("agent", 1, "state"), keys.topic("agent", 4, "state")
    tele4 = keys.topic("agent", 4, "telemetry")  # only the recorder hears it
    with launch(tmp_path, ns, "--clock", "realtime", "--duration", "12", "--insecure", "--listen", attach) as run:
        wait_for_realtime_start(run)
        client = PlainClient(attach)
        try:
            client.subscribe(plant1)
            client.subscribe(agent4)
            client.subscribe(tele4)
            recorded: dict[str, list[bytes]] = {plant1: [], agent4: [], tele4: []}
            deadline = time.monotonic() + WAIT + 20
            while min(len(v) for v in recorded.values()) < 100:  # a second of each
                assert time.monotonic() < deadline, "did not hear a second of plant 1 and agent 4"
                key, payload = client.samples.get(timeout=WAIT)
                recorded[key].append(payload)
            client.unsubscribe()
            client.subscribe(agent1)  # what agent 1 publishes as its own state from now on
            pubs = {k: client.publisher(k) for k in recorded}
            for _ in range(3):  # every recorded sample again, three times
                for key, payloads in recorded.items():
                    for p in payloads:
                        pubs[key].put(p)
            relayed: list[wire.State] = []

            def two_seconds() -> bool:
                _take(client, relayed, agent1)
                return len(relayed) >= 200

            wait_until(two_seconds, WAIT + 20, "two seconds of agent 1's state after the replay")
        finally:
            client.close()
        run.wait(STARTUP)
    ks = [m.k for m in relayed]
    assert ks == sorted(set(ks)), "agent 1 re-published a sample that was not newer than the last"
    rt = Run.load(run.out)
    i1 = list(rt.agent_ids).index(1)
    assert np.nanmax(rt.runtime.drops[:, i1]) > 0  # the replayed plant samples were counted (stale_relay / gate)
    delivery = rt.links.delivery
    assert delivery is not None and np.nanmax(delivery) <= 1.0, np.nanmax(delivery)
    d = rt.links.duplicates[:, i1]  # cumulative per tick; the last tick's telemetry may be lost (NaN)
    assert np.nanmax(d) > 0  # the replayed neighbour samples were counted as duplicates
    # the recorder heard plant 1's samples again too: each tick's is recorded once, and a replay
    # cannot make up for a sample that is missing (the counts never exceed what was expected)
    drops = rt.meta.recorder_drops
    assert drops is not None and rt.meta.samples_recorded is not None and rt.meta.samples_expected is not None
    # 3 x 100 replayed telemetry samples of agent 4, sent in one burst: DROP streams lose part of it on
    # a loaded machine (CI heard 102), so at least one; without the per-slot count it is 0
    assert drops.other.get("duplicate_sample", 0) > 0, drops
    assert rt.meta.samples_recorded <= rt.meta.samples_expected, (rt.meta.samples_recorded, rt.meta.samples_expected)


def _take(client: PlainClient, into: list, key: str) -> None:
    """Decode every sample the client has queued on ``key`` into ``into``; samples of the keys it
    heard before (still queued when it unsubscribed from them) are left out."""
    with contextlib.suppress(queue.Empty):
        while True:
            got, payload = client.samples.get_nowait()
            if got == key:
                into.append(msgspec.msgpack.decode(payload, type=wire.Message))


# =========================================================================== bad input, exit statuses
ACKER = textwrap.dedent("""
    import sys, zenoh
    endpoint, key, payload = sys.argv[1], sys.argv[2], bytes.fromhex(sys.argv[3])
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", '["%s"]' % endpoint)
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as s:
        pub = s.declare_publisher(key)
        while not pub.matching_status.matching:  # the launcher's acknowledgement subscriber
            pass
        while True:  # until the run is over (the test kills this process)
            pub.put(payload)
            import time; time.sleep(0.01)
""")


@pytest.mark.parametrize("node, k, reason", [("x", 1, "ack_key"), ("0", 10**6, "ack_ahead")],
                         ids=["malformed key", "forged, far ahead"])
def test_a_malformed_lockstep_acknowledgement_is_dropped_and_counted_not_a_crash(
        tmp_path: Path, node: str, k: int, reason: str) -> None:
    """An acknowledgement on a key the launcher cannot parse, or one in the recorder's name of a
    tick not granted yet (it would stand for every tick up to it, and end the run before the
    recorder holds them): dropped and counted; the run goes on to the end, complete."""
    ns = f"badack-{os.getpid()}-{reason}"
    attach = tp.loopback_endpoint(tp.free_tcp_port())
    ack = wire.encode(wire.Ack(sender=0, seq=0, k=k, t=k / 100, role="recorder"))
    with launch(tmp_path, ns, "--duration", "10", "--insecure", "--listen", attach) as run:
        up(run)
        acker = subprocess.Popen([sys.executable, "-c", ACKER, attach, f"tether/{ns}/recorder/{node}/ack", ack.hex()],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            run.wait(STARTUP + 60)
        finally:
            acker.kill()
            acker.wait()
    assert run.status == 0, run.launcher_log
    assert "Traceback" not in run.launcher_log
    assert "malformed message(s):" in run.launcher_log and reason in run.launcher_log, run.launcher_log


def test_sigterm_exits_143_and_says_so(tmp_path: Path) -> None:
    with launch(tmp_path, f"term-{os.getpid()}", "--clock", "realtime", "--duration", "60", "--insecure") as run:
        wait_for_realtime_start(run)
        run.proc.send_signal(signal.SIGTERM)
        run.wait(60)
    assert run.status == 143, run.launcher_log
    assert "terminated (SIGTERM)" in run.launcher_log


def test_without_openssl_a_default_run_exits_2_naming_it(tmp_path: Path) -> None:
    bare = tmp_path / "bin"
    bare.mkdir()
    env = {**os.environ, "PATH": str(bare)}  # no openssl on PATH
    assert shutil.which("openssl", path=str(bare)) is None
    r = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--out", str(tmp_path / "out"), "--quiet"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "openssl" in r.stderr and "--insecure" in r.stderr, r.stderr
    assert not (tmp_path / "out" / "logs").exists()  # nothing started


# --------------------------------------------------------------------------- closing while a tap relays
def _race_undeclare(session: object, guard: object | None, trials: int) -> int:
    """Undeclare a publisher while a thread puts on it (through ``guard`` when given, closed first);
    how many undeclares raised ``RuntimeError`` ("Already borrowed")."""
    import threading

    from tether import handoff
    from tether import transport as tp

    raised = 0
    for trial in range(trials):
        pub = tp.declare_publisher(session, f"race/{trial}")  # type: ignore[arg-type]
        gate = handoff.TapGuard() if guard is not None else None
        running, stop = threading.Event(), threading.Event()

        def loop() -> None:
            while not stop.is_set():
                if gate is not None and not gate.enter():
                    running.set()
                    return
                try:
                    pub.put(b"x" * 64)
                except Exception:  # noqa: BLE001 - put on an undeclared publisher: the race's other side
                    return
                finally:
                    if gate is not None:
                        gate.leave()
                    running.set()

        thread = threading.Thread(target=loop, daemon=True)
        thread.start()
        assert running.wait(WAIT)
        if gate is not None:
            assert gate.close(WAIT)
        try:
            pub.undeclare()
        except RuntimeError:
            raised += 1
        stop.set()
        thread.join(WAIT)
    return raised


def test_a_node_closing_while_a_tap_relays_raises_nothing(caplog: pytest.LogCaptureFixture) -> None:
    """An agent relays its plant's state from Zenoh's thread (a tap) while it closes after a land order.
    Undeclaring a publisher that another thread is putting on raises ``RuntimeError: Already borrowed``
    (shown first: the race is real, and it turned clean landings into exit 1); a node's close waits
    for its running taps (``tether.handoff.TapGuard``) before undeclaring, and raises nothing."""
    import asyncio
    import threading

    from tether import node as nd
    from tether import transport as tp
    from tether import wire
    from tether.catalog import builtin_path
    from tether.clock import RealtimeClock

    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    with tp.open_session(tp.ZenohSettings(mode="router", listen=(endpoint,), scouting_delay=0.0)) as session:
        assert _race_undeclare(session, None, 20) > 0  # without the guard
        assert _race_undeclare(session, True, 20) == 0

    m = nd.load_mission(builtin_path("section4"))

    async def one_close(trial: int) -> int:
        ep = tp.loopback_endpoint(tp.free_tcp_port())
        args = nd.NodeArgs(mission_path=builtin_path("section4"), role="agent", node_id=1, clock="realtime",
                           zenoh=tp.ZenohSettings(mode="router", listen=(ep,), scouting_delay=0.0))
        client = tp.ZenohSettings(mode="client", connect=(ep,), scouting_delay=0.0)
        relayed = 0
        async with tp.open_session(args.zenoh) as session, tp.open_session(client) as other:
            node = nd.Node(args, m, session, RealtimeClock(m.dt))
            key = node.keys.topic("plant", 1, "state")

            def relay(rec: tp.Received) -> None:
                nonlocal relayed
                out.put(wire.State(sender=1, seq=relayed, k=relayed, t=relayed * m.dt, p=[0.0, 0.0],
                                   vel=[0.0, 0.0], a=[0.0, 0.0]))
                relayed += 1

            node.source(key, wire.State, 1, tap=relay)
            # declared after its source, so undeclared before it: the source's callbacks still run then
            out = node.publisher(node.keys.topic("agent", 1, "relay"))
            pub = tp.declare_publisher(other, key, tp.STATE)
            await tp.wait_for_subscribers(pub, WAIT)
            stop = threading.Event()

            def flood() -> None:
                k = 0
                while not stop.is_set():
                    pub.put(wire.encode(wire.State(sender=1, seq=k, k=k, t=k * m.dt, p=[0.0, 0.0], vel=[0.0, 0.0],
                                                   a=[0.0, 0.0])))
                    k += 1

            thread = threading.Thread(target=flood, daemon=True)
            thread.start()
            deadline = time.monotonic() + WAIT
            while relayed < 50 and time.monotonic() < deadline:
                await asyncio.sleep(0.005)
            assert relayed >= 50, f"trial {trial}: the tap relayed {relayed} samples"
            try:
                node.close()  # while the tap relays: raised "Already borrowed" without the guard
            finally:
                stop.set()
                thread.join(WAIT)
                pub.undeclare()
            assert "tap_error" not in node.receiver.drops, node.receiver.drops  # no tap met an undeclared publisher
        return relayed

    for trial in range(5):
        assert asyncio.run(one_close(trial)) >= 50
    borrowed = [r.getMessage() for r in caplog.records 
                if any(w in r.getMessage() for w in ("undeclaring", "tap still", "tap failed"))]
    assert not borrowed, borrowed  # close undeclared nothing a tap was using


# --------------------------------------------------------------------------- the launcher's own freeze
LAUNCHER_FREEZE = 8.0
"""How long the launcher is stopped [s]: four leases (2 s), so every link to its router lapses."""


def test_a_frozen_launcher_blames_itself_not_its_processes(tmp_path: Path) -> None:
    """SIGSTOP of the launcher for four leases in a real-time run: on waking it finds every token
    gone and back. It reports its own freeze (an event of ``launcher``, exit status 4: the run's router
    was lost that long), and no process is reported frozen, silent or dead for it."""
    import json

    with launch(tmp_path, "selffreeze", "--clock", "realtime", "--duration", "30", "--insecure") as run:
        wait_for_realtime_start(run)
        os.kill(run.proc.pid, signal.SIGSTOP)
        try:
            time.sleep(LAUNCHER_FREEZE)  # the stimulus itself (a freeze this long), not a wait for a condition
        finally:
            os.kill(run.proc.pid, signal.SIGCONT)
        status = run.wait(STARTUP + 120)
    events = json.loads((run.out / "events.json").read_text())
    own = [e for e in events if e["who"] == "launcher" and e["what"] == "froze"]
    assert len(own) == 1 and "did not run for" in own[0]["why"], events
    blamed = [e for e in events if e["who"] != "launcher" and e["what"] in ("froze", "silent", "died")]
    assert not blamed, blamed
    assert status == 4, run.launcher_log[-3000:]
