"""Studies (sim/study.py): the results file, resume, Monte Carlo replicates and statistics, the CLI's
checks, and real executors: a local spawned pool and a Dask scheduler with two workers started as
separate processes on loopback (``dask scheduler`` / ``dask worker``), one of them killed mid-study."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from sim import study, sweep
from tether import mission as ms
from tether.catalog import builtin_path
from tether.node import load_mission
from tests.support import free_port, tether, wait_until

ROOT = Path(__file__).resolve().parents[1]
GRID = {"loss": [0.0, 30.0], "delay": [0.0, 50.0], "burst": [1.0], "laws": ("sigma", "benchmark")}
DURATION = 8.0  # each cell about a second here: long enough to kill a worker in the middle of one


def _main(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    """The ``tether`` command in this process: its exit status and stderr."""
    from cli.main import main

    code = main(list(args))
    return code, capsys.readouterr().err


def _cells(n: int = 3) -> list[study.Cell]:
    m = load_mission(builtin_path("section4"), 1.0)
    return [study.Cell(f"c{i}", ms.dumps(sweep.point_mission(m, sweep.Point("sigma", 0.0, 10.0 * i, 1.0))),
                       "inprocess") for i in range(n)]


# --------------------------------------------------------------------------- the results file
def test_a_truncated_last_line_is_dropped_and_cut_off_and_earlier_cells_kept(tmp_path: Path) -> None:
    cells = _cells()
    key = study.study_key(cells)
    f = study.StudyFile(tmp_path / "study.jsonl")
    assert f.open(key, {}) == {}
    for c in cells[:2]:
        f.append({"digest": c.digest, "cell": c.name, "row": {"x": 1.5}, "worker": "w", "wall_s": 0.1})
    f.close()
    data = (tmp_path / "study.jsonl").read_bytes()
    cut = data[: len(data) - 9]  # the second record cut short by a kill mid-write
    (tmp_path / "study.jsonl").write_bytes(cut)
    done = study.StudyFile(tmp_path / "study.jsonl").open(key, {})
    assert list(done) == [cells[0].digest]
    assert (tmp_path / "study.jsonl").read_bytes() == data[: data.index(b"\n", data.index(b"\n") + 1) + 1]
    # appending after the cut gives whole lines again
    f = study.StudyFile(tmp_path / "study.jsonl")
    f.open(key, {})
    f.append({"digest": cells[1].digest, "cell": "c1", "row": {"x": math.nan}, "worker": "w", "wall_s": 0.1})
    f.close()
    again = study.StudyFile(tmp_path / "study.jsonl").open(key, {})
    assert set(again) == {cells[0].digest, cells[1].digest} and math.isnan(again[cells[1].digest]["row"]["x"])


def test_a_damaged_line_before_the_last_is_an_error_naming_it(tmp_path: Path) -> None:
    cells = _cells()
    key = study.study_key(cells)
    f = study.StudyFile(tmp_path / "study.jsonl")
    f.open(key, {})
    for c in cells:
        f.append({"digest": c.digest, "cell": c.name, "row": {}, "worker": "w", "wall_s": 0.1})
    f.close()
    lines = (tmp_path / "study.jsonl").read_text().splitlines(keepends=True)
    lines[2] = "{garbage\n"
    (tmp_path / "study.jsonl").write_text("".join(lines))
    with pytest.raises(study.StudyError, match="line 3 is damaged"):
        study.StudyFile(tmp_path / "study.jsonl").open(key, {})


def test_another_study_in_the_same_directory_is_refused_and_left_alone(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    cells = _cells()
    f = study.StudyFile(tmp_path / "study.jsonl")
    f.open(study.study_key(cells), {"mission": "section4"})
    f.close()
    other = study.study_key(cells[:2])
    with pytest.raises(study.StudyError, match="holds another study"):
        study.StudyFile(tmp_path / "study.jsonl").check(other)
    before = (tmp_path / "study.jsonl").read_bytes()
    code, err = _main(capsys, "sweep", "section4", "--out", str(tmp_path), "--loss", "0", "--delay", "0",
                      "--duration", "1")
    assert code == 2 and "holds another study" in err and "new --out" in err, err
    assert (tmp_path / "study.jsonl").read_bytes() == before and not (tmp_path / "points").exists()


def test_the_study_key_is_the_set_of_cells_not_their_order() -> None:
    cells = _cells()
    assert study.study_key(cells) == study.study_key(cells[::-1])
    assert study.study_key(cells) != study.study_key(cells[:2])


class _CtrlCWhileWriting(study.StudyFile):
    """A results file that delivers Ctrl-C to this process in the middle of writing its ``at``-th
    cell: after the line is on disk, before the study has counted it."""

    def __init__(self, path: Path, at: int) -> None:
        super().__init__(path)
        self.at, self.writes = at, 0

    def append(self, record: dict) -> None:
        super().append(record)
        self.writes += 1
        if self.writes == self.at:
            signal.raise_signal(signal.SIGINT)


@pytest.mark.parametrize("at", [1, 2])
def test_ctrl_c_while_a_cell_is_written_reports_what_the_file_holds(tmp_path: Path, at: int) -> None:
    """Ctrl-C between a cell's line reaching the disk and the study counting it: the count it
    reports (and the rerun's message) is the file's, never one short."""
    cells = _cells()
    f = _CtrlCWhileWriting(tmp_path / "study.jsonl", at)
    # Python's own Ctrl-C handler, as in a terminal (a test run started in the background without job
    # control inherits SIGINT ignored)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with study.open_executor(None, 1) as engine, pytest.raises(study.StudyInterrupted) as info:
            study.run(cells, f, engine, sweep.run_point, meta={})
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # Python's own handler is back
    finally:
        signal.signal(signal.SIGINT, before)
    kept = len((tmp_path / "study.jsonl").read_text().splitlines()) - 1
    assert kept == at and info.value.done == at and info.value.total == len(cells)


# --------------------------------------------------------------------------- Monte Carlo
def test_a_replicate_is_a_pure_function_of_the_mission_and_its_index() -> None:
    m = load_mission(builtin_path("section4"))
    a, b, c = study.replicate(m, 3, 0.2), study.replicate(m, 3, 0.2), study.replicate(m, 4, 0.2)
    assert ms.dumps(a) == ms.dumps(b) and ms.dumps(a) != ms.dumps(c)
    assert a.seed != m.seed and a.seed != c.seed
    for new, old in zip(a.agents, m.agents):
        assert np.all(np.abs(np.subtract(new.p0, old.p0)) <= 0.2) and new.p0 != old.p0
        assert isinstance(new.disturbance, ms.Sinusoid) and isinstance(old.disturbance, ms.Sinusoid)
        assert new.disturbance.amplitude == old.disturbance.amplitude and new.disturbance.phase != old.disturbance.phase
    assert not ms.validate(a)
    q = load_mission(builtin_path("exp1"))
    r = study.replicate(q, 0, 0.2)
    assert [x.p0[2] for x in r.agents] == [x.p0[2] for x in q.agents]  # vehicles start on the ground
    assert [x.p0[:2] for x in r.agents] != [x.p0[:2] for x in q.agents]


def test_t_quantiles_and_the_interval() -> None:
    scipy_stats = pytest.importorskip("scipy.stats")
    for df in (1, 2, 5, 10, 29, 30, 31, 50, 200, 5000):
        assert study.t975(df) == pytest.approx(float(scipy_stats.t.ppf(0.975, df)), abs=2e-6)
    s = study.stats([1.0, 2.0, 3.0, 4.0, None, math.nan])
    assert s["n"] == 4 and s["mean"] == 2.5 and s["std"] == pytest.approx(math.sqrt(5 / 3))
    half = float(scipy_stats.t.ppf(0.975, 3)) * math.sqrt(5 / 3) / 2
    assert (s["ci_lo"], s["ci_hi"]) == pytest.approx((2.5 - half, 2.5 + half))
    rows = [{"law": "sigma", "x": 1.0, "diverged": False}, {"law": "sigma", "x": 3.0, "diverged": False},
            {"law": "sigma", "x": 99.0, "diverged": True}]
    (row,) = study.summarise(rows, ["law"], ["x"])
    assert row["replicates"] == 3 and row["diverged"] == 1 and row["x_mean"] == 2.0 and row["x_n"] == 2


def test_gain_convergence_time() -> None:
    t = np.arange(0, 100.0, 0.1)
    k = (1.0 + np.exp(-t / 5.0))[:, None, None] * np.ones((1, 2, 2))  # 5 % of the final value at ~5 ln 20
    got = sweep.gain_convergence_time(t, k, k)
    assert got == pytest.approx(5.0 * math.log(1.0 / (0.05 * (1.0 + math.exp(-99.9 / 5.0)))), abs=0.11)
    drifting = (1.0 + 0.1 * t)[:, None, None] * np.ones((1, 2, 2))
    assert math.isnan(sweep.gain_convergence_time(t, drifting, drifting))  # still moving in the tail
    # the sigma law's gains on Section 4: a decay into a 2 % ripple kept up by the disturbances has a
    # time, whatever the phase the run ends on; a ripple wider than the band has none
    for phase in (0.0, 1.0, 2.0):
        ripple = (1.0 + np.exp(-t / 5.0) + 0.02 * np.sin(2.0 * math.pi * t / 6.3 + phase))[:, None, None] \
            * np.ones((1, 2, 2))
        assert 10.0 < sweep.gain_convergence_time(t, ripple, ripple) < 20.0
    wide = (1.0 + 0.2 * np.sin(t))[:, None, None] * np.ones((1, 2, 2))
    assert math.isnan(sweep.gain_convergence_time(t, wide, wide))


# --------------------------------------------------------------------------- the command's checks
@pytest.mark.parametrize("args, message", [
    (["--seeds", "0"], "--seeds: 0 is not >= 1"),
    (["--seeds", "2.5"], "--seeds: '2.5' is not a whole number"),
    (["--seeds", "20001"], "CPU-hours"),
    (["--executor", "http://127.0.0.1:8786"], "--executor: 'http://127.0.0.1:8786' is not a Dask scheduler"),
    (["--executor", "tcp://127.0.0.1:x"], "--executor: 'tcp://127.0.0.1:x' has no HOST:PORT"),
    (["--sigma", "0,1"], "--sigma: 0 is not allowed"),
    (["--sigma", "1", "--laws", "benchmark"], "--sigma: the benchmark law has no sigma"),
    (["--gamma-p", "-1"], "--gamma-p: -1 is out of range"),
    (["--p0-jitter", "0.1"], "--p0-jitter: applies to Monte Carlo replicates only"),
    (["--connect-timeout", "3"], "--connect-timeout: applies to --executor only"),
])
def test_bad_study_options_are_refused_before_anything_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                            args: list[str], message: str) -> None:
    code, err = _main(capsys, "sweep", "section4", "--out", str(tmp_path / "o"), "--duration", "1", *args)
    assert code == 2 and message in err, err
    assert not (tmp_path / "o").exists()


def test_an_executor_that_does_not_answer_is_exit_2_naming_it(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    address = f"tcp://127.0.0.1:{free_port()}"  # nothing listens there
    code, err = _main(capsys, "montecarlo", "section4", "--seeds", "2", "--out", str(tmp_path / "o"),
                      "--executor", address, "--connect-timeout", "1", "--duration", "1")
    assert code == 2, err
    assert f"--executor: no Dask scheduler answered at {address} within 1 s" in err and "dask scheduler" in err
    assert not (tmp_path / "o").exists()


# --------------------------------------------------------------------------- real executors
def _table(out: Path) -> bytes:
    return (out / "sweep.csv").read_bytes()


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The grid on a local pool of two spawned processes."""
    out = tmp_path_factory.mktemp("local")
    sweep.sweep(load_mission(builtin_path("section4")), out, duration=DURATION, jobs=2, **GRID)  # type: ignore[arg-type]
    return _table(out)


class DaskCluster:
    """A scheduler and workers, each its own process group, on loopback."""

    def __init__(self, tmp: Path) -> None:
        self.port = free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.env = {**os.environ, "PYTHONPATH": str(ROOT), "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
        self.tmp = tmp
        self.procs: list[subprocess.Popen] = []
        self.scheduler = self._start(["scheduler", "--host", "127.0.0.1", "--port", str(self.port), "--no-dashboard"],
                                     "scheduler")
        self.workers = [self.start_worker(i) for i in range(2)]

    def _start(self, args: list[str], name: str) -> subprocess.Popen:
        log = open(self.tmp / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "dask", *args], stdout=log, stderr=subprocess.STDOUT,
                             env=self.env, cwd=ROOT, start_new_session=True)
        self.procs.append(p)
        return p

    def start_worker(self, i: int) -> subprocess.Popen:
        return self._start(["worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard",
                            "--name", f"w{i}"], f"worker{i}")

    def kill(self, p: subprocess.Popen) -> None:
        """SIGKILL a process started here and its children (its own process group)."""
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=10)

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.kill(p)


@pytest.fixture
def cluster(tmp_path: Path) -> Iterator[DaskCluster]:
    from distributed import Client

    c = DaskCluster(tmp_path)
    try:
        with Client(c.address, timeout=30, set_as_default=False) as client:
            client.wait_for_workers(2, timeout=45)
        yield c
    finally:
        c.close()


@pytest.mark.slow  # a Dask scheduler and two workers, real processes
def test_the_same_grid_on_dask_is_bit_identical_to_the_local_pool(tmp_path: Path, cluster: DaskCluster,
                                                                   reference: bytes) -> None:
    out = tmp_path / "dask"
    sweep.sweep(load_mission(builtin_path("section4")), out, duration=DURATION, executor=cluster.address, **GRID)  # type: ignore[arg-type]
    assert _table(out) == reference
    meta = json.loads((out / "sweep.json").read_text())["meta"]
    assert meta["executor"] == "dask" and len(meta["per_worker"]) == 2 and sum(meta["per_worker"].values()) == 8


@pytest.mark.slow  # a Dask worker SIGKILLed mid-study
def test_a_killed_workers_cells_are_rerun_and_the_table_is_the_same(tmp_path: Path, cluster: DaskCluster,
                                                                    reference: bytes) -> None:
    from distributed import Client

    out = tmp_path / "dask"
    errors: list[BaseException] = []

    def study_thread() -> None:
        try:
            sweep.sweep(load_mission(builtin_path("section4")), out, duration=DURATION, executor=cluster.address,
                        **GRID)  # type: ignore[arg-type]
        except BaseException as exc:  # reported by the test
            errors.append(exc)

    th = threading.Thread(target=study_thread)
    th.start()
    with Client(cluster.address, timeout=30, set_as_default=False) as client:
        def busy_worker() -> str | None:  # a worker (one thread) with a cell of ours running on it
            for addr, keys in client.processing().items():
                if any("run_cell" in str(k) for k in keys):
                    return addr
            return None

        addr = wait_until(busy_worker, 60, "a cell running on a Dask worker")
        name = client.scheduler_info(n_workers=-1)["workers"][addr]["name"]
    victim = cluster.workers[int(str(name)[1:])]
    cluster.kill(victim)
    th.join(timeout=120)
    assert not th.is_alive() and not errors, errors
    assert _table(out) == reference
    records = [json.loads(x) for x in (out / "study.jsonl").read_text().splitlines()[1:]]
    assert len(records) == 8 and len({r["digest"] for r in records}) == 8


@pytest.mark.slow  # two studies on a local pool
def test_a_study_interrupted_at_half_and_resumed_equals_an_uninterrupted_one(tmp_path: Path, reference: bytes) -> None:
    m = load_mission(builtin_path("section4"))
    out = tmp_path / "resumed"
    with pytest.raises(study.StudyInterrupted) as info:
        sweep.sweep(m, out, duration=DURATION, jobs=2, stop_after=4, **GRID)  # type: ignore[arg-type]
    assert info.value.done == 4 and info.value.total == 8
    sweep.sweep(m, out, duration=DURATION, jobs=2, **GRID)  # type: ignore[arg-type]
    assert _table(out) == reference
    meta = json.loads((out / "sweep.json").read_text())["meta"]
    assert (meta["resumed"], meta["ran_now"]) == (4, 4)


@pytest.mark.slow  # a real `tether sweep` interrupted with SIGINT, then resumed
def test_ctrl_c_keeps_the_finished_cells_and_the_rerun_resumes(tmp_path: Path) -> None:
    out = tmp_path / "s"
    cells = 16  # enough that the interrupt lands before the last; the rerun then runs the rest (~1 s each)
    args = ["sweep", "section4", "--out", str(out), "--loss", ",".join(str(x) for x in range(0, 20, 5)),
            "--delay", "0,50,100,200", "--laws", "sigma", "--duration", str(DURATION), "--jobs", "2"]
    # Ctrl-C's default in the child: a shell that started the tests in the background without job
    # control ignores SIGINT for them, and a Python started with SIGINT ignored keeps ignoring it
    # (the study then ran all its cells and exited 0)
    p = subprocess.Popen([sys.executable, "-m", "cli", *args], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        results = out / "study.jsonl"
        wait_until(lambda: results.exists() and len(results.read_text().splitlines()) >= 2, 90, "a finished cell")
        p.send_signal(signal.SIGINT)
        _, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    kept = len(results.read_text().splitlines()) - 1
    assert 1 <= kept < cells and f"{kept} of {cells} cells done" in err and "run the same command again" in err, err
    r = tether(*args)
    assert r.returncode == 0, r.stderr
    assert f"{cells - kept} run now, {kept} kept from before" in r.stdout, r.stdout


@pytest.mark.slow  # six short runs
def test_montecarlo_writes_mean_spread_and_interval_per_cell_and_the_figure(tmp_path: Path) -> None:
    out = tmp_path / "mc"
    r = tether("montecarlo", "section4", "--seeds", "3", "--delay", "0,50", "--duration", "2", "--jobs", "2",
             "--out", str(out))
    assert r.returncode == 0, r.stderr
    import csv

    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert len(rows) == 6 and sorted({row["rep"] for row in rows}) == ["0", "1", "2"]
    assert len({row["seed"] for row in rows}) == 3  # one seed per replicate, the same in both cells
    summary = list(csv.DictReader(open(out / "summary.csv")))
    assert len(summary) == 2
    for cell in summary:
        values = [float(x["ultimate_bound_m"]) for x in rows if x["delay_ms"] == cell["delay_ms"]]
        s = study.stats(values)
        assert float(cell["ultimate_bound_m_mean"]) == pytest.approx(s["mean"], rel=1e-5)
        assert float(cell["ultimate_bound_m_ci_lo"]) < float(cell["ultimate_bound_m_mean"]) < \
            float(cell["ultimate_bound_m_ci_hi"])
        assert cell["replicates"] == "3" and float(cell["ultimate_bound_m_std"]) > 0
    assert (out / "study.png").stat().st_size > 0 and "95 % Student-t interval" in (out / "sweep.md").read_text()
