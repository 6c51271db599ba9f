"""Each process imports only what it uses (docs/architecture.md, "The rule").

A role's process loads its role, the core and their libraries: no study or engine (``sim``), no
plotting (``matplotlib``) and, for a mission without ``[netem]``, no network emulator
(``netem.channel``, ``netem.link``: the agent imports them inside the function that builds a
``[netem]`` mission's links). Each module is imported in a fresh interpreter under
``python -X importtime``, whose report names every module the import loaded.
"""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

FORBIDDEN = re.compile(r"^(sim|matplotlib|netem\.channel|netem\.link)(\.|$)")
"""Modules no process of a mission without ``[netem]`` may load at import."""

ENTRY_POINTS = ["agent.node", "leader.node", "plant.node", "recorder.node", "tether.node", "cli.main"]
"""The process adapters, the scaffold they share, and the command every process is started by."""


def loaded_modules(module: str) -> list[str]:
    """Every module ``import module`` loads in a fresh interpreter, from ``-X importtime``'s report."""
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import {module}"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, f"import {module} failed:\n{r.stderr[-2000:]}"
    names = []
    for line in r.stderr.splitlines():
        if line.startswith("import time:") and "|" in line:
            names.append(line.rsplit("|", 1)[1].strip())
    assert names, f"no -X importtime report for {module}:\n{r.stderr[-2000:]}"
    return names


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_a_process_loads_no_study_no_plotting_and_no_emulator(module: str) -> None:
    names = loaded_modules(module)
    assert module in names
    bad = sorted({n for n in names if FORBIDDEN.match(n)})
    assert not bad, f"import {module} loads {', '.join(bad)}; import them inside the function that needs them"


@pytest.mark.parametrize("module", ["plant.node", "agent.node"])
def test_a_simulated_plant_or_an_agent_loads_no_crazyflie_driver(module: str) -> None:
    """The Crazyflie driver (``plant.crazyflie``, its simulator ``plant.cfsim``, the quadrotor model
    it brings) is loaded by the process of a mission that flies one, inside the function that needs it."""
    names = loaded_modules(module)
    bad = sorted({n for n in names if re.match(r"^plant\.(crazyflie|cfsim|quadrotor|payload)(\.|$)", n)})
    assert not bad, f"import {module} loads {', '.join(bad)}"


def test_the_check_itself_sees_a_forbidden_import() -> None:
    """The report parsing is not vacuous: the figures load matplotlib, an emulated link its channel."""
    assert "matplotlib" in loaded_modules("sim.figures")
    assert "netem.channel" in loaded_modules("netem.link")


@pytest.mark.parametrize("module", ["agent.node", "cli.main"])
def test_an_agent_loads_no_numpy(module: str) -> None:
    """An agent's tick runs on Python floats (``tether.vec``): numpy, 13 MiB of an agent's memory,
    is for the simulators, the plants and the run file (``tests/test_runtime.py`` checks a running
    agent's memory map too)."""
    bad = sorted({n for n in loaded_modules(module) if re.match(r"^numpy(\.|$)", n)})
    assert not bad, f"import {module} loads numpy ({len(bad)} modules)"


LEAN = re.compile(r"^(deploy\.(gen|rehearse|pki|acl)|cli\.(study|record|top)|tempfile|difflib|random|importlib\.resources"
                  r"|subprocess|hashlib|shutil|bz2|lzma)(\.|$)")
"""What a control process has no use for: the other subcommands' modules, and the standard library
they (or ``importlib.resources``, or a mistake's spelling suggestion) bring."""


def loaded_by_command(argv: list[str]) -> list[str]:
    """Every module loaded by building the command line for ``argv`` and parsing it, as
    ``python -m cli ARGV`` does before it runs the command (which is not run here)."""
    code = ("import sys; from cli import main; main.build_parser(sys.argv[1] if len(sys.argv) > 1 else None)"
            ".parse_args(sys.argv[1:])")
    r = subprocess.run([sys.executable, "-X", "importtime", "-c", code, *argv], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, f"parsing {argv} failed:\n{r.stderr[-2000:]}"
    return [line.rsplit("|", 1)[1].strip() for line in r.stderr.splitlines()
            if line.startswith("import time:") and "|" in line]


@pytest.mark.parametrize("role", ["agent", "plant", "leader", "recorder", "world"])
def test_a_control_process_loads_no_other_subcommand(role: str) -> None:
    """A process command builds only its own part of the command line: the study, deployment,
    recording and terminal subcommands (and ``subprocess``, ``hashlib``, ``tempfile`` they bring) cost
    every process about 1 MiB of memory."""
    argv = [role, "--mission", "section4"] + (["--id", "1"] if role in ("agent", "plant") else []) \
        + (["--out", "run"] if role == "recorder" else [])
    names = loaded_by_command(argv)
    assert "cli.main" in names
    bad = sorted({n for n in names if LEAN.match(n)})
    assert not bad, f"tether {role} loads {', '.join(bad)}"
    assert "deploy.gen" in loaded_by_command(["check", "section4"]), \
        "the check is vacuous: the full command line loads deploy.gen"


def test_the_full_command_line_still_has_every_subcommand() -> None:
    from cli import main

    text = main.build_parser().format_help()
    for command in ("deploy-gen", "rehearse", "record", "top", "montecarlo", "sweep", "agent", "plant"):
        assert command in text, f"{command} is missing from tether --help"
    with pytest.raises(SystemExit) as exc:
        main.main(["agent", "--mission", "section4", "--id", "1", "--bogus"])
    assert exc.value.code == 2  # a process command's own parser still refuses an unknown option
