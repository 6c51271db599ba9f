"""The record outlives its recorder: a real ``tether run section4`` whose recorder, launcher or whole
process tree is killed with SIGKILL mid-run leaves a journal (``journal.mcap``) that the real MCAP
reader reads up to its last whole chunk, holding every tick the recorder took up to within a second
of the kill; ``recorder.journal`` rebuilds the run from it and says what is missing."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

mcap_stream = pytest.importorskip("mcap.stream_reader")

from recorder import journal  # noqa: E402
from tether import wire  # noqa: E402
from tether.runfile import Run  # noqa: E402

from tests.support import finish, kill, tether_popen, wait_until  # noqa: E402

AGENTS = (1, 2, 3, 4)
SLACK = 1.5
"""Beyond the journal's flush period, how late a flush may come on a loaded machine [s] (the
recorder's event loop shares 2 cores with every other test)."""


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (the launcher puts each child in its own process group)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def raw_journal(path: Path) -> tuple[list[tuple[int, wire.Message]], bool]:
    """Every message of a journal with its log time [ns], read with the ``mcap`` package's own stream
    reader up to where the file is cut; and whether it was cut (no footer)."""
    out: list[tuple[int, wire.Message]] = []
    with open(path, "rb") as fh:
        try:
            for record in mcap_stream.StreamReader(fh, validate_crcs=True).records:
                if type(record).__name__ == "Message":
                    out.append((record.log_time, wire.decode(record.data)))
                elif type(record).__name__ == "Footer":
                    return out, False
        except Exception:  # noqa: BLE001 - where the kill cut the file: what came before stands
            pass
    return out, True


def complete_ticks(msgs: list[tuple[int, wire.Message]]) -> tuple[int, dict[int, int]]:
    """A lockstep journal's ticks: the newest k such that every tick 0..k holds the leader's state,
    each agent's telemetry and each plant's state; and the wall time [ns] each tick was taken."""
    have: dict[tuple[str, int], set[int]] = {}
    taken: dict[int, int] = {}
    for ns, msg in msgs:
        if isinstance(msg, wire.Record):  # plants co-located: the agents' and the leader's records
            items = [("leader", s.k) for s in msg.leader] + [(f"plant {p.sender}", p.k) for p in msg.plant] \
                + [(f"agent {x.sender}", x.k) for x in msg.telemetry]
        else:  # sample by sample
            kind = {wire.State: "leader", wire.PlantState: "plant", wire.Telemetry: "agent"}[type(msg)]
            items = [(kind if kind == "leader" else f"{kind} {msg.sender}", msg.k)]
        for stream, k in items:
            have.setdefault((stream, 0), set()).add(k)
            taken[k] = max(taken.get(k, 0), ns)
    streams = ["leader", *(f"plant {i}" for i in AGENTS), *(f"agent {i}" for i in AGENTS)]
    k = 0
    while all(k in have.get((s, 0), ()) for s in streams):
        k += 1
    return k - 1, taken


def start_lockstep(tmp_path: Path, *extra: str) -> tuple[Path, Path, object]:
    out = tmp_path / "run"
    out.mkdir()
    log = tmp_path / "launcher.log"
    proc = tether_popen("run", "section4", "--clock", "lockstep", "--duration", "600", "--insecure", "--out", str(out),
                  *extra, log=log)
    return out, log, proc


def check_journal(out: Path, killed_ns: int) -> Run:
    """The journal holds every tick up to within FLUSH_PERIOD (+ SLACK) of the kill, read both by the
    real MCAP reader and by :func:`recorder.journal.load`, which says what is missing."""
    assert not (out / "run.npz").exists()
    msgs, cut = raw_journal(out / journal.NAME)
    assert cut, "a killed recorder never writes the journal's footer"
    last, taken = complete_ticks(msgs)
    assert last > 100, f"only {last + 1} complete ticks in the journal"
    lag = (killed_ns - taken[last]) / 1e9
    assert lag <= journal.FLUSH_PERIOD + SLACK, f"the journal ends {lag:.2f} s before the kill"
    said: list[str] = []
    run = journal.load(out, report=said.append)
    assert run.meta.complete is False and run.meta.recovered is not None
    assert f"samples up to tick {max(taken)}" in run.meta.recovered
    assert said[0].startswith("recovered: from the recorder's journal")
    assert "leader: " in said[1] and f"newest t {max(taken) * 0.01:.2f} s" in said[1]
    ticks = slice(0, last + 1)
    assert np.isfinite(run.xi[ticks]).all() and np.isfinite(run.leader_p[ticks]).all()
    assert (run.safety.plant_mode[ticks] == wire.FLYING).all()
    assert np.isnan(run.xi[max(taken) + 1:]).all()
    print(f"journal: {last + 1} complete ticks, the last taken {lag:.3f} s before the kill; "
          f"{(out / journal.NAME).stat().st_size} bytes")
    return run


def _journal_of(tmp_path: Path, chunks: int, per_chunk: int) -> tuple[Path, list[wire.Message]]:
    """A real-time section4 journal of ``chunks`` flushes of ``per_chunk`` leader samples each (sample
    times 1 ms apart: no whole second of mission time, whose first message would flush itself)."""
    from tether import catalog

    text = catalog.resolve("section4").read_text()
    j = journal.Journal.create(tmp_path, journal.Header(mission="section4", mission_text=text, namespace="t",
                                                        duration=10.0, lockstep=False, started_ns=0))
    sent: list[wire.Message] = []
    for c in range(chunks):
        for n in range(per_chunk):
            k = c * per_chunk + n
            msg = wire.State(sender=5, seq=k, k=k, t=k / 1000, p=[0.1 * k, 0.0], vel=[1.0, 0.0], a=[0.0, 0.0])
            j.add(msg)
            sent.append(msg)
        j.flush()
    return j.path, sent


def test_a_journal_cut_anywhere_reads_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    """Every prefix of a journal (as a kill leaves it) reads without error: the header, then whole
    chunks only, in order; the run rebuilt from it says how far it goes."""
    path, sent = _journal_of(tmp_path, chunks=4, per_chunk=50)
    data = path.read_bytes()
    counts = []
    for cut in [*range(len(data) // 40, len(data), max(1, len(data) // 97)), len(data)]:
        part = tmp_path / f"cut{cut}.mcap"
        part.write_bytes(data[:cut])
        try:
            got = journal.read(part)
        except ValueError as exc:  # cut before the header was whole
            assert "not a readable tether journal" in str(exc) or "no tether.journal header" in str(exc)
            continue
        assert got.messages == sent[:len(got.messages)] and len(got.messages) % 50 == 0
        assert got.cut is not None and not got.finished
        counts.append(len(got.messages))
    assert counts == sorted(counts) and counts[-1] == 200 and 0 in counts
    run = journal.recover(path)
    assert run.meta.recovered is not None and "samples up to tick 199" in run.meta.recovered
    np.testing.assert_array_equal(run.leader_p[:200, 0], [0.1 * k for k in range(200)])
    assert np.isnan(run.leader_p[200:]).all() and len(run.t) == 1001  # the header's duration: 10 s


def test_a_journal_that_cannot_write_stops_and_keeps_what_it_wrote(tmp_path: Path) -> None:
    """A full disk (``/dev/full``: every write fails with ENOSPC) stops the journal, noted in its
    ``error``; later messages are ignored, nothing is raised into the recorder."""
    from mcap.writer import CompressionType, Writer

    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    fh = open("/dev/full", "wb")
    writer = Writer(fh, compression=CompressionType.ZSTD)
    writer.start()
    j = journal.Journal(tmp_path / journal.NAME, fh, writer, time.time_ns)
    j.add(wire.State(sender=5, seq=0, k=0, t=0.0, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0]))
    j.flush()
    assert j.closed and j.error is not None and j.error.errno == 28  # ENOSPC
    j.add(wire.State(sender=5, seq=1, k=1, t=0.01, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0]))
    j.drops({"gate": 1})
    j.flush()
    j.finish()
    assert j.messages == 1 and j.flushes == 0


@pytest.mark.slow  # real processes
def test_a_recorder_killed_mid_run_leaves_a_run_file_rebuilt_from_its_journal(tmp_path: Path) -> None:
    """``--fault kill:recorder@5``: the launcher SIGKILLs the recorder between ticks 500 and 501; at the
    run's end it rebuilds ``run.npz`` (and ``run.mcap``) from the journal, which held every tick taken
    up to within a second of that, and says the file is incomplete."""
    out, log, proc = start_lockstep(tmp_path, "--fault", "kill:recorder@5")
    try:
        code, _ = finish(proc, 300)  # type: ignore[arg-type]
    finally:
        kill(proc)  # type: ignore[arg-type]
    text = log.read_text()
    assert code != 0, text[-3000:]
    assert "rebuilt from the recorder's journal" in text and "run recorded INCOMPLETE" in text, text[-3000:]
    assert not (out / journal.NAME).exists()
    run = Run.load(out)
    assert run.meta.complete is False and run.meta.recovered is not None
    newest = int(run.meta.recovered.split("samples up to tick ")[1].split()[0])
    assert 400 <= newest <= 501, run.meta.recovered  # within a second (100 ticks) of the kill, none after it
    ticks = slice(0, newest - 100)
    assert np.isfinite(run.xi[ticks]).all() and np.isfinite(run.leader_p[ticks]).all()
    assert (run.safety.plant_mode[ticks] == wire.FLYING).all()
    assert np.isnan(run.xi[newest + 1:]).all()
    if (out / "run.mcap").exists():
        from mcap.reader import make_reader

        with open(out / "run.mcap", "rb") as fh:
            agent1 = sum(1 for _ in make_reader(fh).iter_messages(topics=["/agent/1"]))
        heard = np.isfinite(run.leader_p).all(axis=1) | (run.safety.safety_mode != -1).any(axis=1)
        assert agent1 == int(heard.sum())


@pytest.mark.slow  # real processes
def test_every_process_killed_at_once_leaves_a_journal_up_to_the_last_second(tmp_path: Path) -> None:
    """The launcher and every process of the run SIGKILLed at once (as a machine that stops): nobody
    writes a run file; the journal holds every tick taken up to within a second of the kill."""
    out, log, proc = start_lockstep(tmp_path)
    try:
        wait_until(lambda: "processes are up" in log.read_text(), 120, "every process up", proc)  # type: ignore[arg-type]
        wait_until(lambda: (out / journal.NAME).exists() and (out / journal.NAME).stat().st_size > 300_000,
                 120, "a journal of a few seconds of mission", proc)  # type: ignore[arg-type]
        pids = [proc.pid, *descendants(proc.pid)]  # type: ignore[attr-defined]
        killed = time.time_ns()
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.communicate(timeout=30)  # type: ignore[attr-defined]
        wait_until(lambda: not any(alive(p) for p in pids), 30, "every process gone")
    finally:
        kill(proc)  # type: ignore[arg-type]
    check_journal(out, killed)


@pytest.mark.slow  # real processes
def test_a_launcher_killed_mid_run_leaves_a_run_file_of_every_tick_taken(tmp_path: Path) -> None:
    """The launcher alone SIGKILLed: the processes see it gone and stop; the recorder writes
    ``run.npz`` of every tick it took (incomplete, nothing after the last), then removes its journal."""
    out, log, proc = start_lockstep(tmp_path)
    try:
        wait_until(lambda: "processes are up" in log.read_text(), 120, "every process up", proc)  # type: ignore[arg-type]
        wait_until(lambda: (out / journal.NAME).exists() and (out / journal.NAME).stat().st_size > 300_000,
                 120, "a journal of a few seconds of mission", proc)  # type: ignore[arg-type]
        children = descendants(proc.pid)  # type: ignore[attr-defined]
        os.kill(proc.pid, signal.SIGKILL)  # type: ignore[attr-defined]
        proc.communicate(timeout=30)  # type: ignore[attr-defined]
        wait_until(lambda: not any(alive(p) for p in children), 120, "the launcher's processes stopping")
    finally:
        kill(proc)  # type: ignore[arg-type]
        for pid in descendants(os.getpid()):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    run = journal.load(out, report=lambda line: None)
    assert not (out / journal.NAME).exists(), "the journal stays only while the run file is not written"
    assert run.meta.complete is False and run.meta.recovered is None
    heard = np.flatnonzero(np.isfinite(run.xi[:, :, 0]).all(axis=1))
    assert len(heard) > 100 and np.array_equal(heard, np.arange(len(heard))), "every tick up to the last"
    assert (run.safety.safety_mode[len(heard):] == -1).all(), "nothing claimed after the last tick heard"


@pytest.mark.slow
def test_tether_mcap_and_plot_read_a_killed_recorders_journal_and_say_what_is_missing(tmp_path: Path) -> None:
    """The commands a user runs next, on the directory a killed recorder left (no run.npz, a journal
    cut mid-chunk): each reads what the journal holds, says what is missing and writes its files."""
    import subprocess
    import sys

    path, _ = _journal_of(tmp_path, chunks=3, per_chunk=50)
    run_dir = tmp_path / "killed"
    run_dir.mkdir(mode=0o700)
    data = path.read_bytes()
    (run_dir / journal.NAME).write_bytes(data[:len(data) - 7])  # cut inside the last chunk
    for command, made in (("mcap", "run.mcap"), ("plot", "formation_error.png")):
        done = subprocess.run([sys.executable, "-m", "cli", command, str(run_dir)], capture_output=True, text=True,
                              timeout=300)
        assert done.returncode == 0, done.stderr
        assert "missing: recovered: from the recorder's journal" in done.stdout, done.stdout
        assert any(line.startswith("missing: leader:") for line in done.stdout.splitlines()), done.stdout
        assert (run_dir / made).exists() or any(run_dir.glob("*.png")), sorted(p.name for p in run_dir.iterdir())


def test_a_journal_flushes_every_second_of_mission_time_however_fast_the_run(tmp_path: Path) -> None:
    """A lockstep run can take many mission seconds within one wall second: the first message at or
    past each whole second of mission time closes a chunk itself, so a cut loses at most one mission
    second too; a non-finite sample time flushes nothing and raises nothing."""
    j = journal.Journal.create(tmp_path, journal.Header(mission="section4", mission_text="", namespace="t",
                                                        duration=10.0, lockstep=True, started_ns=0),
                               now_ns=lambda: 0)
    before = j.flushes
    for k in range(350):  # 3.5 s of mission time at once, no wall time passing
        j.add(wire.State(sender=1, seq=k, k=k, t=0.01 * k, p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0]))
    assert j.flushes - before == 3  # at t = 1.00, 2.00 and 3.00 s
    j.add(wire.State(sender=1, seq=350, k=350, t=float("nan"), p=[0.0, 0.0], vel=[0.0, 0.0], a=[0.0, 0.0]))
    assert j.flushes - before == 3 and not j.closed
    got = journal.read(j.path)
    assert len(got.messages) == 301 and got.messages[-1].t == 3.0  # up to the last whole second's first message
