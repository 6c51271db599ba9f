"""The Foxglove view of a run: ``run.mcap`` read back with the ``mcap`` package (a reader that is
not the writer), the live view read with a plain WebSocket client speaking the Foxglove WebSocket
protocol, and the progress display's rate and ETA."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")

from recorder import viz  # noqa: E402
from sim import lockstep  # noqa: E402
from tether import catalog  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether.progress import Progress  # noqa: E402
from tether.runfile import NO_SAMPLE, Run  # noqa: E402

from tests.foxglove_live import listen  # noqa: E402
from tests.support import REPO, free_port, tether  # noqa: E402

FOXGLOVE_TYPES = {"/scene": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransforms", "/log": "foxglove.Log",
                  "/safety": "foxglove.Log"}


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


def file_content(path: Path) -> tuple[list[tuple[str, int, bytes]], list[tuple[str, dict[str, str]]],
                                      list[tuple[str, str, bytes]]]:
    """Every message in file order (topic, log time, data), the metadata records and the attachments."""
    with open(path, "rb") as fh:
        reader = mcap_reader.make_reader(fh)
        msgs = [(ch.topic, m.log_time, bytes(m.data)) for _s, ch, m in reader.iter_messages(log_time_order=False)]
        meta = [(x.name, dict(x.metadata)) for x in reader.iter_metadata()]
        atts = [(a.name, a.media_type, bytes(a.data)) for a in reader.iter_attachments()]
    return msgs, meta, atts


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
    assert len(msgs.get("/safety", [])) == len(run.safety.events) + len(run.safety.plant_events)
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
    # the recorder's file is the one `tether mcap` makes of its run file, message for message
    assert file_content(out / "run.mcap") == file_content(viz.write_mcap(run, None, tmp_path / "converted.mcap"))


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


def test_a_record_cut_short_says_so_and_shows_no_stale_mode(tmp_path: Path) -> None:
    """A run whose record stops at tick K (a recorder stopped, frozen or killed): the file holds ticks
    0..K, its last scene (tick K + 1) draws every vehicle as "no sample" rather than the last mode
    heard, and ``/log`` says what is missing; the plants' events are on ``/safety`` by their name."""
    from tether import wire

    m = ms.load(catalog.resolve("section4"))
    run = lockstep.simulate(m, duration=0.3)
    K = 12
    run.leader_p[K + 1:] = np.nan
    run.safety.safety_mode[K + 1:] = NO_SAMPLE
    run.safety.plant_mode[K + 1:] = NO_SAMPLE
    run.safety.plant_events = [wire.SafetyEvent(k=5, t=5 * m.dt, vehicle=3, src=wire.FLYING, dst=wire.FLYING,
                                                reason="command rejected: stamp ahead of the tick")]
    path = viz.write_mcap(run, m, tmp_path / "run.mcap", scene_rate=0)
    _, msgs = read_mcap(path)
    assert len(msgs["/agent/1"]) == len(msgs["/leader"]) == K + 1
    assert len(msgs["/scene"]) == K + 2 and msgs["/scene"][-1][0] == viz.stamp((K + 1) * m.dt)
    last_scene = msgs["/scene"][-1][1]
    assert b"FLYING" not in last_scene and last_scene.count(b"no sample") == len(run.agent_ids)
    log = b" ".join(data for _, data in msgs["/log"])
    assert b"missing: telemetry of agent 1: " in log and b"no sample after t = 0.12 s" in log
    safety = msgs["/safety"]
    assert len(safety) == 1 and b"plant 3: FLYING: command rejected" in safety[0][1]


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
    for want in ('"ThreeDee!', '"Plot!', '"Log!', "/agent/1.xi_norm", "/agent/4.kv[1]", '"/safety"'):
        assert want in panels
