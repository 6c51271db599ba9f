"""What recording ``run.mcap`` (and serving the live view) costs, on vs off in the same run.

    .venv/bin/python bench/recording.py                          # lockstep, real time, live, sizes
    .venv/bin/python bench/recording.py --cases lockstep --repeats 5 --duration 200
    .venv/bin/python bench/recording.py --cases realtime live --rt-duration 30

Cases, each run alternately with the feature on and off, ``--repeats`` pairs, medians printed:

1. ``lockstep``: ``tether run section4 --clock lockstep --insecure`` with and without ``--no-mcap``:
   mission seconds per wall second of the whole command (the recorder writes ``run.mcap`` after the
   last tick, before the run ends, so the whole command is what a user waits for), and the
   recorder's CPU for ``run.mcap`` from its log (``recorder CPU: ...``). The sizes of ``run.mcap``
   and ``run.npz`` per agent-second.
2. ``realtime``: the same in real time: the recorder's CPU (recording, ``run.npz``, ``run.mcap``)
   from its log. The cost is the ``run.mcap`` CPU against the recorder's CPU with it off.
3. ``live``: real time with ``--live PORT`` (no viewer connected) against without: the recorder's
   CPU, and the agents' (from ``/proc``, to show the live view adds nothing to them).

The machine is shared: every pair runs back to back, so both sides of a pair see about the same load.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CPU = re.compile(r"recorder CPU: ([0-9.]+) s recording, ([0-9.]+) s run\.npz, ([0-9.]+) s run\.mcap "
                 r"\(wall ([0-9.]+) s, ([0-9.]+) s\); ([0-9.]+) s of start-up")
LIVE = re.compile(r"live view: sent ([0-9]+) ticks in ([0-9.]+) s of CPU")
RAN = re.compile(r"ran ([0-9.]+) s of mission time in ([0-9.]+) s of wall time")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def tether_run(out: Path, clock: str, duration: float, *extra: str, agents_cpu: bool = False) -> dict[str, float]:
    """One ``tether run section4``; its wall time, the recorder's CPU split, file sizes, agents' CPU."""
    cmd = [sys.executable, "-m", "cli", "run", "section4", "--clock", clock, "--duration", repr(duration),
           "--insecure", "--quiet", "--out", str(out), *extra]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            stdin=subprocess.DEVNULL)
    agent_cpu: dict[int, float] = {}
    if agents_cpu:  # sample the agents' CPU (utime + stime) while they run; the last reading stands
        while proc.poll() is None:
            for pid, ticks in _agents(proc.pid).items():
                agent_cpu[pid] = ticks / os.sysconf("SC_CLK_TCK")
            time.sleep(0.5)
    text, _ = proc.communicate(timeout=3600)
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 3, 5):
        raise RuntimeError(f"{' '.join(cmd)}: exit {proc.returncode}\n{text[-2000:]}")
    log = (out / "logs" / "recorder-0.log").read_text()
    cpu = CPU.search(log)
    if cpu is None:
        raise RuntimeError(f"no CPU line in {out / 'logs' / 'recorder-0.log'}")
    ran = RAN.search(text)
    row = {"wall": wall, "rec_cpu": float(cpu[1]), "npz_cpu": float(cpu[2]), "mcap_cpu": float(cpu[3]),
           "npz_wall": float(cpu[4]), "mcap_wall": float(cpu[5]), "startup_cpu": float(cpu[6]),
           "npz": (out / "run.npz").stat().st_size,
           "mcap": (out / "run.mcap").stat().st_size if (out / "run.mcap").exists() else 0.0,
           "stepping": float(ran[2]) if ran else float("nan")}
    if agent_cpu:
        row["agent_cpu"] = statistics.median(agent_cpu.values())
    live = LIVE.search(log)
    if live is not None:
        row["live_ticks"], row["live_cpu"] = float(live[1]), float(live[2])
    return row


def _agents(launcher: int) -> dict[int, int]:
    """CPU ticks of the launcher's agent children, by pid (from /proc)."""
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == launcher and b"agent" in cmdline[3:4]:
            out[int(entry)] = int(fields[11]) + int(fields[12])
    return out


def med(rows: list[dict[str, float]], key: str) -> float:
    return statistics.median(r[key] for r in rows)


def pairs(label: str, repeats: int, on: tuple[str, ...], off: tuple[str, ...], clock: str, duration: float,
          agents_cpu: bool = False) -> tuple[list[dict[str, float]], list[dict[str, float]]]:
    ons: list[dict[str, float]] = []
    offs: list[dict[str, float]] = []
    for r in range(repeats):
        for side, extra, rows in (("on", on, ons), ("off", off, offs)) if r % 2 == 0 else \
                (("off", off, offs), ("on", on, ons)):
            with tempfile.TemporaryDirectory(prefix="tether-bench-rec-") as tmp:
                live = tuple(str(free_port()) if x == "PORT" else x for x in extra)
                row = tether_run(Path(tmp) / "run", clock, duration, *live, agents_cpu=agents_cpu)
            rows.append(row)
            print(f"  {label} {side:>3} #{r + 1}: wall {row['wall']:.2f} s, recorder CPU {row['rec_cpu']:.2f} s "
                  f"+ npz {row['npz_cpu']:.2f} s + mcap {row['mcap_cpu']:.2f} s"
                  + (f", agent CPU {row['agent_cpu']:.2f} s" if "agent_cpu" in row else ""), flush=True)
    return ons, offs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["lockstep", "realtime", "live"],
                    choices=["lockstep", "realtime", "live"])
    ap.add_argument("--repeats", type=int, default=3, help="on/off pairs per case")
    ap.add_argument("--duration", type=float, default=100.0, help="lockstep mission time [s]")
    ap.add_argument("--rt-duration", type=float, default=20.0, help="real-time mission time [s]")
    a = ap.parse_args()
    n = 4  # section4's agents
    if "lockstep" in a.cases:
        print(f"lockstep: tether run section4 --duration {a.duration:g}, run.mcap on vs off (--no-mcap)")
        on, off = pairs("lockstep", a.repeats, (), ("--no-mcap",), "lockstep", a.duration)
        share = [r["mcap_wall"] / (r["stepping"] + r["npz_wall"] + r["mcap_wall"]) for r in on]
        print(f"run.mcap in the same run: written in {med(on, 'mcap_wall'):.2f} s (CPU {med(on, 'mcap_cpu'):.2f} s) after "
              f"{med(on, 'stepping'):.2f} s of stepping and {med(on, 'npz_wall'):.2f} s of run.npz: "
              f"{100 * statistics.median(share):.1f} % of the lockstep run's time (median of {len(on)})")
        s_on, s_off = a.duration / med(on, "wall"), a.duration / med(off, "wall")
        print(f"  whole command, on vs off (start-up included; load differs between runs): {s_on:.2f} vs {s_off:.2f} "
              f"mission s / wall s; stepping alone {med(on, 'stepping'):.2f} s vs {med(off, 'stepping'):.2f} s")
        agent_s = n * a.duration
        print(f"size per agent-second: run.mcap {med(on, 'mcap') / agent_s / 1024:.1f} KiB, "
              f"run.npz {med(on, 'npz') / agent_s / 1024:.1f} KiB (100 Hz; {a.duration:g} s x {n} agents; "
              f"run.mcap / run.npz = {med(on, 'mcap') / med(on, 'npz'):.2f})")
    if "realtime" in a.cases:
        print(f"real time: tether run section4 --clock realtime --duration {a.rt_duration:g}, run.mcap on vs off")
        on, off = pairs("realtime", a.repeats, (), ("--no-mcap",), "realtime", a.rt_duration)
        share = [r["mcap_cpu"] / (r["rec_cpu"] - r["startup_cpu"] + r["npz_cpu"] + r["mcap_cpu"]) for r in on]
        total_on = med(on, "rec_cpu") + med(on, "npz_cpu") + med(on, "mcap_cpu")
        total_off = med(off, "rec_cpu") + med(off, "npz_cpu") + med(off, "mcap_cpu")
        print(f"run.mcap in the same run: {med(on, 'mcap_cpu'):.3f} s of CPU against the recorder's "
              f"{med(on, 'rec_cpu') - med(on, 'startup_cpu'):.2f} s from the start of the run to its end: "
              f"{100 * statistics.median(share):.1f} % (median of {len(on)}; start-up "
              f"{med(on, 'startup_cpu'):.2f} s left out)")
        print(f"  on vs off: recorder CPU {total_on:.2f} s vs {total_off:.2f} s ({100 * (total_on / total_off - 1):+.1f} %; "
              "start-up included, load differs between runs)")
    if "live" in a.cases:
        print(f"live view: tether run section4 --clock realtime --duration {a.rt_duration:g}, --live (no viewer) vs not")
        on, off = pairs("live", a.repeats, ("--live", "PORT", "--no-mcap"), ("--no-mcap",), "realtime", a.rt_duration,
                        agents_cpu=True)
        share = [r["live_cpu"] / (r["rec_cpu"] - r["startup_cpu"]) for r in on]
        print(f"live view in the same run: {med(on, 'live_cpu'):.3f} s of the recorder's "
              f"{med(on, 'rec_cpu') - med(on, 'startup_cpu'):.2f} s of CPU in the run "
              f"to send {med(on, 'live_ticks'):.0f} ticks, {100 * statistics.median(share):.1f} % (median of {len(on)})")
        print(f"  on vs off (load differs between runs): recorder CPU {med(on, 'rec_cpu'):.2f} s vs "
              f"{med(off, 'rec_cpu'):.2f} s; agent CPU (median agent) {med(on, 'agent_cpu'):.2f} s vs "
              f"{med(off, 'agent_cpu'):.2f} s")


if __name__ == "__main__":
    main()
