"""The Foxglove view of a run: ``run.mcap`` read back with the ``mcap`` package (a reader that is
not the writer), the live view read with a plain WebSocket client speaking the Foxglove WebSocket
protocol, and the progress display's rate and ETA."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")

from recorder import viz  # noqa: E402
from sim import lockstep  # noqa: E402
from tether import catalog  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether.progress import Progress  # noqa: E402
from tether.runfile import Run  # noqa: E402

from tests.foxglove_live import free_port, listen  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
FOXGLOVE_TYPES = {"/scene": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms", "/log": "foxglove.Log",
                  "/safety": "foxglove.Log"}


def tether(*args: str, timeout: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, stdin=subprocess.DEVNULL)


def read_mcap(path: Path) -> tuple[dict[str, tuple[str, str, str]], dict[str, list[tuple[int, bytes]]]]:
    """topic -> (schema name, schema encoding, message encoding); topic -> [(log time, data)] in file order."""
    with open(path, "rb") as fh:
        reader = mcap_reader.make_reader(fh)
        summary = reader.get_summary()
        channels = {ch.topic: (summary.schemas[ch.schema_id].name, summary.schemas[ch.schema_id].encoding,
                               ch.message_encoding) for ch in summary.channels.values()}
        messages: dict[str, list[tuple[int, bytes]]] = defaultdict(list)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            messages[channel.topic].append((message.log_time, message.data))
    return channels, dict(messages)


def check_file(path: Path, run: Run, scene_every: int) -> dict[str, list[tuple[int, bytes]]]:
    """Every channel with its schema, the expected counts, times in order, and values equal to the run file's."""
    channels, msgs = read_mcap(path)
    T = len(run.t)
    agents = [f"/agent/{a}" for a in run.agent_ids]
    for topic in agents + ["/leader"]:
        assert channels[topic] == (("tether.Agent" if topic != "/leader" else "tether.Leader"), "jsonschema", "json")
        assert len(msgs[topic]) == T, topic
    for topic, name in FOXGLOVE_TYPES.items():
        if topic in msgs or topic in ("/scene", "/tf", "/log"):
            assert channels[topic] == (name, "protobuf", "protobuf"), topic
    scenes = len(range(0, T, scene_every)) + (0 if (T - 1) % scene_every == 0 else 1)
    assert len(msgs["/scene"]) == len(msgs["/tf"]) == scenes
    assert len(msgs["/log"]) >= 2  # what ran, and its end
    assert len(msgs.get("/safety", [])) == len(run.safety.events)
    for topic, rows in msgs.items():
        times = [t for t, _ in rows]
        assert times == sorted(times), f"{topic}: log times out of order"
    # the epoch: mission time t is logged at EPOCH_NS + t
    assert msgs["/leader"][0][0] == viz.EPOCH_NS
    assert msgs["/leader"][-1][0] == viz.stamp(float(run.t[-1]))
    # values: a few ticks, every agent, equal to the run file (JSON floats round-trip exactly)
    norm = np.linalg.norm(run.xi, axis=2)
    for k in (0, 1, T // 2, T - 1):
        for i, topic in enumerate(agents):
            t_ns, data = msgs[topic][k]
            m = json.loads(data)
            assert t_ns == viz.stamp(float(run.t[k])) and m["k"] == k and m["t"] == run.t[k]
            for f in ("xi", "zeta", "kp", "kv", "u", "p", "v"):
                assert m[f] == getattr(run, f)[k, i].tolist(), (topic, k, f)
            assert m["xi_norm"] == norm[k, i]
            assert m["safety_mode"] == run.safety.safety_mode[k, i]
            assert m["safety_mode_name"] == run.meta.modes[run.safety.safety_mode[k, i]]
        lead = json.loads(msgs["/leader"][k][1])
        assert lead["p"] == run.leader_p[k].tolist() and lead["v"] == run.leader_v[k].tolist()
    return msgs


def test_simulate_writes_run_mcap_beside_run_npz(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    done = tether("simulate", "section4", "--out", str(out), "--duration", "2", "--no-figures")
    assert done.returncode == 0, done.stderr
    run = Run.load(out)
    msgs = check_file(out / "run.mcap", run, viz.scene_every(run.meta.rate, viz.SCENE_RATE))
    assert "links" not in json.loads(msgs["/agent/1"][0][1])  # the reference simulator has no links


@pytest.mark.slow  # real processes
def test_lockstep_tether_run_writes_run_mcap(tmp_path: Path) -> None:
    out = tmp_path / "run"
    done = tether("run", "section4", "--out", str(out), "--duration", "1", "--quiet",
                  "--ns", f"viz-{os.getpid()}", timeout=400.0)
    assert done.returncode == 0, done.stdout + done.stderr
    run = Run.load(out)
    assert run.meta.source == "runtime-lockstep"
    msgs = check_file(out / "run.mcap", run, viz.scene_every(run.meta.rate, viz.SCENE_RATE))
    k = len(run.t) - 1
    m = json.loads(msgs["/agent/1"][k][1])
    lk = run.links
    used = [n for n, s in enumerate(lk.src[0]) if s != 0]
    assert [x["src"] for x in m["links"]] == [int(lk.src[0, n]) for n in used]
    assert [x["delivery"] for x in m["links"]] == [float(lk.delivery[k, 0, n]) for n in used]
    assert [x["age"] for x in m["links"]] == [float(lk.age[k, 0, n]) for n in used]
    assert m["meas_age"] == run.runtime.meas_age[k, 0]
    assert m["plant_mode"] == run.safety.plant_mode[k, 0]
    # lockstep: converted at once after the last tick (during the run it would take the run's CPU)
    assert "run.mcap: 0 ticks written during the run" in (out / "logs" / "recorder-0.log").read_text()


@pytest.mark.slow  # real processes, real time
def test_a_real_time_run_writes_run_mcap_as_it_goes_and_the_same_file_as_converted_at_the_end(
        tmp_path: Path) -> None:
    out = tmp_path / "run"
    done = tether("run", "section4", "--clock", "realtime", "--out", str(out), "--duration", "3", "--quiet",
                  "--insecure", "--ns", f"vizrt-{os.getpid()}", timeout=400.0)
    assert done.returncode in (0, 5), done.stdout + done.stderr  # 5: a sample lost under load (said, recorded)
    log = (out / "logs" / "recorder-0.log").read_text()
    early = re.search(r"run\.mcap: ([0-9]+) ticks written during the run", log)
    assert early is not None and int(early[1]) > 100, log[-2000:]
    run = Run.load(out)
    assert run.runtime is not None
    heard = (np.isfinite(run.leader_p[:, 0]) | np.isfinite(run.xi[:, :, 0]).any(axis=1)
             | np.isfinite(run.runtime.plant_p[:, :, 0]).any(axis=1))
    import dataclasses

    converted = viz.write_mcap(dataclasses.replace(run, t=np.where(heard, run.t, np.nan)), None,
                               tmp_path / "converted.mcap")
    assert file_content(out / "run.mcap") == file_content(converted)


def test_payload_fence_and_events_in_the_file(tmp_path: Path) -> None:
    """exp2 (payload and cables) in the in-process engine; a geofence and safety events added by hand."""
    m = ms.load(catalog.resolve("exp2"))
    run = lockstep.simulate(m, duration=0.5)
    from tether.wire import SafetyEvent

    run.safety.events = [SafetyEvent(k=10, t=10 * m.dt, vehicle=int(run.agent_ids[1]), src=0, dst=1, reason="test")]
    import msgspec

    fence = ms.Geofence(min=[-50.0, -50.0, 0.0], max=[50.0, 50.0, 20.0])
    fenced = msgspec.structs.replace(m, safety=msgspec.structs.replace(m.safety, geofence=fence))
    path = viz.write_mcap(run, fenced, tmp_path / "run.mcap", scene_rate=0)
    channels, msgs = read_mcap(path)
    T = len(run.t)
    assert channels["/payload"] == ("tether.Payload", "jsonschema", "json")
    assert len(msgs["/payload"]) == len(msgs["/scene"]) == T  # scene_rate 0: every tick
    for k in (0, T - 1):
        p = json.loads(msgs["/payload"][k][1])
        assert p["p"] == run.plant.payload_p[k].tolist() and p["tension"] == run.plant.tension[k].tolist()
    assert channels["/safety"] == ("foxglove.Log", "protobuf", "protobuf")
    assert len(msgs["/safety"]) == 1 and msgs["/safety"][0][0] == viz.stamp(10 * m.dt)
    assert b"FLYING -> HOLD: test" in msgs["/safety"][0][1]
    assert b"geofence" in msgs["/scene"][0][1] and b"payload" in msgs["/scene"][0][1]
    assert b"agent_1" in msgs["/tf"][0][1]


def test_tether_mcap_converts_an_existing_run(tmp_path: Path) -> None:
    m = ms.load(catalog.resolve("section4"))
    run = lockstep.simulate(m, duration=0.3)
    run.meta.mission_text = ms.dumps(m)
    run.save(tmp_path / "run.npz")
    done = tether("mcap", str(tmp_path), "--scene-rate", "10")
    assert done.returncode == 0, done.stderr
    check_file(tmp_path / "run.mcap", Run.load(tmp_path), viz.scene_every(m.rate, 10))


# ------------------------------------------------------------------------------------------- live
@pytest.mark.slow  # real processes
def test_simulate_live_serves_the_channels_over_the_foxglove_websocket_protocol(tmp_path: Path) -> None:
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "cli", "simulate", "section4", "--out", str(tmp_path / "live"),
                             "--duration", "30", "--live", str(port), "--speed", "1", "--no-figures", "--no-mcap"],
                            cwd=REPO, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        wanted = {"/agent/1": 2, "/leader": 2, "/scene": 2, "/tf": 2, "/log": 0}
        live = listen(port, wanted, timeout=60, alive=lambda: proc.poll() is None)
        channels, got = live.channels, live.got
        assert channels["/agent/1"]["schemaName"] == "tether.Agent" and channels["/agent/1"]["encoding"] == "json"
        assert channels["/scene"]["schemaName"] == "foxglove.SceneUpdate"
        assert channels["/scene"]["encoding"] == "protobuf"
        sample = json.loads(got["/agent/1"][-1][1])
        assert set(sample) >= {"t", "k", "xi_norm", "xi", "zeta", "kp", "kv", "u", "safety_mode"}
        assert got["/agent/1"][-1][0] == viz.stamp(sample["t"])
        assert sample["t"] < 30.0  # live: while the run goes on
        assert live.clock and live.clock[-1] >= viz.EPOCH_NS
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate(timeout=30)


# ------------------------------------------------------------------------------------------ progress
class FakeStream(io.StringIO):
    def isatty(self) -> bool:
        return False


def test_progress_lines_show_rate_and_eta() -> None:
    now = [100.0]
    out = FakeStream()
    prog = Progress(stream=out, clock=lambda: now[0])
    for k in range(0, 1001, 50):
        prog(k, 1000, "section4")
        now[0] += 0.5  # 50 ticks per half second: 100 ticks/s
    lines = out.getvalue().splitlines()
    assert len(lines) == 11  # one per 10 %
    assert lines[0] == "section4 0% (0/1000)"
    assert lines[5] == "section4 50% (500/1000) 100/s ETA 5s"
    assert lines[-1] == "section4 100% (1000/1000) 100/s elapsed 10s"


def test_the_shipped_layout_is_the_generated_one() -> None:
    """``docs/foxglove/tether.json`` is ``recorder.viz.layout()`` (Section 4's agents); regenerate it
    with ``python -c "from recorder import viz; print(viz.layout())"`` after changing either."""
    shipped = json.loads((REPO / "docs" / "foxglove" / "tether.json").read_text())
    assert shipped == json.loads(viz.layout())
    panels = json.dumps(shipped)
    for want in ('"panelType": "ThreeDee"', '"panelType": "Plot"', '"panelType": "Log"', "/agent/1.xi_norm",
                 "/agent/4.kv[1]", '"/safety"'):
        assert want in panels


# ----------------------------------------------------------------- run.mcap written as the run is filled
def file_content(path: Path) -> tuple[list[tuple[str, int, bytes]], list[tuple[str, dict[str, str]]],
                                      list[tuple[str, str, bytes]]]:
    """Every message in file order (topic, log time, data), the metadata records and the attachments."""
    with open(path, "rb") as fh:
        reader = mcap_reader.make_reader(fh)
        msgs = [(ch.topic, m.log_time, bytes(m.data)) for _s, ch, m in reader.iter_messages(log_time_order=False)]
        meta = [(x.name, dict(x.metadata)) for x in reader.iter_metadata()]
        atts = [(a.name, a.media_type, bytes(a.data)) for a in reader.iter_attachments()]
    return msgs, meta, atts


def _recording(out: Path) -> Any:
    """A recorder's :class:`recorder.node.Recording` of section4 in lockstep, writing into ``out``."""
    from types import SimpleNamespace

    from recorder.node import Recording
    from tether import wire

    m = ms.load(catalog.builtin_path("section4"))
    # the recorder's bookkeeping asks its node for these alone
    node = SimpleNamespace(mission=m, clock=SimpleNamespace(lockstep=True), keys=wire.Keys("test"),
                           args=SimpleNamespace(mission_path=catalog.builtin_path("section4")), arrived_ago=lambda: 0.0)
    return Recording(node, out)  # type: ignore[arg-type]  # the node's fields it reads


def _leader(k: int) -> object:
    from tether import wire

    return wire.State(sender=5, seq=k, k=k, t=k / 100, p=[0.1 * k, 0.0], vel=[1.0, 0.0], a=[0.0, 0.0])


def _converted(rec: Any, out: Path) -> Path:
    """What ``write_mcap`` makes at once of the run the recorder saved, the ticks never heard left out."""
    import dataclasses

    run = Run.load(out / "run.npz")
    heard = dataclasses.replace(run, t=np.where(rec.count > 0, run.t, np.nan))
    return viz.write_mcap(heard, None, out / "converted.mcap")


def _wait(cond: Any, timeout: float, what: str) -> None:
    import time

    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def _feed(rec: Any, k0: int, n: int, agents: tuple[int, ...], rng: np.random.Generator) -> None:
    from tests.test_colocate import _busy_record

    for aid in agents:
        r = _busy_record(k0, n, aid, rng)
        rec.plants(r.plant)
        rec.telemetries(r.telemetry)


def test_the_recorder_has_run_mcap_written_as_ticks_complete_and_it_equals_the_file_converted_at_the_end(
        tmp_path: Path) -> None:
    """``Recording.share`` moves the run into memory shared with a helper process at the lowest CPU
    priority (``recorder/follow.py``), the values kept; ``Recording.stream`` tells it each tick once
    every sample of it is in, in order: a tick still missing a sample stops it (later ticks wait,
    complete or not), and it goes on once that tick is whole. ``save`` hands over the ticks heard
    after it (a stopped run's, some incomplete; ticks of which nothing was heard are left out) and
    the helper ends the file. Message for message, in the same order, with the safety events before
    their tick (sorted by tick, vehicle and time, whichever agent's record brought them first),
    metadata and mission text: the file ``write_mcap`` converts at once from ``run.npz``."""
    import os

    rec = _recording(tmp_path)
    rng = np.random.default_rng(11)
    for k in range(8):  # samples recorded before the helper starts are kept
        rec.leader(_leader(k))
    rec.share()
    follower = rec.follower
    assert follower is not None and rec.run is follower.run and rec.count is follower.count
    assert rec.rt is rec.run.runtime and rec.lk is rec.run.links
    assert np.isfinite(rec.run.leader_p[:8]).all() and rec.count[:8].tolist() == [1] * 8
    _wait(lambda: os.sched_getscheduler(follower.proc.pid) == os.SCHED_IDLE, 30, "the helper at SCHED_IDLE")
    for k in range(8, 96):
        rec.leader(_leader(k))
    rec.leader(_leader(120))  # a tick heard by its leader's sample alone, after ticks never heard
    for k0 in range(0, 64, 16):
        _feed(rec, k0, 16, (1, 2, 4) if k0 == 16 else (1, 2, 3, 4), rng)  # agent 3's ticks 16..31 come last
        rec.stream()
    assert rec.whole == 16 and follower.told == 15
    _wait(lambda: follower.ticks_written == 16, 60, "16 ticks written by the helper")
    assert (tmp_path / "run.mcap.part").exists() and not (tmp_path / "run.mcap").exists()
    _feed(rec, 16, 16, (3,), rng)
    rec.stream()
    assert rec.whole == 64
    _feed(rec, 64, 16, (1, 2), rng)  # ticks 64..79 half heard: the run is stopped here
    rec.stream()
    assert rec.whole == 64
    rec.save(complete=False, drops={})
    assert rec.follower is None and follower.proc.returncode == 0 and not (tmp_path / "run.mcap.part").exists()
    got = file_content(tmp_path / "run.mcap")
    assert got == file_content(_converted(rec, tmp_path))
    msgs = got[0]
    ticks = [json.loads(d)["k"] for topic, _t, d in msgs if topic == "/agent/1"]
    assert ticks == [*range(96), 120]
    safety = [t for topic, t, _d in msgs if topic == "/safety"]
    assert len(safety) == 4 * len(range(0, 64, 7)) + 2 * len(range(70, 80, 7)) and safety == sorted(safety)


def test_when_the_helper_writing_run_mcap_dies_the_recorder_writes_the_file_at_the_end(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The helper is killed mid-run (the kernel's OOM killer, an operator): the recorder says so,
    records on, and converts the whole run itself when it saves it; the helper's unfinished file
    is removed. The same file as ever."""
    import signal

    rec = _recording(tmp_path)
    rng = np.random.default_rng(12)
    rec.share()
    follower = rec.follower
    assert follower is not None
    for k in range(64):
        rec.leader(_leader(k))
    _feed(rec, 0, 32, (1, 2, 3, 4), rng)
    rec.stream()
    _wait(lambda: follower.ticks_written == 32, 60, "32 ticks written by the helper")
    follower.proc.send_signal(signal.SIGKILL)
    follower.proc.wait()
    _feed(rec, 32, 32, (1, 2, 3, 4), rng)
    with caplog.at_level("WARNING", logger="tether"):
        rec.stream()
        assert follower.failed and "the recorder writes it at the end" in caplog.text
        rec.save(complete=True, drops={})
    assert not (tmp_path / "run.mcap.part").exists()
    got = file_content(tmp_path / "run.mcap")
    assert got == file_content(_converted(rec, tmp_path))
    assert sum(1 for topic, _t, _d in got[0] if topic == "/agent/4") == 64


def test_the_helper_writing_run_mcap_removes_its_file_when_its_recorder_is_gone(tmp_path: Path) -> None:
    """Its input ends without the word to close (the recorder was killed): the helper removes its
    unfinished file and exits 3, whatever it had written."""
    rec = _recording(tmp_path)
    rec.share()
    follower = rec.follower
    assert follower is not None
    for k in range(16):
        rec.leader(_leader(k))
    _feed(rec, 0, 16, (1, 2, 3, 4), np.random.default_rng(13))
    rec.stream()
    _wait(lambda: follower.ticks_written == 16, 60, "16 ticks written by the helper")
    assert (tmp_path / "run.mcap.part").exists()
    assert follower.proc.stdin is not None
    follower.proc.stdin.close()
    assert follower.proc.wait(timeout=60) == 3
    assert not (tmp_path / "run.mcap.part").exists() and not (tmp_path / "run.mcap").exists()


@pytest.mark.slow  # waits out recorder.follow.STALL
def test_a_helper_that_stops_writing_run_mcap_is_given_up_and_the_recorder_writes_the_file(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The helper is frozen (as if starved at its lowest priority by other work on every core): once
    the run is saved, the recorder waits for it only while it writes ticks, then stops it, removes its
    unfinished file and converts the run itself."""
    import signal
    import time

    from recorder import follow

    rec = _recording(tmp_path)
    rec.share()
    follower = rec.follower
    assert follower is not None
    for k in range(48):
        rec.leader(_leader(k))
    _feed(rec, 0, 16, (1, 2, 3, 4), np.random.default_rng(14))
    rec.stream()
    _wait(lambda: follower.ticks_written == 16, 60, "16 ticks written by the helper")
    follower.proc.send_signal(signal.SIGSTOP)
    _feed(rec, 16, 32, (1, 2, 3, 4), np.random.default_rng(15))
    rec.stream()
    t0 = time.monotonic()
    with caplog.at_level("WARNING", logger="tether"):
        rec.save(complete=True, drops={})
    assert follow.STALL <= time.monotonic() - t0 < follow.STALL + 30
    assert "no tick written for" in caplog.text and follower.proc.returncode == -signal.SIGKILL
    assert not (tmp_path / "run.mcap.part").exists()
    assert file_content(tmp_path / "run.mcap") == file_content(_converted(rec, tmp_path))
