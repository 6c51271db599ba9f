"""A rehearsal at scale: N agents, two vehicles a host, every host its own network namespace.

    sudo python bench/rehearse_scale.py [--agents 16] [--per-host 2] [--rate 50] [--duration 25] [--runs 1]
                                        [--keep DIR]

Each run writes a ring mission of ``--agents`` (``bench/missions.py``), a hosts file that puts the
router, the leader and the recorder on a ground station (10.77.0.1) and ``--per-host`` vehicles
(agent and plant each) on each companion computer (10.77.0.11, .12, ...), generates the deployment
(``deploy.gen``), rehearses it in real time (``tether rehearse --duration``) and prints one table row:
exit status, the events of ``events.json``, the formation-error envelope over the last half against
the lockstep reference of the same mission (``sim.refsim``), samples recorded of those expected, the
start-up time (the rehearsal's start to tick 0, and of it the router, the units' start and the wait of
``tether-start`` for every process), the wall time, and the whole machine's CPU (cores' worth, from
``/proc/stat``) and peak load average over the run; then, on stderr, the CPU the units used by role
(agents, plants, recorder, router, leader), read from ``/proc`` each second. Needs root (network namespaces), as the rehearsal.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench import missions  # noqa: E402
from bench.procstat import CLK_TCK, children_of, cmdline, cpu_times, machine_jiffies  # noqa: E402
from tests.factories import build  # noqa: E402
from tests.support import log_time  # noqa: E402

LIFT = 4.0
"""Height [m] every start position of the ring mission is raised by: its transient dips up to 2.7 m
below the start (Exp. 1's gains, the sinusoidal disturbances), and a 3D vehicle stops on the ground
(``safety.ground = 0``); raising the leader and every agent alike leaves the formation error as it is."""
GROUND = "10.77.0.1"
"""The ground station's address (router, leader, recorder)."""


def host_of(agent: int, per_host: int) -> str:
    """The companion computer's address of ``agent`` (1-based): ``per_host`` agents a host."""
    return f"10.77.0.{11 + (agent - 1) // per_host}"


def hosts_file(n: int, per_host: int, deploy: Path, recorder_out: Path) -> str:
    """The hosts file (TOML) of ``n`` agents, ``per_host`` a machine, the ground station at
    :data:`GROUND`; ``config_dir`` is each host directory under ``deploy`` (the rehearsal runs the
    units where they were generated)."""
    lines = ["version = 1", f"config_dir = {json.dumps(str(deploy / 'hosts' / '{host}'))}",
             'tether = "/opt/tether/venv/bin/tether"', 'python = "/opt/tether/venv/bin/python"',
             f'[router]\naddress = "{GROUND}"', f'[leader]\naddress = "{GROUND}"',
             f'[recorder]\naddress = "{GROUND}"\nout = {json.dumps(str(recorder_out))}']
    lines += [f'[[agents]]\nid = {i}\naddress = "{host_of(i, per_host)}"' for i in range(1, n + 1)]
    return "\n".join(lines) + "\n"


def prepare(tmp: Path, n: int, per_host: int, rate: float, duration: float) -> tuple[Path, Path]:
    """Write the mission and the hosts file under ``tmp`` and generate the deployment; returns the
    mission's path and the deployment's directory."""
    from deploy import gen

    tmp.mkdir(parents=True, exist_ok=True)
    mission = tmp / f"ring{n}.toml"
    raw = missions.mission_dict(n, rate=rate, duration=duration, name=f"ring{n}")
    for body in (raw["leader"], *raw["agents"]):
        body["p0"] = [*body["p0"][:2], body["p0"][2] + LIFT]
    build(raw)  # the project's strict decoder and validator
    mission.write_text(missions.to_toml(raw))
    out = tmp / "deploy"
    hosts = tmp / "hosts.toml"
    hosts.write_text(hosts_file(n, per_host, out, tmp / "recorder-out"))
    gen.generate(mission, out, hosts=hosts)
    return mission, out


def first(pattern: str, text: str) -> float | None:
    """Time of the first log record matching ``pattern``, or None."""
    m = re.search(rf"^(.*{pattern}.*)$", text, re.M)
    return log_time(m.group(1)) if m else None


@dataclass
class Row:
    status: int
    events: int
    failsafes: int
    envelope: float
    reference: float
    recorded: int
    expected: int
    router_up: float
    units_up: float
    tick0: float
    wall: float
    cores: float
    load_peak: float
    by_role: dict[str, float]

    def line(self) -> str:
        return (f"| {self.status} | {self.events} ({self.failsafes} failsafes) | {self.envelope:.3f} | "
                f"{self.reference:.3f} | {self.recorded}/{self.expected} "
                f"({100 * (1 - self.recorded / max(self.expected, 1)):.2f} % lost) | {self.tick0:.1f} "
                f"({self.router_up:.1f} / {self.units_up:.1f}) | {self.wall:.0f} | {self.cores:.2f} | "
                f"{self.load_peak:.0f} |")

    def cpu(self) -> str:
        """CPU [s] the units used, summed by role."""
        ranked = sorted(self.by_role.items(), key=lambda kv: -kv[1])
        return "units' CPU [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in ranked)


HEADER = ("| exit | events | envelope, last half [m] | lockstep [m] | samples recorded | start-up to tick 0 [s] "
          "(router up / units started) | wall [s] | machine CPU [cores] | peak load |\n"
          "|---|---|---|---|---|---|---|---|---|")


def envelope(xi: np.ndarray, t: np.ndarray, since: float) -> float:
    """max over agents and ticks t_k >= ``since`` of ||xi_i(t_k)|| [m]."""
    return float(np.nanmax(np.linalg.norm(xi[t >= since - 1e-9], axis=-1)))


def role(argv: list[str]) -> str:
    """What a rehearsed unit's process is: agent, plant, leader, recorder, router or other (the start tool)."""
    if "deploy.router" in argv:
        return "router"
    after = argv[argv.index("cli") + 1:] if "cli" in argv else []
    return after[0] if after and after[0] in ("agent", "plant", "leader", "recorder") else "other"


def rehearse(deploy: Path, run: Path, duration: float, log: Path,
             timeout: float) -> tuple[int, float, float, float, dict[str, float]]:
    """``tether rehearse`` to its end; (exit status, wall [s], machine CPU [cores], peak 1-min load,
    CPU [s] of the units by role, read from ``/proc`` every second)."""
    peak = [os.getloadavg()[0]]
    cpu: dict[int, tuple[str, float]] = {}
    done = threading.Event()

    def watch(pid: int) -> None:
        while not done.wait(1.0):
            peak[0] = max(peak[0], os.getloadavg()[0])
            for child in children_of(pid):
                if (times := cpu_times(child)) is not None:
                    name = cpu[child][0] if child in cpu else role(cmdline(child))
                    cpu[child] = (name, sum(times))

    b0, _ = machine_jiffies()
    t0 = time.monotonic()
    with open(log, "wb") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "cli", "rehearse", str(deploy), "--out", str(run),
                                 "--duration", repr(duration), "--timeout", repr(timeout)], cwd=ROOT,
                                stdin=subprocess.DEVNULL, stdout=fh, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONPATH=str(ROOT)))
        watcher = threading.Thread(target=watch, args=(proc.pid,), daemon=True)
        watcher.start()
        status = proc.wait()
    wall = time.monotonic() - t0
    b1, _ = machine_jiffies()
    done.set()
    watcher.join()
    by_role: dict[str, float] = {}
    for name, seconds in cpu.values():
        by_role[name] = by_role.get(name, 0.0) + seconds
    return status, wall, (b1 - b0) / CLK_TCK / wall, peak[0], by_role


def one(tmp: Path, n: int, per_host: int, rate: float, duration: float, timeout: float) -> Row:
    from sim import refsim
    from tether.node import load_mission
    from tether.runfile import Run

    mission, deploy = prepare(tmp, n, per_host, rate, duration)
    run = tmp / "run"
    log = tmp / "rehearse.log"
    started = time.time()
    status, wall, cores, peak, by_role = rehearse(deploy, run, duration, log, timeout)
    text = log.read_text()
    if not (run / "run.npz").exists():
        raise SystemExit(f"no run file (exit {status}):\n{text[-3000:]}")
    r = Run.load(run)
    ref = refsim.simulate(load_mission(mission, duration))
    events = json.loads((run / "events.json").read_text())
    tick0 = re.search(r"real time: tick 0 at ([0-9.]+)", (run / "logs" / "tether-agent-1.log").read_text())
    return Row(status=status, events=len(events), failsafes=sum(e["what"] == "failsafe" for e in events),
               envelope=envelope(r.xi, r.t, duration / 2), reference=envelope(ref.xi, ref.t, duration / 2),
               recorded=int(r.meta.samples_recorded or 0), expected=int(r.meta.samples_expected or 0),
               router_up=(first("router up", text) or started) - started,
               units_up=(first("units started", text) or started) - started,
               tick0=(float(tick0.group(1)) if tick0 else started) - started, wall=wall, cores=cores,
               load_peak=peak, by_role=by_role)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--agents", type=int, default=16)
    ap.add_argument("--per-host", type=int, default=2)
    ap.add_argument("--rate", type=float, default=50.0)
    ap.add_argument("--duration", type=float, default=25.0)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=240.0)
    ap.add_argument("--keep", type=Path, default=None, help="keep every run's directory under DIR")
    a = ap.parse_args()
    hosts = -(-a.agents // a.per_host)
    print(f"{a.agents} agents on {hosts} hosts ({a.per_host} a host) and a ground station, {a.rate:g} Hz, "
          f"{a.duration:g} s; load average before: {os.getloadavg()[0]:.1f}")
    print(HEADER)
    for k in range(a.runs):
        with tempfile.TemporaryDirectory(prefix="rehearse-scale-") as d:
            tmp = Path(d) if a.keep is None else a.keep / f"run{k}"
            tmp.mkdir(parents=True, exist_ok=True)
            row = one(tmp, a.agents, a.per_host, a.rate, a.duration, a.timeout)
            print(row.line(), flush=True)
            print(row.cpu(), file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
