"""``run.mcap`` is the whole run: every array of ``run.npz`` read back from the MCAP file with the
``mcap`` reader (JSON channels) equals the run file's, every event is on a structured topic, a
real-time run's log times are wall-clock, and a vehicle whose agent was killed stays in the scene
where its plant is (``mcap-protobuf-support`` decodes the Foxglove messages)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")
pb_decoder = pytest.importorskip("mcap_protobuf.decoder")

from recorder import viz  # noqa: E402
from recorder.export import EPOCH_NS  # noqa: E402
from sim import lockstep  # noqa: E402
from tether import catalog  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether.runfile import EVENT_FIELDS, EVENT_PREFIXES, Run  # noqa: E402
from tether.wire import SafetyEvent  # noqa: E402

from tests.support import REPO  # noqa: E402


def messages(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """topic -> [(log time, decoded)] in log-time order: JSON channels as Python objects, protobuf
    channels as protobuf messages."""
    out: dict[str, list[tuple[int, Any]]] = defaultdict(list)
    with open(path, "rb") as fh:
        reader = mcap_reader.make_reader(fh, decoder_factories=[pb_decoder.DecoderFactory()])
        for _s, ch, msg in reader.iter_messages(log_time_order=True):
            if ch.message_encoding == "json":
                out[ch.topic].append((msg.log_time, json.loads(msg.data)))
        fh.seek(0)
        reader = mcap_reader.make_reader(fh, decoder_factories=[pb_decoder.DecoderFactory()])
        for _s, ch, msg, dec in reader.iter_decoded_messages(topics=["/tf", "/scene"], log_time_order=True):
            out[ch.topic].append((msg.log_time, dec))
    return dict(out)


def metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as fh:
        return next(dict(m.metadata) for m in mcap_reader.make_reader(fh).iter_metadata() if m.name == "tether")


def nan(value: Any) -> Any:
    """JSON's null (a NaN of the run file) back to NaN, at any depth."""
    if isinstance(value, list):
        return [nan(v) for v in value]
    return np.nan if value is None else value


def rebuild(path: Path, run: Run) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every array of the run file as read from the MCAP file alone (by topic and field names,
    ``docs/foxglove.md``), and the ticks the file holds. Ticks it lacks stay NaN."""
    msgs = messages(path)
    ref = run.arrays()  # only for shapes and dtypes
    got = {name: np.full(a.shape, np.nan if a.dtype.kind == "f" else 0, dtype=a.dtype) for name, a in ref.items()}
    ids = [int(a) for a in run.agent_ids]
    static = msgs["/run/static"]
    assert len(static) == 1
    for name, value in static[0][1].items():
        got[name] = np.array(nan(value), dtype=ref[name].dtype)
    ticks = []
    for _, m in msgs["/run"]:
        k = m.pop("k")
        ticks.append(k)
        for name, value in m.items():
            got[name][k] = nan(value)
    for i, aid in enumerate(ids):
        for _, m in msgs[f"/agent/{aid}"]:
            k = m["k"]
            for name, value in m.items():
                if name in ref and name not in ("t",) and ref[name].ndim >= 2 and ref[name].shape[1] == len(ids):
                    got[name][k, i] = nan(value)
    for topic, rows in msgs.items():
        parts = topic.split("/")
        if parts[1] == "link":  # /link/<dst>/<src>
            i = ids.index(int(parts[2]))
            slot = run.links.src[i].tolist().index(int(parts[3]))
            for _, m in rows:
                k = m.pop("k")
                for field, value in m.items():
                    got[f"link_{field}"][k, i, slot] = nan(value)
    for attr, prefix in EVENT_PREFIXES.items():
        topic = {"events": "/events/agent", "plant_events": "/events/plant"}[attr]
        rows = [m for _, m in msgs.get(topic, [])]
        for f in EVENT_FIELDS:
            got[prefix + f] = np.array([m[f] for m in rows], dtype=ref[prefix + f].dtype)
    return got, np.array(sorted(ticks), dtype=np.int64)


def assert_whole(path: Path, run: Run) -> np.ndarray:
    """Every array equal (NaN where NaN) on the ticks the file holds, which are those the run heard."""
    got, ticks = rebuild(path, run)
    assert ticks.tolist() == np.flatnonzero(viz.heard(run)).tolist()
    T = len(run.t)
    for name, a in run.arrays().items():
        b = got[name]
        assert b.dtype == a.dtype, name
        if a.ndim >= 1 and a.shape[0] == T and name != "agent_ids":
            a, b = a[ticks], b[ticks]
        np.testing.assert_array_equal(b, a, err_msg=name)
    return ticks


def test_every_array_of_an_in_process_run_is_in_its_mcap(tmp_path: Path) -> None:
    """Section 4 in the in-process engine (links with run totals, the disturbance): every array back."""
    m = ms.load(catalog.resolve("section4"))
    run = lockstep.simulate(m, duration=1.0)
    path = viz.write_mcap(run, m, tmp_path / "run.mcap", scene_rate=0)
    assert_whole(path, run)
    assert metadata(path)["epoch_ns"] == str(EPOCH_NS) and metadata(path)["clock"] == "simulated"
    # the scene draws the communication graph between the vehicles and each vehicle's trail
    scenes = messages(path)["/scene"]
    k = len(scenes) - 1
    ents = {e.id: e for e in scenes[k][1].entities}
    graph = ents["graph"].lines[0].points
    assert len(graph) == 2 * len(m.edges)
    ids = [int(a) for a in run.agent_ids]
    for n, e in enumerate(m.edges):  # j -> i, from j's position (the leader's) to i's
        src = run.leader_p[k] if e.src not in ids else run.p[k, ids.index(e.src)]
        dst = run.p[k, ids.index(e.dst)]
        assert [graph[2 * n].x, graph[2 * n].y] == src.tolist() and [graph[2 * n + 1].x, graph[2 * n + 1].y] == dst.tolist()
    trails = ents["trails"].lines
    assert len(trails) == len(ids) and all(len(t.points) == viz.TRAIL for t in trails)
    assert [trails[0].points[-1].x, trails[0].points[-1].y] == run.p[k, 0].tolist()


def test_a_quadrotor_payload_run_has_its_attitude_in_tf(tmp_path: Path) -> None:
    """exp2 (quadrotors and a payload): every array back, and /tf carries each vehicle's attitude."""
    m = ms.load(catalog.resolve("exp2"))
    run = lockstep.simulate(m, duration=0.5)
    assert run.plant.attitude is not None
    path = viz.write_mcap(run, m, tmp_path / "run.mcap", scene_rate=0)
    assert_whole(path, run)
    tf = messages(path)["/tf"]
    k = len(run.t) - 1
    q = viz.quaternions(run.plant.attitude[k])
    frames = {f.child_frame_id: f for f in tf[k][1].transforms}
    for i, aid in enumerate(run.agent_ids):
        r = frames[f"agent_{aid}"].rotation
        np.testing.assert_allclose([r.x, r.y, r.z, r.w], q[i], rtol=0, atol=1e-12)
    assert any(abs(frames[f"agent_{a}"].rotation.w) < 1.0 - 1e-9 for a in run.agent_ids)  # not identity


@pytest.mark.slow
def test_a_killed_agent_stays_where_its_plant_is_at_wall_clock_time(tmp_path: Path) -> None:
    """A real-time run with agent 2 killed at 3 s: the recorder's file holds every array, its log times
    are tick 0's Unix time + t, and after the kill vehicle 2 is drawn where its plant is (not at the
    origin); the launcher's events (events.json) are on /events/launcher."""
    out = tmp_path / "run"
    before = time.time_ns()
    r = subprocess.run([sys.executable, "-m", "cli", "run", "failsafe", "--clock", "realtime", "--duration", "7",
                        "--out", str(out), "--ns", f"mc{uuid.uuid4().hex[:8]}", "--quiet",
                        "--fault", "kill:agent/2@3"], cwd=REPO, capture_output=True, text=True, timeout=240)
    after = time.time_ns()
    assert (out / "run.mcap").exists(), r.stdout[-3000:] + r.stderr[-3000:]
    run = Run.load(out)
    epoch = run.meta.epoch_ns
    assert epoch is not None and before < epoch < after
    ticks = assert_whole(out / "run.mcap", run)
    meta = metadata(out / "run.mcap")
    assert meta["epoch_ns"] == str(epoch) and meta["clock"] == "unix"
    msgs = messages(out / "run.mcap")
    for t_ns, m in msgs["/run"]:
        assert t_ns == epoch + round(m["t"] * 1e9)
    # vehicle 2 after its agent died: no telemetry, its plant's own position in the scene
    col = int(np.flatnonzero(run.agent_ids == 2)[0])
    assert run.runtime is not None
    dead = [k for k in ticks.tolist()
            if np.isnan(run.p[k, col]).all() and np.isfinite(run.runtime.plant_p[k, col]).all()]
    assert len(dead) > run.meta.rate  # over a second of it
    by_time = {t_ns: tf for t_ns, tf in msgs["/tf"]}
    seen = 0
    for k in dead:
        tf = by_time.get(epoch + round(float(run.t[k]) * 1e9))
        if tf is None:
            continue
        frame = {f.child_frame_id: f for f in tf.transforms}["agent_2"]
        p = run.runtime.plant_p[k, col]
        got = [frame.translation.x, frame.translation.y, frame.translation.z][: len(p)]
        assert got == p.tolist(), (k, got, p)
        assert np.hypot(*p[:2]) > 1.0  # far from the origin, where it was once drawn
        seen += 1
    assert seen >= 10
    # the launcher's events (events.json, written when every process has stopped) are in the run's file
    assert (out / "events.json").exists()
    launcher = [m for _, m in msgs["/events/launcher"]]
    assert any(e["who"] == "agent/2" and e["what"] == "died" for e in launcher), launcher


def test_the_shipped_layout_is_in_the_apps_import_format(tmp_path: Path) -> None:
    """``docs/foxglove/tether.json`` has the Foxglove app's layout structure (``configById`` and a
    mosaic tree of its panel ids, each used once), and every topic its panels read is in a Section 4
    file."""
    shipped = json.loads((REPO / "docs" / "foxglove" / "tether.json").read_text())
    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(shipped)
    leaves: list[str] = []

    def walk(node: Any) -> None:
        if isinstance(node, str):
            leaves.append(node)
            return
        assert node["direction"] in ("row", "column") and 0 < node["splitPercentage"] < 100
        walk(node["first"])
        walk(node["second"])

    walk(shipped["layout"])
    assert sorted(leaves) == sorted(shipped["configById"]) and len(set(leaves)) == len(leaves)
    assert {pid.split("!")[0] for pid in leaves} == {"ThreeDee", "Plot", "Log"}
    m = ms.load(catalog.resolve("section4"))
    run = lockstep.simulate(m, duration=0.2)
    run.safety.events = [SafetyEvent(k=5, t=5 * m.dt, vehicle=1, src=0, dst=1, reason="test")]  # a /safety
    with open(viz.write_mcap(run, m, tmp_path / "run.mcap"), "rb") as fh:
        topics = {ch.topic for ch in mcap_reader.make_reader(fh).get_summary().channels.values()}
    for pid, cfg in shipped["configById"].items():
        used = [p["value"].split(".")[0] for p in cfg.get("paths", [])] + \
            ([cfg["topicToRender"]] if "topicToRender" in cfg else []) + list(cfg.get("topics", {}))
        assert used and set(used) <= topics, (pid, used)
