"""Watching a swarm: ``tether run --live`` read with a real WebSocket client speaking the Foxglove
WebSocket protocol, ``tether record`` attached to a real ``tether run --listen`` (before it starts,
and late under mTLS with the operator identity) and stopped with SIGINT, and a run stopped with
SIGINT leaving both files. Real processes, real Zenoh on loopback, the real ``mcap`` reader."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")

from recorder import viz  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether.runfile import Run  # noqa: E402

from tests.foxglove_live import listen  # noqa: E402
from tests.support import REPO, finish, free_port, kill, tether_popen, wait_until  # noqa: E402
from tests.test_viz import file_content  # noqa: E402


def read_mcap(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    with open(path, "rb") as fh:
        reader = mcap_reader.make_reader(fh)
        out: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            out[channel.topic].append((message.log_time, message.data))
    return dict(out)


def heard(run: Run) -> np.ndarray:
    """Ticks of which every agent's telemetry was recorded."""
    return np.flatnonzero(np.all(np.isfinite(run.xi[:, :, 0]), axis=1))


def same_samples(a: np.ndarray, b: np.ndarray, what: str, least: int = 200) -> None:
    """The very same values wherever both files hold the sample (a real-time stream under load drops
    some, in either recorder), and at least ``least`` of them."""
    both = np.isfinite(a) & np.isfinite(b)
    assert both.sum() >= least, f"{what}: only {both.sum()} values in both files"
    assert np.array_equal(a[both], b[both]), what


def ticks_of(run: Run) -> np.ndarray:
    """Ticks with any agent's telemetry."""
    return np.flatnonzero(np.isfinite(run.xi[:, :, 0]).any(axis=1))


def heard_any(run: Run) -> int:
    """How many ticks have any sample (leader, telemetry or plant): those run.mcap holds."""
    assert run.runtime is not None
    any_ = (np.isfinite(run.leader_p[:, 0]) | np.isfinite(run.xi[:, :, 0]).any(axis=1)
            | np.isfinite(run.runtime.plant_p[:, :, 0]).any(axis=1))
    return int(any_.sum())


# ------------------------------------------------------------------------------ bad --live ports
RUN = ["run", "section4", "--insecure"]
RECORD = ["record", "--mission", "section4", "--connect", "tcp/127.0.0.1:7447"]


@pytest.mark.parametrize(("command", "port"), [(RUN, "70000"), (["simulate", "section4"], "0"), (RUN, "busy"),
                                               (RECORD, "busy")])
def test_a_bad_live_port_is_refused_before_anything_starts(tmp_path: Path, command: list[str], port: str) -> None:
    out = tmp_path / "out"
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = str(busy.getsockname()[1])
        done = subprocess.run([sys.executable, "-m", "cli", *command, "--out", str(out), "--live",
                               taken if port == "busy" else port], cwd=REPO, capture_output=True, text=True,
                              timeout=120, stdin=subprocess.DEVNULL)
    assert done.returncode == 2, done.stderr
    if port == "busy":
        assert f"--live: port {taken}" in done.stderr and "in use" in done.stderr and "give a free port" in done.stderr
    else:
        assert f"--live: {port} is not a TCP port; give one in 1..65535" in done.stderr
    assert not out.exists()  # nothing started, nothing written


# ------------------------------------------------------------------------------- tether run --live
@pytest.mark.slow  # real processes
def test_run_live_serves_the_recorders_channels_while_the_run_goes_on(tmp_path: Path) -> None:
    port = free_port()
    duration = 20.0
    proc = tether_popen("run", "section4", "--clock", "realtime", "--duration", str(duration), "--insecure", "--quiet",
                  "--out", str(tmp_path / "run"), "--live", str(port))
    try:
        live = listen(port, {"/agent/2": 10, "/leader": 3, "/scene": 3, "/tf": 3}, timeout=90)
        channels, got = live.channels, live.got
        assert proc.poll() is None  # live: the run still goes on
        assert channels["/agent/2"]["schemaName"] == "tether.Agent" and channels["/agent/2"]["encoding"] == "json"
        assert channels["/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert channels["/scene"]["encoding"] == "protobuf"
        stamps = [s for s, _ in got["/agent/2"]]
        assert stamps == sorted(stamps)
        # a tick the recorder closed without agent 2's telemetry (late or lost under load) is sent
        # as "no sample"; the newest sample that came is the one to check
        heard = [(stamp, json.loads(data)) for stamp, data in got["/agent/2"]]
        real = [(stamp, s) for stamp, s in heard if s["safety_mode_name"] != "no sample"]
        assert real, [s["safety_mode_name"] for _, s in heard]
        stamp, sample = real[-1]
        # real time: log times are wall-clock, tick 0's Unix time + t, one epoch for every sample
        epochs = {s - round(x["t"] * 1e9) for s, x in real}
        assert len(epochs) == 1 and abs(epochs.pop() - time.time_ns()) < 600 * 10**9, epochs
        assert 0.0 <= sample["t"] < duration and sample["k"] == round(sample["t"] * 100)
        assert sample["safety_mode_name"] == "FLYING" and len(sample["xi"]) == 2
        assert all(k >= 1.0 for k in sample["kp"]) and sample["xi_norm"] >= 0.0  # sigma-mod gains stay >= 1
        assert set(sample) >= {"zeta", "kv", "u", "p", "links", "meas_age", "drops"}
        leader = json.loads(got["/leader"][-1][1])
        assert len(leader["p"]) == 2 and abs(leader["t"] - sample["t"]) < 1.0
    finally:
        os.killpg(proc.pid, signal.SIGINT)  # first Ctrl-C: land, then stop
        code, out = finish(proc)
    assert code in (130, 5), out[-3000:]
    assert (tmp_path / "run" / "run.mcap").exists()


# ------------------------------------------------------------------------------------ tether record
@pytest.mark.slow  # real processes
def test_record_started_before_the_swarm_records_it_until_sigint(tmp_path: Path) -> None:
    """``tether record`` waits for a router that is not up yet, records a real-time ``tether run
    --listen`` from its start, and writes both files when stopped mid-run: its samples are the run's."""
    port = tp.free_tcp_port()
    rec_dir, run_dir = tmp_path / "rec", tmp_path / "run"
    rec = tether_popen("record", "--mission", "section4", "--connect", f"tcp/127.0.0.1:{port}", "--out", str(rec_dir),
                 "--duration", "12")
    run = None
    try:
        time.sleep(1.0)  # a recorder that is up before the swarm: it keeps trying the router
        assert rec.poll() is None
        run = tether_popen("run", "section4", "--clock", "realtime", "--duration", "12", "--insecure", "--quiet",
                     "--listen", f"tcp/127.0.0.1:{port}", "--out", str(run_dir))
        logs = run_dir / "logs" / "recorder-0.log"
        # stop the recorder once the run has flown 5 s (the run's own recorder says when it started)
        wait_until(lambda: logs.exists() and "real time: tick 0" in logs.read_text(), 90, "the run's start", run)
        started = time.monotonic()
        wait_until(lambda: time.monotonic() - started > 6.0, 30, "5 s of flight", run)
        rec.send_signal(signal.SIGINT)
        code, out = finish(rec, 60)
        assert code == 0, out[-3000:]
        assert "stopped after" in out and "INCOMPLETE" in out, out[-2000:]
        code, run_out = finish(run)
        assert code in (0, 3, 5), run_out[-3000:]  # clean, a failsafe under load, or samples dropped
    finally:
        kill(rec)
        if run is not None:
            kill(run)
    ours, theirs = Run.load(rec_dir), Run.load(run_dir)
    assert ours.meta.complete is False and ours.meta.namespace == "section4"
    both = np.intersect1d(ticks_of(ours), ticks_of(theirs))
    assert len(both) > 100  # seconds of flight at 100 Hz in both files (under load either drops some)
    assert ticks_of(ours).max() < theirs.meta.steps - 100  # it stopped mid-run
    for f in ("p", "v", "xi", "zeta", "kp", "kv", "u", "leader_p"):
        same_samples(getattr(ours, f)[both], getattr(theirs, f)[both], f)
    msgs = read_mcap(rec_dir / "run.mcap")
    mine = set(np.flatnonzero(np.isfinite(ours.xi[:, 0, 0])))
    agent1 = [json.loads(d) for _, d in msgs["/agent/1"]]
    assert {m["k"] for m in agent1} >= mine  # every tick recorded is in the file, nothing after the stop
    assert len(agent1) == heard_any(ours)  # the ticks heard, nothing after the stop
    norm = np.linalg.norm(ours.xi, axis=2)
    for m in agent1:
        if m["k"] in mine:
            assert m["xi_norm"] == norm[m["k"], 0]
    # and its run.mcap matches the run's own, message for message, where both recorded the tick whole
    theirs_msgs = {json.loads(d)["k"]: json.loads(d) for _, d in read_mcap(run_dir / "run.mcap")["/agent/1"]}
    common = [m for m in agent1 if m["k"] in mine and m["k"] in theirs_msgs
              and np.isfinite(theirs.xi[m["k"], 0, 0])]
    assert len(common) > 100
    from_telemetry = ("t", "k", "xi_norm", "xi", "zeta", "kp", "kv", "u", "p", "v", "safety_mode", "links", "meas_age",
                      "drops")  # d and plant_mode come from the plant's sample, which either recorder may lack
    for m in common:
        assert {f: m[f] for f in from_telemetry} == {f: theirs_msgs[m["k"]][f] for f in from_telemetry}, m["k"]


@pytest.mark.slow  # real processes, mTLS
def test_record_joins_a_running_swarm_late_with_the_operator_identity(tmp_path: Path) -> None:
    """Under mTLS (the default), with ``DIR/tls/control-0.json5``: a recorder that attaches after the
    start message went out infers tick 0 from the samples and records the rest of the run, equal to
    the run's file."""
    port = tp.free_tcp_port()
    rec_dir, run_dir = tmp_path / "rec", tmp_path / "run"
    run = tether_popen("run", "section4", "--clock", "realtime", "--duration", "20", "--quiet",
                 "--listen", f"tls/127.0.0.1:{port}", "--out", str(run_dir))
    rec = None
    try:
        logs = run_dir / "logs" / "recorder-0.log"
        wait_until(lambda: logs.exists() and "real time: tick 0" in logs.read_text(), 90, "the run's start", run)
        rec = tether_popen("record", "--mission", "section4", "--zenoh-config", str(run_dir / "tls" / "control-0.json5"),
                     "--out", str(rec_dir), "--duration", "20")
        code, out = finish(rec, 90)
        assert code == 0, out[-3000:]
        assert "joined a run already under way" in out and "the run ended" in out, out[-2000:]
        code, run_out = finish(run)
        assert code in (0, 3, 5), run_out[-3000:]  # clean, a failsafe under load, or samples dropped
    finally:
        kill(run)
        if rec is not None:
            kill(rec)
    ours, theirs = Run.load(rec_dir), Run.load(run_dir)
    mine = ticks_of(ours)
    assert len(mine) > 100  # it missed the start message (said above), and heard the run from then on
    both = np.intersect1d(mine, ticks_of(theirs))
    for f in ("p", "xi", "kp", "kv", "u", "leader_p"):
        same_samples(getattr(ours, f)[both], getattr(theirs, f)[both], f)
    assert ours.safety.gate_counts is not None
    msgs = read_mcap(rec_dir / "run.mcap")
    assert len(msgs["/agent/3"]) == heard_any(ours)  # the ticks before it joined are not in the file


# ----------------------------------------------------------------------- a stopped run keeps both files
@pytest.mark.slow  # real processes
def test_a_lockstep_run_stopped_by_sigint_leaves_both_files(tmp_path: Path) -> None:
    """Ctrl-C on a long lockstep run: the recorder writes ``run.npz`` then ``run.mcap`` of what it
    recorded, and the launcher waits for it (``deploy.options.write_grace``) instead of killing it."""
    out = tmp_path / "run"
    out.mkdir()
    log = tmp_path / "launcher.log"
    proc = tether_popen("run", "section4", "--duration", "1000", "--insecure", "--out", str(out), log=log)
    try:
        wait_until(lambda: "processes are up" in log.read_text(), 120, "every process up", proc)
        started = time.monotonic()
        wait_until(lambda: time.monotonic() - started > 8.0, 30, "8 s of running", proc)
        os.killpg(proc.pid, signal.SIGINT)
        code, _ = finish(proc, 300)
    finally:
        kill(proc)
    text = log.read_text()
    assert code == 130, text[-3000:]
    assert "did not finish writing" not in text
    run = Run.load(out)
    assert run.meta.complete is False
    assert len(heard(run)) > 100
    msgs = read_mcap(out / "run.mcap")
    assert len(msgs["/agent/1"]) == heard_any(run) == len(msgs["/leader"])
    assert msgs["/leader"][-1][0] == viz.stamp(float(run.t[heard_any(run) - 1]))
    # the same file as converted at once from the ticks heard
    prefix = dataclasses.replace(run, t=np.where(np.arange(len(run.t)) < heard_any(run), run.t, np.nan))
    assert file_content(out / "run.mcap") == file_content(viz.write_mcap(prefix, None, tmp_path / "converted.mcap"))


# ------------------------------------------------------------------------------------- tether top
def telemetry(sender: int, k: int, mode: int = 0, xi: tuple[float, float] = (0.01, 0.0), **kw: object) -> bytes:
    from tether import wire

    links = [wire.LinkStats(src=0, received=k, used=k, stale=0, age=0.01, silent=False, delivery=1.0,
                            age_p50=0.01, age_p99=0.01)]
    msg = wire.Telemetry(sender=sender, seq=k, k=k, t=k * 0.01, meas_t=k * 0.01, p=[0.0, 0.0], vel=[0.0, 0.0],
                         a=[0.0, 0.0], u=[0.3, 0.4], xi=list(xi), zeta=[0.0, 0.0], kp=[1.0, 1.5], kv=[1.0, 1.0],
                         links=links, drops={}, mode=mode, **kw)  # type: ignore[arg-type]
    return wire.encode(msg)


def test_top_board_shows_a_plant_s_newest_event_when_it_came_last() -> None:
    """A plant's watchdog event (on ``plant/<i>/state``) shows in vehicle i's last-event cell when it
    is newer than the agent's; a plant sample under another plant's key is dropped as forged."""
    from recorder.top import Board
    from tether import wire

    b = Board("s4")
    b.telemetry("tether/s4/agent/2/telemetry", telemetry(2, 10), now=0.0)

    def state(sender: int, k: int, events: list[wire.SafetyEvent]) -> bytes:
        return wire.encode(wire.PlantState(sender=sender, seq=k, k=k, t=k * 0.01, p=[0.0, 0.0], vel=[0.0, 0.0],
                                           a=[0.0, 0.0], d=[0.0, 0.0], mode=wire.FLYING, events=events))

    rejected = wire.SafetyEvent(k=12, t=0.12, vehicle=2, src=wire.FLYING, dst=wire.FLYING,
                                reason="command rejected: stamp ahead of the tick")
    b.plant("tether/s4/plant/2/state", state(2, 12, []))  # no event: nothing to show
    assert b.cells(b.rows[2], now=0.1)[0][9] == "-"
    b.plant("tether/s4/plant/3/state", state(2, 12, [rejected]))  # plant 2's sample on plant 3's key
    assert b.drops == {"sender": 1} and b.rows[2].last_plant_event is None
    b.plant("tether/s4/plant/2/state", state(2, 12, [rejected]))
    assert b.cells(b.rows[2], now=0.1)[0][9] == "plant t=0.1s FLYING command rejected: stamp ahead of the tick"
    held = wire.SafetyEvent(k=20, t=0.2, vehicle=2, src=wire.FLYING, dst=wire.HOLD, reason="leader silent 0.5 s")
    b.telemetry("tether/s4/agent/2/telemetry", telemetry(2, 20, mode=1, events=[held]), now=0.2)
    assert b.cells(b.rows[2], now=0.2)[0][9] == "t=0.2s FLYING->HOLD leader silent 0.5 s"  # the agent's is newer


def test_top_board_keeps_each_agents_newest_telemetry_and_drops_the_rest() -> None:
    from recorder.top import Board
    from tether import wire

    b = Board("s4")
    key = "tether/s4/agent/{}/telemetry".format
    b.telemetry(key(1), telemetry(1, 10), now=0.0)
    b.telemetry(key(1), telemetry(1, 9), now=0.0)  # older: dropped
    b.telemetry(key(2), telemetry(3, 5), now=0.0)  # another agent's on agent 2's key: forged
    b.telemetry(key(2), b"\x93junk", now=0.0)
    b.telemetry("tether/s4/agent/x/telemetry", telemetry(1, 11), now=0.0)
    b.telemetry(key(2), wire.encode(wire.Ack(sender=2, seq=0, k=0, t=0.0, role="agent")), now=0.0)
    assert b.drops == {"stale": 1, "sender": 1, "malformed": 1, "key": 1, "type": 1}
    assert sorted(b.rows) == [1] and b.rows[1].msg is not None and b.rows[1].msg.k == 10
    cells, styles = b.cells(b.rows[1], now=0.1)
    assert cells[:6] == ["1", "FLYING", "-", "0.010", "1.00/1.50  1.00/1.00", "0.50"]
    assert styles[1] == "green" and styles[2] == "dim" and styles[3] == ""
    # trouble: a mode other than FLYING, a big |xi|, an event; a gone token; silence
    ev = wire.SafetyEvent(k=20, t=0.2, vehicle=1, src=0, dst=1, reason="leader silent 0.52 s")
    b.telemetry(key(1), telemetry(1, 20, mode=1, xi=(0.6, 0.8), events=[ev]), now=1.0)
    cells, styles = b.cells(b.rows[1], now=1.1)
    assert cells[1] == "HOLD" and styles[1] == "yellow" and styles[3] == "red"
    assert cells[9] == "t=0.2s FLYING->HOLD leader silent 0.52 s"
    # the clock-offset estimate: the most offset link, flagged as its agent flagged it
    assert cells[8] == "-"
    clock = [wire.ClockLink(role="plant", src=1, offset=0.002), wire.ClockLink(role="agent", src=2, offset=-0.004),
             wire.ClockLink(role="leader", src=5, offset=float("nan"))]
    b.telemetry(key(1), telemetry(1, 21, mode=1, clock=clock), now=1.0)
    cells, styles = b.cells(b.rows[1], now=1.1)
    assert (cells[8], styles[8]) == ("agent/2 -4.0 ms", "")
    clock.append(wire.ClockLink(role="agent", src=4, offset=0.0312, warn=True))
    b.telemetry(key(1), telemetry(1, 22, mode=1, clock=clock), now=1.0)
    cells, styles = b.cells(b.rows[1], now=1.1)
    assert (cells[8], styles[8]) == ("agent/4 +31.2 ms !", "bold red")
    assert b.cells(b.rows[1], now=3.0)[0][1].startswith("STALE")
    b.token("@tether/s4/agent/1", False)
    b.token("@tether/s4/agent/4", True)
    assert b.cells(b.rows[1], now=1.1)[0][1] == "GONE (HOLD)"
    assert b.cells(b.rows[4], now=1.1)[0][1] == "no telemetry"


@pytest.mark.slow  # real processes, a real terminal
def test_top_under_tmux_shows_every_vehicle_and_the_one_killed(tmp_path: Path) -> None:
    import shutil

    if shutil.which("tmux") is None:
        pytest.skip("tmux is not installed (apt-get install tmux): tether top is tested in a real terminal")
    port = tp.free_tcp_port()
    run = tether_popen("run", "section4", "--clock", "realtime", "--duration", "30", "--insecure", "--quiet",
                 "--listen", f"tcp/127.0.0.1:{port}", "--out", str(tmp_path / "run"), "--fault", "kill:agent/2@12",
                 "--fault", "skew:agent/3=+0.015", "--fault", "skew:plant/3=+0.015")
    session = f"tether-top-{os.getpid()}"
    rc = tmp_path / "rc"
    # without the COLUMNS/LINES a pytest run exports (80), rich reads the window's own size
    command = (f"cd {REPO} && env -u COLUMNS -u LINES PYTHONPATH={REPO} {sys.executable} -m cli top "
               f"--connect tcp/127.0.0.1:{port} --ns section4; echo $? > {rc}")
    tmux = ["tmux", "-L", session, "-f", "/dev/null"]  # a server of its own: its size is the one asked for
    subprocess.run([*tmux, "new-session", "-d", "-s", session, "-x", "200", "-y", "30", command], check=True)

    def pane() -> str:
        done = subprocess.run([*tmux, "capture-pane", "-p", "-t", session], capture_output=True, text=True)
        return done.stdout

    def clock(vehicle: str) -> str:
        for line in pane().splitlines():
            cells = [c.strip() for c in line.split("│")]
            if len(cells) > 10 and cells[1] == vehicle:
                return cells[9]
        return ""

    def rows(mode: str) -> set[str]:
        out = set()
        for line in pane().splitlines():
            cells = [c.strip() for c in line.split("│")]
            if len(cells) > 3 and cells[1] in "1234" and cells[1] and cells[2].startswith(mode):
                out.add(cells[1])
        return out

    try:
        wait_until(lambda: rows("FLYING") == {"1", "2", "3", "4"}, 90, "a FLYING row for every vehicle", run)
        assert "tether top: namespace 'section4'" in pane()
        # vehicle 3's host 15 ms ahead (within the gate's 2 periods, so every vehicle flies): agent 4
        # hears agent 3's samples ~15 ms before their time (less the link's delay), agent 3 hears agent
        # 2's ~15 ms late (plus the delay); both are outside -5 .. +10 ms, flagged, and top shows it
        try:
            wait_until(lambda: re.fullmatch(r"agent/3 -1\d\.\d ms !", clock("4")) is not None, 30,
                     "vehicle 4's clock cell to show agent 3 ~15 ms ahead, flagged", run)
            wait_until(lambda: re.fullmatch(r"agent/2 \+[1-9]\d\.\d ms !", clock("3")) is not None, 30,
                     "vehicle 3's clock cell to show agent 2's samples ~15 ms late, flagged", run)
        except pytest.fail.Exception as exc:
            raise AssertionError(f"{exc}:\n{pane()}") from None
        print(f"\ntether top clock cells: 3: {clock('3')}, 4: {clock('4')}, 1: {clock('1')}")
        wait_until(lambda: "2" in rows("GONE") | rows("STALE"), 60, "vehicle 2 shown gone once killed", run)
        subprocess.run([*tmux, "send-keys", "-t", session, "q"], check=True)
        wait_until(lambda: rc.exists() and rc.read_text().strip() != "", 30, "tether top to quit on q")
        assert rc.read_text().strip() == "0"
    finally:
        subprocess.run([*tmux, "kill-server"], capture_output=True)
        os.killpg(run.pid, signal.SIGTERM)
        finish(run)
