"""The first run's wait for the compiler: cold (empty compile caches) against warm starts of
``tether simulate``, ``tether sweep`` (one cell; eight cells on two workers) and ``tether montecarlo``.

    python bench/coldstart.py [--repeats 3] [--what simulate sweep1 sweep8 montecarlo] [--tree DIR]

Each command runs as a fresh process. A cold start gets new, empty ``NUMBA_CACHE_DIR`` and
``TETHER_CACHE`` directories (numba's compiled kernels and the generated law modules); a warm
start reuses directories that one untimed run of the same command filled. Cold and warm runs
alternate, so both see the same machine load. Prints, per command, the median wall and CPU time
(the process and its children) cold and warm and the cold/warm ratio, with the load average.

``--tree DIR``: run the tether source tree at ``DIR`` (e.g. a ``git archive`` of a base commit)
instead of this one, to compare a base with this tree under the same load. ``--after-first``: also
time each command on a cold cache right after ``tether demo`` (the README's first command, which
starts the once-per-machine background compile of :func:`sim.warm.prewarm`): the row ``NAME+demo``.

Figures (one repeat each, a 2-core machine shared at load 9-28, so wall times swing with the load;
CPU time is the figure to compare). "before": the engines without :mod:`sim.warm`; "after": with it.

=============== ====== ================ ================ ===============
command         tree   cold CPU [s]     warm CPU [s]     cold wall [s]
=============== ====== ================ ================ ===============
simulate-short  before 11.6             2.3              128.1 (32.6 warm)
simulate-short  after  4.0              2.5              47.4 (24.0 warm)
sweep8          before 31.9             10.2             188.1 (95.1 warm)
sweep8          after  24.2             10.0             298.7 (45.6 warm)
sweep1          before 16.7             3.9              116.4 (19.6 warm)
sweep1          after  13.9             3.2              32.4 (4.8 warm)
simulate        before 10.9             2.3              54.9 (10.9 warm)
montecarlo      before 17.6             3.2              268.3 (68.6 warm)
montecarlo      after  16.4             2.5              46.6 (3.7 warm)
=============== ====== ================ ================ ===============

A cold single-process run of the full Section 4 still pays one compile (about 9 s of CPU for the
discrete reference kernel, 10 s for the continuous one, 14 s for the lockstep engine: ``python -m
sim.warm --parts PART`` with empty caches); ``python -m sim.warm`` pays it ahead of the first run.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

COMMANDS: dict[str, list[str]] = {
    "simulate": ["simulate", "section4", "--no-figures", "--no-mcap"],
    "simulate-short": ["simulate", "section4", "--no-figures", "--no-mcap", "--duration", "200"],
    "sweep1": ["sweep", "section4", "--loss", "0", "--delay", "0", "--laws", "sigma", "--jobs", "1"],
    "sweep8": ["sweep", "section4", "--loss", "0,10,30,50", "--delay", "0,100", "--laws", "sigma", "--jobs", "2"],
    "montecarlo": ["montecarlo", "section4", "--seeds", "2", "--jobs", "1", "--duration", "10"],
}
"""The timed commands (``tether ARGS --out DIR``)."""


FIRST = ["demo"]
"""The README's first command after installing (``tether demo``): ``--after-first`` times a cold
cache's first study right after it, with the background compile it starts (:func:`sim.warm.prewarm`)."""


def run(tree: Path, args: list[str], cache: Path, out: Path, prewarm: bool = False) -> tuple[float, float]:
    """Run ``tether ARGS --out OUT`` from ``tree`` with its caches under ``cache``; blocks until it
    exits. Returns its wall and CPU time [s] (CPU: user + system of it and the children it waited on;
    a detached background compile is not among them). ``prewarm``: let the command start the
    background compile (off otherwise, so that a cold run is the compile it pays itself)."""
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=str(cache / "numba"),
               TETHER_CACHE=str(cache / "tether"), TETHER_PREWARM="1" if prewarm else "0")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "cli", *args, "--out", str(out)], cwd=tree, env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"tether {' '.join(args)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> None:
    """Parse the command line, run the commands cold and warm in turn, print the medians."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--what", nargs="+", choices=sorted(COMMANDS), default=list(COMMANDS))
    ap.add_argument("--tree", type=Path, default=ROOT, help="the tether source tree to run (default: this one)")
    ap.add_argument("--after-first", action="store_true",
                    help="also time each command on a cold cache right after `tether demo` (the README's first "
                         "command, which starts the background compile)")
    a = ap.parse_args()
    tree = a.tree.resolve()
    print(f"tree {tree}; load average at start {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory(prefix="coldstart-") as tmp:
        base = Path(tmp)
        rows = []
        for what in a.what:
            args = COMMANDS[what]
            warm_cache = base / f"{what}-warm"
            run(tree, args, warm_cache, base / f"prime-{what}")  # fills the warm caches, untimed
            cold: list[tuple[float, float]] = []
            warm: list[tuple[float, float]] = []
            first: list[tuple[float, float]] = []
            loads: list[float] = []
            for r in range(a.repeats):
                loads.append(os.getloadavg()[0])
                cold.append(run(tree, args, base / f"{what}-cold-{r}", base / f"o-{what}-c{r}"))
                warm.append(run(tree, args, warm_cache, base / f"o-{what}-w{r}"))
                line = (f"  {what} #{r}: cold {cold[-1][0]:.1f} s wall {cold[-1][1]:.1f} s CPU; "
                        f"warm {warm[-1][0]:.1f} s wall {warm[-1][1]:.1f} s CPU")
                if a.after_first:
                    fresh = base / f"{what}-first-{r}"
                    demo = run(tree, FIRST, fresh, base / f"o-{what}-d{r}", prewarm=True)
                    first.append(run(tree, args, fresh, base / f"o-{what}-f{r}", prewarm=True))
                    line += (f"; after tether demo ({demo[0]:.1f} s wall): {first[-1][0]:.1f} s wall "
                             f"{first[-1][1]:.1f} s CPU")
                print(line, flush=True)
            cw, cc = (statistics.median(x[i] for x in cold) for i in (0, 1))
            ww, wc = (statistics.median(x[i] for x in warm) for i in (0, 1))
            rows.append((what, cw, ww, cc, wc, statistics.median(loads)))
            if first:
                fw, fc = (statistics.median(x[i] for x in first) for i in (0, 1))
                rows.append((f"{what}+demo", fw, ww, fc, wc, statistics.median(loads)))
        print(f"\n{'command':<11} {'cold wall':>9} {'warm wall':>9} {'ratio':>6} {'cold CPU':>8} {'warm CPU':>8} "
              f"{'ratio':>6} {'load':>5}  (medians of {a.repeats}, seconds)")
        for what, cw, ww, cc, wc, load in rows:
            print(f"{what:<11} {cw:9.1f} {ww:9.1f} {cw / ww:6.1f} {cc:8.1f} {wc:8.1f} {cc / wc:6.1f} {load:5.1f}")


if __name__ == "__main__":
    main()
