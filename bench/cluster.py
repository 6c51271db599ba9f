"""Cells per second of one study on every executor of ``sim/study.py``, the engines' overhead per
cell, and what an interrupted-and-resumed study costs against an uninterrupted one. Prints medians
of ``--repeats`` runs, every executor measured in the same run, and checks that every executor gave
the same rows bit for bit.

    python bench/cluster.py [--cells 8] [--duration 20] [--repeats 3]

Executors: ``inline`` (one process, no pool: the baseline), a local pool of 1 and of 2 spawned
processes, and a Dask scheduler with 2 workers (``dask scheduler`` / ``dask worker``, separate
processes on loopback, started here and stopped at the end). A cell is Section 4 under one network
of the grid (loss x delay) for ``--duration`` s of mission time.

Overhead per cell: ``(wall x workers - cells x one cell's inline run time) / cells``, the time a
worker slot spends on anything but running a cell as fast as inline (process start-up and imports,
transfer, scheduling, idle at the end, and contention for the cores); the
run time of a 1000 s cell follows from the measured cost per simulated second, so the overhead's
share of a 1000 s cell follows too.
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from sim import study, sweep
from tether import mission as ms
from tether.catalog import builtin_path
from tether.node import load_mission

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cells(duration: float, n: int) -> list[study.Cell]:
    m = load_mission(builtin_path("section4"), duration)
    loss = [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0][: max(1, (n + 1) // 2)]
    pts = sweep.points_of(m, loss=loss, delay=[0.0, 50.0], burst=[1.0], laws=["sigma"])[:n]
    return [study.Cell(p.name, ms.dumps(sweep.point_mission(m, p)), "inprocess") for p in pts]


def _run(cells: list[study.Cell], address: str | None, jobs: int, tmp: Path, **kw: int) -> tuple[float, study.Outcome]:
    out = Path(tempfile.mkdtemp(dir=tmp))
    t0 = time.perf_counter()
    with study.open_executor(address, jobs) as eng:
        outcome = study.run(cells, study.StudyFile(out / "study.jsonl"), eng, sweep.run_point, meta={}, **kw)  # type: ignore[arg-type]
    return time.perf_counter() - t0, outcome


def _rows(o: study.Outcome) -> str:
    """The rows as text (every float by its repr: NaN equals NaN here, unlike in a dict compare)."""
    import json

    return json.dumps({d: o.records[d]["row"] for d in sorted(o.records)}, allow_nan=True)


class _Dask:
    def __init__(self, tmp: Path, workers: int) -> None:
        from distributed import Client

        port = _free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        args = [["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]]
        args += [["worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"]] * workers
        self.procs = [subprocess.Popen([sys.executable, "-m", "dask", *a], stdout=subprocess.DEVNULL,
                                       stderr=open(tmp / f"dask{i}.log", "w"), env=env, start_new_session=True)
                      for i, a in enumerate(args)]
        with Client(self.address, timeout=60, set_as_default=False) as c:
            c.wait_for_workers(workers, timeout=60)

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=8)
    ap.add_argument("--duration", type=float, default=20.0, help="mission time per cell [s]")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    cells = _cells(args.duration, args.cells)
    n = len(cells)
    with tempfile.TemporaryDirectory() as td:
        tmp = Path(td)
        dask = _Dask(tmp, 2)
        try:
            modes = {"inline (1 process, no pool)": (None, 1, 1), "local pool, 1 worker": (None, 1, 1),
                     "local pool, 2 workers": (None, 2, 2), "Dask, scheduler + 2 workers": (dask.address, 2, 2)}
            walls: dict[str, list[float]] = {k: [] for k in modes}
            busy: dict[str, list[float]] = {k: [] for k in modes}
            want: str | None = None
            for _ in range(args.repeats):
                for label, (address, jobs, slots) in modes.items():
                    if label.startswith("local pool, 1"):  # a pool of one: force the pool, not inline
                        wall, o = _pool1(cells, tmp)
                    else:
                        wall, o = _run(cells, address, jobs, tmp)
                    rows = _rows(o)
                    if want is None:
                        want = rows
                    elif rows != want:
                        print(f"{label}: rows differ from the inline run", file=sys.stderr)
                        return 1
                    walls[label].append(wall)
                    busy[label].append(sum(r["wall_s"] for r in o.records.values()))
            # interrupted at about half, then resumed, on the local pool of 2
            half = n // 2
            t_full = statistics.median(walls["local pool, 2 workers"])
            out = Path(tempfile.mkdtemp(dir=tmp))
            t0 = time.perf_counter()
            try:
                with study.open_executor(None, 2) as eng:
                    study.run(cells, study.StudyFile(out / "study.jsonl"), eng, sweep.run_point, meta={}, stop_after=half)
            except study.StudyInterrupted as exc:
                first = exc.done
            t_first = time.perf_counter() - t0
            t0 = time.perf_counter()
            with study.open_executor(None, 2) as eng:
                resumed = study.run(cells, study.StudyFile(out / "study.jsonl"), eng, sweep.run_point, meta={})
            t_second = time.perf_counter() - t0
            if _rows(resumed) != want:
                print("the resumed study's rows differ", file=sys.stderr)
                return 1
        finally:
            dask.close()
    per_sim_s = statistics.median(busy["inline (1 process, no pool)"]) / n / args.duration
    print(f"{n} cells of Section 4, {args.duration:g} s of mission time each; medians of {args.repeats}; "
          f"{os.cpu_count()} cores; rows bit-identical on every executor: yes")
    print(f"  one cell runs in {per_sim_s * args.duration:.2f} s inline ({per_sim_s * 1e3:.1f} ms per simulated s; "
          f"a 1000 s cell: {per_sim_s * 1000:.0f} s)")
    print(f"  {'executor':<30} {'wall [s]':>9} {'cells/s':>8} {'overhead/cell [s]':>18} {'of a 1000 s cell':>17}")
    local2 = None
    for label, (_, _, slots) in modes.items():
        w = statistics.median(walls[label])
        over = (w * slots - n * per_sim_s * args.duration) / n
        print(f"  {label:<30} {w:9.2f} {n / w:8.3f} {over:18.3f} {100 * over / (per_sim_s * 1000):16.2f}%")
        if label.startswith("local pool, 2"):
            local2 = w
        if label.startswith("Dask") and local2 is not None:
            extra = (w - local2) * slots / n
            print(f"  Dask against the local pool (2 workers): {extra:+.3f} s per cell, "
                  f"{100 * extra / (per_sim_s * 1000):+.2f}% of a 1000 s cell "
                  f"({100 * extra / (per_sim_s * args.duration):+.1f}% of these {args.duration:g} s cells)")
    print(f"  interrupted after {first} of {n} cells ({t_first:.2f} s), resumed: {resumed.ran} more cells run, "
          f"{resumed.resumed} kept ({t_second:.2f} s); cells run in all {first + resumed.ran} of {n}; "
          f"wall {t_first + t_second:.2f} s against {t_full:.2f} s uninterrupted")
    return 0


def _pool1(cells: list[study.Cell], tmp: Path) -> tuple[float, study.Outcome]:
    """A local pool of exactly one spawned process (``open_executor`` runs ``jobs = 1`` inline)."""
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    out = Path(tempfile.mkdtemp(dir=tmp))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn")) as pool:
        o = study.run(cells, study.StudyFile(out / "study.jsonl"), study.Engine(pool, "local", 1), sweep.run_point, meta={})
    return time.perf_counter() - t0, o


if __name__ == "__main__":
    sys.exit(main())
