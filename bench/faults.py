"""The measured fault table of the failsafe mission, and the operator's e-stop / land latency.

    python bench/faults.py                     # default cells x 3 repetitions, then e-stop/land x 5
    python bench/faults.py --quick             # 1 repetition of every cell, e-stop/land x 2
    python bench/faults.py --cells kill:agent/1 forge:leader --reps 5 --at 8 --hold 3
    python bench/faults.py --no-faults --latency-reps 10        # only the latency section
    python bench/faults.py --json /tmp/faults.json               # also keep every figure of every run

Each run is ``tether run failsafe --clock realtime --duration D --quiet --listen tcp/127.0.0.1:P
--fault KIND:TARGET@AT[+HOLD]`` (one launcher, 10 processes). The script itself is a *tap*: a Zenoh
client of the launcher's router (through ``--listen``) that subscribes to the start message, every
agent's ``cmd`` and ``telemetry`` and every plant's ``state``, and stamps each arrival with the wall
clock in the subscriber callback (nothing else is done there). After the run it reads ``run.npz``,
``faults.json``, the plants' logs (``logs/plant-N.log``: the watchdog's own mode changes, with the
command age it acted on) and the launcher's stderr.

Figures (per run; the table prints the median and the 99th percentile over the repetitions — with 3
repetitions p99 is the largest of the three; t_f is the fault's firing time from ``faults.json``,
mission time, and every event time is the tick time ``k h`` of the tick that made it, so a figure is
quantised to h = 20 ms and can read up to one tick *negative*: the tick at 8.00 s ran after the kill
that fired at 8.001 s):

* ``detect`` [s]: first safety event of any vehicle at or after t_f - h/2, minus t_f. Events are the
  agents' supervisor events (``run.safety.events``: mode changes and kappa re-normalisations) and the
  plants' watchdog mode changes (plant logs). For a forge (which by design moves no mode),
  ``detect`` is the first telemetry tick, heard by the tap, whose gate rejection count rose, minus t_f.
  A frozen agent's or plant's own events stamped before the freeze ended are left out of every
  figure: after SIGCONT it runs its missed ticks in a burst, so their tick times are not when they
  ran (a frozen plant's watchdog "holds at 8.50 s" at about 11 s of wall time).
* ``action``: per vehicle, the modes its agent (``a3``) and its plant (``p3``) went through after t_f
  (F FLYING, H HOLD, L LAND, LD LANDED, E ESTOP; ``a3:k`` = agent 3 dropped an edge and re-normalised
  kappa; ``+k`` restored it), union over repetitions.
* ``safe`` [s]: for every vehicle whose agent or plant left FLYING after t_f and had not come back
  to FLYING by the end of the window (it stopped for good), the first instant it left FLYING; the
  largest of those minus t_f (the time until every vehicle that stops has at least begun to hold or
  land). Vehicles that only re-normalised kappa keep flying by design and are not counted; vehicles
  that held and came back (the end of a freeze, or a plant whose agent was starved of CPU for
  cmd_timeout on a loaded machine) are not counted either, but listed as ``transient`` in the
  per-run lines (``H>F`` in ``action``).
* ``xi_surv`` [m]: the true formation error (Eq. 8, ``xi_i = sum_j a_ij ((p_i - h_i) - (p_j - h_j))``,
  leader included, offsets h_i) from the plants' own positions (``plant_p``) over the *surviving*
  graph: at each tick only the vehicles whose agent and plant are both FLYING count, edges from the
  others are removed (as the agents' kappa re-normalisation does; a leader whose sample of the tick
  the recorder lacks counts as gone; a survivor left with no surviving in-edge is left out). Largest ``||xi_i||`` of a survivor
  from t_f to the end of the analysed window; in brackets the same over the 3 s before t_f.
* ``drift`` [m]: for every stretch in which a vehicle's agent or plant is in HOLD or LAND, the largest
  horizontal distance of the vehicle from where it was at the start of that stretch.
* ``sep`` [m]: smallest distance between any two vehicles (plant positions) from t_f on.
* ``fence`` [m]: how far the farthest vehicle went outside the mission's geofence over the whole
  run (0: never left it).
* ``open-loop`` [s]: the longest stretch a plant reported FLYING (``plant_mode``) while the newest
  command of its agent, as heard by the tap, was older than ``cmd_timeout`` at that plant tick (age =
  k h - stamp of the newest command the tap had by the tick instant; the tap is one hop from the
  router, as the plant is, so this is a proxy for what the plant had). In brackets: the largest
  command age a plant's watchdog itself reported when it left FLYING (its log: "no valid command for
  X s"), which is what it flew open-loop before holding. Not observable while a plant's own link is
  cut (partition of a plant: its states do not arrive) — the watchdog's figure then stands alone.
  A frozen plant is a frozen simulator: the simulated vehicle does not move while it is stopped.
* ``forged?``: for a forge only. ``gate`` = samples the agents' plausibility gates rejected over the
  run (``run.safety.gate_counts``, all agents, by reason); ``du`` = the largest command change
  ``||u_k - u_{k-1}||`` of any agent over the 10 ticks from t_f, against the largest over the 3 s
  before (a forged sample that got through would step the command of the agents that hear it by
  about kp * 10^6 m); ``rec`` = whether the run file itself holds a forged value (|p| > 10^5 m in
  ``leader_p``, ``plant_p`` or ``p``). "changed" only if du jumps or the gate rejected nothing.
* ``exit``: the launcher's exit status (0 clean, 3 failsafe fired, 4 a process died / froze / cut off).

The analysed window ends when the launcher starts stopping the processes (its "stopping them" /
"ending the run" line) or at the mission's end, less 0.1 s, so that the shutdown's own silence is
not counted as a fault's effect.

Latency section: runs without fault (``--duration`` 12 s); at mission time ``--order-at`` (5 s) the
tap publishes the operator's order (``land`` or ``estop``: the message :func:`deploy.operator.order`
makes, :data:`deploy.operator.REPEATS` copies over :data:`deploy.operator.SPREAD` s on the control
key, from a publisher declared and matched beforehand: what the launcher's Ctrl-C and ``tether
estop`` do once their session is up). Latency = tap arrival of the first message of each stream
(4 agents' telemetry, 4 plants' state) reporting the ordered mode (ESTOP, or LAND) minus the wall
instant of the first copy's ``put``; per run the largest over the 8 streams ("all report"). This
includes the return trip of the report to the tap (one hop; telemetry is the batched, low-priority
stream). ``tether estop`` as a command adds its own start-up (Python, Zenoh session, waiting for
the subscribers to match): measured separately with ``--cli-latency`` (wall time of the command).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import zenoh  # noqa: E402

from deploy import operator  # noqa: E402
from tether import catalog  # noqa: E402
from tether import jsonout  # noqa: E402
from tether import graph  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether import wire  # noqa: E402
from tether.node import load_mission  # noqa: E402
from tether.runfile import Run  # noqa: E402

MISSION = "failsafe"
DEFAULT_CELLS = ("kill:agent/1", "kill:agent/2", "kill:leader", "kill:plant/3",
                 "freeze:agent/1", "freeze:leader", "freeze:plant/3",
                 "partition:agent/2", "partition:leader",
                 "forge:leader", "forge:agent/2", "forge:plant/3")
CODE = {wire.FLYING: "F", wire.HOLD: "H", wire.LAND: "L", wire.LANDED: "LD", wire.ESTOP: "E"}
NAME_TO_CODE = {name: i for i, name in enumerate(wire.MODES)}
PLANT_EVENT = re.compile(r"vehicle (\d+): (\w+) -> (\w+) at ([-\d.]+) s: (.*)$")
AGE_IN = re.compile(r"no valid command for ([\d.]+) s")
STOP_LINES = ("the survivors had", "ending the run", "s of mission time in", "interrupted")


_WALL_OFFSET = time.time() - time.monotonic()



def drain_stderr(p: subprocess.Popen[str], each: Callable[[str], None]) -> threading.Thread:
    """A daemon thread that hands each line of ``p``'s stderr (without its newline) to ``each`` as it
    comes, so that a launcher never blocks on a full pipe; join it once ``p`` has ended."""

    def reader() -> None:
        assert p.stderr is not None
        for line in p.stderr:
            each(line.rstrip("\n"))

    th = threading.Thread(target=reader, daemon=True)
    th.start()
    return th

def wall() -> float:
    """Wall-clock time [s since the epoch] that never steps: the monotonic clock, placed on the wall
    clock once at import (as tether's processes place the run's epoch). A wall clock stepped during a
    run (NTP; measured once here: +2.65 s mid-run) made every later arrival look 2.7 s late, and
    the bench read it as 14 s of open-loop flight that no watchdog saw."""
    return time.monotonic() + _WALL_OFFSET


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# =========================================================================== the tap
class Tap:
    """A Zenoh client of the run's router: wall-stamped arrivals (:func:`wall`) of start, cmd, telemetry, plant state."""

    def __init__(self, endpoint: str, ns: str, config_file: Path | None = None):
        self.endpoint, self.ns, self.config_file = endpoint, ns, config_file
        self.arrivals: list[tuple[float, str, bytes]] = []
        self.epoch: float | None = None
        self.session: zenoh.Session | None = None
        self._subs: list[zenoh.Subscriber[None]] = []
        self.order_put: float | None = None
        self._pub: zenoh.Publisher | None = None

    def open(self, timeout: float = 20.0) -> None:
        if self.config_file is not None:  # the run's operator identity (through its operator gateway)
            deadline = time.monotonic() + timeout
            while not self.config_file.exists():
                if time.monotonic() > deadline:
                    raise RuntimeError(f"{self.config_file} was not written within {timeout} s")
                time.sleep(0.05)
            cfg = tp.zenoh_config(tp.ZenohSettings(config_file=str(self.config_file)))
        else:
            cfg = tp.zenoh_config(tp.ZenohSettings(mode="client", connect=(self.endpoint,), lease=2.0,
                                                   connect_timeout=timeout))
        deadline = time.monotonic() + timeout
        while True:  # the operator gateway may listen a moment after its configuration is written
            try:
                self.session = zenoh.open(cfg)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        ns = self.ns

        def on_sample(sample: zenoh.Sample) -> None:
            self.arrivals.append((wall(), str(sample.key_expr), sample.payload.to_bytes()))

        def on_start(sample: zenoh.Sample) -> None:
            msg = wire.decode(sample.payload.to_bytes())
            if not isinstance(msg, wire.Start):
                raise TypeError(f"a {type(msg).__name__} on the start key, not a Start")
            self.epoch = msg.epoch

        s = self.session
        self._subs = [s.declare_subscriber(f"tether/{ns}/control/0/start", on_start),
                      s.declare_subscriber(f"tether/{ns}/agent/*/cmd", on_sample),
                      s.declare_subscriber(f"tether/{ns}/agent/*/telemetry", on_sample),
                      s.declare_subscriber(f"tether/{ns}/plant/*/state", on_sample)]

    def declare_order_publisher(self) -> None:
        if self.session is None:
            raise RuntimeError("Tap.declare_order_publisher before Tap.open")
        self._pub = tp.declare_publisher(self.session, wire.Keys(self.ns).safety, tp.SYNC)

    def send_order(self, action: operator.Action) -> None:
        """The operator's order as :func:`deploy.operator.publish` sends it (copies spread over SPREAD)."""
        if self._pub is None:
            raise RuntimeError("Tap.send_order before Tap.declare_order_publisher")
        payload = wire.encode(operator.order(action, "bench/faults.py"))
        gap = operator.SPREAD / max(1, operator.REPEATS - 1)
        for n in range(operator.REPEATS):
            if n == 0:
                self.order_put = wall()
            self._pub.put(payload)
            if n < operator.REPEATS - 1:
                time.sleep(gap)

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        if self._pub is not None:
            self._pub.undeclare()
        if self.session is not None:
            self.session.close()

    def decoded(self) -> list[tuple[float, str, int, Any]]:
        """(wall, role, id, message) for every arrival that decodes."""
        out = []
        for wall, key, data in self.arrivals:
            parts = key.split("/")
            try:
                msg = wire.decode(data)
            except Exception:  # noqa: BLE001 - a malformed sample is not ours to judge here
                continue
            out.append((wall, f"{parts[2]}/{parts[4]}", int(parts[3]), msg))
        return out


class SavedTap:
    """What :func:`analyse` needs of a :class:`Tap`, read back from ``tap.json`` (``--reanalyse``)."""

    def __init__(self, data: dict[str, Any]):
        self.epoch: float | None = data["epoch"]
        self.order_put: float | None = data.get("order_put")
        self._rows = data["rows"]

    def decoded(self) -> list[tuple[float, str, int, Any]]:
        out = []
        for wall, kind, vid, k, t, mode, gate in self._rows:
            msg = argparse.Namespace(k=k, t=t, mode=mode, gate=gate)
            out.append((wall, kind, vid, msg))
        return out


def save_tap(tap: Tap, out: Path) -> None:
    """``tap.json``: wall arrival, stream, id, k, t, mode and gate totals of every message heard."""
    rows = []
    for wall, kind, vid, msg in tap.decoded():
        rows.append((wall, kind, vid, msg.k, msg.t, getattr(msg, "mode", None),
                     dict(msg.gate) if kind == "agent/telemetry" else None))
    (out / "tap.json").write_text(jsonout.dumps({"epoch": tap.epoch, "order_put": tap.order_put, "rows": rows}, indent=None))


# =========================================================================== one run
@dataclass
class RunResult:
    out: Path
    status: int
    tap: Tap | SavedTap
    stop_wall: float | None
    lines: list[tuple[float, str]] = field(default_factory=list)


def launch(out: Path, duration: float, faults: list[str], order: tuple[operator.Action, float] | None = None,
           timeout: float = 180.0, tls: bool = False) -> RunResult:
    """One run. ``tls``: authenticated as ``tether run`` is by default, the tap attaching with the
    operator identity through the operator gateway; otherwise ``--insecure`` with a plain TCP tap."""
    port = free_port()
    ep = f"{'tls' if tls else 'tcp'}/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "cli", "run", MISSION, "--clock", "realtime", "--out", str(out),
           "--duration", repr(duration), "--quiet", "--listen", ep, *(() if tls else ("--insecure",))]
    for f in faults:
        cmd += ["--fault", f]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    lines: list[tuple[float, str]] = []
    stop_wall: list[float] = []

    def each(line: str) -> None:
        now = wall()
        lines.append((now, line))
        if not stop_wall and any(s in line for s in STOP_LINES) and "launcher:" in line:
            stop_wall.append(now)

    th = drain_stderr(p, each)
    tap = Tap(ep, MISSION, out / "tls" / "control-0.json5" if tls else None)
    time.sleep(0.3)
    tap.open()
    if order is not None:
        tap.declare_order_publisher()
    try:
        if order is not None:
            action, at = order
            deadline = wall() + 60
            while tap.epoch is None and wall() < deadline and p.poll() is None:
                time.sleep(0.01)
            if tap.epoch is not None:
                delay = tap.epoch + at - wall()
                if delay > 0:
                    time.sleep(delay)
                tap.send_order(action)
        status = p.wait(timeout)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
        th.join(5)
        tap.close()
    if out.exists():
        save_tap(tap, out)
        (out / "launcher.log").write_text("".join(f"{w:.3f} {line}\n" for w, line in lines))
    return RunResult(out, p.returncode, tap, stop_wall[0] if stop_wall else None, lines)


# =========================================================================== analysis
def plant_events(out: Path) -> list[tuple[float, int, int, int, str]]:
    """(t, vehicle, src, dst, reason) of every plant watchdog mode change, from the plants' logs."""
    evs = []
    for log in sorted((out / "logs").glob("plant-*.log")):
        for line in log.read_text(errors="replace").splitlines():
            if (m := PLANT_EVENT.search(line)) is not None:
                vid, src, dst, t, why = m.groups()
                if src in NAME_TO_CODE and dst in NAME_TO_CODE:
                    evs.append((float(t), int(vid), NAME_TO_CODE[src], NAME_TO_CODE[dst], why))
    return sorted(evs)


def longest(mask: np.ndarray) -> int:
    best = cur = 0
    for x in mask:
        cur = cur + 1 if x else 0
        best = max(best, cur)
    return best


def analyse(res: RunResult, fault: str | None) -> dict[str, Any]:
    m = load_mission(catalog.resolve(MISSION), None)
    sf, h = m.safety, m.dt
    run = Run.load(res.out)
    ids = [int(i) for i in run.agent_ids]
    col = {v: c for c, v in enumerate(ids)}
    T, n = run.safety.safety_mode.shape
    fired = ended = None
    if fault is not None and (res.out / "faults.json").exists():
        rec = json.loads((res.out / "faults.json").read_text())[0]
        fired, ended = rec["fired"], rec.get("ended")
    epoch = res.tap.epoch
    t_end = m.duration
    if res.stop_wall is not None and epoch is not None:
        t_end = min(t_end, res.stop_wall - epoch)
    t_end -= 0.1
    k_end = max(0, min(T - 1, int(math.floor(t_end / h))))
    f = fired if fired is not None else 0.0
    k_f = int(round(f / h))
    out: dict[str, Any] = {"fault": fault, "fired": fired, "exit": res.status, "t_end": t_end}

    # ------------------------------------------------------------ events
    agent_ev = [(e.t, e.vehicle, e.src, e.dst, e.reason) for e in run.safety.events]
    pl_ev = plant_events(res.out)
    after = lambda evs: [e for e in evs if e[0] >= f - h / 2 and e[0] <= t_end]  # noqa: E731
    a_after, p_after = after(agent_ev), after(pl_ev)
    if fault is not None and fault.startswith("freeze:") and ended is not None:
        # a frozen agent or plant runs its missed ticks in a burst after SIGCONT: its own events of
        # those ticks carry tick times at which it was not running, so they are not detections
        role, _, target = fault.split(":", 1)[1].split("@")[0].partition("/")
        if role == "agent":
            a_after = [e for e in a_after if not (e[1] == int(target) and e[0] < ended)]
        elif role == "plant":
            p_after = [e for e in p_after if not (e[1] == int(target) and e[0] < ended)]
    both = sorted([(e[0], "a", *e[1:]) for e in a_after] + [(e[0], "p", *e[1:]) for e in p_after])
    out["detect"] = both[0][0] - f if both and fired is not None else math.nan
    actions: dict[str, list[str]] = {}
    for t, who, vid, src, dst, why in both:
        tag = f"{who}{vid}"
        if src == dst:
            word = "+k" if "restored" in why and "lost" not in why else "k"
        else:
            word = CODE.get(dst, str(dst))
        actions.setdefault(tag, []).append(word)
    out["action"] = {tag: ">".join(words) for tag, words in sorted(actions.items())}
    stopped: dict[int, float] = {}
    last: dict[tuple[str, int], int] = {}
    for t, who, vid, src, dst, why in both:
        if src != dst:
            last[who, vid] = dst
    for t, who, vid, src, dst, why in both:
        if src != dst and dst != wire.FLYING and vid not in stopped:
            stopped[vid] = t
    for_good = {v for (who, v), mode in last.items() if mode != wire.FLYING}
    transient = sorted(set(stopped) - for_good)
    stopped = {v: t for v, t in stopped.items() if v in for_good}
    out["safe"] = max(stopped.values()) - f if stopped and fired is not None else math.nan
    out["stopped"] = sorted(stopped)
    out["transient"] = transient

    # ------------------------------------------------------------ positions
    P = run.runtime.plant_p if run.runtime is not None else run.p
    P = np.where(np.isnan(P), run.p, P)
    offsets = np.array([next(a.offset for a in m.agents if a.id == v) for v in ids], dtype=float)
    A = graph.topology(m).adjacency  # (N+1, N+1), leader last
    surv = (run.safety.safety_mode == wire.FLYING) & (run.safety.plant_mode == wire.FLYING) \
        & np.all(np.isfinite(P), axis=2)

    def xi_max(k0: int, k1: int) -> float:
        best = math.nan
        for k in range(max(0, k0), min(T, k1 + 1)):
            e = np.concatenate([P[k] - offsets, run.leader_p[k][None]], axis=0)
            keep = np.append(surv[k], bool(np.all(np.isfinite(e[-1]))))  # a silent leader is no survivor
            a = A[:n] * keep[None, :]
            xi = a.sum(axis=1)[:, None] * e[:n] - a @ np.nan_to_num(e)
            norms = np.linalg.norm(xi, axis=1)
            norms = norms[surv[k] & np.isfinite(norms) & (a.sum(axis=1) > 0)]  # no in-edge left: undefined
            if norms.size:
                best = float(norms.max()) if math.isnan(best) else max(best, float(norms.max()))
        return best

    out["xi_surv"] = xi_max(k_f, k_end)  # NaN: no survivor after the fault
    out["xi_before"] = xi_max(k_f - int(3 / h), k_f - 1)
    held = np.isin(run.safety.safety_mode, (wire.HOLD, wire.LAND)) | np.isin(run.safety.plant_mode, (wire.HOLD, wire.LAND))
    drift = 0.0
    for i in range(n):
        start = None
        for k in range(min(T, k_end + 1)):
            if held[k, i] and np.all(np.isfinite(P[k, i])):
                if start is None:
                    start = P[k, i, :2].copy()
                drift = max(drift, float(np.linalg.norm(P[k, i, :2] - start)))
            elif not held[k, i] and run.safety.plant_mode[k, i] != -1:
                start = None
    out["drift"] = drift
    sep = math.inf
    for k in range(k_f, k_end + 1):
        for i in range(n):
            for j in range(i + 1, n):
                d = float(np.linalg.norm(P[k, i] - P[k, j]))
                if math.isfinite(d):
                    sep = min(sep, d)
    out["sep"] = sep
    fence = sf.geofence
    if fence is not None:
        lo, hi = np.array(fence.min), np.array(fence.max)
        outside = np.maximum(lo - P, 0) + np.maximum(P - hi, 0)
        out["fence"] = float(np.nanmax(np.linalg.norm(outside, axis=2)))
    else:
        out["fence"] = math.nan

    # ------------------------------------------------------------ open loop
    msgs = res.tap.decoded()
    cmds: dict[int, list[tuple[float, float]]] = {v: [] for v in ids}
    for wall, kind, vid, msg in msgs:
        if kind == "agent/cmd" and vid in cmds:
            cmds[vid].append((wall, msg.t))
    open_loop, max_age = 0.0, 0.0
    if epoch is not None:
        for v in ids:
            arr = sorted(cmds[v])
            walls = np.array([w for w, _ in arr])
            stamps = np.maximum.accumulate(np.array([s for _, s in arr])) if arr else np.array([])
            ages = np.full(T, np.nan)
            for k in range(1, k_end + 1):
                newest = np.searchsorted(walls, epoch + k * h, side="right") - 1
                ages[k] = k * h - stamps[newest] if newest >= 0 else k * h
            flying = run.safety.plant_mode[:, col[v]] == wire.FLYING
            flying[k_end + 1:] = False
            flying[0] = False
            stale = flying & (ages > sf.cmd_timeout)
            open_loop = max(open_loop, longest(stale) * h)
            if np.any(flying):
                max_age = max(max_age, float(np.nanmax(ages[flying])))
    out["open_loop"] = open_loop
    out["max_age_flown"] = max_age
    dog_ages = [float(mm.group(1)) for t, v, src, dst, why in pl_ev
                if src == wire.FLYING and (mm := AGE_IN.search(why)) is not None]
    out["dog_age"] = max(dog_ages) if dog_ages else math.nan

    # ------------------------------------------------------------ forge
    reasons = [str(r) for r in (run.safety.gate_reasons if run.safety.gate_reasons is not None else [])]
    counts = run.safety.gate_counts if run.safety.gate_counts is not None else np.zeros((n, 0), int)
    out["gate"] = {r: int(counts[:, c].sum()) for c, r in enumerate(reasons)}
    du = np.linalg.norm(np.diff(run.u, axis=0), axis=2)  # (T-1, N): du[k-1] = u_k - u_{k-1}
    near = du[max(0, k_f - 1): k_f + 10]
    before = du[max(0, k_f - 1 - int(3 / h)): max(0, k_f - 1)]
    out["du_near"] = float(np.nanmax(near)) if np.any(np.isfinite(near)) else math.nan
    out["du_before"] = float(np.nanmax(before)) if np.any(np.isfinite(before)) else math.nan
    big = [name for name, arr in (("leader_p", run.leader_p), ("plant_p", P), ("p", run.p))
           if np.nanmax(np.abs(arr)) > 1e5]
    out["recorded_forged"] = big
    gate_t = math.nan
    if fault is not None and fault.startswith("forge"):
        seen: dict[int, int] = {}
        for wall, kind, vid, msg in sorted(msgs, key=lambda x: (x[3].k if hasattr(x[3], "k") else 0)):
            if kind != "agent/telemetry":
                continue
            total = sum(msg.gate.values())
            if vid in seen and total > seen[vid] and msg.t >= f - h / 2:
                gate_t = msg.t - f if math.isnan(gate_t) else min(gate_t, msg.t - f)
            seen[vid] = max(total, seen.get(vid, 0))
        out["detect"] = gate_t
    out["changed"] = bool(fault is not None and fault.startswith("forge")
                          and (sum(out["gate"].values()) == 0
                               or (out["du_near"] > 2 * max(out["du_before"], 1e-9) and out["du_near"] > 1.0)))
    return out


def latency(res: RunResult, action: str) -> dict[str, Any]:
    want = wire.ESTOP if action == "estop" else wire.LAND
    t0 = res.tap.order_put
    first: dict[str, float] = {}
    for wall, kind, vid, msg in res.tap.decoded():
        if kind in ("agent/telemetry", "plant/state") and getattr(msg, "mode", None) in (want, wire.LANDED, wire.ESTOP):
            if getattr(msg, "mode") == want or action == "land":
                key = f"{kind.split('/')[0]}/{vid}"
                if key not in first or wall < first[key]:
                    first[key] = wall
    lat = {k: (w - t0) for k, w in first.items()} if t0 is not None else {}
    return {"action": action, "exit": res.status, "streams": lat,
            "all": max(lat.values()) if len(lat) == 8 else math.nan,
            "missing": 8 - len(lat)}


# =========================================================================== report
def pct(xs: list[float], q: float) -> float:
    xs = sorted(x for x in xs if isinstance(x, (int, float)) and math.isfinite(x))
    if not xs:
        return math.nan
    if len(xs) == 1:
        return xs[0]
    return float(np.percentile(xs, q))


def fmt(x: float, unit: str = "", digits: int = 2) -> str:
    return "—" if not isinstance(x, (int, float)) or not math.isfinite(x) else f"{x:.{digits}f}{unit}"


def pair(xs: list[float], digits: int = 2) -> str:
    return f"{fmt(pct(xs, 50), digits=digits)} / {fmt(pct(xs, 99), digits=digits)}"


def table(rows: dict[str, list[dict[str, Any]]]) -> str:
    head = ("| fault | n | detect p50/p99 [s] | action | safe p50/p99 [s] | xi_surv max [m] (before) | "
            "drift [m] | sep min [m] | fence [m] | open-loop [s] (watchdog age) | forged? | exit |")
    lines = [head, "|" + "---|" * head.count("|")[:-1] if False else "|" + "|".join(["---"] * 12) + "|"]
    for cell, rs in rows.items():
        acts: dict[str, set[str]] = {}
        for r in rs:
            for tag, seq in r["action"].items():
                acts.setdefault(tag, set()).add(seq)
        action = "; ".join(f"{tag}:{'/'.join(sorted(s))}" for tag, s in sorted(acts.items())) or "none"
        forged = "—"
        if cell.startswith("forge"):
            g: dict[str, int] = {}
            for r in rs:
                for k, v in r["gate"].items():
                    g[k] = g.get(k, 0) + v
            forged = ("CHANGED" if any(r["changed"] for r in rs) else "no") + \
                f" (gate {', '.join(f'{k} {v}' for k, v in sorted(g.items())) or 'none'}; " \
                f"du {fmt(max(r['du_near'] for r in rs))} vs {fmt(max(r['du_before'] for r in rs))}; " \
                f"rec {'FORGED ' + ','.join(sorted({x for r in rs for x in r['recorded_forged']})) if any(r['recorded_forged'] for r in rs) else 'clean'})"
        exits = ",".join(str(r["exit"]) for r in rs)
        lines.append(
            f"| {cell} | {len(rs)} | {pair([r['detect'] for r in rs])} | {action} | {pair([r['safe'] for r in rs])} | "
            f"{fmt(pct([r['xi_surv'] for r in rs], 100))} ({fmt(pct([r['xi_before'] for r in rs], 100))}) | "
            f"{fmt(max(r['drift'] for r in rs), digits=3)} | {fmt(min(r['sep'] for r in rs))} | "
            f"{fmt(max(r['fence'] for r in rs), digits=3)} | "
            f"{fmt(max(r['open_loop'] for r in rs))} ({fmt(pct([r['dog_age'] for r in rs], 100))}) | {forged} | {exits} |")
    return "\n".join(lines)


def latency_table(lat: dict[str, list[dict[str, Any]]]) -> str:
    lines = ["| order | n | all 8 report, p50 / p99 [ms] | agents' telemetry p50 / p99 [ms] | plants' state p50 / p99 [ms] | "
             "missing reports | exit |", "|---|---|---|---|---|---|---|"]
    for action, rs in lat.items():
        alls = [r["all"] * 1e3 for r in rs]
        ag = [v * 1e3 for r in rs for k, v in r["streams"].items() if k.startswith("agent")]
        pl = [v * 1e3 for r in rs for k, v in r["streams"].items() if k.startswith("plant")]
        lines.append(f"| {action} | {len(rs)} | {pair(alls, 1)} | {pair(ag, 1)} | {pair(pl, 1)} | "
                     f"{sum(r['missing'] for r in rs)} | {','.join(str(r['exit']) for r in rs)} |")
    return "\n".join(lines)


def cli_latency(action: str, duration: float, at: float, work: Path) -> float:
    """Wall time of the ``tether <action> --connect`` command itself (start-up, session, match, send)."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    p = subprocess.Popen([sys.executable, "-m", "cli", "run", MISSION, "--clock", "realtime", "--out",
                          str(work / f"cli-{action}-{port}"), "--duration", repr(duration), "--quiet", "--listen", ep,
                          "--insecure"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=REPO)
    try:
        time.sleep(at + 3.0)
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-m", "cli", action, "--ns", MISSION, "--connect", ep],
                       env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        return time.monotonic() - t0
    finally:
        p.wait(120)


def reanalyse(work: Path, cells: list[str] | None) -> int:
    """Print the table and the latency section again from the runs kept in ``work``."""
    rows: dict[str, list[dict[str, Any]]] = {}
    lat: dict[str, list[dict[str, Any]]] = {}
    for out in sorted(work.iterdir()):
        if not (out / "tap.json").exists() or not (out / "run.npz").exists():
            continue
        tap = SavedTap(json.loads((out / "tap.json").read_text()))
        log = (out / "launcher.log").read_text().splitlines() if (out / "launcher.log").exists() else []
        stop = next((float(line.split(" ", 1)[0]) for line in log
                     if any(x in line for x in STOP_LINES) and "launcher:" in line), None)
        status = next((int(m.group(1)) for line in log if (m := re.search(r"exit status (\d+)", line))), -1)
        res = RunResult(out, status, tap, stop)
        if out.name.startswith("order-"):
            action = out.name.split("-")[1]
            lat.setdefault(action, []).append(latency(res, action))
            continue
        fault = json.loads((out / "faults.json").read_text())[0]["fault"] if (out / "faults.json").exists() else None
        cell = fault.split("@")[0] if fault else "none"
        if cells is not None and cell not in cells:
            continue
        rows.setdefault(cell, []).append(analyse(res, fault))
    order = {c: n for n, c in enumerate(DEFAULT_CELLS)}
    print(table(dict(sorted(rows.items(), key=lambda kv: order.get(kv[0], 99)))))
    if lat:
        print()
        print(latency_table(lat))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", nargs="*", default=None, help=f"KIND:TARGET cells (default: {' '.join(DEFAULT_CELLS)})")
    ap.add_argument("--reps", type=int, default=3, help="repetitions per cell (default 3)")
    ap.add_argument("--quick", action="store_true", help="1 repetition per cell, 2 per latency order")
    ap.add_argument("--at", type=float, default=8.0, help="fault time [s of mission time] (default 8)")
    ap.add_argument("--hold", type=float, default=3.0, help="freeze / partition duration [s] (default 3)")
    ap.add_argument("--duration", type=float, default=20.0, help="mission duration of a fault run [s] (default 20)")
    ap.add_argument("--no-faults", action="store_true", help="skip the fault table")
    ap.add_argument("--no-latency", action="store_true", help="skip the e-stop / land latency")
    ap.add_argument("--latency-reps", type=int, default=5, help="runs per order (default 5)")
    ap.add_argument("--order-at", type=float, default=5.0, help="when the tap orders land / estop [s] (default 5)")
    ap.add_argument("--cli-latency", action="store_true", help="also time the tether estop / land commands")
    ap.add_argument("--tls", action="store_true",
                    help="authenticated runs (tether run's default): orders go through the operator gateway")
    ap.add_argument("--work", default=None, help="directory for the runs (default: a temporary one, kept)")
    ap.add_argument("--json", default=None, help="write every figure of every run here")
    ap.add_argument("--reanalyse", default=None, metavar="WORK",
                    help="no runs: analyse again the runs kept in WORK (their tap.json, run.npz, logs)")
    args = ap.parse_args(argv)
    if args.reanalyse:
        return reanalyse(Path(args.reanalyse), args.cells)
    reps = 1 if args.quick else args.reps
    lreps = 2 if args.quick else args.latency_reps
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="tether-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    cells = args.cells if args.cells is not None else list(DEFAULT_CELLS)
    print(f"# bench/faults.py  {time.strftime('%Y-%m-%d %H:%M:%S')}  runs in {work}", flush=True)
    try:
        rev = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, check=False).stdout.strip()
    except OSError:
        rev = "?"
    print(f"# code {rev}; {os.cpu_count()} cores; load before: {os.getloadavg()}", flush=True)
    report: dict[str, Any] = {"cells": {}, "latency": {}, "load_before": os.getloadavg(), "argv": sys.argv[1:]}
    rows: dict[str, list[dict[str, Any]]] = {}
    if not args.no_faults:
        for cell in cells:
            kind = cell.split(":", 1)[0]
            for rep in range(reps):
                if cell == "none":
                    fault = None
                else:
                    fault = f"{cell}@{args.at:g}" + (f"+{args.hold:g}" if kind in ("freeze", "partition") else "")
                out = work / f"{cell.replace(':', '-').replace('/', '')}-{rep}"
                t0 = time.monotonic()
                res = launch(out, args.duration, [fault] if fault else [])
                try:
                    r = analyse(res, fault)
                except Exception as exc:  # noqa: BLE001 - a run that cannot be read is reported, not fatal
                    r = {"fault": fault, "error": repr(exc), "exit": res.status}
                    print(f"{cell} rep {rep}: cannot analyse: {exc!r}", flush=True)
                    report["cells"].setdefault(cell, []).append(r)
                    continue
                r["wall"] = time.monotonic() - t0
                r["load"] = os.getloadavg()[0]
                rows.setdefault(cell, []).append(r)
                report["cells"].setdefault(cell, []).append(r)
                print(f"{cell} rep {rep}: exit {r['exit']} detect {fmt(r['detect'])} s safe {fmt(r['safe'])} s "
                      f"action {r['action']} transient {r['transient']} open-loop {fmt(r['open_loop'])} s (dog {fmt(r['dog_age'])}) "
                      f"xi {fmt(r['xi_surv'])} sep {fmt(r['sep'])} fence {fmt(r['fence'], digits=3)} "
                      f"gate {r['gate']} du {fmt(r['du_near'])}/{fmt(r['du_before'])} rec {r['recorded_forged']} "
                      f"[{r['wall']:.0f} s wall, load {r['load']:.2f}]", flush=True)
        print()
        print(table(rows))
    if not args.no_latency:
        lat: dict[str, list[dict[str, Any]]] = {}
        orders: tuple[operator.Action, ...] = ("estop", "land")
        for action in orders:
            for rep in range(lreps):
                out = work / f"order-{action}-{rep}"
                res = launch(out, 12.0, [], order=(action, args.order_at), tls=args.tls)
                r = latency(res, action)
                lat.setdefault(action, []).append(r)
                report["latency"].setdefault(action, []).append(r)
                streams = " ".join(f"{k}={v * 1e3:.0f}" for k, v in sorted(r["streams"].items()))
                print(f"{action} rep {rep}: all {fmt(r['all'] * 1e3, digits=1)} ms; {streams} ms; exit {r['exit']}",
                      flush=True)
        print()
        print(latency_table(lat))
        if args.cli_latency:
            for action in ("estop", "land"):
                w = cli_latency(action, 12.0, args.order_at, work)
                report["latency"].setdefault(f"cli-{action}", []).append(w)
                print(f"tether {action} --connect: {w * 1e3:.0f} ms wall for the command itself", flush=True)
    print(f"# load after: {os.getloadavg()}", flush=True)
    if args.json:
        Path(args.json).write_text(jsonout.dumps(report, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
