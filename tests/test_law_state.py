"""A law's own state by its own names: the run file's ``law_state`` (every engine, the old format
still read), the telemetry that carries it (checked on receipt), the recorder's bookkeeping,
``run.mcap`` (the real ``mcap`` reader), ``tether top``'s board and the figures."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import msgspec
import numpy as np
import pytest

from agent import laws
from recorder.recording import Recording, RecordingContext
from recorder.top import Board
from sim import figures, lockstep, lockstep_kernel, refsim
from tests.support import REPO, tether
from tests.test_law_integral import biased, text
from tether import mission as ms
from tether import wire
from tether.runfile import FORMAT_VERSION, Run

NAMES = ("kp", "kv", "s")
UNITS = ("1/s^2", "1/s", "m s")


def integral_mission(tmp_path: Path, duration: float = 1.0) -> Path:
    path = tmp_path / "integral.toml"
    path.write_text(text(duration=duration))
    return path


def test_the_laws_declare_their_state_and_its_units() -> None:
    bound = laws.of_mission(ms.loads(text()))
    assert bound.law.state == NAMES and bound.units == UNITS
    assert laws.resolve("sigma").units == ("1/s^2", "1/s")
    assert laws.resolve("examples.custom_law.pd:PDConsensus").state == ()


def test_a_law_whose_state_names_are_not_identifiers_is_refused(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "badlaw.py").write_text(
        "from agent.laws.sigma import Sigma\n"
        "class Spaced(Sigma):\n    state = ('k p', 'kv')\n"
        "class Twice(Sigma):\n    state = ('kp', 'kp')\n"
        "class Units(Sigma):\n    units = ('1/s^2',)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for cls, words in (("Spaced", "not Python identifiers"), ("Twice", "repeat a name"), ("Units", "do not match")):
        with pytest.raises(laws.LawNotFound, match=words):
            laws.resolve(f"badlaw:{cls}")


def test_every_engine_records_the_integrator_by_name_bit_for_bit() -> None:
    """The reference simulator's numpy path and compiled kernel, the in-process engine and its
    compiled twin: ``s`` by name, the same bits, and ``kp``/``kv`` the first two variables."""
    pytest.importorskip("numba")
    m = biased("integral", 3.0)
    ref = refsim.simulate(m, engine="numpy")
    assert ref.meta.law_state == NAMES and ref.meta.law_units == UNITS
    assert ref.law_state.shape == (3, len(ref.t), m.n, m.dim)
    s = ref.state("s")
    assert np.all(s[0] == 0.0) and np.abs(s[-1]).max() > 0.01  # integrates from 0
    assert np.shares_memory(ref.kp, ref.law_state) and np.array_equal(ref.kp, ref.state("kp"))
    twin = lockstep_kernel.simulate(m)
    assert twin is not None
    for other in (refsim.simulate(m, engine="compiled"), lockstep.simulate(m, engine="python"), twin):
        assert other.meta.law_state == NAMES
        np.testing.assert_array_equal(other.law_state, ref.law_state)
    with pytest.raises(KeyError, match="kp, kv, s"):
        ref.state("ki")


def test_the_continuous_mode_records_the_state_too() -> None:
    run = refsim.simulate(biased("integral", 1.0), "continuous", engine="numpy")
    assert run.meta.law_state == NAMES and np.abs(run.state("s")[-1]).max() > 0.0
    assert np.all(np.isfinite(run.law_state))


def test_the_run_file_round_trips_the_named_state(tmp_path: Path) -> None:
    run = refsim.simulate(biased("integral", 1.0), engine="numpy")
    path = run.save(tmp_path / "run.npz")
    with np.load(path) as z:
        assert "law_state" in z.files and "kp" not in z.files and "kv" not in z.files  # stored once
        assert json.loads(str(z["meta"]))["law_state"] == list(NAMES)
    back = Run.load(path)
    assert back.meta.format_version == FORMAT_VERSION == 5
    assert back.meta.law_state == NAMES and back.meta.law_units == UNITS
    np.testing.assert_array_equal(back.law_state, run.law_state)
    np.testing.assert_array_equal(back.kv, run.kv)
    assert np.shares_memory(back.kv, back.law_state)


def test_a_law_without_state_keeps_zero_gain_columns(tmp_path: Path) -> None:
    from tests.test_law_custom import example

    run = refsim.simulate(example(1.0), engine="numpy")
    assert run.meta.law_state == () and run.law_state.shape[0] == 0
    assert np.all(run.kp == 0.0) and np.all(run.kv == 0.0)
    back = Run.load(run.save(tmp_path / "run.npz"))
    assert back.law_state.shape == run.law_state.shape and np.all(back.kp == 0.0)


def test_a_version_4_run_file_still_loads_with_its_gains_as_the_state(tmp_path: Path) -> None:
    """A file as format version 4 wrote it: ``kp`` and ``kv`` arrays, no ``law_state``, no names."""
    run = refsim.simulate(ms.loads((REPO / "tether" / "missions" / "section4.toml").read_text()
                                   .replace("duration = 1000.0", "duration = 1.0")), engine="numpy")
    arrays = run.arrays()
    del arrays["law_state"]
    arrays["kp"], arrays["kv"] = run.kp, run.kv
    meta = msgspec.to_builtins(run.meta)
    meta["format_version"] = 4
    del meta["law_state"], meta["law_units"]
    np.savez(tmp_path / "run.npz", meta=np.array(json.dumps(meta)), **arrays)
    old = Run.load(tmp_path)
    assert old.meta.law_state == ("kp", "kv") and old.meta.law_units == ()
    np.testing.assert_array_equal(old.kp, run.kp)
    np.testing.assert_array_equal(old.state("kv"), run.kv)
    # a version-5 file whose law_state disagrees with its names is refused, naming both
    arrays["law_state"] = run.law_state[:1]
    del arrays["kp"], arrays["kv"]
    meta["format_version"] = 5
    meta["law_state"] = ["kp", "kv"]
    np.savez(tmp_path / "bad.npz", meta=np.array(json.dumps(meta)), **arrays)
    with pytest.raises(ValueError, match="law_state does not match"):
        Run.load(tmp_path / "bad.npz")


def telemetry(k: int, x: list[float], names: list[str], sender: int = 1) -> wire.Telemetry:
    return wire.Telemetry(sender=sender, seq=k, k=k, t=k * 0.01, meas_t=k * 0.01, p=[0.0, 0.0], vel=[0.0, 0.0],
                          a=[0.0, 0.0], u=[0.1, 0.2], xi=[0.01, 0.0], zeta=[0.0, 0.0], kp=x[0:2] or [0.0, 0.0],
                          kv=x[2:4] or [0.0, 0.0], links=[], drops={}, x=x, x_names=names)


@pytest.mark.parametrize(("x", "names", "reason"), [
    ([2.0, 2.0, 1.0, 1.0, 0.5, float("nan")], list(NAMES), "nonfinite"),
    ([2.0, 2.0, 1.0, 1.0, 0.5], [], "size"),  # not a whole number of axes
    ([2.0, 2.0, 1.0, 1.0], list(NAMES), "size"),  # a name too many
    ([1.0] * 2 * (wire.MAX_STATE + 1), [], "size"),  # beyond the bound
    ([2.0, 2.0, 1.0, 1.0, 0.5, 0.5], ["kp", "kv", "s s"], "malformed"),
    ([2.0, 2.0, 1.0, 1.0, 0.5, 0.5], ["kp", "kv", "s" * (wire.MAX_NAME + 1)], "malformed"),
])
def test_a_telemetry_with_a_bad_law_state_is_dropped_and_counted(x: list[float], names: list[str],
                                                                   reason: str) -> None:
    rx = wire.Receiver(2)
    assert rx.accept(wire.encode(telemetry(3, x, names)), wire.Telemetry, 1) is None
    assert rx.drops == {reason: 1}
    good = telemetry(3, [2.0, 2.0, 1.0, 1.0, 0.5, -0.5], list(NAMES))
    got = rx.accept(wire.encode(good), wire.Telemetry, 1)
    assert got is not None and got.x == good.x and got.x_names == list(NAMES)


def test_the_recorder_files_each_agents_state_by_name_and_counts_a_foreign_one(tmp_path: Path) -> None:
    m = ms.loads(text(duration=0.1))
    rec = Recording(RecordingContext(mission=m, lockstep=True, namespace="x", mission_text=""), tmp_path,
                    mcap=False)
    rec.telemetry(telemetry(0, [2.0, 2.1, 1.0, 1.1, 0.25, -0.5], list(NAMES)))
    rec.telemetries([telemetry(k, [2.0, 2.0, 1.0, 1.0, 0.1 * k, 0.0], list(NAMES), sender=2) for k in range(3)])
    rec.telemetry(telemetry(1, [2.0, 2.0, 1.0, 1.0, 9.0, 9.0], ["kp", "kv", "q"]))  # not this law's state
    rec.telemetry(telemetry(2, [2.0, 2.0, 1.0, 1.0], ["kp", "kv"]))  # a state of the wrong size
    run = rec.finalise(False, {})
    assert run.state("s")[0, 0].tolist() == [0.25, -0.5] and run.kv[0, 0].tolist() == [1.0, 1.1]
    assert run.state("s")[:3, 1, 0].tolist() == [0.0, 0.1, 0.2]
    assert np.all(np.isnan(run.state("s")[1:3, 0])) and run.kp[1, 0].tolist() == [2.0, 2.0]
    assert run.meta.recorder_drops is not None and run.meta.recorder_drops.other == {"law_state": 2}


def test_tether_top_heads_the_state_column_with_the_laws_names() -> None:
    b = Board("s4")
    assert b.state_heading() == "Kp  Kv (per axis)"  # nothing heard yet
    b.telemetry("tether/s4/agent/1/telemetry", wire.encode(telemetry(5, [2.0, 2.5, 1.0, 1.5, 0.25, -0.5],
                                                                     list(NAMES))), now=0.0)
    assert b.state_heading() == "kp  kv  s (per axis)"
    cells, styles = b.cells(b.rows[1], now=0.1)
    assert cells[4] == "2.00/2.50  1.00/1.50  0.25/-0.50" and styles[4] == ""  # after vehicle, mode, plant, |xi|
    from rich.console import Console

    console = Console(width=200, record=True)
    console.print(b.table(0.1))
    assert "kp  kv  s (per axis)" in console.export_text()


def test_the_figures_draw_a_panel_per_further_state_variable_with_its_unit() -> None:
    run = refsim.simulate(biased("integral", 1.0), engine="numpy")
    fig = figures.comparison_figure({"integral": run})
    assert [ax.get_ylabel() for ax in fig.axes][3] == "s [m s]"
    assert {ln.get_label() for ln in fig.axes[3].get_lines()} >= {"1x", "1y", "4x"}
    figures.plt.close(fig)


def mcap_agent_messages(path: Path) -> tuple[dict, list[dict]]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        channel = next(ch for ch in summary.channels.values() if ch.topic == "/agent/1")
        schema = json.loads(summary.schemas[channel.schema_id].data)
        msgs = [json.loads(m.data) for _s, ch, m in reader.iter_messages(topics=["/agent/1"])]
    return schema, msgs


@pytest.mark.slow  # real processes
def test_simulate_writes_the_state_by_name_in_run_npz_and_run_mcap(tmp_path: Path) -> None:
    pytest.importorskip("mcap")
    pytest.importorskip("foxglove")
    out = tmp_path / "sim"
    done = tether("simulate", str(integral_mission(tmp_path)), "--out", str(out), "--no-figures")
    assert done.returncode == 0, done.stderr[-3000:]
    run = Run.load(out)
    assert run.meta.law_state == NAMES
    np.testing.assert_array_equal(run.law_state, refsim.simulate(ms.loads(text(duration=1.0))).law_state)
    schema, msgs = mcap_agent_messages(out / "run.mcap")
    described = schema["properties"]["law"]["properties"]
    assert list(described) == list(NAMES) and described["s"]["description"].startswith("s [m s]")
    by_k = {m["k"]: m for m in msgs}
    k = len(run.t) - 1
    assert by_k[k]["law"] == {name: run.state(name)[k, 0].tolist() for name in NAMES}


@pytest.mark.slow  # real processes
@pytest.mark.parametrize("plants", ["--colocate-plants", "--separate-plants"])
def test_tether_run_in_lockstep_records_the_state_as_the_in_process_engine(tmp_path: Path, plants: str) -> None:
    """The agents' telemetry in records of many ticks (plants on board) and one message a tick
    (plant processes): the recorder files the same state as the in-process engine computes."""
    pytest.importorskip("mcap")
    pytest.importorskip("foxglove")
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "cli", "run", str(integral_mission(tmp_path)), "--out", str(out),
                        "--duration", "1", "--quiet", "--ns", f"lawstate-{os.getpid()}", plants],
                       capture_output=True, text=True, timeout=400, cwd=REPO)
    assert r.returncode == 0, r.stderr[-3000:]
    run = Run.load(out)
    assert run.meta.source == "runtime-lockstep" and run.meta.law_state == NAMES and run.meta.complete
    inproc = lockstep.simulate(ms.loads(text(duration=1.0)), engine="python")
    np.testing.assert_array_equal(run.law_state, inproc.law_state)
    assert np.abs(run.state("s")[-1]).max() > 0.0
    _, msgs = mcap_agent_messages(out / "run.mcap")
    last = max(msgs, key=lambda m: m["k"])
    assert last["law"]["s"] == run.state("s")[last["k"], 0].tolist()
