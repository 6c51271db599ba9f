"""The ``tether`` command. Parses argv and mission files, then calls the library; nothing else.

Exit status (every command's, in ``docs/exit-status.md``): 0 success, 1 a run failed (also a write
that failed part-way: the path and errno are named), 2 bad input (mission file or arguments,
checked before anything starts), 130 interrupted; ``tether run`` also 3 (a failsafe fired or a
value diverged) and 4 (a process died or froze in a real-time run): ``deploy/local.py``.
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import shlex
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TypeVar

from tether import catalog, evloop, jsonout
from tether import mission as ms
from tether.progress import Progress

if TYPE_CHECKING:  # each subcommand imports what it runs
    from tether.clock import LockstepClock, RealtimeClock
    from tether.node import Node, NodeArgs
    from tether.transport import ZenohSettings

T = TypeVar("T")


def _load(arg: str, duration: float | None = None) -> ms.Mission:
    """The mission ``arg`` names, with ``--duration`` applied and checked (:func:`tether.mission.with_duration`)."""
    path = catalog.resolve(arg)
    return ms.with_duration(ms.load(path), duration, str(path))


class BadArgument(Exception):
    """A command-line argument is unusable: ``"<argument>: <what is wrong>; <how to fix it>"`` (exit 2)."""


def _seconds(text: str) -> float:
    """An argparse type: a finite number of seconds > 0 (every ``--duration``)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds; give e.g. 30") from None
    if not math.isfinite(x) or x <= 0:
        raise argparse.ArgumentTypeError(f"{text} s is not a run length; give a finite number of seconds > 0, e.g. 30")
    return x


def _int_at_least(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: a whole number >= ``lo`` (and <= ``hi``, if given)."""
    def convert(text: str) -> int:
        try:
            x = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer; give e.g. 10") from None
        if x < lo:
            raise argparse.ArgumentTypeError(f"{x} is not >= {lo}; give e.g. 10")
        if hi is not None and x > hi:
            raise argparse.ArgumentTypeError(f"{x} is more than {hi}; give at most {hi}")
        return x

    return convert


_positive_int = _int_at_least(1)


def _record_ticks(text: str) -> int:
    """An argparse type: ticks per record, at most ``wire.RECORD_MAX`` (a record of more is dropped
    by its receiver as ``size``)."""
    from tether import wire

    return _int_at_least(1, wire.RECORD_MAX)(text)


def _rt_priority(text: str) -> int:
    """An argparse type: a real-time priority, 1..99 (``SCHED_RR``), or 0 (the normal policy)."""
    from tether import sched

    try:
        x = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer; give {sched.RR_MIN}..{sched.RR_MAX}, "
                                         "e.g. 10") from None
    why = sched.check_priority(x)
    if why is not None:
        raise argparse.ArgumentTypeError(why)
    return x


def _writable_dir(arg: str, text: str, outputs: tuple[str, ...] = ()) -> Path:
    """Check, before anything runs, that directory ``text`` (option ``arg``) can be written in: it
    is a directory, or does not exist yet below a writable one (a probe file is made and removed
    there; nothing else is created), no one else can redirect it (``tether.safefs.out_problem``),
    and none of ``outputs`` inside it is a directory. Raises :class:`BadArgument` naming the
    option, the path and the cause."""
    out = Path(text)
    if out.exists() and not out.is_dir():
        raise BadArgument(f"{arg}: {out} is an existing file, not a directory; give a directory (it is made if missing)")
    base = out.absolute()
    while not base.exists():
        base = base.parent
    if not base.is_dir():
        raise BadArgument(f"{arg}: {base} is a file, so {out} cannot be made; give another directory")
    from tether import safefs

    unsafe = safefs.out_problem(out)
    if unsafe is not None:
        raise BadArgument(f"{arg}: {unsafe}")
    try:
        import tempfile  # here: every process starts through this module

        with tempfile.NamedTemporaryFile(dir=base, prefix=".tether-probe-"):
            pass
    except OSError as exc:
        raise BadArgument(f"{arg}: cannot write in {base} ({exc.strerror or exc}, "
                          f"{errno.errorcode.get(exc.errno or 0, 'errno ' + str(exc.errno))}); "
                          "give a writable directory") from None
    for name in outputs:
        if (out / name).is_dir():
            raise BadArgument(f"{arg}: {out / name} is a directory where the run writes a file; remove it or "
                              "give another --out")
    return out


def cmd_check(args: argparse.Namespace) -> int:
    from tether import graph

    m = _load(args.mission)
    import numpy as np

    topo = graph.topology(m)
    try:
        numeric = graph.lemma3_holds(topo)
    except (AssertionError, np.linalg.LinAlgError) as exc:  # ill-conditioned beyond what the weight range allows
        raise ms.MissionError(str(catalog.resolve(args.mission)), [
            ("edges", f"fail Lemma 3 numerically ({str(exc).splitlines()[0]}); spread the weights less "
                      "(their ratio sets L1's conditioning) or shorten the longest path from the leader")]) from None
    n = m.n
    print(f"mission {m.name!r} (version {m.version}): {n} agents, dim {m.dim}, {m.rate:g} Hz, "
          f"{m.duration:g} s ({m.steps} steps), seed {m.seed}")
    law = m.law
    print(f"law {law.kind}: Kp(0)={ms.per_axis(law.kp0, m.dim)} Kv(0)={ms.per_axis(law.kv0, m.dim)} "
          f"Gamma_p={law.gamma_p:g} Gamma_v={law.gamma_v:g}" + (f" sigma={law.sigma:g}" if law.sigma else ""))
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


def cmd_simulate(args: argparse.Namespace) -> int:
    from sim import figures, metrics, refsim
    from sim.refsim import Setup

    import numpy as np

    m = _load(args.mission, args.duration)
    from tether.graph import DENSE_MAX

    from tether.checks import MAX_AGENT_TICKS

    if args.mode == "continuous" and m.steps * args.substeps * m.n > MAX_AGENT_TICKS:
        raise ms.MissionError(str(args.mission), [(
            "--substeps", f"is {args.substeps}: {m.steps} steps x {args.substeps} substeps x {m.n} agents = "
                          f"{m.steps * args.substeps * m.n:.3g} agent-substeps, beyond the limit of "
                          f"{MAX_AGENT_TICKS:.0e}; use fewer substeps (10 is plenty for RK4) or a shorter --duration")])
    if args.mode == "continuous" and m.n > DENSE_MAX:
        # the numpy path inverts the dense N x N matrix L1; the compiled kernel only each strongly
        # connected block of the agents' graph (sim.kernel.solve_plan)
        from sim import kernel

        s = Setup.of(m)
        block = kernel.largest_block(m.n, s.topo.src, s.topo.dst)
        try:
            compiled = refsim.takes_kernel(s, args.engine, None) and args.live is None
        except ValueError:  # --engine compiled where it cannot run: refused below as the numpy path
            compiled = False
        if not compiled or block > DENSE_MAX:
            why = (f"inverts the dense {m.n} x {m.n} matrix L1 (about {8 * m.n * m.n / 2**30:.3g} GiB and O(N^3) "
                   f"time) on the numpy path (--engine numpy, --live, numba missing or a disturbance it does "
                   f"not know)" if not compiled else
                   f"inverts the largest strongly connected block of the agents' graph, {block} agents here")
            raise ms.MissionError(str(args.mission), [(
                "--mode", f"is continuous, which {why}; use --mode discrete (sparse, the runtime's semantics), "
                          f"or at most {DENSE_MAX} agents in one strongly connected block with the compiled "
                          f"engine")])
    out = _writable_dir("--out", args.out, ("run.npz", "metrics.json"))
    if m.safety.avoid is not None:  # said, not silently flown without it (the vehicles would meet)
        print(f"warning: {m.name} has [safety.avoid], which the reference simulator does not fly: it computes the "
              "law alone, without the safety layer, so these vehicles may pass through each other; `tether run "
              f"{args.mission}` flies the filter (docs/safety.md)", file=sys.stderr)
    prog = Progress()
    live = None
    _check_live(args.live)
    if args.live is not None:  # the live view (docs/foxglove.md): needs the viz extra
        from recorder import viz

        live = viz.Live(port=args.live, speed=args.speed, mission=m, scene_rate=args.scene_rate)
        print(f"live view: ws://127.0.0.1:{live.port} (Foxglove: Open connection, Foxglove WebSocket)", flush=True)
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
    run.meta.mission_text = catalog.resolve(args.mission).read_text()
    from tether import safefs

    real = safefs.make_out(out)  # checked by _writable_dir; made here following no link
    run.save(out / "run.npz")
    summary = jsonout.finite(metrics.summary(run))
    assert isinstance(summary, dict)
    diverged = not all(np.all(np.isfinite(getattr(run, f))) for f in ("p", "v", "kp", "kv"))
    if not diverged:
        summary["tracking_error_m"] = jsonout.finite(metrics.tracking_error(run, Setup.of(m).offsets[: m.n]))
    safefs.write_file(real / "metrics.json", jsonout.dumps(summary).encode())
    if diverged:
        print(f"error: the run diverged (non-finite states or gains); wrote {out / 'run.npz'} and "
              f"{out / 'metrics.json'}, no figures; check the mission's gains and limits", file=sys.stderr)
        return 1
    mcap = None
    if not args.no_mcap:
        from recorder.export import mcap_beside

        mcap = mcap_beside(run, m, out / "run.npz", scene_rate=args.scene_rate)
    if not args.no_figures:
        figures.run_panels(run, out)
    print(jsonout.dumps(summary))
    print(f"wrote {out / 'run.npz'}" + (f" and {mcap}" if mcap else ""))
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from sim import reproduce

    _load(args.what, args.duration)  # --duration checked against the mission it shortens, before anything runs
    _writable_dir("--out", args.out, ("metrics.json", "metrics.md", "report.md"))
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
    from tether.node import load_mission
    from tether.runfile import Run

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s launcher: %(message)s")
    path = catalog.builtin_path("section4")
    _load(str(path), args.duration)
    m = load_mission(path, args.duration)
    out = _writable_dir("--out", args.out, ("run.npz",))
    # the architecture as deployed: one process per plant (tether run co-locates them by default in lockstep)
    opts = options.LaunchOptions(out=out, clock="lockstep", duration=args.duration, colocate_plants=False)
    status = evloop.run(local.run(path, opts))
    if status != 0:
        return status
    run = Run.load(out)
    ref = refsim.simulate(m)
    worst = max(float(np.nanmax(np.abs(getattr(run, f) - getattr(ref, f)))) for f in ("p", "v", "kp", "kv", "xi"))
    for p in figures.run_panels(run, out):
        print(f"wrote {p}")
    print(f"distributed lockstep run vs reference simulator: max |difference| over p, v, xi, Kp, Kv = {worst:.3g}")
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
        out = _writable_dir("--out", args.out if args.out else str(path))
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
    out = _writable_dir("--out", args.out if args.out else str(path if path.is_dir() else path.parent))
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
    t0 = time.perf_counter()
    viz.write_mcap(run, None, out, scene_rate=viz.SCENE_RATE if args.scene_rate is None else args.scene_rate)
    print(f"wrote {out} ({len(run.t)} ticks, {len(run.agent_ids)} agents) in {time.perf_counter() - t0:.2f} s")
    return 0


def _zenoh_settings(args: argparse.Namespace) -> ZenohSettings:
    """The Zenoh settings of ``--zenoh-config FILE``, or of --zenoh-mode/--listen/--connect/--lease/
    --connect-timeout. Raises SettingsError naming the field."""
    from tether import transport as tp

    if args.zenoh_config is not None:
        if args.listen or args.connect:
            raise tp.SettingsError([("--zenoh-config", "is given with --listen/--connect; the file is "
                                                       "the whole configuration: drop those, or drop --zenoh-config")])
        settings = tp.ZenohSettings(config_file=args.zenoh_config)
    else:
        settings = tp.ZenohSettings(mode=args.zenoh_mode, listen=tuple(args.listen), connect=tuple(args.connect),
                                    lease=args.lease, connect_timeout=args.connect_timeout)
    tp.zenoh_config(settings)
    return settings


def _node_args(args: argparse.Namespace, role: str, node_id: int) -> NodeArgs:
    from tether.node import NodeArgs

    settings = _zenoh_settings(args)
    return NodeArgs(mission_path=catalog.resolve(args.mission), role=role, node_id=node_id, clock=args.clock,
                    zenoh=settings, ns=args.ns, stall_timeout=args.stall_timeout, parent_pid=args.parent_pid,
                    duration=args.duration, start_timeout=args.start_timeout,
                    colocate=getattr(args, "colocate_plant", False), record_batch=getattr(args, "record_batch", 1),
                    mesh_peers=getattr(args, "mesh_peers", 0), window=getattr(args, "window", 0))


def _serve(args: argparse.Namespace, role: str, node_id: int, body: Callable[[Node], Awaitable[None]],
           on_stop: Callable[[Node], None] | None = None) -> int:
    from tether.node import serve, setup_logging

    setup_logging(role, node_id, args.log_level)
    if args.rt_priority is not None:  # first: the threads started from now on (Zenoh's) inherit it
        import logging

        from tether import sched

        try:
            applied = sched.apply(args.rt_priority)
        except sched.SchedError as exc:
            raise BadArgument(f"--rt-priority: {exc}") from None
        logging.getLogger("tether").info("CPU scheduling: %s", applied)
    elif args.clock == "realtime" and args.parent_pid is None:  # started alone: the default, or one line why not
        import logging

        from tether import sched

        got, line = sched.apply_best()
        (logging.getLogger("tether").info if got else logging.getLogger("tether").warning)("CPU scheduling: %s", line)
    return evloop.run(serve(_node_args(args, role, node_id), body, on_stop, clock=_skewed_clock(args)))


def _skewed_clock(args: argparse.Namespace) -> LockstepClock | RealtimeClock | None:
    """The process's clock when ``--clock-skew`` offsets it (an emulated unsynchronised host), else None."""
    if not args.clock_skew:
        return None
    from tether.clock import make

    if args.clock != "realtime":
        raise BadArgument("--clock-skew: lockstep ticks follow the clock source, not a clock; use --clock realtime")
    return make("realtime", _load(args.mission, args.duration).dt, args.clock_skew)


def cmd_leader(args: argparse.Namespace) -> int:
    from leader import node

    m = _load(args.mission)
    if args.record_batch and args.clock != "lockstep":
        raise BadArgument("--record-batch: records are for lockstep runs (in real time the recorder hears every "
                          "state); drop it, or give --clock lockstep")
    return _serve(args, "leader", m.leader.id, node.run)


def cmd_agent(args: argparse.Namespace) -> int:
    from agent import node

    _check_id(args)
    return _serve(args, "agent", args.id, node.run)


def cmd_plant(args: argparse.Namespace) -> int:
    from plant import node

    _check_id(args)
    return _serve(args, "plant", args.id, node.run)


def cmd_world(args: argparse.Namespace) -> int:
    from plant import node

    m = _load(args.mission)
    real = [a.id for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]
    if real:
        raise ms.MissionError(str(args.mission), [(f"agent {real[0]}.plant", "is a crazyflie, a real vehicle: a "
                                                   "world hosts simulated vehicles only; run `tether plant --id I` "
                                                   "for each crazyflie")])
    return _serve(args, "world", 0, node.run_world)


def cmd_recorder(args: argparse.Namespace) -> int:
    from recorder import node as recorder

    run, on_stop = recorder.make(Path(args.out), live=args.live, mcap=not args.no_mcap)
    return _serve(args, "recorder", 0, run, on_stop)


def _check_id(args: argparse.Namespace) -> None:
    m = _load(args.mission)
    if args.id not in m.agent_ids:
        raise ms.MissionError(str(args.mission), [("--id", f"{args.id} is not an agent of this mission; use one of {m.agent_ids}")])


def cmd_sweep(args: argparse.Namespace) -> int:
    from cli.study import cmd_study  # studies (executors, resume, Monte Carlo): cli/study.py

    return cmd_study(args)


def cmd_netem_set(args: argparse.Namespace) -> int:
    from tether.netprofile import ProfileError
    from netem import control

    try:
        profile = control.parse_profile(args.profile)
    except ProfileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from tether.transport import TransportError

    settings = _zenoh_settings(args)
    try:
        answers = evloop.run(control.netem_set(settings, args.ns, control.rule_of(profile, args.src, args.dst),
                                               args.at, args.timeout))
    except TimeoutError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except TransportError as exc:  # no router reachable: one line, as land and estop say it
        print(f"error: {exc}; check --connect (the run's router, or an endpoint it opened with --listen) and "
              "that the run is up", file=sys.stderr)
        return 1
    ok = True
    for a in sorted(answers, key=lambda a: (a.node is None, a.node or 0)):
        who = f"agent {a.node}" if a.node is not None else "an agent"
        if a.error is not None:
            ok = False
            print(f"{who}: {a.error}")
        elif not a.changed:
            print(f"{who}: no matching in-link")
        else:
            print(f"{who}: " + ", ".join(f"{c['src']} -> {c['dst']} from t = {c['at']:.3f} s" for c in a.changed))
    if not answers:
        print(f"error: no agent of namespace {args.ns!r} answered within {args.timeout:g} s; "
              "check --ns and --connect", file=sys.stderr)
        return 1
    return 0 if ok else 1


def cmd_safety(args: argparse.Namespace) -> int:
    """``tether land`` / ``tether estop``: one operator order to every vehicle of a running swarm."""
    from deploy import operator
    from tether import transport as tp
    from tether import wire

    try:
        wire.Keys(args.ns)
    except ValueError as exc:
        print(f"error: --ns: {exc}", file=sys.stderr)
        return 2
    if not args.timeout > 0:
        print(f"error: --timeout is {args.timeout}; give seconds > 0", file=sys.stderr)
        return 2
    if args.zenoh_config is None and not args.connect:
        print("error: --connect is missing: give the run's router endpoint (e.g. --connect tcp/127.0.0.1:7447, "
              "one that tether run --listen opened) or --zenoh-config FILE", file=sys.stderr)
        return 2
    settings = _zenoh_settings(args)
    got, line = operator.take_priority()  # before the session opens: its threads inherit it
    print(f"{'info' if got else 'warning'}: CPU scheduling of this order: {line}", file=sys.stderr)
    try:
        msg = evloop.run(operator.send(settings, args.ns, args.action, args.reason, args.timeout))
    except (operator.Unreachable, operator.NobodyListens, tp.TransportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"sent {msg.action} (order {msg.seq}) to namespace {args.ns!r} on {wire.Keys(args.ns).safety}, "
          f"{operator.REPEATS} copies over {operator.SPREAD:g} s")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    import logging

    from deploy import local, options

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s launcher: %(message)s")
    from tether.node import load_mission

    from deploy import faults

    path = catalog.resolve(args.mission)
    _load(args.mission, args.duration)
    load_mission(path, args.duration)
    _writable_dir("--out", args.out, ("run.npz",))
    _check_live(args.live)
    if (Path(args.out) / "logs").exists() and not (Path(args.out) / "logs").is_dir():
        raise BadArgument(f"--out: {Path(args.out) / 'logs'} is a file where the run writes its logs; remove it "
                          "or give another --out")
    if args.ns is not None:
        from tether import wire

        try:
            wire.Keys(args.ns)
        except ValueError as exc:
            raise BadArgument(f"--ns: {exc}") from None
    try:
        injected = tuple(faults.parse(text) for text in args.fault)
    except faults.FaultError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.sitl_args and not args.sitl:
        raise BadArgument("--sitl-args: give it with --sitl")
    if args.colocate_plants and args.separate_plants:
        raise BadArgument("--separate-plants: and --colocate-plants both say where the plants run; give one of them")
    clock: Literal["lockstep", "realtime"] = args.clock or ("realtime" if args.sitl else "lockstep")
    opts = options.LaunchOptions(out=Path(args.out), clock=clock, network=args.network, window=args.window,
                                 ns=args.ns, stall_timeout=args.stall_timeout, progress=not args.quiet,
                                 duration=args.duration, handover_runtime=not args.no_handover,
                                 listen=tuple(args.listen), lease=args.lease, wrap=dict(args.wrap),
                                 vehicle_connect=dict(args.vehicle_connect), faults=injected,
                                 insecure=args.insecure, live=args.live, mcap=not args.no_mcap,
                                 colocate_plants=True if args.colocate_plants else False if args.separate_plants else None,
                                 record_batch=args.record_batch,
                                 shared_plants=args.shared_plants, rt_priority=args.rt_priority,
                                 sitl=tuple(shlex.split(args.sitl_args)) if args.sitl else None)
    return evloop.run(local.run(path, opts))


def _check_live(port: int | None) -> None:
    """``--live PORT``: a port this machine can serve on now (exit 2 before anything starts)."""
    from cli import live

    problem = live.port_problem(port)
    if problem is not None:
        raise BadArgument(problem)


def _vehicle_option(parse: Callable[[str], T], example: str) -> Callable[[str], tuple[int, T]]:
    """An argparse type for ``ID=VALUE``: ``(int(ID), parse(VALUE))``."""
    def convert(text: str) -> tuple[int, T]:
        nid, sep, value = text.partition("=")
        try:
            if not sep:
                raise ValueError
            return int(nid), parse(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not ID=VALUE, e.g. {example}") from None

    return convert


def _zenoh_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh JSON5 configuration (from tether deploy-gen: mTLS, access control); "
                        "replaces the options below")
    g.add_argument("--zenoh-mode", choices=["peer", "client", "router"], default="peer")
    g.add_argument("--listen", action="append", default=[], help="endpoint to listen on (repeatable)")
    g.add_argument("--connect", action="append", default=[], help="endpoint to connect to (repeatable)")
    g.add_argument("--lease", type=_lease, default=2.0, help="link lease [s]: a frozen peer is seen gone after it")
    g.add_argument("--connect-timeout", type=float, default=10.0, help="how long to retry --connect at start [s]")
    g.add_argument("--mesh-peers", type=_int_at_least(0), default=0, metavar="N",
                   help="a peer of a mesh (tether run --network mesh): declare this process's liveliness token only "
                        "once it is linked to N other peers, because the launcher starts the run on the tokens "
                        "(exit 1 if they are not all linked within --connect-timeout)")


def _skew(text: str) -> float:
    from tether.clock import check_skew

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds; write e.g. +0.05") from None
    if (why := check_skew(value, "")) is not None:
        raise argparse.ArgumentTypeError(why.removeprefix(": "))
    return value


def _positive_seconds(text: str) -> float:
    """An argparse type: a finite number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a number of seconds > 0, e.g. 120")
    return value


def _lease(text: str) -> float:
    """An argparse type: a link lease [s], finite, > 0 and at most an hour."""
    value = _positive_seconds(text)
    if value > 3600:
        raise argparse.ArgumentTypeError(f"{text} s: a lease beyond an hour would not see a frozen peer gone within "
                                         "the run; give e.g. 2")
    return value


def _scene_rate(text: str) -> float:
    """An argparse type: a scene rate [Hz], finite and >= 0 (0: every tick)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a rate in Hz >= 0, e.g. 25 (0: every tick)")
    return value


def _process_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mission", required=True)
    p.add_argument("--clock", choices=["lockstep", "realtime"], default="realtime")
    p.add_argument("--ns", default=None, help="key namespace (default: the mission name)")
    p.add_argument("--stall-timeout", type=_positive_seconds, default=30.0, help="lockstep: fail after waiting this long [s]")
    p.add_argument("--window", type=_int_at_least(0), default=0, metavar="TICKS",
                   help="lockstep: the clock's window (tether run's --window); the process keeps each stream's messages "
                        "of its last TICKS + 1 ticks, to send again when a tick has waited for its inputs for a while "
                        "(0: keeps none)")
    p.add_argument("--parent-pid", type=int, default=None, help="stop when this process is gone")
    p.add_argument("--start-timeout", type=_positive_seconds, default=None,
                   help="fail (exit 1) when the start message has not come this long after the process is "
                        "ready [s]; default: wait for ever (a service waiting for its operator's start)")
    p.add_argument("--duration", type=_seconds, default=None, help="override the mission's duration [s]")
    p.add_argument("--clock-skew", type=_skew, default=0.0, metavar="S",
                   help="real time: this process's clock reads S seconds ahead (negative: behind) of the host's, "
                        "to rehearse unsynchronised hosts (tether run --fault skew:ROLE/ID=S)")
    p.add_argument("--log-level", default="INFO")
    p.add_argument("--rt-priority", type=_rt_priority, default=None, metavar="P",
                   help="run this process at real-time priority P (SCHED_RR, 1..99; 0: the normal policy), set "
                        "before its threads start; needs root, CAP_SYS_NICE or an rtprio limit (docs/runtime.md)")
    _zenoh_options(p)


PROCESSES = ("leader", "agent", "plant", "world", "recorder")
"""The process commands: what the launcher and the deployment's units start, one per process."""


class _Formatter(argparse.HelpFormatter):
    """argparse's help layout, measuring the terminal as ``shutil.get_terminal_size`` does without
    importing ``shutil``: argparse imports it for every argument it adds, and with it ``bz2``,
    ``lzma`` and their libraries, 0.34 MiB of every control process's memory for nothing."""

    def __init__(self, prog: str, indent_increment: int = 2, max_help_position: int = 24,
                 width: int | None = None) -> None:
        super().__init__(prog, indent_increment, max_help_position,
                         _terminal_columns() - 2 if width is None else width)


def _terminal_columns() -> int:
    try:
        columns = int(os.environ.get("COLUMNS", "0"))
    except ValueError:
        columns = 0
    if columns <= 0:
        try:
            columns = os.get_terminal_size(sys.__stdout__.fileno()).columns  # type: ignore[union-attr]
        except (AttributeError, ValueError, OSError):
            columns = 0
    return columns if columns > 0 else 80


class _Parser(argparse.ArgumentParser):
    """An argument parser laid out by :class:`_Formatter` (its subparsers are of this class too)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(**kwargs)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; for ``command`` one of :data:`PROCESSES` (how every process of a run
    is started), the process commands alone. The others would cost each control process about
    1 MiB of memory for nothing: their argparse objects, and the modules some of them live in
    (``deploy.gen`` alone brings ``subprocess``, ``hashlib``, ``secrets`` and ``tempfile``)."""
    p = _Parser(prog="tether", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    if command in PROCESSES:
        _process_commands(sub)
        return p
    _run_commands(sub)
    _process_commands(sub)
    _study_and_tool_commands(sub)
    return p


def _run_commands(sub: argparse._SubParsersAction) -> None:
    """check, simulate, reproduce, demo, run."""
    c = sub.add_parser("check", help="validate a mission file and print a summary")
    c.add_argument("mission", help="mission file, or the name of a shipped mission (" + ", ".join(catalog.builtin_names()) + ")")
    c.set_defaults(func=cmd_check)

    s = sub.add_parser("simulate", help="run a mission in the reference simulator (one process)")
    s.add_argument("mission")
    s.add_argument("--out", required=True, help="output directory (run.npz, metrics.json, figures)")
    s.add_argument("--mode", choices=["discrete", "continuous"], default="discrete",
                   help="sampled-data (the runtime's semantics) or continuous-time RK4")
    s.add_argument("--duration", type=_seconds, default=None, help="override the mission's duration [s]")
    s.add_argument("--substeps", type=_positive_int, default=10, help="RK4 steps per control period (continuous mode)")
    s.add_argument("--engine", choices=["auto", "numpy", "compiled"], default="auto",
                   help="the compiled kernels (numba, the [fast] extra) or the numpy reference; auto: the "
                        "kernels when installed (without --live)")
    s.add_argument("--no-figures", action="store_true")
    s.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
    s.add_argument("--scene-rate", type=_scene_rate, default=None, metavar="HZ",
                   help="rate of the 3D scene in run.mcap and the live view (default 25; 0: every tick)")
    s.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve the run over the Foxglove WebSocket protocol while it goes on (default port 8765)")
    s.add_argument("--speed", type=float, default=1.0,
                   help="with --live: mission seconds per wall second (default 1: real time; 0: as fast as it goes)")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reproduce", help="reproduce a result of the paper")
    r.add_argument("what", choices=["section4", "exp1", "exp2"])
    r.add_argument("--out", required=True)
    r.add_argument("--duration", type=_seconds, default=None, help="override the 1000 s horizon [s]")
    r.add_argument("--continuous", action="store_true",
                   help="also run the continuous-time RK4 mode (under a second for section4 with the compiled "
                        "kernels, the [fast] extra; minutes on the numpy path)")
    r.set_defaults(func=cmd_reproduce)

    dm = sub.add_parser("demo", help="the main demo: Section 4 as separate processes over Zenoh (lockstep), figures")
    dm.add_argument("--out", default="runs/demo")
    dm.add_argument("--duration", type=_seconds, default=30.0, help="mission time to run [s] (the mission's is 1000)")
    dm.set_defaults(func=cmd_demo)

    rn = sub.add_parser("run", help="run a mission as separate processes over Zenoh (leader, agents, plants, recorder)")
    rn.add_argument("mission")
    rn.add_argument("--out", required=True, help="directory for run.npz and logs/")
    rn.add_argument("--clock", choices=["lockstep", "realtime"], default=None,
                    help="lockstep (default) or realtime (the default with --sitl)")
    rn.add_argument("--network", choices=["star", "mesh"], default=None,
                    help="star: clients around one router session; mesh: peers (default: a mesh in lockstep where "
                         "the plants are co-located by default and at most 16 agents fly, faster; else the star)")
    rn.add_argument("--window", type=int, default=None,
                    help="lockstep ticks in flight (default: 32 with the plants co-located, else 8; at most what every "
                         "process's input queue holds of a window of the recorder's 1 + 2N streams: 3640 for 4 "
                         "vehicles, 504 for 32)")
    rn.add_argument("--duration", type=_seconds, default=None, help="override the mission's duration [s]")
    rn.add_argument("--no-handover", action="store_true",
                    help="leave Zenoh's runtime threads as they are (default: hand them over, ZENOH_RUNTIME)")
    rn.add_argument("--ns", default=None)
    rn.add_argument("--stall-timeout", type=_positive_seconds, default=30.0)
    rn.add_argument("--listen", action="append", default=[],
                    help="another endpoint for the launcher's router, for tools that attach to the run "
                         "(tether netem-set, plain Zenoh clients); repeatable")
    rn.add_argument("--lease", type=_lease, default=2.0,
                    help="Zenoh link lease [s] of every process: a frozen or cut-off one is seen gone after it")
    rn.add_argument("--wrap", action="append", default=[], metavar="ID=PREFIX",
                    type=_vehicle_option(lambda v: tuple(shlex.split(v)), "3='ip netns exec uav3'"),
                    help="run vehicle ID's agent and plant under a command prefix that execs it, e.g. "
                         "3='ip netns exec uav3' (a network namespace); repeatable")
    rn.add_argument("--vehicle-connect", action="append", default=[], metavar="ID=ENDPOINT",
                    type=_vehicle_option(str, "3=tcp/127.0.0.1:7448"),
                    help="vehicle ID's agent and plant connect to ENDPOINT (e.g. its on-board Zenoh router, "
                         "linked to a --listen endpoint) instead of the launcher's router; repeatable")
    rn.add_argument("--fault", action="append", default=[], metavar="KIND:TARGET@T[+D]",
                    help="inject a fault at mission time T [s]: kill:agent/2@10 (SIGKILL), freeze:leader@5+3 "
                         "(SIGSTOP, SIGCONT D s later), partition:agent/3@8+2 (its link cut for D s), "
                         "forge:leader@12 (one far-off sample on its state key), skew:agent/2=+0.05 (its clock 50 ms "
                         "ahead, real time); repeatable (deploy/faults.py)")
    rn.add_argument("--sitl", action="store_true",
                    help="start the software Crazyflies the mission's udp:// crazyflie plants need (python -m "
                         "plant.cfsim, one per vehicle at its p0) and stop them at the end (deploy/sitl.py)")
    rn.add_argument("--sitl-args", default="", metavar="ARGS",
                    help="with --sitl: extra simulator options, e.g. '--noise 0.1 --seed 2' (docs/cfsim.md)")
    rn.add_argument("--insecure", action="store_true",
                    help="no certificates and no access rules (plain TCP): anyone who reaches the router can "
                         "publish on the run's keys. Default: mTLS, one identity per process, deny-by-default "
                         "rules; tools attach to --listen tls/... with --zenoh-config OUT/tls/control-0.json5")
    rn.add_argument("--rt-priority", type=_rt_priority, default=None, metavar="P",
                    help="run the control processes (the launcher's router, leader, agents, plants or world, and "
                         "--sitl's software Crazyflies) at real-time priority P (SCHED_RR, 1..99, e.g. 10), so that "
                         "other work on the machine does not delay their ticks; the recorder keeps the normal policy "
                         "and the operator gateway its idle one. Needs root, CAP_SYS_NICE or an rtprio limit "
                         "(docs/runtime.md)")
    rn.add_argument("--quiet", action="store_true", help="no progress display")
    rn.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                    help="serve the run over the Foxglove WebSocket protocol while it goes on, from the recorder "
                         "(default port 8765; docs/foxglove.md)")
    rn.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
    rn.add_argument("--colocate-plants", action="store_true",
                    help="lockstep, simulated plants: each agent computes its own plant (no plant processes; "
                         "the same run bit for bit, faster: docs/benchmarks.md). The default in lockstep when "
                         "every plant is simulated and no --fault, --wrap, --vehicle-connect, --listen, --sitl or "
                         "--shared-plants is given; with this flag, a run that cannot is refused (exit 2)")
    rn.add_argument("--separate-plants", action="store_true",
                    help="lockstep: one process per plant even where the plants could run inside their agents")
    rn.add_argument("--shared-plants", action="store_true",
                    help="simulated plants: one world process steps every vehicle, each with its own watchdog, "
                         "instead of one process per vehicle (fewer processes for many agents on one machine; "
                         "one point of failure for every vehicle; no crazyflie)")
    rn.add_argument("--record-batch", type=_positive_int, default=None, metavar="TICKS",
                    help="with --colocate-plants: ticks per message to the recorder, at most --window and 256 "
                         "(default: half the window, 256 at most)")
    rn.set_defaults(func=cmd_run)


def _process_commands(sub: argparse._SubParsersAction) -> None:
    """The processes of a run (:data:`PROCESSES`)."""
    for role, fn, helptext in (("leader", cmd_leader, "the virtual leader's process"),
                               ("agent", cmd_agent, "one agent's process"),
                               ("plant", cmd_plant, "one simulated plant's process"),
                               ("world", cmd_world, "a world's process: every simulated vehicle (and the payload, if any)"),
                               ("recorder", cmd_recorder, "the recorder's process")):
        rp = sub.add_parser(role, help=helptext)
        _process_options(rp)
        if role in ("agent", "plant"):
            rp.add_argument("--id", type=int, required=True)
        if role in ("agent", "recorder"):
            rp.add_argument("--colocate-plant", action="store_true",
                            help="lockstep: the agent computes its simulated plant itself (no plant process) and "
                                 "sends the recorder batched records; the recorder listens for them")
        if role == "agent":
            rp.add_argument("--record-batch", type=_record_ticks, default=1, metavar="TICKS",
                            help="with --colocate-plant: ticks per record sent to the recorder")
        if role == "leader":
            rp.add_argument("--record-batch", type=_record_ticks, default=0, metavar="TICKS",
                            help="lockstep, for a recorder given --colocate-plant: also send it this process's "
                                 "states in records of TICKS ticks (default: none)")
        if role == "recorder":
            rp.add_argument("--out", required=True)
            rp.add_argument("--live", type=int, default=None, metavar="PORT",
                            help="serve the run over the Foxglove WebSocket protocol on this port while it goes on")
            rp.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
        rp.set_defaults(func=fn)


def _study_and_tool_commands(sub: argparse._SubParsersAction) -> None:
    """Studies, operator tools, deployment, recording, files."""
    sw = sub.add_parser("sweep", help="degradation study: a mission over a grid of link loss and delay, both laws")
    sw.add_argument("mission")
    sw.add_argument("--out", required=True, help="directory for sweep.csv, sweep.md, heatmaps and each point's mission")
    sw.add_argument("--loss", default="0,10,30,50", help="loss ratios [%%], comma-separated (default 0,10,30,50)")
    sw.add_argument("--delay", default="0,20,50,100,200", help="one-way delays [ms] (default 0,20,50,100,200)")
    sw.add_argument("--burst", default="1", help="mean loss-burst lengths [messages]; 1: independent losses")
    sw.add_argument("--jitter", type=float, default=0.0, help="uniform delay jitter, half-width [ms]")
    sw.add_argument("--laws", default="sigma,benchmark", help="laws to run (default both)")
    sw.add_argument("--duration", type=_seconds, default=None, help="override the mission's duration [s]")
    sw.add_argument("--engine", choices=["inprocess", "runtime"], default="inprocess",
                    help="inprocess: the lockstep runtime's arithmetic in one process (equal bit for bit, "
                         "several times faster: bench/sweep_engine.py); runtime: real processes over Zenoh (tether run) for every point")
    sw.add_argument("--jobs", type=int, default=1, help="grid points run at once (processes)")
    sw.add_argument("--compensate", action=argparse.BooleanOptionalAction, default=None,
                    help="latency compensation on every agent (default: as the mission's [links] says)")
    sw.set_defaults(func=cmd_sweep)
    from cli import study as study_cli

    study_cli.extend(sub, sw)  # --executor, --seeds, --sigma/--gamma-p/--gamma-v, and `tether montecarlo`

    nc = sub.add_parser("netem-set", help="change the emulated links of a running swarm (its mission needs [netem])")
    nc.add_argument("profile", help='a preset (wifi, wifi-lossy, ...) or an inline TOML table, e.g. "{ loss = { p = 0.3 } }"')
    nc.add_argument("--ns", required=True, help="the run's namespace: its mission's name unless the run was given --ns")
    nc.add_argument("--from", dest="src", type=int, default=None, help="only links from this node (default: all)")
    nc.add_argument("--to", dest="dst", type=int, default=None, help="only links into this agent (default: all)")
    nc.add_argument("--at", type=float, default=None, help="mission time [s] it takes effect (default: on receipt)")
    nc.add_argument("--timeout", type=float, default=5.0, help="how long to wait for the agents' answers [s]")
    _zenoh_options(nc)
    nc.set_defaults(func=cmd_netem_set, zenoh_mode="client")

    for action, helptext in (("land", "land every vehicle of a running swarm (operator order on the control key)"),
                             ("estop", "stop every motor of a running swarm at once (operator order)")):
        op = sub.add_parser(action, help=helptext)
        op.add_argument("--ns", required=True, help="the run's namespace: its mission's name unless the run was given --ns")
        op.add_argument("--reason", default="", help="why, recorded with the vehicles' mode change")
        op.add_argument("--timeout", type=float, default=5.0,
                        help="how long to wait for a router and a subscriber of the control key [s]")
        _zenoh_options(op)
        op.set_defaults(func=cmd_safety, action=action, zenoh_mode="client", connect_timeout=5.0)

    from deploy import gen as deploy_gen

    dg = sub.add_parser("deploy-gen", help="companion computers: every host's Zenoh profiles, mTLS certificates, "
                                           "access control and service units, from a mission")
    deploy_gen.add_arguments(dg)
    dg.set_defaults(func=deploy_gen.run_args)

    from deploy import rehearse

    rh = sub.add_parser("rehearse", help="fly a generated deployment on this machine, each host in a network "
                                         "namespace of its own (root)")
    rehearse.add_arguments(rh)
    rh.set_defaults(func=rehearse.run_args)

    mc = sub.add_parser("mcap", help="write a run's Foxglove file (run.mcap) from its run file")
    mc.add_argument("run", help="a run.npz or the directory holding it")
    mc.add_argument("--out", default=None, help="the MCAP file (default: run.mcap beside run.npz)")
    mc.add_argument("--scene-rate", type=_scene_rate, default=None, metavar="HZ",
                    help="rate of the 3D scene (default 25; 0: every tick)")
    mc.set_defaults(func=cmd_mcap)

    from cli import record, top

    record.add_parser(sub)
    top.add_parser(sub)

    pl = sub.add_parser("plot", help="draw a run's figures from its run file (safety mode changes marked)")
    pl.add_argument("run", help="a run.npz or the directory holding it")
    pl.add_argument("--out", default=None)
    pl.set_defaults(func=cmd_plot)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    from tether.schema import SchemaError

    try:
        evloop.choose()  # TETHER_LOOP: a wrong value is an error before anything starts
        return int(args.func(args))
    except (SchemaError, BadArgument, evloop.LoopError) as exc:  # a mission, settings, profile or hosts
        # file; an argument; the environment's TETHER_LOOP
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a write (or read) failed part-way: a full disk, a vanished directory
        code = errno.errorcode.get(exc.errno or 0, f"errno {exc.errno}")
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"error: {where}{exc.strerror or exc} ({code}); free space or fix the path, then run again",
              file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
