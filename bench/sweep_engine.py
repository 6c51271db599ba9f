"""How much faster the in-process lockstep engine (sim/lockstep.py, what ``tether sweep`` runs by
default) is than the distributed lockstep runtime (``tether run``) on the same mission, and that the
two still agree bit for bit. Prints medians of ``--repeats`` runs of each, measured in one go.

    python bench/sweep_engine.py [--duration 20] [--repeats 3] [--profile lossy-burst]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sim import lockstep
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0, help="mission time per run [s]")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--profile", default="lossy-burst", help="the [netem] default of every link")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.toml"
        path.write_text(builtin_path("section4").read_text() + f'\n[netem]\ndefault = "{args.profile}"\n')
        m = load_mission(path, args.duration)
        inproc, runtime = [], []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            want = lockstep.simulate(m)
            inproc.append(time.perf_counter() - t0)
            out = Path(tmp) / f"run{r}"
            t0 = time.perf_counter()
            done = subprocess.run([sys.executable, "-m", "cli", "run", str(path), "--out", str(out),
                                   "--duration", str(args.duration), "--quiet"], capture_output=True, text=True)
            runtime.append(time.perf_counter() - t0)
            if done.returncode != 0:
                print(done.stderr[-2000:], file=sys.stderr)
                return 1
            got = Run.load(out)
            same = all(np.array_equal(getattr(got, f), getattr(want, f)) for f in ("p", "u", "xi", "kp", "kv"))
            if not same:
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


if __name__ == "__main__":
    sys.exit(main())
