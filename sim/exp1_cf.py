"""Figures of merit of recorded runs of a mission, one table row per run:
``python -m sim.exp1_cf MISSION LABEL=DIR [LABEL=DIR ...]`` prints a Markdown table (the definitions
of :func:`sim.experiments.summary`). Used for ``docs/results/exp1-cf.md``: Experiment 1 flown with
``tether run exp1_cf --sitl`` with and without estimator noise."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from sim.experiments import summary
from tether import catalog
from tether import mission as ms
from tether.runfile import Run

COLUMNS = ("formation_reached_s", "settling_time_s", "ultimate_bound_xi_m", "peak_kp", "peak_kv",
           "final_kp_mean", "final_kv_mean", "tracking_error_tail_m")


def _fmt(x: object) -> str:
    if isinstance(x, float):
        return "n/a" if math.isnan(x) else f"{x:.3g}"
    return str(x)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m sim.exp1_cf", description=__doc__.split("\n")[0])
    ap.add_argument("mission")
    ap.add_argument("runs", nargs="+", metavar="LABEL=DIR")
    args = ap.parse_args(argv)
    m = ms.load(catalog.resolve(args.mission))
    print("| run | samples | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 2) + "|")
    for item in args.runs:
        label, _, d = item.partition("=")
        run = Run.load(Path(d))
        s = summary(m, run)
        have = float(np.mean(np.isfinite(run.p[:, :, 0])))
        print(f"| {label} | {have:.1%} | " + " | ".join(_fmt(s[c]) for c in COLUMNS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
