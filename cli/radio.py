"""A radio host: ``python -m cli.radio [--log-fds FD,...] -- PLANT_ARGS [-- PLANT_ARGS ...]``, every
Crazyflie of one dongle flown from one process.

cflib shares a Crazyradio only among the links of one process (a second process gets "device
busy"), so the vehicles of one dongle (:func:`plant.radio.dongles`) cannot each have a plant process
of their own. This process hosts them all: each ``PLANT_ARGS`` is the command line of one ``tether
plant`` (what ``tether run`` would have started for that vehicle: ``--mission M --id I`` and its
Zenoh settings and identity), and each vehicle runs exactly as that process would, with its own
Zenoh session, keys, liveliness token, command watchdog and link recovery
(:func:`plant.node.run`); only the process, its event loop and the dongle are shared. SIGTERM or
SIGINT stops every vehicle (each lands); the exit status is the worst of theirs (0 finished, 1
failed, 2 bad input, 143 stopped).

Each vehicle's log records go to stderr, or with ``--log-fds`` (one inherited file descriptor per
vehicle after the first, in order) the second vehicle's to the first descriptor and so on: the
launcher keeps a log per vehicle. What no vehicle's task wrote (cflib's own threads, the host) goes
to stderr.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import signal
import os
import sys
from typing import TYPE_CHECKING

from cli import roles
from cli.args import BadArgument
from cli.main import build_parser
from tether import evloop
from tether import mission as ms

if TYPE_CHECKING:
    from tether.node import NodeArgs

VEHICLE: contextvars.ContextVar[str] = contextvars.ContextVar("vehicle", default="radio")
"""The vehicle a log record is about (``plant/I``), from the task (and its threads) that wrote it."""


class _Only(logging.Filter):
    """Passes the records of ``names`` (the vehicle of the record's task), naming it on the record."""

    def __init__(self, names: set[str]) -> None:
        super().__init__()
        self.names = names

    def filter(self, record: logging.LogRecord) -> bool:
        name = VEHICLE.get()
        setattr(record, "vehicle", name)  # the formatter's %(vehicle)s
        return name in self.names


def split(argv: list[str]) -> list[list[str]]:
    """``-- A... -- B...`` -> ``[[A...], [B...]]``; ``BadArgument`` if there is none or one is empty."""
    if not argv or argv[0] != "--":
        raise BadArgument("give each vehicle's plant options after --: python -m cli.radio -- --mission M --id 1 "
                          "... -- --mission M --id 2 ...")
    groups: list[list[str]] = []
    for a in argv:
        if a == "--":
            groups.append([])
        else:
            groups[-1].append(a)
    if not all(groups):
        raise BadArgument("an empty vehicle between two --: give each vehicle's plant options")
    return groups


async def serve_all(vehicles: list[tuple[str, NodeArgs]]) -> int:
    """Serve every ``(name, NodeArgs)`` as :func:`tether.node.serve` serves one plant, in one event
    loop, with one signal handler that stops them all; returns the worst exit status."""
    from plant import node as plant_node
    from tether import transport as tp
    from tether.clock import make as make_clock
    from tether.node import EXIT_BAD_INPUT, Node, _run_tasks, load_mission, report_drops

    loop = asyncio.get_running_loop()
    nodes: list[Node] = []
    stop = asyncio.Event()

    def stop_all() -> None:
        stop.set()
        for n in nodes:
            n.stop.set()

    async def one(name: str, args: NodeArgs) -> int:
        VEHICLE.set(name)
        try:
            mission = load_mission(args.mission_path, args.duration)
        except ms.MissionError as exc:  # named; nothing started for this vehicle
            logging.getLogger("tether").error("%s", exc)
            return EXIT_BAD_INPUT
        async with tp.open_session(args.zenoh) as session:
            node = Node(args, mission, session, make_clock(args.clock, mission.dt))
            nodes.append(node)
            if stop.is_set():
                node.stop.set()
            try:
                status = await _run_tasks(node, plant_node.run)
                report_drops(node.receiver.drops)
            finally:
                node.close()
        return status

    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop_all)
    try:
        codes = await asyncio.gather(*(one(name, a) for name, a in vehicles))
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
    return max(codes, key=lambda c: (c != 0, c != 143, c))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    fds: list[int] = []
    try:
        if argv[:1] == ["--log-fds"]:
            fds = [int(f) for f in argv[1].split(",")] if len(argv) > 1 else []
            argv = argv[2:]
        groups = split(argv)
        if fds and len(fds) != len(groups) - 1:
            raise BadArgument(f"--log-fds: give {len(groups) - 1} descriptors, one per vehicle after the first")
    except (BadArgument, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    parser = build_parser("plant")
    parsed = [parser.parse_args(["plant", *g]) for g in groups]
    first = parsed[0]
    names = [f"plant/{a.id}" for a in parsed]
    if len(set(names)) != len(names):
        print(f"error: a vehicle is given twice: {names}", file=sys.stderr)
        return 2
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(vehicle)s: %(message)s")
    handlers: list[logging.Handler] = []
    own = set(names[1:]) if not fds else set()
    for name, fd in zip(names[1:], fds):
        handlers.append(logging.StreamHandler(os.fdopen(fd, "a", buffering=1)))
        handlers[-1].addFilter(_Only({name}))
    handlers.append(logging.StreamHandler())
    handlers[-1].addFilter(_Only({"radio", names[0], *own}))
    for h in handlers:
        h.setFormatter(fmt)
    logging.basicConfig(level=getattr(logging, first.log_level.upper(), logging.INFO), handlers=handlers)
    log = logging.getLogger("tether")
    if first.rt_priority is not None:  # first: the threads started from now on (Zenoh's, cflib's) inherit it
        from tether import sched

        try:
            log.info("CPU scheduling: %s", sched.apply(first.rt_priority))
        except sched.SchedError as exc:
            log.error("--rt-priority: %s", exc)
            return 2
    log.info("radio host: %s", ", ".join(names))
    try:
        return evloop.run(serve_all([(name, roles._node_args(a, "plant", a.id)) for name, a in zip(names, parsed)]))
    except BadArgument as exc:
        log.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
