"""``tether top``: the live terminal monitor of a running swarm (``recorder/top.py``)."""

from __future__ import annotations

import argparse
import math
import sys

from cli import args as cli_args


def _positive(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a finite number > 0, e.g. 0.5")
    return x


def add_parser(sub: argparse._SubParsersAction) -> None:
    t = sub.add_parser("top", help="live terminal monitor of a running swarm: a row per vehicle (q quits)")
    t.add_argument("--ns", required=True, help="the swarm's namespace: its mission's name unless the run was given --ns")
    t.add_argument("--xi-warn", type=_positive, default=0.5, metavar="M",
                   help="show |xi_i| red beyond this [m] (default 0.5)")
    t.add_argument("--age-warn", type=_positive, default=0.1, metavar="S",
                   help="show a link's age p99 amber beyond this [s] (default 0.1)")
    t.add_argument("--wait", type=_positive, default=300.0, metavar="S",
                   help="started before the swarm: try its router every 0.5 s for up to S s, saying so "
                        "(default 300; exit 1 after)")
    cli_args.zenoh_options(t)
    # each try waits this long for the router; --wait is how long it tries
    t.set_defaults(func=cmd_top, zenoh_mode="client", connect_timeout=1.0)


def cmd_top(args: argparse.Namespace) -> int:
    from recorder import top
    from tether import evloop
    from tether import transport as tp

    cli_args.check_ns(args.ns)
    cli_args.need_router(args)
    settings = cli_args.zenoh_settings(args)
    where = ", ".join(args.connect) if args.zenoh_config is None else args.zenoh_config
    try:
        return evloop.run(top.run(settings, args.ns, where, xi_warn=args.xi_warn, age_warn=args.age_warn,
                                  wait=args.wait))
    except top.NoSwarm as exc:
        print(f"error: {exc}; start the swarm (or its router) first, or give --wait a longer time", file=sys.stderr)
        return 1
    except tp.TransportError as exc:
        print(f"error: {exc}; is the swarm's router up at {where}?", file=sys.stderr)
        return 1
