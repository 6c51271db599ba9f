"""A ground station on a busy host: ``exp1_cf --sitl`` (four software Crazyflies on one simulated
radio, flown from one radio host) beside busy loops, at the normal CPU policy and at the launcher's
default.

    python bench/radio_busy.py [--hogs 8] [--reps 2] [--duration 20] [--priorities 0 default]

Each run: ``--hogs`` busy loops (``python -c 'while ...: pass'``, normal policy, each ending by itself
after the run's bound) start first, then ``tether run exp1_cf --sitl --duration D`` with
``--rt-priority 0`` (every process at the normal policy) or with no option (``default``: the
launcher's own choice, real-time priority where permitted; the simulators, started by the launcher,
inherit it, as the hardware they stand for does not compete for the host). Configurations alternate
run by run. Prints per run: the 1-minute load average at the start, the failsafe mode changes (agents'
supervisors and plants' watchdogs: every one is for nothing, nothing was broken), the vehicles
landed by a failsafe, the vehicles whose link was judged degraded or failed, the simulated radio's lost and dropped
packets, and the launcher's exit status.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def run(priority: str, hogs: int, duration: float) -> dict[str, object]:
    bound = duration + 150.0
    loops = [subprocess.Popen([sys.executable, "-c", f"import time\nt = time.monotonic() + {bound}\n"
                               "while time.monotonic() < t: pass"]) for _ in range(hogs)]
    try:
        time.sleep(2.0)
        load = os.getloadavg()[0]
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "run"
            cmd = [sys.executable, "-m", "cli", "run", "exp1_cf", "--sitl", "--duration", str(duration),
                   "--out", str(out), "--quiet"]
            if priority != "default":
                cmd += ["--rt-priority", priority]
            env = dict(os.environ, PYTHONPATH=str(REPO))
            p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=bound)
            text = p.stdout + p.stderr
            plants = "".join((out / "logs" / f"plant-{i}.log").read_text(errors="replace")
                             for i in range(1, 5) if (out / "logs" / f"plant-{i}.log").exists())
            sim = (out / "logs" / "cfsim-1.log").read_text(errors="replace") if (out / "logs" / "cfsim-1.log").exists() else ""
    finally:
        for h in loops:
            h.kill()
            h.wait()
    failsafes = len(re.findall(r"failsafe: mode \w+ -> (?:HOLD|LAND)", text))
    landed = len(re.findall(r"-> LANDED", text))
    m = re.search(r"radio 0: up \d+ sent, (\d+) lost, (\d+) dropped \(queue\), \d+ attempts; down \d+ sent, (\d+) lost, "
                  r"(\d+) dropped", sim)
    radio = "n/a" if m is None else f"{int(m[1]) + int(m[3])} / {int(m[2]) + int(m[4])}"
    return {"priority": priority, "load": load, "failsafes": failsafes, "landed": landed,
            "degraded": len(set(re.findall(r"crazyflie (\d+): link degraded", plants))),
            "failed": len(set(re.findall(r"crazyflie (\d+): link failed", plants))), "radio": radio,
            "exit": p.returncode}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hogs", type=int, default=8)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--priorities", nargs="+", default=["0", "default"])
    args = ap.parse_args()
    print(f"exp1_cf --sitl, {args.duration:g} s, beside {args.hogs} busy loops, {os.cpu_count()} cores")
    print(f"{'policy':>10} {'load':>5} {'failsafes':>9} {'landed':>6} {'degraded':>8} {'failed':>6} "
          f"{'radio lost/dropped':>18} {'exit':>4}")
    for _ in range(args.reps):
        for prio in args.priorities:
            r = run(prio, args.hogs, args.duration)
            name = "normal" if prio == "0" else prio
            print(f"{name:>10} {r['load']:>5.1f} {r['failsafes']:>9} {r['landed']:>6} {r['degraded']:>8} "
                  f"{r['failed']:>6} {r['radio']:>18} {r['exit']:>4}", flush=True)


if __name__ == "__main__":
    main()
