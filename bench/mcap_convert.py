"""What converting a run file to ``run.mcap`` costs: CPU seconds and file size, median of repeats.

    .venv/bin/python bench/mcap_convert.py RUN_DIR [--repeats 3] [--scene-rate 25]

CPU time (``time.process_time``) rather than wall time, since the shared machine's load changes from
one conversion to the next. Run it under two checkouts (``PYTHONPATH=CHECKOUT``) on the same run
file to compare them; it prints one line per repeat and the medians.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from recorder import viz
from tether.runfile import Run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a run directory or run.npz")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scene-rate", type=float, default=viz.SCENE_RATE)
    a = ap.parse_args()
    run = Run.load(a.run)
    cpu, size = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for n in range(a.repeats):
            t0 = time.process_time()
            path = viz.write_mcap(run, None, Path(tmp) / "run.mcap", scene_rate=a.scene_rate)
            cpu.append(time.process_time() - t0)
            size.append(path.stat().st_size)
            print(f"repeat {n + 1}: {cpu[-1]:.2f} s CPU, {size[-1] / 2**20:.1f} MiB")
    ticks, agents = len(run.t), len(run.agent_ids)
    print(f"{ticks} ticks, {agents} agents: median {statistics.median(cpu):.2f} s CPU, "
          f"{statistics.median(size) / 2**20:.1f} MiB ({statistics.median(size) / (ticks / run.meta.rate * agents) / 1024:.1f} "
          "KiB per agent-second)")


if __name__ == "__main__":
    main()
