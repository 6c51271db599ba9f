"""The bare Zenoh baseline of ``bench/runtime.py``: the processes of ``bench/baseline_node.py`` with
the keys, payload sizes, QoS, rates, topology and transport of a ``tether run`` but trivial work, and
the latency probe that listens to either.

``run_baseline`` writes the spec every baseline process reads (:func:`baseline_spec`), starts the
hub and its members and measures them from outside as ``bench/runtime.py`` measures ``tether run``.
Run as a script, this file is the probe::

    python bench/baseline.py ENDPOINT NAMESPACE RATE KIND N_AGENTS STEPS OUT.json
"""

from __future__ import annotations

import json
import os
import queue
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from bench.procstat import Proc, Result, Window, pct, read_lines, reap  # noqa: E402
from deploy import localtls  # noqa: E402
from deploy.children import HANDOVER  # noqa: E402
from deploy.supervise import pace  # noqa: E402

try:  # real time: agents tick this fraction of a period after plants and the leader (if the runtime does)
    from tether.clock import AGENT_PHASE  # noqa: E402
except ImportError:
    AGENT_PHASE = 0.0
from tether import jsonout  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether import safefs  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether import wire  # noqa: E402

if TYPE_CHECKING:
    from tether.clock import ClockKind

PY = sys.executable
BASELINE = str(REPO / "bench" / "baseline_node.py")
REALTIME_QOS = {"cmd": "COMMAND", "telemetry": "TELEMETRY"}
"""Real time: the presets ``agent/node.py`` declares its command and telemetry publishers with (every
other stream, and every stream in lockstep, gets what ``Node.publisher`` gives: STATE / SYNC)."""
START_LEAD = 1.0  # deploy.options.LaunchOptions.start_lead: tick 0 comes this long after "all up"
WINDOW = 8  # deploy.options.WINDOW: tether run's window with one process per plant
LOOP = {"bare": "asyncio"}
"""The event loop of the bare baseline's processes (``--bare-loop``; by default tether's own,
``tether/evloop.py``)."""


# =========================================================================== sizes and specs
def example_message(cls: type, m: ms.Mission, width: int) -> Any:
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
            elif isinstance(t.item_type, msgspec.inspect.StructType):
                values[f.name] = [example_message(t.item_type.cls, m, width)] * width
            else:
                raise TypeError(f"wire_sizes: no example for {cls.__name__}.{f.name} (a list of {t.item_type})")
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
    size = {name: len(wire.encode(example_message(cls, m, width)))
            for name, cls in (("state", wire.State), ("plant_state", wire.PlantState), ("cmd", wire.Command),
                              ("telemetry", wire.Telemetry), ("tick", wire.Tick), ("ack", wire.Ack),
                              ("start", wire.Start))}
    size["start"] = max(24, size["start"])
    return size


def baseline_spec(m: ms.Mission, clock: ClockKind, duration: float, wake: bool,
                  variant: dict[str, Any] | None = None) -> dict[str, Any]:
    """What every baseline process needs: the mission's shape, the sizes, the exact Zenoh configs
    (those ``deploy.local`` gives the launcher's router and its clients). ``variant`` changes one
    thing for an experiment: ``direct`` callbacks, ``qos`` (real time: stream -> preset), ``window``,
    ``colocate`` (lockstep: plants computed inside their agents), ``handover`` (False: no
    ``ZENOH_RUNTIME``), ``config`` (Zenoh key -> JSON value, inserted in every config), ``mesh``
    (every process but the hub a peer: :func:`run_baseline` gives each its endpoint)."""
    v = variant or {}
    placeholder = tp.loopback_endpoint(7447)  # replaced by the real endpoint in each process
    client = tp.ZenohSettings(mode="client", connect=(placeholder,), lease=2.0, connect_timeout=10.0)
    # the router's per-link ingress limits (real time), as the launcher's pace gives its router
    limits = pace(clock).limits(m, m.name)
    router = tp.ZenohSettings(mode="router", listen=(placeholder,), lease=2.0, ingress_limits=limits)
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
        "wake": wake, "start_lead": START_LEAD, "direct": bool(v.get("direct")),
        "qos": v.get("qos", REALTIME_QOS), "agent_phase": AGENT_PHASE, "colocate": bool(v.get("colocate")),
        "batch": int(v.get("batch", 0)), "loop": v.get("loop", LOOP["bare"]),
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
    if kind == "tether":
        msg = wire.decode(payload)
        if not isinstance(msg, wire.Start):
            raise TypeError(f"the probe heard a {type(msg).__name__} on the start key, not a Start")
        epoch = msg.epoch
    else:
        epoch = struct.unpack_from("<d", payload, 16)[0]
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
    Path(out).write_text(jsonout.dumps({"rows": rows, "received": len(arrivals), "expected": expected}, indent=None))


PHASES = (0.25, 0.5, 0.75, 0.9)


def probe_stats(probe: dict[str, Any] | None, rate: float) -> dict[str, Any]:
    """p50/p99 [us] of: plant tick instant -> probe (one hop), agent relay of the same sample -> probe
    (two hops), their difference per sample (one hop through the agent: its callback, hand-off,
    decode and relay publish), and for the baseline put -> callback; sample counts; and, for agents
    ticking a fraction ``phase`` of a period after their plants, the share of relayed samples that
    arrive after that instant (a neighbour hears them about when the probe does)."""
    if not probe or "error" in probe:
        return {"error": (probe or {}).get("error", "no probe data")}
    rows = probe["rows"]
    plant = {(i, k): lat for role, i, k, lat, _ in rows if role == 0}
    agent = {(i, k): lat for role, i, k, lat, _ in rows if role == 1}
    relay = [agent[key] - plant[key] for key in agent.keys() & plant.keys()]
    h_us = 1e6 / rate
    out: dict[str, Any] = {"received": f"{probe['received']}/{probe['expected']}",
                           "plant_received": len(plant), "agent_received": len(agent),
                           "after_phase": {str(ph): float(np.mean([x > ph * h_us for x in agent.values()]))
                                           if agent else float("nan") for ph in PHASES}}
    for name, xs in (("plant_tick", list(plant.values())), ("agent_tick", list(agent.values())), ("relay", relay),
                     ("put_cb", [sent for *_, sent in rows if sent is not None])):
        out[name] = [pct(xs, 50), pct(xs, 99)] if xs else [float("nan")] * 2
    return out


def spawn_probe(endpoint: str, ns: str, rate: float, kind: str, n: int, steps: int, out: Path,
                 wait: bool = True) -> subprocess.Popen[str]:
    """Start the probe; ``wait``: until it has subscribed (else call :func:`probe_ready`)."""
    p = subprocess.Popen([PY, __file__, endpoint, ns, repr(rate), kind, str(n), str(steps), str(out)],
                         env=child_env(), stdout=subprocess.PIPE, stdin=subprocess.DEVNULL, text=True,
                         start_new_session=True)
    if wait:
        probe_ready(p)
    return p


def probe_ready(p: subprocess.Popen[str]) -> None:
    if p.stdout is None:
        raise RuntimeError("the probe was started without a pipe on its stdout")
    line = p.stdout.readline().strip()
    if line != "ready":
        raise RuntimeError(f"probe did not start (said {line!r})")


# =========================================================================== baseline runs
def run_baseline(m: ms.Mission, clock: ClockKind, duration: float, work: Path, probe: bool = False,
                 wake: bool = False, variant: dict[str, Any] | None = None, secure: bool = True) -> Result:
    """The same run with ``bench/baseline_node.py`` processes (hub = router + clock, like the launcher).

    ``secure`` (what ``tether run`` does without ``--insecure``): every process's session is the one
    ``deploy.localtls`` gives the launcher's children, made for this run the same way: mTLS with one
    certificate per process, the router's access rules and ingress limits (so the baseline pays for
    the transport what tether pays). Otherwise plain TCP (tether with ``--insecure``)."""
    spec = baseline_spec(m, clock, duration, wake, variant)
    env = child_env(handover=(variant or {}).get("handover", True))
    tag = f"baseline-{clock}-{m.n}-{time.monotonic_ns()}"
    spec_path = work / f"{tag}.json"
    res = Result("baseline", m.n, clock, m.rate)
    endpoint = tp.loopback_endpoint(tp.free_tcp_port())
    roles = ("agent",) if spec.get("colocate") else ("agent", "plant")
    members = [("leader", m.leader.id), *[(r, a) for a in m.agent_ids for r in roles], ("recorder", 0)]
    if (variant or {}).get("mesh"):  # every process a peer on its own port, as deploy.local's mesh
        spec["mesh"] = {f"{r}-{i}": tp.loopback_endpoint(tp.free_tcp_port()) for r, i in members}
    if secure:
        if probe:
            raise ValueError("the latency probe is a plain client: run the baseline with secure=False")
        endpoint = "tls/" + endpoint.split("/", 1)[1]
        sec = localtls.prepare(m, m.name, safefs.make_out(work / tag), members, endpoint, (), 2.0,
                               pace(clock).limits(m, m.name))
        listen = {k: "tls/" + ep.split("/", 1)[1] for k, ep in spec.get("mesh", {}).items()}
        spec["tls"] = {"router": str(sec.configs["router"]),
                       **{f"{r}-{i}": str(sec.child(r, i, endpoint, listen.get(f"{r}-{i}"))) for r, i in members}}
    spec_path.write_text(json.dumps(spec))
    t_start = time.monotonic()
    hub = subprocess.Popen([PY, BASELINE, str(spec_path), "hub", endpoint], stdout=subprocess.PIPE,
                           stdin=subprocess.DEVNULL, text=True, env=launcher_env(), start_new_session=True)
    kids: list[tuple[subprocess.Popen[str], str, int]] = []
    probe_proc = None
    probe_out = work / f"{tag}.probe.json"
    try:
        if hub.stdout is None:
            raise RuntimeError("the baseline hub was started without a pipe on its stdout")
        if hub.stdout.readline().strip() != "listening":
            raise RuntimeError("baseline hub did not start")
        if probe:
            probe_proc = spawn_probe(endpoint, m.name, m.rate, "bare", m.n, spec["steps"], probe_out)
        for role, nid in members:
            kp = subprocess.Popen([PY, BASELINE, str(spec_path), role, str(nid), endpoint], stdout=subprocess.PIPE,
                                  stdin=subprocess.DEVNULL, text=True, env=env, start_new_session=True)
            kids.append((kp, role, nid))
        res.procs = [Proc(kp.pid, role, nid) for kp, role, nid in kids] + [Proc(hub.pid, "launcher", 0)]
        if probe_proc is not None:
            res.procs.append(Proc(probe_proc.pid, "probe", 0))
        _watch_hub(hub.stdout, res, Window(res.procs), clock, t_start, 120 + 3 * duration)
        hub.wait(timeout=30)
        if not res.ok:
            return res
        _collect(kids, res, m, spec["steps"])
    finally:
        for kp, _, _ in kids:
            if kp.poll() is None:
                kp.kill()
                kp.wait()
        if hub.poll() is None:
            hub.kill()
            hub.wait()
        if probe_proc is not None:
            reap(probe_proc, 30.0)
    if probe and probe_out.exists():
        res.probe = json.loads(probe_out.read_text())
    return res



def _watch_hub(stdout: Iterable[str], res: Result, window: Window, clock: str, t_start: float,
               timeout: float) -> None:
    """Follow the hub's lines until it closes its stdout: start-up time, the measured window (opened
    at tick 0, closed at "ran ..."), a stall or missing process. Blocks up to ``timeout`` [s]."""
    lines: queue.Queue[str | None] = queue.Queue()
    threading.Thread(target=read_lines, args=(stdout, lines), daemon=True).start()
    deadline = time.monotonic() + timeout
    while True:
        try:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise TimeoutError("baseline hub did not finish in time") from None
        if line is None:
            return
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


def _collect(kids: list[tuple[subprocess.Popen[str], str, int]], res: Result, m: ms.Mission, steps: int) -> None:
    """Read each member's last line (its JSON summary; blocks until it exits): the agents' late ticks
    (real time) and the samples the recorder received."""
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
            res.complete = f"{info['received']}/{(1 + 2 * m.n) * (steps + 1)}"
    if res.clock == "realtime" and late:
        res.late = sum(late) / (len(late) * (steps + 1))
        res.late_max = max(late) / (steps + 1)


if __name__ == "__main__":
    ep, ns, rate, kind, n, steps, out = sys.argv[1:8]
    run_probe(ep, ns, float(rate), kind, int(n), int(steps), out)
