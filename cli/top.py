"""``tether top``: the live terminal monitor of a running swarm (``recorder/top.py``)."""

from __future__ import annotations

import argparse
import math


def _positive(text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a finite number > 0, e.g. 0.5")
    return x


def add_parser(sub: argparse._SubParsersAction) -> None:
    from cli import main

    t = sub.add_parser("top", help="live terminal monitor of a running swarm: a row per vehicle (q quits)")
    t.add_argument("--ns", required=True, help="the swarm's namespace: its mission's name unless the run was given --ns")
    t.add_argument("--xi-warn", type=_positive, default=0.5, metavar="M",
                   help="show |xi_i| red beyond this [m] (default 0.5)")
    t.add_argument("--age-warn", type=_positive, default=0.1, metavar="S",
                   help="show a link's age p99 amber beyond this [s] (default 0.1)")
    main._zenoh_options(t)
    t.set_defaults(func=cmd_top, zenoh_mode="client", connect_timeout=5.0)


def cmd_top(args: argparse.Namespace) -> int:
    from cli import main
    from recorder import top
    from tether import evloop, wire
    from tether import transport as tp

    try:
        wire.Keys(args.ns)
    except ValueError as exc:
        raise main.BadArgument(f"--ns: {exc}") from None
    if args.zenoh_config is None and not args.connect:
        raise main.BadArgument("--connect is missing: give the swarm's router endpoint (e.g. --connect "
                               "tcp/127.0.0.1:7447, one that tether run --listen opened) or --zenoh-config FILE "
                               "(under mTLS the operator identity, e.g. DIR/tls/control-0.json5)")
    settings = main._zenoh_settings(args)
    where = ", ".join(args.connect) if args.zenoh_config is None else args.zenoh_config
    try:
        return evloop.run(top.run(settings, args.ns, where, xi_warn=args.xi_warn, age_warn=args.age_warn))
    except tp.TransportError as exc:
        print(f"error: {exc}; is the swarm's router up at {where}?", file=__import__("sys").stderr)
        return 1
