"""``tether record``: the recorder of a deployed swarm, attached from outside it as a plain Zenoh client.

It is the recorder role of ``tether run`` (``recorder/node.py``, ``make(attach=True)``) with no
liveliness token and no lockstep acknowledgements: it waits for the swarm's router (which may come
up after it), then for the start, records every sample a run file holds (leader state, agent
telemetry, plant and world states) until the run's last tick or until it is stopped (SIGINT,
SIGTERM), and writes ``run.npz`` and ``run.mcap``; ``--live`` serves the run to Foxglove meanwhile.
A stop is a normal end: exit 0, the file marked incomplete when samples are missing.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from cli import args as cli_args
from tether import evloop

if TYPE_CHECKING:
    from tether.node import NodeArgs

log = logging.getLogger("tether")

RETRY = 0.5
"""How often to try the swarm's router again while it is not up [s]."""


def add_parser(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("record", help="record a running (deployed) swarm from outside it: run.npz and run.mcap "
                                      "until stopped")
    r.add_argument("--mission", required=True,
                   help="the swarm's mission file (or a shipped mission's name): the run file's agents, "
                        "rate and length")
    r.add_argument("--ns", default=None, help="the swarm's namespace (default: the mission's name)")
    r.add_argument("--out", required=True, help="directory for run.npz and run.mcap")
    r.add_argument("--duration", type=cli_args.seconds, default=None,
                   help="the swarm's --duration, when it was given one [s]")
    r.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                   help="serve the run over the Foxglove WebSocket protocol while it goes on (default port 8765)")
    r.add_argument("--live-host", default="127.0.0.1",
                   help="address the live view listens on (default 127.0.0.1; 0.0.0.0: every interface)")
    r.add_argument("--no-mcap", action="store_true", help="no run.mcap beside run.npz")
    r.add_argument("--log-level", default="INFO", help="DEBUG, INFO (default), WARNING or ERROR")
    cli_args.zenoh_options(r)
    r.set_defaults(func=cmd_record, zenoh_mode="client", connect_timeout=2.0)


def cmd_record(args: argparse.Namespace) -> int:
    from cli import live as live_mod
    from tether.node import NodeArgs

    path = cli_args.mission_path(args.mission)
    m = cli_args.load(args.mission, args.duration)
    ns = args.ns or m.name
    cli_args.check_ns(ns)
    cli_args.need_router(args)
    out = cli_args.writable_dir("--out", args.out, ("run.npz", "run.mcap"))
    problem = live_mod.port_problem(args.live, args.live_host)
    if problem is not None:
        raise cli_args.BadArgument(problem)
    settings = cli_args.zenoh_settings(args)
    node_args = NodeArgs(mission_path=path, role="recorder", node_id=0, clock="realtime", zenoh=settings, ns=ns,
                         duration=args.duration)
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s record: %(message)s")
    status = evloop.run(_record(node_args, out, args))
    return status


async def _record(node_args: NodeArgs, out: Path, args: argparse.Namespace) -> int:
    from recorder import node as recorder
    from tether import transport as tp
    from tether.node import EXIT_OK, EXIT_STOPPED, serve

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    try:
        # the swarm's router may come up after this process: try it until it answers, or a stop
        where = ", ".join(args.connect) if args.zenoh_config is None else args.zenoh_config
        told = False
        while True:
            try:
                async with tp.open_session(node_args.zenoh):
                    break
            except tp.TransportError as exc:
                if not told:
                    log.info("waiting for the swarm's router (%s): %s", where, str(exc).splitlines()[0])
                    told = True
            try:
                async with asyncio.timeout(RETRY):
                    await stop.wait()
            except TimeoutError:
                continue
            log.warning("stopped before the swarm's router answered: nothing recorded")
            return EXIT_OK
        log.info("connected to the swarm's router (%s); namespace %r", where, node_args.ns)
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)
    t0 = time.monotonic()
    role, on_stop = recorder.make(out, live=args.live, attach=True, mcap=not args.no_mcap,
                                  live_host=args.live_host)
    status = await serve(node_args, role, on_stop)
    if status not in (EXIT_OK, EXIT_STOPPED):
        return status
    return _report(out, time.monotonic() - t0, stopped=status == EXIT_STOPPED)


def _report(out: Path, seconds: float, stopped: bool) -> int:
    """Say what the files hold; 0 when they were written (complete or not), 1 when not."""
    import numpy as np

    from tether import runfile

    npz, mcap = out / "run.npz", out / "run.mcap"
    if not npz.exists():
        print("no run file written: no sample of the swarm was heard", file=sys.stderr)
        return 0 if stopped else 1
    with np.load(npz, allow_pickle=False) as run:
        meta = runfile.decode_meta(str(run["meta"]))
    got, want = meta.samples_recorded, meta.samples_expected
    how = "complete" if meta.complete else "INCOMPLETE"
    why = "stopped" if stopped else "the run ended"
    print(f"{why} after {seconds:.1f} s: wrote {npz}" + (f" and {mcap}" if mcap.exists() else "")
          + f", {how}: {got} of {want} samples", flush=True)
    return 0
