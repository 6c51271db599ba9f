"""Which samples real-time runs lose, run by run: ``tether run MISSION --clock realtime`` repeated, each
run's exit status, samples recorded of those expected, and where the missing ones are (an agent's
telemetry, a plant's state; at which tick, of which agent), optionally beside a base commit's build
run by run, alternating.

    python bench/lost_samples.py [--agents 16] [--rate 50] [--duration 15] [--runs 5] [--base e7c6170]
                                 [--mission FILE] [--insecure] [-- tether run options, e.g. --shared-plants]

The mission is a ring of ``--agents`` (``bench/missions.py``) unless ``--mission`` names one. ``--base
REV``: that commit, checked out in a temporary ``git worktree`` (removed afterwards; this tree too, as it
is: ``bench/worktree.py``), runs first in each pair, so that both builds see the same machine. A run's missing telemetry shows as NaN ``xi`` in its run
file, a missing plant sample as NaN ``d`` (only the plant's own sample carries the disturbance), a
missing leader sample as NaN ``leader_p``. ``--keep DIR`` keeps every run's directory (logs, run file). What
a run at N = 16 on two cores loses is small and varies from run to run: quote the counts of every run.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import worktree  # noqa: E402

CHILD = r"""
import json, sys
import numpy as np
from tether.runfile import Run
r = Run.load(sys.argv[1])
out = {"recorded": int(r.meta.samples_recorded), "expected": int(r.meta.samples_expected), "missing": []}
for k in np.flatnonzero(np.isnan(r.leader_p[:, 0])).tolist():
    out["missing"].append(["leader state", int(k), 0])  # 0: no agent
for field, what in (("xi", "telemetry"), ("d", "plant state")):
    for k, i in np.argwhere(np.isnan(getattr(r, field)[..., 0])).tolist():
        out["missing"].append([what, int(k), int(r.agent_ids[i])])
print(json.dumps(out))
"""


def one(tree: Path, mission: Path, out: Path, duration: float, insecure: bool, extra: tuple[str, ...] = ()) -> dict:
    """One real-time run of ``mission`` by the build in ``tree`` (``extra``: more ``tether run``
    options); its exit status and what it lost."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "cli", "run", str(mission), "--clock", "realtime", "--duration", repr(duration),
           "--out", str(out), "--quiet", *(["--insecure"] if insecure else []), *extra]
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if not (out / "run.npz").exists():
        raise SystemExit(f"no run file from {tree} (exit {done.returncode}):\n{done.stderr[-3000:]}")
    read = subprocess.run([sys.executable, "-c", CHILD, str(out)], cwd=tree, env=env, capture_output=True,
                          text=True, check=True)
    return {"status": done.returncode, **json.loads(read.stdout.strip().splitlines()[-1])}


def describe(res: dict) -> str:
    lost = res["expected"] - res["recorded"]
    kinds = collections.Counter(w for w, _, _ in res["missing"])
    where = ", ".join(f"{w} k={k}" + (f" agent {a}" if a else "") for w, k, a in res["missing"][:6])
    more = "" if len(res["missing"]) <= 6 else f", ... ({len(res['missing'])} in all)"
    return (f"exit {res['status']}; lost {lost} of {res['expected']}"
            + (f" ({', '.join(f'{n} {w}' for w, n in kinds.items())}: {where}{more})" if lost else ""))


def main() -> None:
    argv = sys.argv[1:]
    extra: tuple[str, ...] = ()
    if "--" in argv:  # what follows goes to every run's tether run (e.g. -- --shared-plants)
        at = argv.index("--")
        argv, extra = argv[:at], tuple(argv[at + 1:])
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog="options after -- go to every tether run")
    ap.add_argument("--agents", type=int, default=16)
    ap.add_argument("--rate", type=float, default=50.0)
    ap.add_argument("--duration", type=float, default=15.0)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--mission", type=Path, default=None, help="a mission file (default: a ring of --agents)")
    ap.add_argument("--base", default=None, help="a commit whose build runs beside this one, run by run")
    ap.add_argument("--keep", type=Path, default=None, help="keep every run's directory here (logs, run file)")
    ap.add_argument("--insecure", action="store_true", help="runs without mTLS and access rules")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="tether-lost-") as tmp:
        work = Path(tmp)
        mission = args.mission
        if mission is None:
            mission = work / "ring.toml"
            subprocess.run([sys.executable, str(ROOT / "bench" / "missions.py"), str(args.agents), "--rate",
                            repr(args.rate), "--duration", repr(args.duration), "--out", str(mission)], check=True,
                           capture_output=True)
        with contextlib.ExitStack() as stack:
            trees = [("this", ROOT)]
            if args.base is not None:  # both builds from checkouts of the same kind (bench/worktree.py)
                trees = [(args.base, stack.enter_context(worktree.checked_out(args.base, work / "base"))),
                         ("this", stack.enter_context(worktree.checked_out(None, work / "this")))]
            print(f"{mission.name}: {args.runs} real-time runs of {args.duration:g} s per build; load average "
                  f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
            totals: dict[str, list[int]] = {name: [] for name, _ in trees}
            for run in range(1, args.runs + 1):
                for name, tree in trees:
                    out = (args.keep or work) / f"{name}-{run}"
                    res = one(tree, mission.resolve(), out, args.duration, args.insecure, extra)
                    totals[name].append(res["expected"] - res["recorded"])
                    print(f"  run {run} {name:>8}: {describe(res)}; load {os.getloadavg()[0]:.1f}", flush=True)
            for name, lost in totals.items():
                print(f"{name:>10}: {sum(1 for x in lost if x == 0)} of {len(lost)} runs lost nothing; "
                      f"lost per run {lost}")


if __name__ == "__main__":
    main()
