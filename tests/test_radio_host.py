"""Several Crazyflies per radio: the grouping rule (:func:`plant.radio.dongles`), and four software
Crazyflies on one simulated radio flying ``exp1_cf`` from one radio host process (``cli/radio.py``),
each vehicle still its own plant on the wire, with its own log."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from plant import radio
from tests.support import tether_popen
from tests.test_sitl import PORTS, mission, simulators
from tether.runfile import Run


def test_vehicles_are_grouped_by_the_dongle_their_uri_names() -> None:
    got = radio.dongles([(1, "radio://0/80/2M/E7E7E7E701"), (2, "radio://1/90/2M/E7E7E7E702"),
                         (3, "radio://0/80/2M/E7E7E7E703"), (4, "usb://0"), (5, "radio://0/20/250K/E7E7E7E705")])
    assert got == [radio.Dongle("radio://0", (1, 3, 5)), radio.Dongle("radio://1", (2,)), radio.Dongle("usb://0", (4,))]


def test_software_crazyflies_are_grouped_by_host_in_port_order_four_to_a_simulated_radio() -> None:
    uris = [(10 + k, f"udp://127.0.0.1:{19850 + (k * 7) % 10}") for k in range(10)] + [(30, "udp://10.0.0.2:19850")]
    got = radio.dongles(uris)
    ports = {aid: int(uri.rsplit(":", 1)[1]) for aid, uri in uris}
    assert [d.name for d in got] == ["sim://127.0.0.1/0", "sim://127.0.0.1/1", "sim://127.0.0.1/2", "sim://10.0.0.2/0"]
    assert [len(d.agents) for d in got] == [4, 4, 2, 1]
    flat = [ports[a] for d in got[:3] for a in d.agents]
    assert flat == sorted(flat)
    assert all(d.simulated for d in got)
    assert sorted(a for d in got for a in d.agents) == sorted(a for a, _ in uris)
    assert len(radio.dongles(uris, sim_size=8)) == 3
    with pytest.raises(ValueError, match="sim_size"):
        radio.dongles(uris, sim_size=0)


def test_the_radio_host_takes_one_plant_command_line_per_vehicle() -> None:
    from cli import radio as host
    from cli.args import BadArgument

    assert host.split(["--", "--mission", "m.toml", "--id", "1", "--", "--id", "2"]) == \
        [["--mission", "m.toml", "--id", "1"], ["--id", "2"]]
    for bad in ([], ["--mission", "m.toml"], ["--", "--id", "1", "--"]):
        with pytest.raises(BadArgument):
            host.split(bad)
    assert host.main(["--log-fds", "5,6", "--", "--id", "1", "--", "--id", "2"]) == 2  # one descriptor too many
    assert host.main(["--", "--mission", "exp1_cf", "--id", "1", "--", "--mission", "exp1_cf", "--id", "1"]) == 2


@pytest.mark.slow
def test_four_crazyflies_on_one_simulated_radio_fly_exp1_cf_from_one_radio_host(tmp_path: Path) -> None:
    out_dir = tmp_path / "run"
    p = tether_popen("run", str(mission(tmp_path)), "--sitl", "--duration", "10", "--out", str(out_dir))
    out, _ = p.communicate(timeout=300)
    assert p.returncode in (0, 5), out  # 5: a sample lost on the way to the recorder (real time)
    assert not simulators()
    logs = out_dir / "logs"
    host = (logs / "plant-1.log").read_text()
    assert "radio host: plant/1, plant/2, plant/3, plant/4" in host
    for i in range(1, 5):  # each vehicle its own plant, with its own log
        text = (logs / f"plant-{i}.log").read_text()
        assert f"crazyflie {i}: airborne" in text and f"crazyflie {i}: landing" in text, text[-2000:]
        assert all(f"crazyflie {j}:" not in text for j in range(1, 5) if j != i)
    radio_line = next(line for line in (logs / "cfsim-1.log").read_text().splitlines() if " radio 0: up " in line)
    counts = [int(w) for w in radio_line.replace(",", "").split() if w.isdigit()]  # up: sent lost dropped attempts; down
    assert counts[1] == counts[2] == counts[5] == counts[6] == 0, radio_line  # nothing lost, no queue overflow
    assert counts[4] > 4 * 150 * 8, radio_line  # four vehicles' logs came down the one radio
    run = Run.load(out_dir)
    assert run.p.shape[1] == 4 and np.isfinite(run.p[-1]).all()
    assert len(PORTS) == 4
