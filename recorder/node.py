"""The recorder's process: hears every sample of a run and writes one run file (``run.npz``).

It subscribes to the leader's state, every agent's telemetry and every plant's state, and fills a
:class:`~tether.runfile.Run` indexed by tick. In lockstep it acknowledges tick k once it holds
every sample of k, so the clock never runs ahead of what is recorded. In real time it records
until every producer has sent its last tick or gone, or until it is stopped; the file is written
in both cases (a stopped run is marked ``complete = false``).
"""

from __future__ import annotations

import asyncio
import json
import logging
from pathlib import Path

import numpy as np

from tether import wire
from tether.node import Node
from tether.runfile import Run

log = logging.getLogger("tether")

STOP_GRACE = 2.0
"""Real time: when every producer has left before the last tick, how long to wait for this
process's own stop signal before calling the run cut short [s]."""


class Recording:
    """The run being filled, sample by sample (pure bookkeeping, no I/O until :meth:`save`)."""

    def __init__(self, node: Node, out: Path):
        m = node.mission
        self.mission = m
        self.out = out
        self.col = {aid: i for i, aid in enumerate(m.agent_ids)}
        n, d, T = m.n, m.dim, m.steps + 1
        self.degree = {a.id: sum(1 for e in m.edges if e.dst == a.id) for a in m.agents}
        width = max(self.degree.values())
        meta = {"mission": m.name, "source": f"runtime-{node.clock.kind}", "law": m.law.kind, "rate": m.rate,
                "steps": m.steps, "seed": m.seed, "namespace": node.keys.ns,
                "mission_text": node.args.mission_path.read_text()}
        self.run = Run.empty(T, m.agent_ids, d, meta)
        self.run.t[:] = np.arange(T) * m.dt
        ex = self.run.extra
        for name in ("plant_p", "plant_v", "plant_a"):
            ex[name] = np.full((T, n, d), np.nan)
        ex["link_src"] = np.zeros((n, width), dtype=np.int64)
        for name in ("link_age", "link_received", "link_stale", "link_silent", "link_duplicates", "link_reordered",
                     "link_corrupt", "link_delivery", "link_age_p50", "link_age_p99", "link_used"):
            ex[name] = np.full((T, n, width), np.nan)
        ex["drops"] = np.full((T, n), np.nan)
        ex["meas_age"] = np.full((T, n), np.nan)
        ex["late"] = np.full((T, n), np.nan)
        self.netem: list[dict] = []
        """Link decisions, when the mission logs them (written to ``netem.jsonl``)."""
        if m.payload is not None:
            ex["payload_p"], ex["payload_v"] = np.full((T, 3), np.nan), np.full((T, 3), np.nan)
            ex["tension"], ex["slack_events"] = np.full((T, n), np.nan), np.full((T, n), np.nan)
        self.count = np.zeros(T, dtype=np.int64)
        self.expected = 1 + 2 * n + (m.payload is not None)
        self.saved = False

    def leader(self, msg: wire.State) -> None:
        if 0 <= msg.k < len(self.count):
            r = self.run
            r.leader_p[msg.k], r.leader_v[msg.k], r.leader_a[msg.k] = msg.p, msg.vel, msg.a
            self.count[msg.k] += 1

    def plant(self, msg: wire.PlantState) -> None:
        if 0 <= msg.k < len(self.count):
            i, ex = self.col[msg.sender], self.run.extra
            ex["plant_p"][msg.k, i], ex["plant_v"][msg.k, i], ex["plant_a"][msg.k, i] = msg.p, msg.vel, msg.a
            self.run.d[msg.k, i] = msg.d
            self.count[msg.k] += 1

    def world(self, msg: wire.WorldState) -> None:
        if 0 <= msg.k < len(self.count) and len(msg.tension) == self.mission.n == len(msg.slack_events):
            ex = self.run.extra
            ex["payload_p"][msg.k], ex["payload_v"][msg.k] = msg.p, msg.vel
            ex["tension"][msg.k], ex["slack_events"][msg.k] = msg.tension, msg.slack_events
            self.count[msg.k] += 1

    def telemetry(self, msg: wire.Telemetry) -> None:
        k = msg.k
        if not 0 <= k < len(self.count):
            return
        i, r, ex = self.col[msg.sender], self.run, self.run.extra
        r.p[k, i], r.v[k, i], r.a[k, i], r.u[k, i] = msg.p, msg.vel, msg.a, msg.u
        r.xi[k, i], r.zeta[k, i], r.kp[k, i], r.kv[k, i] = msg.xi, msg.zeta, msg.kp, msg.kv
        for n, link in enumerate(msg.links[: ex["link_src"].shape[1]]):
            ex["link_src"][i, n] = link.src
            ex["link_age"][k, i, n] = link.age
            ex["link_received"][k, i, n] = link.received
            ex["link_stale"][k, i, n] = link.stale
            ex["link_silent"][k, i, n] = float(link.silent)
            ex["link_used"][k, i, n] = link.used
            ex["link_duplicates"][k, i, n] = link.duplicates
            ex["link_reordered"][k, i, n] = link.reordered
            ex["link_corrupt"][k, i, n] = link.corrupt
            ex["link_delivery"][k, i, n] = link.delivery
            ex["link_age_p50"][k, i, n] = link.age_p50
            ex["link_age_p99"][k, i, n] = link.age_p99
        ex["drops"][k, i] = sum(msg.drops.values())
        ex["meas_age"][k, i] = msg.t - msg.meas_t
        for d in msg.netem:
            self.netem.append({"dst": msg.sender, "src": d.src, "seq": d.seq, "now": d.now, "event": d.event,
                               "at": d.at})
        ex["late"][k, i] = msg.late
        self.count[k] += 1

    def save(self, complete: bool, drops: dict[str, int]) -> Path:
        self.run.meta["complete"] = complete
        self.run.meta["recorder_drops"] = json.loads(json.dumps(drops))
        self.run.meta["samples_recorded"] = int(self.count.sum())
        self.run.meta["samples_expected"] = int(self.expected * len(self.count))
        path = self.run.save(self.out / "run.npz")
        if self.mission.netem is not None and self.mission.netem.log:
            self.netem.sort(key=lambda d: (d["dst"], d["src"], d["seq"], d["at"] is None, d["at"] or 0.0))
            lines = "".join(json.dumps(d) + "\n" for d in self.netem)
            (self.out / "netem.jsonl").write_text(lines)
        self.saved = True
        log.info("wrote %s (%d of %d samples)", path, self.count.sum(), self.expected * len(self.count))
        return path


def make(out: Path):
    """The recorder role writing to ``out``, and its stop hook (writes a partial file)."""
    holder: dict[str, Recording] = {}

    async def run(node: Node) -> None:
        m, keys = node.mission, node.keys
        rec = Recording(node, out)
        holder["rec"] = rec
        # three wildcard subscriptions, not 2N+1: each subscription costs a callback thread woken
        # per sample (measured: half the recorder's CPU, docs/benchmarks.md)
        node.source(keys.topic("leader", m.leader.id, "state"), wire.State, m.leader.id, on_message=rec.leader,
                    keep=False)
        producers = [("leader", m.leader.id)]
        for aid in m.agent_ids:
            node.source(keys.topic("agent", aid, "telemetry"), wire.Telemetry, aid, on_message=rec.telemetry,
                        subscribe=False, keep=False)
            node.source(keys.topic("plant", aid, "state"), wire.PlantState, aid, on_message=rec.plant,
                        subscribe=False, keep=False)
            producers += [("agent", aid), ("plant", aid)]
        if m.payload is not None:
            node.source(keys.topic("world", 0, "state"), wire.WorldState, 0, on_message=rec.world, keep=False)
            producers.append(("world", 0))
        node.subscribe(f"tether/{keys.ns}/agent/*/telemetry")
        node.subscribe(f"tether/{keys.ns}/plant/*/state")
        ack = node.publisher(keys.topic("recorder", node.args.node_id, "ack"))
        seen: set[str] = set()
        gone: set[str] = set()
        wanted = {keys.token(r, i) for r, i in producers}
        for r, i in producers:
            node.watch(r, i)
        await node.ready()
        last = m.steps
        if node.clock.lockstep:
            for k in range(last + 1):
                await node.until(lambda: rec.count[k] >= rec.expected, node.args.stall_timeout,
                                 f"every sample of tick {k} (have {rec.count[k]} of {rec.expected})")
                ack.send(wire.Ack, k, k * m.dt, role="recorder")
        else:
            def finished() -> bool:
                for key, alive in node.token_log:
                    (seen if alive else gone).add(key)
                node.token_log.clear()
                return rec.count[last] >= rec.expected or (seen >= wanted and (gone & wanted) == wanted)

            await node.until(finished, None, "the end of the run")
        complete = bool(np.all(rec.count >= rec.expected))
        rec.save(complete=complete, drops=node.receiver.drops)
        if rec.count[last] == 0:
            # the producers may have left because the run is being stopped (Ctrl-C): then this
            # process's own stop follows within moments, and ends it as stopped, not failed
            try:
                async with asyncio.timeout(STOP_GRACE):
                    await node.stop.wait()
                    await asyncio.Event().wait()  # stopping: serve() cancels this task (exit 143)
            except TimeoutError:
                pass
            raise RuntimeError("every producer left before the last tick: the run was cut short "
                               f"(recorded {int(rec.count.sum())} of {rec.expected * len(rec.count)} samples)")

    def on_stop(node: Node) -> None:
        rec = holder.get("rec")
        if rec is not None and not rec.saved:
            rec.save(complete=False, drops=node.receiver.drops)

    return run, on_stop
