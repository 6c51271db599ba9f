"""The event loop every process runs on (tether/evloop.py): uvloop where installed, TETHER_LOOP to choose."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sim import lockstep
from tether import evloop
from tether.catalog import builtin_path
from tether.node import load_mission
from tether.runfile import Run

SERIES = ("p", "v", "u", "xi", "zeta", "kp", "kv", "leader_p")


def test_unset_it_is_uvloop_where_installed() -> None:
    pytest.importorskip("uvloop")  # a dependency of tether on Linux (pyproject.toml)
    assert evloop.choose({}) == "uvloop"
    assert evloop.choose({evloop.ENV: " uvloop "}) == "uvloop"
    assert evloop.choose({evloop.ENV: "asyncio"}) == "asyncio"


def test_without_uvloop_it_is_asyncio_unless_uvloop_was_asked_for(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "uvloop", None)  # import uvloop raises ImportError
    assert evloop.choose({}) == "asyncio"
    with pytest.raises(evloop.LoopError, match="TETHER_LOOP=uvloop, but uvloop is not installed: pip install uvloop"):
        evloop.choose({evloop.ENV: "uvloop"})


def test_an_unknown_loop_is_an_error_that_names_the_variable_and_the_fix() -> None:
    with pytest.raises(evloop.LoopError, match=r"TETHER_LOOP='trio' is not a loop; set it to uvloop or asyncio"):
        evloop.choose({evloop.ENV: "trio"})


@pytest.mark.parametrize("kind", ["uvloop", "asyncio"])
def test_run_runs_a_coroutine_on_the_loop_it_was_given(kind: str) -> None:
    if kind == "uvloop":
        pytest.importorskip("uvloop")

    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        fired = loop.create_future()
        loop.call_soon_threadsafe(fired.set_result, 1.5)  # a hand-off from "another thread", as Zenoh's
        return evloop.running(), await asyncio.wait_for(fired, 5.0)

    assert evloop.run(main(), kind) == (kind, 1.5)


def test_a_bad_tether_loop_stops_a_run_before_anything_starts(tmp_path: Path) -> None:
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--out", str(out), "--duration", "1"],
                       capture_output=True, text=True, timeout=60, env={**os.environ, evloop.ENV: "uv"})
    assert r.returncode == 2, r.stderr
    assert "TETHER_LOOP='uv' is not a loop; set it to uvloop or asyncio" in r.stderr
    assert not out.exists()


@pytest.mark.slow  # real processes
@pytest.mark.parametrize("kind", ["uvloop", "asyncio"])
def test_a_lockstep_run_is_the_reference_bit_for_bit_on_either_loop(tmp_path: Path, kind: str) -> None:
    if kind == "uvloop":
        pytest.importorskip("uvloop")
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, "-m", "cli", "run", "section4", "--out", str(out), "--duration", "2",
                        "--quiet", "--no-mcap"], capture_output=True, text=True, timeout=180,
                       env={**os.environ, evloop.ENV: kind})
    assert r.returncode == 0, r.stderr[-3000:]
    logs = {p.name: p.read_text() for p in (out / "logs").iterdir()}
    served = [name for name, text in logs.items() if "event loop:" in text]
    assert len(served) >= 6, sorted(logs)  # the leader, four agents, the recorder
    for name in served:
        assert f"event loop: {kind}" in logs[name], name
    got = Run.load(out)
    want = lockstep.simulate(load_mission(builtin_path("section4"), 2.0))
    for name in SERIES:
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
