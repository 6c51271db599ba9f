"""``tether missions`` and ``tether check``: the shipped missions, and what a mission file says."""

from __future__ import annotations

import argparse
import sys

from cli import args as cli_args
from tether import catalog
from tether import mission as ms


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """missions, check."""
    ls = sub.add_parser("missions", help="list the shipped missions, one line each")
    ls.set_defaults(func=cmd_missions)

    c = sub.add_parser("check", help="validate a mission file and print a summary")
    c.add_argument("mission", help=cli_args.MISSION_HELP)
    c.set_defaults(func=cmd_check)


def cmd_missions(args: argparse.Namespace) -> int:
    """One line per shipped mission: its name, size, rate, length and description."""
    rows = []
    for name in catalog.builtin_names():
        m = ms.load(catalog.builtin_path(name))
        rows.append((name, f"{m.n} agents, {m.dim}D, {m.rate:g} Hz, {m.duration:g} s", m.description))
    width = max(len(name) for name, _, _ in rows)
    size = max(len(what) for _, what, _ in rows)
    for name, what, description in rows:
        print(f"{name:<{width}}  {what:<{size}}  {description}")
    print("\nGive a name where a command takes a mission (tether check section4, tether simulate exp1 --out runs/exp1), "
          "or the path of your own mission file (docs/mission.md).")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    import numpy as np

    from tether import graph

    m = cli_args.load(args.mission)
    topo = graph.topology(m)
    try:
        numeric = graph.lemma3_holds(topo)
    except (AssertionError, np.linalg.LinAlgError) as exc:  # ill-conditioned beyond what the weight range allows
        raise ms.MissionError(str(cli_args.mission_path(args.mission)), [
            ("edges", f"fail Lemma 3 numerically ({str(exc).splitlines()[0]}); spread the weights less "
                      "(their ratio sets L1's conditioning) or shorten the longest path from the leader")]) from None
    n = m.n
    print(f"mission {m.name!r} (version {m.version}): {n} agents, dim {m.dim}, {m.rate:g} Hz, "
          f"{m.duration:g} s ({m.steps} steps), seed {m.seed}")
    print(_law_line(m))
    print(f"leader {m.leader.id}: p0={m.leader.p0} profile={type(m.leader.profile).__name__}")
    lemma = ("Lemma 3 checked (-L1^-1 L2 >= 0, unit row sums)" if numeric else
             f"Lemma 3 follows from Assumption 1 (N > {graph.DENSE_MAX}: not re-computed densely)")
    print(f"{len(m.edges)} edges; Assumption 1 holds; {lemma}")
    print(f"{'agent':>5} {'kappa':>6} {'hears leader':>12}  in-neighbours (weight)   offset    plant / disturbance")
    ends = [*topo.starts[1:], len(topo.dst)]
    for i, a in enumerate(m.agents):
        span = range(topo.starts[i], ends[i])
        nbrs = [(m.leader.id if topo.src[k] == n else m.agents[topo.src[k]].id, topo.weight[k]) for k in span]
        nb = ", ".join(f"{j}({w:g})" for j, w in nbrs)
        hears = "yes" if any(topo.src[k] == n for k in span) else "no"
        print(f"{a.id:>5} {topo.kappa[i]:>6g} {hears:>12}  {nb:<23} {a.offset}  "
              f"{type(a.plant).__name__} / {type(a.disturbance).__name__}")
    for note in m.assumed:
        print(f"assumed: {note}")
    from tether import checks

    for line in checks.ground_starts(m):  # a warning: exit status 0 (a pad start is by design)
        print(f"warning: {line}", file=sys.stderr)
    return 0


def _law_line(m: ms.Mission) -> str:
    """``law NAME (state ...): param=value ...``: the law a mission flies, by the names it gives its
    state and parameters (a per-axis parameter as its list)."""
    import msgspec

    from agent import laws

    bound = laws.of_mission(m)  # the mission loaded: its law is known to bind
    params = ", ".join(f"{k}={v}" for k, v in msgspec.structs.asdict(bound.params).items())
    state = f" (state per axis: {', '.join(bound.law.state)})" if bound.law.state else ""
    use = f" [{m.law.use}]" if m.law.use else ""
    return f"law {bound.name}{use}{state}: {params}"
