"""What agent i says at each tick: its telemetry (the law's state, the command, every in-link's
statistics, the drops and the gate's rejections), to the recorder on its own key, or, with the
plant on board (lockstep, ``--colocate-plant``), in records of ``--record-batch`` ticks that carry
the plant's samples too.
"""

from __future__ import annotations

from agent import laws
from agent.hearing import Hearing
from agent.tick import AgentTick, TickResult
from tether import transport as tp
from tether import wire
from tether.gate import merged
from tether.inputs import Source
from tether.node import Node


class Report:
    """Agent ``node.args.node_id``'s telemetry, declared on ``node`` (before :meth:`Node.ready`).
    ``onboard``: the plant is computed in this process; its samples go to the recorder with the
    telemetry, ``node.args.record_batch`` ticks a record."""

    def __init__(self, node: Node, hearing: Hearing, onboard: bool) -> None:
        self.node, self.hearing = node, hearing
        self.aid = node.args.node_id
        self.last = node.mission.steps
        keys = node.keys
        self.tele = None if onboard else node.publisher(keys.topic("agent", self.aid, "telemetry"), tp.TELEMETRY)
        self.records = node.publisher(keys.topic("agent", self.aid, "record")) if onboard else None
        self.batch = max(1, node.args.record_batch)
        self.pending: tuple[list[wire.PlantState], list[wire.Telemetry]] = ([], [])
        """With a co-located plant: the plant samples and telemetry not yet sent to the recorder."""
        self.seq = 0
        self.x_names = list(laws.of_mission(node.mission).law.state)
        """The law's state variables' names, said with each telemetry's state."""

    def links(self, k: int, tick: AgentTick, out: TickResult) -> list[wire.LinkStats]:
        """Each in-link's statistics at tick ``k``."""
        clock = self.node.clock
        stats = []
        for n, (j, s) in enumerate(zip(self.hearing.neighbours, self.hearing.nbrs)):
            received = clock.received(s, k)
            p50, p99 = tick.age_percentiles(n)
            sent = clock.sent(s, k)  # samples j sent up to its newest received
            stats.append(wire.LinkStats(
                src=j, received=received, used=tick.used[n], stale=s.stale, age=out.ages[n], silent=s.silent_at(k),
                duplicates=s.duplicates, reordered=s.reordered, corrupt=s.corrupt,
                delivery=(received - s.duplicates) / sent if sent else 0.0, age_p50=p50, age_p99=p99))
        return stats

    def send(self, k: int, t: float, own: wire.PlantState, tick: AgentTick, out: TickResult, u: list[float],
             events: list[wire.SafetyEvent]) -> None:
        """Say tick ``k`` (``t`` [s]): the own measurement ``own``, the law's output ``out``, the
        command ``u`` sent [m/s^2] and the supervisor's ``events``."""
        hearing, node = self.hearing, self.node
        decisions = [wire.LinkDecision(src=j, seq=d.seq, now=d.now, event=d.event, at=d.at)
                     for j, ch in hearing.channels for d in ch.link.take_decisions()]
        report = wire.Telemetry(
            sender=self.aid, seq=self.seq, k=k, t=t, clock=hearing.clocks(), netem=decisions, meas_t=own.t, p=own.p,
            vel=own.vel, a=own.a, u=u, xi=out.xi, zeta=out.zeta, kp=out.kp, kv=out.kv,
            links=self.links(k, tick, out), drops=dict(node.ingress.receiver.drops), late=node.clock.late, mode=out.mode,
            events=events, gate=_with_conflicts(merged(hearing.gates), [s for _, s in hearing.judged]),
            x=[c for var in out.x for c in var], x_names=self.x_names)
        self.seq += 1
        if self.tele is not None:
            self.tele.put(report)
        elif self.records is not None:
            # one message per `batch` ticks for the recorder, within the clock's window: the
            # recorder acknowledges tick k (and the clock grants further) only once it holds it
            plants, reports = self.pending
            plants.append(own)
            reports.append(report)
            if len(reports) >= self.batch or k == self.last:
                self.records.send(wire.Record, k, t, plant=plants[:], telemetry=reports[:])
                plants.clear()
                reports.clear()


def _with_conflicts(rejected: dict[str, int], sources: list[Source]) -> dict[str, int]:
    """The gate's rejections by reason, and the samples that conflicted with their own stream
    (``conflict``: two contents for one tick, or a plant's mode report against its earlier ones)."""
    n = sum(s.conflicts for s in sources)
    return {**rejected, "conflict": n} if n else rejected
