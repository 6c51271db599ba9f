"""``tether run`` and the commands for a swarm that is flying: ``netem-set``, ``land``, ``estop``;
and a deployment's ``deploy-gen`` and ``rehearse`` (their options are ``deploy/``'s)."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import Literal

from cli import args as cli_args
from cli.args import BadArgument
from tether import evloop

NS_HELP = "the run's namespace: its mission's name unless the run was given --ns"


def add_run_parser(sub: argparse._SubParsersAction) -> None:
    rn = sub.add_parser("run", help="run a mission as separate processes over Zenoh (leader, agents, plants, recorder)")
    rn.add_argument("mission", help=cli_args.MISSION_HELP)
    rn.add_argument("--out", required=True, help="directory for run.npz, run.mcap and logs/")
    rn.add_argument("--clock", choices=["lockstep", "realtime"], default=None,
                    help="lockstep (default): every process waits for the tick's inputs, so the run is reproducible "
                         "and as fast as the machine allows; realtime: ticks on the clock, as in flight (the default "
                         "with --sitl)")
    rn.add_argument("--network", choices=["star", "mesh"], default=None,
                    help="star: clients around one router session; mesh: peers (default: a mesh in lockstep where "
                         "the plants are co-located by default and at most 16 agents fly, faster; else the star)")
    rn.add_argument("--window", type=int, default=None, metavar="TICKS",
                    help="lockstep: how many ticks the processes may run ahead of the slowest input (default: 32 "
                         "with the plants co-located, else 8); more is faster until the input queues fill: at most "
                         "3640 for 4 vehicles, 504 for 32")
    rn.add_argument("--duration", type=cli_args.seconds, default=None, help="override the mission's duration [s]")
    rn.add_argument("--no-handover", action="store_true",
                    help="let each process keep Zenoh's own pool of threads (default: one thread per process does "
                         "Zenoh's work, which costs less CPU when many processes share few cores)")
    rn.add_argument("--ns", default=None, metavar="NAME",
                    help="the namespace of the run's Zenoh keys (default: the mission's name); give two runs on "
                         "one network different names")
    rn.add_argument("--stall-timeout", type=cli_args.positive_seconds, default=30.0, metavar="S",
                    help="lockstep: end the run (exit 4) when a process has waited this long for an input, naming "
                         "the input it lacks (default 30 s)")
    rn.add_argument("--listen", action="append", default=[],
                    help="another endpoint for the launcher's router, for tools that attach to the run "
                         "(tether netem-set, plain Zenoh clients); repeatable")
    rn.add_argument("--lease", type=cli_args.lease, default=2.0,
                    help="Zenoh link lease [s] of every process: a frozen or cut-off one is seen gone after it")
    rn.add_argument("--wrap", action="append", default=[], metavar="ID=PREFIX",
                    type=cli_args.vehicle_option(lambda v: tuple(shlex.split(v)), "3='ip netns exec uav3'"),
                    help="run vehicle ID's agent and plant under a command prefix that execs it, e.g. "
                         "3='ip netns exec uav3' (a network namespace); repeatable")
    rn.add_argument("--vehicle-connect", action="append", default=[], metavar="ID=ENDPOINT",
                    type=cli_args.vehicle_option(str, "3=tcp/127.0.0.1:7448"),
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
    rn.add_argument("--rt-priority", type=cli_args.rt_priority, default=None, metavar="P",
                    help="run the control processes (the launcher's router, leader, agents, plants or world, and "
                         "--sitl's software Crazyflies) at real-time priority P (SCHED_RR, 1..99, e.g. 10), so that "
                         "other work on the machine does not delay their ticks; the recorder keeps the normal policy "
                         "and the operator gateway its idle one. Needs root, CAP_SYS_NICE or an rtprio limit "
                         "(docs/runtime.md)")
    rn.add_argument("--replace", action="store_true",
                    help="write over the finished run --out holds (its run file, results and report are removed "
                         "first); a run going on there is never replaced")
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
    rn.add_argument("--record-batch", type=cli_args.positive_int, default=None, metavar="TICKS",
                    help="with the plants co-located: how many ticks each agent sends the recorder in one message "
                         "(fewer, larger messages); at most --window and 256 (default: half the window, 256 at most)")
    rn.set_defaults(func=cmd_run)


def add_operator_parsers(sub: argparse._SubParsersAction) -> None:
    """netem-set, land, estop: orders to a running swarm."""
    nc = sub.add_parser("netem-set", help="change the emulated links of a running swarm (its mission needs [netem])")
    nc.add_argument("profile", help='a preset (wifi, wifi-lossy, ...) or an inline TOML table, e.g. "{ loss = { p = 0.3 } }"')
    nc.add_argument("--ns", required=True, help=NS_HELP)
    nc.add_argument("--from", dest="src", type=int, default=None, help="only links from this node (default: all)")
    nc.add_argument("--to", dest="dst", type=int, default=None, help="only links into this agent (default: all)")
    nc.add_argument("--at", type=float, default=None, help="mission time [s] it takes effect (default: on receipt)")
    nc.add_argument("--timeout", type=float, default=5.0, help="how long to wait for the agents' answers [s]")
    cli_args.zenoh_options(nc)
    nc.set_defaults(func=cmd_netem_set, zenoh_mode="client")

    for action, helptext in (("land", "land every vehicle of a running swarm (operator order on the control key)"),
                             ("estop", "stop every motor of a running swarm at once (operator order)")):
        op = sub.add_parser(action, help=helptext)
        op.add_argument("--ns", required=True, help=NS_HELP)
        op.add_argument("--reason", default="", help="why, recorded with the vehicles' mode change")
        op.add_argument("--timeout", type=float, default=5.0,
                        help="how long to wait for a router and a subscriber of the control key [s]")
        cli_args.zenoh_options(op)
        op.set_defaults(func=cmd_safety, action=action, zenoh_mode="client", connect_timeout=5.0)


def add_deploy_parsers(sub: argparse._SubParsersAction) -> None:
    """deploy-gen, rehearse: their options and commands are ``deploy/``'s."""
    from deploy import gen as deploy_gen

    dg = sub.add_parser("deploy-gen", help="companion computers: every host's Zenoh profiles, mTLS certificates, "
                                           "access control and service units, from a mission")
    deploy_gen.add_arguments(dg)
    dg.set_defaults(func=deploy_gen.run_args)

    from deploy import rehearse

    rh = sub.add_parser("rehearse", help="fly a generated deployment on this machine, each host in a network "
                                         "namespace of its own (root)")
    rehearse.add_arguments(rh)
    rh.set_defaults(func=cmd_rehearse)


def cmd_rehearse(args: argparse.Namespace) -> int:
    """``tether rehearse`` (``deploy/rehearse.py``), then the report of the run it recorded."""
    from deploy import rehearse

    status = rehearse.run_args(args)
    out = Path(args.out)
    if status != 2 and (out / "run.npz").is_file():  # 2: refused before anything ran (maybe unreadable)
        page = _write_results(out, status, f"tether rehearse ended with exit status {status} (docs/exit-status.md)")
        if page is not None:
            print(f"the report (one page, for the log book): {page}")
    return status


def cmd_run(args: argparse.Namespace) -> int:
    import logging

    from deploy import faults, local, options

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s launcher: %(message)s")
    path = cli_args.mission_path(args.mission)
    cli_args.load(args.mission, args.duration)  # every mission and --duration problem, before anything starts
    cli_args.writable_dir("--out", args.out, ("run.npz",))
    cli_args.check_live(args.live)
    if (Path(args.out) / "logs").exists() and not (Path(args.out) / "logs").is_dir():
        raise BadArgument(f"--out: {Path(args.out) / 'logs'} is a file where the run writes its logs; remove it "
                          "or give another --out")
    cli_args.check_ns(args.ns)
    _claim_out(Path(args.out), args.replace)
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
    status = evloop.run(local.run(path, opts))
    out = Path(args.out)
    if (out / "run.npz").exists():  # what was recorded, whatever the ending: its metrics, figures and report
        page = _write_results(out, status)
        from cli.sim import foxglove_step, next_steps

        steps = [f"the report (one page, for the log book): {page}"] if page else []
        steps += [f"the figures in {out} (SVG beside each PNG), the metrics in {out / 'metrics.json'}"]
        steps += [foxglove_step(out / "run.mcap")] if (out / "run.mcap").exists() else []
        steps += [f"the processes' logs: {out / 'logs'}"]
        next_steps(steps)
    return status


def _write_results(out: Path, status: int, said: str | None = None) -> Path | None:
    """``metrics.json``, the figures and ``report.html`` of the run recorded in ``out``, as
    ``tether simulate`` writes them; the page, or None (said on stderr) if the run file cannot be
    read back. The exit status stands either way. ``said``: the status in words where it is not
    ``tether run``'s (a rehearsal's)."""
    from cli import report
    from deploy import outcome
    from sim import figures, metrics
    from tether import jsonout, safefs
    from tether.runfile import Run

    try:
        run = Run.load(out / "run.npz")
    except (OSError, ValueError, KeyError) as exc:
        print(f"warning: {out / 'run.npz'} could not be read back ({exc}): no figures, metrics or report",
              file=sys.stderr)
        return None
    if not metrics.recorded(run).any():
        print(f"warning: {out / 'run.npz'} holds no complete tick: no figures, metrics or report", file=sys.stderr)
        return None
    print(f"drawing the figures and the report in {out}", file=sys.stderr, flush=True)
    try:
        values = jsonout.finite(metrics.report(run))
        safefs.write_file(out / "metrics.json", jsonout.dumps(values).encode())
        drawn = figures.run_panels(run, out)
        if said is not None:
            return report.write_run(out, run, drawn=drawn, notes=(said,))
        return report.write_run(out, run, drawn=drawn, status=(status, outcome.MEANING.get(status, "unknown")))
    except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not hide the run's exit status
        print(f"warning: the figures, metrics or report of {out} could not be made ({type(exc).__name__}: {exc}); "
              f"the run is in {out / 'run.npz'}, and `tether report {out}` tries again", file=sys.stderr)
        return None


RESULTS = ("run.npz", "run.npz.part", "journal.mcap", "run.mcap", "metrics.json", "report.html", "events.json",
           "faults.json", "outcome.json", *(f"{name}.{ext}" for name in ("errors_gains", "velocities", "xy",
                                                                        "formation") for ext in ("png", "svg")))
"""What a run leaves in its ``--out`` besides its logs and certificates (which a new run rewrites)."""


def _claim_out(out: Path, replace: bool) -> None:
    """Refuse an ``--out`` that holds a run going on now, or a finished one unless ``replace`` (then
    remove its results, so that nothing of it is taken for the new run's): exit 2 naming ``--out``
    and the flag, before anything starts."""
    from deploy import local

    if not out.is_dir():
        return
    try:
        os.close(local.claim_out(out))
    except BlockingIOError:
        raise BadArgument(f"--out: {out} {local.LIVE}; give another --out, or wait for that run to end") from None
    except OSError:
        return  # not ours to judge here: writable_dir has named what is wrong with it
    held = [name for name in RESULTS if (out / name).exists()]
    if not held:
        return
    if not replace:
        raise BadArgument(f"--out: {out} holds a finished run ({', '.join(held[:4])}{', …' if len(held) > 4 else ''}); "
                          "give another --out, or --replace to write over it")
    for name in held:
        (out / name).unlink()
    print(f"--replace: removed the previous run's {', '.join(held)} from {out}", file=sys.stderr)


def cmd_netem_set(args: argparse.Namespace) -> int:
    from netem import control
    from tether.netprofile import ProfileError
    from tether.transport import TransportError

    try:
        profile = control.parse_profile(args.profile)
    except ProfileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    settings = cli_args.zenoh_settings(args)
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

    cli_args.check_ns(args.ns)
    if not args.timeout > 0:
        raise BadArgument(f"--timeout is {args.timeout}; give seconds > 0")
    if args.zenoh_config is None and not args.connect:
        raise BadArgument("--connect is missing: give the run's router endpoint (e.g. --connect tcp/127.0.0.1:7447, "
                          "one that tether run --listen opened) or --zenoh-config FILE")
    settings = cli_args.zenoh_settings(args)
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
