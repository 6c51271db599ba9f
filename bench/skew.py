"""What a clock skew does to a formation: real-time runs of one mission, one host's clock offset.

    python bench/skew.py [--mission section4] [--duration 20] [--vehicle 2] [--skews 0,1,10,50,200] [--out DIR]

For each skew S [ms], ``tether run MISSION --clock realtime`` with vehicle V's agent and plant
(its companion computer) both ``--fault skew:...=+S/1000``; prints one row per run, beside the
unskewed run of the same invocation: the formation-error envelope max ||xi_i|| [m] over the last
half of the run (as the agents computed it) and over the whole run, the plausibility gate's
rejections by reason, the safety supervisor's mode changes, the offset bounds the agents
estimated on the links into and out of vehicle V (tether/skew.py; median over the last half), and
the launcher's exit status. Real time on a shared machine: figures vary by a few per cent between
runs; each row is one run.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tether.runfile import Run  # noqa: E402
from tether.wire import MODES  # noqa: E402


def one(mission: str, duration: float, vehicle: int, skew_ms: float, out: Path) -> dict:
    cmd = [sys.executable, "-m", "cli", "run", mission, "--clock", "realtime", "--duration", repr(duration),
           "--out", str(out), "--quiet"]
    if skew_ms:
        s = f"{skew_ms / 1000:+g}"
        cmd += ["--fault", f"skew:agent/{vehicle}={s}", "--fault", f"skew:plant/{vehicle}={s}"]
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)))
    run = Run.load(out)
    half = run.t >= duration / 2 - 1e-9
    norm = np.linalg.norm(run.xi, axis=-1)
    gate: dict[str, int] = {}
    if run.safety.gate_counts is not None and run.safety.gate_reasons is not None:
        for r, n in zip(run.safety.gate_reasons, run.safety.gate_counts.sum(axis=0)):
            if n:
                gate[str(r)] = int(n)
    events = [f"{e.vehicle}:{MODES[e.dst]}@{e.t:.1f}" for e in run.safety.events]
    offsets = {}
    if run.clock is not None:
        for i, aid in enumerate(run.agent_ids):
            for slot in range(run.clock.src.shape[1]):
                role, src = str(run.clock.role[i, slot]), int(run.clock.src[i, slot])
                if not role:
                    continue
                if int(aid) == vehicle or (role == "agent" and src == vehicle):
                    vals = run.clock.offset[half, i, slot]
                    if np.isfinite(vals).any():
                        offsets[f"{role}/{src}->{aid}"] = 1000 * float(np.nanmedian(vals))
    return {"skew_ms": skew_ms, "status": done.returncode, "xi_late": float(np.nanmax(norm[half])),
            "xi_all": float(np.nanmax(norm)), "gate": gate, "events": events, "offsets": offsets}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mission", default="section4")
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--vehicle", type=int, default=2)
    p.add_argument("--skews", default="0,1,10,50,200", help="ms, comma-separated (0: the baseline)")
    p.add_argument("--out", default=None)
    a = p.parse_args()
    root = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="tether-skew-"))
    rows = []
    for s in [float(x) for x in a.skews.split(",")]:
        r = one(a.mission, a.duration, a.vehicle, s, root / f"skew-{s:g}ms")
        rows.append(r)
        print(f"skew {s:g} ms: status {r['status']}, max|xi| last half {r['xi_late']:.4f} m, whole run "
              f"{r['xi_all']:.4f} m, gate {r['gate']}, events {r['events']}, offsets "
              + ", ".join(f"{k} {v:+.1f} ms" for k, v in r["offsets"].items()), flush=True)
    print("\n| skew of vehicle %d's host | max ‖ξ‖, last half [m] | whole run [m] | gate rejections | "
          "supervisor events | offset bounds on its links [ms] | exit |" % a.vehicle)
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['skew_ms']:g} ms | {r['xi_late']:.4f} | {r['xi_all']:.4f} | "
              f"{', '.join(f'{k} {v}' for k, v in r['gate'].items()) or '0'} | {', '.join(r['events']) or '–'} | "
              f"{', '.join(f'{k} {v:+.1f}' for k, v in r['offsets'].items())} | {r['status']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
