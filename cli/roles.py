"""The process commands: ``tether leader``, ``agent``, ``plant``, ``world`` and ``recorder``, one per
process of a run, as ``tether run`` and a deployment's service units start them.

Each parses its options and the mission, then hands its role to :func:`tether.node.serve`. This
module and :mod:`cli.args` are all a control process loads of the command line.
"""

from __future__ import annotations

import argparse
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING

from cli import args as cli_args
from cli.args import BadArgument
from tether import evloop
from tether import mission as ms

if TYPE_CHECKING:  # each command imports what it runs
    from tether.clock import LockstepClock, RealtimeClock
    from tether.node import Node, NodeArgs

PROCESSES = ("leader", "agent", "plant", "world", "recorder")
"""The process commands: what the launcher and the deployment's units start, one per process."""

HEADING = "processes (started by `tether run` and by deployments, one per process)"
"""The heading of the process commands in ``tether --help``."""


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """The processes of a run (:data:`PROCESSES`)."""
    for role, fn, helptext in (("leader", cmd_leader, "the virtual leader's process"),
                               ("agent", cmd_agent, "one agent's process"),
                               ("plant", cmd_plant, "one simulated plant's process"),
                               ("world", cmd_world, "a world's process: every simulated vehicle (and the payload, if any)"),
                               ("recorder", cmd_recorder, "the recorder's process")):
        rp = sub.add_parser(role, help=helptext, description=f"{helptext[0].upper()}{helptext[1:]}, as "
                            "`tether run` and a deployment's service units start it.")
        _process_options(rp)
        if role in ("agent", "plant"):
            rp.add_argument("--id", type=int, required=True, help="the vehicle's agent id in the mission")
        if role in ("agent", "recorder"):
            rp.add_argument("--colocate-plant", action="store_true",
                            help="lockstep: the agent computes its simulated plant itself (no plant process) and "
                                 "sends the recorder batched records; the recorder listens for them")
        if role == "agent":
            rp.add_argument("--record-batch", type=cli_args.record_ticks, default=1, metavar="TICKS",
                            help="with --colocate-plant: ticks per record sent to the recorder")
        if role == "leader":
            rp.add_argument("--record-batch", type=cli_args.record_ticks, default=0, metavar="TICKS",
                            help="lockstep, for a recorder given --colocate-plant: also send it this process's "
                                 "states in records of TICKS ticks (default: none)")
        if role == "recorder":
            rp.add_argument("--out", required=True, help="directory for run.npz and run.mcap")
            rp.add_argument("--live", type=int, default=None, metavar="PORT",
                            help="serve the run over the Foxglove WebSocket protocol on this port while it goes on")
            rp.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
        rp.set_defaults(func=fn)


def _process_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mission", required=True, help=cli_args.MISSION_HELP)
    p.add_argument("--clock", choices=["lockstep", "realtime"], default="realtime",
                   help="realtime (default): tick on the host's clock; lockstep: tick when every input of the "
                        "tick has come (simulated plants only)")
    p.add_argument("--ns", default=None, help="key namespace (default: the mission name)")
    p.add_argument("--stall-timeout", type=cli_args.positive_seconds, default=30.0,
                   help="lockstep: fail after waiting this long [s]")
    p.add_argument("--window", type=cli_args.int_at_least(0), default=0, metavar="TICKS",
                   help="lockstep: the clock's window (tether run's --window); the process keeps each stream's messages "
                        "of its last TICKS + 1 ticks, to send again when a tick has waited for its inputs for a while "
                        "(0: keeps none)")
    p.add_argument("--parent-pid", type=int, default=None, help="stop when this process is gone")
    p.add_argument("--start-timeout", type=cli_args.positive_seconds, default=None,
                   help="fail (exit 1) when the start message has not come this long after the process is "
                        "ready [s]; default: wait for ever (a service waiting for its operator's start)")
    p.add_argument("--duration", type=cli_args.seconds, default=None, help="override the mission's duration [s]")
    p.add_argument("--clock-skew", type=cli_args.skew, default=0.0, metavar="S",
                   help="real time: this process's clock reads S seconds ahead (negative: behind) of the host's, "
                        "to rehearse unsynchronised hosts (tether run --fault skew:ROLE/ID=S)")
    p.add_argument("--log-level", default="INFO", help="DEBUG, INFO (default), WARNING or ERROR")
    p.add_argument("--rt-priority", type=cli_args.rt_priority, default=None, metavar="P",
                   help="run this process at real-time priority P (SCHED_RR, 1..99; 0: the normal policy), set "
                        "before its threads start; needs root, CAP_SYS_NICE or an rtprio limit (docs/runtime.md)")
    cli_args.zenoh_options(p)


def _node_args(args: argparse.Namespace, role: str, node_id: int) -> NodeArgs:
    from tether.node import NodeArgs

    settings = cli_args.zenoh_settings(args)
    return NodeArgs(mission_path=cli_args.mission_path(args.mission), role=role, node_id=node_id, clock=args.clock,
                    zenoh=settings, ns=args.ns, stall_timeout=args.stall_timeout, parent_pid=args.parent_pid,
                    duration=args.duration, start_timeout=args.start_timeout,
                    colocate=getattr(args, "colocate_plant", False), record_batch=getattr(args, "record_batch", 1),
                    mesh_peers=getattr(args, "mesh_peers", 0), window=getattr(args, "window", 0))


def _serve(args: argparse.Namespace, role: str, node_id: int, m: ms.Mission | None,
           body: Callable[[Node], Awaitable[None]], on_stop: Callable[[Node], None] | None = None) -> int:
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
    return evloop.run(serve(_node_args(args, role, node_id), body, on_stop, clock=_skewed_clock(args, m)))


def _skewed_clock(args: argparse.Namespace, m: ms.Mission | None) -> LockstepClock | RealtimeClock | None:
    """The process's clock when ``--clock-skew`` offsets it (an emulated unsynchronised host), else
    None. ``m``: the mission, when the command has loaded it already."""
    if not args.clock_skew:
        return None
    from tether.clock import make

    if args.clock != "realtime":
        raise BadArgument("--clock-skew: lockstep ticks follow the clock source, not a clock; use --clock realtime")
    if m is None:
        m = cli_args.load(args.mission, args.duration)
    return make("realtime", m.dt, args.clock_skew)


def cmd_leader(args: argparse.Namespace) -> int:
    from leader import node

    m = cli_args.load(args.mission, args.duration)
    if args.record_batch and args.clock != "lockstep":
        raise BadArgument("--record-batch: records are for lockstep runs (in real time the recorder hears every "
                          "state); drop it, or give --clock lockstep")
    return _serve(args, "leader", m.leader.id, m, node.run)


def cmd_agent(args: argparse.Namespace) -> int:
    from agent import node

    return _serve(args, "agent", args.id, _check_id(args), node.run)


def cmd_plant(args: argparse.Namespace) -> int:
    from plant import node

    return _serve(args, "plant", args.id, _check_id(args), node.run)


def cmd_world(args: argparse.Namespace) -> int:
    from plant import node

    m = cli_args.load(args.mission, args.duration)
    real = [a.id for a in m.agents if isinstance(a.plant, ms.CrazyfliePlant)]
    if real:
        raise ms.MissionError(str(args.mission), [(f"agent {real[0]}.plant", "is a crazyflie, a real vehicle: a "
                                                   "world hosts simulated vehicles only; run `tether plant --id I` "
                                                   "for each crazyflie")])
    return _serve(args, "world", 0, m, node.run_world)


def cmd_recorder(args: argparse.Namespace) -> int:
    from recorder import node as recorder

    run, on_stop = recorder.make(Path(args.out), live=args.live, mcap=not args.no_mcap)
    return _serve(args, "recorder", 0, None, run, on_stop)


def _check_id(args: argparse.Namespace) -> ms.Mission:
    """The mission, once ``--id`` is known to be one of its agents."""
    m = cli_args.load(args.mission, args.duration)
    if args.id not in m.agent_ids:
        raise ms.MissionError(str(args.mission), [("--id", f"{args.id} is not an agent of this mission; use one of {m.agent_ids}")])
    return m
