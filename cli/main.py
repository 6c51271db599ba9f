"""The ``tether`` command line: its commands under their headings, ``--version``, a mistyped
command or option answered with the nearest one, and the exit status of every error.

Exit status (every command's, in ``docs/exit-status.md``): 0 success, 1 a run failed (also a write
that failed part-way: the path and errno are named), 2 bad input (mission file or arguments,
checked before anything starts), 130 interrupted; ``tether run`` also 3 (a failsafe fired or a
value diverged) and 4 (a process died or froze in a real-time run): ``deploy/local.py``.

The commands live beside this module: :mod:`cli.missions`, :mod:`cli.sim`, :mod:`cli.swarm`,
:mod:`cli.study`, :mod:`cli.record`, :mod:`cli.top` and the process commands of :mod:`cli.roles`.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from cli import roles
from cli.args import BadArgument
from tether import evloop

DESCRIPTION = ("Fly a quadcopter swarm in formation with the adaptive formation law of Su, Bhowmick & Lanzon "
               "(2023): simulate a mission, run it as separate processes over Zenoh, study it over a grid of "
               "network conditions, deploy it to companion computers.")

EPILOG = ("New here? `tether demo` flies the paper's Section 4 case study as separate processes and draws its "
          "figures; `tether missions` lists the shipped missions. `tether COMMAND --help` shows a command's "
          "options. Exit status: 0 done, 1 failed, 2 bad input (nothing started), 130 interrupted; `tether run` "
          "also 3 (a failsafe fired) and 4 (a process died or froze): docs/exit-status.md.")

GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("start here", ("demo", "reproduce", "missions")),
    ("a mission", ("check", "simulate", "run")),
    ("a run's files", ("plot", "mcap", "report")),
    ("studies", ("sweep", "montecarlo", "warm")),
    ("a swarm that is flying", ("record", "top", "netem-set", "land", "estop")),
    ("deployment", ("deploy-gen", "rehearse")),
    (roles.HEADING, roles.PROCESSES),
)
"""The headings of ``tether --help`` and the commands under each (every command is under one)."""


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


def _unrecognized(parser: argparse.ArgumentParser, extras: list[str]) -> str:
    """argparse's "unrecognized arguments" message, with the nearest option of ``parser`` to each
    mistyped one (``--durration`` -> ``--duration``)."""
    from tether.schema import close_matches  # only when explaining a mistake

    known = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
    hints = []
    for word in extras:
        if word.startswith("-"):
            near = close_matches(word.partition("=")[0], known, n=1)
            hints += [f"did you mean {near[0]}?"] if near else []
    return f"unrecognized arguments: {' '.join(extras)}" + (f"; {' '.join(hints)}" if hints else
                                                             f"; `{parser.prog} --help` lists the options")


class _Parser(argparse.ArgumentParser):
    """An argument parser laid out by :class:`_Formatter` (its subparsers are of this class too)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", _Formatter)
        super().__init__(**kwargs)


class _Tether(_Parser):
    """The ``tether`` command's parser: its commands listed under :data:`GROUPS`, and a mistyped
    command or option answered with the usage of the command it was given to and the nearest
    spelling."""

    commands: argparse._SubParsersAction

    def format_help(self) -> str:
        f = self._get_formatter()
        f.add_usage(self.usage, self._actions, self._mutually_exclusive_groups)
        f.add_text(self.description)
        listed = {a.dest: a for a in self.commands._choices_actions}
        for heading, names in GROUPS:
            actions = [listed.pop(n) for n in names if n in listed]
            if actions:
                f.start_section(heading)
                f.add_arguments(actions)
                f.end_section()
        assert not listed, f"commands under no heading of GROUPS: {sorted(listed)}"
        f.start_section("options")
        f.add_arguments([a for a in self._actions if a.option_strings])
        f.end_section()
        f.add_text(self.epilog)
        return f.format_help()

    def parse_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                   namespace: argparse.Namespace | None = None) -> argparse.Namespace:
        argv = list(sys.argv[1:] if args is None else args)
        names = list(self.commands.choices)
        if argv and not argv[0].startswith("-") and argv[0] not in names:
            from tether.schema import close_matches

            near = close_matches(argv[0], names, n=1)
            self.error(f"{argv[0]!r} is not a command; " + (f"did you mean {near[0]}? " if near else "")
                       + "`tether --help` lists them")
        ns, extras = self.parse_known_args(argv, namespace)
        if extras:
            command = self.commands.choices.get(getattr(ns, "command", None) or "")
            where = command if command is not None else self
            where.error(_unrecognized(where, extras))
        return ns


class _Version(argparse.Action):
    """``--version``: the installed distribution's version, read only when asked (``importlib.metadata``
    is no part of a control process)."""

    def __init__(self, option_strings: list[str], dest: str = argparse.SUPPRESS, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS,
                         help="print tether's version and exit")

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> NoReturn:
        from importlib import metadata

        try:
            version = metadata.version("tether")
        except metadata.PackageNotFoundError:
            version = "(not installed: run from a source tree)"
        print(f"tether {version}")
        parser.exit(0)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; for ``command`` one of :data:`cli.roles.PROCESSES` (how every process
    of a run is started), the process commands alone. The others would cost each control process
    about 1 MiB of memory for nothing: their argparse objects, and the modules some of them live in
    (``deploy.gen`` alone brings ``subprocess``, ``hashlib``, ``secrets`` and ``tempfile``)."""
    p = _Tether(prog="tether", description=DESCRIPTION, epilog=EPILOG)
    p.add_argument("--version", action=_Version)
    p.commands = p.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    if command in roles.PROCESSES:
        roles.add_parsers(p.commands)
        return p
    from cli import missions, record, sim, study, swarm, top

    missions.add_parsers(p.commands)
    sim.add_parsers(p.commands)
    swarm.add_run_parser(p.commands)
    roles.add_parsers(p.commands)
    study.add_parsers(p.commands)
    swarm.add_operator_parsers(p.commands)
    swarm.add_deploy_parsers(p.commands)
    record.add_parser(p.commands)
    top.add_parser(p.commands)
    for listed in p.commands._choices_actions:  # `tether X --help` opens with what X does
        parser = p.commands.choices[listed.dest]
        if parser.description is None and listed.help:
            parser.description = f"{listed.help[0].upper()}{listed.help[1:]}."
    return p


PREWARM_ON = ("demo", "simulate", "run", "check", "missions", "reproduce")
"""Commands that start the once-per-machine background compile (:func:`sim.warm.prewarm`)."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv[0] if argv else None)
    if not argv:  # a first try: the commands, not "the following arguments are required"
        print(parser.format_help(), file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    from tether.schema import SchemaError

    try:
        evloop.choose()  # TETHER_LOOP: a wrong value is an error before anything starts
        if argv[0] in PREWARM_ON:  # a new user's first commands: the first study's kernels, compiled meanwhile
            from sim import warm

            warm.prewarm(idle=argv[0] == "run")  # beside a swarm in real time: what no one else wants only
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
