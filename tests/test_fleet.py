"""The fleet file (``tether/fleet.py``): what a lab keeps about its Crazyflies, validated with every
problem named by its field and fix; a mission that names a fleet is checked against it."""

from __future__ import annotations

from pathlib import Path

import pytest

from tether import fleet as fl
from tether import mission as ms
from tests.support import REPO, tether

EXAMPLE = REPO / "examples" / "lab" / "fleet.toml"


def test_the_example_fleet_loads_with_per_vehicle_masses() -> None:
    f = fl.load(EXAMPLE)
    assert [v.name for v in f.vehicles] == ["cf1", "cf2", "cf3", "cf4"]
    assert [f.mass_of(v) for v in f.vehicles] == [0.029, 0.029, 0.0325, 0.029]
    assert f.type_of(f.vehicles[0]).params["stabilizer.estimator"] == 2
    assert f.by_uri("udp://127.0.0.1:19972") is f.vehicles[2]


BASE = """
version = 1
[types.a]
mass = 0.03
[[vehicles]]
name = "cf1"
uri = "radio://0/80/2M/E7E7E7E701"
type = "a"
p0 = [0.0, 0.0, 0.0]
"""

BAD = [
    # (what replaces what in BASE, the field named, a word of the fix)
    (("mass = 0.03", "mass = 3.0"), "types.a.mass", "kg"),
    (("mass = 0.03", "mass = 0.03\nparams = { \"stabilizer.estimater\" = 2 }"),
     "types.a.params.stabilizer.estimater", "stabilizer.estimator"),
    (("mass = 0.03", "mass = 0.03\nparams = { \"stabilizer.estimator\" = 7 }"), "types.a.params.stabilizer.estimator",
     "[0, 3]"),
    (("mass = 0.03", "mass = 0.03\nposition_source = \"mocap\""), "vehicle cf1.type", "[mocap]"),
    (("radio://0/80/2M/E7E7E7E701", "radio://0/200/2M/E7E7E7E701"), "vehicle cf1.uri", "0..125"),
    (("radio://0/80/2M/E7E7E7E701", "E7E7E7E701"), "vehicle cf1.uri", "radio://"),
    (('type = "a"', 'type = "b"'), "vehicle cf1.type", "[types.b]"),
    (("p0 = [0.0, 0.0, 0.0]", "p0 = [0.0, 0.0]"), "vehicle cf1.p0", "[x, y, z]"),
    (("p0 = [0.0, 0.0, 0.0]", "p0 = [0.0, 0.0, 0.0]\nmass = -1.0"), "vehicle cf1.mass", "kg"),
    (("p0 = [0.0, 0.0, 0.0]", "p0 = [0.0, 0.0, 0.0]\nmas = 0.03"), "vehicles[0]", "mas"),
    (("version = 1", "version = 1\n[health]\nbattery_min = 5.0"), "health.battery_min", "3.8"),
    (("version = 1", "version = 1\n[mocap]\nbackend = \"vycon\""), "mocap.backend", "vicon"),
    (("version = 1", "version = 2"), "version", "version = 1"),
]


@pytest.mark.parametrize("change,field,fix", BAD, ids=[b[1] + ":" + b[2] for b in BAD])
def test_each_bad_field_is_named_with_its_fix(change: tuple[str, str], field: str, fix: str) -> None:
    text = BASE.replace(*change, 1)
    assert text != BASE
    with pytest.raises(fl.FleetError) as err:
        fl.loads(text, "lab.toml")
    fields = [f for f, _ in err.value.problems]
    assert any(f.startswith(field) for f in fields), err.value
    assert fix in str(err.value), err.value


def test_two_vehicles_on_one_address_and_one_name_are_both_refused() -> None:
    text = BASE + BASE.split("[[vehicles]]")[1].join(["[[vehicles]]", ""])
    with pytest.raises(fl.FleetError) as err:
        fl.loads(text)
    assert ("vehicle cf1.name" in [f for f, _ in err.value.problems]
            and "vehicle cf1.uri" in [f for f, _ in err.value.problems]), err.value


def _mission_with_fleet(tmp_path: Path, fleet_text: str, uri: str = "udp://127.0.0.1:19970") -> Path:
    src = (REPO / "tether" / "missions" / "exp1_cf.toml").read_text()
    (tmp_path / "fleet.toml").write_text(fleet_text)
    text = src.replace('seed = 1\n', 'seed = 1\nfleet = "fleet.toml"\n', 1).replace("udp://127.0.0.1:19970", uri)
    path = tmp_path / "m.toml"
    path.write_text(text)
    return path


def test_a_mission_names_its_fleet_and_every_vehicle_must_be_in_it(tmp_path: Path) -> None:
    m = ms.load(_mission_with_fleet(tmp_path, EXAMPLE.read_text()))
    assert m.fleet == str((tmp_path / "fleet.toml").resolve())
    with pytest.raises(ms.MissionError) as err:
        ms.load(_mission_with_fleet(tmp_path, EXAMPLE.read_text(), uri="udp://127.0.0.1:19999"))
    assert err.value.problems[0][0] == "agent 1.plant.uri" and "[[vehicles]]" in str(err.value)
    moved = EXAMPLE.read_text().replace("p0 = [-1.2, -1.9, 0.0]", "p0 = [1.2, 1.9, 0.0]", 1)
    with pytest.raises(ms.MissionError) as err:
        ms.load(_mission_with_fleet(tmp_path, moved))
    assert err.value.problems[0][0] == "agent 1.p0" and "vehicle cf1" in str(err.value)


@pytest.mark.slow  # the command as a subprocess
def test_check_refuses_a_bad_fleet_with_exit_2_naming_the_field(tmp_path: Path) -> None:
    bad = EXAMPLE.read_text().replace("battery_min = 3.8", "battery_min = 38", 1)
    r = tether("check", str(_mission_with_fleet(tmp_path, bad)))
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert "health.battery_min" in r.stderr and "3.8 V" in r.stderr, r.stderr


def test_sitl_weighs_each_software_vehicle_as_the_fleet_does(tmp_path: Path) -> None:
    """``tether run --sitl`` gives each simulated vehicle the fleet's mass for its URI (cf3 carries
    more), and the simulator's ``--mass`` once per vehicle builds each airframe with its own."""
    from deploy import sitl
    from plant.cfsim.__main__ import config, parse_args

    m = ms.load(_mission_with_fleet(tmp_path, EXAMPLE.read_text()))
    assert [v.mass for v in sitl.vehicles(m)] == [0.029, 0.029, 0.0325, 0.029]
    plain = ms.load(REPO / "tether" / "missions" / "exp1_cf.toml")  # no fleet: the plant table's mass
    assert {v.mass for v in sitl.vehicles(plain)} == {0.029}
    cfg = config(parse_args(["--count", "3", "--mass", "0.029", "--mass", "0.0325", "--mass", "0.03"]))
    assert [v.quadrotor.mass for v in cfg.vehicles if v.quadrotor is not None] == [0.029, 0.0325, 0.03]
    cfg = config(parse_args(["--count", "2", "--mass", "0.04"]))
    assert [v.quadrotor.mass for v in cfg.vehicles if v.quadrotor is not None] == [0.04, 0.04]
    with pytest.raises(SystemExit) as exc:
        parse_args(["--count", "3", "--mass", "0.03", "--mass", "0.04"])
    assert exc.value.code == 2
