"""``tether simulate``, ``reproduce``, ``demo``, ``plot`` and ``mcap``: a mission in the reference
simulator, the paper's results, the distributed demo, and a run's figures and Foxglove file."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cli import args as cli_args
from cli.args import BadArgument
from tether import catalog, evloop, jsonout
from tether import mission as ms
from tether.progress import Progress

if TYPE_CHECKING:
    from tether.runfile import Run

FOXGLOVE_LAYOUT = "docs/foxglove/tether.json"
"""The Foxglove layout shipped in tether's source tree (docs/foxglove.md): a run's 3D view and plots."""


def next_steps(lines: list[str]) -> None:
    """End a command with what to do next: one line each, on stdout."""
    print("\nnext:")
    for line in lines:
        print(f"  {line}")


def foxglove_step(mcap: Path) -> str:
    """How to open a run's Foxglove file."""
    return (f"open {mcap} in Foxglove (Open local file), with the layout {FOXGLOVE_LAYOUT} from tether's source "
            "(Layout, Import from file; docs/foxglove.md)")


def _size(run: Run) -> str:
    """The run file's size, from its arrays (``run.npz`` stores them uncompressed)."""
    mb = sum(a.nbytes for a in run.arrays().values()) / 1e6
    return f"{mb:.3g} MB"


def unflown(m: ms.Mission, text: str) -> list[str]:
    """What ``m`` (its file's ``text``) asks for that the reference simulator does not fly: it steps
    the law alone, on double integrators, over ideal links, with no safety layer. One phrase each."""
    import tomllib

    try:
        tables = set(tomllib.loads(text))
    except tomllib.TOMLDecodeError:
        tables = set()
    said = []
    if m.netem is not None:
        said.append("[netem] (its links are flown ideal: no loss, no delay)")
    if "links" in tables:
        said.append("[links] (no neighbour is ever stale or dropped)")
    if "safety" in tables:
        said.append("[safety] (no supervisor, no envelope, no watchdog)")
    if m.payload is not None:
        said.append("its payload (no cables, no load)")
    kinds = sorted({type(a.plant).__name__ for a in m.agents} - {"DoubleIntegrator"})
    if kinds:
        said.append(f"its {', '.join(kinds)} plants (flown as double integrators)")
    return said


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """simulate, reproduce, demo, plot, mcap, report."""
    s = sub.add_parser("simulate", help="run a mission in the reference simulator (one process)")
    s.add_argument("mission", help=cli_args.MISSION_HELP)
    s.add_argument("--out", required=True, help="output directory (run.npz, metrics.json, figures)")
    s.add_argument("--mode", choices=["discrete", "continuous"], default="discrete",
                   help="sampled-data (the runtime's semantics) or continuous-time RK4")
    s.add_argument("--duration", type=cli_args.seconds, default=None, help="override the mission's duration [s]")
    s.add_argument("--substeps", type=cli_args.positive_int, default=10,
                   help="RK4 steps per control period (continuous mode)")
    s.add_argument("--engine", choices=["auto", "numpy", "compiled"], default="auto",
                   help="the compiled kernels (numba, the [fast] extra) or the numpy reference; auto: the "
                        "kernels when installed (without --live)")
    s.add_argument("--no-figures", action="store_true", help="no PNG figures (faster)")
    s.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
    s.add_argument("--scene-rate", type=cli_args.scene_rate, default=None, metavar="HZ",
                   help="rate of the 3D scene in run.mcap and the live view (default 25; 0: every tick)")
    s.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve the run over the Foxglove WebSocket protocol while it goes on (default port 8765)")
    s.add_argument("--speed", type=float, default=1.0,
                   help="with --live: mission seconds per wall second (default 1: real time; 0: as fast as it goes)")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reproduce", help="reproduce a result of the paper")
    r.add_argument("what", choices=["section4", "exp1", "exp2"],
                   help="section4: the Matlab case study (Figs. 4-6); exp1, exp2: the experiments of Section 5 in "
                        "simulation")
    r.add_argument("--out", required=True, help="directory for the figures, the metrics and report.md")
    r.add_argument("--duration", type=cli_args.seconds, default=None, help="override the 1000 s horizon [s]")
    r.add_argument("--continuous", action="store_true",
                   help="also run the continuous-time RK4 mode (under a second for section4 with the compiled "
                        "kernels, the [fast] extra; minutes on the numpy path)")
    r.set_defaults(func=cmd_reproduce)

    dm = sub.add_parser("demo", help="the main demo: Section 4 as separate processes over Zenoh (lockstep), figures")
    dm.add_argument("--out", default="runs/demo",
                    help="directory for the run (run.npz, run.mcap), its figures and logs (default runs/demo)")
    dm.add_argument("--duration", type=cli_args.seconds, default=30.0,
                    help="mission time to run [s] (the mission's is 1000)")
    dm.set_defaults(func=cmd_demo)

    mc = sub.add_parser("mcap", help="write a run's Foxglove file (run.mcap) from its run file")
    mc.add_argument("run", help="a run.npz or the directory holding it")
    mc.add_argument("--out", default=None, help="the MCAP file (default: run.mcap beside run.npz)")
    mc.add_argument("--scene-rate", type=cli_args.scene_rate, default=None, metavar="HZ",
                    help="rate of the 3D scene (default 25; 0: every tick)")
    mc.set_defaults(func=cmd_mcap)

    pl = sub.add_parser("plot", help="draw a run's figures from its run file (safety mode changes marked)")
    pl.add_argument("run", help="a run.npz or the directory holding it")
    pl.add_argument("--out", default=None,
                    help="directory for the figures (default: beside the run file)")
    pl.set_defaults(func=cmd_plot)

    from cli import report

    report.add_parser(sub)


def cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from sim import capacity, figures, metrics, refsim

    path = cli_args.mission_path(args.mission)
    m = cli_args.load(args.mission, args.duration)
    problems = capacity.problems(m, args.mode, args.substeps, args.engine, args.live is not None)
    if problems:
        raise ms.MissionError(str(args.mission), problems)
    out = cli_args.writable_dir("--out", args.out, ("run.npz", "metrics.json"))
    if m.safety.avoid is not None:  # said, not silently flown without it (the vehicles would meet)
        print(f"warning: {m.name} has [safety.avoid], which the reference simulator does not fly: it computes the "
              "law alone, without the safety layer, so these vehicles may pass through each other; `tether run "
              f"{args.mission}` flies the filter (docs/safety.md)", file=sys.stderr)
    skipped = unflown(m, path.read_text())
    note = None
    if skipped:  # said in one line, and on the report: the figures are of the law alone
        note = (f"tether simulate flies the law alone: {m.name} asks for {'; '.join(skipped)}, which it does not "
                f"fly; `tether run {args.mission}` flies them all (docs/netem.md)")
        print(f"warning: {note}", file=sys.stderr)
    cli_args.check_live(args.live)
    slow = capacity.slow_path() if args.engine == "auto" else None
    if slow is not None:
        print(slow, file=sys.stderr)
    prog = Progress()
    live = None
    if args.live is not None:  # the live view (docs/foxglove.md): needs the viz extra
        from recorder import viz

        live = viz.Live(port=args.live, speed=args.speed, mission=m, scene_rate=args.scene_rate)
        print(f"live view: ws://127.0.0.1:{live.port} (Foxglove: Open connection, Foxglove WebSocket)", flush=True)
    print(f"simulating {m.name}: {m.steps} ticks of {m.n} agents, {args.mode}", file=sys.stderr, flush=True)
    try:
        try:
            run = refsim.simulate(m, args.mode, substeps=args.substeps, progress=lambda k, n: prog(k, n, m.name),
                                  on_tick=live.tick if live else None, engine=args.engine)
        except ValueError as e:
            if args.engine != "compiled":
                raise
            print(f"tether simulate: --engine compiled: {e}", file=sys.stderr)
            return 2
        if live is not None:
            live.finish(run)
    finally:
        if live is not None:
            live.close()
    run.meta.mission_text = path.read_text()
    from tether import safefs

    real = safefs.make_out(out)  # checked by writable_dir; made here following no link
    print(f"writing {out / 'run.npz'} ({_size(run)})", file=sys.stderr, flush=True)
    run.save(out / "run.npz")
    diverged = not all(np.all(np.isfinite(getattr(run, f))) for f in ("p", "v", "kp", "kv"))
    summary = jsonout.finite(metrics.report(run) if not diverged else metrics.summary(run))
    assert isinstance(summary, dict)
    if note is not None:
        summary["not_flown"] = skipped
    safefs.write_file(real / "metrics.json", jsonout.dumps(summary).encode())
    if diverged:
        print(f"error: the run diverged (non-finite states or gains); wrote {out / 'run.npz'} and "
              f"{out / 'metrics.json'}, no figures; check the mission's gains and limits", file=sys.stderr)
        return 1
    mcap = None
    if not args.no_mcap:
        from recorder.export import mcap_beside

        print(f"writing {out / 'run.mcap'} (the Foxglove file)", file=sys.stderr, flush=True)
        mcap = mcap_beside(run, m, out / "run.npz", scene_rate=args.scene_rate)
    drawn: list[Path] = []
    if not args.no_figures:
        print(f"drawing the figures in {out}", file=sys.stderr, flush=True)
        drawn = list(figures.run_panels(run, out))
    from cli import report

    page = report.write_run(out, run, drawn=drawn, notes=(note,) if note else ())
    print(jsonout.dumps(summary))
    print(f"wrote {out / 'run.npz'}" + (f" and {mcap}" if mcap else "") + f"; the report: {page}")
    steps = [f"the report (one page, for the log book): {page}"]
    steps += [f"the figures (SVG beside each): {', '.join(str(p) for p in drawn)}"] if drawn else []
    steps += [foxglove_step(mcap)] if mcap else []
    steps += [f"tether run {args.mission} --out DIR: the same mission as separate processes over Zenoh"]
    next_steps(steps)
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from sim import reproduce

    cli_args.load(args.what, args.duration)  # --duration checked against the mission it shortens, before anything runs
    cli_args.writable_dir("--out", args.out, ("metrics.json", "metrics.md", "report.md"))
    from sim import capacity

    slow = capacity.slow_path()
    if slow is not None:
        print(slow, file=sys.stderr)
    prog = Progress()
    if args.what != "section4":
        from sim import experiments

        result = experiments.run_experiment(args.what, Path(args.out), duration=args.duration, progress=prog)
        print((Path(args.out) / "report.md").read_text())
        print("figures: " + ", ".join(result["figures"]))
        return 0
    result = reproduce.section4(Path(args.out), duration=args.duration, continuous=args.continuous,
                                progress=prog)
    print((Path(args.out) / "metrics.md").read_text())
    print("figures: " + ", ".join(result["figures"]))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """The README's demo: the Section 4 mission as separate processes over Zenoh in lockstep,
    its figures, and its agreement with the reference simulator (the runtime's oracle)."""
    import logging

    import numpy as np

    from deploy import local, options
    from sim import figures, refsim
    from tether.runfile import Run

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s launcher: %(message)s")
    path = catalog.builtin_path("section4")
    m = cli_args.load(str(path), args.duration)
    out = cli_args.writable_dir("--out", args.out, ("run.npz",))
    # the architecture as deployed: one process per plant (tether run co-locates them by default in lockstep)
    opts = options.LaunchOptions(out=out, clock="lockstep", duration=args.duration, colocate_plants=False)
    status = evloop.run(local.run(path, opts))
    if status != 0:
        return status
    run = Run.load(out)
    print("simulating the same mission in the reference simulator, to compare", file=sys.stderr, flush=True)
    ref = refsim.simulate(m)
    worst = max(float(np.nanmax(np.abs(getattr(run, f) - getattr(ref, f)))) for f in ("p", "v", "kp", "kv", "xi"))
    print(f"drawing the figures in {out}", file=sys.stderr, flush=True)
    drawn = list(figures.run_panels(run, out))
    for p in drawn:
        print(f"wrote {p}")
    from cli import report
    from sim import metrics
    from tether import safefs

    safefs.write_file(out / "metrics.json", jsonout.dumps(jsonout.finite(metrics.report(run))).encode())
    page = report.write_run(out, run, drawn=drawn, status=(status, "clean"))
    print(f"distributed lockstep run vs reference simulator: max |difference| over p, v, xi, Kp, Kv = {worst:.3g}")
    steps = [f"the report (one page, for the log book): {page}", f"the figures: {', '.join(str(p) for p in drawn)}"]
    steps += [foxglove_step(out / "run.mcap")] if (out / "run.mcap").exists() else []
    steps += [f"the processes' logs: {out / 'logs'}",
              "tether reproduce section4 --out runs/section4: the paper's Figs. 4-6 over 1000 s and the report "
              "(metrics.md)",
              "tether missions: the other shipped missions, to simulate or run"]
    next_steps(steps)
    return 0 if worst <= 1e-9 else 1


def cmd_plot(args: argparse.Namespace) -> int:
    import zipfile

    import msgspec

    from recorder import journal
    from sim import figures
    from tether.runfile import Run

    path = Path(args.run)
    file = path / "run.npz" if path.is_dir() else path
    if path.is_dir() and not file.exists() and (path / journal.NAME).exists():  # a recorder killed mid-run
        try:
            run = journal.load(path, report=lambda line: print(f"missing: {line}"))
        except (OSError, ValueError) as exc:
            raise BadArgument(f"run: {path / journal.NAME} is not a readable journal ({exc}); "
                              "give a run.npz that tether wrote") from None
        out = cli_args.writable_dir("--out", args.out if args.out else str(path))
        for p in figures.run_panels(run, out):
            print(f"wrote {p}")
        return 0
    if not path.exists():
        raise BadArgument(f"run: {path} does not exist; give a run.npz or the directory holding it "
                          "(tether simulate/run --out DIR writes DIR/run.npz)")
    if not file.is_file():
        raise BadArgument(f"run: {file} is not a file; give a run.npz or the directory holding it")
    with open(file, "rb") as fh:
        head = fh.read(4)
    if head != b"PK\x03\x04":
        raise BadArgument(f"run: {file} is not a run file (a run.npz is a zip archive; this file does not start "
                          "like one: truncated, or another kind of file); give a run.npz that tether wrote")
    try:
        run = Run.load(file)
    except (OSError, ValueError, KeyError, IndexError, TypeError, EOFError, zipfile.BadZipFile,
            msgspec.MsgspecError) as exc:  # a bad zip, a truncated array, foreign metadata
        raise BadArgument(f"run: {file} is not a readable run file ({type(exc).__name__}: "
                          f"{str(exc).splitlines()[0] if str(exc) else 'no detail'}); give a run.npz that "
                          "tether wrote, or write it again") from None
    out = cli_args.writable_dir("--out", args.out if args.out else str(path if path.is_dir() else path.parent))
    for p in figures.run_panels(run, out):
        print(f"wrote {p}")
    return 0


def cmd_mcap(args: argparse.Namespace) -> int:
    from recorder import journal, viz

    path = Path(args.run)
    try:  # run.npz, or the journal a killed recorder left; what the run lacks, line by line
        run = journal.load(path, report=lambda line: print(f"missing: {line}"))
    except (OSError, ValueError) as exc:
        raise BadArgument(f"run: {path} holds no readable run ({exc}); give a run.npz or the directory "
                          "tether run --out wrote") from None
    npz = path / "run.npz" if path.is_dir() else path
    out = Path(args.out) if args.out else npz.with_suffix(".mcap")
    import numpy as np

    from tether.runfile import NO_SAMPLE

    t0 = time.perf_counter()
    viz.write_mcap(run, None, out, scene_rate=viz.SCENE_RATE if args.scene_rate is None else args.scene_rate)
    have = int(np.any(run.safety.safety_mode != NO_SAMPLE, axis=1).sum())  # ticks with any agent's telemetry
    ticks = f"{have} ticks" if have == len(run.t) else f"{have} of {len(run.t)} planned ticks recorded"
    print(f"wrote {out} ({ticks}, {len(run.agent_ids)} agents) in {time.perf_counter() - t0:.2f} s")
    return 0
