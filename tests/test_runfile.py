"""Run files: every typed record written and read back, numpy alone can read them, versions 1-3 still
load, and what a run lacks is said per stream."""

from __future__ import annotations

import json
from pathlib import Path

import msgspec
import numpy as np
import pytest

from tether import wire
from tether.runfile import (FORMAT_VERSION, NO_SAMPLE, ClockRecord, DropCounts, Links, PlantRecord, Run, RunMeta,
                            RuntimeRecord)

T, IDS, DIM = 4, [3, 5, 8], 3


def _meta(**kw) -> RunMeta:
    return RunMeta(mission="m", source="runtime-realtime", law="sigma", rate=50.0, steps=T - 1, seed=7, **kw)


def _full_run() -> Run:
    """A run with every record filled with distinct values."""
    rng = np.random.default_rng(1)
    run = Run.empty(T, IDS, DIM, _meta(mission_text="name = 'm'\n", namespace="ns", complete=False,
                                       samples_recorded=20, samples_expected=28,
                                       recorder_drops=DropCounts.of({"malformed": 2, "size": 1, "new_reason": 4})))
    n = len(IDS)
    run.t[:] = np.arange(T) / 50.0
    for name in ("p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d"):
        getattr(run, name)[:] = rng.normal(size=(T, n, DIM))
    run.leader_p[:] = rng.normal(size=(T, DIM))
    run.links = Links.empty(T, n, 2)
    run.links.src[:] = [[0, 5], [3, 0], [3, 5]]
    for f in Links.__struct_fields__[1:]:
        getattr(run.links, f)[:] = rng.integers(0, 9, size=(T, n, 2))
    run.runtime = RuntimeRecord.empty(T, n, DIM)
    run.runtime.plant_p[:] = rng.normal(size=(T, n, DIM))
    run.runtime.drops[:] = 1.0
    run.plant = PlantRecord(payload_p=rng.normal(size=(T, 3)), payload_v=rng.normal(size=(T, 3)),
                            tension=rng.random(size=(T, n)), slack_events=np.zeros((T, n)),
                            attitude=rng.normal(size=(T, n, 3)))
    s = run.safety
    s.safety_mode[:] = wire.FLYING
    s.safety_mode[2:, 1] = wire.HOLD
    s.safety_mode[3, 2] = NO_SAMPLE
    s.plant_mode[:] = wire.FLYING
    s.plant_mode[3, 1] = wire.LAND
    s.events = [wire.SafetyEvent(k=2, t=0.04, vehicle=5, src=wire.FLYING, dst=wire.HOLD, reason="leader silent 0.5 s"),
                wire.SafetyEvent(k=3, t=0.06, vehicle=8, src=wire.FLYING, dst=wire.ESTOP, reason="operator")]
    s.plant_events = [wire.SafetyEvent(k=1, t=0.02, vehicle=3, src=wire.FLYING, dst=wire.FLYING,
                                       reason="command rejected: stamp 1e9 s ahead"),
                      wire.SafetyEvent(k=3, t=0.06, vehicle=5, src=wire.FLYING, dst=wire.LAND, reason="geofence")]
    s.gate_reasons = np.array(["future", "jump"])
    s.gate_counts = np.array([[0, 1], [2, 0], [0, 0]], dtype=np.int64)
    run.clock = ClockRecord.empty(T, n, 2)
    run.clock.role[:] = [["plant", "leader"], ["plant", "agent"], ["plant", ""]]
    run.clock.src[:] = [[IDS[0], 5], [IDS[1], 3], [IDS[2], 0]]
    run.clock.offset[1:, :, 0] = rng.normal(size=(T - 1, n)) * 1e-3
    return run


def test_every_typed_record_round_trips(tmp_path: Path) -> None:
    run = _full_run()
    run.save(tmp_path / "run.npz")
    back = Run.load(tmp_path)
    assert back.meta == run.meta and back.meta.format_version == FORMAT_VERSION == 5
    assert back.meta.recorder_drops == DropCounts(malformed=2, size=1, other={"new_reason": 4})
    assert back.meta.recorder_drops.total() == 7
    assert back.meta.modes == wire.MODES
    assert back.safety.events == run.safety.events and back.safety.plant_events == run.safety.plant_events
    for name, want in run.arrays().items():
        got = back.arrays()[name]
        assert got.dtype == want.dtype or got.dtype.kind == want.dtype.kind == "U", name
        np.testing.assert_array_equal(got, want, err_msg=name)
    assert back.safety.safety_mode.dtype == np.int64 and back.safety.safety_mode[3, 2] == NO_SAMPLE
    np.testing.assert_array_equal(back.safety.gate_counts, [[0, 1], [2, 0], [0, 0]])
    assert list(back.safety.gate_reasons) == ["future", "jump"]


def test_numpy_alone_reads_the_file_and_names_the_modes(tmp_path: Path) -> None:
    _full_run().save(tmp_path / "run.npz")
    with np.load(tmp_path / "run.npz", allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        assert meta["format_version"] == 5 and meta["recorder_drops"]["malformed"] == 2
        names = [meta["modes"][c] for c in z["event_dst"]]
        assert names == ["HOLD", "ESTOP"] and list(z["event_vehicle"]) == [5, 8]
        assert list(z["event_reason"]) == ["leader silent 0.5 s", "operator"]
        assert [meta["modes"][c] for c in z["plant_event_dst"]] == ["FLYING", "LAND"]
        assert list(z["plant_event_vehicle"]) == [3, 5]
        assert meta["modes"][z["safety_mode"][3, 1]] == "HOLD"
        assert z["link_src"].shape == (3, 2) and z["tension"].shape == (T, 3)


def test_a_run_without_events_or_optional_records(tmp_path: Path) -> None:
    run = Run.empty(T, IDS, 2, _meta(), mode=wire.FLYING)
    run.save(tmp_path / "run.npz")
    back = Run.load(tmp_path)
    assert back.safety.events == [] and back.links is None and back.runtime is None
    assert back.plant == PlantRecord()
    assert np.all(back.safety.safety_mode == wire.FLYING) and np.all(back.safety.plant_mode == wire.FLYING)
    assert back.meta.diverged_at is None and back.meta.recorder_drops is None


def test_a_version_1_file_still_loads(tmp_path: Path) -> None:
    """Written as format version 1 did: meta a plain JSON object, drops a reason -> count object."""
    run = _full_run()
    arrays = {k: v for k, v in run.arrays().items()
              if not k.startswith(("event_", "plant_event_", "gate_")) and k not in ("safety_mode", "plant_mode",
                                                                                      "law_state")}
    meta = {"mission": "m", "source": "runtime-lockstep", "law": "sigma", "rate": 50.0, "steps": 3, "seed": 0,
            "namespace": "ns", "mission_text": "x", "complete": True, "recorder_drops": {"size": 3},
            "samples_recorded": 28, "samples_expected": 28, "format_version": 1}
    np.savez_compressed(tmp_path / "run.npz", meta=np.array(json.dumps(meta)), **arrays)
    back = Run.load(tmp_path)
    assert back.meta.format_version == 1 and back.meta.recorder_drops == DropCounts(size=3)
    assert back.meta.complete is True
    assert np.all(back.safety.safety_mode == NO_SAMPLE) and back.safety.events == []
    np.testing.assert_array_equal(back.plant.tension, run.plant.tension)
    np.testing.assert_array_equal(back.links.received, run.links.received)


def test_another_version_or_an_unknown_array_is_an_error_that_names_it(tmp_path: Path) -> None:
    run = Run.empty(T, IDS, 2, _meta())
    arrays = run.arrays()
    np.savez(tmp_path / "v6.npz", meta=np.array(json.dumps({"format_version": 6})), **arrays)
    with pytest.raises(ValueError, match="format version 6"):
        Run.load(tmp_path / "v6.npz")
    run.save(tmp_path / "ok.npz")
    with np.load(tmp_path / "ok.npz") as z:
        np.savez(tmp_path / "typo.npz", **{k: z[k] for k in z.files}, link_recieved=np.zeros(1))
    with pytest.raises(ValueError, match="link_recieved"):
        Run.load(tmp_path / "typo.npz")
    meta = json.loads(str(np.load(tmp_path / "ok.npz")["meta"])) | {"complet": True}
    np.savez(tmp_path / "meta.npz", meta=np.array(json.dumps(meta)), **arrays)
    with pytest.raises(ValueError, match="complet"):
        Run.load(tmp_path / "meta.npz")


def test_figures_mark_mode_changes_only_when_there_are_events(tmp_path: Path) -> None:
    import matplotlib.pyplot as plt

    from sim import figures

    run = _full_run()
    fig, axes = plt.subplots(2, 1)
    for a in axes:
        a.set_xlim(0.0, 0.06)  # the run's span
    figures.mark_events(run, axes)
    assert [len(a.lines) for a in axes] == [2, 2]
    assert sorted(t.get_text() for t in axes[0].texts) == ["1", "2"]  # numbered as figures.event_lines lists them
    lines = figures.event_lines(run)
    assert [line.split()[0] for line in lines] == ["1", "2"] and "HOLD" in lines[0] and "ESTOP" in lines[1]
    run.safety.events = []
    fig, axes = plt.subplots(2, 1)
    figures.mark_events(run, axes)
    assert [len(a.lines) for a in axes] == [0, 0] and not axes[0].texts
    plt.close("all")
    run = _full_run()
    paths = figures.run_panels(run, tmp_path)
    assert all(p.stat().st_size > 10_000 for p in paths)


def test_a_version_2_file_loads_without_a_clock_record(tmp_path: Path) -> None:
    """Written as format version 2 did: no ``clock_*`` arrays."""
    run = _full_run()
    arrays = {k: v for k, v in run.arrays().items() if not k.startswith(("clock_", "plant_event_", "law_state"))}
    meta = json.loads(msgspec.json.encode(run.meta).decode()) | {"format_version": 2}
    np.savez(tmp_path / "run.npz", meta=np.array(json.dumps(meta)), **arrays)
    back = Run.load(tmp_path)
    assert back.meta.format_version == 2 and back.clock is None
    np.testing.assert_array_equal(back.links.received, run.links.received)


def test_a_version_3_file_loads_without_plant_events_and_refuses_them(tmp_path: Path) -> None:
    """Written as format version 3 did: no ``plant_event_*`` arrays; a version-3 file that has them
    is refused naming them (they are version 4's)."""
    run = _full_run()
    meta = json.loads(msgspec.json.encode(run.meta).decode()) | {"format_version": 3}
    del meta["recovered"]
    arrays = {k: v for k, v in run.arrays().items() if not k.startswith(("plant_event_", "law_state"))}
    np.savez(tmp_path / "run.npz", meta=np.array(json.dumps(meta)), **arrays)
    back = Run.load(tmp_path)
    assert back.meta.format_version == 3 and back.safety.plant_events == [] and back.safety.events == run.safety.events
    np.savez(tmp_path / "bad.npz", meta=np.array(json.dumps(meta)), **run.arrays())
    with pytest.raises(ValueError, match="plant_event_dst"):
        Run.load(tmp_path / "bad.npz")


def test_gaps_name_each_stream_s_missing_ticks_and_a_full_run_has_none() -> None:
    from tether.runfile import gaps, missing_report

    run = Run.empty(10, [1, 2], 2, _meta(), mode=wire.FLYING)
    run.leader_p[:] = 0.0
    run.runtime = RuntimeRecord.empty(10, 2, 2)
    assert gaps(run) == [] and missing_report(run) == []
    run.leader_p[7:] = np.nan  # a recorder that heard nothing after tick 6
    run.safety.safety_mode[7:] = NO_SAMPLE
    run.safety.plant_mode[7:] = NO_SAMPLE
    run.safety.plant_mode[2:4, 1] = NO_SAMPLE  # and lost two samples of plant 2
    found = {g.stream: g for g in gaps(run)}
    assert set(found) == {"leader", "plant 1", "plant 2", "telemetry of agent 1", "telemetry of agent 2"}
    assert found["plant 2"].spans == ((2, 3), (7, 9)) and found["plant 2"].missing == 5
    assert found["plant 2"].last == 6 and found["leader"].spans == ((7, 9),)
    lines = missing_report(run)
    assert "plant 2: 5 ticks missing: 2-3, 7-9 (t 0.04-0.18 s); newest t 0.12 s" in lines
    run.meta.recovered = "from the recorder's journal: samples up to tick 6"
    assert missing_report(run)[0] == "recovered: from the recorder's journal: samples up to tick 6"


def test_the_mission_checks_count_the_run_file_s_series() -> None:
    """``tether.checks`` sizes a run from a number of its own (so that a process checking its mission
    does not load the run file's numpy): the engines' series and the recorder's three plant ones."""
    from tether import checks, runfile

    assert checks.SERIES_RECORDED == len(runfile.SERIES) + len(("plant_p", "plant_v", "plant_a"))
    assert {"plant_p", "plant_v", "plant_a"} <= set(runfile.RuntimeRecord.__struct_fields__)


def test_metrics_of_a_run_cut_short_are_those_of_its_recorded_ticks() -> None:
    """A recorder's run that lacks its last ticks (modes -1, NaN series) is not called diverged, and
    its final gains are its last recorded tick's; an engine's run (every tick) is summed up as before."""
    from sim import metrics

    T2 = 20
    run = Run.empty(T2, [1, 2], 2, _meta(), mode=wire.FLYING)
    run.t[:] = np.arange(T2) / 50.0
    run.xi[:] = 0.1
    run.kp[:] = np.linspace(1.0, 2.0, T2)[:, None, None]
    run.kv[:] = 1.0
    whole = metrics.summary(run)
    assert whole["diverged"] is False and whole["final_kp_mean"] == 2.0
    run.xi[15:] = np.nan
    run.kp[15:] = np.nan
    run.safety.safety_mode[15:] = NO_SAMPLE
    cut = metrics.summary(run)
    assert cut["diverged"] is False and cut["final_kp_mean"] == pytest.approx(1.0 + 14 / 19)
    run.safety.safety_mode[15:] = wire.FLYING  # the same NaN in an engine's run: a divergence
    assert metrics.summary(run)["diverged"] is True
