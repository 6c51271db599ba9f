"""A bare process for the runtime benchmarks: tether's message pattern with no tether in it.

    python bench/baseline_node.py SPEC.json hub ENDPOINT     # router session (+ lockstep clock source)
    python bench/baseline_node.py SPEC.json leader|agent|plant|recorder ID ENDPOINT

``bench/runtime.py`` writes SPEC.json and starts these processes; they are not meant to be run by
hand. Each one does what the tether process of the same role does on the wire — same keys, same
payload sizes, same QoS, same star topology (a router session in the hub, every other process a
client), same liveliness handshake, same ``ZENOH_RUNTIME`` as the launcher gives its children, the
same transport (mTLS with the run's certificates, access rules and ingress limits, or plain TCP as
``tether run --insecure``: ``bench/runtime.py`` writes the configurations) —
but its "work" is trivial: a payload is 16 header bytes ``<qq`` (tick k, send time
[ns, CLOCK_MONOTONIC]) padded with zeros to the size of the tether message it stands for, and
nothing is decoded beyond ``k``.

Imports are zenoh and the standard library only (no numpy, no msgspec, no tether), and uvloop when
the spec's ``loop`` says so (``bench/runtime.py --bare-loop``; by default the loop tether's processes
run on, ``tether/evloop.py``), so this process is also the memory and CPU floor of "a Python process
that speaks Zenoh" on that loop.

Hand-off (like tether's): a subscriber callback runs on zenoh-python's per-subscriber thread and
only appends ``(input, payload)`` to a deque; where the process must react to a sample (every
input in lockstep, the agent's plant input in real time) it also wakes the asyncio loop (one
``call_soon_threadsafe`` per burst, as ``tether.handoff.Wakeup``). Otherwise the loop is
timer-driven and reads the newest payload per input at its tick.

Lockstep per tick k (the dependency pattern of tether's roles):

* leader: publish state(k) once the clock granted k;
* plant i: publish state(k) once it holds cmd(k-1) (state(0) at once);
* agent i: on plant(k) publish state(k) (the relay), then once every in-neighbour's state(k) is
  in, publish cmd(k) and telemetry(k);
* recorder: once leader(k), every plant(k) and every telemetry(k) are in, publish ack(k);
* hub (the launcher's twin): on ack(k) grant k + window; once the last tick is acknowledged, say
  so on ``control/0/recorded`` (again every 0.5 s while a producer's token remains), and every
  producer keeps its session open until it hears that, as tether's do (``Node.linger``): a session
  closed right after its last put can lose it, which left the recorder short of the last batch. The
  recorder, which tether's access rules keep off that key, stays open :data:`RECORDER_LINGER` after
  its last acknowledgement (tether's writes the run file then).

Real time: every process ticks at ``epoch + k h`` (agents at ``epoch + (k + agent_phase) h``, as
tether's agents do); the leader and the plants publish their state at each tick, each agent relays
its plant's sample as its state the moment it arrives (so its plant input wakes the loop) and
publishes cmd and telemetry at its tick; the recorder only counts what arrives.

Experiments (spec keys, all off by default): ``direct`` callbacks on Zenoh's thread, ``colocate`` (lockstep: the plant is computed inside its agent process
and no plant process runs), ``batch`` (with ``colocate``: each agent sends the recorder one message
per ``batch`` ticks instead of two per tick, and the leader its states in one message per ``batch``
ticks besides its state of each tick, which the recorder then no longer hears: tether's records), ``wake`` (every input wakes the loop), ``mesh``
(each process's own endpoint, by ``role-id``: every process but the hub is a peer listening there,
linked by gossip to every other, and declares its token only once linked to all of them, as
``tether run --network mesh`` makes its children; the hub stays the router, the clock and the
liveliness watch).

Prints one JSON line on stdout when done: role, id, late ticks, samples received.
"""

from __future__ import annotations

import asyncio
import collections
import json
import struct
import sys
import threading
import time
from collections.abc import Coroutine
from typing import Any

import zenoh

HEADER = struct.Struct("<qq")  # tick k, send time [ns, CLOCK_MONOTONIC]

TIMER_GRAIN = 0.001  # tether.evloop.TIMER_GRAIN: the shortest sleep worth asking uvloop for

RECORDER_LINGER = 0.25
"""Lockstep: how long [s] the recorder stays open after acknowledging the last tick."""


PRESETS = {  # tether.transport's presets, spelled out
    "SYNC": (zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_LOW, True),
    "STATE": (zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_HIGH, True),
    "COMMAND": (zenoh.CongestionControl.DROP, zenoh.Priority.REAL_TIME, True),
    "TELEMETRY": (zenoh.CongestionControl.DROP, zenoh.Priority.DATA_LOW, False),
}


def _qos(kind: str, stream: str = "state", override: dict | None = None) -> dict:
    """The QoS of a stream: SYNC for every stream in lockstep (as tether's ``Node.publisher`` forces),
    in real time STATE unless ``override`` (the spec's ``qos``, real time only) names another preset
    for the stream (``bench/runtime.py`` gives the presets tether's agents declare)."""
    name = "SYNC" if kind == "lockstep" else (override or {}).get(stream) or "STATE"
    cc, prio, express = PRESETS[name]
    return {"congestion_control": cc, "priority": prio, "express": express}




class Bare:
    """One bare process: a session, its subscriptions, its publishers, a deque and a wake-up."""

    def __init__(self, spec: dict, role: str, nid: int, endpoint: str):
        self.spec, self.role, self.nid = spec, role, nid
        self.ns = spec["ns"]
        self.clock = spec["clock"]
        self.h = 1.0 / spec["rate"]
        self.steps = spec["steps"]
        self.sizes = spec["sizes"]
        self.mesh = spec.get("mesh", {}).get(f"{role}-{nid}")
        """Its own listening endpoint in a peer mesh, else None (a client of the hub)."""
        if "tls" in spec:  # the run's identity of this process: its whole configuration (router included)
            cfg = zenoh.Config.from_file(spec["tls"][f"{role}-{nid}"])
        else:
            cfg = zenoh.Config.from_json5(spec["client_config"])
            cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
            if self.mesh:  # as tether's launcher makes a mesh's child without TLS: a peer, listening
                cfg.insert_json5("mode", json.dumps("peer"))
                cfg.insert_json5("listen/endpoints", json.dumps([self.mesh]))
        self.session = zenoh.open(cfg)
        self.loop = asyncio.get_running_loop()
        self.queue: collections.deque = collections.deque()
        self.latest: dict[int, bytes] = {}
        self.received = 0
        self.event = asyncio.Event()
        self.lock = threading.Lock()
        self.pending = False
        self.wake = self.clock == "lockstep" or bool(spec.get("wake"))
        self.declared: list[zenoh.Subscriber[None] | zenoh.Publisher] = []
        self.token: zenoh.LivelinessToken | None = None
        self.pubs: dict[str, zenoh.Publisher] = {}
        self.seq = 0
        self.late = 0

    def key(self, role: str, nid: int, topic: str) -> str:
        return f"tether/{self.ns}/{role}/{nid}/{topic}"

    # ---------------------------------------------------------------- wiring
    def subscribe(self, key: str, idx: int, wake: bool | None = None) -> None:
        """Hand every sample of ``key`` to the deque as input ``idx``; wake the loop if ``wake``
        (default: in lockstep, or when the spec asks every input to wake it)."""
        q, latest, notify = self.queue, self.latest, self._notify
        wake = self.wake if wake is None else wake or self.wake

        def on_sample(sample: zenoh.Sample) -> None:
            data = sample.payload.to_bytes()
            q.append((idx, data))
            latest[idx] = data
            if wake:
                notify()

        handler = zenoh.handlers.Callback(on_sample, indirect=False) if self.spec.get("direct") else on_sample
        self.declared.append(self.session.declare_subscriber(key, handler))

    def _notify(self) -> None:
        with self.lock:
            if self.pending:
                return
            self.pending = True
        try:
            self.loop.call_soon_threadsafe(self.event.set)
        except RuntimeError:
            pass

    async def wait(self) -> None:
        await self.event.wait()
        self.event.clear()
        with self.lock:
            self.pending = False

    def publisher(self, name: str, key: str) -> None:
        pub = self.session.declare_publisher(key, **_qos(self.clock, name, self.spec.get("qos")))
        self.declared.append(pub)
        self.pubs[name] = pub

    def put(self, name: str, size: int, k: int) -> None:
        self.pubs[name].put(HEADER.pack(k, time.monotonic_ns()) + bytes(size - HEADER.size))

    def drain(self) -> list[tuple[int, int]]:
        """Pending samples as ``(input, k)``, oldest first."""
        out = []
        q = self.queue
        while q:
            idx, data = q.popleft()
            self.received += 1
            out.append((idx, HEADER.unpack_from(data)[0]))
        return out

    async def ready(self) -> float:
        """Declare the token, wait for the hub's start; returns tick 0's instant on CLOCK_MONOTONIC."""
        start_key = self.key("control", 0, "start")
        got: list[float] = []

        def on_start(sample: zenoh.Sample) -> None:
            epoch = struct.unpack_from("<d", sample.payload.to_bytes(), HEADER.size)[0]
            got.append(epoch)
            self._notify()

        self.declared.append(self.session.declare_subscriber(start_key, on_start))
        if self.mesh:  # the token once linked to every other peer, as tether's (Node._mesh_linked)
            want = len(self.spec["mesh"]) - 1
            end = time.monotonic() + self.spec.get("startup_timeout", 60.0)
            while len(self.session.info.peers_zid()) < want:
                if time.monotonic() > end:
                    raise SystemExit(f"{self.role} {self.nid}: linked to {len(self.session.info.peers_zid())} of "
                                     f"the mesh's {want} other peers")
                await asyncio.sleep(0.02)  # tether.node.MESH_POLL
        self.token = self.session.liveliness().declare_token(f"@tether/{self.ns}/{self.role}/{self.nid}")
        while not got:
            await self.wait()
        epoch = got[0]
        return time.monotonic() + (epoch - time.time())

    def close(self) -> None:
        for d in reversed(self.declared):
            try:
                d.undeclare()
            except zenoh.ZError:
                pass
        if self.token is not None:
            self.token.undeclare()
        self.session.close()

    # ---------------------------------------------------------------- roles
    async def run(self) -> dict:
        spec, nid = self.spec, self.nid
        sz = self.sizes
        if self.role == "leader":
            if self.clock == "lockstep":
                self.subscribe(self.key("clock", 0, "tick"), 0)
            self.publisher("state", self.key("leader", nid, "state"))
            if self.clock == "lockstep" and spec.get("batch"):  # its states for the recorder, as tether's leader
                self.publisher("record", self.key("leader", nid, "record"))
        elif self.role == "plant":
            self.subscribe(self.key("agent", nid, "cmd"), 0)
            self.publisher("state", self.key("plant", nid, "state"))
        elif self.role == "agent" and spec.get("colocate"):  # experiment: the plant runs inside the agent
            for n, (role, j) in enumerate(spec["nbrs"][str(nid)]):
                self.subscribe(self.key(role, j, "state"), 1 + n)
            for topic in ("state", "telemetry"):
                self.publisher(topic, self.key("agent", nid, topic))
            # its plant's state for the recorder, on the key of tether's co-located records
            self.publisher("plant_state", self.key("agent", nid, "record"))
        elif self.role == "agent":
            self.subscribe(self.key("plant", nid, "state"), 0, wake=True)  # relayed on arrival
            for n, (role, j) in enumerate(spec["nbrs"][str(nid)]):
                self.subscribe(self.key(role, j, "state"), 1 + n)
            for topic in ("state", "cmd", "telemetry"):
                self.publisher(topic, self.key("agent", nid, topic))
        elif self.role == "recorder":
            # with batches (lockstep), the leader's states come in its records, as tether's recorder hears them
            leader = "record" if self.clock == "lockstep" and spec.get("batch") else "state"
            self.subscribe(self.key("leader", spec["leader"], leader), 0)
            for aid in spec["agents"]:
                self.subscribe(self.key("agent", aid, "telemetry"), 1)
                if spec.get("colocate") and not spec.get("batch"):
                    self.subscribe(self.key("agent", aid, "record"), 2)
                elif not spec.get("batch"):
                    self.subscribe(self.key("plant", aid, "state"), 2)
            self.publisher("ack", self.key("recorder", nid, "ack"))
        recorded: list[int] = []
        if self.clock == "lockstep" and self.role != "recorder":
            def on_recorded(sample: zenoh.Sample) -> None:
                recorded.append(HEADER.unpack_from(sample.payload.to_bytes())[0])
                self._notify()

            self.declared.append(self.session.declare_subscriber(self.key("control", 0, "recorded"), on_recorded))
        t0 = await self.ready()
        if self.clock == "lockstep":
            await getattr(self, f"_lockstep_{self.role}")()
            if self.role == "recorder":
                await asyncio.sleep(RECORDER_LINGER)
            else:
                try:  # linger until the hub's word that the last tick is recorded
                    async with asyncio.timeout(self.spec.get("stall_timeout", 30.0)):
                        while not any(k >= self.steps for k in recorded):
                            await self.wait()
                except TimeoutError:
                    print(f"{self.role} {nid}: no word that the run is recorded; closing anyway", file=sys.stderr,
                          flush=True)
        else:
            await self._realtime(t0)
        return {"role": self.role, "id": nid, "late": self.late, "received": self.received}

    async def _realtime(self, t0: float) -> None:
        sz, steps, h = self.sizes, self.steps, self.h
        if self.role == "recorder":  # records nothing: count what arrives until the end
            end = t0 + steps * h + 0.5
            while time.monotonic() < end:
                await asyncio.sleep(min(0.5, max(0.0, end - time.monotonic())))
                self.drain()
            return
        agent = self.role == "agent"
        if agent:  # tether's agent ticks a fraction of a period after its plant and the leader
            t0 += self.spec.get("agent_phase", 0.0) * h
        task = None
        if self.wake or agent:  # drain on every wake-up (the agent relays its plant's samples at once)
            async def drainer() -> None:
                while True:
                    await self.wait()
                    self.relay(self.drain())
            task = asyncio.create_task(drainer())
        for k in range(steps + 1):
            due = t0 + k * h
            delay = due - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
                # never before the instant, as tether's clock (uvloop's timers can fire ~1 ms early)
                while (rest := due - time.monotonic()) > 0:
                    await asyncio.sleep(max(rest, TIMER_GRAIN))
            if time.monotonic() - due > h:
                self.late += 1
            self.relay(self.drain())
            if self.role == "leader":
                self.put("state", sz["state"], k)
            elif self.role == "plant":
                self.latest.get(0)  # the newest command
                self.put("state", sz["plant_state"], k)
            else:
                [self.latest.get(i) for i in range(len(self.spec["nbrs"][str(self.nid)]) + 1)]
                self.put("cmd", sz["cmd"], k)
                self.put("telemetry", sz["telemetry"], k)
        if task is not None:
            task.cancel()

    def relay(self, items: list[tuple[int, int]]) -> None:
        """Agent: publish each plant sample as the agent's state, with the plant's tick."""
        if self.role == "agent":
            for idx, k in items:
                if idx == 0:
                    self.put("state", self.sizes["state"], k)

    async def _lockstep_leader(self) -> None:
        granted, k = -1, 0
        batch = int(self.spec.get("batch", 0))
        while k <= self.steps:
            for _, g in self.drain():
                granted = max(granted, g)
            while k <= min(granted, self.steps):
                self.put("state", self.sizes["state"], k)
                if batch and (k % batch == batch - 1 or k == self.steps):  # ticks k - k % batch .. k
                    self.put("record", HEADER.size + (k % batch + 1) * self.sizes["state"], k)
                k += 1
            if k <= self.steps:
                await self.wait()

    async def _lockstep_plant(self) -> None:
        cmds: set[int] = set()
        self.put("state", self.sizes["plant_state"], 0)
        k = 1
        while k <= self.steps:
            await self.wait()
            cmds.update(j for _, j in self.drain())
            while k <= self.steps and k - 1 in cmds:
                cmds.discard(k - 1)
                self.put("state", self.sizes["plant_state"], k)
                k += 1

    async def _lockstep_agent_colocated(self) -> None:
        """Experiment: the plant is a function call in the agent, so a tick needs only the
        neighbours' states; the plant's state still goes out for the recorder."""
        n_nbrs = len(self.spec["nbrs"][str(self.nid)])
        have: dict[int, int] = collections.defaultdict(int)
        sz = self.sizes
        batch = int(self.spec.get("batch", 0))  # > 0: the recorder's samples go out every `batch` ticks
        record_size = sz["plant_state"] + sz["telemetry"]
        if not batch:
            self.put("plant_state", sz["plant_state"], 0)
        self.put("state", sz["state"], 0)
        k = 0
        while k <= self.steps:
            for _, j in self.drain():
                have[j] += 1
            while k <= self.steps and have[k] >= n_nbrs:
                if batch:
                    if k % batch == batch - 1 or k == self.steps:  # ticks k - k % batch .. k in one message
                        self.put("telemetry", HEADER.size + (k % batch + 1) * record_size, k)
                else:
                    self.put("telemetry", sz["telemetry"], k)
                del have[k]
                k += 1
                if k <= self.steps:
                    if not batch:
                        self.put("plant_state", sz["plant_state"], k)
                    self.put("state", sz["state"], k)
            if k <= self.steps:
                await self.wait()

    async def _lockstep_agent(self) -> None:
        if self.spec.get("colocate"):
            return await self._lockstep_agent_colocated()
        n_nbrs = len(self.spec["nbrs"][str(self.nid)])
        plant: set[int] = set()
        have: dict[int, int] = collections.defaultdict(int)
        k, sent_state = 0, -1
        sz = self.sizes
        while k <= self.steps:
            for idx, j in self.drain():
                if idx == 0:
                    plant.add(j)
                else:
                    have[j] += 1
            while k <= self.steps and k in plant:
                if sent_state < k:
                    self.put("state", sz["state"], k)
                    sent_state = k
                if have[k] < n_nbrs:
                    break
                self.put("cmd", sz["cmd"], k)
                self.put("telemetry", sz["telemetry"], k)
                plant.discard(k)
                del have[k]
                k += 1
            if k <= self.steps:
                await self.wait()

    async def _lockstep_recorder(self) -> None:
        batch = int(self.spec.get("batch", 0))
        expected = 1 + (1 if batch else 2) * len(self.spec["agents"])
        count: dict[int, int] = collections.defaultdict(int)
        k = 0
        while k <= self.steps:
            await self.wait()
            for idx, j in self.drain():
                if batch and idx in (0, 1):  # a batch (the leader's, or telemetry + plant state) ending at tick j
                    for t in range(j - j % batch, j + 1):
                        count[t] += 1
                else:
                    count[j] += 1
            # as tether's recorder: one acknowledgement for the ticks completed together
            done = k
            while k <= self.steps and count[k] >= expected:
                del count[k]
                k += 1
            if k > done:
                self.put("ack", self.sizes["ack"], k - 1)


# -------------------------------------------------------------------- the hub
async def hub(spec: dict, endpoint: str) -> None:
    """Router session + (lockstep) clock source, as ``deploy.local`` runs in the launcher process.

    Prints ``listening``, then ``up <s>`` when every token is in, ``start <epoch>``, and at the end
    ``ran <mission s> <wall s>`` (wall time from the first grant / from tick 0 to the last tick)."""
    if "tls" in spec:
        cfg = zenoh.Config.from_file(spec["tls"]["router"])
    else:
        cfg = zenoh.Config.from_json5(spec["router_config"])
        cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    session = zenoh.open(cfg)
    loop = asyncio.get_running_loop()
    event = asyncio.Event()
    q: collections.deque = collections.deque()
    ns = spec["ns"]

    def notify() -> None:
        try:
            loop.call_soon_threadsafe(event.set)
        except RuntimeError:  # the loop has closed: a late liveliness event, nobody to wake
            pass

    members = {f"@tether/{ns}/leader/{spec['leader']}", f"@tether/{ns}/recorder/0"}
    roles = ("agent",) if spec.get("colocate") else ("agent", "plant")
    members |= {f"@tether/{ns}/{r}/{a}" for a in spec["agents"] for r in roles}
    alive: set[str] = set()
    put_kind = zenoh.SampleKind.PUT

    def on_token(sample: zenoh.Sample) -> None:
        q.append(("token", str(sample.key_expr), sample.kind == put_kind))
        notify()

    declared: list[zenoh.Subscriber[None] | zenoh.Publisher] = [
        session.liveliness().declare_subscriber(f"@tether/{ns}/**", on_token, history=True)]
    print("listening", flush=True)
    t_open = time.monotonic()
    try:
        while not alive >= members:
            try:
                async with asyncio.timeout(spec.get("startup_timeout", 60.0)):
                    await event.wait()
            except TimeoutError:
                print(f"missing {sorted(members - alive)}", flush=True)
                sys.exit(1)
            event.clear()
            while q:
                _, key, up = q.popleft()
                (alive.add if up else alive.discard)(key)
        print(f"up {time.monotonic() - t_open:.3f}", flush=True)
        steps, h = spec["steps"], 1.0 / spec["rate"]
        start_pub = session.declare_publisher(f"tether/{ns}/control/0/start", **_qos("lockstep"))
        declared.append(start_pub)
        if spec["clock"] == "realtime":
            epoch = time.time() + spec["start_lead"]
            start_pub.put(HEADER.pack(0, 0) + struct.pack("<d", epoch) + bytes(spec["sizes"]["start"] - 24))
            print(f"start {epoch:.6f}", flush=True)
            t1 = time.monotonic() + (epoch - time.time())
            await asyncio.sleep(max(0.0, t1 + steps * h - time.monotonic()))
            print(f"ran {steps * h:g} {time.monotonic() - t1:.3f}", flush=True)
            return
        acks: collections.deque = collections.deque()

        def on_ack(sample: zenoh.Sample) -> None:
            acks.append(sample.payload.to_bytes())
            notify()

        declared.append(session.declare_subscriber(f"tether/{ns}/*/*/ack", on_ack))
        tick = session.declare_publisher(f"tether/{ns}/clock/0/tick", **_qos("lockstep"))
        declared.append(tick)
        window, done, seq = spec["window"], -1, 0
        tick_pad = bytes(spec["sizes"]["tick"] - HEADER.size)
        start_pub.put(HEADER.pack(0, 0) + struct.pack("<d", time.time()) + bytes(spec["sizes"]["start"] - 24))
        print(f"start {time.time():.6f}", flush=True)
        t1 = time.monotonic()
        tick.put(HEADER.pack(min(steps, done + window), time.monotonic_ns()) + tick_pad)
        while done < steps:
            try:
                async with asyncio.timeout(spec.get("stall_timeout", 30.0)):
                    await event.wait()
            except TimeoutError:
                print(f"stalled at tick {done + 1}", flush=True)
                sys.exit(1)
            event.clear()
            moved = False
            while acks:
                k = HEADER.unpack_from(acks.popleft())[0]
                if k > done:
                    done, moved = k, True
            if moved:
                tick.put(HEADER.pack(min(steps, done + window), time.monotonic_ns()) + tick_pad)
                seq += 1
        print(f"ran {steps * h:g} {time.monotonic() - t1:.3f}", flush=True)
        # the word that every sample is in: the producers close only then (repeated while any remains)
        recorded = session.declare_publisher(f"tether/{ns}/control/0/recorded", **_qos("lockstep"))
        declared.append(recorded)
        producers = members - {f"@tether/{ns}/recorder/0"}
        end = time.monotonic() + spec.get("stall_timeout", 30.0)
        while alive & producers and time.monotonic() < end:
            recorded.put(HEADER.pack(steps, time.monotonic_ns()) + tick_pad)
            try:
                async with asyncio.timeout(0.5):
                    await event.wait()
            except TimeoutError:
                pass
            event.clear()
            while q:
                _, key, up = q.popleft()
                (alive.add if up else alive.discard)(key)
    finally:
        for d in reversed(declared):
            try:
                d.undeclare()
            except zenoh.ZError:
                pass
        session.close()


async def node(spec: dict, role: str, nid: int, endpoint: str) -> None:
    b = Bare(spec, role, nid, endpoint)
    try:
        out = await b.run()
    finally:
        b.close()
    print(json.dumps(out), flush=True)


def run(main: Coroutine[Any, Any, None], kind: str) -> None:
    """``asyncio.run`` on the event loop the spec names (``loop``: ``uvloop`` or ``asyncio``), as
    ``tether.evloop.run`` runs tether's processes."""
    if kind == "uvloop":
        import uvloop

        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            runner.run(main)
    else:
        asyncio.run(main)


def main(argv: list[str]) -> None:
    with open(argv[0]) as fh:
        spec = json.load(fh)
    kind = spec.get("loop", "asyncio")
    if argv[1] == "hub":
        run(hub(spec, argv[2]), kind)
    else:
        run(node(spec, argv[1], int(argv[2]), argv[3]), kind)


if __name__ == "__main__":
    main(sys.argv[1:])
