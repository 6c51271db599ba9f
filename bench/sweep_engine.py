"""How fast the in-process lockstep engine (sim/lockstep.py, what ``tether sweep`` runs by default) is
on Section 4 degradation-map cells, beside the same engine at a base commit and beside the
distributed lockstep runtime (``tether run``), all measured in one go; and that they agree bit for bit.

    python bench/sweep_engine.py [--duration 20] [--repeats 3] [--cells 0:0 10:50 30:200]
                                 [--base cad57b1] [--engine auto|python|compiled] [--runtime]
                                 [--profile lossy-burst]

* ``--cells LOSS:DELAY ...``: the map cells (loss [%], delay [ms], both laws' sigma law, burst 1)
  built by :func:`sim.sweep.point_mission`, as ``tether sweep section4`` builds them.
* ``--base REV``: the same cells run by the engine of commit ``REV``, checked out in a temporary
  ``git worktree`` (removed afterwards); each repeat runs the base and the current engine in fresh
  processes one after the other, so both see the same machine load. Prints the medians of each
  engine's CPU time and wall time per cell, their ratio, and whether the runs are bit-identical.
* ``--engine``: this tree's engine (``lockstep.simulate(engine=...)``): ``auto`` takes the compiled
  twin (:mod:`sim.lockstep_kernel`) where it applies, ``python`` the agents' own tick. A process's
  first run is timed apart (it loads the compiled engine from numba's cache, or compiles it).
* ``--runtime``: also ``tether run --clock lockstep`` of section4 with ``[netem] default =
  PROFILE`` against the in-process engine (the original comparison of this bench).

The machine may be shared: the CPU-time ratio is the figure to quote; the load average is printed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import worktree  # noqa: E402
FIELDS = ("t", "p", "v", "a", "u", "xi", "zeta", "kp", "kv", "d")

CHILD = r"""
import json, sys, time
import numpy as np
from sim import lockstep, sweep
from tether.catalog import builtin_path
from tether.node import load_mission
cells, duration, out, engine = json.loads(sys.argv[1]), float(sys.argv[2]), sys.argv[3], sys.argv[4]
kw = {} if engine == "auto" else {"engine": engine}  # a base commit may not know the argument
base = load_mission(builtin_path("section4"), duration)
times, arrays = {}, {}
# the first run of a process pays for loading (or compiling) the engine: timed on its own
w0, c0 = time.perf_counter(), time.process_time()
lockstep.simulate(sweep.point_mission(base, sweep.Point("sigma", 10, 50, 1.0), duration=0.1), **kw)
times["first"] = (time.process_time() - c0, time.perf_counter() - w0)
for loss, delay in cells:
    m = sweep.point_mission(base, sweep.Point("sigma", loss, delay, 1.0), duration=duration)
    w0, c0 = time.perf_counter(), time.process_time()
    run = lockstep.simulate(m, **kw)
    times[f"{loss:g}:{delay:g}"] = (time.process_time() - c0, time.perf_counter() - w0)
    for f in %r:
        arrays[f"{loss:g}:{delay:g}/{f}"] = getattr(run, f)
    arrays[f"{loss:g}:{delay:g}/age"] = run.links.age
np.savez(out, **arrays)
print(json.dumps(times))
""" % (FIELDS,)


def child(tree: Path, cells: list[tuple[float, float]], duration: float, out: Path,
          engine: str = "auto") -> dict[str, list[float]]:
    env = {**os.environ, "PYTHONPATH": str(tree), "OPENBLAS_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(cells), str(duration), str(out), engine], cwd=tree,
                          env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"engine at {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def same(a: Path, b: Path) -> bool:
    x, y = np.load(a), np.load(b)
    return sorted(x.files) == sorted(y.files) and all(x[f].tobytes() == y[f].tobytes() for f in x.files)


def cells_vs_base(args: argparse.Namespace, tmp: Path) -> None:
    cells = [(float(c.split(":")[0]), float(c.split(":")[1])) for c in args.cells]
    cur: dict[str, list[tuple[float, float]]] = {}
    old: dict[str, list[tuple[float, float]]] = {}
    identical = True
    with contextlib.ExitStack() as stack:
        base_tree: Path | None = None
        this = ROOT
        if args.base:  # both engines from checkouts of the same kind (bench/worktree.py)
            base_tree = stack.enter_context(worktree.checked_out(args.base, tmp / "base"))
            this = stack.enter_context(worktree.checked_out(None, tmp / "this"))
        for r in range(args.repeats):
            if base_tree is not None:
                for key, tw in child(base_tree, cells, args.duration, tmp / f"base{r}.npz").items():
                    old.setdefault(key, []).append((tw[0], tw[1]))
            for key, tw in child(this, cells, args.duration, tmp / f"cur{r}.npz", args.engine).items():
                cur.setdefault(key, []).append((tw[0], tw[1]))
            if base_tree is not None:
                identical &= same(tmp / f"base{r}.npz", tmp / f"cur{r}.npz")
    ticks = int(round(args.duration * 100)) + 1
    print(f"section4 map cells (sigma law, burst 1), {args.duration:g} s of mission time ({ticks} ticks, 4 agents), "
          f"median of {args.repeats}; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    head = f"{'cell loss%:delay ms':>20} {'CPU s':>8} {'wall s':>8} {'x real time':>12} {'us/tick':>8}"
    print(head + (f" {'base CPU s':>11} {'base wall':>10} {'CPU ratio':>10}" if base_tree is not None else ""))
    ratios = []
    first = cur.pop("first")
    if base_tree is not None:
        base_first = old.pop("first")
    for key in cur:
        c = statistics.median(x[0] for x in cur[key])
        w = statistics.median(x[1] for x in cur[key])
        line = f"{key:>20} {c:8.3f} {w:8.3f} {args.duration / w:12.1f} {c / ticks * 1e6:8.0f}"
        if base_tree is not None:
            bc = statistics.median(x[0] for x in old[key])
            bw = statistics.median(x[1] for x in old[key])
            ratios.append(bc / c)
            line += f" {bc:11.3f} {bw:10.3f} {bc / c:9.2f}x"
        print(line)
    line = f"  a process's first run (0.1 s of mission): CPU {statistics.median(x[0] for x in first):.3f} s"
    if base_tree is not None:
        line += f", base {statistics.median(x[0] for x in base_first):.3f} s"
    print(line + (" (loading the compiled engine from numba's cache, or compiling it)" if args.engine != "python" else ""))
    if base_tree is not None:
        print(f"  CPU ratio, median over cells: {statistics.median(ratios):.2f}x against {args.base}; "
              f"runs bit-identical to the base: {'yes' if identical else 'NO'}")
        if not identical:
            raise SystemExit(1)


def against_runtime(args: argparse.Namespace, tmp: Path) -> int:
    from sim import lockstep
    from tether.catalog import builtin_path
    from tether.node import load_mission
    from tether.runfile import Run

    path = tmp / "m.toml"
    path.write_text(builtin_path("section4").read_text() + f'\n[netem]\ndefault = "{args.profile}"\n')
    m = load_mission(path, args.duration)
    inproc, runtime = [], []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        want = lockstep.simulate(m)
        inproc.append(time.perf_counter() - t0)
        out = tmp / f"run{r}"
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, "-m", "cli", "run", str(path), "--out", str(out),
                               "--duration", str(args.duration), "--quiet"], capture_output=True, text=True)
        runtime.append(time.perf_counter() - t0)
        if done.returncode != 0:
            print(done.stderr[-2000:], file=sys.stderr)
            return 1
        got = Run.load(out)
        if not all(np.array_equal(getattr(got, f), getattr(want, f)) for f in ("p", "u", "xi", "kp", "kv")):
            print("the engines disagree", file=sys.stderr)
            return 1
    a, b = statistics.median(inproc), statistics.median(runtime)
    steps = m.steps + 1
    print(f"section4 + netem {args.profile}, {args.duration:g} s of mission time ({steps} ticks, 4 agents), "
          f"median of {args.repeats}:")
    print(f"  in-process engine   {a:7.2f} s   {args.duration / a:7.1f}x real time   {a / steps * 1e6:6.0f} us/tick")
    print(f"  tether run lockstep {b:7.2f} s   {args.duration / b:7.1f}x real time   (process start-up included)")
    print(f"  ratio               {b / a:7.1f}x   runs bit-identical: yes")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="mission time per run [s]")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--cells", nargs="+", default=["0:0", "10:50", "30:200"], help="LOSS%%:DELAYms map cells")
    ap.add_argument("--base", default=None, help="a commit whose engine to time beside this one (e.g. cad57b1)")
    ap.add_argument("--engine", default="auto", choices=("auto", "python", "compiled"),
                    help="this tree's in-process engine (lockstep.simulate's engine=; the base runs its default)")
    ap.add_argument("--runtime", action="store_true", help="also time tether run (distributed lockstep)")
    ap.add_argument("--profile", default="lossy-burst", help="--runtime: the [netem] default of every link")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        cells_vs_base(args, Path(tmp))
        if args.runtime:
            return against_runtime(args, Path(tmp))
    return 0


if __name__ == "__main__":
    sys.exit(main())
