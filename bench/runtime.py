"""Figures of the distributed runtime, each beside a bare Zenoh baseline measured in the same run.

    .venv/bin/python bench/runtime.py                        # every case (about 5-7 minutes)
    .venv/bin/python bench/runtime.py --cases lockstep --repeats 5
    .venv/bin/python bench/runtime.py --cases scale --sizes 4 8 16 32
    .venv/bin/python bench/runtime.py --cases latency cpu --json /tmp/bench.json

Cases (``docs/benchmarks.md`` has the method, the figures and what they mean):

1. ``lockstep``: simulated seconds per wall second of ``tether run MISSION --clock lockstep``
   (section4: N = 4, 100 Hz), from the launcher's "ran X s of mission time in Y s of wall time";
   beside it the in-process reference simulator on the same mission and a bare lockstep baseline
   (``bench/baseline_node.py``: the same processes, keys, sizes and per-tick message pattern,
   trivial work).
2. ``scale``: real time at 50 Hz, N = 4, 8, 16 (32 if 16 holds) agents on a ring
   (``bench/missions.py``); late ticks from the run file's ``extra["late"]``; total CPU of every
   process (launcher/router included) from ``/proc/<pid>/stat`` over the mission window, beside the
   baseline's at the same N.
3. ``latency``: real time, N = 8, 100 Hz. A probe process (a Zenoh client of the same router)
   subscribes to every agent's state key and to the start message, and records each sample's
   arrival on CLOCK_MONOTONIC in its subscriber callback; the latency of a sample of tick k is
   ``arrival - (t0 + k h)``, where ``t0`` is the start epoch mapped to CLOCK_MONOTONIC exactly as
   the nodes' ``RealtimeClock`` maps it. This is *tick instant -> receiving callback*: the
   publisher's timer lateness, its work before ``put``, and the transport. The baseline's payload
   also carries its send time, which splits off the transport alone. Plus ``extra["link_age"]``.
4. ``cpu``: CPU and VmRSS per agent process, tether vs baseline, from the real-time runs of cases
   2 and 3 (or one N = 8, 50 Hz pair if neither ran).

Figures are medians over ``--repeats`` (runs) and over processes; tether and baseline runs alternate.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import re
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench import missions  # noqa: E402
from deploy.local import HANDOVER  # noqa: E402

try:  # real time: agents tick this fraction of a period after plants and the leader (if the runtime does)
    from agent.node import AGENT_PHASE  # noqa: E402
except ImportError:
    AGENT_PHASE = 0.0
from tether import mission as ms  # noqa: E402
from tether import catalog  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether import wire  # noqa: E402

CLK_TCK = os.sysconf("SC_CLK_TCK")
PY = sys.executable
BASELINE = str(REPO / "bench" / "baseline_node.py")
START_LEAD = 1.0  # deploy.local.LaunchOptions.start_lead: tick 0 comes this long after "all up"
WINDOW = 8  # deploy.local.LaunchOptions.window (tether run's default)


# =========================================================================== /proc
def cpu_times(pid: int) -> tuple[float, float] | None:
    """(utime, stime) of ``pid`` [s] (``/proc/<pid>/stat`` fields 14, 15), or None if it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            rest = fh.read().rpartition(")")[2].split()
        return int(rest[11]) / CLK_TCK, int(rest[12]) / CLK_TCK
    except (OSError, IndexError, ValueError):
        return None


def cpu_seconds(pid: int) -> float | None:
    """utime + stime of ``pid`` [s], or None if it is gone."""
    t = cpu_times(pid)
    return None if t is None else t[0] + t[1]


def context_switches(pid: int) -> int | None:
    """Voluntary + involuntary context switches of every thread of ``pid``."""
    total = 0
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            try:
                with open(f"/proc/{pid}/task/{tid}/status") as fh:
                    for line in fh:
                        if "ctxt_switches" in line:
                            total += int(line.split()[1])
            except OSError:
                pass
    except OSError:
        return None
    return total


def thread_cpu(pid: int) -> dict[int, tuple[str, float]] | None:
    """CPU time [s] of every thread of ``pid``: tid -> (kind, seconds), kind ``main`` (the asyncio
    thread), ``zenoh`` (Zenoh's runtime threads: ``app-*``, ``rx-*``, ``tx-*``, ``net-*``, ``acc-*``)
    or ``callback`` (the other Python threads: zenoh-python runs one per subscriber callback)."""
    out = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return None
    for tid in tids:
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as fh:
                comm = fh.read().strip()
            with open(f"/proc/{pid}/task/{tid}/stat") as fh:
                rest = fh.read().rpartition(")")[2].split()
        except OSError:
            continue
        if int(tid) == pid:
            kind = "main"
        elif re.match(r"(app|rx|tx|net|acc)-\d+$", comm):
            kind = "zenoh"
        else:
            kind = "callback"
        out[int(tid)] = (kind, (int(rest[11]) + int(rest[12])) / CLK_TCK)
    return out


def threads(pid: int) -> int | None:
    try:
        return len(os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return None


def machine_jiffies() -> tuple[int, int]:
    """(busy, total) jiffies of the whole machine since boot (``/proc/stat``, first line)."""
    with open("/proc/stat") as fh:
        f = [int(x) for x in fh.readline().split()[1:]]
    idle = f[3] + (f[4] if len(f) > 4 else 0)  # idle + iowait
    return sum(f) - idle, sum(f)


def busy_cores(seconds: float = 1.0) -> float:
    """Cores' worth of CPU the whole machine used over the next ``seconds`` (blocks that long)."""
    b0, _ = machine_jiffies()
    time.sleep(seconds)
    b1, _ = machine_jiffies()
    return (b1 - b0) / CLK_TCK / seconds


def wait_quiet(limit: float, timeout: float) -> float:
    """Wait (up to ``timeout`` s) until the machine uses less than ``limit`` cores with none of our runs
    going, so that another user's burst does not land in a measurement; returns the last reading."""
    deadline = time.monotonic() + timeout
    busy = busy_cores()
    while busy > limit and time.monotonic() < deadline:
        busy = busy_cores(2.0)
    return busy


def rss_kib(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def children_of(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as fh:
                    if int(fh.read().rpartition(")")[2].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, IndexError, ValueError):
                pass
    return out


def cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return [a.decode() for a in fh.read().split(b"\0") if a]
    except OSError:
        return []


@dataclass
class Proc:
    """One measured process: its role and id, CPU [s] and RSS [KiB] at the two snapshots."""

    pid: int
    role: str
    nid: int
    cpu0: tuple[float, float] | None = None
    cpu1: tuple[float, float] | None = None
    ctx0: int | None = None
    ctx1: int | None = None
    rss: int | None = None
    threads: int | None = None

    th0: dict[int, tuple[str, float]] | None = None
    th1: dict[int, tuple[str, float]] | None = None

    def snap0(self) -> None:
        self.cpu0 = cpu_times(self.pid)
        self.ctx0 = context_switches(self.pid)
        self.th0 = thread_cpu(self.pid)

    def snap1(self) -> None:
        """Read the end of the window; a process already gone keeps its last sampled values."""
        cpu, ctx, rss, nth = cpu_times(self.pid), context_switches(self.pid), rss_kib(self.pid), threads(self.pid)
        th = thread_cpu(self.pid)
        if None not in (cpu, ctx, rss, nth, th):
            self.cpu1, self.ctx1, self.rss, self.threads = cpu, ctx, rss, nth
            self.th1 = {**(self.th1 or {}), **th}  # threads that ended keep their last reading

    def by_thread(self) -> dict[str, float]:
        """CPU over the window [s] by thread kind (see :func:`thread_cpu`)."""
        out = {"main": 0.0, "callback": 0.0, "zenoh": 0.0}
        if self.th0 is None or self.th1 is None:
            return {k: float("nan") for k in out}
        for tid, (kind, sec) in self.th1.items():
            out[kind] += sec - self.th0.get(tid, (kind, 0.0))[1]
        return out

    @property
    def cpu(self) -> float:
        """CPU time over the window [s]."""
        return self.user + self.system

    @property
    def user(self) -> float:
        if self.cpu0 is None or self.cpu1 is None:
            return float("nan")
        return self.cpu1[0] - self.cpu0[0]

    @property
    def system(self) -> float:
        if self.cpu0 is None or self.cpu1 is None:
            return float("nan")
        return self.cpu1[1] - self.cpu0[1]

    @property
    def switches(self) -> float:
        if self.ctx0 is None or self.ctx1 is None:
            return float("nan")
        return float(self.ctx1 - self.ctx0)


class Sampler:
    """Samples every process's end-of-window figures every ``period`` s while the window is open, so
    that a process that exits just before the window closes (its last tick done) is still counted."""

    def __init__(self, procs: list[Proc], period: float = 0.1):
        self.procs, self.period = procs, period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            for p in self.procs:
                p.snap1()

    def stop(self) -> None:
        """Close the window: one last reading of every live process."""
        self._stop.set()
        self._thread.join()
        for p in self.procs:
            p.snap1()


class Window:
    """The measured window of one run: every process's CPU, and the whole machine's."""

    def __init__(self, procs: list[Proc]):
        self.procs = procs
        self.sampler = Sampler(procs)

    def open(self) -> None:
        self.t0 = time.monotonic()
        self.m0 = machine_jiffies()[0]
        for p in self.procs:
            p.snap0()
        self.sampler.start()

    def close(self, res: "Result") -> None:
        self.sampler.stop()
        res.window_s = time.monotonic() - self.t0
        machine = 100 * (machine_jiffies()[0] - self.m0) / CLK_TCK / res.window_s
        res.foreign_pct = machine - sum(100 * p.cpu / res.window_s for p in self.procs if p.cpu == p.cpu)


@dataclass
class Result:
    """One run (tether or baseline)."""

    kind: str
    n: int
    clock: str
    rate: float
    ok: bool = True
    why: str = ""
    mission_s: float = float("nan")
    wall_s: float = float("nan")
    startup_s: float = float("nan")
    window_s: float = float("nan")
    """Wall time between the two CPU snapshots [s]."""
    foreign_pct: float = float("nan")
    """CPU used by everything else on the machine during the window [% of one core]: noise."""
    procs: list[Proc] = field(default_factory=list)
    late: float = float("nan")
    """Late ticks / agent ticks (real time)."""
    late_max: float = float("nan")
    link_age: np.ndarray | None = None
    meas_age: np.ndarray | None = None
    probe: dict | None = None
    complete: str = ""

    @property
    def speed(self) -> float:
        return self.mission_s / self.wall_s

    def cpu_pct(self, role: str | None = None) -> list[float]:
        """CPU per process over the window [% of one core]; every measured role but the probe by default."""
        return [100 * p.cpu / self.window_s for p in self.procs
                if (role is None and p.role != "probe") or p.role == role]

    def thread_pct(self, role: str) -> dict[str, float]:
        """Median over the role's processes of CPU by thread kind [% of one core]."""
        rows = [p.by_thread() for p in self.procs if p.role == role]
        return {k: med([100 * r[k] / self.window_s for r in rows]) for k in ("main", "callback", "zenoh")}

    def total_cpu_pct(self) -> float:
        return float(sum(self.cpu_pct()))

    def rss_mib(self, role: str) -> list[float]:
        return [p.rss / 1024 for p in self.procs if p.role == role and p.rss is not None]


# =========================================================================== sizes and specs
def _example(cls: type, m: ms.Mission, width: int) -> Any:
    """A message of ``cls`` filled from its schema (so that the sizes follow ``tether/wire.py`` as it
    changes): vectors of ``dim`` numbers, ``width`` link records, plausible scalars."""
    import msgspec

    v = [0.123456789] * m.dim
    values: dict[str, Any] = {}
    for f in msgspec.structs.fields(cls):
        if f.default is not msgspec.NODEFAULT or f.default_factory is not msgspec.NODEFAULT:
            if f.name not in ("late",):
                continue
        t = msgspec.inspect.type_info(f.type)
        if isinstance(t, msgspec.inspect.ListType):
            if isinstance(t.item_type, msgspec.inspect.FloatType):
                values[f.name] = v
            else:
                values[f.name] = [_example(t.item_type.cls, m, width)] * width
        elif isinstance(t, msgspec.inspect.DictType):
            values[f.name] = {}
        elif isinstance(t, msgspec.inspect.FloatType):
            values[f.name] = 10.0 if f.name != "epoch" else time.time()
        elif isinstance(t, msgspec.inspect.BoolType):
            values[f.name] = False
        elif isinstance(t, msgspec.inspect.IntType):
            values[f.name] = 1000 if f.name != "sender" else m.leader.id
        elif isinstance(t, msgspec.inspect.StrType):
            values[f.name] = "recorder"
        else:
            raise TypeError(f"wire_sizes: no example for {cls.__name__}.{f.name} ({t})")
    return cls(**values)


def wire_sizes(m: ms.Mission) -> dict[str, int]:
    """Encoded sizes of tether's messages for this mission (widest telemetry: the largest in-degree)."""
    width = max(sum(1 for e in m.edges if e.dst == a.id) for a in m.agents)
    size = {name: len(wire.encode(_example(cls, m, width)))
            for name, cls in (("state", wire.State), ("plant_state", wire.PlantState), ("cmd", wire.Command),
                              ("telemetry", wire.Telemetry), ("tick", wire.Tick), ("ack", wire.Ack),
                              ("start", wire.Start))}
    size["start"] = max(24, size["start"])
    return size


def baseline_spec(m: ms.Mission, clock: str, duration: float, wake: bool,
                  variant: dict[str, Any] | None = None) -> dict[str, Any]:
    """What every baseline process needs: the mission's shape, the sizes, the exact Zenoh configs
    (those ``deploy.local`` gives the launcher's router and its clients). ``variant`` changes one
    thing for an experiment: ``direct`` callbacks, ``mesh`` (peers, as ``--network mesh``), ``qos``
    (stream -> preset), ``window``, ``config`` (Zenoh key -> JSON value, inserted in every config)."""
    v = variant or {}
    placeholder = tp.loopback_endpoint(7447)  # replaced by the real endpoint in each process
    if v.get("mesh"):
        client = tp.ZenohSettings(mode="peer", connect=(placeholder,), listen=(placeholder,), lease=2.0,
                                  connect_timeout=10.0)
    else:
        client = tp.ZenohSettings(mode="client", connect=(placeholder,), lease=2.0, connect_timeout=10.0)
    router = tp.ZenohSettings(mode="router", listen=(placeholder,), lease=2.0)
    configs = []
    for settings in (client, router):
        cfg = tp.zenoh_config(settings)
        for key, value in v.get("config", {}).items():
            cfg.insert_json5(key, json.dumps(value))
        configs.append(str(cfg))
    nbrs = {}
    for a in m.agents:
        srcs = [e.src for e in m.edges if e.dst == a.id]
        nbrs[str(a.id)] = [["leader" if j == m.leader.id else "agent", j] for j in srcs]
    return {
        "ns": m.name, "clock": clock, "rate": m.rate, "steps": int(round(duration * m.rate)),
        "window": v.get("window", WINDOW), "leader": m.leader.id, "agents": m.agent_ids, "nbrs": nbrs,
        "sizes": wire_sizes(m), "client_config": configs[0], "router_config": configs[1],
        "wake": wake, "start_lead": START_LEAD, "direct": bool(v.get("direct")), "mesh": bool(v.get("mesh")),
        "qos": v.get("qos", {}), "agent_phase": AGENT_PHASE, "colocate": bool(v.get("colocate")),
    }


def child_env(handover: bool = True) -> dict[str, str]:
    env = dict(os.environ)
    if handover:
        env.setdefault("ZENOH_RUNTIME", HANDOVER)  # what deploy.local gives its children
    else:
        env.pop("ZENOH_RUNTIME", None)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def launcher_env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("ZENOH_RUNTIME", None)  # the launcher (router) itself runs Zenoh's default runtime
    return env


# =========================================================================== the probe (case 3)
def run_probe(endpoint: str, ns: str, rate: float, kind: str, n_agents: int, steps: int, out: str) -> None:
    """Child process: subscribe to every plant's and agent's state key and to the start message,
    stamp each arrival on CLOCK_MONOTONIC in the callback (nothing else there), write them as JSON."""
    import zenoh

    cfg = tp.zenoh_config(tp.ZenohSettings(mode="client", connect=(endpoint,), lease=2.0, connect_timeout=10.0))
    arrivals: list[tuple[int, str, bytes]] = []
    start: list[tuple[int, float, bytes]] = []
    expected = 2 * n_agents * (steps + 1)

    def on_state(sample: zenoh.Sample) -> None:
        arrivals.append((time.monotonic_ns(), str(sample.key_expr), sample.payload.to_bytes()))

    def on_start(sample: zenoh.Sample) -> None:
        start.append((time.monotonic_ns(), time.time(), sample.payload.to_bytes()))

    with zenoh.open(cfg) as session:
        subs = [session.declare_subscriber(f"tether/{ns}/control/0/start", on_start),
                session.declare_subscriber(f"tether/{ns}/agent/*/state", on_state),
                session.declare_subscriber(f"tether/{ns}/plant/*/state", on_state)]
        print("ready", flush=True)
        deadline = time.monotonic() + 120 + 2 * steps / rate
        while len(arrivals) < expected and time.monotonic() < deadline:
            time.sleep(0.2)
            if start and time.monotonic_ns() > start[0][0] + int((START_LEAD + steps / rate + 2.0) * 1e9):
                break
        for sub in subs:
            sub.undeclare()
    if not start:
        Path(out).write_text(json.dumps({"error": "the probe missed the start message"}))
        return
    got_mono, got_wall, payload = start[0]
    epoch = wire.decode(payload).epoch if kind == "tether" else struct.unpack_from("<d", payload, 16)[0]
    t0_ns = got_mono + (epoch - got_wall) * 1e9  # tick 0 on CLOCK_MONOTONIC, as RealtimeClock maps it
    rows = []  # role (0 plant, 1 agent), id, k, arrival - tick instant [us], arrival - send [us] (baseline)
    for arr, key, data in arrivals:
        sent = None
        if kind == "tether":
            k = wire.decode(data).k
        else:
            k, sent_ns = struct.unpack_from("<qq", data)
            sent = (arr - sent_ns) / 1e3
        parts = key.split("/")
        rows.append((int(parts[2] == "agent"), int(parts[3]), k, (arr - (t0_ns + k * 1e9 / rate)) / 1e3, sent))
    Path(out).write_text(json.dumps({"rows": rows, "received": len(arrivals), "expected": expected}))


def probe_stats(probe: dict) -> dict[str, Any]:
    """p50/p99 [us] of: plant tick instant -> probe (one hop), agent relay of the same sample -> probe
    (two hops), their difference per sample (one hop through the agent: its callback, hand-off,
    decode and relay publish), and for the baseline put -> callback; sample counts."""
    if not probe or "error" in probe:
        return {"error": (probe or {}).get("error", "no probe data")}
    rows = probe["rows"]
    plant = {(i, k): lat for role, i, k, lat, _ in rows if role == 0}
    agent = {(i, k): lat for role, i, k, lat, _ in rows if role == 1}
    relay = [agent[key] - plant[key] for key in agent.keys() & plant.keys()]
    out: dict[str, Any] = {"received": f"{probe['received']}/{probe['expected']}",
                           "plant_received": len(plant), "agent_received": len(agent)}
    for name, xs in (("plant_tick", list(plant.values())), ("agent_tick", list(agent.values())), ("relay", relay),
                     ("put_cb", [sent for *_, sent in rows if sent is not None])):
        out[name] = [pct(xs, 50), pct(xs, 99)] if xs else [float("nan")] * 2
    return out


def _spawn_probe(endpoint: str, ns: str, rate: float, kind: str, n: int, steps: int, out: Path) -> subprocess.Popen:
    p = subprocess.Popen([PY, __file__, "_probe", endpoint, ns, repr(rate), kind, str(n), str(steps), str(out)],
                         env=child_env(), stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                         start_new_session=True)
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"probe did not start (said {line!r})")
    return p


# =========================================================================== tether runs
def _reader(stream, q: queue.Queue) -> None:
    for line in stream:
        q.put(line)
    q.put(None)


def _tether_cmd() -> list[str]:
    exe = Path(PY).parent / "tether"
    return [str(exe)] if exe.exists() else [PY, "-m", "tether.cli"]


def run_tether(mission_path: Path, m: ms.Mission, clock: str, duration: float, work: Path,
               probe: bool = False, timeout: float = 300.0) -> Result:
    """``tether run MISSION --clock CLOCK --duration S --quiet``, measured from outside."""
    out = work / f"tether-{clock}-{m.n}-{time.monotonic_ns()}"
    cmd = [*_tether_cmd(), "run", str(mission_path), "--out", str(out), "--clock", clock,
           "--duration", repr(duration), "--quiet"]
    res = Result("tether", m.n, clock, m.rate)
    t_start = time.monotonic()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=launcher_env(),
                         cwd=REPO)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=_reader, args=(p.stderr, lines), daemon=True).start()
    log: list[str] = []
    probe_proc = None
    probe_out = out.with_suffix(".probe.json")
    timer = None
    try:
        deadline = time.monotonic() + timeout
        while True:
            if probe and probe_proc is None:
                for c in children_of(p.pid):
                    args = cmdline(c)
                    if "--connect" in args:
                        ep = args[args.index("--connect") + 1]
                        steps = int(round(duration * m.rate))
                        probe_proc = _spawn_probe(ep, m.name, m.rate, "tether", m.n, steps, probe_out)
                        break
            try:
                line = lines.get(timeout=0.02)
            except queue.Empty:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"tether run did not finish in {timeout} s")
                continue
            if line is None:
                break
            log.append(line)
            if "processes are up after" in line:
                res.startup_s = time.monotonic() - t_start
                for c in children_of(p.pid):
                    args = cmdline(c)
                    if "tether.cli" in args:
                        role = args[args.index("tether.cli") + 1]
                        nid = int(args[args.index("--id") + 1]) if "--id" in args else 0
                        res.procs.append(Proc(c, role, nid))
                res.procs.append(Proc(p.pid, "launcher", 0))
                t_up = time.monotonic()
                lead = START_LEAD if clock == "realtime" else 0.0

                if probe_proc is not None:
                    res.procs.append(Proc(probe_proc.pid, "probe", 0))
                window = Window(res.procs)
                timer = threading.Timer(max(0.0, t_up + lead - time.monotonic()), window.open)
                timer.start()
            mo = re.search(r"ran (\S+) s of mission time in (\S+) s of wall time", line)
            if mo:
                timer.join()
                window.close(res)
                res.mission_s, res.wall_s = float(mo[1]), float(mo[2])
        rc = p.wait(timeout=60)
        if rc != 0:
            res.ok, res.why = False, f"tether run exited {rc}: " + "".join(log[-5:])
    finally:
        if p.poll() is None:
            p.terminate()
            p.wait()
        if probe_proc is not None:
            try:
                probe_proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                probe_proc.kill()
                probe_proc.wait()
    run_file = out / "run.npz"
    if run_file.exists():
        with np.load(run_file) as z:
            meta = json.loads(str(z["meta"]))
            res.complete = f"{meta.get('samples_recorded')}/{meta.get('samples_expected')}"
            late = z["late"] if "late" in z.files else None
            if late is not None and clock == "realtime":
                per_agent = np.nanmax(np.where(np.isfinite(late), late, -1), axis=0)
                per_agent = np.maximum(per_agent, 0)
                steps = int(round(duration * m.rate)) + 1
                res.late = float(per_agent.sum() / (m.n * steps))
                res.late_max = float(per_agent.max() / steps)
            for name in ("link_age", "meas_age"):
                if name in z.files:
                    age = z[name]
                    setattr(res, name, age[np.isfinite(age)])
    if probe and probe_out.exists():
        res.probe = json.loads(probe_out.read_text())
    return res


# =========================================================================== baseline runs
def run_baseline(m: ms.Mission, clock: str, duration: float, work: Path, probe: bool = False,
                 wake: bool = False, variant: dict[str, Any] | None = None) -> Result:
    """The same run with ``bench/baseline_node.py`` processes (hub = router + clock, like the launcher)."""
    spec = baseline_spec(m, clock, duration, wake, variant)
    env = child_env(handover=(variant or {}).get("handover", True))
    tag = f"baseline-{clock}-{m.n}-{time.monotonic_ns()}"
    spec_path = work / f"{tag}.json"
    spec_path.write_text(json.dumps(spec))
    res = Result("baseline", m.n, clock, m.rate)
    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    t_start = time.monotonic()
    hub = subprocess.Popen([PY, BASELINE, str(spec_path), "hub", endpoint], stdout=subprocess.PIPE,
                           stdin=subprocess.DEVNULL, text=True, env=launcher_env(), start_new_session=True)
    kids: list[tuple[subprocess.Popen, str, int]] = []
    probe_proc = None
    probe_out = work / f"{tag}.probe.json"
    try:
        if hub.stdout.readline().strip() != "listening":
            raise RuntimeError("baseline hub did not start")
        roles = ("agent",) if spec.get("colocate") else ("agent", "plant")
        members = [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in roles], ("recorder", 0)]
        if probe:
            probe_proc = _spawn_probe(endpoint, m.name, m.rate, "bare", m.n, spec["steps"], probe_out)
        for role, nid in members:
            kp = subprocess.Popen([PY, BASELINE, str(spec_path), role, str(nid), endpoint], stdout=subprocess.PIPE,
                                  stdin=subprocess.DEVNULL, text=True, env=env, start_new_session=True)
            kids.append((kp, role, nid))
        res.procs = [Proc(kp.pid, role, nid) for kp, role, nid in kids] + [Proc(hub.pid, "launcher", 0)]
        if probe_proc is not None:
            res.procs.append(Proc(probe_proc.pid, "probe", 0))
        window = Window(res.procs)
        lines: queue.Queue = queue.Queue()
        threading.Thread(target=_reader, args=(hub.stdout, lines), daemon=True).start()
        deadline = time.monotonic() + 120 + 3 * duration
        while True:
            try:
                line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise TimeoutError("baseline hub did not finish in time") from None
            if line is None:
                break
            word, *rest = line.split() or [""]
            if word in ("stalled", "missing"):
                res.ok, res.why = False, f"baseline hub: {line.strip()}"
            if word == "up":
                res.startup_s = time.monotonic() - t_start
            elif word == "start":
                if clock == "realtime":
                    t_tick0 = time.monotonic() + (float(rest[0]) - time.time())
                    time.sleep(max(0.0, t_tick0 - time.monotonic()))
                window.open()
            elif word == "ran":
                window.close(res)
                res.mission_s, res.wall_s = float(rest[0]), float(rest[1])
        hub.wait(timeout=30)
        if not res.ok:
            return res
        late = []
        for kp, role, nid in kids:
            out, _ = kp.communicate(timeout=30)
            if kp.returncode != 0 or not out.strip():
                res.ok, res.why = False, f"baseline {role}/{nid} exited {kp.returncode}"
                continue
            info = json.loads(out.strip().splitlines()[-1])
            if role == "agent":
                late.append(info["late"])
            if role == "recorder":
                res.complete = f"{info['received']}/{(1 + 2 * m.n) * (spec['steps'] + 1)}"
        if clock == "realtime" and late:
            steps = spec["steps"] + 1
            res.late = sum(late) / (len(late) * steps)
            res.late_max = max(late) / steps
    finally:
        for kp, _, _ in kids:
            if kp.poll() is None:
                kp.kill()
                kp.wait()
        if hub.poll() is None:
            hub.kill()
            hub.wait()
        if probe_proc is not None:
            try:
                probe_proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                probe_proc.kill()
                probe_proc.wait()
    if probe and probe_out.exists():
        res.probe = json.loads(probe_out.read_text())
    return res


# =========================================================================== helpers
def med(xs: list[float]) -> float:
    xs = [x for x in xs if x == x]
    return statistics.median(xs) if xs else float("nan")


def pct(xs, q: float) -> float:
    xs = np.asarray(xs, dtype=float)
    return float(np.percentile(xs, q)) if xs.size else float("nan")


def ratio(a: float, b: float) -> float:
    return a / b if b else float("nan")


def say(text: str = "") -> None:
    print(text, flush=True)


QUIET = {"limit": 0.5, "timeout": 60.0}


def settle() -> None:
    """Before a run: wait for the machine to be quiet (see :func:`wait_quiet`); say so if it is not."""
    busy = wait_quiet(QUIET["limit"], QUIET["timeout"])
    if busy > QUIET["limit"]:
        say(f"   (the machine is busy with other work: {busy:.2f} cores in use before this run)")


def mission_file(work: Path, n: int, rate: float, duration: float) -> tuple[Path, ms.Mission]:
    path = work / f"ring{n}-{rate:g}hz.toml"
    return path, missions.write(path, n, rate=rate, duration=duration, topology="ring")


# =========================================================================== cases
def case_lockstep(a: argparse.Namespace, work: Path, report: dict) -> None:
    from tether import refsim
    from tether.node import load_mission

    path = catalog.resolve(a.mission)
    m = load_mission(path, a.lockstep_duration)
    say(f"\n== 1. lockstep speed: {a.mission} ({m.n} agents, {m.dim}D, {m.rate:g} Hz), "
        f"{a.lockstep_duration:g} s of mission time, window {WINDOW}, {a.repeats} repeats")
    rows = []
    t, b, r = [], [], []
    for i in range(a.repeats):
        settle()
        rt = run_tether(path, m, "lockstep", a.lockstep_duration, work)
        settle()
        rb = run_baseline(m, "lockstep", a.lockstep_duration, work)
        t0 = time.perf_counter()
        refsim.simulate(m, "discrete")
        r.append(m.duration / (time.perf_counter() - t0))
        for res in (rt, rb):
            if not res.ok:
                say(f"   {res.kind} failed: {res.why}")
        t.append(rt.speed if rt.ok else float("nan"))
        b.append(rb.speed if rb.ok else float("nan"))
        rows.append({"tether_speed": t[-1], "baseline_speed": b[-1], "refsim_speed": r[-1],
                     "tether_cpu_pct": rt.total_cpu_pct(), "baseline_cpu_pct": rb.total_cpu_pct(),
                     "tether_startup_s": rt.startup_s, "baseline_startup_s": rb.startup_s,
                     "tether_cpu_by_role": {ro: med(rt.cpu_pct(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")},
                     "baseline_cpu_by_role": {ro: med(rb.cpu_pct(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")}})
        say(f"   run {i + 1}: tether {t[-1]:6.2f} x   baseline {b[-1]:6.2f} x   refsim {r[-1]:8.0f} x   "
            f"(total CPU {rt.total_cpu_pct():.0f} % vs {rb.total_cpu_pct():.0f} % of one core; "
            f"start-up {rt.startup_s:.1f} s vs {rb.startup_s:.1f} s)")
    st, sb, sr = med(t), med(b), med(r)
    h = m.dt
    say(f"   median: tether {st:.2f} x real time ({1e3 * h / st:.2f} ms per tick), target >= 20 x")
    say(f"           bare baseline {sb:.2f} x ({1e3 * h / sb:.2f} ms per tick): tether/baseline = {ratio(st, sb):.2f}; "
        f"the transport pattern alone takes {100 * ratio(st, sb):.0f} % of tether's per-tick time")
    say(f"           reference simulator {sr:.0f} x: tether/refsim = {ratio(st, sr):.4f} (refsim is {ratio(sr, st):.0f} x faster)")
    by = {ro: med([row["tether_cpu_by_role"][ro] for row in rows]) for ro in rows[0]["tether_cpu_by_role"]}
    byb = {ro: med([row["baseline_cpu_by_role"][ro] for row in rows]) for ro in rows[0]["baseline_cpu_by_role"]}
    say("           CPU per process [% of one core], tether / baseline: "
        + ", ".join(f"{ro} {by[ro]:.0f}/{byb[ro]:.0f}" for ro in by))
    report["lockstep"] = {"mission": a.mission, "n": m.n, "rate": m.rate, "duration": a.lockstep_duration,
                          "runs": rows, "median": {"tether": st, "baseline": sb, "refsim": sr},
                          "cpu_by_role": {"tether": by, "baseline": byb}}


def _rt_row(rt: Result, rb: Result) -> dict[str, Any]:
    return {"n": rt.n, "rate": rt.rate, "tether_ok": rt.ok, "tether_why": rt.why, "baseline_ok": rb.ok,
            "tether_late": rt.late, "tether_late_max": rt.late_max, "baseline_late": rb.late,
            "tether_total_cpu": rt.total_cpu_pct(), "baseline_total_cpu": rb.total_cpu_pct(),
            "tether_cpu_by_role": {ro: med(rt.cpu_pct(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")},
            "baseline_cpu_by_role": {ro: med(rb.cpu_pct(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")},
            "tether_rss_mib": {ro: med(rt.rss_mib(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")},
            "baseline_rss_mib": {ro: med(rb.rss_mib(ro)) for ro in ("launcher", "leader", "agent", "plant", "recorder")},
            "link_age_ms": [1e3 * pct(rt.link_age, q) if rt.link_age is not None else float("nan") for q in (50, 99)],
            "meas_age_ms": [1e3 * pct(rt.meas_age, q) if rt.meas_age is not None else float("nan") for q in (50, 99)],
            "tether_recorded": rt.complete, "baseline_recorded": rb.complete,
            "complete": rt.complete, "tether_startup_s": rt.startup_s, "baseline_startup_s": rb.startup_s}


def case_scale(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    say(f"\n== 2. real-time scale: ring missions, {a.scale_rate:g} Hz, {a.rt_duration:g} s, 3D; "
        "'holds' = < 1 % late ticks (tick started > 1 period late), run complete")
    say(f"   {'N':>3} {'procs':>5} {'late %':>7} {'max/agent':>9} {'bl late %':>9} {'CPU tether':>10} {'CPU base':>9} "
        f"{'ratio':>6} {'link age p50/p99 ms':>20} {'recorded':>14}  holds")
    rows = []
    largest = None
    for n in a.sizes:
        path, m = mission_file(work, n, a.scale_rate, a.rt_duration)
        settle()
        rt = run_tether(path, m, "realtime", a.rt_duration, work)
        settle()
        rb = run_baseline(m, "realtime", a.rt_duration, work, wake=a.baseline_wake)
        pairs.append((rt, rb))
        row = _rt_row(rt, rb)
        holds = rt.ok and rt.late == rt.late and rt.late < 0.01
        row["holds"] = holds
        rows.append(row)
        say(f"   {n:>3} {len(rt.procs):>5} {100 * rt.late:>7.2f} {100 * rt.late_max:>8.2f}% {100 * rb.late:>9.2f} "
            f"{row['tether_total_cpu']:>9.0f}% {row['baseline_total_cpu']:>8.0f}% "
            f"{ratio(row['tether_total_cpu'], row['baseline_total_cpu']):>6.2f} "
            f"{row['link_age_ms'][0]:>9.1f} / {row['link_age_ms'][1]:<8.1f} {rt.complete:>14}  {'yes' if holds else 'NO'}"
            + ("" if rt.ok else f"  ({rt.why.strip()[:120]})"))
        if holds:
            largest = n
        else:
            break
    say(f"   largest N holding {a.scale_rate:g} Hz: {largest}")
    report["scale"] = {"rate": a.scale_rate, "duration": a.rt_duration, "rows": rows, "largest": largest}


def case_latency(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    n, rate = a.latency_n, a.latency_rate
    path, m = mission_file(work, n, rate, a.latency_duration)
    say(f"\n== 3. latency: ring of {n}, {rate:g} Hz, {a.latency_duration:g} s; a probe subscribes to every plant's and "
        f"agent's state ({a.repeats} repeats); microseconds, p50 / p99")
    say("   plant: plant tick instant -> probe callback (plant timer + one hop through the router)")
    say("   relay: probe arrival of agent i's relay of plant i's sample k - arrival of that sample itself (one more hop:")
    say("          router -> agent callback -> hand-off -> decode -> relay put -> router)")
    rows = []
    for i in range(a.repeats):
        settle()
        rt = run_tether(path, m, "realtime", a.latency_duration, work, probe=True)
        settle()
        rb = run_baseline(m, "realtime", a.latency_duration, work, probe=True, wake=a.baseline_wake)
        pairs.append((rt, rb))
        row = _rt_row(rt, rb)
        row["tether_probe"], row["baseline_probe"] = probe_stats(rt.probe), probe_stats(rb.probe)
        rows.append(row)
        tp_, bp = row["tether_probe"], row["baseline_probe"]
        if "error" in tp_ or "error" in bp:
            say(f"   run {i + 1}: probe failed: {tp_.get('error')} {bp.get('error')}")
            continue
        say(f"   run {i + 1}: plant {tp_['plant_tick'][0]:.0f}/{tp_['plant_tick'][1]:.0f} vs {bp['plant_tick'][0]:.0f}/"
            f"{bp['plant_tick'][1]:.0f}; relay {tp_['relay'][0]:.0f}/{tp_['relay'][1]:.0f} vs {bp['relay'][0]:.0f}/"
            f"{bp['relay'][1]:.0f}; baseline put->callback {bp['put_cb'][0]:.0f}/{bp['put_cb'][1]:.0f}; "
            f"probe got {tp_['received']} vs {bp['received']}; recorder {rt.complete} vs {rb.complete}; "
            f"link age {row['link_age_ms'][0]:.1f}/{row['link_age_ms'][1]:.1f} ms; late {100 * rt.late:.2f} %")
    ok = [r for r in rows if "error" not in r["tether_probe"] and "error" not in r["baseline_probe"]]
    mm: dict[str, Any] = {}
    for who in ("tether", "baseline"):
        for name in ("plant_tick", "agent_tick", "relay", "put_cb"):
            mm[f"{who}_{name}"] = [med([r[f"{who}_probe"][name][j] for r in ok]) for j in (0, 1)]
    age = [med([r["link_age_ms"][j] for r in rows]) for j in (0, 1)]
    meas = [med([r["meas_age_ms"][j] for r in rows]) for j in (0, 1)]
    say(f"   median: plant tick -> callback  tether {mm['tether_plant_tick'][0]:.0f} / {mm['tether_plant_tick'][1]:.0f}, "
        f"baseline {mm['baseline_plant_tick'][0]:.0f} / {mm['baseline_plant_tick'][1]:.0f}  "
        f"(p99 ratio {ratio(mm['tether_plant_tick'][1], mm['baseline_plant_tick'][1]):.2f})")
    say(f"           relay hop through an agent   tether {mm['tether_relay'][0]:.0f} / {mm['tether_relay'][1]:.0f}, "
        f"baseline {mm['baseline_relay'][0]:.0f} / {mm['baseline_relay'][1]:.0f}  "
        f"(p99 ratio {ratio(mm['tether_relay'][1], mm['baseline_relay'][1]):.2f}; target p99 < 2000 and <= 1.5 x)")
    say(f"           baseline put -> callback (transport alone) {mm['baseline_put_cb'][0]:.0f} / {mm['baseline_put_cb'][1]:.0f}")
    say(f"           neighbour data age at use (extra['link_age']) {age[0]:.2f} / {age[1]:.2f} ms; own measurement "
        f"age (extra['meas_age']) {meas[0]:.2f} / {meas[1]:.2f} ms; period {1e3 / rate:.1f} ms")
    report["latency"] = {"n": n, "rate": rate, "duration": a.latency_duration, "runs": rows, "median": mm,
                         "link_age_ms": age, "meas_age_ms": meas}


def case_cpu(a: argparse.Namespace, work: Path, report: dict, pairs: list) -> None:
    if not pairs:
        path, m = mission_file(work, 8, 50.0, a.rt_duration)
        pairs.append((run_tether(path, m, "realtime", a.rt_duration, work),
                      run_baseline(m, "realtime", a.rt_duration, work, wake=a.baseline_wake)))
    say("\n== 4. per process: CPU [% of one core] and VmRSS [MiB], medians over processes (tether / baseline = ratio)")
    say(f"   {'N':>3} {'Hz':>4} {'agent CPU':>22} {'agent RSS':>22} {'plant CPU':>18} {'recorder CPU':>18} {'launcher CPU':>18}")
    rows = []
    for rt, rb in pairs:
        if not (rt.ok and rb.ok):
            continue
        row = {"n": rt.n, "rate": rt.rate}
        cells = []
        for ro, what in (("agent", "cpu"), ("agent", "rss"), ("plant", "cpu"), ("recorder", "cpu"), ("launcher", "cpu")):
            x = med(rt.cpu_pct(ro)) if what == "cpu" else med(rt.rss_mib(ro))
            y = med(rb.cpu_pct(ro)) if what == "cpu" else med(rb.rss_mib(ro))
            row[f"{ro}_{what}"] = [x, y, ratio(x, y)]
            w = 22 if ro == "agent" else 18
            cells.append(f"{x:.1f}/{y:.1f}={ratio(x, y):.2f}".rjust(w))
        rows.append(row)
        say(f"   {rt.n:>3} {rt.rate:>4g} " + " ".join(cells))
    if rows:
        cpu_r = med([r["agent_cpu"][2] for r in rows])
        rss_r = med([r["agent_rss"][2] for r in rows])
        say(f"   median agent ratios: CPU {cpu_r:.2f} (target <= 1.3), RSS {rss_r:.2f} (target <= 1.1)")
        report["cpu"] = {"rows": rows, "agent_cpu_ratio": cpu_r, "agent_rss_ratio": rss_r}


def profile_run(mission: str, clock: str, duration: float, who: str, work: Path, top: int = 25) -> None:
    """Run ``tether run`` (launcher in this process) with one child under cProfile and print where its
    time goes. ``who`` is ``role:id`` (``agent:1``, ``recorder:0``, ...). The child is started by the
    launcher exactly as usual but through ``bench/runtime.py _cprofile FILE`` instead of ``-m
    tether.cli``: ``cProfile`` with ``time.thread_time`` as its timer, so the figures are CPU time of
    the asyncio thread (time asleep in epoll counts as zero, Zenoh's and the callbacks' threads are
    not in it: see the per-thread CPU of the cases for those)."""
    import asyncio
    import cProfile  # noqa: F401  (the child runs it)
    import pstats

    from deploy import local
    from tether.node import load_mission

    role, nid = who.split(":")
    path = catalog.resolve(mission)
    out = work / f"profile-{role}-{nid}-{clock}"
    prof = out / f"{role}-{nid}.prof"
    out.mkdir(parents=True, exist_ok=True)
    real_popen = subprocess.Popen

    def popen(cmd, *args, **kwargs):
        if "tether.cli" in cmd and cmd[cmd.index("tether.cli") + 1] == role and \
                (role in ("leader", "recorder") or cmd[cmd.index("--id") + 1] == nid):
            i = cmd.index("-m")
            cmd = [*cmd[:i], __file__, "_cprofile", str(prof), *cmd[i + 2:]]
        return real_popen(cmd, *args, **kwargs)

    load_mission(path, duration)
    opts = local.LaunchOptions(out=out, clock=clock, duration=duration, progress=False)
    local.subprocess.Popen = popen
    try:
        status = asyncio.run(local.run(path, opts))
    finally:
        local.subprocess.Popen = real_popen
    say(f"tether run {mission} --clock {clock} --duration {duration:g}: exit {status}; profile of {role}/{nid}: {prof}")
    if prof.exists():
        st = pstats.Stats(str(prof))
        st.sort_stats("tottime").print_stats(top)
        st.sort_stats("cumulative").print_stats(top)


def cprofile_child(out: str, args: list[str]) -> int:
    """``python bench/runtime.py _cprofile OUT <tether.cli args>``: run the CLI under cProfile timed by
    the main thread's CPU clock; stats are written to OUT when it returns (SIGTERM ends it normally)."""
    import cProfile
    import signal

    from tether import cli

    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    prof = cProfile.Profile(time.thread_time)
    try:
        return prof.runcall(cli.main, args)
    finally:
        prof.dump_stats(out)


def main(argv: list[str]) -> None:
    if argv and argv[0] == "_cprofile":
        sys.exit(cprofile_child(argv[1], argv[2:]))
    if argv and argv[0] == "_probe":
        ep, ns, rate, kind, n, steps, out = argv[1:8]
        return run_probe(ep, ns, float(rate), kind, int(n), int(steps), out)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", nargs="+", choices=["lockstep", "scale", "latency", "cpu"],
                    default=["lockstep", "scale", "latency", "cpu"])
    ap.add_argument("--repeats", type=int, default=3, help="runs per figure in cases 1 and 3 (medians)")
    ap.add_argument("--mission", default="section4", help="case 1's mission (N = 4, 100 Hz)")
    ap.add_argument("--lockstep-duration", type=float, default=10.0, help="case 1: mission seconds per run")
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16, 32], help="case 2: N, stepped until one fails")
    ap.add_argument("--scale-rate", type=float, default=50.0)
    ap.add_argument("--rt-duration", type=float, default=15.0, help="case 2 (and 4): mission seconds per run")
    ap.add_argument("--latency-n", type=int, default=8)
    ap.add_argument("--latency-rate", type=float, default=100.0)
    ap.add_argument("--latency-duration", type=float, default=10.0)
    ap.add_argument("--baseline-wake", action="store_true",
                    help="real-time baseline wakes its loop on every sample, as tether's nodes do")
    ap.add_argument("--quiet-below", type=float, default=0.5,
                    help="before each run, wait until the machine uses fewer cores than this (other users)")
    ap.add_argument("--quiet-timeout", type=float, default=60.0, help="... but no longer than this [s]")
    ap.add_argument("--work", type=Path, default=None, help="keep run directories here (default: a temp dir)")
    ap.add_argument("--json", type=Path, default=None, help="write every figure here")
    ap.add_argument("--profile", metavar="ROLE:ID", default=None,
                    help="instead of the cases: one tether run with this process under cProfile (e.g. agent:1)")
    ap.add_argument("--profile-clock", choices=["lockstep", "realtime"], default="lockstep")
    ap.add_argument("--profile-duration", type=float, default=10.0)
    a = ap.parse_args(argv)
    if a.profile:
        work = a.work or Path(tempfile.mkdtemp(prefix="tether-profile-"))
        return profile_run(a.mission, a.profile_clock, a.profile_duration, a.profile, work)
    QUIET.update(limit=a.quiet_below, timeout=a.quiet_timeout)
    report: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python": sys.version.split()[0],
                                          "load_at_start": os.getloadavg()}}
    say(f"bench/runtime.py: {os.cpu_count()} CPUs, Python {sys.version.split()[0]}, load average at start "
        + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    pairs: list = []
    with tempfile.TemporaryDirectory(prefix="tether-bench-") as tmp:
        work = a.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        if "lockstep" in a.cases:
            case_lockstep(a, work, report)
        if "scale" in a.cases:
            case_scale(a, work, report, pairs)
        if "latency" in a.cases:
            case_latency(a, work, report, pairs)
        if "cpu" in a.cases:
            case_cpu(a, work, report, pairs)
        say(f"\ndone in {time.monotonic() - t0:.0f} s; load average at end " + " ".join(f"{x:.2f}" for x in os.getloadavg()))
    if a.json is not None:
        report["machine"]["load_at_end"] = os.getloadavg()
        a.json.write_text(json.dumps(report, indent=1, default=float))


if __name__ == "__main__":
    main(sys.argv[1:])
