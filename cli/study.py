"""``tether sweep`` and ``tether montecarlo``: a study's options and its command (``sim/study.py``).

Every option is checked before anything runs (exit 2 naming the option and the fix); an executor
that does not answer is an exit 2 too, before anything is written. Ctrl-C keeps the finished cells
and exits 130 saying how to resume (the same command again).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from cli.args import MISSION_HELP, BadArgument, load, seconds, writable_dir


def _grid_options(p: argparse.ArgumentParser, *, seeds_required: bool) -> None:
    """The options a sweep and a Monte Carlo study share (beyond the network grid)."""
    p.add_argument("--executor", default=None, metavar="tcp://HOST:PORT",
                   help="run the cells on the Dask scheduler at this address (pip install 'tether[cluster]'; "
                        "default: local processes, --jobs of them)")
    p.add_argument("--connect-timeout", default=None, metavar="S",
                   help="how long --executor waits for the scheduler and its first worker [s] (default 10)")
    p.add_argument("--seeds", default=None, required=seeds_required, metavar="N",
                   help="Monte Carlo: N replicates of every cell (new seed for random disturbances and network, "
                        "jittered start positions, random sinusoid phases); mean, std and 95%% t-interval per cell")
    p.add_argument("--p0-jitter", default=None, metavar="M",
                   help="with --seeds: start-position jitter per horizontal axis [m] (default 0.2)")
    p.add_argument("--sigma", default=None, help="sigma values of the sigma law, comma-separated (a sigma map)")
    p.add_argument("--gamma-p", default=None, help="Gamma_p values, comma-separated")
    p.add_argument("--gamma-v", default=None, help="Gamma_v values, comma-separated")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """sweep, montecarlo, warm."""
    from sim.warm import PARTS

    sw = sub.add_parser("sweep", help="degradation study: a mission over a grid of link loss and delay, both laws")
    sw.add_argument("mission", help=MISSION_HELP)
    sw.add_argument("--out", required=True, help="directory for sweep.csv, sweep.md, heatmaps and each point's mission")
    sw.add_argument("--loss", default="0,10,30,50", help="loss ratios [%%], comma-separated (default 0,10,30,50)")
    sw.add_argument("--delay", default="0,20,50,100,200", help="one-way delays [ms] (default 0,20,50,100,200)")
    sw.add_argument("--burst", default="1", help="mean loss-burst lengths [messages]; 1: independent losses")
    sw.add_argument("--jitter", type=float, default=0.0, help="uniform delay jitter, half-width [ms]")
    sw.add_argument("--laws", default=None, help="laws to run, comma-separated: sigma, benchmark (default both)")
    sw.add_argument("--duration", type=seconds, default=None, help="override the mission's duration [s]")
    sw.add_argument("--engine", choices=["inprocess", "runtime"], default="inprocess",
                    help="inprocess: the lockstep runtime's arithmetic in one process (equal bit for bit, "
                         "several times faster: bench/sweep_engine.py); runtime: real processes over Zenoh "
                         "(tether run) for every point")
    sw.add_argument("--jobs", type=int, default=1, help="grid points run at once (processes)")
    sw.add_argument("--compensate", action=argparse.BooleanOptionalAction, default=None,
                    help="latency compensation on every agent (default: as the mission's [links] says)")
    _grid_options(sw, seeds_required=False)
    sw.set_defaults(func=cmd_study)

    mc = sub.add_parser("montecarlo", help="Monte Carlo study: a sweep's grid, N replicates per cell, "
                                           "mean / std / 95%% CI per cell")
    mc.add_argument("mission", help=MISSION_HELP)
    mc.add_argument("--out", required=True, help="directory for sweep.csv, summary.csv, sweep.md and the figure")
    mc.add_argument("--loss", default="0", help="loss ratios [%%] (default 0)")
    mc.add_argument("--delay", default="0", help="one-way delays [ms] (default 0)")
    mc.add_argument("--burst", default="1", help="mean loss-burst lengths [messages]")
    mc.add_argument("--jitter", type=float, default=0.0, help="uniform delay jitter, half-width [ms]")
    mc.add_argument("--laws", default=None, help="laws to run (default: the mission's)")
    mc.add_argument("--duration", type=seconds, default=None, help="override the mission's duration [s]")
    mc.add_argument("--engine", choices=["inprocess", "runtime"], default="inprocess",
                    help="inprocess (default): the lockstep runtime's arithmetic, one process per cell (equal bit for "
                         "bit, faster); runtime: real processes over Zenoh (tether run) for every cell")
    mc.add_argument("--jobs", type=int, default=1, help="cells run at once (local processes)")
    mc.add_argument("--compensate", action=argparse.BooleanOptionalAction, default=None,
                    help="latency compensation on every agent (default: as the mission's [links] says)")
    _grid_options(mc, seeds_required=True)
    mc.set_defaults(func=cmd_study, montecarlo=True)
    wm = sub.add_parser("warm", help="compile the engines a mission's runs take, once for this machine (after "
                                     "installing, on a CI runner, on each Dask host)")
    wm.add_argument("mission", nargs="?", default="section4", help=MISSION_HELP + " (default section4)")
    wm.add_argument("--parts", nargs="+", choices=PARTS, default=None, help="the compiled pieces to warm (default: discrete, continuous and the "
                                       "in-process engine)")
    wm.set_defaults(func=cmd_warm)


def _number(text: str | None, option: str, lo: float, hi: float, default: float) -> float:
    if text is None:
        return default
    try:
        x = float(text)
    except ValueError:
        raise BadArgument(f"{option}: {text!r} is not a number; give e.g. {option} {default:g}") from None
    if not math.isfinite(x) or not lo <= x <= hi:
        raise BadArgument(f"{option}: {text} is out of range; give a value from {lo:g} to {hi:g}")
    return x


def _positive(text: str | None, option: str, hi: float) -> list[float] | None:
    """A comma-separated list of values in (0, hi], or None."""
    from sim import sweep

    if text is None:
        return None
    values = sweep.parse_list(text, option, 0.0, hi, "1/s")
    if any(v <= 0 for v in values):
        extra = " (sigma = 0 is the benchmark law: --laws benchmark)" if option == "--sigma" else ""
        raise BadArgument(f"{option}: 0 is not allowed; every value must be > 0{extra}")
    return values


def cmd_study(args: argparse.Namespace) -> int:
    from sim import study, sweep
    from tether.progress import Progress

    m = load(args.mission, args.duration)
    writable_dir("--out", args.out, ("sweep.csv", "sweep.md", "study.jsonl"))
    try:
        loss = sweep.parse_list(args.loss, "--loss", 0.0, 100.0, "%", hi_open=True)
        delay = sweep.parse_list(args.delay, "--delay", 0.0, 60_000.0, "ms")
        burst = sweep.parse_list(args.burst, "--burst", 1.0, 1e6, "messages")
        sigma = _positive(args.sigma, "--sigma", 1e3)
        gamma_p = _positive(args.gamma_p, "--gamma-p", 1e3)
        gamma_v = _positive(args.gamma_v, "--gamma-v", 1e3)
        if args.laws is not None:
            laws = tuple(x.strip() for x in args.laws.split(","))
        elif sigma is not None or getattr(args, "montecarlo", False):
            laws = ("sigma",) if sigma is not None else (m.law.kind,)
        else:
            laws = sweep.LAWS
        seeds = None
        if args.seeds is not None:
            try:
                seeds = int(args.seeds)
            except ValueError:
                raise BadArgument(f"--seeds: {args.seeds!r} is not a whole number; give e.g. --seeds 20") from None
            if seeds < 1:
                raise BadArgument(f"--seeds: {seeds} is not >= 1; give e.g. --seeds 20")
            if seeds > study.MAX_SEEDS:
                per = len(sweep.points_of(m, loss=loss, delay=delay, burst=burst, laws=laws, sigma=sigma,
                                          gamma_p=gamma_p, gamma_v=gamma_v))
                raise BadArgument(f"--seeds: {seeds} is more than {study.MAX_SEEDS} ({seeds * per} cells, "
                                  f"{study.estimate(m, seeds * per)}); give at most {study.MAX_SEEDS}")
        if args.p0_jitter is not None and seeds is None:
            raise BadArgument("--p0-jitter: applies to Monte Carlo replicates only; add --seeds N")
        p0_jitter = _number(args.p0_jitter, "--p0-jitter", 0.0, 10.0, sweep.P0_JITTER_M)
        if args.jobs < 1:
            raise BadArgument(f"--jobs: {args.jobs} must be at least 1")
        if args.executor is not None:
            study.check_address(args.executor)
        elif args.connect_timeout is not None:
            raise BadArgument("--connect-timeout: applies to --executor only; add --executor tcp://HOST:PORT")
        timeout = _number(args.connect_timeout, "--connect-timeout", 0.1, 3600.0, study.CONNECT_TIMEOUT_S)
        if args.engine == "inprocess" and args.executor is None:
            from sim import capacity

            slow = capacity.slow_path()
            if slow is not None:
                print(slow, file=sys.stderr)
        prog = Progress()
        out = Path(args.out)

        def started(cells: int, kind: str) -> None:
            where = {"inline": "in this process", "local": f"on {args.jobs} local processes",
                     "dask": f"on the Dask scheduler at {args.executor}"}[kind]
            print(f"{cells} cells {where}; results kept in {out / 'study.jsonl'} as they finish", file=sys.stderr)

        rows = sweep.sweep(m, out, laws=laws, jitter_ms=args.jitter, duration=args.duration, engine=args.engine,
                           jobs=args.jobs, compensate=args.compensate, progress=prog, sigma=sigma, gamma_p=gamma_p,
                           gamma_v=gamma_v, seeds=seeds, p0_jitter=p0_jitter, executor=args.executor,
                           connect_timeout=timeout, on_start=started, loss=loss, delay=delay, burst=burst)
    except (sweep.SweepError, study.StudyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except study.StudyInterrupted as exc:
        print(f"\ninterrupted: {exc.done} of {exc.total} cells done, kept in {exc.path}; run the same command "
              "again to resume (finished cells are skipped)", file=sys.stderr)
        return 130
    except (sweep.StudyFailed, study.StudyBroken) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    import json

    meta = json.loads((out / "sweep.json").read_text())["meta"]
    diverged = sum(bool(r["diverged"]) for r in rows)
    workers = ", ".join(f"{w} {k}" for w, k in sorted(meta["per_worker"].items())) or "none"
    print(f"{len(rows)} cells ({meta['ran_now']} run now, {meta['resumed']} kept from before), {diverged} diverged; "
          f"cells per worker: {workers}")
    from cli import report

    page = report.write_study(out)
    print(f"wrote {out / 'sweep.csv'}" + (", summary.csv" if seeds else "") + ", sweep.md and figures"
          + (f"; the report: {page}" if page else ""))
    return 0



def cmd_warm(args: argparse.Namespace) -> int:
    """Compile the kernels the mission's runs take into the machine's cache; blocks until done."""
    from sim import kernel, warm

    if not kernel.AVAILABLE:
        print("tether warm: numba is not installed, nothing to compile (pip install 'tether[fast]')", file=sys.stderr)
        return 0
    m = load(args.mission)
    parts = tuple(args.parts) if args.parts else ("refsim-discrete", "refsim-continuous", "lockstep")
    for part, compiled in warm.warm(m, parts).items():
        print(f"{part}: {'compiled' if compiled else 'already in the cache'}")
    return 0
