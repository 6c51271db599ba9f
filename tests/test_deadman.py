"""The dead-man guardian's orders and decisions (:mod:`plant.deadman`); the landing it orders of a
software Crazyflie whose plant was killed is in ``tests/test_lab_deadman.py``."""

from __future__ import annotations

import io
import logging
import subprocess
import sys

import pytest

from plant import deadman
from tests.support import REPO, cli_env


def test_orders_are_parsed_and_anything_else_is_not_an_order() -> None:
    assert deadman.parse("arm udp://127.0.0.1:19850\n") == ("arm", "udp://127.0.0.1:19850")
    assert deadman.parse("disarm radio://0/80/2M/E7E7E7E701") == ("disarm", "radio://0/80/2M/E7E7E7E701")
    assert deadman.parse("bye") == ("bye", "")
    for junk in ("", "arm", "arm a b", "land udp://x", "bye now", "ARM udp://x"):
        assert deadman.parse(junk) is None, junk


def test_the_armed_set_follows_the_orders_and_bye_ends_them(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="tether.deadman"):
        armed, bye = deadman.listen(["arm a://1", "arm a://2", "garbage here", "disarm a://1", "arm a://2", ""])
    assert armed == {"a://2"} and not bye
    assert "not an order" in caplog.text
    armed, bye = deadman.listen(["arm a://1", "bye", "arm a://3"])
    assert armed == {"a://1"} and bye  # nothing after bye is read


def test_a_guardian_told_bye_or_with_nothing_armed_does_nothing() -> None:
    assert deadman.guard(io.StringIO("arm nope://1\nbye\n"), 2.0) == 0
    assert deadman.guard(io.StringIO("arm nope://1\ndisarm nope://1\n"), 2.0) == 0


def test_a_vehicle_that_cannot_be_reached_is_said_and_fails_the_guardian(caplog: pytest.LogCaptureFixture) -> None:
    pytest.importorskip("cflib")
    with caplog.at_level(logging.ERROR, logger="tether.deadman"):
        assert deadman.guard(io.StringIO("arm nope://1\n"), 2.0) == 1  # no link driver for the scheme
    assert "the plant process is gone; landing nope://1" in caplog.text
    assert "nope://1 could not be ordered to land" in caplog.text


@pytest.mark.parametrize("bad", ["0", "-1", "nan", "inf", "soon"])
def test_the_guardian_command_refuses_a_bad_land_time(bad: str) -> None:
    p = subprocess.run([sys.executable, "-m", "plant.deadman", "--land-time", bad], cwd=REPO, env=cli_env(),
                       input="", capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "--land-time" in p.stderr, p.stderr


def test_a_guardian_process_lives_only_while_a_vehicle_is_armed() -> None:
    g = deadman.Guardian(2.0)
    assert g.pid is None
    g.disarm("nope://1")  # nothing armed yet: no process is started for it
    assert g.pid is None
    g.arm("nope://1")
    g.arm("nope://2")
    first = g._proc
    assert first is not None and first.poll() is None
    g.disarm("nope://1")
    assert g._proc is first and first.poll() is None  # vehicle 2 is still in the air
    g.disarm("nope://2")  # nothing in the air: the guardian is let go, without acting
    assert g.pid is None and first.returncode == 0
    g.arm("nope://3")  # the next take-off starts another
    second = g._proc
    assert second is not None and second is not first
    g.close()
    assert second.returncode == 0 and g.pid is None
