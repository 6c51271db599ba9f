"""The ``tether`` command. Parses argv and mission files, then calls the library; nothing else.

Exit status: 0 success, 1 a run failed, 2 bad input (mission file or arguments), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from tether import graph
from tether import mission as ms
from tether import reproduce


class Progress:
    """A one-line progress display on stderr (redrawn on a terminal, every 10 % otherwise)."""

    def __init__(self) -> None:
        self.tty = sys.stderr.isatty()
        self.last: dict[str, int] = {}

    def __call__(self, k: int, n: int, label: str = "") -> None:
        pct = 100 * k // max(n, 1)
        if self.tty:
            sys.stderr.write(f"\r{label:>20} {pct:3d}% ({k}/{n})")
            if k >= n:
                sys.stderr.write("\n")
            sys.stderr.flush()
        elif pct // 10 != self.last.get(label, -1):
            self.last[label] = pct // 10
            sys.stderr.write(f"{label} {pct}%\n")


def _load(arg: str) -> ms.Mission:
    return ms.load(reproduce.resolve(arg))


def cmd_check(args: argparse.Namespace) -> int:
    m = _load(args.mission)
    topo = graph.topology(m)
    graph.check_lemma3(topo.adjacency)
    n = m.n
    print(f"mission {m.name!r} (version {m.version}): {n} agents, dim {m.dim}, {m.rate:g} Hz, "
          f"{m.duration:g} s ({m.steps} steps), seed {m.seed}")
    law = m.law
    print(f"law {law.kind}: Kp(0)={ms.per_axis(law.kp0, m.dim)} Kv(0)={ms.per_axis(law.kv0, m.dim)} "
          f"Gamma_p={law.gamma_p:g} Gamma_v={law.gamma_v:g}" + (f" sigma={law.sigma:g}" if law.sigma else ""))
    print(f"leader {m.leader.id}: p0={m.leader.p0} profile={type(m.leader.profile).__name__}")
    print(f"{len(m.edges)} edges; Assumption 1 holds; Lemma 3 checked (-L1^-1 L2 >= 0, unit row sums)")
    print(f"{'agent':>5} {'kappa':>6} {'hears leader':>12}  in-neighbours (weight)   offset    plant / disturbance")
    for i, a in enumerate(m.agents):
        nbrs = [(m.leader.id if j == n else m.agents[j].id, topo.adjacency[i, j]) for j in np.nonzero(topo.adjacency[i])[0]]
        nb = ", ".join(f"{j}({w:g})" for j, w in nbrs)
        hears = "yes" if topo.adjacency[i, n] > 0 else "no"
        print(f"{a.id:>5} {topo.kappa[i]:>6g} {hears:>12}  {nb:<23} {a.offset}  "
              f"{type(a.plant).__name__} / {type(a.disturbance).__name__}")
    for note in m.assumed:
        print(f"assumed: {note}")
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from tether import figures, metrics, refsim
    from tether.refsim import Setup

    m = _load(args.mission)
    out = Path(args.out)
    prog = Progress()
    run = refsim.simulate(m, args.mode, duration=args.duration, substeps=args.substeps,
                          progress=lambda k, n: prog(k, n, m.name))
    run.meta["mission_text"] = reproduce.resolve(args.mission).read_text()
    run.save(out / "run.npz")
    summary = metrics.summary(run)
    summary["tracking_error_m"] = metrics.tracking_error(run, Setup.of(m).offsets[: m.n])
    (out / "metrics.json").write_text(json.dumps(summary, indent=2))
    if not args.no_figures:
        figures.run_panels(run, out)
    print(json.dumps(summary, indent=2))
    print(f"wrote {out / 'run.npz'}")
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    prog = Progress()
    result = reproduce.section4(Path(args.out), duration=args.duration, continuous=args.continuous,
                                progress=prog)
    print((Path(args.out) / "metrics.md").read_text())
    print("figures: " + ", ".join(result["figures"]))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The README's demo: Section 4 reproduced with both laws."""
    args.what, args.continuous = "section4", False
    return cmd_reproduce(args)


def cmd_plot(args: argparse.Namespace) -> int:
    from tether import figures
    from tether.runfile import Run

    path = Path(args.run)
    run = Run.load(path)
    out = Path(args.out) if args.out else (path if path.is_dir() else path.parent)
    for p in figures.run_panels(run, out):
        print(f"wrote {p}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tether", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("check", help="validate a mission file and print a summary")
    c.add_argument("mission", help="mission file, or the name of a shipped mission (" + ", ".join(reproduce.builtin_names()) + ")")
    c.set_defaults(func=cmd_check)

    s = sub.add_parser("simulate", help="run a mission in the reference simulator (one process)")
    s.add_argument("mission")
    s.add_argument("--out", required=True, help="output directory (run.npz, metrics.json, figures)")
    s.add_argument("--mode", choices=["discrete", "continuous"], default="discrete",
                   help="sampled-data (the runtime's semantics) or continuous-time RK4")
    s.add_argument("--duration", type=float, default=None, help="override the mission's duration [s]")
    s.add_argument("--substeps", type=int, default=10, help="RK4 steps per control period (continuous mode)")
    s.add_argument("--no-figures", action="store_true")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reproduce", help="reproduce a result of the paper")
    r.add_argument("what", choices=["section4"])
    r.add_argument("--out", required=True)
    r.add_argument("--duration", type=float, default=None, help="override the 1000 s horizon [s]")
    r.add_argument("--continuous", action="store_true", help="also run the continuous-time RK4 mode (slow)")
    r.set_defaults(func=cmd_reproduce)

    dm = sub.add_parser("demo", help="the main demo: Section 4 with both laws, figures and metrics")
    dm.add_argument("--out", default="runs/demo")
    dm.add_argument("--duration", type=float, default=None, help="override the 1000 s horizon [s]")
    dm.set_defaults(func=cmd_demo)

    pl = sub.add_parser("plot", help="draw a run's figures from its run file")
    pl.add_argument("run", help="a run.npz or the directory holding it")
    pl.add_argument("--out", default=None)
    pl.set_defaults(func=cmd_plot)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except ms.MissionError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
