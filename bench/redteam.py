"""The red-team table: forged inputs against a real ``section4`` run in real time.

    python bench/redteam.py                                  # every attack once, 32 s missions
    python bench/redteam.py --attacks stamp estop --reps 3   # some attacks, 3 runs each
    python bench/redteam.py --json FILE                      # also keep every figure of every run
    python bench/redteam.py --reanalyse WORK                 # the table again from the runs kept in WORK

Each run is ``tether run section4 --clock realtime --insecure --listen tcp/127.0.0.1:P --duration D
--quiet`` (one launcher, ten processes). The script is the attacker: a plain Zenoh client of the
run's router that hears every state, command and telemetry key and publishes well-formed forged
samples with the victim's sender id on the victim's key (:func:`forge`), from the attack's start
``--at`` (mission time, from the run's start message) on. It also records every genuine sample it
hears, stamped with the wall clock, and after the run reads ``run.npz``, the plants' logs and the
launcher's exit status. Each run is bounded (the mission's duration, then ``--grace`` s) and
stops by itself.

Attacks (the victim's real sample is the template of each forged one: its sequence number + 1, so
the victim's next genuine sample reads as a duplicate):

* ``none``: no attack (the baseline row);
* ``stamp``: one command on ``agent/2/cmd`` for the current tick (the one after the genuine command
  just heard: a receiver keeps the first sample of each tick, so a forgery must come first) stamped
  ``t = 1e9``;
* ``cmd``: commands ``u = [20, 0]`` on ``agent/2/cmd`` for ``--cmd-for`` (1 s), each for the tick
  after the genuine one just heard, stamped for that tick;
* ``leader-drift``: the leader's state for the next tick, computed from the mission's own leader
  profile, moved ``--drift`` (0.5 m/s) times the time since ``--at`` along +y, its velocity
  +0.5 m/s along y, for ``--drift-for`` (20 s): every sample a plausible step ahead of the truth;
* ``agent-drift`` / ``plant-drift``: the same drift on ``agent/1/state`` / ``plant/1/state``
  (``p + v h`` of the genuine sample, plus the drift);
* ``hold``: ``agent/1/state`` samples saying ``mode = HOLD`` for ``--hold-for`` (5 s);
* ``estop``: one ``plant/2/state`` sample saying ``mode = ESTOP``;
* ``recorder-kill``: SIGKILL to the run's recorder process (a child of the launcher); ``record``
  then says what run file is left (``run.npz`` and how many ticks it holds, or the recorder's
  journal, ``journal.mcap``, alone).

Figures (per run; the table prints the worst over the repetitions, latency as median / largest):

* ``err`` [m]: the true formation error, ``max_i ||p_i - h_i - p_L(t)||`` over the vehicles whose
  plant and agent both report FLYING, with ``p_i`` from the plants' own genuine samples (as heard by
  the attacker, the forged ones left out) and ``p_L`` the leader's analytic profile (never a leader
  sample): the largest from ``--at`` on, and the largest over the last 10 s of the run.
* ``out``: whether a vehicle left the envelope, and how. A vehicle leaves it when (a) its speed is
  above the mission's ``max_speed``; (b) it is outside the mission's geofence, if it has one; (c)
  while its plant and agent have reported FLYING for 5 s in a row (a vehicle back from a HOLD has
  that long to catch up with its slot), it is more than ``--slot`` (5 m) from its slot
  ``p_L(t) + h_i``; (d) while either reports another mode, it is more than ``--slot`` beyond the
  distance its brake takes it (:func:`tether.failsafe.stopping_distance` of its speed) from where
  that stretch began (a holding or landed vehicle that moves away). Judged from ``--at`` on (the
  baseline row too), so that a start on a busy host is not counted against an attack.
* ``sep`` [m]: the smallest distance between two vehicles from ``--at`` on.
* ``reaction``: what the swarm did about it from ``--at`` on: the agents' gate rejections by reason
  (growth of ``Telemetry.gate`` over the attack), mode changes of agents (``a2``) and plants
  (``p2``) with their reasons, and the plants' watchdog rejections (their logs' end-of-run counts).
* ``first`` [s]: the first reaction's mission time (an event's tick time, or the telemetry tick
  whose gate count rose) minus the first forged sample's send time. A reaction is not a detection
  by itself: the reasons say whether the swarm named the attack or was moved by it.
* ``rec`` [m]: the largest distance between a plant position in ``run.npz`` and the genuine sample
  of the same tick (0: the run file tells the truth; large: it recorded a forgery, or lost the truth).
* ``end``: the final mode of every vehicle (plant's), and the launcher's exit status.

The load average (1 min) is printed beside every run: this is a real-time run, and a busy host
changes it.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import zenoh  # noqa: E402

from bench.faults import drain_stderr, fmt, pct, plant_events, wall  # noqa: E402
from leader import profile  # noqa: E402
from tether import catalog  # noqa: E402
from tether import failsafe  # noqa: E402
from tether import jsonout  # noqa: E402
from tether import mission as ms  # noqa: E402
from tether import transport as tp  # noqa: E402
from tether import wire  # noqa: E402
from tether.node import load_mission  # noqa: E402
from tether.runfile import Run  # noqa: E402

MISSION = "section4"
ATTACKS = ("none", "stamp", "cmd", "leader-drift", "agent-drift", "plant-drift", "hold", "estop", "recorder-kill")
WHAT = {
    "none": "no attack",
    "stamp": "one agent/2/cmd, next tick, t = 1e9",
    "cmd": "agent/2/cmd u = [20, 0] for 1 s",
    "leader-drift": "leader/5/state drift 0.5 m/s for 20 s",
    "agent-drift": "agent/1/state drift 0.5 m/s for 20 s",
    "plant-drift": "plant/1/state drift 0.5 m/s for 20 s",
    "hold": "agent/1/state mode = HOLD for 5 s",
    "estop": "one plant/2/state mode = ESTOP",
    "recorder-kill": "kill -9 of the recorder",
}
DOG_LINE = re.compile(r"vehicle (\d+): commands rejected by its watchdog: (.*)$")
CODE = {wire.FLYING: "F", wire.HOLD: "H", wire.LAND: "L", wire.LANDED: "LD", wire.ESTOP: "E"}


@dataclass(frozen=True)
class Plan:
    """When and how hard an attack is, in mission time [s] (real time since the run's tick 0)."""

    at: float = 8.0
    """The attack's start [s]."""
    drift: float = 0.5
    """Drift speed of the drift attacks [m/s]."""
    drift_for: float = 20.0
    """How long a drift lasts [s]."""
    cmd_for: float = 1.0
    """How long forged commands are sent [s]."""
    hold_for: float = 5.0
    """How long forged HOLD reports are sent [s]."""
    cmd_u: float = 20.0
    """The forged command's x component [m/s^2]."""


def victim(attack: str, m: ms.Mission) -> str | None:
    """The key an attack publishes on (and whose genuine samples trigger each forgery)."""
    keys = wire.Keys(m.name)
    return {"stamp": keys.topic("agent", 2, "cmd"), "cmd": keys.topic("agent", 2, "cmd"),
            "leader-drift": keys.topic("leader", m.leader.id, "state"),
            "agent-drift": keys.topic("agent", 1, "state"), "plant-drift": keys.topic("plant", 1, "state"),
            "hold": keys.topic("agent", 1, "state"), "estop": keys.topic("plant", 2, "state")}.get(attack)


def forge(attack: str, msg: Any, now: float, sent: int, m: ms.Mission, plan: Plan,
          leader: profile.Reference) -> Any | None:
    """The forged sample to publish in answer to the genuine ``msg`` heard at mission time ``now`` [s]
    (``sent`` forged so far), or None. Pure: the attack's whole logic."""
    h = m.dt
    if now < plan.at:
        return None
    k1 = msg.k + 1
    e = np.zeros(m.dim)
    e[1] = 1.0  # the drift's direction: across the leader's path (+y)
    off = plan.drift * max(0.0, k1 * h - plan.at) * e

    def ahead(**kw: Any) -> Any:
        """The genuine sample one tick on (``p + v h``), its sequence number + 1, with ``kw`` changed."""
        fields: dict[str, Any] = {"seq": msg.seq + 1, "k": k1, "t": k1 * h,
                                  "p": (np.asarray(msg.p) + h * np.asarray(msg.vel)).tolist()}
        if "events" in msg.__struct_fields__:
            fields["events"] = []
        fields.update(kw)
        return msgspec.structs.replace(msg, **fields)

    if attack == "stamp":
        return msgspec.structs.replace(msg, seq=msg.seq + 1, k=k1, t=1e9) if sent == 0 else None
    if attack == "cmd":
        if now >= plan.at + plan.cmd_for:
            return None
        u = [0.0] * m.dim
        u[0] = plan.cmd_u
        return msgspec.structs.replace(msg, seq=msg.seq + 1, k=k1, t=k1 * h, u=u)
    if attack == "leader-drift":
        if now >= plan.at + plan.drift_for:
            return None
        p, v, a = leader(k1 * h)
        return ahead(p=(p + off).tolist(), vel=(v + plan.drift * e).tolist(), a=np.asarray(a).tolist())
    if attack in ("agent-drift", "plant-drift"):
        if now >= plan.at + plan.drift_for:
            return None
        p = np.asarray(msg.p) + h * np.asarray(msg.vel) + off
        return ahead(p=p.tolist(), vel=(np.asarray(msg.vel) + plan.drift * e).tolist())
    if attack == "hold":
        return ahead(mode=wire.HOLD) if now < plan.at + plan.hold_for else None
    if attack == "estop":
        return ahead(mode=wire.ESTOP) if sent == 0 else None
    return None


# =========================================================================== the attacker
class Attacker:
    """A Zenoh client of the run's router: hears every state, command and telemetry key (arrivals
    stamped with :func:`bench.faults.wall` in the callback, which only appends), and forges on the
    victims' keys from a thread of its own (the callback hands the victims' samples to it). ``plans``:
    the attacks of the run, each with its own plan (two attacks on one key: one of them is used)."""

    def __init__(self, endpoint: str, m: ms.Mission, plans: dict[str, Plan]):
        self.endpoint, self.m, self.plans = endpoint, m, plans
        self.by_key = {key: attack for attack in plans if (key := victim(attack, m)) is not None}
        self.leader = profile.build(m.leader, m.dim)
        self.arrivals: list[tuple[float, str, bytes]] = []
        self.forged: set[bytes] = set()
        self.sent: dict[str, list[tuple[float, int]]] = {attack: [] for attack in plans}
        """Per attack: (mission time, tick) of every forged sample put."""
        self.epoch: float | None = None
        self._q: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._session: zenoh.Session | None = None
        self._subs: list[Any] = []
        self._pubs: dict[str, zenoh.Publisher] = {}
        self._worker: threading.Thread | None = None

    def open(self, timeout: float = 20.0) -> None:
        cfg = tp.zenoh_config(tp.ZenohSettings(mode="client", connect=(self.endpoint,), lease=2.0,
                                               connect_timeout=timeout))
        deadline = time.monotonic() + timeout
        while True:  # the launcher's router listens a moment after it starts
            try:
                self._session = zenoh.open(cfg)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        ns, s, by_key = self.m.name, self._session, self.by_key

        def on_sample(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()
            k = str(sample.key_expr)
            self.arrivals.append((wall(), k, data))
            if k in by_key:
                self._q.put((k, data))

        def on_start(sample: zenoh.Sample) -> None:
            msg = wire.decode(sample.payload.to_bytes())
            if isinstance(msg, wire.Start):
                self.epoch = msg.epoch

        self._subs = [s.declare_subscriber(wire.Keys(ns).start, on_start)]
        for pattern in ("agent/*/cmd", "agent/*/state", "agent/*/telemetry", "plant/*/state", "leader/*/state"):
            self._subs.append(s.declare_subscriber(f"tether/{ns}/{pattern}", on_sample))
        self._pubs = {key: tp.declare_publisher(s, key, tp.SYNC) for key in by_key}
        if by_key:
            self._worker = threading.Thread(target=self._run, name="attacker", daemon=True)
            self._worker.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                key, data = self._q.get(timeout=0.1)
            except queue.Empty:
                continue
            if data in self.forged or self.epoch is None:
                continue
            now = wall() - self.epoch
            try:
                msg = wire.decode(data)
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue
            attack = self.by_key[key]
            sent = self.sent[attack]
            fake = forge(attack, msg, now, len(sent), self.m, self.plans[attack], self.leader)
            if fake is None:
                continue
            payload = wire.encode(fake)
            self.forged.add(payload)  # before the put: our own sample comes back to our subscriber
            self._pubs[key].put(payload)
            sent.append((wall() - self.epoch, fake.k))

    def close(self) -> None:
        self._stop.set()
        if self._worker is not None:
            self._worker.join(5)
        for sub in self._subs:
            try:
                sub.undeclare()
            except zenoh.ZError:
                pass
        for pub in self._pubs.values():
            pub.undeclare()
        if self._session is not None:
            self._session.close()

    def save(self, out: Path) -> None:
        """``attack.npz``: every genuine arrival (wall, key, payload); ``attack.json``: the attacks, their
        plans and every forged sample's send time and tick."""
        genuine = [(w, k, d) for w, k, d in self.arrivals if d not in self.forged]
        np.savez_compressed(out / "attack.npz",
                            wall=np.array([w for w, _, _ in genuine], dtype=float),
                            key=np.array([k for _, k, _ in genuine], dtype=object),
                            payload=np.array([d for _, _, d in genuine], dtype=object),
                            epoch=np.array(math.nan if self.epoch is None else self.epoch))
        (out / "attack.json").write_text(json.dumps({"plans": {a: p.__dict__ for a, p in self.plans.items()},
                                                     "sent": self.sent}) + "\n")


@dataclass
class Heard:
    """What the attacker heard of one run: genuine messages (wall, role, id, topic, message) and its own sends."""

    rows: list[tuple[float, str, int, str, Any]]
    sent: dict[str, list[tuple[float, int]]]
    """Per attack: (mission time [s], tick) of every forged sample put."""
    epoch: float | None

    @classmethod
    def load(cls, out: Path) -> "Heard":
        z = np.load(out / "attack.npz", allow_pickle=True)
        rows = []
        for w, key, data in zip(z["wall"], z["key"], z["payload"]):
            try:
                role, nid, topic = wire.Keys.parse(str(key))
                rows.append((float(w), role, nid, topic, wire.decode(bytes(data))))
            except (ValueError, msgspec.DecodeError, msgspec.ValidationError):
                continue
        epoch = float(z["epoch"])
        meta = json.loads((out / "attack.json").read_text())
        # the first runs of this script kept one attack's sends in attack.npz
        sent = meta["sent"] if "sent" in meta else {meta["attack"]: z["sent"].tolist()}
        return cls(rows, {a: [(float(t), int(k)) for t, k in xs] for a, xs in sent.items()},
                   None if math.isnan(epoch) else epoch)


# =========================================================================== one run
@dataclass
class Launched:
    out: Path
    status: int
    wall: float
    load: tuple[float, float, float]
    stderr: list[str] = field(default_factory=list)


def child_pid(parent: int, role: str) -> int | None:
    """The pid of ``parent``'s child process running ``python -m cli <role>`` (Linux ``/proc``), or None."""
    kids: list[str] = []
    for task in Path(f"/proc/{parent}/task").glob("*"):
        try:
            kids += (task / "children").read_text().split()
        except OSError:
            continue
    for kid in kids:
        try:
            argv = Path(f"/proc/{kid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"cli" in argv and role.encode() in argv:
            return int(kid)
    return None


def _kill_when_due(att: Attacker, p: subprocess.Popen[str], role: str, at: float, deadline: float) -> None:
    """SIGKILL ``role``'s process of the run at mission time ``at``; its send time goes in ``att.sent``."""
    while p.poll() is None and time.monotonic() < deadline:
        if att.epoch is not None and wall() - att.epoch >= at:
            pid = child_pid(p.pid, role)
            if pid is not None:
                os.kill(pid, signal.SIGKILL)
                att.sent.setdefault(f"{role}-kill", []).append((wall() - att.epoch, -1))
            return
        time.sleep(0.01)


def launch(out: Path, plans: dict[str, Plan], m: ms.Mission, duration: float, grace: float = 90.0) -> Launched:
    """One run under the attacks ``plans``, bounded: ``duration`` + ``grace`` s, then SIGKILL."""
    port = tp.free_tcp_port()
    ep = f"tcp/127.0.0.1:{port}"
    cmd = [sys.executable, "-m", "cli", "run", MISSION, "--clock", "realtime", "--out", str(out),
           "--duration", repr(duration), "--quiet", "--listen", ep, "--insecure"]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)
    lines: list[str] = []

    th = drain_stderr(p, lines.append)
    att = Attacker(ep, m, plans)
    try:
        att.open()
        if "recorder-kill" in plans:
            att.sent.pop("recorder-kill", None)  # filled when the kill is made
            _kill_when_due(att, p, "recorder", plans["recorder-kill"].at, t0 + duration + grace)
        p.wait(max(1.0, t0 + duration + grace - time.monotonic()))
    except subprocess.TimeoutExpired:
        lines.append(f"redteam: the run outlived {duration + grace:g} s: killed")
    finally:
        if p.poll() is None:
            p.kill()
        p.wait()
        th.join(5)
        att.close()
    out.mkdir(parents=True, exist_ok=True)
    att.save(out)
    (out / "launcher.log").write_text("\n".join(lines) + "\n")
    return Launched(out, p.returncode, time.monotonic() - t0, os.getloadavg(), lines)


# =========================================================================== analysis
def _series(heard: Heard, role: str, topic: str, n_ticks: int, ids: list[int]) -> dict[int, dict[int, Any]]:
    """Per id, per tick: the first genuine message of that role and topic heard for the tick."""
    by: dict[int, dict[int, Any]] = {i: {} for i in ids}
    for _, r, nid, tp_, msg in heard.rows:
        if r == role and tp_ == topic and nid in by and 0 <= msg.k <= n_ticks:
            by[nid].setdefault(msg.k, msg)
    return by


def analyse(out: Path, attack: str, plan: Plan, slot: float = 5.0, status: int | None = None,
            rejoin: float = 5.0) -> dict[str, Any]:
    """Every figure of one run (see the module docstring)."""
    m = load_mission(catalog.resolve(MISSION), None)
    sf, h = m.safety, m.dt
    heard = Heard.load(out)
    duration = float(json.loads((out / "redteam.json").read_text())["duration"]) \
        if (out / "redteam.json").exists() else m.duration
    T = int(round(duration / h))
    ids = [a.id for a in m.agents]
    n = len(ids)
    offsets = np.array([a.offset for a in m.agents], dtype=float)
    t = np.arange(T + 1) * h
    pl = profile.build(m.leader, m.dim)(t)[0]
    P = np.full((T + 1, n, m.dim), np.nan)
    V = np.full((T + 1, n, m.dim), np.nan)
    pmode = np.full((T + 1, n), -1)
    amode = np.full((T + 1, n), -1)
    plants = _series(heard, "plant", "state", T, ids)
    tele = _series(heard, "agent", "telemetry", T, ids)
    for c, i in enumerate(ids):
        for k, msg in plants[i].items():
            P[k, c], V[k, c], pmode[k, c] = msg.p, msg.vel, msg.mode
        for k, msg in tele[i].items():
            amode[k, c] = msg.mode
    for arr in (pmode, amode):  # a tick not heard keeps the mode heard before it
        for k in range(1, T + 1):
            arr[k] = np.where(arr[k] < 0, arr[k - 1], arr[k])
    sent = sorted(x for xs in heard.sent.values() for x in xs)
    t_a = sent[0][0] if sent else plan.at
    k_a = int(math.ceil(t_a / h))
    res: dict[str, Any] = {"attack": attack, "forged": len(sent), "first_sent": sent[0][0] if sent else None,
                           "heard_plant_ticks": int(np.isfinite(P[:, :, 0]).all(axis=1).sum()), "ticks": T + 1}

    # ------------------------------------------------------------ true error and the envelope
    err = np.linalg.norm(P - offsets[None] - pl[:, None], axis=2)  # (T+1, n)
    flying = (pmode == wire.FLYING) & (amode == wire.FLYING)
    e_fly = np.where(flying & np.isfinite(err), err, np.nan)

    def nanmax(a: np.ndarray) -> float:
        return float(np.nanmax(a)) if np.any(np.isfinite(a)) else math.nan

    res["err_max"] = nanmax(e_fly[k_a:])
    res["err_last10"] = nanmax(e_fly[max(0, T - int(round(10 / h))):])
    res["err_before"] = nanmax(e_fly[max(0, k_a - int(round(3 / h))):k_a])
    res["err_all_max"] = nanmax(err[k_a:])
    left: dict[str, str] = {}
    speed = np.linalg.norm(V, axis=2)
    fence = sf.geofence
    settled = np.zeros_like(flying)  # FLYING for `rejoin` s in a row: back from a HOLD, it has caught up
    run_len = np.zeros(n, dtype=int)
    for k in range(T + 1):
        run_len = np.where(flying[k], run_len + 1, 0)
        settled[k] = run_len > int(round(rejoin / h))
    for c, i in enumerate(ids):
        why = []
        if np.nanmax(speed[k_a:, c], initial=0.0) > sf.max_speed:
            why.append(f"speed {np.nanmax(speed[k_a:, c]):.0f} m/s")
        if fence is not None:
            lo, hi = np.array(fence.min), np.array(fence.max)
            outside = np.nanmax(np.maximum(lo - P[k_a:, c], P[k_a:, c] - hi), initial=0.0)
            if outside > 0:
                why.append(f"fence +{outside:.1f} m")
        slot_off = np.where(settled[k_a:, c], err[k_a:, c], np.nan)
        if nanmax(slot_off) > slot:
            why.append(f"slot {nanmax(slot_off):.1f} m")
        drift, start, reach = 0.0, None, 0.0
        for k in range(k_a, T + 1):
            if not flying[k, c] and pmode[k, c] >= 0 and np.all(np.isfinite(P[k, c])):
                if start is None:  # a held vehicle may travel as far as its brake takes it from here
                    start = P[k, c].copy()
                    v0 = float(np.linalg.norm(V[k, c])) if np.all(np.isfinite(V[k, c])) else 0.0
                    reach = failsafe.stopping_distance(v0, sf.hold_kp, sf.max_accel)
                drift = max(drift, float(np.linalg.norm(P[k, c] - start)) - reach)
            elif flying[k, c]:
                start = None
        if drift > slot:
            why.append(f"held drift {drift:.1f} m")
        if why:
            left[f"v{i}"] = ", ".join(why)
    res["left"] = left
    res["speed_max"] = nanmax(speed)
    seps = [np.linalg.norm(P[k_a:, a] - P[k_a:, b], axis=1) for a in range(n) for b in range(a + 1, n)]
    res["sep"] = -nanmax(-np.stack(seps)) if seps else math.nan

    # ------------------------------------------------------------ reactions
    first: list[float] = []
    gate0: dict[int, dict[str, int]] = {}
    gate1: dict[int, dict[str, int]] = {}
    rises: list[tuple[float, int]] = []
    """(telemetry tick time [s], agent) of the first ticks after the attack whose gate count rose."""
    events: list[tuple[float, str, int, int, int, str]] = []
    for c, i in enumerate(ids):
        total = 0
        for k in sorted(tele[i]):
            msg = tele[i][k]
            g = dict(msg.gate)
            if msg.t < t_a:
                gate0[i] = g
            else:
                gate1[i] = g
                if sum(g.values()) > total and len(rises) < 200:
                    rises.append((msg.t, i))
            total = sum(g.values())
            for ev in msg.events:
                if ev.t >= t_a - h / 2:
                    events.append((ev.t, "a", i, ev.src, ev.dst, ev.reason))
        for k in sorted(plants[i]):
            for ev in getattr(plants[i][k], "events", []):
                if ev.t >= t_a - h / 2:
                    events.append((ev.t, "p", i, ev.src, ev.dst, ev.reason))
    for tt, vid, src, dst, reason in plant_events(out):
        if tt >= t_a - h / 2 and not any(e[1] == "p" and e[2] == vid and abs(e[0] - tt) < h / 2 for e in events):
            events.append((tt, "p", vid, src, dst, reason))
    events.sort()
    if (out / "run.npz").exists():
        run = Run.load(out)
        for ev in run.safety.events:
            if ev.t >= t_a - h / 2 and not any(e[1] == "a" and e[2] == ev.vehicle and abs(e[0] - ev.t) < h / 2
                                               for e in events):
                events.append((ev.t, "a", ev.vehicle, ev.src, ev.dst, ev.reason))
        rp = run.runtime.plant_p if run.runtime is not None else run.p
        kk = min(rp.shape[0], T + 1)
        d = np.linalg.norm(rp[:kk] - P[:kk], axis=2)
        res["rec"] = nanmax(d)
        res["rec_missing"] = int(np.sum(np.isnan(rp[:kk]).any(axis=2) & np.isfinite(P[:kk]).all(axis=2)))
        held = np.flatnonzero(np.isfinite(rp).all(axis=(1, 2)))
        res["record"] = f"run.npz to {held[-1] * h:.1f} s" if held.size else "run.npz without a plant sample"
        if run.safety.gate_counts is not None and run.safety.gate_reasons is not None:
            res["gate_file"] = {str(r): int(run.safety.gate_counts[:, j].sum())
                                for j, r in enumerate(run.safety.gate_reasons)}
    else:
        res["rec"], res["rec_missing"] = math.nan, -1
        left_files = sorted(f.name for f in out.iterdir() if f.is_file() and f.name.startswith(("run", "journal")))
        res["record"] = "no run.npz" + (f" ({', '.join(left_files)} left)" if left_files else ", no run file")
    events.sort()
    rises.sort()
    first += [e[0] for e in events] + [r[0] for r in rises[:1]]
    res["gate_rises"] = rises
    res["sent"] = {a: xs[0][0] for a, xs in heard.sent.items() if xs}
    res["first"] = (min(first) - t_a) if first and sent else math.nan
    gate: dict[str, int] = {}
    for i in ids:
        for r, v in gate1.get(i, {}).items():
            dv = v - gate0.get(i, {}).get(r, 0)
            if dv:
                gate[f"a{i} {r}"] = gate.get(f"a{i} {r}", 0) + dv
    res["gate"] = gate
    res["events"] = [{"t": e[0], "who": f"{e[1]}{e[2]}", "from": wire.MODES[e[3]] if 0 <= e[3] < 5 else e[3],
                      "to": wire.MODES[e[4]] if 0 <= e[4] < 5 else e[4], "why": e[5]} for e in events]
    res["watchdog"] = [f"p{mm.group(1)} {mm.group(2)}" for line in _log_lines(out, "plant-")
                       if (mm := DOG_LINE.search(line)) is not None]
    res["end"] = {f"v{i}": CODE.get(int(pmode[-1, c]), "?") + "/" + CODE.get(int(amode[-1, c]), "?")
                  for c, i in enumerate(ids)}
    res["exit"] = status
    return res


def _log_lines(out: Path, prefix: str) -> list[str]:
    lines: list[str] = []
    for log in sorted((out / "logs").glob(f"{prefix}*.log")):
        lines += log.read_text(errors="replace").splitlines()
    return lines


# =========================================================================== report
def _reaction(rs: list[dict[str, Any]]) -> str:
    gate: dict[str, int] = {}
    modes: dict[str, list[str]] = {}
    dog: set[str] = set()
    for r in rs:
        for k, v in r["gate"].items():
            gate[k] = gate.get(k, 0) + v
        for e in r["events"]:
            word = "k" if e["from"] == e["to"] else CODE.get(wire.MODES.index(e["to"]), str(e["to"])) \
                if e["to"] in wire.MODES else str(e["to"])
            seq = modes.setdefault(e["who"], [])
            if not seq or seq[-1] != word:
                seq.append(word)
        dog.update(r["watchdog"])
    parts = []
    if gate:
        parts.append("gate " + ", ".join(f"{k} {v}" for k, v in sorted(gate.items())))
    if modes:
        parts.append("; ".join(f"{w}:{'>'.join(s[:6])}{'…' if len(s) > 6 else ''}" for w, s in sorted(modes.items())))
    if dog:
        parts.append("watchdog " + "; ".join(sorted(dog)))
    return "; ".join(parts) or "none"


def _reasons(rs: list[dict[str, Any]], most: int = 3) -> str:
    seen: dict[str, int] = {}
    for r in rs:
        for e in r["events"]:
            seen[f"{e['who']} {e['why']}"] = seen.get(f"{e['who']} {e['why']}", 0) + 1
    top = sorted(seen.items(), key=lambda kv: -kv[1])[:most]
    return "; ".join(f"{w} (x{c})" if c > 1 else w for w, c in top)


def _records(rs: list[dict[str, Any]]) -> str:
    return "/".join(sorted({str(r.get("record", "?")) for r in rs}))


def table(rows: dict[str, list[dict[str, Any]]]) -> str:
    head = ["attack", "n", "err max / last 10 s [m]", "left the envelope", "sep min [m]", "reaction",
            "first [s] p50 / max", "rec [m] (ticks missing; run file)", "end (plant/agent); exit", "load"]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * len(head)) + "|"]
    for attack, rs in rows.items():
        left: dict[str, str] = {}
        for r in rs:
            left.update(r["left"])
        ends = sorted({" ".join(f"{v}:{s}" for v, s in r["end"].items()) for r in rs})
        firsts = [r["first"] for r in rs]
        lines.append(
            f"| {attack}: {WHAT[attack]} | {len(rs)} | {fmt(max(r['err_max'] for r in rs), digits=1)} / "
            f"{fmt(max(r['err_last10'] for r in rs), digits=1)} | "
            f"{'YES ' + '; '.join(f'{k}: {v}' for k, v in sorted(left.items())) if left else 'no'} | "
            f"{fmt(min(r['sep'] for r in rs))} | {_reaction(rs)}"
            f"{' (' + _reasons(rs) + ')' if any(r['events'] for r in rs) else ''} | "
            f"{fmt(pct(firsts, 50))} / {fmt(pct(firsts, 100))} | {fmt(max(r['rec'] for r in rs), digits=1)} ({max(r['rec_missing'] for r in rs)}; {_records(rs)}) | "
            f"{' · '.join(ends)}; {','.join(str(r['exit']) for r in rs)} | "
            f"{'/'.join(format(r['load'], '.1f') for r in rs)} |")
    return "\n".join(lines)


def _side(rs: list[dict[str, Any]] | None) -> list[str]:
    """One side of the before/after table: err, envelope, separation, first reaction, end modes, run file."""
    if not rs:
        return ["to measure"] + ["—"] * 4
    left = sorted({v for r in rs for v in r["left"]})
    stopped = sorted({v for r in rs for v, s in r["end"].items() if not s.startswith("F")})
    return [f"{fmt(max(r['err_max'] for r in rs), digits=1)} / {fmt(max(r['err_last10'] for r in rs), digits=1)}",
            ("YES: " + ", ".join(left)) if left else "no",
            fmt(min(r["sep"] for r in rs)),
            f"{fmt(pct([r['first'] for r in rs], 50))}; " + (f"{', '.join(stopped)} stopped" if stopped else "all flying"),
            _records(rs)]


def compare(before: dict[str, list[dict[str, Any]]], after: dict[str, list[dict[str, Any]]]) -> str:
    """The before/after table of ``docs/results/redteam.md``, from two ``--json`` files' runs."""
    head = ["attack"] + [f"{side}: {col}" for side in ("before", "after")
                         for col in ("err max / last 10 s [m]", "left the envelope", "sep min [m]",
                                     "first reaction [s]; end", "run file")]
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join(["---"] * len(head)) + "|"]
    for attack in ATTACKS:
        if attack in before or attack in after:
            lines.append("| " + " | ".join([WHAT[attack], *_side(before.get(attack)), *_side(after.get(attack))]) + " |")
    return "\n".join(lines)


def run_all(attacks: list[str], reps: int, plan: Plan, duration: float, work: Path, slot: float,
            say: Callable[[str], None] = print) -> dict[str, list[dict[str, Any]]]:
    m = load_mission(catalog.resolve(MISSION), None)
    rows: dict[str, list[dict[str, Any]]] = {}
    for rep in range(reps):
        for attack in attacks:
            out = work / f"{attack}-{rep}"
            launched = launch(out, {attack: plan}, m, duration)
            (out / "redteam.json").write_text(json.dumps({"attack": attack, "duration": duration,
                                                          "status": launched.status,
                                                          "load": launched.load[0]}) + "\n")
            try:
                r = analyse(out, attack, plan, slot, launched.status)
            except Exception as exc:  # noqa: BLE001 - a run that cannot be read is reported, not fatal
                say(f"{attack} rep {rep}: cannot analyse: {exc!r}; launcher: {launched.stderr[-5:]}")
                continue
            r["load"], r["wall"] = launched.load[0], launched.wall
            rows.setdefault(attack, []).append(r)
            say(f"{attack} rep {rep}: err {fmt(r['err_max'])}/{fmt(r['err_last10'])} m, left {r['left'] or 'no'}, "
                f"sep {fmt(r['sep'])} m, first {fmt(r['first'])} s, forged {r['forged']}, gate {r['gate']}, "
                f"events {len(r['events'])}, rec {fmt(r['rec'])} m, end {r['end']}, exit {r['exit']} "
                f"[{r['wall']:.0f} s wall, load {r['load']:.2f}]")
    return rows


def reanalyse(work: Path, plan: Plan, slot: float) -> dict[str, list[dict[str, Any]]]:
    rows: dict[str, list[dict[str, Any]]] = {}
    for out in sorted(work.iterdir()):
        if not (out / "redteam.json").exists():
            continue
        meta = json.loads((out / "redteam.json").read_text())
        r = analyse(out, meta["attack"], plan, slot, meta["status"])
        r["load"] = meta["load"]
        rows.setdefault(meta["attack"], []).append(r)
    return {a: rows[a] for a in ATTACKS if a in rows}


def main(argv: list[str] | None = None) -> int:
    doc = __doc__ or ""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--attacks", nargs="*", choices=ATTACKS, default=list(ATTACKS))
    ap.add_argument("--reps", type=int, default=1, help="runs per attack (default 1)")
    ap.add_argument("--duration", type=float, default=32.0, help="mission duration [s] (default 32)")
    ap.add_argument("--at", type=float, default=8.0, help="the attack's start [s of mission time] (default 8)")
    ap.add_argument("--drift", type=float, default=0.5, help="drift speed [m/s] (default 0.5)")
    ap.add_argument("--drift-for", type=float, default=20.0, help="drift duration [s] (default 20)")
    ap.add_argument("--cmd-for", type=float, default=1.0, help="forged command duration [s] (default 1)")
    ap.add_argument("--hold-for", type=float, default=5.0, help="forged HOLD duration [s] (default 5)")
    ap.add_argument("--slot", type=float, default=5.0, help="the envelope's distance from the slot [m] (default 5)")
    ap.add_argument("--work", default=None, help="directory for the runs (default: a temporary one, kept)")
    ap.add_argument("--json", default=None, help="write every figure of every run here")
    ap.add_argument("--reanalyse", default=None, metavar="WORK", help="no runs: the table from the runs in WORK")
    ap.add_argument("--compare", nargs="+", default=None, metavar="JSON",
                    help="no runs: the before/after table from one or two --json files (before, after)")
    args = ap.parse_args(argv)
    if args.compare:
        sides = [{a: [{k: math.nan if v is None else v for k, v in r.items()} for r in rs]  # JSON null: NaN
                  for a, rs in json.loads(Path(f).read_text())["runs"].items()} for f in args.compare[:2]]
        print(compare(sides[0], sides[1] if len(sides) > 1 else {}))
        return 0
    plan = Plan(at=args.at, drift=args.drift, drift_for=args.drift_for, cmd_for=args.cmd_for, hold_for=args.hold_for)
    rev = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"], capture_output=True,
                         text=True, check=False).stdout.strip()
    if args.reanalyse:
        rows = reanalyse(Path(args.reanalyse), plan, args.slot)
    else:
        work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="tether-redteam-"))
        work.mkdir(parents=True, exist_ok=True)
        print(f"# bench/redteam.py {time.strftime('%Y-%m-%d %H:%M:%S')}; code {rev}; {os.cpu_count()} cores; "
              f"load {os.getloadavg()[0]:.2f}; runs in {work}", flush=True)
        rows = run_all(args.attacks, args.reps, plan, args.duration, work, args.slot,
                       say=lambda s: print(s, flush=True))
    print()
    print(table(rows))
    print(f"# load after: {os.getloadavg()[0]:.2f}")
    if args.json:
        Path(args.json).write_text(jsonout.dumps({"code": rev, "argv": sys.argv[1:], "plan": plan.__dict__,
                                                  "runs": rows}, indent=1, default=str) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
