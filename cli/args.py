"""What the ``tether`` commands share on their command lines: the mission argument, argument types,
the checks of an output directory and a live-view port, the Zenoh options.

Every check here runs before anything starts and says what is wrong and how to fix it
(:class:`BadArgument`, exit 2). Nothing heavy is imported at module level: every process of a run
is started through these functions.
"""

from __future__ import annotations

import argparse
import errno
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from tether import catalog
from tether import mission as ms

if TYPE_CHECKING:
    from tether.transport import ZenohSettings

T = TypeVar("T")

MISSION_HELP = "a mission file, or the name of a shipped mission (`tether missions` lists them)"
"""The help text of every command's mission argument."""


class BadArgument(Exception):
    """A command-line argument is unusable: ``"<argument>: <what is wrong>; <how to fix it>"`` (exit 2)."""


def mission_path(arg: str) -> Path:
    """The mission file ``arg`` names: a path, or a shipped mission's name. A word that is neither
    (no such file, no ``/``, no ``.toml``) raises :class:`BadArgument` listing the shipped missions."""
    path = catalog.resolve(arg)
    if path.exists() or arg.endswith(".toml") or "/" in arg:
        return path  # a path: the mission loader says what is wrong with it
    names = catalog.builtin_names()
    from tether.schema import close_matches

    near = close_matches(arg, names, n=1)
    hint = f"did you mean {near[0]}? Else " if near else ""
    raise BadArgument(f"mission: {arg!r} is neither a mission file nor a shipped mission; {hint}give a file's path "
                      f"or one of {', '.join(names)} (`tether missions` describes them)")


def load(arg: str, duration: float | None = None) -> ms.Mission:
    """The mission ``arg`` names, with ``--duration`` applied and checked (:func:`tether.mission.with_duration`)."""
    path = mission_path(arg)
    return ms.with_duration(ms.load(path), duration, str(path))


def check_ns(ns: str | None) -> None:
    """``--ns``: a key namespace Zenoh can use (one key chunk), or None (the mission's name)."""
    if ns is None:
        return
    from tether import wire

    try:
        wire.Keys(ns)
    except ValueError as exc:
        raise BadArgument(f"--ns: {exc}") from None


def need_router(args: argparse.Namespace) -> None:
    """A tool that attaches to a running swarm needs ``--connect`` or ``--zenoh-config``."""
    if args.zenoh_config is None and not args.connect:
        raise BadArgument("--connect is missing: give the swarm's router endpoint (e.g. --connect "
                          "tcp/127.0.0.1:7447, one that tether run --listen opened) or --zenoh-config FILE "
                          "(under mTLS the operator identity, e.g. DIR/tls/control-0.json5)")


# --------------------------------------------------------------------------- argparse types
def seconds(text: str) -> float:
    """An argparse type: a finite number of seconds > 0 (every ``--duration``)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds; give e.g. 30") from None
    if not math.isfinite(x) or x <= 0:
        raise argparse.ArgumentTypeError(f"{text} s is not a run length; give a finite number of seconds > 0, e.g. 30")
    return x


def int_at_least(lo: int, hi: int | None = None) -> Callable[[str], int]:
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


positive_int = int_at_least(1)


def record_ticks(text: str) -> int:
    """An argparse type: ticks per record, at most ``wire.RECORD_MAX`` (a record of more is dropped
    by its receiver as ``size``)."""
    from tether import wire

    return int_at_least(1, wire.RECORD_MAX)(text)


def rt_priority(text: str) -> int:
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


def skew(text: str) -> float:
    """An argparse type: a clock offset [s] (``--clock-skew``)."""
    from tether.clock import check_skew

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds; write e.g. +0.05") from None
    if (why := check_skew(value, "")) is not None:
        raise argparse.ArgumentTypeError(why.removeprefix(": "))
    return value


def positive_seconds(text: str) -> float:
    """An argparse type: a finite number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a number of seconds > 0, e.g. 120")
    return value


def lease(text: str) -> float:
    """An argparse type: a link lease [s], finite, > 0 and at most an hour."""
    value = positive_seconds(text)
    if value > 3600:
        raise argparse.ArgumentTypeError(f"{text} s: a lease beyond an hour would not see a frozen peer gone within "
                                         "the run; give e.g. 2")
    return value


def scene_rate(text: str) -> float:
    """An argparse type: a scene rate [Hz], finite and >= 0 (0: every tick)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: give a rate in Hz >= 0, e.g. 25 (0: every tick)")
    return value


def vehicle_option(parse: Callable[[str], T], example: str) -> Callable[[str], tuple[int, T]]:
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


# --------------------------------------------------------------------------- outputs
def writable_dir(arg: str, text: str, outputs: tuple[str, ...] = ()) -> Path:
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


def check_live(port: int | None) -> None:
    """``--live PORT``: a port this machine can serve on now (exit 2 before anything starts)."""
    from cli import live

    problem = live.port_problem(port)
    if problem is not None:
        raise BadArgument(problem)


# --------------------------------------------------------------------------- Zenoh
def zenoh_options(p: argparse.ArgumentParser) -> None:
    """The options of a process's Zenoh session (a process command, or a tool attached to a swarm)."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="a Zenoh JSON5 configuration (from tether deploy-gen: mTLS, access control); "
                        "replaces the options below")
    g.add_argument("--zenoh-mode", choices=["peer", "client", "router"], default="peer",
                   help="how this session joins the network: peer (talks to other peers directly), client "
                        "(through a router) or router")
    g.add_argument("--listen", action="append", default=[], help="endpoint to listen on (repeatable)")
    g.add_argument("--connect", action="append", default=[], help="endpoint to connect to (repeatable)")
    g.add_argument("--lease", type=lease, default=2.0, help="link lease [s]: a frozen peer is seen gone after it")
    g.add_argument("--connect-timeout", type=float, default=10.0, help="how long to retry --connect at start [s]")
    g.add_argument("--mesh-peers", type=int_at_least(0), default=0, metavar="N",
                   help="a peer of a mesh (tether run --network mesh): declare this process's liveliness token only "
                        "once it is linked to N other peers, because the launcher starts the run on the tokens "
                        "(exit 1 if they are not all linked within --connect-timeout)")


def zenoh_settings(args: argparse.Namespace) -> ZenohSettings:
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
