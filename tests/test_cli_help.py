"""The ``tether`` command's first screen, tried as a new user would: ``--help`` under headings,
``--version``, the shipped missions, a mistyped command, option or mission answered with the nearest
one (exit 2, nothing run), a notice where the compiled kernels are missing, and what to do next.
Real subprocesses, as a user runs them."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

from tether import catalog

TIMEOUT = 120.0
"""Each command answers in about a second; ample margin on a shared machine [s]."""


def tether(*args: str, code: str = "") -> subprocess.CompletedProcess[str]:
    """``python -m cli ARGS``; with ``code``, that Python first (e.g. hiding numba) and then the command."""
    if code:
        argv = [sys.executable, "-c", f"{code}\nimport sys\nfrom cli.entry import main\nsys.exit(main(sys.argv[1:]))",
                *args]
    else:
        argv = [sys.executable, "-m", "cli", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=TIMEOUT, stdin=subprocess.DEVNULL,
                          env={**os.environ, "COLUMNS": "120", "MPLBACKEND": "Agg"})


def _commands() -> dict[str, argparse.ArgumentParser]:
    from cli import main

    parser = main.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def test_help_lists_the_commands_under_headings_and_no_developer_text() -> None:
    r = tether("--help")
    assert r.returncode == 0, r.stderr
    text = r.stdout
    for heading in ("start here:", "a mission:", "studies:", "deployment:",
                    "processes (started by `tether run` and by deployments, one per process):"):
        assert heading in text, text
    for command in _commands():
        assert f"\n  {command} " in text, f"{command} missing from tether --help"
    # the process commands come last, under their own heading
    processes = text.index("processes (started by")
    assert all(text.index(f"\n  {role} ") > processes for role in ("leader", "agent", "plant", "world", "recorder"))
    assert all(text.index(f"\n  {c} ") < processes for c in ("demo", "simulate", "run", "sweep", "land"))
    assert "``" not in text and "Parses argv" not in text and "nothing else" not in text
    words = " ".join(text.split())  # the epilog as wrapped to the terminal
    assert "`tether demo`" in words and "`tether missions`" in words and "--version" in words


def test_tether_alone_shows_the_help_and_exits_2() -> None:
    r = tether()
    assert r.returncode == 2 and "start here:" in r.stderr and "Traceback" not in r.stderr


def test_version_is_the_installed_distributions() -> None:
    r = tether("--version")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"tether {metadata.version('tether')}"


def test_every_argument_of_every_command_has_help_text() -> None:
    missing = [f"{name} {a.option_strings[0] if a.option_strings else a.dest}"
               for name, p in _commands().items() for a in p._actions
               if not a.help and not isinstance(a, argparse._HelpAction)]
    assert not missing, f"arguments without help: {missing}"


def test_missions_lists_every_shipped_mission_with_its_description() -> None:
    r = tether("missions")
    assert r.returncode == 0, r.stderr
    lines = {ln.split()[0]: ln for ln in r.stdout.splitlines() if ln and not ln[0].isspace()}
    from tether import mission as ms

    for name in catalog.builtin_names():
        m = ms.load(catalog.builtin_path(name))
        assert name in lines and m.description and m.description in lines[name], r.stdout
        assert f"{m.n} agents" in lines[name]


@pytest.mark.parametrize("command", [("check",), ("simulate", "--out", "{tmp}/o"), ("run", "--out", "{tmp}/o")])
def test_an_unknown_mission_lists_the_shipped_ones(command: tuple[str, ...], tmp_path: Path) -> None:
    name, *rest = command
    r = tether(name, "sectoin4", *[a.format(tmp=tmp_path) for a in rest])
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "mission: 'sectoin4'" in r.stderr and "did you mean section4?" in r.stderr
    assert all(n in r.stderr for n in catalog.builtin_names()) and "tether missions" in r.stderr
    assert not (tmp_path / "o").exists()


def test_a_mission_file_that_is_not_there_is_still_named_as_a_file(tmp_path: Path) -> None:
    r = tether("check", str(tmp_path / "mine.toml"))
    assert r.returncode == 2 and "cannot be read" in r.stderr and "tether missions" not in r.stderr


def test_a_mistyped_option_shows_the_commands_usage_and_the_nearest_option(tmp_path: Path) -> None:
    r = tether("simulate", "section4", "--out", str(tmp_path / "o"), "--durration", "3")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert "usage: tether simulate" in r.stderr and "did you mean --duration?" in r.stderr, r.stderr
    assert not (tmp_path / "o").exists()
    r = tether("agent", "--mission", "section4", "--id", "1", "--clock-skwe", "0.1")
    assert r.returncode == 2 and "usage: tether agent" in r.stderr and "did you mean --clock-skew?" in r.stderr
    r = tether("check", "section4", "--frobnicate")
    assert r.returncode == 2 and "usage: tether check" in r.stderr and "tether check --help" in r.stderr


def test_a_mistyped_command_suggests_the_nearest() -> None:
    r = tether("simulat", "section4")
    assert r.returncode == 2 and "'simulat' is not a command" in r.stderr and "did you mean simulate?" in r.stderr


def test_simulate_says_what_it_does_and_what_to_do_next(tmp_path: Path) -> None:
    out = tmp_path / "o"
    r = tether("simulate", "section4", "--out", str(out), "--duration", "1")
    assert r.returncode == 0, r.stderr
    assert "simulating section4: 100 ticks of 4 agents" in r.stderr
    assert f"writing {out / 'run.npz'} (" in r.stderr and "MB)" in r.stderr
    assert f"drawing the figures in {out}" in r.stderr
    assert "\nnext:\n" in r.stdout and str(out / "xy.png") in r.stdout
    if (out / "run.mcap").exists():  # the viz extra
        assert f"open {out / 'run.mcap'} in Foxglove" in r.stdout and "docs/foxglove/tether.json" in r.stdout


HIDE_NUMBA = "import sys\nsys.modules['numba'] = None  # `import numba` now raises ImportError"


def test_without_numba_a_simulation_and_a_sweep_say_so_once(tmp_path: Path) -> None:
    r = tether("simulate", "section4", "--out", str(tmp_path / "s"), "--duration", "1", "--no-figures", "--no-mcap",
               code=HIDE_NUMBA)
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("numba is not installed") == 1 and "tether[fast]" in r.stderr, r.stderr
    r = tether("sweep", "section4", "--out", str(tmp_path / "w"), "--duration", "0.5", "--loss", "0", "--delay", "0",
               "--laws", "sigma", code=HIDE_NUMBA)
    assert r.returncode == 0, r.stderr
    assert r.stderr.count("numba is not installed") == 1, r.stderr


def test_with_numba_no_notice(tmp_path: Path) -> None:
    pytest.importorskip("numba")
    r = tether("simulate", "section4", "--out", str(tmp_path / "s"), "--duration", "1", "--no-figures", "--no-mcap")
    assert r.returncode == 0 and "numba is not installed" not in r.stderr, r.stderr


def test_a_process_command_loads_none_of_the_users_commands() -> None:
    """A control process builds its own command alone: the modules of the other commands (and the
    spelling suggestion's ``difflib``) are no part of its memory."""
    code = ("import sys; from cli import main; main.build_parser(sys.argv[1]).parse_args(sys.argv[1:])")
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", code, "agent", "--mission", "section4", "--id", "1"],
                       capture_output=True, text=True, timeout=TIMEOUT)
    assert r.returncode == 0, r.stderr[-2000:]
    names = [ln.rsplit("|", 1)[1].strip() for ln in r.stderr.splitlines() if ln.startswith("import time:") and "|" in ln]
    assert "cli.roles" in names and "cli.args" in names
    bad = [n for n in names if n.startswith(("cli.sim", "cli.swarm", "cli.missions", "cli.study", "sim.", "difflib",
                                             "importlib.metadata"))]
    assert not bad, f"tether agent loads {bad}"


@pytest.mark.slow  # a lockstep run of every process, then the demo's separate plant processes
def test_run_and_demo_end_with_what_to_do_next(tmp_path: Path) -> None:
    out = tmp_path / "run"
    r = tether("run", "section4", "--out", str(out), "--duration", "1", "--insecure", "--quiet")
    assert r.returncode == 0, r.stderr[-3000:]
    assert "\nnext:\n" in r.stdout and str(out / "report.html") in r.stdout and str(out / "logs") in r.stdout
    demo = tmp_path / "demo"
    r = tether("demo", "--out", str(demo), "--duration", "1")
    assert r.returncode == 0, r.stderr[-3000:]
    assert str(demo / "xy.png") in r.stdout.split("\nnext:\n")[1] and (demo / "report.html").exists()
    assert "tether reproduce section4" in r.stdout and "tether missions" in r.stdout
    assert "simulating the same mission in the reference simulator" in r.stderr


def test_every_commands_help_is_shown() -> None:
    for name, p in _commands().items():
        assert f"usage: tether {name}" in p.format_help(), name
    r = tether("run", "--help")
    assert r.returncode == 0 and "usage: tether run" in r.stdout and "--stall-timeout" in r.stdout, r.stderr
    assert "Run a mission as separate processes over Zenoh" in " ".join(r.stdout.split())  # what it does, first
